"""Monte Carlo validation: real feedback filters on the nonlinear INS against the linear analysis.

Oracles: the linear covariance analysis itself (the same filter model gives
the same P_f and K bit for bit; a noise-free single run follows Φ x with the
eq (16) feedback), χ² statistics (closed-form bounds checked by sampling),
and the block sensitivities (compensating with ĉ = x returns the ideal
increments).  A small 31-state truth on a 5-min route keeps the suite fast;
the full 58-state study is `studies/monte_carlo_validation.toml`.
"""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import numpy as np
import pytest

import covtool
from covtool.analysis import consistency as mc
from covtool.validation import feedback, monte_carlo
from covtool.lincov.reference import propagate_with_filter
from covtool.errors import StudyFileError
from covtool.lincov.reduced import zupt_matrices
from covtool.nav.imu.simulator import ImuSimulator, ideal_increments
from covtool.validation.sensor_errors import SensorErrors, sample_states
from covtool.io.writers import write_outputs
from covtool.analysis.metrics import ned_position_covariance
from covtool.parallel import ProcessBackend, SerialBackend
from covtool.nav.attitude import attitude_error_matrix
from covtool.studies import monte_carlo as smc
from covtool.studies.inputs import load_trajectory
from covtool.studies.zupt_setup import setup

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "studies" / "monte_carlo_validation.toml"

MODEL = """
[model]
name = "mc_small"
description = "31-state test truth: every kind of fed-back state (constant, Markov, AD-reset, gravity)"

[[block]]
kind = "navigation"
position_sigma = ["0 rad", "0 rad", "0 m"]
velocity_sigma = "0.001 ft/s"
quaternion_sigma = ["0", "0.73e-4 rad", "0.73e-4 rad", "1.45e-3 rad"]
angle_random_walk = "0.002 deg/sqrt(h)"
velocity_random_walk = "5 ug/sqrt(Hz)"

[[block]]
kind = "accel_bias"
sigma = ["20 ug", "20 ug", "30 ug"]

[[block]]
kind = "gyro_bias"
sigma = ["0.018 deg/h", "0.018 deg/h", "0.025 deg/h"]

[[block]]
kind = "accel_scale_factor"
sigma = "35 ppm"

[[block]]
kind = "gyro_scale_factor"
sigma = "35 ppm"

[[block]]
kind = "gyro_markov_drift"
sigma = "0.02 deg/h"
process = "markov"
tau = "120 s"

[[block]]
kind = "ad_reset_velocity"
sigma = "0.7 mm/s"
process = "markov"
tau = "20 s"

[[block]]
kind = "gravity_disturbance"
sigma = ["5 arcsec", "5 arcsec", "25 mGal"]
process = "markov_distance"
distance = "2 km"
"""

FILTERS = """
[[filter]]
name = "OPT"
truth = "mc_small"
description = "the truth itself: optimal, feeds back every kind of state"
keep = "all"
equivalent_noise = false

[[filter]]
name = "B"
truth = "mc_small"
keep = ["nav", "acc_bias", "gyro_bias", "acc_sf", "gyro_sf"]
equivalent_noise = "eq11-13"

[[filter]]
name = "N"
truth = "mc_small"
keep = ["nav"]
equivalent_noise = "eq11-13"
"""


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("mc")
    (d / "mc_small.toml").write_text(MODEL)
    (d / "filters.toml").write_text(FILTERS)
    return d


def small_decl(files, **mc) -> dict:
    """5 min on a shortened route: stops [110, 150] and [260, 300] s, ZUPTs over the last 20 s of each."""
    return {
        "study": {"kind": "monte_carlo", "name": "mc_test", "duration": "5 min", "dt": "1 s"},
        "trajectory": {"builtin": "land_vehicle", "cycles": 2, "period": "150 s", "stop_duration": "40 s",
                       "distance": "1500 m", "accel_duration": "10 s", "grade_duration": "20 s"},
        "truth": {"model": str(files / "mc_small.toml")},
        "filters": {"file": str(files / "filters.toml"), "cases": ["OPT", "B", "N"], "pure_ins": True},
        "zupt": {"interval": "150 s", "duration": "20 s", "rate": "1 Hz", "sigma": "0.01 ft/s"},
        "monte_carlo": {"runs": 60, "runs_per_chunk": 30, "seed": 7, "imu_rate": "100 Hz", "samples_per_step": 4,
                        **mc},
        "output": {"history_every": "10 s", "report_times": ["5 min"]},
    }


@pytest.fixture(scope="module")
def small(files):
    decl = small_decl(files)
    return decl, setup(decl, extra_sections=("monte_carlo",))


@pytest.fixture(scope="module")
def study(files):
    """The small study end to end, in-process (two chunks of 30 runs)."""
    return covtool.run_study(small_decl(files), backend=SerialBackend())


def _design(S, name):
    fm, Phi_f, Qd_f = S.filter_model(name)
    ff = feedback.FeedbackFilter.design(name, fm.names, Phi_f, Qd_f, fm.P0, S.filter_R(name), S.update_steps,
                                  form=S.specs[name].update)
    return fm, Phi_f, Qd_f, ff


