"""Error budget with declared measurements (issue 15): sources, linearity, closed forms, the study.

* Linearity: with the nominal gains fixed, seed 002 eq (15)–(16) is linear in
  (P0, Q_d, R), so the contributions of every source (INS initial errors and
  noises, each measurement-error state, each measurement's R) sum to the
  nominal run (≤ 1e-9 relative), for a reduced filter with dropped states.
* Closed form, static vehicle, optimal filter, one position fix of
  prior ``S₀ = H P⁻ Hᵀ`` and noise R, gain ``G = S₀ (S₀ + R)⁻¹`` in the fix's
  coordinates: R contributes ``G R Gᵀ`` to ``H P⁺ Hᵀ`` and any other source
  of prior contribution ``C⁻`` contributes ``(I − G) C⁻ (I − G)ᵀ``.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from covtool.analysis.budget import aided_sources, grid_noise, MEASUREMENT, MEASUREMENT_ERROR, run_aided_budget
from covtool.errors import StudyFileError
from covtool.lincov.aided import augment, build_epochs, error_processes, propagate_aided
from covtool.lincov.dynamics import Context, error_dynamics, NoiseSource
from covtool.lincov.discretize import discretize
from covtool.lincov.measurements import GnssPosition, GnssVelocity, Schedule
from covtool.lincov.measurements.base import error_state
from covtool.nav.trajectory.profiles import static
from covtool.studies.error_budget import run as run_budget_study
from covtool.studies.grid import initial_covariance
from covtool.studies.inputs import load_truth
from covtool.studies.zupt_setup import setup

ROOT = Path(__file__).resolve().parents[1]


def rel(A, B):
    """Largest ``|A − B|_ij / (σ_i σ_j)`` (σ of B; the δq block scaled by its largest σ, as the guard does)."""
    d = np.sqrt(np.abs(np.diagonal(B, axis1=-2, axis2=-1)))
    d[..., 6:10] = np.max(d[..., 6:10], axis=-1, keepdims=True)
    s = d[..., :, None] * d[..., None, :]
    return float(np.max(np.abs(A - B) / np.where(s > 0, s, 1.0)))


# ---------------------------------------------------------------------------
# closed forms on a static vehicle


def static_case(duration=300.0):
    truth = load_truth({"truth": {"model": "sdins58"}}, "<test>", None)
    traj = static(duration, lat=math.radians(45.0), lon=math.radians(10.0), h=100.0, dt=1.0)
    t = traj.t
    dyn = error_dynamics(truth, Context.from_trajectory(traj.sample(t[:1])))
    Phi1, Qd1 = discretize(dyn.F, dyn.Qc, np.array([1.0]), "van_loan")
    N = t.size - 1
    Phi = np.broadcast_to(Phi1, (N,) + Phi1.shape[1:])
    Qd = np.broadcast_to(Qd1, (N,) + Qd1.shape[1:])
    F = np.broadcast_to(dyn.F[:1], (N,) + dyn.F.shape[1:])
    noise = [NoiseSource(s.name, np.broadcast_to(s.G[:1], (N,) + s.G.shape[1:]),
                         np.broadcast_to(s.psd[:1], (N,) + s.psd.shape[1:])) for s in dyn.noise]
    return truth, traj, t, Phi, Qd, F, noise, initial_covariance(truth, traj, "<test>")


@pytest.fixture(scope="module")
def fix_budget():
    """Optimal filter (truth = filter), one GNSS position fix with a constant N/E/D bias at the last step."""
    truth, traj, t, Phi, Qd, F, noise, P0 = static_case()
    bias = tuple(error_state("fix", "gnss_position", a, s) for a, s in zip("NED", (0.7, 0.9, 1.6)))
    fix = GnssPosition(name="fix", sigma=np.array([0.4, 0.5, 0.8]), lever_arm=np.array([0.3, -0.2, 1.1]),
                       states=bias)
    k = t.size - 1
    names = list(truth.names) + [s.name for s in bias]
    P0a, _, D = augment(P0, np.eye(truth.n), bias, [s.name for s in bias])
    epochs = build_epochs([(fix, np.array([k]))], traj, names, names)
    err = error_processes(bias, np.diff(t))[:2]
    run = propagate_aided(Phi, Qd, P0a, Phi, Qd, P0a, D, epochs, err=err, err_f=err, times=t, names=names,
                          filter_names=names, all_gains=True)
    sources, factors = aided_sources(truth, noise, traj.q_nb[0], bias, ["fix"])
    br = run_aided_budget(Phi, grid_noise(F, factors), np.diff(t), sources, bias, ["fix"], D, epochs, run.gains, [k - 1, k],
                          err=err, keep=slice(None), names=names, times=t)
    return dict(truth=truth, run=run, br=br, H=epochs[0].H, R=epochs[0].R, k=k, sources=sources, bias=bias)


def test_static_fix_R_source_is_the_kalman_closed_form(fix_budget):
    """R's contribution to H P⁺ Hᵀ is G R Gᵀ with G = S₀ (S₀ + R)⁻¹ (≤ 1e-9)."""
    f = fix_budget
    H, R, k = f["H"], f["R"], f["k"]
    S0 = H @ f["run"].prior_truth[k] @ H.T
    G = S0 @ np.linalg.inv(S0 + R)
    b = [s.name for s in f["sources"]].index("fix noise (R)")
    got = H @ f["br"].P[b, 1] @ H.T
    np.testing.assert_allclose(got, G @ R @ G.T, rtol=1e-9, atol=1e-12 * np.max(np.diag(R)))
    assert np.all(f["br"].P[b, 0] == 0.0)                        # before the fix R has contributed nothing


