"""Truth-magnitude sweep (issue 11, acceptance 5).

Oracles: the flagship run on the default truth (the declared magnitude is a
sweep point), the flagship run on models/sdins58_uncalibrated.toml (10 arcsec
misalignments, computed by an independent path: its own truth P0, filter P0
and equivalent noise), and the closed form of the log interpolation.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import covtool
from covtool.errors import StudyFileError
from covtool.studies.magnitude_sweep import threshold_table

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "studies" / "misalignment_sweep.toml"
FLAGSHIP = ROOT / "studies" / "zupt_filter_order.toml"


def decl(duration="11 min", **sweep):
    d = tomllib.loads(STUDY.read_text())
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["study"]["duration"] = duration
    d["output"]["report_times"] = [duration]
    d["filters"]["cases"] = ["A", "B1", "D"]
    d["sweep"]["values"] = ["2 arcsec", "10 arcsec"]
    d["sweep"]["group"] = [{"name": "gyro", "states": ["gyro_mis"]},
                           {"name": "misalignments", "states": ["acc_mis", "gyro_mis"]}]
    d["sweep"].update(sweep)
    return d


@pytest.fixture(scope="module")
def short():
    return covtool.run_study(decl())


def _flagship(model):
    d = tomllib.loads(FLAGSHIP.read_text())
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["study"]["duration"] = "11 min"
    d["output"]["report_times"] = ["11 min"]
    d["filters"]["cases"] = ["A", "B1", "D"]
    d["truth"]["model"] = model
    d["impact"] = {"filters": []}
    return covtool.run_study(d).summary.set_index("case")


@pytest.mark.parametrize("model,group,value", [("sdins58", "gyro", "2 arcsec"),
                                               ("sdins58_uncalibrated", "misalignments", "10 arcsec")])
def test_sweep_points_equal_flagship_runs(short, model, group, value):
    ref = _flagship(model)
    sw = short.tables["sweep"]
    for f in ("A", "B1", "D"):
        row = sw[(sw["group"] == group) & (sw["magnitude"] == value) & (sw["filter"] == f)].iloc[0]
        assert row["CEP [ft]"] == pytest.approx(ref.loc[f, "CEP [ft]"], rel=1e-8), f
        assert row["alt PE [ft]"] == pytest.approx(ref.loc[f, "alt PE [ft]"], rel=1e-8), f
        assert row["azimuth 1sigma [arcmin]"] == pytest.approx(ref.loc[f, "azimuth 1sigma [arcmin]"], rel=1e-8), f
    assert set(short.summary["filter"]) == {"B1", "D"}


def test_threshold_is_interpolated_in_log_magnitude():
    """Ratios 1.2 at 1 and 1.8 at 4: 1.5 is crossed half-way in log, at 2."""
    from covtool.io.library import load_model_by_name
    truth = load_model_by_name("sdins58")
    sweep = pd.DataFrame({"group": "g", "filter": ["B1"] * 3 + ["D"] * 3, "magnitude": ["1", "4", "8"] * 2,
                          "magnitude, SI value": [1.0, 4.0, 8.0] * 2, "CEP / A [-]": [1.2, 1.8, 2.0, 1.6, 1.7, 1.9]})
    opts = {"groups": [{"name": "g", "states": ["gyro_mis_xy"], "unit_text": ""}]}
    t = threshold_table(sweep, 1.5, ["g"], ["B1", "D"], truth, opts).set_index("filter")
    assert t.loc["B1", "crossing, SI value"] == pytest.approx(2.0, rel=1e-12)
    assert t.loc["D", "crossing, SI value"] == 0.0 and t.loc["D", "crossing"].startswith("below the sweep")


@pytest.mark.parametrize("mutate,match", [
    (lambda d: d.pop("sweep"), r"\[sweep\]: missing \[sweep\] table"),
    (lambda d: d["sweep"].update(threshold=1.0), r"\[sweep\] threshold: 1.0 is not a number greater than 1"),
    (lambda d: d["sweep"].update(group=[{"name": "x", "states": ["gyro_mis_qq"]}]),
     r"group 1 states: unknown state or block 'gyro_mis_qq'"),
    (lambda d: d["sweep"].update(group=[{"name": "x", "states": ["gyro_mis", "acc_bias"]}]),
     r"group 1 states: states of different dimensions \(acceleration, angle\)"),
    (lambda d: d["sweep"].update(values=["2 ug"]), r"\[sweep\] values: '2 ug' is not an angle"),
    (lambda d: d["sweep"].update(group=[]), r"\[sweep\] group: declare at least one"),
    (lambda d: d["truth"].update(override={"gyro_mis_xy": {"sigma": "0 arcsec"}}),
     r"state 'gyro_mis_xy' is declared with sigma 0"),
    (lambda d: d["filters"].update(cases=["B1", "D"]), r"needs filter \"A\""),
])
def test_sweep_declaration_errors(mutate, match):
    d = decl("6 min")
    mutate(d)
    with pytest.raises(StudyFileError, match=match):
        covtool.run_study(d)
