"""Tests of covtool.nav.strapdown: the nonlinear reference mechanization.

Oracles: the closed-form coning and sculling residuals of the n-sample +
1-previous algorithm (Ignagni 1996; Roscoe 2001), exact error-free IMU data
(the navigation errors are then the algorithm's own), the Schuler response
to an accelerometer bias, and covtool's linear error model (ẋ = F x from
covtool.lincov.dynamics) for injected sensor biases.
"""

from __future__ import annotations

import math
import time
from fractions import Fraction

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.special import j1

from covtool.nav import earth
from covtool.nav import attitude as quat
from covtool.nav import strapdown as sd, coning
from covtool.lincov.dynamics import error_dynamics
from covtool.nav.imu.simulator import ImuRecord, ImuSimulator, ideal_increments
from covtool.validation.sensor_errors import SensorErrors
from covtool.io.model_file import model_from_dict
from covtool.studies.grid import midpoint_context
from covtool.nav.trajectory.profiles import land_vehicle, static
from covtool.units import parse_quantity

LAT, LON, H = math.radians(36.37), math.radians(127.36), 60.0


@pytest.fixture(scope="module")
def lv():
    return land_vehicle(dt=1.0)


def _ned_metres(err, lat, h):
    """Position errors (δL, δl, δh) as north, east, down metres."""
    rm, rn = earth.radii(lat)
    return np.stack([err[..., 0] * (rm + h), err[..., 1] * (rn + h) * np.cos(lat), -err[..., 2]], axis=-1)


def _attitude(err, q):
    """φ (north tilt, east tilt, azimuth) of additive quaternion errors."""
    return np.einsum("...ij,...j->...i", quat.attitude_error_matrix(q), err[..., 6:10])


# --------------------------------------------------------------------------
# coefficients and closed-form residuals
# --------------------------------------------------------------------------


def test_coefficients_are_seed001_eq2():
    """The derivation reproduces seed 001 eq (2) and the classic 1/12."""
    assert coning.coning_coefficients(4) == tuple(Fraction(k, 315) for k in (656, 262, 168, -1))
    assert coning.coning_coefficients(1) == (Fraction(1, 12),)
    with pytest.raises(ValueError, match=r"integer in 1\.\.6, got 0"):
        coning.coning_coefficients(0)
    with pytest.raises(ValueError, match="got 2.5"):
        coning.coning_coefficients(2.5)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_residual_order(n):
    """The n-sample residual is O(λ^(2n+3)); the uncompensated one O(λ³)."""
    lam = 0.3        # small enough for the leading term, large enough for double precision
    r = coning.coning_residual(n, lam) / coning.coning_residual(n, lam / 2)
    assert r == pytest.approx(2.0 ** (2 * n + 3), rel=0.03)
    lam = 0.02
    ru = coning.coning_residual(n, lam, compensated=False) / coning.coning_residual(n, lam / 2, compensated=False)
    assert ru == pytest.approx(8.0, rel=0.01)


def _coning_drift(n, h, f, beta, duration, compensated=True):
    """Simulated attitude drift rate along the cone axis [rad/s].

    Classical coning: ``q(t) = [cos β/2, 0, sin β/2 cos Ωt, sin β/2 sin Ωt]``
    (body → inertial), ``ω = [−2Ω sin²(β/2), −Ω sin β sin Ωt, Ω sin β cos Ωt]``
    (Savage 1998); the gyro increments are the exact integrals of ω.
    """
    W = 2.0 * math.pi * f
    K = int(round(duration / h))
    K -= K % n
    t = h * np.arange(K + 1)
    dth = np.column_stack([np.full(K, -2.0 * W * math.sin(beta / 2) ** 2 * h),
                           math.sin(beta) * np.diff(np.cos(W * t)),
                           math.sin(beta) * np.diff(np.sin(W * t))])
    S = K // n
    D = dth.reshape(S, n, 3)
    prev = np.concatenate([np.zeros((1, 3)), D[:-1, -1]])
    if compensated:
        phi, _ = coning.body_increments(D, np.zeros_like(D), prev, np.zeros_like(prev))
    else:
        phi = D.sum(axis=1)
    dq = quat.from_rotvec(phi)
    q = np.array([math.cos(beta / 2), 0.0, math.sin(beta / 2), 0.0])
    qs = np.empty((S, 4))
    for m in range(S):
        q = quat.mul(q, dq[m])
        qs[m] = q
    tm = t[n::n]
    qt = np.column_stack([np.full(S, math.cos(beta / 2)), np.zeros(S),
                          math.sin(beta / 2) * np.cos(W * tm), math.sin(beta / 2) * np.sin(W * tm)])
    err = quat.to_rotvec(quat.mul(qs, quat.conj(qt)))      # inertial-frame attitude error
    return np.polyfit(tm, err[:, 0], 1)[0]