# --------------------------------------------------------------------------
# the filter: the same model gives the same P_f and K
# --------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["OPT", "B", "N"])
def test_filter_covariance_equals_linear_analysis(small, name):
    """P_f and every K of the feedback filter equal propagate_with_filter's, bit for bit."""
    _, S = small
    fm, Phi_f, Qd_f, ff = _design(S, name)
    ref = propagate_with_filter(S.Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, S.H, zupt_matrices(fm.names), fm.D, S.R,
                                S.update_steps, Rf=S.filter_R(name))
    assert np.array_equal(ff.P, ref.P_filter)
    assert sorted(ff.gains) == sorted(ref.gains) == sorted(int(k) for k in S.update_steps)
    assert all(np.array_equal(ff.gains[k], ref.gains[k]) for k in ff.gains)


# --------------------------------------------------------------------------
# sensor feedback: compensating with ĉ = x removes the injected errors
# --------------------------------------------------------------------------


def test_compensation_with_true_states_returns_ideal_increments(files, small):
    """Constant, Markov, AD-reset and gravity states: Δ − h S ĉ with ĉ = x is the ideal increment.

    Noise off, so every state follows its deterministic mean; 10 s at 100 Hz
    in 1-s records while the vehicle turns and climbs.  The residual is the
    second-order S(δf)·x (scale factors of ~200 ppm times the errors) and the
    0.1-s process grid of the simulator.
    """
    decl, S = small
    truth = S.truth
    traj = load_trajectory(decl, "<test>", None, 1.0)
    M, t0, T = 3, 40.0, 10.0
    x0 = sample_states(truth, M, 5, q0=traj.sample([t0]).q_nb[0]) * 5.0       # 5 σ: well above round-off
    sim = ImuSimulator(traj, 100.0, t0=t0, duration=T, errors=SensorErrors(truth, x0, noise=False, process_dt=0.1))
    ideal = ideal_increments(traj, 100.0, t0=t0, duration=T)
    fb = feedback.SensorFeedback(truth, truth.names, M)
    fb.add(x0[:, 10:])
    rec = sim.record()
    worst = {}
    for a in range(0, rec.n_samples, 100):
        part = rec.slice(a, a + 100)
        ctx = feedback.RecordContext.along(traj, part.t0, part.dt, 100)
        dth, dv = fb.compensate(part.dtheta, part.dv, part.dt, ctx)
        for nm, got, raw, ref in (("gyro", dth, part.dtheta, ideal.dtheta), ("accel", dv, part.dv, ideal.dv)):
            err = np.abs(got - ref[a:a + 100]).max() / np.abs(raw - ref[a:a + 100]).max()
            worst[nm] = max(worst.get(nm, 0.0), err)
    assert worst["gyro"] < 1e-3 and worst["accel"] < 1e-3, worst


# --------------------------------------------------------------------------
# a deterministic run against the linear prediction
# --------------------------------------------------------------------------


@pytest.mark.parametrize("name, sources", [
    ("B", {"acc_bias_x": 300e-6 * 9.80665, "gyro_bias_z": np.radians(0.1) / 3600, "azimuth": 1e-3}),
    ("OPT", {"gyro_markov_y": np.radians(0.2) / 3600, "acc_ad_x": 5e-3, "grav_dg": 5e-4, "acc_sf_z": 200e-6}),
])
def test_single_run_follows_the_linear_prediction(files, small, name, sources, capsys):
    """Noise off, a few error sources: the nonlinear run with real feedback equals Φ x with eq (16) feedback.

    The linear prediction: ``x_{k+1} = Φ_k x_k`` and, at a ZUPT,
    ``x ← (I − D K H) x`` (noise-free measurement).  The nonlinear run uses
    the same K on its own velocity and feeds back into the INS and the IMU
    compensation.  Tolerance: 1.5 % of the largest value of each quantity.
    """
    decl, S = small
    truth = S.truth
    traj = load_trajectory(decl, "<test>", None, 1.0)
    fm, _, _, ff = _design(S, name)
    x = np.zeros(truth.n)
    for nm, v in sources.items():
        if nm == "azimuth":      # δq = −½ R(q0) φ for φ = (0, 0, ψ)
            x[6:10] = np.linalg.pinv(attitude_error_matrix(traj.sample([0.0]).q_nb[0])) @ np.array([0.0, 0.0, v])
        else:
            x[truth.index[nm]] = v
    x0 = x[None, :]
    sim = ImuSimulator(traj, 100.0, duration=S.t[-1], errors=SensorErrors(truth, x0, noise=False))
    case = monte_carlo.EnsembleCase(name, ff)
    _, errs = monte_carlo.run_ensemble(sim, x0, [case], S.t, samples_per_step=4, R=S.R, measurement_noise=False,
                              model=truth, record_errors=True)
    e = errs[name][:, 0, :]
    # linear prediction
    H, D = S.H, fm.D
    lin = np.empty((S.t.size, truth.n))
    xl = x.copy()
    for k in range(S.t.size):
        if k in ff.gains:
            xl = xl - D @ (ff.gains[k] @ (H @ xl))
        lin[k] = xl
        if k < S.t.size - 1:
            xl = S.Phi[k] @ xl
    n = S.nodes
    Pn = np.stack([ned_position_covariance(np.eye(3)[None], n.lat, n.h)[:, i, i] for i in range(3)], axis=-1)
    scale = np.sqrt(Pn)                                   # (R_M+h, (R_N+h) cos L, 1)
    A = attitude_error_matrix(n.q_nb)
    lines = []
    for label, a, b in (("position", e[:, :3] * scale, lin[:, :3] * scale), ("velocity", e[:, 3:6], lin[:, 3:6]),
                        ("attitude", np.einsum("kij,kj->ki", A, e[:, 6:10]),
                         np.einsum("kij,kj->ki", A, lin[:, 6:10]))):
        rel = np.abs(a - b).max() / np.abs(b).max()
        lines.append(f"{name} {label}: max |linear| {np.abs(b).max():.4g}, max difference {100 * rel:.2f} %")
        assert rel < 0.015, lines[-1]
    with capsys.disabled():
        print(f"\n[single run vs linear, {', '.join(sources)}]\n  " + "\n  ".join(lines))


