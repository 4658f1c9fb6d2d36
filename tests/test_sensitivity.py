"""Sensitivity sweeps and the zupt_sensitivity study (Fig 8).

Seed 002 §3.2.

Oracles: synthetic curves with known coefficients for the fit; the stepwise
reference :func:`covtool.lincov.reference.propagate_with_filter` with the same
scaled P_f(0), Q_f, R_f for the batched sweep; the flagship's own filter
discretisation (declared Taylor series) for the nominal point.
"""

from __future__ import annotations

import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from threadpoolctl import threadpool_limits

from covtool.lincov.reference import propagate_with_filter
from covtool.lincov.batch import System, events
from covtool.errors import StudyFileError
from covtool.lincov.reduced import zupt_matrices
from covtool.io.workbook import sheet_title
from covtool.io.writers import write_outputs
from covtool.analysis.metrics import nav_metrics
from covtool.analysis.sensitivity import fit_loglog, run_sweep, scale_grid, sensitivity_figures, sweep_cases
from covtool.studies import zupt_sensitivity as study
from covtool.units import FT
from covtool.studies.grid import discretize_chunked

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "studies" / "zupt_sensitivity.toml"
FLAGSHIP = ROOT / "studies" / "zupt_filter_order.toml"


# ---------------------------------------------------------------- pure numerics

def test_scale_grid_is_exact_and_contains_nominal():
    s = scale_grid(0.01, 100, 4)
    assert s.size == 17
    assert s[0] == pytest.approx(0.01, rel=1e-15) and s[-1] == pytest.approx(100, rel=1e-15)
    assert np.count_nonzero(s == 1.0) == 1
    np.testing.assert_allclose(np.diff(np.log10(s)), 0.25, rtol=1e-12)


@pytest.mark.parametrize("args,match", [
    ((0.01, 100, 0), "positive integer"),
    ((0.01, 100, 2.5), "positive integer"),
    ((0.0, 100, 4), "must be positive"),
    ((2.0, 100, 4), "bracket the nominal"),
    ((0.03, 100, 4), "not on a grid"),
])
def test_scale_grid_errors(args, match):
    with pytest.raises(ValueError, match=match):
        scale_grid(*args)


def test_sweep_cases_share_the_nominal():
    s = scale_grid(0.01, 100, 1)
    c = sweep_cases(["P0", "Q", "R"], s)
    assert c.n_cases == 1 + 3 * 4
    assert np.all(c.index[:, 2] == 0)
    np.testing.assert_array_equal(c.p0[c.index[0]], s)
    np.testing.assert_array_equal(c.q[c.index[1]], s)
    np.testing.assert_array_equal(c.r[c.index[2]], s)
    np.testing.assert_array_equal(c.q[c.index[0]], 1.0)
    with pytest.raises(ValueError, match="unknown sweep parameter"):
        sweep_cases(["P"], s)


def test_fit_recovers_known_coefficients():
    """An exact cubic in log-log is recovered to 1e-12.

    log10 e = c0 + c1 x + c2 x² + c3 x³: coefficients to 1e-12, zero
    residual, R² = 1.
    """
    s = scale_grid(0.01, 100, 4)
    coef = np.array([1.2, -0.15, 0.08, 0.01])
    x = np.log10(s)
    e = 10 ** (coef[0] + coef[1] * x + coef[2] * x**2 + coef[3] * x**3)
    f = fit_loglog(s, e, 3)
    np.testing.assert_allclose(f.coef, coef, rtol=1e-12, atol=1e-12)
    assert f.resid_rms < 1e-12 and f.r2 == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(f(s), e, rtol=1e-12)
    np.testing.assert_allclose(f.log_slope(s), coef[1] + 2 * coef[2] * x + 3 * coef[3] * x**2, atol=1e-12)


def test_fit_residual_measures_the_noise():
    """Alternating ±δ noise in log10 e leaves an RMS residual ≈ δ."""
    s = scale_grid(0.01, 100, 8)
    x = np.log10(s)
    d = 0.01 * (-1.0) ** np.arange(s.size)
    f = fit_loglog(s, 10 ** (0.5 + 0.2 * x + d), 1)
    assert f.resid_rms == pytest.approx(0.01, rel=0.05)
    np.testing.assert_allclose(f.coef, [0.5, 0.2], atol=2e-3)
    assert 0.9 < f.r2 < 1.0