@pytest.mark.parametrize("n,f", [(4, 60.0), (4, 80.0), (1, 10.0), (2, 30.0)])
def test_coning_motion_drift_matches_theory(n, f, capsys):
    """Classical coning: simulated residual drift = −sin²β ε(λ)/T within 10 %.

    β = 0.05° keeps the O(β⁴) terms of the Bortz equation (neglected by
    every algorithm of this family) below 1 % of the residual.
    """
    h, beta = 1.0 / 400.0, math.radians(0.05)
    lam = 2.0 * math.pi * f * h
    theory = -math.sin(beta) ** 2 * coning.coning_residual(n, lam) / (n * h)
    sim = _coning_drift(n, h, f, beta, 20.0)
    theory_u = -math.sin(beta) ** 2 * coning.coning_residual(n, lam, compensated=False) / (n * h)
    sim_u = _coning_drift(n, h, f, beta, 20.0, compensated=False)
    with capsys.disabled():
        print(f"\n[coning n={n}, f={f:g} Hz at 400 Hz, beta=0.05 deg] drift theory {theory:.4e} rad/s, "
              f"simulated {sim:.4e} ({100 * (sim / theory - 1):+.2f} %); uncompensated {sim_u:.4e} "
              f"(theory {theory_u:.4e}), {sim_u / sim:.3g}x larger")
    assert sim == pytest.approx(theory, rel=0.10)
    assert sim_u == pytest.approx(theory_u, rel=0.01)
    assert abs(sim_u) > 20.0 * abs(sim)


def _sculling_error(n, h, f, th0, A, duration, extra=None):
    """Velocity-error rate along z under in-phase sculling [m/s²].

    Rotation about x by ``θ₀ sin Ωt`` and specific force ``A sin Ωt`` along
    body y; the true inertial z velocity at whole periods is ``A J₁(θ₀) t``.
    """
    W = 2.0 * math.pi * f
    K = int(round(duration / h))
    K -= K % n
    t = h * np.arange(K + 1)
    dth = np.zeros((K, 3))
    dv = np.zeros((K, 3))
    dth[:, 0] = th0 * np.diff(np.sin(W * t))
    dv[:, 1] = -(A / W) * np.diff(np.cos(W * t))
    S = K // n
    D, V = dth.reshape(S, n, 3), dv.reshape(S, n, 3)
    pth = np.concatenate([np.zeros((1, 3)), D[:-1, -1]])
    pdv = np.concatenate([np.zeros((1, 3)), V[:-1, -1]])
    _, dvb = coning.body_increments(D, V, pth, pdv)
    if extra is not None:
        dvb = dvb + extra(pth, pdv, D, V)
    tm = t[::n][:-1]
    q = quat.from_rotvec(np.column_stack([th0 * np.sin(W * tm), 0 * tm, 0 * tm]))   # exact attitude
    v = np.einsum("sij,sj->i", quat.dcm(q), dvb)
    assert abs(v[1]) < 1e-10
    return (v[2] - A * j1(th0) * t[-1]) / t[-1]