# --------------------------------------------------------------------------
# χ² bounds
# --------------------------------------------------------------------------


def test_rms_and_nees_bounds_cover_95_percent():
    """Simulated ensembles fall inside the χ² bounds 95 % of the time."""
    rng = np.random.default_rng(11)
    trials, N = 20000, 200
    x = 2.0 * rng.standard_normal((trials, N))
    lo, hi = mc.rms_bounds(2.0, N)
    rms = np.sqrt((x**2).mean(axis=1))
    assert np.mean((rms >= lo) & (rms <= hi)) == pytest.approx(0.95, abs=0.006)
    assert np.mean(rms < lo) == pytest.approx(0.025, abs=0.005)
    # 9-dof NEES of a consistent covariance: the mean over N runs of χ²_9 draws
    nees = rng.chisquare(9, (trials, N)).mean(axis=1)
    nlo, nhi = mc.nees_bounds(9, N)
    assert np.mean((nees >= nlo) & (nees <= nhi)) == pytest.approx(0.95, abs=0.006)
    # an inconsistent covariance (true 2× the claimed): expected NEES 2d, bounds around it
    nees2 = 2.0 * rng.chisquare(9, (trials, N)).mean(axis=1)
    lo2, hi2 = mc.nees_bounds(9, N, mean=18.0)
    assert np.mean((nees2 >= lo2) & (nees2 <= hi2)) == pytest.approx(0.95, abs=0.006)
    # Satterthwaite dof: circular 2, degenerate 1, none 1
    assert mc.horizontal_dof(np.diag([4.0, 4.0])) == pytest.approx(2.0)
    assert mc.horizontal_dof(np.diag([4.0, 0.0])) == pytest.approx(1.0)
    assert mc.horizontal_dof(np.zeros((2, 2))) == 1.0
    fr = mc.inside_fraction([0.0, 1.0, 3.0, 0.5], [0.0, 0.9, 1.0, 0.6], [0.0, 1.1, 2.0, 0.7])
    assert fr == {"inside": 0.5, "above": 0.25, "below": 0.25, "points": 4}


def test_chi2_quantile_is_scipy_stats_chi2_ppf_bit_for_bit():
    """The bounds use scipy.special (no scipy.stats import): the same numbers as scipy.stats."""
    from scipy import stats

    from covtool.analysis.consistency import chi2_quantile

    rng = np.random.default_rng(5)
    q = np.r_[0.025, 0.975, 0.5, rng.uniform(1e-6, 1 - 1e-6, 500)]
    nu = np.r_[200.0, 350.5, 1.0, rng.uniform(0.5, 2e5, 500)]
    assert np.array_equal(chi2_quantile(q, nu), stats.chi2.ppf(q, nu))
    assert chi2_quantile(0.5, 2.0) == pytest.approx(2.0 * np.log(2.0), rel=1e-14)     # χ²₂ is exponential(1/2)
    lo, hi = mc.rms_bounds(3.0, 200, [1.0, 1.7])
    nu2 = 200 * np.array([1.0, 1.7])
    np.testing.assert_array_equal(lo, 3.0 * np.sqrt(stats.chi2.ppf(0.025, nu2) / nu2))
    np.testing.assert_array_equal(hi, 3.0 * np.sqrt(stats.chi2.ppf(0.975, nu2) / nu2))


def test_horizontal_bounds_cover_95_percent():
    """Radial RMS of an elongated 2-D error: Satterthwaite bounds cover ≈ 95 %; 2N dof would not."""
    rng = np.random.default_rng(3)
    N, trials = 50, 20000
    P2 = np.array([[9.0, 2.0], [2.0, 1.0]])
    L = np.linalg.cholesky(P2)
    x = rng.standard_normal((trials, N, 2)) @ L.T
    rms = np.sqrt((x**2).sum(axis=-1).mean(axis=-1))
    sig = np.sqrt(np.trace(P2))
    lo, hi = mc.rms_bounds(sig, N, mc.horizontal_dof(P2))
    cover = np.mean((rms >= lo) & (rms <= hi))
    lo2, hi2 = mc.rms_bounds(sig, N, 2.0)
    cover2 = np.mean((rms >= lo2) & (rms <= hi2))
    assert cover == pytest.approx(0.95, abs=0.01)
    assert cover2 < 0.92


# --------------------------------------------------------------------------
# the ensemble against the linear σ
# --------------------------------------------------------------------------


