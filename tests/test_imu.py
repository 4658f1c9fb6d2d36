"""Tests of covtool.nav.imu: exact increments, sensor errors, grades, extras.

Oracles: adaptive quadrature of the trajectory's exact rates, the
independent sensor-error equations of ``tests/nonlinear_reference.py``,
closed-form process statistics, covtool's linear model (ẋ = F x) for
errors drawn from a truth model, and the exact kinematics of a vibrating
IMU.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.linalg import expm

import nonlinear_reference as nr
from covtool.nav import earth
from covtool.nav import attitude as quat
from covtool.nav import strapdown as sd
from covtool.lincov.dynamics import error_dynamics
from covtool.errors import ModelFileError
from covtool.nav.imu.simulator import ImuSimulator, ideal_increments
from covtool.nav.imu.vibration import RandomVibration, Tone, Vibration, right_jacobian_apply
from covtool.validation.sensor_errors import SensorErrors, grade_simulator, sample_states
from covtool.io.imu_grade import dump_imu_grade, imu_grade_from_dict, list_imu_grades, load_imu_grade
from covtool.io.library import load_model_by_name
from covtool.io.model_file import model_from_dict
from covtool.studies.grid import midpoint_context
from covtool.nav.trajectory.profiles import land_vehicle, static
from covtool.units import parse_quantity

LAT, LON, H = math.radians(36.37), math.radians(127.36), 60.0
DEG_H = math.pi / 180.0 / 3600.0


@pytest.fixture(scope="module")
def lv():
    return land_vehicle(dt=1.0)


@pytest.fixture(scope="module")
def sdins58():
    return load_model_by_name("sdins58")


def _ned(err, lat, h):
    rm, rn = earth.radii(lat)
    return np.stack([err[..., 0] * (rm + h), err[..., 1] * (rn + h) * np.cos(lat), -err[..., 2]], axis=-1)


# --------------------------------------------------------------------------
# exact increments
# --------------------------------------------------------------------------


def test_ideal_increments_are_integrals_of_the_rates(lv):
    """Δθ = ∫ω_ib^b, Δv = ∫f^b (adaptive quadrature) across a turn transition."""
    rate = 100.0
    # the first turn of the route starts after the 20 s start and a cruise; pick samples in it
    t_turn = float(lv.t[np.argmax(np.abs(lv.w_ib_b[:, 2]) > 1e-3)])
    t0 = math.floor(t_turn * rate) / rate - 0.02
    rec = ideal_increments(lv, rate, t0=t0, duration=0.1, nodes=3)
    for k in (0, 3, 9):
        a, b = rec.t0 + k * rec.dt, rec.t0 + (k + 1) * rec.dt
        for c in range(3):
            w = quad(lambda t: lv.sample([t]).w_ib_b[0, c], a, b, epsabs=1e-16, epsrel=1e-13)[0]
            f = quad(lambda t: lv.sample([t]).f_b[0, c], a, b, epsabs=1e-16, epsrel=1e-13)[0]
            assert rec.dtheta[k, c] == pytest.approx(w, rel=1e-9, abs=1e-15)
            assert rec.dv[k, c] == pytest.approx(f, rel=1e-9, abs=1e-13)
    np.testing.assert_allclose(rec.t, t0 + rec.dt * np.arange(1, 11))
    assert rec.rate == pytest.approx(rate)
    part = rec.slice(2, 5)
    assert part.t0 == pytest.approx(t0 + 0.02) and part.n_samples == 3


def test_span_errors(lv):
    with pytest.raises(ValueError, match="IMU rate must be positive"):
        ideal_increments(lv, 0.0)
    with pytest.raises(ValueError, match="holds no whole sample"):
        ideal_increments(lv, 10.0, duration=0.05)
    with pytest.raises(ValueError, match="exceeds the trajectory"):
        ideal_increments(lv, 10.0, t0=1790.0, duration=20.0)


def test_mounting_rotation(lv):
    """A rotated IMU navigates its own frame: truth q_nb ⊗ q_bs."""
    q_bs = quat.from_euler(0.1, -0.2, 0.3)
    sim = ImuSimulator(lv, 100.0, t0=10.0, duration=60.0, mounting=q_bs)
    body = ideal_increments(lv, 100.0, t0=10.0, duration=60.0)
    rec = sim.record()
    np.testing.assert_allclose(rec.dtheta[0] @ quat.dcm(q_bs).T, body.dtheta, atol=1e-15)
    hist = sd.run(sim.initial_state(), sim, 4, every=100)
    err = hist.errors(sim)[:, 0]
    s = lv.sample(hist.t)
    assert np.abs(_ned(err, s.lat, s.h)).max() < 1e-5
    assert np.abs(err[:, 6:10]).max() < 1e-10
    # the body-frame truth differs by the mounting rotation
    assert np.abs(hist.errors(lv)[:, 0, 6:10]).max() > 0.05


# --------------------------------------------------------------------------
# sensor-error definitions
# --------------------------------------------------------------------------


def test_injection_matches_reference_sensor_equations(sdins58):
    """δf, δω per sample = tests/nonlinear_reference.corrupt_many (seed 002 eq (3), (5))."""
    rng = np.random.default_rng(5)
    model = sdins58
    x = sample_states(model, 1, rng)[0] * 100.0
    x[model.idx(["grav_xi", "grav_eta", "grav_dg"])] = 0.0    # environment: tested separately
    N, h = 50, 1e-4
    f = rng.normal(0.0, 5.0, (N, 3)) + [0.0, 0.0, -9.8]
    w = rng.normal(0.0, 0.5, (N, 3))
    # N runs with one sample each (per-run increments), all at the same x
    err = SensorErrors(model, np.repeat(x[None], N, 0), noise=False, process_dt=h)
    still = {"speed_fn": lambda t: np.zeros(np.size(t)), "attitude": np.tile([1.0, 0, 0, 0], (1, 1)),
             "gravity": np.full(1, 9.8)}
    ddth, ddv = err.increment_errors(0.0, h, (w * h)[:, None], (f * h)[:, None], **still)
    f_hat, w_hat = nr.corrupt_many(model, x, f, w)
    # tolerance: the Markov and AD-reset states decay by h/2τ within the sample
    np.testing.assert_allclose(ddv[:, 0] / h, f_hat - f, rtol=1e-6, atol=2e-8)
    np.testing.assert_allclose(ddth[:, 0] / h, w_hat - w, rtol=1e-6, atol=1e-13)


def test_gravity_disturbance_as_specific_force(sdins58):
    """δf^b = C_n^b diag(g, g, −1) [ξ, η, Δg]: the INS sees −Δg^n."""
    model = sdins58
    x = np.zeros(model.n)
    x[model.idx(["grav_xi", "grav_eta", "grav_dg"])] = [1e-5, -2e-5, 3e-4]
    q = quat.from_euler(0.1, 0.2, 0.3)[None]
    err = SensorErrors(model, x[None], noise=False)
    _, ddv = err.increment_errors(0.0, 0.01, np.zeros((1, 1, 3)), np.zeros((1, 1, 3)), attitude=q,
                                  gravity=np.array([9.8]), speed_fn=lambda t: np.zeros(np.size(t)))
    dg_n = np.array([-9.8 * 1e-5, 9.8 * 2e-5, 3e-4])     # Δg^n = [−gξ, −gη, Δg]
    np.testing.assert_allclose(quat.dcm(q[0]) @ ddv[0, 0] / 0.01, -dg_n, rtol=1e-6)
    with pytest.raises(ValueError, match="needs the true attitude and gravity"):
        SensorErrors(model, x[None]).increment_errors(0.0, 0.01, np.zeros((1, 1, 3)), np.zeros((1, 1, 3)),
                                                      speed_fn=lambda t: np.zeros(np.size(t)))
    with pytest.raises(ValueError, match="Markov-in-distance states need the horizontal speed"):
        SensorErrors(model, x[None]).increment_errors(0.0, 0.01, np.zeros((1, 1, 3)), np.zeros((1, 1, 3)),
                                                      attitude=q, gravity=np.array([9.8]))


def test_model_samples_match_linear_model(lv, sdins58, capsys):
    """Errors drawn from the 58-state truth model: nonlinear = Φ x0 at 5 min.

    All sensor and environment blocks and the initial navigation errors,
    without driving noise (the deterministic part ẋ = F x); three runs in one
    vectorised simulation.
    """
    model = sdins58
    x0 = sample_states(model, 3, 11, q0=lv.q_nb[0])
    T = 300.0
    sim = ImuSimulator(lv, 100.0, duration=T, errors=SensorErrors(model, x0, noise=False, process_dt=0.5))
    hist = sd.run(sim.initial_state(x0[:, :10]), sim, 4, every=750)
    nl = hist.errors(sim)[-1]
    dt = 0.5
    t = np.arange(0.0, T + 0.5 * dt, dt)
    x = x0.copy()
    for F in error_dynamics(model, midpoint_context(lv, t)).F:
        x = x @ expm(F * dt).T
    s = lv.sample([T])
    lat, h, q = s.lat[0], s.h[0], s.q_nb[0]
    lines = []
    for m in range(3):
        pn, pl = _ned(nl[m], lat, h), _ned(x[m, :10], lat, h)
        an = quat.attitude_error_matrix(q) @ nl[m, 6:10]
        al = quat.attitude_error_matrix(q) @ x[m, 6:10]
        for name, a, b in (("horizontal", pn[:2], pl[:2]), ("down", pn[2:], pl[2:]),
                           ("velocity", nl[m, 3:6], x[m, 3:6]), ("attitude", an, al)):
            rel = np.linalg.norm(a - b) / np.linalg.norm(b)
            lines.append(f"run {m} {name}: nonlinear {np.linalg.norm(a):.4g}, linear {np.linalg.norm(b):.4g}, "
                         f"difference {100 * rel:.2f} %")
            assert rel < 0.03, lines[-1]
    with capsys.disabled():
        print("\n[sdins58 samples vs linear, 5 min]\n  " + "\n  ".join(lines))


def test_process_statistics(capsys):
    """Markov σ and correlation e^{−Δ/τ}, random-walk growth rw² t, ARW/VRW variance."""
    decl = {"model": {"name": "proc"}, "block": [
        {"kind": "navigation", "angle_random_walk": "0.05 deg/sqrt(h)", "velocity_random_walk": "50 ug/sqrt(Hz)"},
        {"kind": "gyro_markov_drift", "sigma": "10 deg/h", "process": "markov", "tau": "20 s"},
        {"kind": "accel_bias", "sigma": "0 ug", "process": "random_walk", "rw": "100 ug/sqrt(s)"}]}
    model = model_from_dict(decl)
    M, h, k = 4000, 0.01, 100
    x0 = sample_states(model, M, 3)
    err = SensorErrors(model, x0, 4, process_dt=0.1)
    zeros = np.zeros((1, k, 3))
    chunks = [err.increment_errors(float(j), h, zeros, zeros) for j in range(10)]
    sig = parse_quantity("10 deg/h", "angular_rate")
    arw = parse_quantity("0.05 deg/sqrt(h)", "angle_random_walk")
    vrw = parse_quantity("50 ug/sqrt(Hz)", "velocity_random_walk")
    rw = parse_quantity("100 ug/sqrt(s)", "acceleration_random_walk")
    # 1-s means of the rate error: Markov (σ², e^{−Δ/τ}) plus averaged white noise arw²/(k h)
    g0 = chunks[0][0][:, :, 0].mean(axis=1) / h
    g9 = chunks[9][0][:, :, 0].mean(axis=1) / h
    white = arw**2 / (k * h)
    rho_theory = sig**2 * math.exp(-9.0 / 20.0) / (sig**2 + white)
    rho = np.corrcoef(g0, g9)[0, 1]
    # 1-s means of the specific-force error: random walk rw² t (t = 9.5 s) plus white vrw²/(k h)
    a9 = chunks[9][1][:, :, 0].mean(axis=1) / h
    var_a = rw**2 * 9.5 + vrw**2 / (k * h)
    with capsys.disabled():
        print(f"\n[processes] Markov var {g9.var():.4g} (theory {sig**2 + white:.4g}), corr {rho:.3f} "
              f"(theory {rho_theory:.3f}); random walk var {a9.var():.4g} (theory {var_a:.4g})")
    assert g9.var() == pytest.approx(sig**2 + white, rel=0.08)
    assert rho == pytest.approx(rho_theory, abs=0.05)
    assert a9.var() == pytest.approx(var_a, rel=0.08)
    # white parts: differences of adjacent samples remove the slow processes
    assert np.diff(chunks[5][0][:, :, 1], axis=1).var() == pytest.approx(2 * arw**2 * h, rel=0.03)
    assert np.diff(chunks[5][1][:, :, 2], axis=1).var() == pytest.approx(2 * vrw**2 * h, rel=0.03)


def test_sample_states_covariance(sdins58, lv):
    x = sample_states(sdins58, 20000, 1, q0=lv.q_nb[0])
    P = sdins58.initial_covariance(lv.q_nb[0])
    sd_ = np.sqrt(np.diag(P))
    keep = sd_ > 0
    C = np.cov(x.T)[np.ix_(keep, keep)] / np.outer(sd_[keep], sd_[keep])
    np.testing.assert_allclose(np.diag(C), 1.0, atol=0.05)
    assert np.all(x[:, ~keep] == 0.0)


def test_sensor_errors_validation(sdins58):
    with pytest.raises(ValueError, match=r"x0 must have shape \(M, 58\) for model 'sdins58'"):
        SensorErrors(sdins58, np.zeros((2, 10)))
    with pytest.raises(ValueError, match="process_dt must be positive"):
        SensorErrors(sdins58, np.zeros((1, 58)), process_dt=0.0)


# --------------------------------------------------------------------------
# extras outside the linear model
# --------------------------------------------------------------------------


def test_quantization_does_not_accumulate(lv):
    qa, qv = parse_quantity("1 arcsec", "angle"), parse_quantity("1 mm/s", "velocity")
    ideal = ImuSimulator(lv, 100.0, duration=30.0).record()
    quant = ImuSimulator(lv, 100.0, duration=30.0, quantization=(qa, qv), chunk=333).record()
    assert np.allclose(quant.dtheta / qa, np.round(quant.dtheta / qa), atol=1e-6)
    assert np.allclose(quant.dv / qv, np.round(quant.dv / qv), atol=1e-6)
    drift_a = np.cumsum(quant.dtheta - ideal.dtheta, axis=1)
    drift_v = np.cumsum(quant.dv - ideal.dv, axis=1)
    assert np.abs(drift_a).max() <= 0.5 * qa * (1 + 1e-6)
    assert np.abs(drift_v).max() <= 0.5 * qv * (1 + 1e-6)
    assert np.abs(quant.dv - ideal.dv).max() > 0.1 * qv


def test_saturation_clips_sample_means():
    traj = static(10.0, lat=LAT, lon=LON, h=H)
    rec = ImuSimulator(traj, 100.0, saturation=(1e-6, 5.0)).record()
    assert rec.dv[0, :, 2].max() == pytest.approx(-5.0 * 0.01)
    assert np.abs(rec.dtheta).max() <= 1e-6 * 0.01 + 1e-18


def test_right_jacobian_is_the_body_rate():
    """ω = J_r(θ) θ̇ satisfies q̇ = ½ q ⊗ ω for q = exp(θ(t))."""
    def theta(t):
        return np.array([0.3 * np.sin(2 * t), -0.2 * np.cos(3 * t), 0.5 * t])

    def dtheta(t):
        return np.array([0.6 * np.cos(2 * t), 0.6 * np.sin(3 * t), 0.5])

    for t in (0.1, 0.7, 1.3):
        e = 1e-6
        qd = (quat.from_rotvec(theta(t + e)) - quat.from_rotvec(theta(t - e))) / (2 * e)
        w = 2.0 * quat.mul(quat.conj(quat.from_rotvec(theta(t))), qd)
        np.testing.assert_allclose(w[1:], right_jacobian_apply(theta(t), dtheta(t)), atol=1e-8)
        assert abs(w[0]) < 1e-8


def test_vibration_is_a_consistent_motion(lv, capsys):
    """Error-free IMU under coning + sculling vibration tracks the vibrating truth.

    Angular 30 Hz tones on x and y in quadrature (coning, 0.1 mrad) with an
    in-phase 5 m/s² tone on y (sculling), plus random angular and linear
    vibration (5–40 Hz) realised per run: the 4-sample algorithm's error
    stays at the residual level, and the per-run truth includes the
    vibration.  (Above ~λ = 1, i.e. 60 Hz at 400 Hz, the residual of
    :func:`covtool.nav.coning.coning_residual` becomes visible: with the same
    random levels over 20–80 Hz the attitude drifts by ~1e-6 rad in 20 s.)
    """
    vib = Vibration((
        Tone("angular", "x", 1e-4, 30.0), Tone("angular", "y", 1e-4, 30.0, math.pi / 2),
        Tone("linear", "y", 5.0, 30.0),
        RandomVibration("angular", 0.002, (5.0, 40.0), tones=8),
        RandomVibration("linear", 0.05, (5.0, 40.0), axes="xz", tones=8)))
    sim = ImuSimulator(lv, 400.0, t0=100.0, duration=60.0, n_runs=3, vibration=vib, rng=7)
    assert sim.nodes > 3
    rec = sim.record()
    assert rec.dtheta.shape == (3, 24000, 3)
    assert not np.allclose(rec.dtheta[0], rec.dtheta[1])
    hist = sd.run(sim.initial_state(), sim, 4, every=400)
    err = hist.errors(sim)
    s = lv.sample(hist.t)
    pos = np.abs(_ned(err, s.lat[:, None], s.h[:, None])).max()
    att = np.abs(err[..., 6:10]).max()
    vel = np.abs(err[..., 3:6]).max()
    # the same data against the non-vibrating truth shows the vibration itself
    att_nominal = np.abs(hist.errors(lv)[..., 6:10]).max()
    with capsys.disabled():
        print(f"\n[vibration] max errors vs vibrating truth: position {pos:.2e} m, velocity {vel:.2e} m/s, "
              f"quaternion {att:.2e}; vs nominal truth quaternion {att_nominal:.2e}")
    assert pos < 1e-3 and vel < 1e-4 and att < 1e-8
    assert att_nominal > 1e-5


def test_vibration_validation(lv):
    with pytest.raises(ValueError, match="vibration kind 'spin' is not"):
        Vibration((Tone("spin", "x", 1.0, 10.0),)).realize()
    with pytest.raises(ValueError, match="tone frequency must be positive"):
        Vibration((Tone("angular", "x", 1.0, 0.0),)).realize()
    with pytest.raises(ValueError, match="band .* must satisfy 0 < f1 < f2"):
        Vibration((RandomVibration("linear", 1.0, (50.0, 20.0)),)).realize()
    with pytest.raises(ValueError, match="axis 'w' is not"):
        Vibration((Tone("linear", "w", 1.0, 10.0),)).realize()
    with pytest.raises(ValueError, match="non-zero 3-vector"):
        Vibration((Tone("linear", (0, 0, 0), 1.0, 10.0),)).realize()
    real = Vibration((RandomVibration("linear", 1.0, (20.0, 50.0)),)).realize(4, 1)
    errs = SensorErrors(load_model_by_name("sdins58"), np.zeros((3, 58)))
    with pytest.raises(ValueError, match=r"inconsistent numbers of runs: \[3, 4\]"):
        ImuSimulator(lv, 100.0, errors=errs, vibration=real)
    with pytest.raises(ValueError, match="chunk must be a positive number"):
        ImuSimulator(lv, 100.0, chunk=0)


# --------------------------------------------------------------------------
# grades
# --------------------------------------------------------------------------


def test_presets_carry_seed001_table2():
    assert {"main_imu", "kimu", "nav_grade_sdins"} <= set(list_imu_grades())
    main, kimu = load_imu_grade("main_imu"), load_imu_grade("kimu")
    table2 = {  # seed 001 Table 2: main, KIMU
        ("gyro", "bias"): ("20 deg/h", "30 deg/h"), ("gyro", "bias_instability"): ("1 deg/h", "5 deg/h"),
        ("gyro", "scale_factor"): ("600 ppm", "700 ppm"), ("accel", "bias"): ("5 mg", "2 mg"),
        ("accel", "scale_factor"): ("750 ppm", "500 ppm"), ("accel", "range"): ("73 g", "50 g")}
    dims = {"bias": None, "bias_instability": None, "scale_factor": "dimensionless", "range": "acceleration"}
    for (sensor, key), values in table2.items():
        dim = dims[key] or ("angular_rate" if sensor == "gyro" else "acceleration")
        for grade, text in zip((main, kimu), values):
            assert getattr(grade, sensor)[key][0] == pytest.approx(parse_quantity(text, dim))
            assert "seed 001 Table 2" in grade.sources[f"{sensor}.{key}"] or key == "bias_instability"
    # every value says where it comes from; assumed ones say so
    for grade in (main, kimu):
        for sensor in ("gyro", "accel"):
            for key in getattr(grade, sensor):
                src = grade.sources[f"{sensor}.{key}"]
                assert "seed 001" in src or "assumed" in src or "engineering judgement" in src, (key, src)
    assert kimu.rate == pytest.approx(4.0 * main.rate)


def test_nav_grade_matches_sdins58(sdins58):
    """nav_grade_sdins.to_model() carries the sdins58 sensor magnitudes."""
    grade = load_imu_grade("nav_grade_sdins")
    model = grade.to_model()
    truth = sdins58
    shared = [n for n in model.names[10:]]
    assert len(shared) == 42
    for name in shared:
        a, b = model.states[model.index[name]], truth.states[truth.index[name]]
        assert a.sigma == pytest.approx(b.sigma), name
        assert a.process == b.process and a.tau == b.tau, name
    assert model.arw == pytest.approx(truth.arw) and model.vrw == pytest.approx(truth.vrw)


def test_grade_model_and_round_trip(tmp_path):
    kimu = load_imu_grade("kimu")
    model = kimu.to_model()
    assert model.name == "imu_kimu"
    s = model.states[model.index["gyro_markov_z"]]
    assert s.process == "markov" and s.tau == pytest.approx(100.0)
    assert s.sigma == pytest.approx(5 * DEG_H)
    assert model.arw == pytest.approx(parse_quantity("0.3 deg/sqrt(h)", "angle_random_walk"))
    assert kimu.quantization[0] == pytest.approx(parse_quantity("1 arcsec", "angle"))
    path = tmp_path / "kimu_copy.toml"
    path.write_text(dump_imu_grade(kimu))
    again = load_imu_grade(str(path))
    assert again == imu_grade_from_dict(kimu.decl, path=str(path))
    assert again.gyro == kimu.gyro and again.accel == kimu.accel and again.sources == kimu.sources


def test_simulator_from_grade(lv):
    kimu = load_imu_grade("kimu")
    a = grade_simulator(lv, kimu, 3, rng=42, t0=100.0, duration=5.0)
    b = grade_simulator(lv, kimu, 3, rng=42, t0=100.0, duration=5.0)
    ra, rb = a.record(), b.record()
    assert ra.dtheta.shape == (3, 2000, 3) and a.rate == pytest.approx(400.0)
    np.testing.assert_array_equal(ra.dtheta, rb.dtheta)
    assert not np.allclose(ra.dv[0], ra.dv[1])
    qa = kimu.quantization[0]
    assert np.allclose(ra.dtheta / qa, np.round(ra.dtheta / qa), atol=1e-6)
    hist = sd.run(a.initial_state(), grade_simulator(lv, kimu, 3, rng=42, t0=100.0, duration=5.0), 4)
    assert hist.lat.shape == (501, 3)
    nogr = imu_grade_from_dict({"imu": {"name": "x"}})
    with pytest.raises(ValueError, match="IMU grade 'x' has no rate; pass rate="):
        grade_simulator(lv, nogr, 1)


BASE = {"imu": {"name": "t", "rate": "100 Hz"},
        "gyro": {"bias": "1 deg/h", "bias_instability": "0.1 deg/h", "bias_instability_tau": "100 s",
                 "source": {"bias": "test"}},
        "accel": {"bias": "1 mg", "misalignment": "1 mrad"}}


def _mut(path, value):
    d = copy.deepcopy(BASE)
    *head, last = path
    node = d
    for k in head:
        node = node[k]
    if value is _DEL:
        del node[last]
    else:
        node[last] = value
    return d


_DEL = object()


@pytest.mark.parametrize("decl,match", [
    (_mut(("extra",), {}), r"g\.toml: unknown key 'extra'"),
    (_mut(("imu",), _DEL), r"g\.toml: missing the \[imu\] table"),
    (_mut(("imu", "name"), _DEL), r"\[imu\] name: missing or not a non-empty string"),
    (_mut(("imu", "vendor"), "x"), r"\[imu\]: unknown key 'vendor'"),
    (_mut(("imu", "rate"), "100 m"), r"\[imu\] rate: '100 m' is not a frequency"),
    (_mut(("imu", "rate"), "0 Hz"), r"\[imu\] rate: '0 Hz' must be positive"),
    (_mut(("gyro", "drift"), "1 deg/h"), r"\[gyro\]: unknown key 'drift'"),
    (_mut(("gyro", "bias"), "1 mg"), r"gyro\.bias: '1 mg' is not an angular rate"),
    (_mut(("gyro", "bias"), ["1 deg/h", "1 deg/h"]), r"gyro\.bias: expected 3 values, got 2"),
    (_mut(("gyro", "bias"), "-1 deg/h"), r"gyro\.bias: '-1 deg/h' is negative"),
    (_mut(("gyro", "bias_instability_tau"), "0 s"), r"gyro\.bias_instability_tau: '0 s' must be positive"),
    (_mut(("gyro", "bias_instability_tau"), _DEL), r"\[gyro\]: give 'bias_instability' together with"),
    (_mut(("gyro", "bias_instability"), _DEL), r"\[gyro\]: give 'bias_instability' together with"),
    (_mut(("gyro", "angle_random_walk"), ["1 deg/sqrt(h)"]), r"angle_random_walk: expected one value"),
    (_mut(("gyro", "source", "scale_factor"), "x"), r"\[gyro\.source\]: unknown key 'scale_factor'"),
    (_mut(("gyro", "source", "bias"), 3), r"gyro\.source\.bias: 3 is not a string"),
    (_mut(("accel", "misalignment"), ["1 mrad"] * 3), r"accel\.misalignment: expected 6 values, got 3"),
    (_mut(("accel", "range"), "0 g"), r"accel\.range: '0 g' must be positive"),
    (_mut(("accel", "quantization"), "1 mm/s/s"), r"accel\.quantization: '1 mm/s/s' is not a velocity"),
])
def test_grade_file_errors(decl, match):
    imu_grade_from_dict(BASE, path="g.toml")   # the base is valid
    with pytest.raises(ModelFileError, match=match):
        imu_grade_from_dict(decl, path="g.toml")


def test_grade_loader_errors(tmp_path):
    with pytest.raises(ModelFileError, match=r"no_such: no such IMU grade \(looked in .*imu; known: .*kimu"):
        load_imu_grade("no_such")
    bad = tmp_path / "bad.toml"
    bad.write_text("[imu\nname = 1")
    with pytest.raises(ModelFileError, match=r"bad\.toml: TOML syntax error"):
        load_imu_grade(str(bad))
    with pytest.raises(ModelFileError, match=r"no such IMU grade"):
        load_imu_grade(str(tmp_path / "missing.toml"))


def test_compiled_path_kernels_equal_numpy_interpolation():
    """_mean_path_apply and _path_difference_add equal the numpy interpolation they replaced (issue 13)."""
    from covtool.validation.sensor_errors import _mean_path_apply, _path_difference_add

    rng = np.random.default_rng(8)
    M, K, J, nd = 3, 57, 9, 4
    nx = rng.normal(size=(M, J + 2, nd))[:, 1:-1]                  # a non-contiguous node array, as in use
    nt = np.sort(rng.uniform(0, 1, J))
    te = np.linspace(nt[0], nt[-1], K + 1)
    j = np.clip(np.searchsorted(nt, te, side="right") - 1, 0, J - 2)
    u = (te - nt[j]) / (nt[j + 1] - nt[j])
    path = nx[:, j] + u[None, :, None] * (nx[:, j + 1] - nx[:, j])  # (M, K+1, nd): the numpy reference
    cols = np.array([3, 0, 2], np.int64)
    for S in (rng.normal(size=(1, K, 3, 3)), rng.normal(size=(M, K, 3, 3))):
        acc = np.ones((M, K, 3))
        _mean_path_apply(nx, j.astype(np.int64), u, np.ascontiguousarray(S), cols, acc)
        xbar = 0.5 * (path[:, 1:] + path[:, :-1])[:, :, cols]
        ref = 1.0 + np.einsum("vkij,mkj->mki" if S.shape[0] == 1 else "mkij,mkj->mki", S, xbar)
        np.testing.assert_allclose(acc, ref, rtol=1e-13, atol=1e-13)
    out = np.zeros((M, K, 3))
    _path_difference_add(nx, j.astype(np.int64), u, cols, out)
    np.testing.assert_allclose(out, path[:, 1:, cols] - path[:, :-1, cols], rtol=1e-13, atol=1e-13)
    single = nx[:, :1]                                               # one node: constant path, zero differences
    out = np.zeros((M, K, 3))
    _path_difference_add(single, np.zeros(K + 1, np.int64), np.zeros(K + 1), cols, out)
    assert not out.any()


def test_compiled_noise_kernels_equal_numpy_draws():
    """_add_white and _process_steps draw the stream numpy would and give its numbers, bit for bit."""
    from covtool.validation.sensor_errors import _add_white, _process_steps

    M, K, J, nd = 4, 301, 7, 5
    base = np.random.default_rng(1).normal(size=(M, K, 3))
    a, b = np.random.default_rng(9), np.random.default_rng(9)
    got = base.copy()
    _add_white(got, 3e-7, a)
    assert np.array_equal(got, base + 3e-7 * b.standard_normal((M, K, 3)))
    x = np.random.default_rng(2).normal(size=(M, nd))
    ca, cb = np.random.default_rng(3).uniform(0.5, 1.0, (J, nd)), np.random.default_rng(4).uniform(0, 1e-3, (J, nd))
    out = np.empty((M, J, nd))
    _process_steps(x, ca, cb, a, True, out)
    w = b.standard_normal((J, M, nd))
    ref, cur = np.empty_like(out), x
    for j in range(J):
        cur = ca[j] * cur + cb[j] * w[j]
        ref[:, j] = cur
    assert np.array_equal(out, ref)
    assert a.bit_generator.state == b.bit_generator.state       # the same draws, no more
    _process_steps(x, ca, cb, a, False, out)                     # no noise: the mean decay, nothing drawn
    cur = x
    for j in range(J):
        cur = ca[j] * cur
    assert np.array_equal(out[:, -1], cur)
    assert a.bit_generator.state == b.bit_generator.state


def test_fill_cache_samples_what_a_pass_of_records_samples():
    """fill_cache fills truth_cache as a pass of records() does (keys and values), injecting nothing
    (noise-free errors draw nothing); a simulator with errors on the filled cache gives the records
    of one without it, bit for bit."""
    truth = load_model_by_name("sdins58")
    traj = land_vehicle()
    x0 = sample_states(truth, 3, 1, q0=traj.sample([0.0]).q_nb[0])

    def sim(rng, cache, noise=True):
        return ImuSimulator(traj, 100.0, t0=0.0, duration=24.0, truth_cache=cache,
                            errors=SensorErrors(truth, x0, rng, noise=noise, process_dt=0.1))

    by_pass, filled = {}, {}
    for _ in sim(5, by_pass).records(chunk=600):
        pass
    rng = np.random.default_rng(5)
    state = rng.bit_generator.state
    sim(rng, filled, noise=False).fill_cache(chunk=600)
    assert rng.bit_generator.state == state
    assert set(filled) == set(by_pass) and len(filled) > 8       # increments, attitude and speed look-ups
    for key, v in by_pass.items():
        w = filled[key]
        assert all(np.array_equal(a, b) for a, b in zip(v, w)) if isinstance(v, tuple) else np.array_equal(v, w)
    for a, b in zip(sim(7, filled).records(chunk=600), sim(7, None).records(chunk=600)):
        assert np.array_equal(a.dtheta, b.dtheta) and np.array_equal(a.dv, b.dv)
    with pytest.raises(ValueError, match="fill_cache needs a truth_cache"):
        sim(7, None).fill_cache()
