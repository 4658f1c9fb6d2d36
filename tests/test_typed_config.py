"""Typed study configurations (issue 12): parsed once before any computation, varied by model_copy in SI.

* ``covtool.run_study`` parses the whole file into its kind's frozen configuration before the runner starts;
* the cross-field rules live in the declarations (dt within the duration, report times within the study, the
  trade grid's own keys), each refusal one line naming file, table and key;
* the trade grid varies its configuration by ``model_copy`` (typed SI values), never through strings, and
  applies an IMU grade to the truth model in SI;
* the land-vehicle route takes every parameter from its declaration;
* ``[output] units`` reaches the Fig 8 fits and the trade grid's pivot tables and figure.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

import covtool
from covtool.errors import StudyFileError
from covtool.studies.config import (GradeEntry, LandVehicle, load_config, TradeGridConfig, ZuptFilterOrderConfig)
from covtool.studies.inputs import graded, load_trajectory, load_truth, UNSCALED_KINDS
from covtool.units import FT

ROOT = Path(__file__).resolve().parents[1]
STUDIES = ROOT / "studies"
DEG_H = math.pi / 180 / 3600          # 1 deg/h in rad/s


def _decl(name):
    return tomllib.loads((STUDIES / name).read_text())


# ---------------------------------------------------------------------------
# parsed once, before any computation
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("name, section, key", [
    ("zupt_sensitivity.toml", "cost", "measure"),
    ("zupt_filter_order.toml", "impact", "filters"),
    ("error_budget.toml", "budget", "resolution"),
    ("trade_grid.toml", "grid", "q_scale"),
    ("misalignment_sweep.toml", "sweep", "threshold"),
])
def test_a_bad_last_section_is_refused_before_the_runner_starts(monkeypatch, name, section, key):
    decl = _decl(name)
    kind = decl["study"]["kind"]
    module = __import__(f"covtool.studies.{kind}", fromlist=["run"])

    def computed(*a, **k):
        raise AssertionError("the runner started")

    monkeypatch.setattr(module, "run", computed)
    decl.setdefault(section, {})[key] = {"not": "a value"}
    with pytest.raises(StudyFileError, match=rf"^<study>: \[{section}\] {key}: "):
        covtool.run_study(decl)


@pytest.mark.parametrize("decl, match", [
    ({"study": {"kind": "pure_ins", "duration": "1 min", "dt": "2 min"}},
     r"^s.toml: \[study\] dt: '2 min' is longer than the duration \(60 s\)"),
    ({"study": {"kind": "zupt_filter_order", "duration": "6 min"}, "output": {"report_times": ["1 min", "7 min"]}},
     r"^s.toml: \[output\] report_times\[1\]: '7 min' is after the end of the study \(360 s\)"),
    ({"study": {"kind": "pure_ins"}, "output": {"report_times": ["6 min", "360 s"]}},
     r"^s.toml: \[output\] report_times: a time is listed twice in \['6 min', '360 s'\]"),
    ({"study": {"kind": "pure_ins"}, "truth": {"model": 3}}, r"^s.toml: \[truth\] model: 3 is not a model name"),
    ({"study": {"kind": "pure_ins"}, "trajectory": {"builtin": "land_vehicle", "lon": "200 deg"}},
     r"^s.toml: \[trajectory\] lon: '200 deg' is not within ±180 deg"),
    ({"study": {"kind": "pure_ins"}, "trajectory": {"builtin": "static", "lat": "1 deg", "lon": "-181 deg",
                                                    "h": "0 m"}},
     r"^s.toml: \[trajectory\] lon: '-181 deg' is not within ±180 deg"),
])
def test_cross_field_rules_live_in_the_declarations(decl, match):
    with pytest.raises(StudyFileError, match=match):
        load_config(decl, "s.toml")


def _grid(**change):
    d = _decl("trade_grid.toml")
    for k, v in change.items():
        d[k] = v
    return d


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d.pop("grid"), r"^s.toml: missing \[grid\] table"),
    (lambda d: d["zupt"].update(interval="5 min"), r"^s.toml: \[zupt\] interval: the ZUPT interval is a grid axis"),
    (lambda d: d["trajectory"].update(cycles=3), r"^s.toml: \[trajectory\] cycles: is set per ZUPT interval"),
    (lambda d: d["grid"].update(q_scale=[1.0, math.nan]), r"^s.toml: \[grid\] q_scale\[1\]: nan is not finite"),
    (lambda d: d["grid"].update(p0_scale=[2, 2.0]), r"^s.toml: \[grid\] p0_scale: repeated values in \[2, 2.0\]"),
    (lambda d: d["grid"].update(r_scale=[]), r"^s.toml: \[grid\] r_scale: expected a non-empty list"),
    (lambda d: d["grid"].update(zupt_interval=["3 min", "180 s"]),
     r"^s.toml: \[grid\] zupt_interval: repeated values in \['3 min', '180 s'\]"),
    (lambda d: d.update(grade={"name": "x"}), r"^s.toml: \[\[grade\]\]: expected an array of tables"),
    (lambda d: d["grade"].append({"scale": 2}), r"^s.toml: \[\[grade\]\] #5: missing 'name'"),
    (lambda d: d["grade"].append({"name": "tactical"}), r"^s.toml: \[\[grade\]\] #5 name: grade 'tactical' is "
                                                          r"declared twice"),
    (lambda d: d["grade"].append({"name": "y", "colour": 1}), r"^s.toml: \[\[grade\]\] #5: unknown key 'colour'"),
    (lambda d: d["grade"].append({"name": "y", "scale": 1e9}), r"^s.toml: \[\[grade\]\] #5 scale: 1000000000.0 is "
                                                                r"not a number"),
    (lambda d: d["grade"].append({"name": "y", "override": {"gyro_bias_z": 1}}),
     r"^s.toml: \[\[grade\]\] #5 override: expected a table of state tables"),
])
def test_trade_grid_declaration_refusals(mutate, match):
    d = _grid()
    mutate(d)
    with pytest.raises(StudyFileError, match=match):
        load_config(d, "s.toml")


def test_a_grade_override_with_a_bad_unit_names_the_grade():
    cfg = load_config(_grid(grade=[{"name": "y", "override": {"gyro_bias_z": {"sigma": "1 ug"}}}]), "s.toml")
    with pytest.raises(StudyFileError, match=r"^s.toml: \[\[grade\]\] 'y' override gyro_bias_z sigma: '1 ug' is "
                                             r"not an angular rate"):
        load_truth(cfg, "s.toml", None, grade=cfg.grade[0])


@pytest.mark.parametrize("key, value, match", [
    ("arw", "1 m", r"^s.toml: \[\[grade\]\] 'y' arw: '1 m' is not an angle random walk"),
    ("vrw", "1 m", r"^s.toml: \[\[grade\]\] 'y' vrw: '1 m' is not a velocity random walk"),
    ("vrw", "-1 ug/sqrt(Hz)", r"^s.toml: \[\[grade\]\] 'y' vrw: '-1 ug/sqrt\(Hz\)' is negative"),
])
def test_a_grade_arw_or_vrw_is_checked_with_the_grade_named(key, value, match):
    cfg = load_config(_grid(grade=[{"name": "y", key: value}]), "s.toml")
    with pytest.raises(StudyFileError, match=match):
        load_truth(cfg, "s.toml", None, grade=cfg.grade[0])


# ---------------------------------------------------------------------------
# the trade grid varies typed configurations
# ---------------------------------------------------------------------------

def test_trade_grid_chunk_configuration_equals_the_declared_study_of_that_interval():
    """model_copy in SI gives the configuration a user would declare for that interval, exactly."""
    from covtool.studies.trade_grid import TradePlan

    d = _decl("trade_grid.toml")
    plan = TradePlan(d, STUDIES / "trade_grid.toml")
    ii = plan.intervals.index(240.0)
    sub = plan.configs[ii]
    assert isinstance(sub, ZuptFilterOrderConfig)
    stop, acc = d["trajectory"]["stop_duration"], "20 s"      # land_vehicle's declared accel_duration
    cycles = math.ceil(1800.0 / 240.0)                        # 8 cycles of 4 min cover 30 min
    speed = 45 / 3.6                                          # [grid] cruise_speed = "45 km/h"
    by_hand = {**{k: v for k, v in d.items() if k in ("trajectory", "truth", "filters", "zupt", "output")},
               "study": {**d["study"], "kind": "zupt_filter_order"}}
    by_hand["trajectory"] = {**d["trajectory"], "period": "4 min", "cycles": cycles,
                             "distance": f"{speed * cycles * (240.0 - 60.0 - 20.0)!r} m"}
    by_hand["zupt"] = {**d["zupt"], "interval": "4 min"}
    by_hand["filters"] = {**d["filters"], "pure_ins": False}
    declared = load_config(by_hand, "s.toml")
    assert stop == "60 s" and acc == "20 s"
    assert sub.trajectory == declared.trajectory
    assert sub.zupt == declared.zupt and sub.filters == declared.filters and sub.truth == declared.truth
    assert sub.study.duration == declared.study.duration and sub.study.kind == "zupt_filter_order"
    # the trade grid's own configuration is untouched (frozen, varied by copies)
    assert plan.config.zupt.interval == 300.0 and plan.config.trajectory.period == 300.0


def test_grade_scales_the_truth_in_si_and_the_filters_follow():
    cfg = load_config(_grid(), "s.toml")
    base = load_truth(cfg, "s.toml", None)
    g = GradeEntry.model_validate({"name": "x", "scale": 7.0, "override": {"gyro_bias": {"sigma": "2 deg/h"},
                                                                           "gyro_bias_z": {"sigma": "1 deg/h"}},
                                   "arw": "0.05 deg/sqrt(h)"})
    truth, filters = load_truth(cfg, "s.toml", None, grade=g, for_filters=True)
    assert filters is truth
    for s0, s1 in zip(base.states, truth.states):
        if s1.name == "gyro_bias_z":                           # a state's own table wins over its block's
            assert s1.sigma == pytest.approx(1.0 * DEG_H, rel=1e-15)
        elif s1.block == "gyro_bias":                          # the grade's block override, after the scaling
            assert s1.sigma == pytest.approx(2.0 * DEG_H, rel=1e-15)
        elif s0.kind in UNSCALED_KINDS:
            assert s1.sigma == s0.sigma, s0.name
        else:
            assert s1.sigma == 7.0 * s0.sigma and s1.rw == 7.0 * s0.rw, s0.name
    assert truth.arw == pytest.approx(0.05 * math.radians(1) / 60, rel=1e-15)
    assert truth.vrw == 7.0 * base.vrw
    assert graded(base, 1.0) is base


# ---------------------------------------------------------------------------
# the land-vehicle route: its declaration is the one home of its defaults
# ---------------------------------------------------------------------------

def test_land_vehicle_route_is_built_from_its_declaration():
    from covtool.nav.trajectory.profiles import land_vehicle

    declared = LandVehicle()
    route = load_trajectory({}, "s.toml", None, 2.0)
    params = {k: getattr(declared, k) for k in LandVehicle.model_fields if k not in ("builtin", "name_")}
    ref = land_vehicle(dt=2.0, **params)                    # every parameter given: no default used
    np.testing.assert_array_equal(route.f_b, ref.f_b)
    np.testing.assert_array_equal(route.t, ref.t)
    assert route.stationary == ref.stationary
    changed = load_trajectory({"trajectory": {"builtin": "land_vehicle", "stop_duration": "1 min"}}, "s.toml", None,
                              5.0)
    assert changed.stationary[0] == (240.0, 300.0)


def test_land_vehicle_errors_name_the_study_file():
    with pytest.raises(covtool.errors.TrajectoryError, match=r"^s.toml: \[trajectory\]: builtin 'land_vehicle': "
                                                            r"the drive of 30 s per cycle is too short"):
        load_trajectory({"trajectory": {"builtin": "land_vehicle", "period": "2 min"}}, "s.toml", None, 1.0)


# ---------------------------------------------------------------------------
# [output] units reaches the Fig 8 fits and the trade grid
# ---------------------------------------------------------------------------

def _short_sensitivity(units):
    d = _decl("zupt_sensitivity.toml")
    d["study"]["duration"] = "11 min"
    d["output"]["report_times"] = ["11 min"]
    d["output"]["units"] = units
    d["filters"] = {"cases": ["B1"]}                          # the library's filter file
    d["sweep"].update({"scales": {"from": 0.01, "to": 100, "per_decade": 1}, "fit_degree": 2,
                       "parameters": ["Q"]})
    d["cost"]["measure"] = False
    return covtool.run_study(d)


@pytest.fixture(scope="module")
def sensitivity_ft_m():
    return _short_sensitivity("ft"), _short_sensitivity("m")


def test_fig8_fits_are_in_the_chosen_unit(sensitivity_ft_m):
    ft, m = sensitivity_ft_m
    assert m.length_unit == "m" and ft.length_unit == "ft"
    s = m.scales
    for key, f_m in m.fits.items():
        # a log-log least-squares fit moves by log10(0.3048) in c0 and nothing else when the unit changes
        np.testing.assert_allclose(f_m(s), ft.fits[key](s) * FT, rtol=1e-9)
        np.testing.assert_allclose(f_m.coef[1:], ft.fits[key].coef[1:], rtol=1e-9, atol=1e-12)
    fits = m.tables["fits"]
    assert "c0 [log10 m]" in fits and "c0 [log10 ft]" not in fits
    np.testing.assert_allclose(fits["c0 [log10 m]"], ft.tables["fits"]["c0 [log10 ft]"] + math.log10(FT),
                               rtol=1e-12)
    sheet = m.tables["fig8_1_horizontal"]
    np.testing.assert_allclose(sheet["Q B1 swept [m]"].to_numpy()[:s.size], m.curves[("B1", "Q", "horizontal")],
                               rtol=1e-15)
    assert all(c["y_title"].endswith("[m]") for c in m.charts)
    fig = m.figures["fig8_1_horizontal"]()
    assert fig.axes[0].get_ylabel().endswith("[m]")
    assert m.provenance["fit_model"].startswith("log10(error [m])")


def test_trade_grid_tables_and_figure_in_metres():
    d = _decl("trade_grid.toml")
    d["study"].update(duration="8 min", dt="2 s")
    d["trajectory"].update(turn_rate="2.5 deg/s", turn_angle="45 deg")
    d["output"].update(report_times=["8 min"], units="m")
    d["zupt"]["rate"] = "0.5 Hz"
    d["filters"] = {"cases": ["D"]}
    d["grid"].update(zupt_interval=["4 min"], zupt_sigma=["0.01 ft/s"], q_scale=[1.0])
    d["grade"] = d["grade"][:1]
    r = covtool.run_study(d)
    assert r.length_unit == "m"
    pv = r.tables["pivot_cep"]
    assert list(pv.columns) == ["grade", "ZUPT interval [min]", "D CEP [m]"]
    nominal_ft = r.nominal["CEP [ft]"].item()
    assert pv["D CEP [m]"].item() == pytest.approx(nominal_ft * FT, rel=1e-12)
    assert "CEP nominal [m]" in r.tables["tuning_spread"]
    fig = r.figures["trade_grid"]()
    assert fig.axes[0].get_ylabel() == "horizontal CEP [m]"
    line = fig.axes[0].get_lines()[0]
    assert line.get_ydata()[0] == pytest.approx(nominal_ft * FT, rel=1e-12)