def test_sculling_motion_error_matches_theory(capsys):
    """Sculling: residual = −(θ₀A/Ω) ε(λ)/T (Roscoe equivalency) within 10 %.

    Also documents the sign slip of seed 001 eq (4): with ``+1/315`` on
    ``Δθ_{m−1}(4) × Δv_m(4)`` as printed, the residual is several times the
    theory; the derivation gives ``−1/315`` on both previous-sample terms.
    """
    n, h, f, th0, A = 4, 1.0 / 400.0, 60.0, 1e-3, 10.0
    W, lam = 2.0 * math.pi * f, 2.0 * math.pi * f * h
    theory = -(th0 * A / W) * coning.coning_residual(n, lam) / (n * h)
    sim = _sculling_error(n, h, f, th0, A, 40.0)
    printed = _sculling_error(n, h, f, th0, A, 40.0,
                              extra=lambda pth, pdv, D, V: 2.0 / 315.0 * np.cross(pth, V[:, -1]))
    theory_u = -(th0 * A / W) * coning.coning_residual(n, lam, compensated=False) / (n * h)
    none = _sculling_error(n, h, f, th0, A, 40.0, extra=lambda pth, pdv, D, V: (
        -coning.body_increments(D, V, pth, pdv)[1] + V.sum(1) + 0.5 * np.cross(D.sum(1), V.sum(1))))
    with capsys.disabled():
        print(f"\n[sculling n=4, f=60 Hz at 400 Hz] error rate theory {theory:.4e} m/s^2, simulated {sim:.4e} "
              f"({100 * (sim / theory - 1):+.2f} %); eq (4) as printed {printed:.4e}; "
              f"uncompensated {none:.4e} (theory {theory_u:.4e})")
    assert sim == pytest.approx(theory, rel=0.10)
    assert none == pytest.approx(theory_u, rel=0.01)
    assert abs(printed - theory) > 2.0 * abs(theory)


# --------------------------------------------------------------------------
# error-free data: the algorithm's own error
# --------------------------------------------------------------------------


def test_error_free_land_vehicle_30min(lv, capsys):
    """Acceptance 1: horizontal < 0.5 m, altitude < 5 m at 30 min.

    Error-free 100 Hz increments, 4 samples per 25 Hz navigation step.  The
    regression bounds (1 cm) are far tighter than the acceptance limits.
    """
    rec = ideal_increments(lv, 100.0)
    hist = sd.run(sd.NavState.from_trajectory(lv), rec, 4, every=25)
    err = hist.errors(lv)[:, 0]
    s = lv.sample(hist.t)
    ned = _ned_metres(err, s.lat, s.h)
    hor = np.hypot(ned[:, 0], ned[:, 1])
    phi = _attitude(err, s.q_nb)
    with capsys.disabled():
        print(f"\n[acceptance 1, land vehicle 30 min, 100 Hz / n=4] horizontal {hor[-1]:.3e} m "
              f"(max {hor.max():.3e}), altitude {abs(ned[-1, 2]):.3e} m (max {np.abs(ned[:, 2]).max():.3e}), "
              f"velocity {np.linalg.norm(err[-1, 3:6]):.2e} m/s, attitude {np.abs(phi).max():.2e} rad")
    assert hist.t[-1] == pytest.approx(1800.0)
    assert hor[-1] < 0.5 and abs(ned[-1, 2]) < 5.0
    assert hor.max() < 0.01 and np.abs(ned[:, 2]).max() < 0.01
    assert np.abs(phi).max() < 1e-8


def test_static_error_free():
    """A vehicle at rest stays at rest (error-free data, 10 min, 10 Hz steps).

    The residual (µm) is the third-order Earth-rate terms of the 0.1 s step.
    """
    traj = static(600.0, lat=LAT, lon=LON, h=H, heading=math.radians(30.0))
    hist = sd.run(sd.NavState.from_trajectory(traj), ideal_increments(traj, 40.0), 4, every=500)
    err = hist.errors(traj)[:, 0]
    assert np.abs(_ned_metres(err, LAT, H)).max() < 1e-4
    assert np.abs(err[:, 3:6]).max() < 1e-6
    assert np.abs(_attitude(err, traj.q_nb[0])).max() < 1e-10


def test_static_accel_bias_schuler():
    """North accelerometer bias at rest: δN = b/ω_s² (1 − cos ω_s t).

    Half a Schuler period (42 min); Earth-rate (Foucault) coupling, absent
    from the closed form, stays below 2 % of the peak.
    """
    traj = static(2532.0, lat=LAT, lon=LON, h=H)
    model = _small_model(("accel_bias",))
    x0 = np.zeros((1, model.n))
    b = parse_quantity("100 ug", "acceleration")
    x0[0, model.index["acc_bias_x"]] = b
    sim = ImuSimulator(traj, 8.0, errors=SensorErrors(model, x0, noise=False))
    hist = sd.run(sim.initial_state(), sim, 4, every=120)
    ned = _ned_metres(hist.errors(traj)[:, 0], LAT, H)
    ws = earth.schuler_frequency(LAT, H)
    closed = b / ws**2 * (1.0 - np.cos(ws * hist.t))
    peak = 2.0 * b / ws**2
    assert np.abs(ned[:, 0] - closed).max() < 0.02 * peak
    assert ned[-1, 0] == pytest.approx(peak, rel=0.02)