def test_small_ensemble_matches_the_linear_sigma(study, capsys):
    """60 runs, 5 min: RMS inside χ² bounds, truth NEES ≈ 9, the optimal filter's NEES ≈ d.

    The RMS curves are strongly correlated in time, so one unlucky draw can
    leave a 95 % band for tens of seconds; the test asks for 95 % of the
    points inside the 99 % bounds, which a model error of 25 % fails.
    """
    r = study
    comp = r.tables["comparison"]
    N = int(r.summary["runs"].iloc[0])
    lines = []
    for c, bands in r.bands.items():
        for q, (x, sig, _, _) in bands.items():
            dof = r.linear[c]["dof_h"] if q == "horizontal" else 1.0
            lo, hi = mc.rms_bounds(sig, N, dof, confidence=0.99)
            fr = mc.inside_fraction(x[1:], lo[1:], hi[1:])
            row = comp[(comp["case"] == c) & (comp["quantity"] == q)].iloc[0]
            lines.append(f"{c:8s} {q:10s} inside 95 %: {row['inside [%]']:5.1f} %, 99 %: {100 * fr['inside']:5.1f} %, "
                         f"mean RMS/σ {row['mean RMS/sigma']:.3f}")
            assert fr["inside"] >= 0.95, lines[-1]
            b = mc.rms_bounds(1.0, N, 1.0, confidence=0.99)
            assert b[0] < row["mean RMS/sigma"] < b[1], lines[-1]
    nees = r.tables["nees"]
    lines += [f"NEES {row['case']} {row['NEES']}: d = {row['dof']}, time-mean/d {row['time-mean NEES/dof']:.3f} "
              f"(linear prediction {row.get('linear-predicted time-mean NEES/dof', np.nan):.3f}), "
              f"inside {row['inside [%]']:.1f} %" for _, row in nees.iterrows()]
    with capsys.disabled():
        print(f"\n[small Monte Carlo, N = {N}]\n  " + "\n  ".join(lines))
    truth = nees[nees["NEES"] == "truth"]
    assert truth["time-mean NEES/dof"].between(0.9, 1.1).all() and (truth["inside [%]"] >= 90.0).all()
    opt = nees[(nees["case"] == "OPT") & (nees["NEES"] == "filter")].iloc[0]
    assert opt["dof"] == 9 + 12 and 0.9 < opt["time-mean NEES/dof"] < 1.1 and opt["inside [%]"] >= 90.0
    # the eq (11)-(13) filters are pessimistic: NEES of their own claim below d, as the linear analysis predicts
    for c in ("B", "N"):
        for key in ("filter", "filter_nav"):
            row = nees[(nees["case"] == c) & (nees["NEES"] == key)].iloc[0]
            assert row["time-mean NEES/dof"] < 0.8 and row["below [%]"] == 100.0
            assert row["time-mean NEES/dof"] == pytest.approx(row["linear-predicted time-mean NEES/dof"], rel=0.05)
            assert row["inside bounds of prediction [%]"] >= 90.0


def test_study_outputs(study, tmp_path):
    """Workbook sheets, one figure per case plus ratio and NEES, provenance, filter check."""
    r = study
    assert list(r.summary["case"]) == ["pure_ins", "OPT", "B", "N"]
    assert set(r.tables) == {"summary", "comparison", "nees", "history", "settings"}
    assert r.filter_check == {"OPT": 0.0, "B": 0.0, "N": 0.0}
    assert sum(s.n_runs for s in [r.sums["B"]]) == 60
    files = {p.name for p in write_outputs(r, tmp_path / "out")}
    assert {"mc_pure_ins.png", "mc_OPT.png", "mc_B.png", "mc_N.png", "mc_ratio.png", "mc_nees.png",
            "mc_test.xlsx", "summary.csv", "history.csv"} <= files
    from openpyxl import load_workbook
    wb = load_workbook(tmp_path / "out" / "mc_test.xlsx")
    assert {"summary", "comparison", "nees", "history", "settings", "provenance"} <= set(wb.sheetnames)


def test_chunks_are_independent_of_backend_and_resume(files, tmp_path):
    """Two local processes, and a resumed store, give the in-process sums bit for bit."""
    decl = small_decl(files, runs=6, runs_per_chunk=3)
    decl["filters"].update(cases=["B"], pure_ins=False)
    r1 = covtool.run_study(decl, backend=SerialBackend())
    with ProcessBackend(2) as be:
        # with a store, the workers map the reference from one file beside it (SharedReference), removed after
        r2 = covtool.run_study(decl, backend=be, store=tmp_path / "cases")
    assert not (tmp_path / ".monte_carlo_reference.bin").exists()
    s1, s2 = r1.sums["B"], r2.sums["B"]
    assert s1.n_runs == s2.n_runs == 6
    assert np.array_equal(s1.s2, s2.s2) and np.array_equal(s1.s1, s2.s1)
    assert all(np.array_equal(s1.nees[k], s2.nees[k]) for k in s1.nees)
    r3 = covtool.run_study(decl, backend=SerialBackend(), store=tmp_path / "cases", resume=True)
    assert r3.stats["reused"] == 2 and r3.stats["computed"] == 0
    assert np.array_equal(r3.sums["B"].s2, s1.s2)


# --------------------------------------------------------------------------
# study files
# --------------------------------------------------------------------------


def test_validation_study_declares_the_acceptance_case():
    decl = tomllib.loads(STUDY.read_text())
    o = smc.mc_options(decl, str(STUDY))
    assert decl["study"]["kind"] == "monte_carlo" and o["runs"] >= 200
    assert {"B1", "D"} <= set(decl["filters"]["cases"]) and decl["filters"]["pure_ins"] is True
    assert decl["zupt"]["interval"] == "5 min" and decl["study"]["duration"] == "30 min"
    assert o["navigation_rate"] == 25.0 and o["samples_per_grid_step"] == 100


