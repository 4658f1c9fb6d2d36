"""Aided propagation (issue 15): same maths as the ZUPT engine, stacked = sequential, closed forms.

* a ZUPT-only run of :func:`covtool.lincov.aided.propagate_aided` equals the
  existing :func:`covtool.lincov.reference.propagate_with_filter` (≤ 1e-9);
* stacking the measurements of an epoch equals processing them one after the
  other (``H_f = H D``, block-diagonal R_f; module notes of covtool.lincov.aided);
* CUPT on a static vehicle: the position block after the fix is the
  information-form combination ``((M P⁻ M)⁻¹ + R⁻¹)⁻¹`` of the prior and the fix;
* barometric aiding holds the vertical channel over 24 h (unaided: cosh √2 ω_s t);
* GNSS outage: position growth against the bias/tilt closed form.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from covtool.errors import NumericalError
from covtool.lincov.aided import augment, build_epochs, error_processes, propagate_aided
from covtool.lincov.discretize import discretize
from covtool.lincov.dynamics import Context, error_dynamics
from covtool.lincov.measurements import (Baro, Cupt, GnssPosition, GnssVelocity, Schedule,
                                         Zupt)
from covtool.lincov.measurements.base import error_state, ned_metres
from covtool.lincov.reference import propagate, propagate_with_filter
from covtool.nav import earth
from covtool.nav.trajectory.profiles import static
from covtool.studies.grid import initial_covariance
from covtool.studies.inputs import load_truth
from covtool.studies.zupt_setup import setup

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def S():
    d = tomllib.loads((ROOT / "studies" / "zupt_filter_order.toml").read_text())
    d["study"].update(duration="10 min", dt="1 s")
    d["output"]["report_times"] = ["10 min"]
    d["filters"]["cases"] = ["A", "B1"]
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    return setup(d)


def rel_diff(A, B):
    """Largest ``|A − B|_ij / (σ_i σ_j)`` over a history (relative to the σ's of B).

    The quaternion error δq0…δq3 is scaled by the largest σ of the four, as
    the guard does (:func:`covtool.lincov.kalman.scale_groups`): ``q·δq = 0``
    makes one component's σ structurally near zero (δq3 ≈ 2e-8 at a 90°
    heading), and relative to it round-off means nothing.
    """
    d = np.sqrt(np.abs(np.diagonal(B, axis1=-2, axis2=-1)))
    d[..., 6:10] = np.max(d[..., 6:10], axis=-1, keepdims=True)
    scale = d[..., :, None] * d[..., None, :]
    return float(np.max(np.abs(A - B) / np.where(scale > 0, scale, 1.0)))


@pytest.mark.parametrize("name", ["A", "B1"])
def test_zupt_only_equals_the_zupt_engine(S, name):
    fm, Phi_f, Qd_f = S.filter_model(name)
    ref = propagate_with_filter(S.Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, S.H, S.H @ fm.D, fm.D, S.R,
                                S.update_steps, Rf=S.filter_R(name))
    z = Zupt(name="zupt", sigma=np.full(3, S.zupt_sigma))
    epochs = build_epochs([(z, S.update_steps)], S.nodes, S.truth.names, fm.names)
    run = propagate_aided(S.Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, fm.D, epochs, times=S.t)
    assert len(epochs) == len(S.update_steps) == 2
    assert rel_diff(run.P_truth, ref.P_truth) <= 1e-9
    assert rel_diff(run.P_filter, ref.P_filter) <= 1e-9


def gnss_mix(S):
    """GNSS position (Markov N/E/D) + velocity at 1 Hz over [60, 300] s, baro (bias, scale factor) at 0.5 Hz."""
    pos = GnssPosition(name="gps", sigma=np.array([2.0, 2.0, 4.0]), lever_arm=np.array([0.5, 0.2, -1.5]),
                       states=tuple(error_state("gps", "gnss_position", a, 1.5, "markov", tau=300.0) for a in "NED"))
    vel = GnssVelocity(name="gpsv", sigma=np.full(3, 0.05), lever_arm=np.array([0.5, 0.2, -1.5]))
    baro = Baro(name="baro", sigma=np.array([1.0]),
                states=(error_state("baro", "baro", "bias", 5.0, "markov", tau=1800.0),
                        error_state("baro", "baro", "scale_factor", 1e-3)))
    sch = Schedule(period=1.0, start=60.0, end=300.0)
    steps = sch.steps(S.t, S.nodes)
    return [(pos, steps), (vel, steps), (baro, steps[::2])], [*pos.states, *baro.states]


@pytest.mark.parametrize("kept", [["gps_N", "gps_E", "gps_D", "baro_bias", "baro_scale_factor"],
                                  ["gps_N", "gps_E"]])
def test_stacked_equals_sequential(S, kept):
    """Stacked and one-after-the-other updates give the same truth and filter covariances (≤ 1e-9)."""
    fm, Phi_f, Qd_f = S.filter_model("B1")
    plan, states = gnss_mix(S)
    P0, Pf_e, D = augment(S.P0, fm.D, states, kept)
    Pf0 = np.block([[fm.P0, np.zeros((fm.P0.shape[0], len(kept)))], [np.zeros((len(kept), fm.P0.shape[0])), Pf_e]])
    names = list(S.truth.names) + [s.name for s in states]
    fnames = list(fm.names) + kept
    epochs = build_epochs(plan, S.nodes, names, fnames)
    dt = np.diff(S.t)
    err = error_processes(states, dt)[:2]
    err_f = error_processes([s for s in states if s.name in kept], dt)[:2]
    a = propagate_aided(S.Phi, S.Qd, P0, Phi_f, Qd_f, Pf0, D, epochs, err=err, err_f=err_f)
    b = propagate_aided(S.Phi, S.Qd, P0, Phi_f, Qd_f, Pf0, D, epochs, err=err, err_f=err_f, sequential=True)
    assert max(e.H.shape[0] for e in epochs) == 7                  # 3 + 3 + 1 rows at the even seconds
    assert rel_diff(b.P_truth, a.P_truth) <= 1e-9
    assert rel_diff(b.P_filter, a.P_filter) <= 1e-9
    # the aiding worked: horizontal position σ at 300 s is metres, not the pure INS's
    k = int(np.searchsorted(S.t, 300.0))
    M = ned_metres(np.array([S.nodes.lat[k], 0, S.nodes.h[k]]))
    sig_n = math.sqrt(M[0, 0] ** 2 * a.P_truth[k, 0, 0])
    assert sig_n < 3.0


def static_system(duration, dt, truth_model="sdins58"):
    """A level vehicle at rest at 45° N: F is constant, so Φ and Q_d of one step serve every step."""
    truth = load_truth({"truth": {"model": truth_model}}, "<test>", None)
    traj = static(duration, lat=math.radians(45.0), lon=math.radians(10.0), h=100.0, dt=dt)
    t = traj.t
    ctx = Context.from_trajectory(traj.sample(t[:1]))
    dyn = error_dynamics(truth, ctx)
    Phi1, Qd1 = discretize(dyn.F, dyn.Qc, np.array([dt]), "van_loan")
    N = t.size - 1
    Phi = np.broadcast_to(Phi1, (N,) + Phi1.shape[1:])
    Qd = np.broadcast_to(Qd1, (N,) + Qd1.shape[1:])
    return truth, traj, t, Phi, Qd, initial_covariance(truth, traj, "<test>")


def test_cupt_static_is_the_information_form():
    """A position fix on a static vehicle combines with the prior position by the information form (≤ 1e-9)."""
    truth, traj, t, Phi, Qd, P0 = static_system(600.0, 1.0)
    sig = np.array([0.05, 0.08, 0.12])
    cupt = Cupt(name="mark", sigma=sig, lever_arm=np.array([0.3, -0.2, 1.1]))
    k = t.size - 1
    epochs = build_epochs([(cupt, np.array([k]))], traj, truth.names, truth.names)
    D = np.eye(truth.n)
    run = propagate_aided(Phi, Qd, P0, Phi, Qd, P0, D, epochs, times=t)   # the optimal filter: truth = filter
    x = np.array([traj.lat[k], traj.lon[k], traj.h[k]])
    M = ned_metres(x)
    # the lever arm makes H touch the attitude too: combine in the fix's own coordinates, z = H x
    H = epochs[0].H
    prior = H @ run.prior_truth[k] @ H.T
    post = H @ run.P_truth[k] @ H.T
    expect = np.linalg.inv(np.linalg.inv(prior) + np.diag(1 / sig**2))
    np.testing.assert_allclose(post, expect, rtol=1e-9, atol=1e-12 * np.max(sig) ** 2)
    # the static INS drifted metres in 10 min; the fix resets the NED position σ to the fix σ (within 1 %)
    pos = M @ run.P_truth[k][:3, :3] @ M
    prior_pos = M @ run.prior_truth[k][:3, :3] @ M
    assert np.all(np.sqrt(np.diag(prior_pos)) > 20 * sig)
    np.testing.assert_allclose(np.sqrt(np.diag(pos)), sig, rtol=0.01)


def test_baro_holds_the_vertical_channel_over_24_hours():
    """Unaided, the altitude σ grows like cosh √2 ω_s t; with a 0.1 Hz baro it stays bounded by the baro σ."""
    truth, traj, t, Phi, Qd, P0 = static_system(86400.0, 10.0)
    pure = propagate(Phi, Qd, P0, check=False)
    baro = Baro(name="baro", sigma=np.array([1.0]), states=(error_state("baro", "baro", "bias", 3.0, "markov",
                                                                         tau=3600.0),))
    steps = Schedule(period=10.0).steps(t, traj)
    P0a, Pf_e, D = augment(P0, np.eye(truth.n), baro.states, ["baro_bias"])
    Pf0 = np.block([[P0, np.zeros((truth.n, 1))], [np.zeros((1, truth.n)), Pf_e]])
    names = list(truth.names) + ["baro_bias"]
    epochs = build_epochs([(baro, steps)], traj, names, names)
    err = error_processes(baro.states, np.diff(t))[:2]
    run = propagate_aided(Phi, Qd, P0a, Phi, Qd, Pf0, D, epochs, err=err, err_f=err)
    sig_h = np.sqrt(run.P_truth[:, 2, 2])
    sig_pure = np.sqrt(pure[:, 2, 2])
    ws = earth.schuler_frequency(math.radians(45.0), 100.0)
    # unaided: past 6 h the vertical channel runs away (cosh √2 ω_s t ≫ 1 at 24 h)
    assert math.cosh(math.sqrt(2) * ws * 86400) > 1e10 and sig_pure[-1] > 1e6
    # aided: bounded by the baro bias and noise (3 m, 1 m), not growing
    assert np.max(sig_h[t >= 600]) < 3.5
    assert sig_h[-1] <= sig_h[t.size // 2] * 1.01


def test_propagate_aided_refuses_a_bad_R(S):
    fm, Phi_f, Qd_f = S.filter_model("A")
    z = Zupt(name="zupt", sigma=np.full(3, S.zupt_sigma), filter_sigma=np.array([0.01, np.nan, 0.01]))
    epochs = build_epochs([(z, S.update_steps)], S.nodes, S.truth.names, fm.names)
    with pytest.raises(NumericalError, match=r"\(filter\) at .*R.*non-finite"):
        propagate_aided(S.Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, fm.D, epochs, times=S.t)


def test_propagate_aided_names_the_first_epoch_with_a_bad_R_of_mixed_layouts(S):
    """The epochs' R and R_f are guarded as stacks per row layout; the message names the first bad epoch in time.

    GNSS position + velocity at 1 Hz, baro every other second (two layouts): the truth R of the baro at
    one late epoch and the filter R_f of a GNSS epoch before it are broken; the earlier (the filter's at
    the GNSS epoch) is reported, with its time, its stage and its component.
    """
    import dataclasses

    fm, Phi_f, Qd_f = S.filter_model("A")
    plan, states = gnss_mix(S)
    names = list(S.truth.names) + [s.name for s in states]
    P0, Pf_e, D = augment(S.P0, fm.D, states, [])
    epochs = build_epochs(plan, S.nodes, names, list(fm.names))
    err = error_processes(states, np.diff(S.t))[:2]
    layouts = {tuple(nm for nm, _ in ep.rows) for ep in epochs}
    assert layouts == {("gps", "gpsv", "baro"), ("gps", "gpsv")}
    late = next(i for i in range(150, len(epochs)) if len(epochs[i].rows) == 3)
    early = next(i for i in range(40, late) if len(epochs[i].rows) == 2)
    R = epochs[late].R.copy()
    R[6, 6] = -1.0                                                      # the baro's true variance
    Rf = epochs[early].Rf.copy()
    Rf[4, 4] = np.inf                                                   # the GNSS velocity's east, assumed
    epochs[late] = dataclasses.replace(epochs[late], R=R)
    epochs[early] = dataclasses.replace(epochs[early], Rf=Rf)
    when = re.escape(f"t = {S.t[epochs[early].step]:.1f} s")
    with pytest.raises(NumericalError, match=rf"^x \(filter\) at {when}: R: covariance .*non-finite.*'gpsv\[1\]'"):
        propagate_aided(S.Phi, S.Qd, P0, Phi_f, Qd_f, fm.P0, D, epochs, err=err, times=S.t, label="x")
    epochs[early] = dataclasses.replace(epochs[early], Rf=epochs[early + 2].Rf)
    when = re.escape(f"t = {S.t[epochs[late].step]:.1f} s")
    with pytest.raises(NumericalError, match=rf"^x \(truth\) at {when}.*: R: covariance has a negative .*'baro\[0\]'"):
        propagate_aided(S.Phi, S.Qd, P0, Phi_f, Qd_f, fm.P0, D, epochs, err=err, times=S.t, label="x")


def test_a_flagged_epoch_that_passes_alone_does_not_hide_a_later_bad_R(S, monkeypatch):
    """A stack may flag an R at the PSD tolerance that its epoch alone passes (the stacked test takes the
    eigenvalue path for the whole chunk): every flagged epoch is checked again alone, in time order, so a bad
    R after it is still named (review of the stacked guard)."""
    import dataclasses

    import covtool.lincov.aided as aided

    fm, Phi_f, Qd_f = S.filter_model("A")
    z = Zupt(name="zupt", sigma=np.full(3, S.zupt_sigma))
    epochs = build_epochs([(z, S.update_steps)], S.nodes, S.truth.names, fm.names)
    R = epochs[1].R.copy()
    R[0, 1] = R[1, 0] = 2.0 * R[0, 0]                                   # correlation 2: not a covariance
    epochs[1] = dataclasses.replace(epochs[1], R=R)
    flagged = np.array([True, True])                                   # the first passes alone
    monkeypatch.setattr(aided, "_noise_ok", lambda eps, attr: ~flagged if attr == "R" else np.ones(len(eps), bool))
    when = re.escape(f"t = {S.t[epochs[1].step]:.1f} s")
    with pytest.raises(NumericalError, match=rf"^x \(truth\) at {when}.*: R: covariance lost positive"):
        propagate_aided(S.Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, fm.D, epochs, times=S.t, label="x")


def test_propagate_aided_refuses_inconsistent_sizes(S):
    fm, Phi_f, Qd_f = S.filter_model("A")
    with pytest.raises(ValueError, match="inconsistent sizes"):
        propagate_aided(S.Phi, S.Qd, S.P0[:57, :57], Phi_f, Qd_f, fm.P0, fm.D, [])


def test_augment_refuses_an_unknown_state(S):
    with pytest.raises(ValueError, match="'odo_sf' is not a measurement-error state"):
        augment(S.P0, np.eye(58), [], ["odo_sf"])


def test_gnss_outage_growth_matches_the_bias_tilt_closed_form():
    """North position σ over a 60-s GNSS outage against the short-time closed form (≤ 0.5 % in the growth).

    Level, heading north, at rest at 45° N, truth with accelerometer and gyro
    biases, ARW and VRW only; 1 Hz GNSS position and velocity for 19 min under
    the optimal filter, then nothing.  With the attitude error φ of Britting
    (``Ĉ = (I − [φ×]) C``, docs of :func:`covtool.nav.attitude.attitude_error_matrix`)
    and ``τ`` from the outage start, for ``τ ≪ 1/ω_s``::

        δv̇_N = g φ_E + b_N,      φ̇_E = −ω_D φ_N + ω_N φ_D − ε_E    (ω = ω_ie^n)
        δN(τ) = δN₀ + δV_N₀ τ + (g φ_E₀ + b_N) τ²/2 + g (−ω_D φ_N₀ + ω_N φ_D₀ − ε_E) τ³/6
        var δN(τ) = aᵀ C₀ a + q_VRW τ³/3 + g² q_ARW τ⁵/20

    The Schuler feedback (``(ω_s τ)²/12 = 5e-4``) and Coriolis terms are left out.
    """
    truth = load_truth({"truth": {"model": "sdins58", "only": ["nav", "acc_bias", "gyro_bias", "arw", "vrw"]}},
                       "<test>", None)
    lat = math.radians(45.0)
    traj = static(1200.0, lat=lat, lon=math.radians(10.0), h=100.0, dt=1.0)
    t = traj.t
    ctx = Context.from_trajectory(traj.sample(t[:1]))
    dyn = error_dynamics(truth, ctx)
    Phi1, Qd1 = discretize(dyn.F, dyn.Qc, np.array([1.0]), "van_loan")
    Phi = np.broadcast_to(Phi1, (t.size - 1,) + Phi1.shape[1:])
    Qd = np.broadcast_to(Qd1, (t.size - 1,) + Qd1.shape[1:])
    P0 = initial_covariance(truth, traj, "<test>")
    pos = GnssPosition(name="gps", sigma=np.array([2.0, 2.0, 4.0]))
    vel = GnssVelocity(name="gpsv", sigma=np.full(3, 0.03))
    steps = Schedule(period=1.0, start=1.0, end=1140.0).steps(t, traj)
    epochs = build_epochs([(pos, steps), (vel, steps)], traj, truth.names, truth.names)
    run = propagate_aided(Phi, Qd, P0, Phi, Qd, P0, np.eye(truth.n), epochs, times=t)
    k0 = 1140
    T = np.zeros((7, truth.n))
    rm, _ = earth.radii(lat)
    T[0, 0] = rm + 100.0
    T[1, 3] = 1.0
    from covtool.nav.attitude import attitude_error_matrix
    T[2:5, 6:10] = attitude_error_matrix(traj.q_nb[k0])
    ix = {n: i for i, n in enumerate(truth.names)}
    T[5, ix["acc_bias_x"]] = 1.0                     # body x is north
    T[6, ix["gyro_bias_y"]] = 1.0                    # body y is east
    C0 = T @ run.P_truth[k0] @ T.T
    g = float(earth.gravity(lat, 100.0))
    wN, wD = earth.OMEGA_IE * math.cos(lat), -earth.OMEGA_IE * math.sin(lat)
    growth, closed = [], []
    for tau in (20.0, 40.0, 60.0):
        a = np.array([1.0, tau, -g * wD * tau**3 / 6, g * tau**2 / 2, g * wN * tau**3 / 6, tau**2 / 2,
                      -g * tau**3 / 6])
        var = a @ C0 @ a + truth.vrw**2 * tau**3 / 3 + g**2 * truth.arw**2 * tau**5 / 20
        closed.append(var - C0[0, 0])
        growth.append(T[0] @ run.P_truth[k0 + int(tau)] @ T[0] - C0[0, 0])
    closed, growth = np.array(closed), np.array(growth)
    assert growth[-1] > 0.5 * C0[0, 0]                # the outage matters: σ grows by > 20 %
    np.testing.assert_allclose(growth, closed, rtol=0.005)        # measured 0.12 % at 60 s (Schuler, Coriolis)


def test_guard_names_the_first_bad_covariance(S):
    """A non-finite Φ at step 100 (not checked on entry: system_checked) is caught after that propagation."""
    fm, Phi_f, Qd_f = S.filter_model("A")
    Phi = S.Phi.copy()
    Phi[100, 3, 3] = np.nan
    z = Zupt(name="zupt", sigma=np.full(3, S.zupt_sigma))
    epochs = build_epochs([(z, S.update_steps)], S.nodes, S.truth.names, fm.names)
    with pytest.raises(NumericalError, match=r"truth after the propagation at .*non-finite.*'dvN'"):
        propagate_aided(Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, fm.D, epochs, times=S.t, names=S.truth.names,
                        filter_names=fm.names, system_checked=True, record=[0, 600])


def test_recorded_steps_equal_the_full_history(S):
    fm, Phi_f, Qd_f = S.filter_model("B1")
    z = Zupt(name="zupt", sigma=np.full(3, S.zupt_sigma))
    epochs = build_epochs([(z, S.update_steps)], S.nodes, S.truth.names, fm.names)
    full = propagate_aided(S.Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, fm.D, epochs)
    part = propagate_aided(S.Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, fm.D, epochs, record=[300, 0, 600])
    np.testing.assert_array_equal(part.steps, [0, 300, 600])
    np.testing.assert_array_equal(part.P_truth, full.P_truth[[0, 300, 600]])
    assert sorted(part.prior_truth) == [300, 600]


def test_shared_jacobians_equal_each_epochs_own_and_follow_the_geometry(S):
    """The measurement Jacobians shared by a study's runs (covtool.lincov.aided.Jacobians, issue 13).

    Epochs built with one shared instance, for two filters and a σ-scaled copy of the plan, equal those
    built alone, element for element; a copy differing only in σ takes the same arrays, one with another
    lever arm its own (and different) ones; Jacobians of another trajectory are refused.
    """
    import dataclasses

    from covtool.lincov.aided import Jacobians
    from covtool.lincov.measurements.base import nav_point

    plan, states = gnss_mix(S)
    names = list(S.truth.names) + [s.name for s in states]
    jac = Jacobians(S.nodes)
    scaled = [(dataclasses.replace(m, sigma=m.sigma * 3.0, filter_sigma=m.sigma * 0.5), st) for m, st in plan]
    for f, kept in (("A", ["gps_N", "baro_bias"]), ("B1", [])):
        fnames = list(S.filter_model(f)[0].names) + kept
        for p in (plan, scaled):
            shared, alone = build_epochs(p, S.nodes, names, fnames, jacobians=jac), build_epochs(p, S.nodes, names,
                                                                                                 fnames)
            assert len(shared) == len(alone) > 100
            for a, b in zip(shared, alone):
                assert a.step == b.step and a.rows == b.rows
                for x in ("H", "R", "Hf", "Rf"):
                    assert np.array_equal(getattr(a, x), getattr(b, x)), (f, x, a.step)
    pos, k = plan[0][0], int(plan[0][1][7])
    x, w = nav_point(S.nodes, k)
    H_nav, H_err = jac(pos, k)
    want = pos.jacobian(x, w)
    assert np.array_equal(H_nav, want[0]) and np.array_equal(H_err, want[1])
    assert jac(scaled[0][0], k)[0] is H_nav                         # σ does not enter H (seed 002, eq (14))
    moved = dataclasses.replace(pos, lever_arm=pos.lever_arm + np.array([0.0, 0.0, 1.0]))
    assert moved.geometry_key() != pos.geometry_key() == scaled[0][0].geometry_key()
    H_moved = jac(moved, k)[0]
    assert H_moved is not H_nav and np.array_equal(H_moved, moved.jacobian(x, w)[0])
    assert not np.array_equal(H_moved, H_nav)
    assert not H_nav.flags.writeable
    other = S.nodes.sample(S.t)
    with pytest.raises(ValueError, match="another trajectory"):
        build_epochs(plan, other, names, names, jacobians=jac)
