"""Labelled results (issue 12) and figures drawn from them (issue 14 item 7).

Histories know their times and state names; each study kind returns its own
result class; figures are functions of result objects (never closures in a
runner): log axes that span the data, distinct styles and a note when curves
coincide, shaded ZUPT stops, legends beside the axes, one colour per source.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import matplotlib
import numpy as np
import pandas as pd
import pytest

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import covtool  # noqa: E402
from covtool.errors import StudyFileError  # noqa: E402
from covtool.lincov.batch import System, events, run_batch  # noqa: E402
from covtool.lincov.history import NAV_STATES, CovarianceHistory  # noqa: E402
from covtool.lincov.reference import propagate_with_filter  # noqa: E402
from covtool.plotting.budget import budget_figure  # noqa: E402
from covtool.plotting.navigation import error_history_figure  # noqa: E402
from covtool.plotting.sensitivity import fig8_figure  # noqa: E402
from covtool.plotting.style import coincident_groups, log_limits  # noqa: E402
from covtool.results import (ErrorBudgetResult, PureInsResult, ZuptFilterOrderResult,  # noqa: E402
                             ZuptSensitivityResult)

ROOT = Path(__file__).resolve().parents[1]


def flagship_decl(duration="6 min", cases=("A", "B1", "D"), **output):
    d = tomllib.loads((ROOT / "studies" / "zupt_filter_order.toml").read_text())
    d["study"]["duration"] = duration
    d["filters"]["cases"] = list(cases)
    d["filters"].pop("file")
    d["output"] = {"history_every": "10 s", "report_times": [duration], **output}
    d["impact"] = {"filters": []}
    return d


@pytest.fixture(scope="module")
def flagship():
    return covtool.run_study(flagship_decl())


# ---------------------------------------------------------------- CovarianceHistory

def _random_walk_run():
    """One state x, Φ = 1, Q_d = q per step, update z = x + v (R = r) at step 2 of 4."""
    p0, q, r = 4.0, 0.5, 1.0
    N = 4
    Phi = np.ones((N, 1, 1))
    Qd = np.full((N, 1, 1), q)
    t = np.arange(N + 1) * 10.0
    H = np.ones((1, 1))
    run = propagate_with_filter(Phi, Qd, np.array([[p0]]), Phi, Qd, np.array([[p0]]), H, H, np.eye(1),
                                np.array([[r]]), [2], times=t, names=["x"], filter_names=["x"])
    return run, (p0, q, r, t)


def test_filter_run_histories_keep_times_names_priors_and_gains():
    """Scalar Riccati: prior p0 + 2q at the update, posterior prior·r/(prior + r), gain prior/(prior + r)."""
    run, (p0, q, r, t) = _random_walk_run()
    h = run.truth_history()
    prior = p0 + 2 * q
    post = prior * r / (prior + r)
    assert h.names == ("x",) and np.array_equal(h.times, t)
    assert np.array_equal(h.update_times, [t[2]])
    assert h.prior[0, 0, 0] == pytest.approx(prior, rel=1e-15)
    np.testing.assert_allclose(h.variance("x"), [p0, p0 + q, post, post + q, post + 2 * q], rtol=1e-14)
    np.testing.assert_allclose(h.sigma("x"), np.sqrt([p0, p0 + q, post, post + q, post + 2 * q]), rtol=1e-14)
    g = run.gain_table()
    assert np.array_equal(g["times"], [t[2]]) and g["filter_names"] == ("x",)
    assert g["K"][0, 0, 0] == pytest.approx(prior / (prior + r), rel=1e-15)
    df = h.to_pandas()
    assert list(df.columns) == ["x"] and df.index.name == "t [s]"
    np.testing.assert_allclose(df["x"].to_numpy(), h.sigma("x"), rtol=0)


def test_batch_result_carries_names_and_times():
    """The batched engine against the same closed form, its history labelled."""
    _, (p0, q, r, t) = _random_walk_run()
    N = 4
    ev = events(N, [2], range(N + 1))
    truth = System.from_steps(np.ones((N, 1, 1)), np.full((N, 1, 1), q), ev)
    res = run_batch(truth, np.array([[[p0]]]), np.ones((1, 1)), np.array([[r]]), np.eye(1), [2], list(range(N + 1)),
                    filt=truth, Pf0=np.array([[[p0]]]), Hf=np.ones((1, 1)), Rf=np.array([[[r]]]), keep=slice(0, 1),
                    names=["x"], filter_names=["x"], times=t)
    h = res.history(0, label="batch")
    prior = p0 + 2 * q
    post = prior * r / (prior + r)
    assert h.names == ("x",) and res.filter_names == ("x",)
    assert np.array_equal(h.times, t) and np.array_equal(h.update_times, [t[2]])
    np.testing.assert_allclose(h.variance("x"), [p0, p0 + q, post, post + q, post + 2 * q], rtol=1e-13)


def test_history_refuses_bad_shapes_and_unknown_names():
    P = np.tile(np.eye(2), (3, 1, 1))
    with pytest.raises(ValueError, match=r"P has shape \(3, 2, 2\); expected \(3, 3, 3\)"):
        CovarianceHistory([0, 1, 2], ["a", "b", "c"], P)
    with pytest.raises(ValueError, match="duplicate state names"):
        CovarianceHistory([0, 1, 2], ["a", "a"], P)
    with pytest.raises(ValueError, match="times are not increasing"):
        CovarianceHistory([0, 2, 1], ["a", "b"], P)
    with pytest.raises(ValueError, match=r"prior has shape \(2, 2, 2\); expected \(1, 2, 2\)"):
        CovarianceHistory([0, 1, 2], ["a", "b"], P, [1.0], np.zeros((2, 2, 2)))
    h = CovarianceHistory([0, 1, 2], ["a", "b"], P, label="h")
    with pytest.raises(KeyError, match=r"h: no state 'dh' \(stored: a, b\)"):
        h.sigma("dh")
    Pn = P.copy()
    Pn[1, 0, 0] = -1.0
    assert np.isnan(CovarianceHistory([0, 1, 2], ["a", "b"], Pn).sigma("a")[1])     # never a σ of a negative


def test_study_result_is_typed_and_labelled(flagship):
    r = flagship
    assert isinstance(r, ZuptFilterOrderResult) and r.kind == "zupt_filter_order"
    assert set(r.histories) == {"pure_ins", "A", "B1", "D"}
    h = r.histories["B1"]
    assert h.names == NAV_STATES and h.times.shape == r.times.shape
    # the height error's σ equals the down-position σ of the NED metrics (an independent transform)
    np.testing.assert_allclose(h.sigma("dh"), r.metrics["B1"]["sigma_down"], rtol=1e-12)
    # the filter's claim is evaluated at the report times only (exact CEP is costly)
    k = [int(np.argmin(np.abs(r.times - tr))) for tr in r.report_times]
    np.testing.assert_allclose(r.claimed["B1"].sigma("dh")[k], r.claimed_metrics["B1"]["sigma_down"], rtol=1e-12)
    assert np.array_equal(h.update_times, r.update_times) and r.update_times.size >= 1
    pd.testing.assert_frame_equal(r.to_pandas(), r.summary)
    fig = r.plot()
    assert fig.axes[0].get_title().startswith("Fig 6")
    plt.close(fig)
    with pytest.raises(KeyError, match="no figure 'fig9'"):
        r.plot("fig9")


# ---------------------------------------------------------------- figures from results

def _nav_result(**metrics_by_case):
    t = np.arange(0, 601, 10.0)
    metrics = {c: {"cep": y, "alt_pe": y / 3} for c, y in metrics_by_case.items()}
    return ZuptFilterOrderResult(name="synthetic", kind="zupt_filter_order", tables={"summary": pd.DataFrame()},
                                 times=t, metrics=metrics, update_times=np.array([300.0, 600.0]),
                                 stops=((210.0, 300.0), (510.0, 600.0)), length_unit="m")


def test_fig6_log_axis_spans_the_data_and_styles_differ(flagship):
    r = flagship
    for q, key in (("horizontal", "cep"), ("altitude", "alt_pe")):
        fig = error_history_figure(r, q)
        ax = fig.axes[0]
        assert ax.get_yscale() == "log"
        lo, hi = ax.get_ylim()
        after = r.times >= r.update_times[0]
        for m in r.metrics.values():            # no curve is clipped after the first update (no fixed floor)
            y = m[key][after] / 0.3048
            assert lo < y.min() and y.max() < hi
        lines = [ln for ln in ax.get_lines() if ln.get_label() in r.metrics]
        styles = {(ln.get_color(), str(ln.get_linestyle()), ln.get_marker()) for ln in lines}
        assert len(lines) == len(r.metrics) == len(styles)
        assert ax.get_ylabel() == f"{'horizontal CEP' if q == 'horizontal' else 'altitude PE'} [ft]"
        plt.close(fig)


def test_fig6_notes_coinciding_curves_shades_stops_and_keeps_the_legend_outside():
    y = np.linspace(0.01, 50.0, 61)
    r = _nav_result(A=y, B1=y * 1.004, D=y * 2)
    fig = error_history_figure(r, "horizontal")
    ax = fig.axes[0]
    texts = " ".join(t.get_text() for t in fig.texts)
    assert "A, B1 coincide (within 1 %)" in texts and "D" not in texts.split("Note:")[1].split("coincide")[0]
    spans = [p for p in ax.patches if p.get_label() == "stop with ZUPT" or p.get_facecolor()[:3] != (1, 1, 1)]
    assert len(spans) == 2
    fig.canvas.draw()
    leg = ax.get_legend().get_window_extent()
    assert leg.x0 >= ax.get_window_extent().x1          # beside the axes, over no curve
    assert ax.get_ylabel() == "horizontal CEP [m]"
    plt.close(fig)


def test_coincident_groups_and_log_limits():
    a = np.array([1.0, 2.0, 4.0])
    assert coincident_groups({"A": a, "B": a * 1.009, "C": a * 1.02, "D": a * 1.0205}) == [["A", "B"], ["C", "D"]]
    assert log_limits([np.array([0.0, 0.2, 5.0, np.nan])], pad=2.0) == (0.1, 10.0)
    assert log_limits([np.zeros(3)]) is None


def test_budget_figure_log_variance_and_one_colour_per_source():
    t = np.linspace(0, 600, 61)
    grow = 1.0 + t
    v = {"horizontal": np.array([grow * 1e2, grow, 1e-3 * grow]), "altitude": np.array([grow, grow * 10, grow]),
         "azimuth": np.array([1e-8 * grow, 1e-9 * grow, 1e-10 * grow])}
    r = ErrorBudgetResult(name="b", kind="error_budget", tables={"summary": pd.DataFrame()}, times=t,
                          variances={"B1": v}, sources={"B1": ["s1", "s2", "s3"]}, source_order=["s1", "s2", "s3"],
                          top=3, stops=((200.0, 300.0),), length_unit="ft")
    fig = budget_figure(r, "B1")
    left = fig.axes[0::2]
    assert all(ax.get_yscale() == "log" for ax in left)
    colours = {}
    for ax in left:
        for ln in ax.get_lines():
            colours.setdefault(ln.get_label(), set()).add(matplotlib.colors.to_hex(ln.get_color()))
    assert all(len(c) == 1 for c in colours.values())                      # a source keeps its colour
    assert len({next(iter(colours[s])) for s in ("s1", "s2", "s3", "total")}) == 4
    # the state at 10 min is on the axis (before: a linear axis flattened it under the first peak)
    lo, hi = left[0].get_ylim()
    s2 = v["horizontal"][1] / 0.3048**2
    assert lo < s2[1:].min() and hi > v["horizontal"].sum(axis=0).max() / 0.3048**2     # s2, 100x below s1, shows
    assert lo >= hi * 1e-5 * 0.999                      # but no decades are spent below 1e-5 of the peak
    assert left[0].get_ylabel() == "variance [ft²]"
    plt.close(fig)


def test_fig8_is_log_log_with_the_legend_beside():
    s = np.geomspace(0.01, 100, 5)
    curves = {(c, p, m): (1 + k) * (1 + s) for k, c in enumerate(("A", "B1", "B2")) for p in ("P0", "R")
              for m in ("horizontal", "altitude")}
    curves.update({("B2", p, m): curves[("B1", p, m)] * 1.001 for p in ("P0", "R") for m in ("horizontal", "altitude")})
    fits = {k: (lambda x, k=k: np.interp(x, s, curves[k] / 0.3048)) for k in curves}
    r = ZuptSensitivityResult(name="s", kind="zupt_sensitivity", tables={"summary": pd.DataFrame()}, scales=s,
                              parameters=["P0", "R"], filters=["A", "B1", "B2"], curves=curves, fits=fits,
                              report_time=1800.0, labels={"metrics": {"horizontal": "horizontal RMS",
                                                                      "altitude": "altitude RMS"},
                                                          "params": {"P0": "P_f(0)", "R": "R_f"}})
    fig = fig8_figure(r, "altitude")
    axes = [ax for ax in fig.axes]
    assert all(ax.get_xscale() == "log" and ax.get_yscale() == "log" for ax in axes)
    fig.canvas.draw()
    leg = axes[-1].get_legend()
    assert leg.get_window_extent().x0 >= axes[-1].get_window_extent().x1
    assert "B1, B2 coincide" in " ".join(t.get_text() for t in fig.texts)
    plt.close(fig)


def test_units_setting_draws_metres_and_refuses_others(tmp_path):
    r = covtool.run_study(flagship_decl("6 min", ("B1",), units="m"))
    assert r.length_unit == "m"
    assert r.charts[0]["y"] == ["CEP [m]"]
    fig = r.plot("fig7_altitude_pe")
    assert fig.axes[0].get_ylabel() == "altitude PE [m]"
    plt.close(fig)
    with pytest.raises(StudyFileError, match=r"\[output\] units: 'km' is not one of: 'ft', 'm'"):
        covtool.run_study(flagship_decl("6 min", ("B1",), units="km"))


def test_pure_ins_result(tmp_path):
    d = tomllib.loads((ROOT / "studies" / "pure_ins_land_vehicle.toml").read_text())
    d["study"]["duration"] = "3 min"
    d["output"] = {"history_every": "30 s", "report_times": ["3 min"]}
    r = covtool.run_study(d)
    assert isinstance(r, PureInsResult)
    np.testing.assert_allclose(r.history.sigma("dh"), r.metrics["sigma_down"], rtol=1e-12)
    fig = r.plot()
    assert [ax.get_yscale() for ax in fig.axes] == ["log"] * 3 and fig.axes[0].get_ylabel().endswith("[ft]")
    plt.close(fig)


def test_trade_grid_figure_from_its_result():
    import importlib.util
    spec = importlib.util.spec_from_file_location("tt", ROOT / "tests" / "test_trade.py")
    tt = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tt)
    from covtool.results import TradeGridResult
    r = covtool.run_study(tt.small_decl())
    assert isinstance(r, TradeGridResult) and set(r.nominal["filter"]) <= set(r.filters)
    fig = r.plot()
    axes = fig.axes
    assert all(ax.get_yscale() == "log" for ax in axes)
    for ax, col in ((axes[0], "CEP [ft]"), (axes[len(axes) // 2], "alt PE [ft]")):
        lo, hi = ax.get_ylim()
        assert lo < r.nominal[col].min() and r.nominal[col].max() < hi
    plt.close(fig)


def test_figures_are_functions_of_the_result(flagship):
    """No closure over runner locals: every figure is a plotting function applied to the result itself."""
    from functools import partial
    assert set(flagship.figures) == {"fig6_horizontal_cep", "fig7_altitude_pe"}
    for f in flagship.figures.values():
        assert isinstance(f, partial) and f.args[0] is flagship and f.func.__module__.startswith("covtool.plotting.")


def test_results_have_no_untyped_data_dict():
    """Issue 12 "Labelled results": every field of every result class is named; no ``data`` grab-bag."""
    import dataclasses

    from covtool.results import RESULT_CLASSES, StudyResult
    for cls in (StudyResult, *RESULT_CLASSES.values()):
        assert "data" not in {f.name for f in dataclasses.fields(cls)}, cls.__name__