@pytest.mark.parametrize("axis", range(3))
def test_static_fix_bias_source_is_the_kalman_closed_form(fix_budget, axis):
    """A constant fix bias: before the fix σ² h hᵀ (h its H column), after it (I − G) σ² h hᵀ (I − G)ᵀ."""
    f = fix_budget
    H, R, k = f["H"], f["R"], f["k"]
    s = f["bias"][axis]
    n0 = f["truth"].n
    S0 = H @ f["run"].prior_truth[k] @ H.T
    G = S0 @ np.linalg.inv(S0 + R)
    h = H[:, n0 + axis]
    C = s.sigma**2 * np.outer(h, h)
    b = [x.name for x in f["sources"]].index(s.name)
    assert f["sources"][b].kind == MEASUREMENT_ERROR
    np.testing.assert_allclose(H @ f["br"].P[b, 0] @ H.T, C, rtol=1e-12, atol=1e-15)
    A = np.eye(3) - G
    np.testing.assert_allclose(H @ f["br"].P[b, 1] @ H.T, A @ C @ A.T, rtol=1e-9, atol=1e-9 * s.sigma**2)


def test_static_fix_sources_sum_to_the_information_form(fix_budget):
    """Σ sources = the nominal run; in the fix's coordinates (S₀⁻¹ + R⁻¹)⁻¹ (≤ 1e-9)."""
    f = fix_budget
    H, R, k = f["H"], f["R"], f["k"]
    total = f["br"].P[:, 1].sum(axis=0)
    assert rel(total, f["run"].P_truth[k]) <= 1e-9
    S0 = H @ f["run"].prior_truth[k] @ H.T
    np.testing.assert_allclose(H @ total @ H.T, np.linalg.inv(np.linalg.inv(S0) + np.linalg.inv(R)), rtol=1e-9)


# ---------------------------------------------------------------------------
# linearity on the land vehicle, reduced filter with dropped measurement-error states


@pytest.fixture(scope="module")
def S():
    d = tomllib.loads((ROOT / "studies" / "zupt_filter_order.toml").read_text())
    d["study"].update(duration="5 min", dt="1 s")
    d["output"]["report_times"] = ["5 min"]
    d["filters"]["cases"] = ["B1"]
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    return setup(d)