@pytest.mark.parametrize("change, match", [
    ({"monte_carlo": None}, r"missing \[monte_carlo\] table"),
    ({"monte_carlo": {}}, "missing required key 'runs'"),
    ({"monte_carlo": {"runs": 10, "bogus": 1}}, "unknown key 'bogus'"),
    ({"monte_carlo": {"runs": 1}}, r"runs: 1 is not an integer in 2\.\.10_000"),
    ({"monte_carlo": {"runs": 10.5}}, "runs: 10.5 is not an integer"),
    ({"monte_carlo": {"runs": 10, "runs_per_chunk": 0}}, "runs_per_chunk: 0 is not an integer"),
    ({"monte_carlo": {"runs": 10, "samples_per_step": 7}}, r"samples_per_step: 7 is not an integer in 1\.\.6"),
    ({"monte_carlo": {"runs": 10, "imu_rate": "100 m/s"}}, "imu_rate"),
    ({"monte_carlo": {"runs": 10, "imu_rate": "90 Hz"}}, "puts 90 samples into one grid step"),
    ({"monte_carlo": {"runs": 10, "imu_rate": "100.5 Hz"}}, "must be a whole multiple of samples_per_step"),
    ({"monte_carlo": {"runs": 10, "confidence": 1.5}}, "confidence: 1.5 is not a number > 0 and < 1"),
    ({"monte_carlo": {"runs": 10, "sensor_noise": "yes"}}, "sensor_noise: 'yes' is not true or false"),
    ({"monte_carlo": {"runs": 10, "nees_every": "-1 s"}}, "nees_every: '-1 s' must be positive"),
    ({"monte_carlo": {"runs": 10, "process_dt": "3 m"}}, "process_dt"),
    ({"monte_carlo": {"runs": 10, "null_replicas": 5}}, r"null_replicas: 5 replicas cannot give a null distribution"),
    ({"monte_carlo": {"runs": 10, "null_replicas": -1}}, "null_replicas: -1 is not an integer"),
])
def test_monte_carlo_table_errors(files, change, match):
    decl = small_decl(files)
    for k, v in change.items():
        if v is None:
            decl.pop(k)
        else:
            decl[k] = v
    with pytest.raises(StudyFileError, match=match):
        covtool.run_study(decl, backend=SerialBackend())


def test_study_section_errors(files):
    decl = small_decl(files)
    bad = copy.deepcopy(decl)
    bad["filters"]["cases"] = ["B", "Z"]
    with pytest.raises(StudyFileError, match=r"\[filters\] cases: unknown filter 'Z'"):
        covtool.run_study(bad, backend=SerialBackend())
    bad = copy.deepcopy(decl)
    bad["filters"].update(cases=[], pure_ins=False)
    with pytest.raises(StudyFileError, match="nothing to run"):
        covtool.run_study(bad, backend=SerialBackend())
    bad = copy.deepcopy(decl)
    bad["filters"]["pure_ins"] = "no"
    with pytest.raises(StudyFileError, match="pure_ins: 'no' is not true or false"):
        covtool.run_study(bad, backend=SerialBackend())
    bad = copy.deepcopy(decl)
    bad["study"]["duration"] = "299.5 s"
    bad["output"]["report_times"] = ["299.5 s"]
    with pytest.raises(StudyFileError, match="not a whole number of grid steps"):
        covtool.run_study(bad, backend=SerialBackend())


# --------------------------------------------------------------------------
# compiled kernels against the numpy reference (issue 13)
# --------------------------------------------------------------------------


@pytest.mark.parametrize("kind", sorted(k for k, b in __import__("covtool.lincov.model.blocks", fromlist=["x"])
                                        .BLOCK_KINDS.items() if b.sensitivity is not None))
def test_column_table_reproduces_the_block_sensitivity(kind):
    """Each probed entry (row, 1 | f_a | ω_a | |f_a| | f_a f_b) equals the block's function at new points."""
    from covtool.lincov.model.blocks import BLOCK_KINDS

    tab = feedback._column_table(kind)
    assert tab is not None
    rng = np.random.default_rng(11)
    f, w = rng.normal(0, 5, (50, 3)), rng.normal(0, 0.5, (50, 3))
    S = BLOCK_KINDS[kind].sensitivity(f, w)
    rebuilt = np.zeros_like(S)
    for col, (r, ty, a, b) in enumerate(tab):
        rebuilt[:, r, col] = [np.ones(50), f[:, a], w[:, a], np.abs(f[:, a]), f[:, a] * f[:, b]][ty]
    np.testing.assert_array_equal(rebuilt, S)


def test_column_table_refuses_other_shapes(monkeypatch):
    """A sensitivity with two entries in a column is not tabulated: the numpy reference compensates it."""
    from covtool.lincov.model import blocks

    bk = blocks.BLOCK_KINDS["gyro_bias"]
    monkeypatch.setitem(blocks.BLOCK_KINDS, "gyro_bias", type(bk)(**{**bk.__dict__, "sensitivity": lambda f, w: (
        np.stack([f, w, f], axis=-1))}))
    feedback._column_table.cache_clear()
    try:
        assert feedback._column_table("gyro_bias") is None
    finally:
        feedback._column_table.cache_clear()