# --------------------------------------------------------------------------
# two rates, ensembles, per-step API
# --------------------------------------------------------------------------


def test_two_rate_synchronisation(lv):
    """KIMU at 4× the main rate (n = 4) = main IMU (n = 1), error-free.

    Both run on the main IMU's interval; the KIMU samples are assigned to
    the main intervals by their time tags (:func:`group_samples`).
    """
    main = ideal_increments(lv, 25.0, t0=0.0, duration=300.0)
    kimu = ideal_increments(lv, 100.0, t0=0.0, duration=300.0)
    edges = np.concatenate([[main.t0], main.t])
    idx = sd.group_samples(kimu.t, edges, "KIMU")
    assert idx.shape == (main.n_samples, 4)
    grouped = ImuRecord(kimu.t0, kimu.dt, kimu.dtheta[idx.ravel()], kimu.dv[idx.ravel()])
    s0 = sd.NavState.from_trajectory(lv)
    a = sd.run(s0, main, 1, every=25)
    b = sd.run(s0, grouped, 4, every=25)
    np.testing.assert_allclose(a.t, b.t)
    diff = a.errors(lv)[:, 0] - b.errors(lv)[:, 0]
    s = lv.sample(a.t)
    assert np.abs(_ned_metres(diff, s.lat, s.h)).max() < 1e-3
    assert np.abs(diff[:, 3:6]).max() < 1e-5
    assert np.abs(_attitude(diff, s.q_nb)).max() < 1e-9


def test_group_samples_refuses_gaps():
    edges = np.arange(0.0, 1.01, 0.1)
    ts = np.arange(1, 41) * 0.025
    assert sd.group_samples(ts, edges).shape == (10, 4)
    with pytest.raises(ValueError, match=r"KIMU: main interval 2 .* holds 3 samples, expected 4"):
        sd.group_samples(np.delete(ts, 10), edges, "KIMU")
    with pytest.raises(ValueError, match=r"sample 40 \(t = 1.025 s\) lies outside"):
        sd.group_samples(np.append(ts, 1.025), edges, "KIMU")
    with pytest.raises(ValueError, match="must be 1-D"):
        sd.group_samples(ts, edges[:1])



def test_rows_let_runs_share_record_rows(lv):
    """run(rows=) reads each run's row in place: the same numbers as the record with the rows copied out."""
    rec = ideal_increments(lv, 100.0, t0=20.0, duration=6.0)
    rng = np.random.default_rng(4)
    src = ImuRecord(rec.t0, rec.dt, rec.dtheta[None] * (1 + 1e-4 * rng.normal(size=(3, 1, 3))),
                    rec.dv[None] * (1 + 1e-4 * rng.normal(size=(3, 1, 3))))
    rows = np.array([2, 0, 0, 1, 2])
    s0 = sd.NavState.from_trajectory(lv, 20.0, errors=rng.normal(size=(5, 10)) * 1e-6)
    got = sd.run(s0, src, 4, every=5, rows=rows)
    ref = sd.run(s0, ImuRecord(src.t0, src.dt, src.dtheta[rows], src.dv[rows]), 4, every=5)
    for key in ("t", "lat", "lon", "h", "v_n", "q"):
        assert np.array_equal(getattr(got, key), getattr(ref, key)), key
    with pytest.raises(ValueError, match="rows must have shape"):
        sd.run(s0, src, 4, rows=rows[:4])
    with pytest.raises(ValueError, match="the record has 3"):
        sd.run(s0, src, 4, rows=rows + 1)
    with pytest.raises(ValueError, match="rows cannot be combined with a callback"):
        sd.run(s0, src, 4, rows=rows, callback=lambda st: None)