def test_reduced_filter_sources_sum_to_the_nominal_run(S):
    """B1 keeping gps_N, gps_E only: the 10-state nav block of Σ sources equals the nominal run (≤ 1e-9)."""
    pos = GnssPosition(name="gps", sigma=np.array([2.0, 2.0, 4.0]), lever_arm=np.array([0.5, 0.2, -1.5]),
                       states=tuple(error_state("gps", "gnss_position", a, 1.5, "markov", tau=300.0) for a in "NED"))
    vel = GnssVelocity(name="gpsv", sigma=np.full(3, 0.05), lever_arm=np.array([0.5, 0.2, -1.5]))
    steps = Schedule(period=1.0, start=60.0, end=200.0).steps(S.t, S.nodes)
    plan, states = [(pos, steps), (vel, steps[::3])], list(pos.states)
    kept = ["gps_N", "gps_E"]
    fm, Phi_f, Qd_f = S.filter_model("B1")
    P0, Pf_e, D = augment(S.P0, fm.D, states, kept)
    Pf0 = np.block([[fm.P0, np.zeros((fm.P0.shape[0], 2))], [np.zeros((2, fm.P0.shape[0])), Pf_e]])
    names = list(S.truth.names) + [s.name for s in states]
    epochs = build_epochs(plan, S.nodes, names, list(fm.names) + kept)
    dt = np.diff(S.t)
    err = error_processes(states, dt)[:2]
    err_f = error_processes(states[:2], dt)[:2]
    rec = np.arange(0, S.t.size, 20)
    run = propagate_aided(S.Phi, S.Qd, P0, Phi_f, Qd_f, Pf0, D, epochs, err=err, err_f=err_f, record=rec,
                          all_gains=True)
    assert len(run.gains) == len(epochs) > len(set(rec) & set(steps))   # every gain kept, recorded or not
    sources, factors = aided_sources(S.truth, S.dyn.noise, S.nodes.q_nb[0], states, ["gps", "gpsv"])
    kinds = [s.kind for s in sources]
    assert kinds.count(MEASUREMENT_ERROR) == 3 and kinds.count(MEASUREMENT) == 2
    br = run_aided_budget(S.Phi, grid_noise(S.dyn.F, factors), dt, sources, states, ["gps", "gpsv"], D, epochs, run.gains,
                          rec, err=err, names=names, times=S.t)
    assert rel(br.P.sum(axis=0), run.P_truth[:, :10, :10]) <= 1e-9
    # the dropped gps_D and the kept gps_N both matter after the first fix; nothing measurement-made before it
    pre = rec < steps[0]
    b_D, b_N = (names.index(x) - S.truth.n for x in ("gps_D", "gps_N"))
    for name in ("gps_D", "gps_N", "gps noise (R)", "gpsv noise (R)"):
        b = [s.name for s in sources].index(name)
        assert np.all(br.P[b][pre] == 0.0)
        assert np.trace(br.P[b][-1][:3, :3]) > 0.0
    assert b_D == 2 and b_N == 0


# ---------------------------------------------------------------------------
# the study


def budget_decl(duration="3 min") -> dict:
    d = tomllib.loads((ROOT / "studies" / "error_budget_gnss_outage.toml").read_text())
    d["study"]["duration"] = duration
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["filters"]["cases"] = ["pure_ins", "B1"]
    for m in d["measurement"]:
        m["schedule"]["outages"] = [["1 min", "2 min"]]
    d["output"]["report_times"] = ["1 min", "2 min", duration]
    return d


def test_study_sources_and_residuals():
    r = run_budget_study(budget_decl())
    src = r.tables["sources"]
    assert {"gnss_N", "gnss_E", "gnss_D", "gnss noise (R)", "gnss_vel noise (R)"} <= set(src["source"])
    assert set(src[src["source"] == "gnss_N"]["kind"]) == {MEASUREMENT_ERROR}
    # the pure INS never sees a measurement: its budget leaves their sources out
    assert not any(n.startswith("gnss") for n in r.sources["pure_ins"])
    assert "gnss_N" in r.sources["B1"]
    s = r.tables["summary"]
    assert s["sum vs nominal run residual"].max() <= 1e-9
    # shares sum to 100 % per case, time and error
    b = r.tables["budget_horizontal"]
    tot = b.groupby(["case", "t [min]"])["share [%]"].sum()
    np.testing.assert_allclose(tot.to_numpy(), 100.0, rtol=1e-9)
    # no R before the first fix (t = 0); over the outage (1-2 min) the total grows
    h = r.tables["history_horizontal"]
    hb = h[h["case"] == "B1"].set_index("t [min]")
    assert hb.loc[0.0, "gnss noise (R) [ft^2]"] == 0.0 and hb.loc[1.0, "gnss noise (R) [ft^2]"] > 0.0
    assert hb.loc[2.0, "total [ft^2]"] > hb.loc[1.0, "total [ft^2]"]


