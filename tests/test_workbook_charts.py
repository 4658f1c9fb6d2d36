"""Workbook charts, number formats, headers and provenance (issue 14 item 8, acceptance 4).

Before: the flagship workbook's only chart was one series over all seven
cases' rows concatenated, on a linear axis; the Fig 8 charts were linear in
y while the PNGs are log-log; the budget workbook had no chart; cells showed
``14.999999999999996``; headers said ``[SI]``/``[SI^2 s]``; the provenance
cell was cut at Excel's 32 767 characters.
"""

from __future__ import annotations

import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from openpyxl import load_workbook

import covtool
from covtool.io.workbook import (EXCEL_CELL_MAX, build_workbook, number_format, provenance_frame,
                                 read_provenance)
from covtool.io.writers import write_outputs
from covtool.units import si_unit

ROOT = Path(__file__).resolve().parents[1]


def flagship_decl(duration="6 min", cases=("A", "B1", "D"), **zupt):
    d = tomllib.loads((ROOT / "studies" / "zupt_filter_order.toml").read_text())
    d["study"]["duration"] = duration
    d["filters"]["cases"] = list(cases)
    d["filters"].pop("file")
    d["zupt"].update(zupt)
    d["output"] = {"history_every": "10 s", "report_times": [duration]}
    d["impact"] = {"filters": []}
    return d


@pytest.fixture(scope="module")
def flagship(tmp_path_factory):
    r = covtool.run_study(flagship_decl())
    out = tmp_path_factory.mktemp("flag") / "out"
    write_outputs(r, out)
    return r, out


def _series_titles(chart):
    return [s.tx.v for s in chart.series]


def test_flagship_charts_one_series_per_case_on_log_axes(flagship):
    r, out = flagship
    wb = load_workbook(out / f"{r.name}.xlsx")
    charts = wb["history"]._charts
    assert len(charts) == 2
    cases = ["pure_ins", "A", "B1", "D"]
    hist = r.tables["history"]
    for ch in charts:
        assert _series_titles(ch) == cases
        assert ch.y_axis.scaling.logBase == 10
        # each series spans exactly its case's rows of the history sheet (header is row 1), but t = 0
        # (σ = 0 has no place on a log axis)
        for s, c in zip(ch.series, cases):
            rows = np.flatnonzero(hist["case"].to_numpy() == c) + 2
            assert hist["t [s]"].iloc[rows[0] - 2] == 0.0
            for ref in (s.yVal.numRef.f, s.xVal.numRef.f):
                assert ref.endswith(f"${rows[1]}:$" + ref.split(":$")[-1].split("$")[0] + f"${rows[-1]}")


def test_no_header_is_a_placeholder_unit(flagship):
    r, out = flagship
    wb = load_workbook(out / f"{r.name}.xlsx")
    heads = [c.value for ws in wb.worksheets for c in ws[1] if c.value is not None]
    assert heads and not [h for h in heads if "[SI" in str(h)]
    fs = r.tables["filter_states"].set_index(["filter", "state"])
    # the unit named beside the SI value is the state's real SI unit
    assert fs.loc[("B1", "acc_bias_x"), "SI unit"] == "m/s^2"
    assert fs.loc[("B1", "gyro_bias_z"), "SI unit"] == "rad/s"
    ewn = r.tables["equivalent_noise"]
    units = {(r_["dropped state"]): (r_["P0 SI unit"], r_["q_eq SI unit"]) for _, r_ in ewn.iterrows()}
    assert units["acc_markov_x"] == ("m^2/s^4", "m^2/s^3")       # (m/s^2)^2 and its PSD (m/s^2)^2 s


@pytest.mark.parametrize("unit, power, seconds, text", [
    ("ug", 1, 0, "m/s^2"), ("deg/h", 1, 0, "rad/s"), ("deg/sqrt(h)", 1, 0, "rad/s^(1/2)"),
    ("ug", 2, 1, "m^2/s^3"), ("deg/h", 1, -0.5, "rad/s^(3/2)"), ("ppm", 1, 0, "-"), ("", 1, -0.5, "1/s^(1/2)"),
    ("ft/s", 2, 0, "m^2/s^2")])