def test_ensemble_runs_are_independent_copies(lv, capsys):
    """M runs with identical inputs give identical results; M=200 timing."""
    rec = ideal_increments(lv, 100.0, duration=120.0)
    one = sd.run(sd.NavState.from_trajectory(lv, n_runs=1), rec, 4, every=100)
    many = sd.run(sd.NavState.from_trajectory(lv, n_runs=7), rec, 4, every=100)
    for key in ("lat", "lon", "h", "v_n", "q"):
        a, b = getattr(one, key), getattr(many, key)
        assert np.array_equal(np.broadcast_to(a, b.shape), b), key
    # per-run increments (a run axis) give the same as shared ones
    per_run = ImuRecord(rec.t0, rec.dt, np.repeat(rec.dtheta[None], 3, 0), np.repeat(rec.dv[None], 3, 0))
    three = sd.run(sd.NavState.from_trajectory(lv, n_runs=3), per_run, 4, every=100)
    np.testing.assert_allclose(three.lat, np.broadcast_to(one.lat, three.lat.shape), rtol=0, atol=1e-15)
    timing = {}
    for M in (1, 200):
        st = sd.NavState.from_trajectory(lv, n_runs=M)
        t0 = time.perf_counter()
        sd.run(st, rec, 4, every=100)
        timing[M] = time.perf_counter() - t0
    with capsys.disabled():
        print(f"\n[ensemble] 3000 steps: M=1 {timing[1]:.2f} s, M=200 {timing[200]:.2f} s "
              f"({timing[200] / timing[1]:.2f}x)")


def test_step_api_and_feedback(lv):
    """step() = run(); correct() with the true errors restores the truth (eq (10))."""
    rec = ideal_increments(lv, 100.0, t0=20.0, duration=2.0)
    x0 = np.zeros((2, 10))
    x0[1] = [1e-6, -2e-6, 3.0, 0.1, -0.2, 0.05, 0.0, 1e-4, -2e-4, 3e-4]
    s = sd.NavState.from_trajectory(lv, 20.0, errors=x0)
    hist = sd.run(s, rec, 4)
    for dth, dv, T in sd.iter_intervals(rec, 4):
        s = sd.step(s, dth, dv, T)
    np.testing.assert_allclose(s.as_vector(), hist.state(-1).as_vector(), rtol=0, atol=1e-12)
    truth = sd.truth_state(lv, [s.t])
    err = sd.nav_errors(s, truth)
    fixed = sd.correct(s, err)
    assert np.abs(sd.nav_errors(fixed, truth)).max() < 1e-9
    # feedback through run()'s callback: reset every step, the error stays at the algorithm level
    calls = []

    def feedback(state):
        calls.append(state.t)
        return sd.correct(state, sd.nav_errors(state, sd.truth_state(lv, [state.t])))

    fb = sd.run(sd.NavState.from_trajectory(lv, 20.0, errors=x0), rec, 4, callback=feedback)
    assert len(calls) == 50
    assert np.abs(fb.errors(lv)[-1]).max() < 1e-9


def test_nav_error_conventions(lv):
    """δq = q̂ − q (sign-aligned) and φ = −2R(q)ᵀδq: Ĉ = (I − [φ×]) C."""
    s = lv.sample([100.0])
    phi = np.array([2e-5, -3e-5, 4e-4])
    q_hat = quat.mul(quat.from_rotvec(-phi), s.q_nb[0])          # Ĉ = C(−φ) C ≈ (I − [φ×]) C
    st = sd.NavState(100.0, s.lat, s.lon + 2 * np.pi, s.h + 1.0, s.v_n, -q_hat[None],
                     np.zeros((1, 3)), np.zeros((1, 3)))
    err = sd.nav_errors(st, sd.truth_state(lv, [100.0]))[0]
    assert err[1] == pytest.approx(0.0, abs=1e-12)     # longitude wrapped
    assert err[2] == pytest.approx(1.0)
    np.testing.assert_allclose(quat.attitude_error_matrix(s.q_nb[0]) @ err[6:10], phi, rtol=1e-3, atol=1e-12)