def test_fit_flat_curve_has_undefined_r2():
    s = scale_grid(0.1, 10, 2)
    f = fit_loglog(s, np.full(s.size, 3.0), 2)
    assert np.isnan(f.r2) and f.resid_rms < 1e-14


@pytest.mark.parametrize("scale,err,deg,match", [
    ([0.1, 1, 10], [1, 0, 1], 1, "finite and positive"),
    ([0.1, 1, 10], [1, 2], 1, "same length"),
    ([0.1, 1, 10], [1, 2, 3], 3, "cannot determine"),
    ([0.1, 1, 10], [1, 2, 3], -1, "non-negative integer"),
])
def test_fit_errors(scale, err, deg, match):
    with pytest.raises(ValueError, match=match):
        fit_loglog(scale, err, deg)


def test_sensitivity_figures_closed_form():
    """e = s^0.5: e(100)/e(1) = 10, e(0.01)/e(1) = 0.1, slope 0.5."""
    s = scale_grid(0.01, 100, 4)
    f = sensitivity_figures(s, s**0.5)
    assert f["rel_high"] == pytest.approx(10.0) and f["rel_low"] == pytest.approx(0.1)
    assert f["primary"] == pytest.approx(9.0)
    assert f["mean_log_slope"] == pytest.approx(0.5)
    u = sensitivity_figures(s, 1 + np.log10(s) ** 2)                  # U-shaped, optimum at x1
    assert u["primary"] == pytest.approx(4.0)
    with pytest.raises(ValueError, match="nominal 1"):
        sensitivity_figures([0.5, 2.0], [1.0, 1.0])


def test_run_sweep_equals_stepwise_reference_on_a_random_system():
    """Batched sweep = stepwise reference per case (rel 1e-10).

    propagate_with_filter with the same scaled P_f(0), Q_f, R_f.
    """
    rng = np.random.default_rng(7)
    n, nf, m, N = 6, 4, 2, 40
    Phi = np.eye(n) + 0.05 * rng.standard_normal((N, n, n))
    L = rng.standard_normal((N, n, n))
    Qd = 1e-3 * L @ np.swapaxes(L, 1, 2)
    D = np.eye(n)[:, :nf]
    Phi_f = Phi[:, :nf, :nf].copy()
    Qd_f = 2.0 * Qd[:, :nf, :nf]
    P0 = np.eye(n)
    Pf0 = 0.5 * np.eye(nf)
    H = np.eye(n)[:m]
    Hf = np.eye(nf)[:m]
    R = 0.1 * np.eye(m)
    Rf = 0.3 * np.eye(m)
    upd = [5, 6, 7, 20, 21, 30]
    cases = sweep_cases(["P0", "Q", "R"], scale_grid(0.01, 100, 1))
    ev = events(N, upd, [N])
    res = run_sweep(System.from_steps(Phi, Qd, ev), P0, H, R, D, System.from_steps(Phi_f, Qd_f, ev), Pf0, Hf, Rf,
                    cases, upd, [N], keep=slice(0, n))
    for b in range(cases.n_cases):
        ref = propagate_with_filter(Phi, Qd, P0, Phi_f, cases.q[b] * Qd_f, cases.p0[b] * Pf0, H, Hf, D, R, upd,
                                    Rf=cases.r[b] * Rf)
        np.testing.assert_allclose(res.P_truth[b, 0], ref.P_truth[-1], rtol=1e-10, atol=1e-12)