@pytest.mark.parametrize("change,match", [
    (lambda d: d.update(zupt={"interval": "5 min"}),
     r"^<study>: \[zupt\]: a budget with \[\[measurement\]\] declares its ZUPTs as a measurement"),
    (lambda d: d["filters"].update(ewn_interval="1 s"), r"^<study>: \[filters\]: unknown key 'ewn_interval'"),
    (lambda d: d["measurement"][0].update(kind="lidar"),
     r"^<study>: \[\[measurement\]\] 'gnss' kind: unknown measurement kind 'lidar'"),
    (lambda d: d["measurement"][1].update(name="gnss"),
     r"^<study>: \[\[measurement\]\] 'gnss': the name is used twice"),
    (lambda d: d["measurement"][0]["schedule"].update(end="10 min"),
     r"^<study>: \[\[measurement\]\] 'gnss' schedule: end 600 s is outside the study"),
    (lambda d: d.update(measurement=[]), r"^<study>: \[\[measurement\]\]: expected a non-empty list"),
    (lambda d: d["measurement"].append({"name": "gyro", "kind": "heading", "sigma": "1 deg",
                                        "errors": {"bias": {"sigma": "2 deg"}}}),
     r"^<study>: \[\[measurement\]\] 'gyro' name: its error state 'gyro_bias' has the name of a truth-model"),
    (lambda d: [m["schedule"].update(outages=[["0 s", "3 min"]]) for m in d["measurement"]],
     r"^<study>: \[\[measurement\]\]: no update falls inside the study"),
])
def test_bad_budget_declarations_are_one_line(change, match):
    d = budget_decl()
    change(d)
    with pytest.raises(StudyFileError, match=match):
        run_budget_study(d)


def test_state_resolution_sums_to_the_nominal_run():
    d = budget_decl("2 min")
    d["output"]["report_times"] = ["1 min", "2 min"]
    d["budget"] = {"resolution": "state"}
    r = run_budget_study(d)
    assert r.tables["summary"]["sum vs nominal run residual"].max() <= 1e-9
    assert {"gnss_N", "gnss noise (R)", "initial gyro_bias_x"} <= set(r.sources["B1"])


def test_budget_members_refuse_a_missing_gain_and_name_a_bad_source(fix_budget):
    from covtool.errors import NumericalError
    from covtool.lincov.aided import budget_members

    f = fix_budget
    br = f["br"]
    n = f["H"].shape[1]
    N = f["k"]
    Phi = np.broadcast_to(np.eye(n - 3), (N, n - 3, n - 3))
    ep = type("E", (), {"step": 2, "H": f["H"], "R": f["R"], "rows": (("fix", slice(0, 3)),)})()
    P0s = np.zeros((2, n, n))
    zero_q = lambda k: np.zeros((2, n - 3, n - 3))              # noqa: E731
    with pytest.raises(ValueError, match=r"^error budget: no gain at step 2$"):
        budget_members(Phi, P0s, np.eye(n), [ep], {}, qd=zero_q, r_weights=np.zeros((2, 1)), meas_names=["fix"],
                       record=[0], keep=np.arange(10))
    P0s[1, 4, 4] = np.nan
    with pytest.raises(NumericalError, match=r"^b: source 'bad' at step 0: covariance has a non-finite entry "
                                             r"\(nan\) in state #4$"):
        budget_members(Phi, P0s, np.eye(n), [], {}, qd=zero_q, r_weights=np.zeros((2, 1)), meas_names=["fix"],
                       record=[0], keep=np.arange(10), label="b", members=["good", "bad"])
    assert br.P.shape[0] == len(f["sources"])


# ---------------------------------------------------------------------------
# streamed in time: the same numbers as on the whole grid, memory bounded