def test_input_validation(lv):
    s = sd.NavState.from_trajectory(lv, n_runs=2)
    good = np.zeros((4, 3))
    with pytest.raises(ValueError, match="shapes differ"):
        sd.step(s, good, np.zeros((3, 3)), 0.04)
    with pytest.raises(ValueError, match=r"shape \(n, 3\) or \(M, n, 3\)"):
        sd.step(s, np.zeros(3), np.zeros(3), 0.04)
    with pytest.raises(ValueError, match="increments have 3 runs, the state has 2"):
        sd.step(s, np.zeros((3, 4, 3)), np.zeros((3, 4, 3)), 0.04)
    with pytest.raises(ValueError, match=r"samples per interval must be in 1\.\.6, got 7"):
        sd.step(s, np.zeros((7, 3)), np.zeros((7, 3)), 0.04)
    with pytest.raises(ValueError, match=r"dx must have shape \(10,\) or \(M, 10\)"):
        sd.correct(s, np.zeros(9))
    with pytest.raises(ValueError, match="errors must have 10 columns"):
        sd.NavState.from_trajectory(lv, errors=np.zeros((2, 9)))
    rec = ideal_increments(lv, 100.0, duration=1.0)
    with pytest.raises(ValueError, match="samples_per_step must be in"):
        sd.run(s, rec, 0)
    with pytest.raises(ValueError, match="every must be a positive integer"):
        sd.run(s, rec, 4, every=0)
    with pytest.raises(ValueError, match="record of 100 samples is not a multiple of 3"):
        sd.run(s, rec, 3)
    with pytest.raises(ValueError, match="record of 100 samples is not a multiple of 3"):
        next(sd.iter_intervals(rec, 3))
    with pytest.raises(ValueError, match=r"starts at 0 s but the state is at 5 s"):
        sd.run(s.replace(t=5.0), rec, 4)
    per_run = ImuRecord(rec.t0, rec.dt, np.zeros((3, 100, 3)), np.zeros((3, 100, 3)))
    with pytest.raises(ValueError, match="IMU record has 3 runs, the state has 2"):
        sd.run(s, per_run, 4)


# --------------------------------------------------------------------------
# injected errors against the linear model
# --------------------------------------------------------------------------


def _small_model(kinds):
    blocks = [{"kind": "navigation"}] + [{"kind": k} for k in kinds]
    return model_from_dict({"model": {"name": "test"}, "block": blocks})


def _linear_response(model, traj, x0, T, dt=0.5):
    """x(T) = Π expm(F_k dt) x0 with covtool.lincov.dynamics' F at step mid-points."""
    t = np.arange(0.0, T + 0.5 * dt, dt)
    F = error_dynamics(model, midpoint_context(traj, t)).F
    x = np.array(x0, dtype=float)
    for Fk in F:
        x = x @ expm(Fk * dt).T
    return x


def test_injected_biases_match_linear_model(lv, capsys):
    """One run per injected bias, all in one vectorised run; 5 min, within 3 %.

    The accelerometer biases (100 µg) and gyro biases (0.1 °/h) are large
    enough to dominate the algorithm error and small enough to stay linear
    (at 1 °/h the second-order tilt term g φ²/2 already moves the height
    error by 17 %).
    """
    model = _small_model(("accel_bias", "gyro_bias"))
    cases = [("acc_bias_x", "100 ug"), ("acc_bias_z", "100 ug"), ("gyro_bias_x", "0.1 deg/h"),
             ("gyro_bias_z", "0.1 deg/h")]
    x0 = np.zeros((len(cases), model.n))
    for m, (name, value) in enumerate(cases):
        dim = "acceleration" if name.startswith("acc") else "angular_rate"
        x0[m, model.index[name]] = parse_quantity(value, dim)
    T = 300.0
    sim = ImuSimulator(lv, 100.0, duration=T, errors=SensorErrors(model, x0, noise=False))
    hist = sd.run(sim.initial_state(), sim, 4, every=750)
    nl = hist.errors(sim)[-1]
    lin = _linear_response(model, lv, x0, T)[:, :10]
    s = lv.sample([T])
    lat, h = s.lat[0], s.h[0]
    groups = {"horizontal [m]": lambda e: _ned_metres(e, lat, h)[..., :2],
              "down [m]": lambda e: _ned_metres(e, lat, h)[..., 2:],
              "velocity [m/s]": lambda e: e[..., 3:6],
              "attitude [rad]": lambda e: _attitude(e, s.q_nb[0])}
    lines = []
    for m, (name, value) in enumerate(cases):
        for g, fn in groups.items():
            a, b = fn(nl[m]), fn(lin[m])
            rel = np.linalg.norm(a - b) / np.linalg.norm(b)
            lines.append(f"{name} {value}: {g} nonlinear {np.linalg.norm(a):.4g}, linear "
                         f"{np.linalg.norm(b):.4g}, difference {100 * rel:.2f} %")
            if np.linalg.norm(b) > 1e-3 * np.abs(fn(lin)).max():
                assert rel < 0.03, lines[-1]
    with capsys.disabled():
        print("\n[injection vs linear, 5 min]\n  " + "\n  ".join(lines))