def test_joint_scaling_of_p0_q_r_leaves_the_truth_unchanged():
    """Scaling P_f(0), Q_f and R_f together leaves the gains alone.

    Eq (6a)-(8) are homogeneous of degree one in (P_f, Q_f, R_f).
    """
    from covtool.analysis.sensitivity import SweepCases
    rng = np.random.default_rng(3)
    n, m, N = 5, 2, 30
    Phi = np.eye(n) + 0.05 * rng.standard_normal((N, n, n))
    L = rng.standard_normal((N, n, n))
    Qd = 1e-3 * L @ np.swapaxes(L, 1, 2)
    upd = [4, 5, 17, 18, 29]
    ev = events(N, upd, [N])
    sys_ = System.from_steps(Phi, Qd, ev)
    c = np.array([1.0, 0.01, 37.0])
    cases = SweepCases(("joint",), c, c, c, c, np.arange(3)[None])
    H = np.eye(n)[:m]
    res = run_sweep(sys_, np.eye(n), H, 0.2 * np.eye(m), np.eye(n), sys_, 2 * np.eye(n), H, 0.5 * np.eye(m), cases,
                    upd, [N], keep=slice(0, n))
    np.testing.assert_allclose(res.P_truth[1:, 0], res.P_truth[[0, 0], 0], rtol=1e-9)
    np.testing.assert_allclose(res.P_filter[1:, 0], c[1:, None, None] * res.P_filter[[0, 0], 0], rtol=1e-9)


# ---------------------------------------------------------------- the study (short)

def short_decl(**sweep):
    d = tomllib.loads(STUDY.read_text())
    d["study"]["duration"] = "11 min"
    d["output"]["report_times"] = ["11 min"]
    d["filters"]["cases"] = ["A", "B1", "D"]
    d["sweep"].update({"scales": {"from": 0.01, "to": 100, "per_decade": 1}, "fit_degree": 2, **sweep})
    d["cost"]["measure"] = False
    return d


@pytest.fixture(scope="module")
def short():
    return study.run(short_decl(), path=STUDY)


def test_filters_swept_in_a_forked_process_give_the_same_tables(forking, short, monkeypatch):
    """Half the filters are built and swept in a forked process: every table equals the one-process run.

    The shares: the truth copy A stays here, B1 and D are balanced by their states (D forked).
    """
    assert short.provenance["filters_swept_in_a_forked_process"] == "D"
    # streamed in time (ZuptSetup.composed_filter): the models hold no F_f, Q_c,f over the grid
    assert short.filter_models["D"].F is None and short.filter_models["D"].D.shape == (58, 10)
    monkeypatch.setattr(study, "can_split", lambda: False)
    one = study.run(short_decl(), path=STUDY)
    assert one.provenance["filters_swept_in_a_forked_process"] == "none"
    for name, tab in one.tables.items():
        if name == "timing":
            continue
        pd.testing.assert_frame_equal(short.tables[name], tab, check_exact=True, obj=name)
    for c, fm in one.filter_models.items():
        assert short.filter_models[c].names == fm.names and np.array_equal(short.filter_models[c].P0, fm.P0)


def _rms(P, S, k):
    m = nav_metrics(P[None, :10, :10], S.nodes.lat[k:k + 1], S.nodes.h[k:k + 1], S.nodes.q_nb[k:k + 1])
    return m["sigma_horizontal"][0], m["sigma_down"][0]


@pytest.mark.parametrize("case,param,scale", [("B1", "Q", 100.0), ("D", "P0", 0.01), ("A", "R", 0.01),
                                              ("B1", "P0", 10.0)])
def test_sweep_point_equals_independent_stepwise_run(short, case, param, scale):
    """A swept point = an independent stepwise run (rel ≤ 1e-8).

    propagate_with_filter with P_f(0), Q_f or R_f scaled by hand.
    """
    S = short.setup
    fm = short.filter_models[case]
    # the reference: F_f, Q_c,f over the whole grid (ZuptSetup.filter_build), discretised at once and
    # propagated step by step; the sweep made and composed them chunk by chunk (ZuptSetup.composed_filter)
    whole = S.filter_build(case)
    sp, sq, sr = (scale if param == p else 1.0 for p in ("P0", "Q", "R"))
    with threadpool_limits(limits=1, user_api="blas"):
        Phi_f, Qd_f = discretize_chunked(whole.F, whole.Qc, np.diff(S.t), fm.spec.discretization,
                                         fm.spec.taylor_order)
        ref = propagate_with_filter(S.Phi, S.Qd, S.P0, Phi_f, sq * Qd_f, sp * fm.P0, S.H, zupt_matrices(fm.names),
                                    fm.D, S.R, S.update_steps, Rf=sr * S.filter_R(case), form=fm.spec.update)
    k = S.t.size - 1
    h_ref, v_ref = _rms(ref.P_truth[k], S, k)
    sw = short.tables["sweep"]
    row = sw[(sw["filter"] == case) & (sw["parameter"] == param) & np.isclose(sw["scale [-]"], scale)]
    assert len(row) == 1
    assert row["horizontal RMS [m]"].iloc[0] == pytest.approx(h_ref, rel=1e-8)
    assert row["altitude RMS [m]"].iloc[0] == pytest.approx(v_ref, rel=1e-8)
    if case == "B1" and param == "Q":           # the scaling matters: far from the nominal
        nom = sw[(sw["filter"] == case) & (sw["scale [-]"] == 1.0)]["horizontal RMS [m]"].iloc[0]
        assert abs(h_ref / nom - 1) > 0.05


