"""Trade-grid study: cases equal the stepwise reference; grades scale the truth; file errors name the culprit."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

import covtool
from covtool.lincov.reference import propagate_with_filter
from covtool.errors import InputError, StudyFileError
from covtool.lincov.reduced import zupt_matrices
from covtool.analysis.metrics import nav_metrics
from covtool.units import ARCMIN, FT
from covtool.studies.inputs import load_truth
from covtool.studies.trade_grid import TradePlan, run
from covtool.studies.zupt_setup import setup

ROOT = Path(__file__).resolve().parents[1]
TRADE = ROOT / "studies" / "trade_grid.toml"


def small_decl() -> dict:
    """8 min, 2 s steps; 2 grades x 2 intervals x 2 filters x 2 Q scales = 16 cases in 4 chunks.

    The turns are 45° at 2.5°/s, so that a 2 s step turns by 5° (within the 5.7° per step that holding F
    constant allows, covtool.studies.grid.check_step_motion).
    """
    d = tomllib.loads(TRADE.read_text())
    d["study"].update(duration="8 min", dt="2 s")
    d["trajectory"].update(turn_rate="2.5 deg/s", turn_angle="45 deg")
    d["output"]["report_times"] = ["8 min"]
    d["zupt"]["rate"] = "0.5 Hz"
    d["filters"] = {"cases": ["B1", "D"]}
    d["grid"].update(zupt_interval=["3 min", "4 min"], zupt_sigma=["0.01 ft/s"], q_scale=[1.0, 3.0])
    d["grade"] = [d["grade"][0], d["grade"][3]]
    return d


@pytest.fixture(scope="module")
def small():
    d = small_decl()
    return d, run(d)


def test_default_grid_has_over_a_thousand_cases():
    plan = TradePlan(tomllib.loads(TRADE.read_text()), TRADE)
    assert plan.n_cases == 6 * 6 * 4 * 3 * 3 == 1296
    assert len(plan.chunks) == 24 and all(len(c["cases"]) == 54 for c in plan.chunks)


@pytest.mark.parametrize("grade, interval, filt, q", [(0, 1, "B1", 1.0), (1, 0, "D", 3.0)])
def test_cases_equal_propagate_with_filter(small, grade, interval, filt, q):
    """A trade case equals the stepwise reference run with the same graded truth and scaled Q_f (≤ 1e-9)."""
    d, r = small
    plan = TradePlan(d, None)
    S = setup(plan.configs[interval], grade=plan.grade_entries[grade])
    fm, Phi_f, Qd_f = S.filter_model(filt)
    ref = propagate_with_filter(S.Phi, S.Qd, S.P0, Phi_f, q * Qd_f, fm.P0, S.H, zupt_matrices(fm.names), fm.D,
                                S.R, S.update_steps, Rf=S.filter_R(filt))
    k = S.t.size - 1
    n = S.nodes
    m = nav_metrics(ref.P_truth[k:, :10, :10], n.lat[k:], n.h[k:], n.q_nb[k:], n.distance[k:])
    c = nav_metrics(ref.P_filter[k:, :10, :10], n.lat[k:], n.h[k:], n.q_nb[k:], n.distance[k:])
    s = r.summary
    row = s[(s["grade"] == plan.grades[grade]["name"]) & np.isclose(s["ZUPT interval [min]"],
                                                                     plan.intervals[interval] / 60)
            & (s["filter"] == filt) & (s["Q scale"] == q)]
    assert len(row) == 1
    row = row.iloc[0]
    np.testing.assert_allclose(row["CEP [ft]"], m["cep"][0] / FT, rtol=1e-9)
    np.testing.assert_allclose(row["alt PE [ft]"], m["alt_pe"][0] / FT, rtol=1e-9)
    np.testing.assert_allclose(row["azimuth 1sigma [arcmin]"], m["sigma_azimuth"][0] / ARCMIN, rtol=1e-9)
    np.testing.assert_allclose(row["filter-claimed CEP [ft]"], c["cep"][0] / FT, rtol=1e-9)


def test_filter_A_shares_the_truth_system_and_equals_the_optimal_filter():
    """Filter A reuses the truth's Φ, Q_d (Taylor truth) and still equals the stepwise reference."""
    d = small_decl()
    d["filters"]["cases"] = ["A"]
    d["grid"].update(zupt_interval=["4 min"], q_scale=[1.0])
    d["grade"] = d["grade"][:1]
    r = run(d)
    assert r.provenance["filters_reusing_truth_phi_qd"] == "A"
    plan = TradePlan(d, None)
    S = setup(plan.configs[0], grade=plan.grade_entries[0])
    fm, Phi_f, Qd_f = S.filter_model("A")                     # computed separately here
    ref = propagate_with_filter(S.Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, S.H, zupt_matrices(fm.names), fm.D, S.R,
                                S.update_steps, Rf=S.filter_R("A"))
    n, k = S.nodes, S.t.size - 1
    m = nav_metrics(ref.P_truth[k:, :10, :10], n.lat[k:], n.h[k:], n.q_nb[k:], n.distance[k:])
    row = r.summary.iloc[0]
    np.testing.assert_allclose(row["CEP [ft]"], m["cep"][0] / FT, rtol=1e-9)
    np.testing.assert_allclose(row["filter-claimed CEP [ft]"], row["CEP [ft]"], rtol=1e-9)   # optimal filter