def _whole_grid_budget(d):
    """The budget of ``d``'s filter and pure INS on whole-grid stacks (the kind's path before it streamed)."""
    from covtool.analysis.budget import aided_sources as sources_of
    from covtool.io.filters import load_filters
    from covtool.lincov.aided import Jacobians
    from covtool.studies.aided import filter_run, filter_system, measurement_steps, parse_measurements
    from covtool.studies.error_budget import report_record_steps
    from covtool.studies.grid import time_grid, truth_system
    from covtool.studies.inputs import load_trajectory, study_header, output_options

    hdr = study_header(d, "<study>")
    every, rtimes = output_options(d, "<study>", hdr["duration"])
    plan, states = parse_measurements(d["measurement"], "<study>")
    mnames = [m.name for m, _ in plan]
    truth = load_truth(d, "<study>", None)
    spec = load_filters(d["filters"]["file"], truth)["B1"]
    traj = load_trajectory(d, "<study>", None, hdr["dt"], hdr["duration"])
    t = time_grid(hdr["duration"], hdr["dt"], "<study>")
    nodes = traj.sample(t)
    steps, all_steps = measurement_steps(plan, t, nodes, "<study>")
    rec = report_record_steps(t, every, rtimes)
    moving = t[-1] - sum(max(0.0, min(b, t[-1]) - max(a, 0.0)) for a, b in traj.stationary)
    ctx, dyn, Phi, Qd = truth_system(truth, traj, t, hdr["discretization"], where="<study>")
    P0 = initial_covariance(truth, nodes, "<study>")
    names_all = list(truth.names) + [s.name for s in states]
    err = error_processes(states, np.diff(t))[:2]
    sources, factors = sources_of(truth, dyn.noise, nodes.q_nb[0], states, mnames)
    noise = grid_noise(dyn.F, factors)
    fm, Phi_f, Qd_f = filter_system(spec, truth, ctx, dyn, Phi, Qd, hdr, t, nodes, ewn_dt=float(t[-1]) / all_steps.size,
                                    mean_speed=float(nodes.distance[-1] / moving), update_steps=all_steps)
    r, _, D, epochs = filter_run(fm, Phi, Qd, Phi_f, Qd_f, P0, states, [s.name for s in states],
                                 list(zip([m for m, _ in plan], steps)), nodes, names_all, err, rec,
                                 form=spec.update, label="B1", all_gains=True, jacobians=Jacobians(nodes))
    pure = [s for s in sources if s.kind not in (MEASUREMENT, MEASUREMENT_ERROR)]
    return {"pure_ins": run_aided_budget(Phi, noise, np.diff(t), pure, [], mnames, np.zeros((truth.n, 0)), [], {},
                                         rec).P,
            "B1": run_aided_budget(Phi, noise, np.diff(t), sources, states, mnames, D, epochs, r.gains, rec,
                                   err=err).P}


def test_streamed_budget_equals_the_whole_grid_budget():
    """12 min (two stream chunks, 12 budget chunks): every contribution as on whole-grid stacks (≤ 1e-12 of σ_i σ_j)."""
    d = budget_decl("12 min")
    r = run_budget_study(d)
    ref = _whole_grid_budget(d)
    for c in ("pure_ins", "B1"):
        got, want = r.runs[c].P, ref[c]
        assert got.shape == want.shape and r.runs[c].record_steps[-1] == 720
        total = want.sum(axis=0)
        d_ = np.sqrt(np.abs(np.einsum("kii->ki", total)))
        scale = d_[:, None, :, None] * d_[:, None, None, :]
        assert np.max(np.abs(got - want)) <= 1e-12 * np.max(scale), c
        assert np.max(np.abs(got - want) / np.where(scale[0] > 0, scale[0], 1.0)) <= 1e-12, c


def test_budget_refuses_noise_whose_factors_change(fix_budget):
    """A ``noise`` whose second span has other factors (a source lost at rest) is refused, naming the steps."""
    truth, traj, t, Phi, Qd, F, noise, P0 = static_case(200.0)
    sources, factors = aided_sources(truth, noise, traj.q_nb[0], [], [])
    whole = grid_noise(F, factors)

    def lossy(a, b):
        F_, f = whole(a, b)
        return F_, f if a == 0 else f[:-1]

    pure = [s for s in sources if s.kind not in (MEASUREMENT, MEASUREMENT_ERROR)]
    with pytest.raises(ValueError, match=r"^b: the noise factors of steps 64 … 127 are not those of the first steps"):
        run_aided_budget(Phi, lossy, np.diff(t), pure, [], [], np.zeros((truth.n, 0)), [], {}, [t.size - 1],
                         label="b")