@pytest.fixture(scope="module")
def flagship():
    """The flagship study's own setup (Van Loan truth), shortened like ``short``."""
    from covtool.studies.zupt_setup import setup
    d = tomllib.loads(FLAGSHIP.read_text())
    d["study"]["duration"] = "11 min"
    d["output"]["report_times"] = ["11 min"]
    with threadpool_limits(limits=1, user_api="blas"):
        return setup(d, path=FLAGSHIP)


@pytest.mark.parametrize("case", ["A", "B1", "D"])
def test_nominal_point_equals_the_flagship_run(short, flagship, case):
    """The ×1 point equals the flagship's run (rel ≤ 1e-8).

    The flagship (studies/zupt_filter_order.toml) discretises the truth by
    Van Loan and each filter as declared (Taylor eq (6b)-(6d)) and runs
    propagate_with_filter; the sweep's truth is the Taylor series.
    """
    F = flagship
    assert F.hdr["discretization"] != short.setup.hdr["discretization"]
    with threadpool_limits(limits=1, user_api="blas"):
        fm, Phi_f, Qd_f = F.filter_model(case)
        ref = propagate_with_filter(F.Phi, F.Qd, F.P0, Phi_f, Qd_f, fm.P0, F.H, zupt_matrices(fm.names), fm.D,
                                    F.R, F.update_steps, Rf=F.filter_R(case), form=fm.spec.update)
    k = F.t.size - 1
    h_ref, v_ref = _rms(ref.P_truth[k], F, k)
    summ = short.summary.set_index("filter")
    assert summ.loc[case, "horizontal RMS [ft]"] * FT == pytest.approx(h_ref, rel=1e-8)
    assert summ.loc[case, "altitude RMS [ft]"] * FT == pytest.approx(v_ref, rel=1e-8)
    sw = short.tables["sweep"]
    nominal = sw[(sw["filter"] == case) & (sw["scale [-]"] == 1.0)]
    assert len(nominal) == 3 and np.ptp(nominal["horizontal RMS [m]"]) == 0.0


def test_filter_a_reuses_the_truth_discretisation():
    """Filter A takes the truth's Φ, Q_d; that shortcut is right only if
    discretising A's own F, Q_c by its declared method gives them again."""
    from covtool.lincov.discretize import discretize
    from covtool.studies.zupt_setup import setup

    with threadpool_limits(limits=1, user_api="blas"):
        flagship = setup(short_decl(), path=STUDY, extra_sections=("sweep", "cost"))
    fm, Phi_f, Qd_f, reused = flagship.filter_system("A")
    assert reused
    Phi_own, Qd_own = discretize(fm.F[:50], fm.Qc[:50], np.diff(flagship.t)[:50], fm.spec.discretization,
                                 fm.spec.taylor_order)
    np.testing.assert_allclose(Phi_own, flagship.Phi[:50], rtol=0, atol=1e-12)
    np.testing.assert_allclose(Qd_own, flagship.Qd[:50], rtol=1e-9, atol=1e-12 * np.abs(flagship.Qd[:50]).max())
    fm_b, _, _, reused_b = flagship.filter_system("B1")
    assert not reused_b and fm_b.F.shape[1] == 22


def test_optimal_filter_is_at_the_bottom_of_its_curves(short):
    """Filter A is optimal: every mistuning raises its error.

    D = I and its P0, Q, R are the truth's.
    """
    sens = short.tables["sensitivity"]
    a = sens[sens["filter"] == "A"]
    assert np.all(a["sensitivity [-]"] > 0)
    sw = short.tables["sweep"]
    for p in ("P0", "Q", "R"):
        g = sw[(sw["filter"] == "A") & (sw["parameter"] == p)]
        assert g["horizontal RMS [ft]"].min() == pytest.approx(
            g.loc[g["scale [-]"] == 1.0, "horizontal RMS [ft]"].iloc[0], rel=1e-9)