def test_si_unit_names(unit, power, seconds, text):
    from fractions import Fraction
    assert si_unit(unit, power, seconds=Fraction(seconds)) == text


def test_si_unit_refuses_an_unknown_unit():
    from covtool.errors import UnitError
    with pytest.raises(UnitError, match="unknown unit 'blorbs'"):
        si_unit("blorbs")


@pytest.mark.parametrize("value, fmt, shown", [
    (14.999999999999996, "0.00", None), (0.30479999999999996, "0.0000", None), (1234.5678, "0", None),
    (2.5e-7, "0.000E+00", None), (3.0e7, "0.000E+00", None), (0.0, "0", None), (-0.012345, "0.00000", None)])
def test_number_format_shows_four_significant_digits(value, fmt, shown, tmp_path):
    assert number_format(value) == fmt
    df = pd.DataFrame({"x [m]": [value]})
    build_workbook({"t": df}, {}, path=tmp_path / "w.xlsx")
    cell = load_workbook(tmp_path / "w.xlsx")["t"]["A2"]
    assert cell.value == pytest.approx(value, rel=1e-15, abs=0)    # stored at full precision (16 digits)
    assert cell.number_format == fmt


def test_long_provenance_round_trips_without_truncation(tmp_path):
    toml = "".join(f'key_{i} = "{"x" * 60}"\n' for i in range(1000))      # 71 000 characters, many lines
    line = "".join(chr(65 + i % 26) for i in range(70_000))                # one 70 000-character line
    prov = {"resolved_study": toml, "one_line": line, "short": "=1+2", "empty": ""}
    assert len(toml) > EXCEL_CELL_MAX and len(line) > EXCEL_CELL_MAX
    build_workbook({"t": pd.DataFrame({"a [m]": [1.0]})}, prov, path=tmp_path / "p.xlsx")
    ws = load_workbook(tmp_path / "p.xlsx")["provenance"]
    assert max(len(str(c.value or "")) for row in ws.iter_rows() for c in row) <= EXCEL_CELL_MAX
    assert read_provenance(ws) == prov
    f = provenance_frame(prov)
    assert (f["key"] == "one_line").sum() == 9 and f.loc[f["key"] == "one_line", "continues"].sum() == 8


def test_budget_workbook_has_log_charts_per_case_and_error(tmp_path):
    d = tomllib.loads((ROOT / "studies" / "error_budget.toml").read_text())
    d["filters"].pop("file", None)
    d["study"]["duration"] = "6 min"
    d["filters"]["cases"] = ["pure_ins", "B1"]
    d["output"] = {"history_every": "30 s", "report_times": ["6 min"]}
    r = covtool.run_study(d)
    write_outputs(r, tmp_path / "o", figures=False)
    wb = load_workbook(tmp_path / "o" / f"{r.name}.xlsx")
    charts = wb["charts"]._charts
    assert len(charts) == 3 * 2
    for ch in charts:
        assert ch.y_axis.scaling.logBase == 10
        titles = _series_titles(ch)
        assert titles[0].startswith("total [") and len(titles) == len(set(titles)) >= 3
    with zipfile.ZipFile(tmp_path / "o" / f"{r.name}.xlsx") as z:
        xml = [z.read(n).decode() for n in z.namelist() if n.startswith("xl/charts/chart")]
    assert all("history_" in x for x in xml)


def test_chart_refuses_rows_of_a_case_that_are_not_contiguous(tmp_path):
    from covtool.io.workbook import add_line_chart
    df = pd.DataFrame({"case": ["A", "B", "A"], "t [s]": [0.0, 1.0, 2.0], "x [m]": [1.0, 2.0, 3.0]})
    wb = build_workbook({"h": df}, {})
    with pytest.raises(ValueError, match="rows of one 'case' are not contiguous"):
        add_line_chart(wb, {"sheet": "h", "x": "t [s]", "y": ["x [m]"], "group": "case"})
    with pytest.raises(ValueError, match="has no column 'y \\[m\\]'"):
        add_line_chart(wb, {"sheet": "h", "x": "t [s]", "y": ["y [m]"]})