@pytest.mark.parametrize("model_name, keep", [("sdins58", "all"), ("sdins58", "B1"), ("small", "all")])
def test_compiled_compensation_equals_reference(files, small, model_name, keep):
    """The compiled compensation equals compensate_reference: increments and the advanced ĉ.

    sdins58 has every block kind (biases, scale factors, asymmetric scale factor,
    misalignments, g-sensitivity, anisoelasticity, Markov, gravity in distance, AD reset);
    B1 keeps a subset; random ĉ of 100 σ, measured increments of a turning, climbing record.
    """
    from covtool.io.library import load_model_by_name

    decl, S = small
    truth = load_model_by_name("sdins58") if model_name == "sdins58" else S.truth
    traj = load_trajectory(decl, "<test>", None, 1.0)
    names = truth.names
    if keep == "B1":
        names = names[:10] + [n for n in names[10:] if n.startswith(("acc_bias", "gyro_bias", "acc_sf", "gyro_sf"))]
    M, k, h = 4, 250, 0.01
    x0, rec, ctx = _amplified_record(truth, traj, M, k, h, rng=np.random.default_rng(3), stream=5)
    a, b = feedback.SensorFeedback(truth, names, M), feedback.SensorFeedback(truth, names, M)
    est = x0[:, [truth.index[n] for n in a.names]]
    a.add(est)
    b.add(est)
    assert a._table() is not None
    got = a.compensate(rec.dtheta, rec.dv, h, ctx)
    ref = b.compensate_reference(rec.dtheta, rec.dv, h, ctx)
    for g, r, raw in zip(got, ref, (rec.dtheta, rec.dv)):
        corr = np.abs(raw - r).max()
        assert corr > 0 and np.abs(g - r).max() <= 1e-12 * corr + 1e-18
    np.testing.assert_allclose(a.c, b.c, rtol=1e-14, atol=0)



def _amplified_record(truth, traj, M, k, h, *, rng, stream):
    """``M`` runs' initial states ×100 (the compensation is visible), one 100 Hz record of ``k`` samples
    from t = 40 s with their sensor errors, and its context: ``(x0, record, RecordContext)``."""
    x0 = sample_states(truth, M, rng, q0=traj.sample([40.0]).q_nb[0]) * 100.0
    sim = ImuSimulator(traj, 1.0 / h, t0=40.0, duration=k * h, errors=SensorErrors(truth, x0, stream, process_dt=0.1))
    rec = sim.record()
    return x0, rec, feedback.RecordContext.along(traj, rec.t0, h, k)


def test_cases_compensated_together_equal_each_alone(files, small):
    """compensate_cases: several feedbacks on one record give each one's own increments and ĉ, bit for bit.

    Three filters (every sdins58 state, Markov, gravity and AD reset included;
    accelerometer scale factors and gyro biases; gyro misalignments) written
    into one strided buffer, as the ensemble loop does.
    """
    from covtool.io.library import load_model_by_name

    decl, _ = small
    truth = load_model_by_name("sdins58")
    traj = load_trajectory(decl, "<test>", None, 1.0)
    M, k, h = 3, 200, 0.01
    rng = np.random.default_rng(5)
    x0, rec, ctx = _amplified_record(truth, traj, M, k, h, rng=rng, stream=6)
    keep = [truth.names, truth.names[:10] + [n for n in truth.names if n.startswith(("acc_sf", "gyro_bias"))],
            truth.names[:10] + [n for n in truth.names if n.startswith("gyro_mis")]]
    together = [feedback.SensorFeedback(truth, names, M) for names in keep]
    alone = [feedback.SensorFeedback(truth, names, M) for names in keep]
    for a, b in zip(together, alone):
        est = x0[:, [truth.index[n] for n in a.names]] * rng.uniform(0.5, 1.5)
        a.add(est)
        b.add(est)
    buf = np.full((2, 4 * M, k + 7, 3), np.nan)
    out = (buf[0, M:, 3:k + 3], buf[1, M:, 3:k + 3])
    feedback.compensate_cases(together, rec.dtheta, rec.dv, h, ctx, out=out)
    for i, b in enumerate(alone):
        th, dv = b.compensate(rec.dtheta, rec.dv, h, ctx)
        assert np.array_equal(out[0][i * M:(i + 1) * M], th) and np.array_equal(out[1][i * M:(i + 1) * M], dv)
        assert np.array_equal(together[i].c, b.c)
    assert np.isnan(buf[:, :M]).all() and np.isnan(buf[:, :, :3]).all()       # nothing written outside

# --------------------------------------------------------------------------
# the conditional prediction (docs/monte_carlo.md, "Statistics")
# --------------------------------------------------------------------------


@pytest.mark.parametrize("share", [0.0, 0.5, 0.97])
def test_conditional_bounds_cover_95_percent(share):
    """Fixed constants a_i plus driven d_i ~ N(0, σ_d²): the conditional bounds cover ≈ 95 %.

    ``share`` of the variance is the constants' part.  The χ² bounds with N dof about the
    same conditional σ are conservative (cover more) whenever constants are present, and
    equal to the conditional ones without them.
    """
    rng = np.random.default_rng(17)
    N, trials = 200, 20000
    a = rng.standard_normal(N) * np.sqrt(share)             # one draw of constants, kept fixed
    sd2 = 1.0 - share
    sig_c = np.sqrt(np.mean(a**2) + sd2)
    ms = np.mean((a[None] + np.sqrt(sd2) * rng.standard_normal((trials, N)))**2, axis=1)
    rms = np.sqrt(ms)
    Lc = {"altitude": np.array([sig_c])}
    Ld = {"altitude": np.array([np.sqrt(sd2)])}
    lo, hi = mc.rms_bounds(sig_c, N, smc.conditional_dof(Lc, Ld, "altitude"), 0.95)
    cover = np.mean((rms >= lo) & (rms <= hi))
    lo2, hi2 = mc.rms_bounds(sig_c, N, 1.0, 0.95)
    cover_chi2 = np.mean((rms >= lo2) & (rms <= hi2))
    assert cover == pytest.approx(0.95, abs=0.01)
    # normal approximation: the χ² band is wider by √(2 / (4 s (1 − s) + 2 (1 − s)²))
    from scipy.stats import norm

    widen = np.sqrt(2.0 / (4 * share * (1 - share) + 2 * (1 - share) ** 2))
    assert cover_chi2 == pytest.approx(2 * norm.cdf(1.959964 * widen) - 1, abs=0.01)
    if share > 0:
        assert cover_chi2 > cover + 0.02