def test_summary_has_the_three_criteria(short):
    s = short.summary
    assert list(s["filter"]) == ["A", "B1", "D"]
    for col in ("CEP [ft]", "alt PE [ft]", "azimuth 1sigma [arcmin]", "sensitivity horizontal P0 [-]",
                "sensitivity altitude R [-]", "FLOPs/cycle [FLOP]", "measured [us/cycle]",
                "paper 8086/8087 [s/cycle]"):
        assert col in s.columns
    assert s.set_index("filter").loc["A", "paper 8086/8087 [s/cycle]"] == 22.62
    assert np.isnan(s.set_index("filter").loc["B1", "paper 8086/8087 [s/cycle]"])
    r = short.tables["sensitivity_ratio"]
    assert set(r["filter"]) == {"B1", "D"} and set(r["reference"]) == {"A"}


def test_workbook_round_trip_and_native_charts(short, tmp_path):
    out = tmp_path / "out"
    files = write_outputs(short, out)
    xlsx = out / f"{short.name}.xlsx"
    assert xlsx in files
    assert (out / "fig8_1_horizontal.png").stat().st_size > 0 and (out / "fig8_2_altitude.png").stat().st_size > 0
    for name, df in short.tables.items():
        back = pd.read_excel(xlsx, sheet_name=sheet_title(name))
        assert list(back.columns) == [str(c) for c in df.columns], name
        for col in df.columns:
            if pd.api.types.is_numeric_dtype(df[col]):
                assert "[" in col, f"{name}: numeric column {col!r} has no unit"
                exp = df[col].to_numpy(float)
                exp = np.where(np.isfinite(exp), exp, np.nan)
                np.testing.assert_allclose(back[col].to_numpy(float), exp, rtol=1e-12, equal_nan=True,
                                           err_msg=f"{name}: {col}")
            else:
                assert list(back[col].astype(str)) == list(df[col].astype(str)), f"{name}: {col}"
    from openpyxl import load_workbook
    wb = load_workbook(xlsx)
    assert len(wb["fig8_1_horizontal"]._charts) == 3 and len(wb["fig8_2_altitude"]._charts) == 3
    assert wb["sweep"].freeze_panes == "A2"
    with zipfile.ZipFile(xlsx) as z:
        charts = [n for n in z.namelist() if n.startswith("xl/charts/chart")]
        assert len(charts) == 6
        xml = z.read(charts[0]).decode()
    # log-log as the PNG (before: linear y), data from the sheet
    assert xml.count('logBase val="10"') == 2 and "fig8_1_horizontal" in xml
    ch = wb["fig8_1_horizontal"]._charts[0]
    n = len(short.scales)
    # one series per filter and kind; the swept points span exactly the swept scales (no text cell on a log axis)
    assert len(ch.series) == 2 * len(short.summary)
    assert ch.series[0].yVal.numRef.f.endswith(f"$2:${ch.series[0].yVal.numRef.f.split(':$')[1].split('$')[0]}${n + 1}")
    prov = pd.read_excel(xlsx, sheet_name="provenance").set_index("key")["value"]
    assert prov["kind"] == "zupt_sensitivity" and "sensitivity_definition" in prov.index


# ---------------------------------------------------------------- study-file errors

def _with(section, key, value):
    d = short_decl()
    if key is None:
        d[section] = value
    else:
        d.setdefault(section, {})[key] = value
    return d


