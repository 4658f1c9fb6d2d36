"""The workbook and the CSV files read back equal the result's tables (issue 13, acceptance 1).

Writing was made faster (figures drawn once, in child processes); the
content may not change: every table of a real study run is read back from
its workbook sheet and from its CSV file and compared with the table,
cell by cell, by the rules of :mod:`covtool.io.cells` (text stays text,
NaN/inf are text in the workbook, finite floats are numbers stored to 16
significant digits).
"""

from __future__ import annotations

import csv
import math
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from openpyxl import load_workbook

import covtool
from covtool.io.cells import csv_text_value
from covtool.io.workbook import build_workbook, sheet_title
from covtool.io.writers import write_outputs

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def flagship(tmp_path_factory):
    d = tomllib.loads((ROOT / "studies" / "zupt_filter_order.toml").read_text())
    d["study"]["duration"] = "6 min"
    d["filters"]["cases"] = ["A", "B1", "D"]
    d["filters"].pop("file")
    d["output"] = {"history_every": "10 s", "report_times": ["6 min"]}
    r = covtool.run_study(d)
    out = tmp_path_factory.mktemp("roundtrip") / "out"
    write_outputs(r, out, figures=False)
    return r, out


def _expected_cell(v):
    """What a workbook cell holds for a table value (the rules of covtool.io.cells)."""
    if v is None or v is pd.NA:
        return None
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isnan(v):
            return "NaN"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return v
    if isinstance(v, (int, np.integer)):
        return int(v)
    return str(v) or None                     # an empty text is an empty cell


def _same(cell, want) -> bool:
    if isinstance(want, float):
        # a double is written with 16 significant digits: equal to 1e-15 relative, and a number
        # (a whole number reads back as an int)
        return isinstance(cell, (int, float)) and not isinstance(cell, bool) \
            and cell == pytest.approx(want, rel=1e-15, abs=0)
    if isinstance(want, bool):
        return cell is want
    return cell == want and type(cell) is type(want)


def test_every_sheet_reads_back_equal_to_its_table(flagship):
    r, out = flagship
    wb = load_workbook(out / f"{r.name}.xlsx")
    assert wb.sheetnames == [sheet_title(n) for n in r.tables] + ["provenance"]
    checked = 0
    for name, df in r.tables.items():
        rows = list(wb[sheet_title(name)].iter_rows(values_only=True))
        assert list(rows[0]) == [str(c) for c in df.columns], name
        assert len(rows) == len(df) + 1, name
        for i, (got, want) in enumerate(zip(rows[1:], df.itertuples(index=False, name=None))):
            got = list(got) + [None] * (len(want) - len(got))          # trailing empty cells are not stored
            for j, (g, w) in enumerate(zip(got, want)):
                assert _same(g, _expected_cell(w)), (name, i + 2, df.columns[j], g, w)
                checked += 1
    assert checked > 5000


def test_every_csv_reads_back_equal_to_its_table(flagship):
    r, out = flagship
    for name, df in r.tables.items():
        with open(out / f"{name}.csv", newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
        assert [csv_text_value(h) for h in rows[0]] == [str(c) for c in df.columns], name
        assert len(rows) == len(df) + 1, name
        for got, want in zip(rows[1:], df.itertuples(index=False, name=None)):
            for g, w in zip(got, want):
                if isinstance(w, (float, np.floating)) and not isinstance(w, bool):
                    # a CSV float is written at full precision: it reads back exactly
                    assert (math.isnan(w) and g == "nan") or float(g) == float(w), (name, g, w)
                elif isinstance(w, str):
                    assert csv_text_value(g) == w, (name, g, w)


def test_a_table_of_every_kind_of_value_reads_back_by_the_rules(tmp_path):
    """A table of every kind of value, written by the writer's path and read back."""
    df = pd.DataFrame({
        "case": pd.Series(["=1+2", "plain", "@x", "a\x01b", "-3", None], dtype=object),   # None: no value
        "x [m]": [1.0 / 3.0, np.nan, np.inf, -np.inf, 2.5e-7, 14.999999999999996],
        "n": np.arange(6),
        "flag": [True, False, True, False, True, False],
        "mixed": pd.Series([1.5, "text", 2, None, np.nan, "=A1"], dtype=object),
    })
    build_workbook({"t": df}, {"source": "=cmd|' /C calc'!A0"}, path=tmp_path / "w.xlsx")
    ws = load_workbook(tmp_path / "w.xlsx")["t"]
    got = [list(r) for r in ws.iter_rows(min_row=2, values_only=True)]
    assert got[0] == ["=1+2", pytest.approx(1.0 / 3.0, rel=1e-15), 0, True, 1.5]
    assert got[1] == ["plain", "NaN", 1, False, "text"]
    assert got[2] == ["@x", "inf", 2, True, 2]
    assert got[3][:4] == ["a\\x01b", "-inf", 3, False] and got[3][4] is None
    assert got[4] == ["-3", pytest.approx(2.5e-7, rel=1e-15), 4, True, "NaN"]
    assert got[5][1:] == [pytest.approx(14.999999999999996, rel=1e-15), 5, False, "=A1"] and got[5][0] is None
    cells = {c.coordinate: c for row in ws.iter_rows() for c in row}
    assert all(cells[f"A{i}"].quotePrefix for i in (2, 4, 6)) and not cells["A3"].quotePrefix
    assert cells["E7"].data_type == "s" and cells["E7"].quotePrefix              # "=A1" is text, never a formula
    assert cells["B2"].number_format == "0.0000" and cells["B6"].number_format == "0.000E+00"
    assert cells["B7"].number_format == "0.00" and cells["E2"].number_format == "0.000"
    assert all(c.font.b for c in ws[1]) and ws.freeze_panes == "A2"