def test_conditional_horizontal_dof_closed_forms():
    """Horizontal: without constants the dof is Satterthwaite's (λ₁+λ₂)²/(λ₁²+λ₂²); without noise it is capped."""
    Pd = np.array([[[9.0, 2.0], [2.0, 1.0]]])
    d = smc.conditional_dof({"P_ne": Pd}, {"P_ne": Pd}, "horizontal")
    np.testing.assert_allclose(d, mc.horizontal_dof(Pd), rtol=1e-12)
    A = np.array([[[4.0, 0.0], [0.0, 1.0]]])
    d = smc.conditional_dof({"P_ne": A + Pd}, {"P_ne": Pd}, "horizontal")
    tr = np.trace(A[0] + Pd[0])
    np.testing.assert_allclose(d, 2 * tr**2 / (4 * np.trace(Pd[0] @ A[0]) + 2 * np.trace(Pd[0] @ Pd[0])), rtol=1e-12)
    assert smc.conditional_dof({"P_ne": A}, {"P_ne": 0 * A}, "horizontal")[0] == 1e6


def test_conditional_prediction_follows_the_drawn_constants(study, files, monkeypatch, capsys):
    """Pure-INS azimuth is almost all initial azimuth: given the draws, the linear σ matches the RMS.

    Against the conditional σ (sample second moments of the 60 drawn initial states) the
    ensemble RMS lies inside the 99 % exact-variance bounds; against the model's σ it carries
    the draws' sampling error.  The same comparison with the drawn constants' σ 5 % too high
    (a deliberately wrong linear model, in the linear analysis only) falls outside.
    """
    r = study
    N = int(r.summary["runs"].iloc[0])

    def inside(res):
        x, sig_c, _, _ = res.bands_conditional["pure_ins"]["azimuth"]
        dof = smc.conditional_dof(res.linear_conditional["pure_ins"], res.linear_driven["pure_ins"],
                                  "azimuth")
        lo, hi = mc.rms_bounds(sig_c, N, dof, confidence=0.99)
        return mc.inside_fraction(x[1:], lo[1:], hi[1:])["inside"], float(np.mean(x[1:] / sig_c[1:]))

    x, sig, _, _ = r.bands["pure_ins"]["azimuth"]
    fr, ratio_c = inside(r)
    ratio = float(np.mean(x[1:] / sig[1:]))
    orig = smc._sample_moment
    monkeypatch.setattr(smc, "_sample_moment", lambda *a: orig(*a) * 1.05**2)
    wrong = covtool.run_study(small_decl(files), backend=SerialBackend())
    fr_wrong, ratio_wrong = inside(wrong)
    with capsys.disabled():
        print(f"\n[conditional] pure-INS azimuth RMS/σ: model {ratio:.4f}, conditional {ratio_c:.4f} "
              f"({100 * fr:.1f} % inside 99 % exact bounds); wrong model {ratio_wrong:.4f} ({100 * fr_wrong:.1f} %)")
    assert fr >= 0.95 and abs(ratio_c - 1.0) < abs(ratio - 1.0)
    assert fr_wrong < 0.5
    comp = r.tables["comparison"]
    assert {"conditional: inside [%]", "conditional, exact variance: inside [%]",
            "conditional: pass (>= 95 % inside)"} <= set(comp.columns)
    assert "inside bounds of conditional prediction [%]" in r.tables["nees"].columns


def test_acceptance_test_is_reported_per_cell(study, files):
    """Every cell has its null percentile, p-value and verdict; the family's level is Bonferroni."""
    r = study
    comp = r.tables["comparison"]
    cells = len(comp)
    assert cells == 4 * 3
    assert set(comp["verdict"]) <= {"accept", "reject"}
    assert np.allclose(comp["cell false-alarm rate"], 0.05 / cells)
    assert ((comp["verdict"] == "reject") == (comp["p-value"] < 0.05 / cells)).all()
    # the reported T is the time mean of RMS²/σ_cond² over t >= dt, recomputed here from the bands
    for _, row in comp.iterrows():
        x, sig_c, _, _ = r.bands_conditional[row["case"]][row["quantity"]]
        assert row["T = time-mean RMS^2/sigma^2"] == pytest.approx(np.mean(x[1:] ** 2 / sig_c[1:] ** 2), rel=1e-12)
        assert 0.0 <= row["null: inside 5th percentile [%]"] <= 100.0 and 0.0 < row["inside p-value (one-sided)"] <= 1
    acc = r.tables["settings"].set_index("setting")["value"]["acceptance test"]
    assert "Bonferroni over 12 cells" in acc and "verdict:" in acc
    # null_replicas = 0: the per-point bands only, no verdict columns
    off = covtool.run_study(small_decl(files, null_replicas=0, runs=20, runs_per_chunk=20), backend=SerialBackend())
    assert "verdict" not in off.tables["comparison"].columns
    assert "none (null_replicas = 0)" in off.tables["settings"].set_index("setting")["value"]["acceptance test"]