@pytest.mark.parametrize("decl,field,match", [
    (_with("sweep", "step", 1), r"\[sweep\]", "unknown key 'step'"),
    (_with("sweep", "parameters", "P0"), r"\[sweep\] parameters", "non-empty list"),
    (_with("sweep", "parameters", []), r"\[sweep\] parameters", "non-empty list"),
    (_with("sweep", "parameters", ["P0", "H"]), r"\[sweep\] parameters", "unknown parameter 'H'"),
    (_with("sweep", "parameters", ["Q", "Q"]), r"\[sweep\] parameters", "listed twice"),
    (_with("sweep", "scales", [0.01, 1, 100]), r"\[sweep\] scales", "expected a table"),
    (_with("sweep", "scales", {"from": 0.01, "to": 100}), r"\[sweep\] scales", "missing key 'per_decade'"),
    (_with("sweep", "scales", {"from": 0.01, "to": 100, "per_decade": 4, "by": 2}), r"\[sweep\] scales",
     "unknown key 'by'"),
    (_with("sweep", "scales", {"from": -1, "to": 100, "per_decade": 4}), r"\[sweep\] scales from",
     "-1 is not a number >= 1e-06"),
    (_with("sweep", "scales", {"from": 0.01, "to": "100", "per_decade": 4}), r"\[sweep\] scales to",
     "'100' is not a number"),
    (_with("sweep", "scales", {"from": 0.01, "to": 100, "per_decade": 2.5}), r"\[sweep\] scales per_decade",
     "2.5 is not an integer in 1..100"),
    (_with("sweep", "scales", {"from": 0.03, "to": 100, "per_decade": 4}), r"\[sweep\] scales",
     "not on a grid"),
    (_with("sweep", "scales", {"from": 2, "to": 100, "per_decade": 4}), r"\[sweep\] scales", "bracket the nominal"),
    (_with("sweep", "fit_degree", 1.5), r"\[sweep\] fit_degree", "1.5 is not an integer in 0..10"),
    (_with("sweep", "fit_degree", 4), r"\[sweep\] fit_degree", "needs at least 6 scales"),
    (_with("sweep", "fit_degree", -1), r"\[sweep\] fit_degree", "-1 is not an integer in 0..10"),
    (_with("sweep", "discretization", "exact"), r"\[sweep\] discretization", "'declared', 'van_loan'"),
    (_with("cost", "mode", 1), r"\[cost\]", "unknown key 'mode'"),
    (_with("cost", "measure", "yes"), r"\[cost\] measure", "not true or false"),
    (_with("cost", "repeats", 0), r"\[cost\] repeats", "0 is not an integer in 1..1000"),
    (_with("cost", "taylor_order", 1), r"\[cost\] taylor_order", "'auto' or an integer"),
    (_with("cost", "taylor_order", "full"), r"\[cost\] taylor_order", "'auto' or an integer"),
    (_with("cost", "paper_seconds", 22.62), r"\[cost\] paper_seconds", "expected a table"),
    (_with("cost", "paper_seconds", {"A": -1}), r"\[cost\] paper_seconds A", "-1 is not a number > 0"),
    (_with("filters", "pure_ins", True), r"\[filters\] pure_ins", "not used by a zupt_sensitivity"),
    (_with("sweeps", None, {}), "", "unknown key 'sweeps'"),
])
def test_study_file_errors(decl, field, match):
    """Every raise names the file, the field and the problem."""
    with pytest.raises(StudyFileError, match=rf"zupt_sensitivity\.toml: .*{field}.*{match}"):
        study.run(decl, path=STUDY)


def test_unknown_paper_filter_is_named():
    d = short_decl()
    d["cost"]["paper_seconds"] = {"A": 22.62, "E": 1.0}
    d["study"]["duration"] = "6 min"
    d["output"]["report_times"] = ["6 min"]
    with pytest.raises(StudyFileError, match=r"zupt_sensitivity\.toml: \[cost\] paper_seconds E: unknown filter 'E'"):
        study.run(d, path=STUDY)


def test_study_file_as_shipped_is_fig8():
    """The shipped study is Fig 8: six filters, P0/Q/R, ×1/100…×100.

    At least 9 points, ×1 included.
    """
    d = tomllib.loads(STUDY.read_text())
    assert d["study"]["kind"] == "zupt_sensitivity"
    assert d["filters"]["cases"] == ["A", "B1", "B2", "B3", "C", "D"]
    sw = study.sweep_options(d["sweep"], str(STUDY))
    assert sw["parameters"] == ("P0", "Q", "R")
    assert sw["scales"].size >= 9 and sw["scales"][0] == pytest.approx(0.01) and sw["scales"][-1] == pytest.approx(100)
    assert 1.0 in sw["scales"]