def test_grade_scales_sensor_errors_only():
    d = small_decl()
    base = load_truth(d, "t", None)
    g = {"name": "x", "scale": 7.0, "override": {"gyro_bias_z": {"sigma": "1 deg/h"}}}
    graded = load_truth(d, "t", None, grade=g)
    for s0, s1 in zip(base.states, graded.states):
        if s1.name == "gyro_bias_z":
            np.testing.assert_allclose(s1.sigma, np.radians(1.0) / 3600, rtol=1e-15)
        elif s0.kind in ("navigation", "gravity_disturbance"):
            assert s1.sigma == s0.sigma, s0.name
        else:
            np.testing.assert_allclose(s1.sigma, 7.0 * s0.sigma, rtol=1e-15, err_msg=s0.name)
    np.testing.assert_allclose([graded.arw, graded.vrw], [7.0 * base.arw, 7.0 * base.vrw], rtol=1e-15)


def test_tables_and_nominal_pivot(small):
    d, r = small
    assert len(r.summary) == 16 and list(r.summary["case"]) == list(range(16))
    cep = r.tables["pivot_cep"]
    assert list(cep.columns) == ["grade", "ZUPT interval [min]", "B1 CEP [ft]", "D CEP [ft]"]
    s = r.summary
    nom = s[(s["grade"] == "tactical") & (s["ZUPT interval [min]"] == 4.0) & (s["filter"] == "D")
            & (s["Q scale"] == 1.0)]["CEP [ft]"].item()
    assert cep.loc[(cep["grade"] == "tactical") & (cep["ZUPT interval [min]"] == 4.0), "D CEP [ft]"].item() == nom
    # a tactical IMU is worse than a navigation one for every filter
    assert (cep[cep["grade"] == "tactical"].iloc[:, 2:].to_numpy()
            > cep[cep["grade"] == "navigation"].iloc[:, 2:].to_numpy()).all()
    sp = r.tables["tuning_spread"]
    assert (sp["CEP max [ft]"] >= sp["CEP nominal [ft]"]).all() and (sp["CEP min [ft]"] <= sp["CEP nominal [ft]"]).all()


def _bad(mutate, tmp_path=None):
    d = small_decl()
    mutate(d)
    return d


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d.pop("grid"), r"missing \[grid\] table"),
    (lambda d: d["grid"].update(zupt_interval=[]), r"\[grid\] zupt_interval: expected a non-empty list"),
    (lambda d: d["grid"].update(zupt_interval=["3 min", "3 min"]), r"repeated values"),
    (lambda d: d["grid"].update(zupt_interval=["3 km"]), r"zupt_interval\[0\]: '3 km' is not a time"),
    (lambda d: d["grid"].update(q_scale=[1.0, -2.0]), r"\[grid\] q_scale\[1\]: -2.0 is not a number >= 1e-06 and <= 1e\+06"),
    (lambda d: d["grid"].update(bogus=1), r"\[grid\].*bogus"),
    (lambda d: d["zupt"].update(interval="5 min"), r"\[zupt\] interval: the ZUPT interval is a grid axis"),
    (lambda d: d["trajectory"].update(period="5 min"), r"\[trajectory\] period: is set per ZUPT interval"),
    (lambda d: d["grid"].update(zupt_interval=["1 min"]), r"zupt_interval '1 min'.*shorter than the stop"),
    (lambda d: d["grid"].update(zupt_interval=["2 min"]), r"zupt_interval = '2 min'.*too short"),
    (lambda d: d.update(grade={"name": "x"}), r"\[\[grade\]\]: expected an array of tables"),
    (lambda d: d["grade"].append({"name": "navigation", "scale": 2}), r"grade 'navigation' is declared twice"),
    (lambda d: d["grade"].append({"scale": 2}), r"\[\[grade\]\] #3: missing 'name'"),
    (lambda d: d["grade"].append({"name": "y", "scale": 0}), r"#3 scale: 0 is not a number >= 1e-06"),
    (lambda d: d["grade"].append({"name": "y", "colour": "red"}), r"\[\[grade\]\] #3.*colour"),
    (lambda d: d["grade"].append({"name": "y", "override": {"gyro_bias_z": 3}}),
     r"#3 override: expected a table of state tables"),
    (lambda d: d["grade"].append({"name": "y", "override": {"no_such_state": {"sigma": "1 ug"}}}),
     r"\[\[grade\]\] 'y'.*unknown state or block 'no_such_state'"),
    (lambda d: d["grade"].append({"name": "y", "override": {"gyro_bias_z": {"sigma": "1 ug"}}}),
     r"\[\[grade\]\] 'y'.*'1 ug' is not an angular rate"),
    (lambda d: d["filters"].update(cases=["B1", "Z9"]), r"unknown filter 'Z9'"),
    (lambda d: d["filters"].update(cases=[]), r"\[filters\] cases: expected a non-empty list"),
    (lambda d: d.update(extra={}), r"extra"),
])
def test_study_file_errors(mutate, match):
    with pytest.raises(StudyFileError, match=match):
        covtool.run_study(_bad(mutate))


def test_study_file_error_names_the_file(tmp_path):
    d = small_decl()
    d["grid"]["zupt_sigma"] = ["0.01 ft"]
    p = tmp_path / "grid.toml"
    p.write_text(tomli_w.dumps(d))
    with pytest.raises(StudyFileError, match=r"grid\.toml: \[grid\] zupt_sigma\[0\]: '0.01 ft' is not a velocity"):
        covtool.run_study(p)


def test_backend_is_refused_by_one_piece_kinds():
    d = tomllib.loads((ROOT / "studies" / "pure_ins_land_vehicle.toml").read_text())
    with pytest.raises(InputError, match=r"'pure_ins' runs in-process in one piece; it takes no backend"):
        covtool.run_study(d, backend="processes")
    with pytest.raises(InputError, match=r"takes no resume"):
        covtool.run_study(copy.deepcopy(d), resume=True)