def test_reference_sampled_ahead_in_a_forked_process_is_the_cases_one(forking, files, monkeypatch):
    """The trajectory reference a forked process samples before the gains exist is the one the cases need.

    The study samples it from the update steps and the filters' states
    while it computes the gains; :func:`reference_inputs` of the cases
    gives the same inputs (else it would sample again), and the ensemble
    sums are those of sampling it in-process after the gains, bit for bit.
    """
    import covtool.studies.monte_carlo as study_mc
    from covtool.validation.monte_carlo import reference_inputs

    decl = small_decl(files, runs=4, runs_per_chunk=2)
    seen = []

    def recording(cases):
        seen.append(reference_inputs(cases))
        return seen[-1]

    forks = []

    class Recorded(study_mc.Forked):
        def __init__(self, fn, *args, **kwargs):
            forks.append(self)
            super().__init__(fn, *args, **kwargs)

        def cancel(self):
            forks.remove(self)
            super().cancel()

    monkeypatch.setattr(study_mc, "reference_inputs", recording)
    monkeypatch.setattr(study_mc, "Forked", Recorded)
    ahead = covtool.run_study(decl, backend=SerialBackend())
    assert len(seen) == 1 and len(forks) == 1                  # sampled ahead once, and that one was used
    S = setup(decl, extra_sections=("monte_carlo",))
    steps, names = seen[0]
    # the gains are at the ZUPTs: 1 Hz over the 20 s ending at each 150-s interval (both ends), 1-s grid
    assert steps == list(range(130, 151)) + list(range(280, 301))
    assert names == [list(S.filter_model(c)[0].names) for c in ("OPT", "B", "N")]
    monkeypatch.setattr(study_mc, "can_split", lambda: False)           # sampled here, after the gains
    here = covtool.run_study(decl, backend=SerialBackend())
    for c in ahead.sums:
        a, b = ahead.sums[c], here.sums[c]
        assert np.array_equal(a.s2, b.s2) and np.array_equal(a.s1, b.s1)
        assert all(np.array_equal(a.nees[k], b.nees[k]) for k in a.nees)


def test_a_failed_linear_analysis_leaves_no_reference_process(forking, files, monkeypatch):
    """An error while the gains are computed stops the forked reference sampling at once (not at collection)."""
    import covtool.forked
    import covtool.studies.monte_carlo as study_mc

    def diverges(*a, **k):
        raise RuntimeError("pure INS diverged")

    monkeypatch.setattr(study_mc, "propagate", diverges)
    with pytest.raises(RuntimeError, match="pure INS diverged") as caught:
        covtool.run_study(small_decl(files, runs=4, runs_per_chunk=2), backend=SerialBackend())
    assert caught.value is not None                       # the traceback (and its frames) still held here
    assert covtool.forked._ACTIVE["children"] == 0 and covtool.forked.can_split()


def test_a_failed_fork_samples_the_reference_here(files, monkeypatch):
    """No fork to be had (``OSError``): the study samples the reference itself, after the gains, same sums."""
    import covtool.studies.monte_carlo as study_mc

    decl = small_decl(files, runs=4, runs_per_chunk=2)
    monkeypatch.setattr(study_mc, "can_split", lambda: False)
    here = covtool.run_study(decl, backend=SerialBackend())

    def no_fork(*a, **k):
        raise BlockingIOError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(study_mc, "can_split", lambda: True)
    monkeypatch.setattr(study_mc, "Forked", no_fork)
    refused = covtool.run_study(decl, backend=SerialBackend())
    for c in here.sums:
        assert np.array_equal(here.sums[c].s2, refused.sums[c].s2)
        assert np.array_equal(here.sums[c].s1, refused.sums[c].s1)


def test_shared_reference_maps_the_same_arrays_read_only(tmp_path):
    """The ensemble's reference written once and mapped by the workers: the same values bit for bit, the
    arrays views of the file (read-only), nested objects and empty arrays kept, the file removed after."""
    from covtool.validation.monte_carlo import SharedReference

    rng = np.random.default_rng(4)
    a = rng.normal(size=(1000, 3))
    b = rng.normal(size=(7, 4, 3)).astype(np.float32)
    ref = {"truth": {(1, 0.01, 3, None, 0.0, 600): (a, a[::2]), (1, "attitude"): b, "empty": np.zeros((0, 3))},
           "contexts": {(0, 5): {"w": rng.normal(size=(5, 3)), "name": "span"}}}
    sh = SharedReference(ref, tmp_path / "ref.bin")
    got = sh.load()
    x, y = got["truth"][(1, 0.01, 3, None, 0.0, 600)]
    assert np.array_equal(x, a) and x.dtype == a.dtype and not x.flags.writeable
    assert np.array_equal(y, a[::2])                                   # a strided view: pickled in-band
    assert np.array_equal(got["truth"][(1, "attitude")], b) and got["truth"][(1, "attitude")].dtype == np.float32
    assert got["truth"]["empty"].shape == (0, 3)
    assert np.array_equal(got["contexts"][(0, 5)]["w"], ref["contexts"][(0, 5)]["w"])
    assert got["contexts"][(0, 5)]["name"] == "span"
    with pytest.raises(ValueError, match="read-only"):
        x[0, 0] = 1.0
    import pickle
    assert pickle.loads(pickle.dumps(sh)).load()["truth"]["empty"].shape == (0, 3)   # what a task carries
    sh.remove()
    assert not (tmp_path / "ref.bin").exists()
    sh.remove()                                                         # already gone: fine