def test_budget_memory_estimate_bounds_its_peak_and_long_runs_fit():
    """A 12-min budget: traced peak ≤ its recorded estimate ≤ 6 × the peak; 24 h is estimated under 5 GB.

    That is under a third of the whole-grid estimate of the same 24-h study (the aided kind's for whole-grid
    systems, 15.5 GB, which did not even count the per-source Q_d): what remains grows with the duration
    only as N × n (the filter build, the trajectory) and as the records (the contributions themselves).
    """
    from memory_peaks import recorded_estimate, traced_peak

    from covtool.io.filters import load_filters
    from covtool.studies import aided_budget
    from covtool.studies.aided import _memory as whole_grid_memory, parse_measurements
    from covtool.studies.inputs import output_options, study_header

    d = budget_decl("12 min")
    r, peak = traced_peak(lambda: run_budget_study(d), warm=True)
    est = recorded_estimate(r)
    assert 0 < peak <= est <= 6.0 * peak, (peak, est)
    d = budget_decl("24 h")
    hdr = study_header(d, "<study>")
    every, _ = output_options(d, "<study>", hdr["duration"])
    plan, states = parse_measurements(d["measurement"], "<study>")
    truth = load_truth(d, "<study>", None)
    specs = load_filters(d["filters"]["file"], truth)
    long = aided_budget._memory(hdr, truth, specs, ["pure_ins", "B1"], states, every, plan)["bytes"]
    whole = whole_grid_memory(hdr, truth, specs, ["B1"], {}, states, every, True)["bytes"]
    assert long < 5e9 and 3.0 * long < whole, (long, whole)


@pytest.mark.parametrize("target", ["truth model 'sdins58'", "filter B1"])
def test_a_bad_streamed_chunk_names_its_own_step(nan_in_qd, target):
    """A NaN in Q_d at t = 700 s of the truth's or B1's system, made in the budget's second chunk: the guard's
    own message (the system, 700 s, the state), not wrapped as a failed gain at the update before it."""
    from covtool.errors import SystemCheckError

    nan_in_qd(target.split()[-1].strip("'"), 700.0)
    with pytest.raises(SystemCheckError, match=rf"^<study>: {target}: Q_d of the step at t = 700\.0 s \(11\.7 min\): "
                                               r"covariance has a non-finite entry \(nan\) in state 'dvN'$"):
        run_budget_study(budget_decl("12 min"))


def test_budget_refuses_noise_spans_of_another_length():
    """A ``noise`` that gives another number of steps than asked is refused, naming the span."""
    truth, traj, t, Phi, Qd, F, noise, P0 = static_case(200.0)
    sources, factors = aided_sources(truth, noise, traj.q_nb[0], [], [])
    whole = grid_noise(F, factors)

    def short(a, b):
        F_, f = whole(a, b)
        return (F_[:-1], f) if a == 64 else (F_, f)

    pure = [s for s in sources if s.kind not in (MEASUREMENT, MEASUREMENT_ERROR)]
    with pytest.raises(ValueError, match=r"^b: noise\(64, 128\) gave spans of another length than 64 steps$"):
        run_aided_budget(Phi, short, np.diff(t), pure, [], [], np.zeros((truth.n, 0)), [], {}, [t.size - 1],
                         label="b")


def test_scaled_steps_read_one_step_at_a_time():
    from covtool.lincov.streamed import ScaledSteps

    Q = np.arange(8.0).reshape(2, 2, 2)
    s = ScaledSteps(Q, 2.5)
    assert s.shape == (2, 2, 2) and len(s) == 2 and np.array_equal(s[1], 2.5 * Q[1])
    with pytest.raises(TypeError, match=r"^a scaled stack is read one step at a time"):
        s[0:1]