# --------------------------------------------------------------------------
# the compiled kernel against the Python reference it replaced (issue 13)
# --------------------------------------------------------------------------


def _reference_run(state, dth, dv, n):
    """Step by step with the numpy body increments and _nav_core (the pre-kernel code path)."""
    M = state.n_runs
    S = dth.shape[1] // n
    x = sd._unpack(state)
    pth, pdv = state.dtheta_prev, state.dv_prev
    out = []
    for j in range(S):
        a, b = dth[:, j * n:(j + 1) * n], dv[:, j * n:(j + 1) * n]
        phi, dvb = coning.body_increments(a, b, pth, pdv)
        r = coning.body_position_increment(a, b)
        x = sd._nav_core(x, sd._rotvec_quat(phi).T, dvb.T, r.T, n * 0.01)
        pth, pdv = a[:, -1].copy(), b[:, -1].copy()
        out.append(np.column_stack(x))
    return np.stack(out), pth, pdv


@pytest.mark.parametrize("n,shared", [(4, False), (1, False), (3, True)])
def test_compiled_strapdown_equals_python_reference(lv, n, shared):
    """sd.run (numba kernel: coning, sculling, position weighting, nav update) equals the numpy step path.

    Random large increments (rates up to ~1 rad/s, ~3 g) exercise the series and the full
    branches of every term; all 10 state components agree to 1e-12 relative.
    """
    rng = np.random.default_rng(5)
    M, S = 3, 40
    dth = rng.normal(0, 0.01, (1 if shared else M, S * n, 3))
    dth[..., 0, :] *= 1e-4                         # one small-angle sample too
    dv = rng.normal(0, 0.3, dth.shape)
    s0 = sd.NavState.from_trajectory(lv, n_runs=M, errors=rng.normal(0, 1e-4, (M, 10)),
                                     previous=(rng.normal(0, 0.01, 3), rng.normal(0, 0.3, 3)))
    hist = sd.run(s0, ImuRecord(s0.t, 0.01, dth if not shared else dth[0], dv if not shared else dv[0]), n)
    ref, pth, pdv = _reference_run(s0, np.broadcast_to(dth, (M,) + dth.shape[1:]),
                                   np.broadcast_to(dv, (M,) + dv.shape[1:]), n)
    got = np.concatenate([hist.lat[1:, :, None], hist.lon[1:, :, None], hist.h[1:, :, None], hist.v_n[1:],
                          hist.q[1:]], axis=-1)
    scale = np.maximum(np.abs(ref).max(axis=(0, 1)), 1e-3)
    assert np.max(np.abs(got - ref) / scale) < 1e-12
    # the callback path (one compiled step per call) gives the same states
    seen = []
    hist2 = sd.run(s0, ImuRecord(s0.t, 0.01, dth if not shared else dth[0], dv if not shared else dv[0]), n,
                   callback=lambda st: seen.append(st.q.copy()))
    assert len(seen) == S and np.max(np.abs(hist2.q - hist.q)) < 1e-14
    fin = sd.run(s0, ImuRecord(s0.t, 0.01, dth if not shared else dth[0], dv if not shared else dv[0]), n,
                 every=7).state(-1)
    assert np.max(np.abs(fin.q - ref[-1, :, 6:10])) < 1e-12 and hist.t.size == S + 1


def test_compiled_strapdown_keeps_every_kth_across_records(lv):
    """Kept states follow the global step count across records of different lengths."""
    rng = np.random.default_rng(6)
    s0 = sd.NavState.from_trajectory(lv, n_runs=2)
    dth = rng.normal(0, 1e-3, (2, 60, 3))
    dv = rng.normal(0, 0.1, (2, 60, 3))
    one = sd.run(s0, ImuRecord(s0.t, 0.01, dth, dv), 4, every=3)
    parts = [ImuRecord(s0.t, 0.01, dth[:, :20], dv[:, :20]), ImuRecord(s0.t + 0.2, 0.01, dth[:, 20:], dv[:, 20:])]
    two = sd.run(s0, parts, 4, every=3)
    np.testing.assert_allclose(two.t, one.t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(two.t, s0.t + 0.04 * np.array([0, 3, 6, 9, 12, 15]), rtol=0, atol=1e-12)
    assert np.max(np.abs(two.q - one.q)) < 1e-14 and np.max(np.abs(two.lat - one.lat)) < 1e-15
