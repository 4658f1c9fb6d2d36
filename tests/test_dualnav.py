"""Tests of the dual-IMU verification (seed 001 method II, issue 6).

Oracles:

* the navigation equations themselves for the flight profile (as in
  tests/test_trajectory.py), also inside the vibration interval;
* closed forms: levelling (tilt = accelerometer error / g), the BCH term of
  the attitude difference, the Gaussian moments of a quadratic form, the
  Van Loan exponential;
* linear-Gaussian data drawn from the difference model itself: the
  innovations are then exactly white with covariance S (NIS ~ χ²(m)), the
  fault estimate is unbiased with the predicted σ, and feedback of the
  navigation estimates leaves the innovations unchanged;
* end to end on a short flight with the nonlinear strapdown: the false-alarm
  rate stays at its design, an injected g-sensitive scale factor is detected,
  identified and estimated within 20 %, gaps are bridged and reported;
* every raise with pytest.raises(match=...).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import math

import numpy as np
import pytest

from covtool.nav import earth
from covtool.nav import attitude as quat
from covtool.dualnav.gaps import BridgedLog, CLOCK_PPM_TOL, bridge_gaps, clock_rate, find_gaps
from covtool.validation.sensor_errors import GSensitiveErrors
from covtool.dualnav.difference import (ImuLinearization, discretize_difference, difference_model,
                                        nav_difference)
from covtool.dualnav.monitor import Whitener, flagged_intervals, gsens_estimates, innovations, window_test
from covtool.dualnav.alignment import small_angle, alignment_jacobian, alignment_second_order, triad_alignment
from covtool.dualnav.run import ppm_text, run_dual
from covtool.nav import strapdown as sd
from covtool.lincov.discretize import van_loan
from covtool.lincov.dynamics import Context, error_dynamics
from covtool.errors import InputError, StudyFileError, TrajectoryError
from covtool.nav.trajectory.flight import (FlightProfile, Segment, VibrationInterval, VibrationTone, flight,
                                           quadrature_nodes)
from covtool.io.flight import flight_from_config, high_dynamics_flight
from covtool.nav.imu.simulator import ImuSimulator, ideal_increments
from covtool.validation.sensor_errors import SensorErrors
from covtool.io.imu_grade import load_imu_grade
from covtool.studies import run_study
from covtool.studies.dual_imu_config import gsens_coefficient, parse_study
from covtool.units import PPM_G
from covtool.studies.dual_imu import make_setup, simulate_logs

G = 9.80665
INITIAL = {"lat": "36 deg", "lon": "127 deg", "h": "50 m", "heading": "30 deg", "pitch": "10 deg"}

#: a 25 s flight: launcher stand, boost with a heading change, banked turn, vibration, sustain with a turn
SHORT = {
    "initial": INITIAL,
    "segment": [
        {"kind": "stand", "duration": "6 s"},
        {"kind": "fly", "duration": "4 s", "to_speed": "300 m/s", "turn": "20 deg", "transition": "1 s"},
        {"kind": "fly", "duration": "2 s", "to_pitch": "0 deg", "to_roll": "60 deg", "transition": "0.5 s"},
        {"kind": "fly", "duration": "4 s", "turn": "40 deg", "transition": "1 s"},
        {"kind": "fly", "duration": "2 s", "to_roll": "0 deg", "transition": "0.5 s"},
        {"kind": "fly", "duration": "4 s", "to_speed": "400 m/s", "turn": "-30 deg", "transition": "1 s"},
        {"kind": "fly", "duration": "3 s"},
    ],
    "vibration": {"start": "19 s", "duration": "3 s", "ramp": "0.5 s", "tone": [
        {"kind": "angular", "axis": "x", "amplitude": "0.2 mrad", "frequency": "17 Hz"},
        {"kind": "linear", "axis": "z", "amplitude": "1 g", "frequency": "23 Hz"}]},
}


def short_decl(runs=30, fault_runs=8, gaps=True):
    decl = {
        "study": {"kind": "dual_imu", "name": "short_dual"},
        "trajectory": copy.deepcopy(SHORT),
        "imu": {"kimu": {"mounting": ["2 deg", "-1.5 deg", "3 deg"]}},
        "alignment": {"duration": "5 s", "lat": "36 deg", "lon": "127 deg", "h": "50 m", "heading": "30 deg"},
        "monitor": {"window": "5 s"},
        "simulation": {"runs": runs, "fault_runs": fault_runs, "batch": 50, "seed": 3,
                       "fault": {"gyro": "z", "accel": "x", "coefficient": "3000 ppm/g"}},
    }
    if gaps:
        decl["simulation"]["gap"] = [{"imu": "kimu", "start": "8 s", "duration": "20 ms"},
                                     {"imu": "main", "start": "13 s", "duration": "30 ms"}]
    return decl


@pytest.fixture(scope="module")
def hdf():
    return high_dynamics_flight()


@pytest.fixture(scope="module")
def short_study():
    return run_study(short_decl())


def test_flight_latitude_iteration_never_stops_unconverged(monkeypatch):
    """The Picard iteration of the latitude raises when it has not converged, naming the flight."""
    import covtool.nav.trajectory.flight as fl

    monkeypatch.setattr(fl, "_PICARD_MAX", 1)
    with pytest.raises(TrajectoryError, match=r"^f: the latitude did not converge in 1 Picard iterations "
                                              r"\(last change [0-9.e+-]+ rad, round-off [0-9.e+-]+ rad\)"):
        FlightProfile([Segment("fly", 20.0, to_speed=300.0)], lat=0.6, lon=2.2, h=50.0, where="f")


def test_flight_past_the_pole_is_refused():
    """A flight whose latitude leaves ±89.9 deg is refused with the time (the NED frame is singular there)."""
    with pytest.raises(TrajectoryError, match=r"^f: the flight reaches latitude 89\.9\d* deg near t = \d"):
        FlightProfile([Segment("fly", 10.0, to_speed=300.0), Segment("fly", 300.0)], lat=math.radians(89.7),
                      lon=0.0, h=50.0, where="f")


def test_flight_meridian_arc_against_quadrature():
    """A due-north cruise at 250 m/s for 20 min: the meridian arc ∫(R_M(φ) + h) dφ flown equals v Δt.

    The arc is integrated by ``scipy.integrate.quad`` between the profile's
    latitudes at two cruise times (independent of its Picard iteration);
    agreement to 1e-9 of the 300 km flown (0.3 mm).
    """
    from scipy.integrate import quad

    v, h = 250.0, 50.0
    traj = flight([Segment("fly", 10.0, to_speed=v), Segment("fly", 1200.0)], lat=0.6, lon=2.2, h=h, dt=1.0)
    a, b = traj.sample(np.array([20.0, 1210.0])).lat
    arc = quad(lambda phi: earth.radii(phi)[0] + h, a, b, epsabs=0.0, epsrel=1e-13)[0]
    assert abs(arc - v * 1190.0) <= 1e-9 * v * 1190.0


# --------------------------------------------------------------------------
# the flight profile
# --------------------------------------------------------------------------


def _five_point(traj, t, h, get):
    s = [get(traj.sample(t + k * h)) for k in (-2, -1, 1, 2)]
    return (s[0] - 8.0 * s[1] + 8.0 * s[2] - s[3]) / (12.0 * h)


@pytest.mark.parametrize("span, h, tol", [
    # outside the vibration: truncation ~1e-7 m/s, ~1e-6 m/s², ~1e-7 1/s at h = 5 ms (roll at 144 deg/s)
    ((1.0, 32.5), 0.005, (1e-6, 2e-6, 2e-7)),
    ((43.5, 66.0), 0.005, (1e-6, 2e-6, 2e-7)),
    # inside the 13–31 Hz vibration: h = 0.1 ms, round-off ~2e-5 m/s in position
    ((33.5, 42.5), 1e-4, (5e-5, 1e-7, 1e-10)),
])
def test_flight_navigation_equations_hold(hdf, span, h, tol):
    """Position, velocity and quaternion rates satisfy the nav equations.

    Fourth-order central differences of the profile's own position,
    velocity and attitude against ``earth.position_rates``, seed 002 eq (4)
    unperturbed with the produced f_b, and ``q̇ = ½ q⊗ω_ib − ½ ω_in⊗q``.
    Leaving out the Coriolis term would give ~0.1 m/s² at 650 m/s, the
    transport rate ~0.07 m/s², the Earth rate in ω_ib ~7e-5 1/s.
    """
    rng = np.random.default_rng(7)
    t = np.sort(rng.uniform(*span, 400))
    br = hdf._source.breakpoints
    t = t[np.min(np.abs(t[:, None] - br[None, :]), axis=1) > 2.5 * h]
    assert t.size > 300
    c = hdf.sample(t)
    dp = np.column_stack([_five_point(hdf, t, h, lambda s: s.lat), _five_point(hdf, t, h, lambda s: s.lon),
                          _five_point(hdf, t, h, lambda s: s.h)])
    e = dp - earth.position_rates(c.lat, c.h, c.v_n)
    rm, rn = earth.radii(c.lat)
    e_m = np.column_stack([e[:, 0] * (rm + c.h), e[:, 1] * (rn + c.h) * np.cos(c.lat), e[:, 2]])
    assert np.abs(e_m).max() < tol[0]
    f_n = np.einsum("kij,kj->ki", quat.dcm(c.q_nb), c.f_b)
    e_v = _five_point(hdf, t, h, lambda s: s.v_n) - earth.velocity_rate(c.lat, c.h, c.v_n, f_n)
    assert np.abs(e_v).max() < tol[1]
    w_in = earth.earth_rate_n(c.lat) + earth.transport_rate_n(c.lat, c.h, c.v_n)
    z = np.zeros((t.size, 1))
    qdot = 0.5 * quat.mul(c.q_nb, np.hstack([z, c.w_ib_b])) - 0.5 * quat.mul(np.hstack([z, w_in]), c.q_nb)
    assert np.abs(_five_point(hdf, t, h, lambda s: s.q_nb) - qdot).max() < tol[2]
    d_dist = _five_point(hdf, t, h, lambda s: s.distance) - np.linalg.norm(c.v_n, axis=1)
    assert np.abs(d_dist).max() < 10 * tol[0]


def test_flight_profile_is_high_dynamics(hdf, capsys):
    s = hdf.sample(np.linspace(0.0, 67.0, 20001))
    f = np.abs(s.f_b).max(axis=0) / G
    w = np.degrees(np.abs(s.w_ib_b).max(axis=0))
    speed = np.linalg.norm(s.v_n, axis=1)
    with capsys.disabled():
        print(f"\nflight: max |f| {np.round(f, 1)} g, max |ω| {np.round(w, 1)} deg/s, "
              f"top speed {speed.max():.0f} m/s, {s.distance[-1] / 1e3:.1f} km")
    assert f[0] > 10.0                        # the boost, along the body x axis
    assert max(f[1], f[2]) > 12.0             # the banked turn
    assert w[0] > 100.0                       # the full roll
    assert hdf.stationary == ((0.0, 12.0),)
    np.testing.assert_allclose(s.v_n[s.t < 12.0], 0.0, atol=1e-12)
    assert speed[-1] == pytest.approx(760.0)
    # exactly the start attitude on the launcher (roll 0, pitch 10 deg, heading 45 deg)
    np.testing.assert_allclose(np.degrees(hdf.euler()[0]), [0.0, 10.0, 45.0], atol=1e-12)
    assert hdf._source.max_frequency == 31.0
    assert quadrature_nodes(hdf, 100.0) > quadrature_nodes(hdf, 400.0) >= 3
    assert quadrature_nodes(high_dynamics_flight(vibration=False), 100.0) == 3


def test_flight_vibration_is_zero_mean_and_bounded(hdf):
    """The vibration adds the declared amplitudes and leaves the mean motion."""
    quiet = high_dynamics_flight(vibration=False)
    t = np.linspace(35.0, 41.0, 6001)
    a, b = hdf.sample(t), quiet.sample(t)
    dang = quat.to_rotvec(quat.mul(quat.conj(b.q_nb), a.q_nb))
    assert np.abs(dang).max() == pytest.approx(np.sqrt(0.2**2 + 0.15**2 + 0.1**2) * 1e-3, rel=0.3)
    df = a.f_b - b.f_b
    assert np.abs(df[:, 0]).max() == pytest.approx(G, rel=0.1)          # the 1 g tone along x
    assert abs(df[:, 0].mean()) < 0.05 * G
    np.testing.assert_allclose(a.lat, b.lat, atol=1e-9)                 # mm-level displacement


@pytest.mark.parametrize("cfg, match", [
    ({"builtin": "nope"}, r"f: builtin: unknown flight profile 'nope'"),
    ({"builtin": "high_dynamics_flight", "segment": []}, r"'builtin' takes only 'vibration' and 'name'"),
    ({"builtin": "high_dynamics_flight", "vibration": "yes"}, r"f: vibration: 'yes' is not true or false"),
    ({"builtin": "high_dynamics_flight", "name": 3}, r"f: name: 3 is not a string"),
    ({"segment": []}, r"f: missing required key 'initial'"),
    ({"initial": INITIAL, "segment": [], "wind": 1}, r"f: unknown key 'wind'"),
    ({"initial": {"lat": "1 deg", "lon": "1 deg"}, "segment": [{"kind": "stand", "duration": "1 s"}]},
     r"f: initial: missing required key 'h'"),
    ({"initial": {**INITIAL, "roll": "1 deg"}, "segment": []}, r"f: initial: unknown key 'roll'"),
    ({"initial": {**INITIAL, "lat": "1 m"}, "segment": []}, r"f: initial: lat: '1 m' is not an angle"),
    ({"initial": INITIAL, "segment": []}, r"f: segment: expected a non-empty list"),
    ({"initial": INITIAL, "segment": ["stand"]}, r"f: segment\[0\]: expected a table, got str"),
    ({"initial": INITIAL, "segment": [{"kind": "hover", "duration": "1 s"}]},
     r"f: segment\[0\]: unknown segment kind 'hover'"),
    ({"initial": INITIAL, "segment": [{"kind": "stand"}]}, r"f: segment\[0\] \(stand\): missing required key"),
    ({"initial": INITIAL, "segment": [{"kind": "stand", "duration": "1 s", "turn": "1 deg"}]},
     r"f: segment\[0\] \(stand\): unknown key 'turn'"),
    ({"initial": INITIAL, "segment": [{"kind": "fly", "duration": "1 s", "to_speed": "3 g"}]},
     r"f: segment\[0\] \(fly\): to_speed: '3 g' is not a velocity"),
    ({"initial": INITIAL, "segment": [{"kind": "stand", "duration": "1 s"}], "vibration": 3},
     r"f: vibration: expected a table or a list of tables"),
    ({"initial": INITIAL, "segment": [{"kind": "stand", "duration": "1 s"}], "vibration": {"start": "1 s"}},
     r"f: vibration\[0\]: missing required key 'duration'"),
    ({"initial": INITIAL, "segment": [{"kind": "stand", "duration": "1 s"}],
      "vibration": {"start": "0 s", "duration": "1 s", "tone": []}}, r"f: vibration\[0\]: tone: expected a non-empty"),
    ({"initial": INITIAL, "segment": [{"kind": "stand", "duration": "1 s"}],
      "vibration": {"start": "0 s", "duration": "1 s", "tone": [{"kind": "angular"}]}},
     r"f: vibration\[0\]: tone\[0\]: missing required key 'axis'"),
    ({"initial": INITIAL, "segment": [{"kind": "stand", "duration": "1 s"}],
      "vibration": {"start": "0 s", "duration": "1 s",
                    "tone": [{"kind": "twist", "axis": "x", "amplitude": "1 g", "frequency": "1 Hz"}]}},
     r"f: vibration\[0\]: tone\[0\]: kind: 'twist' is not 'angular' or 'linear'"),
    ({"initial": INITIAL, "segment": [{"kind": "stand", "duration": "1 s"}],
      "vibration": {"start": "0 s", "duration": "1 s",
                    "tone": [{"kind": "angular", "axis": "x", "amplitude": "1 g", "frequency": "1 Hz"}]}},
     r"f: vibration\[0\]: tone\[0\]: amplitude: '1 g' is not an angle"),
])
def test_flight_config_errors(cfg, match):
    with pytest.raises(TrajectoryError, match=match):
        flight_from_config(cfg, where="f", dt=0.1)


FLY = Segment("fly", 2.0, to_speed=100.0)


@pytest.mark.parametrize("kw, match", [
    (dict(segments=[FLY], lat=math.radians(89.95)), r"f: initial: lat: 89\.95 deg is not within ±89\.9 deg"),
    (dict(segments=[FLY], h=2e5), r"f: initial: h: 200000 m is outside"),
    (dict(segments=[FLY], pitch=math.radians(85)), r"f: initial: pitch: 85 deg is not within ±80 deg"),
    (dict(segments=[]), r"f: segment: expected a non-empty list of segments"),
    (dict(segments=[Segment("stand", 0.0)]), r"f: segment\[0\] \(stand\): duration: must be positive, got 0 s"),
    (dict(segments=[FLY, Segment("stand", 1.0)]), r"f: segment\[1\] \(stand\): the vehicle is moving"),
    (dict(segments=[Segment("fly", 1.0, to_speed=10.0, transition=0.0)]),
     r"f: segment\[0\] \(fly\): transition: must be positive"),
    (dict(segments=[Segment("fly", 1.0, turn=1.0)]), r"f: segment\[0\] \(fly\): flying at zero speed"),
    (dict(segments=[FLY, Segment("fly", 1.0, to_speed=-1.0)]), r"f: segment\[1\] \(fly\): to_speed: -1 m/s"),
    (dict(segments=[FLY, Segment("fly", 1.0, to_pitch=math.radians(85))]),
     r"f: segment\[1\] \(fly\): to_pitch: 85 deg is not within ±80 deg"),
    (dict(segments=[Segment("glide", 1.0)]), r"f: segment\[0\] \(glide\): unknown segment kind 'glide'"),
    (dict(segments=[FLY], vibration=[VibrationInterval(0.5, 1.0, 0.6, ())]),
     r"f: vibration\[0\]: needs duration > 0 and 0 < ramp <= duration/2"),
    (dict(segments=[FLY], vibration=[VibrationInterval(1.5, 1.0, 0.1, ())]),
     r"f: vibration\[0\]: \[1\.5, 2\.5\] s is outside the flight \[0, 2\] s"),
    (dict(segments=[Segment("stand", 1.0), FLY], vibration=[VibrationInterval(0.5, 1.0, 0.1, ())]),
     r"f: vibration\[0\]: overlaps a stand segment"),
    (dict(segments=[FLY], vibration=[VibrationInterval(0.1, 1.0, 0.1, ()), VibrationInterval(0.5, 1.0, 0.1, ())]),
     r"f: vibration\[1\]: overlaps the previous vibration interval"),
    (dict(segments=[FLY], vibration=[VibrationInterval(0.1, 1.0, 0.1, (VibrationTone("spin", "x", 1.0, 1.0),))]),
     r"f: vibration\[0\]: tone\[0\]: kind 'spin' is not 'angular' or 'linear'"),
    (dict(segments=[FLY], vibration=[VibrationInterval(0.1, 1.0, 0.1, (VibrationTone("linear", "w", 1.0, 1.0),))]),
     r"f: vibration\[0\]: tone\[0\]: axis 'w' is not 'x', 'y' or 'z'"),
    (dict(segments=[FLY], vibration=[VibrationInterval(0.1, 1.0, 0.1, (VibrationTone("linear", "x", 1.0, 0.0),))]),
     r"f: vibration\[0\]: tone\[0\]: frequency 0 Hz must be positive"),
])
def test_flight_profile_errors(kw, match):
    args = dict(lat=0.6, lon=2.2, h=50.0, where="f")
    args.update(kw)
    with pytest.raises(TrajectoryError, match=match):
        FlightProfile(args.pop("segments"), **args)


def test_flight_config_must_be_tables():
    with pytest.raises(TrajectoryError, match=r"f: expected a table, got str"):
        flight_from_config("high_dynamics_flight", where="f", dt=0.1)
    with pytest.raises(TrajectoryError, match=r"f: initial: expected a table, got list"):
        flight_from_config({"initial": [], "segment": []}, where="f", dt=0.1)


def test_flight_dt_error():
    with pytest.raises(TrajectoryError, match=r"f: dt: must be positive, got 0"):
        flight([FLY], lat=0.6, lon=2.2, h=50.0, dt=0.0, where="f")


# --------------------------------------------------------------------------
# alignment, difference, discretisation
# --------------------------------------------------------------------------

MOUNT = quat.from_euler(math.radians(2.0), math.radians(-1.5), math.radians(3.0))


@pytest.mark.parametrize("mount", [None, MOUNT])
def test_triad_alignment_is_exact_without_errors(hdf, mount):
    s = hdf.sample([5.0])
    q_s = s.q_nb[0] if mount is None else quat.mul(s.q_nb[0], mount)
    f_s = quat.dcm(q_s).T @ quat.dcm(s.q_nb[0]) @ s.f_b[0]
    q = triad_alignment(f_s, math.radians(45.0), mount)[0]
    assert np.abs(small_angle(q, q_s)).max() < 1e-12


def test_levelling_closed_form():
    """Level vehicle: φ_N = (C δf)_E / g, φ_E = −(C δf)_N / g, φ_D = −δψ."""
    lat, psi = 0.6, 0.7
    g = earth.gravity(lat, 0.0)
    C = quat.dcm(quat.from_euler(0.0, 0.0, psi))
    f = C.T @ np.array([0.0, 0.0, -g])
    A = alignment_jacobian(f, psi)
    df = np.array([3e-3, -2e-3, 5e-3])
    dfn = C @ df
    np.testing.assert_allclose(A[:, :3] @ df, [dfn[1] / g, -dfn[0] / g, 0.0], atol=1e-12)
    np.testing.assert_allclose(A[:, 3], [0.0, 0.0, -1.0], atol=1e-9)


def test_alignment_second_order_matches_sampling(hdf):
    """Hessian moments of the quadratic residual vs 40 000 nonlinear draws."""
    s = hdf.sample([5.0])
    f, psi = s.f_b[0], math.radians(45.0)
    cov = np.diag([0.05**2, 0.05**2, 0.03**2, 0.002**2])         # 5 mg, 3 mg, 0.1 deg
    mean, C = alignment_second_order(f, psi, None, cov)
    rng = np.random.default_rng(2)
    u = rng.multivariate_normal(np.zeros(4), cov, 40000)
    q0 = triad_alignment(f, psi)[0]
    phi = small_angle(triad_alignment(f + u[:, :3], psi + u[:, 3]), q0)
    r = phi - u @ alignment_jacobian(f, psi).T
    np.testing.assert_allclose(np.sqrt(np.diag(C)), r.std(axis=0), rtol=0.05)
    np.testing.assert_allclose(mean, r.mean(axis=0), atol=3 * r.std(axis=0).max() / 200)


def test_nav_difference_bch_and_mounting():
    """δφ = φ_m − φ_k + ½ φ_m × φ_k; the mounting is compensated exactly."""
    q_b = quat.normalize(np.array([0.8, 0.2, -0.3, 0.4]))
    pm, pk = np.array([4e-3, -3e-3, 2e-3]), np.array([-2e-3, 5e-3, 1e-3])
    qm = quat.mul(quat.from_rotvec(-pm), q_b)
    qk = quat.mul(quat.mul(quat.from_rotvec(-pk), q_b), MOUNT)
    lat, h = 0.6, 100.0

    def hist(q, dlat, v):
        return sd.NavHistory(np.array([0.0]), np.array([[lat + dlat]]), np.array([[2.0]]), np.array([[h]]),
                             np.array([[v]]), q[None, None])

    z = nav_difference(hist(qm, 1e-7, [1.0, 2.0, 3.0]), hist(qk, 0.0, [0.5, 2.0, 3.5]), None, MOUNT)[0, 0]
    rm, _ = earth.radii(lat + 1e-7)
    assert z[0] == pytest.approx(1e-7 * (rm + h))
    np.testing.assert_allclose(z[3:6], [0.5, 0.0, -0.5])
    np.testing.assert_allclose(z[6:], pm - pk + 0.5 * np.cross(pm, pk), atol=2e-8)
    with pytest.raises(ValueError, match="same output times"):
        h2 = hist(qk, 0.0, [0, 0, 0])
        nav_difference(hist(qm, 0, [0, 0, 0]), dataclasses.replace(h2, t=np.array([1.0])))


def test_structured_discretisation_matches_van_loan(hdf):
    s = hdf.sample(np.linspace(12.0, 60.0, 30))
    ctx = Context(s.lat, s.h, s.v_n, s.q_nb, s.f_b, s.w_ib_b)
    model = load_imu_grade("kimu").to_model()
    dyn = error_dynamics(model, ctx)
    Fc = np.zeros((30, model.n, 1))
    Fc[:, 6:10, 0] = 0.5 * quat.Q_matrix(s.q_nb)[:, :, 2] * 50.0
    Phi, Qd, Gam = discretize_difference(dyn.F, dyn.Qc, 0.04, Fc)
    Fa = np.zeros((30, model.n + 1, model.n + 1))
    Fa[:, :model.n, :model.n] = dyn.F
    Fa[:, :model.n, model.n:] = Fc
    Qa = np.zeros_like(Fa)
    Qa[:, :model.n, :model.n] = dyn.Qc
    P2, Q2 = van_loan(Fa, Qa, 0.04)
    # the Markov decay within a step at its mid-value: relative error Δ/(6τ) ~ 7e-5 on those columns
    assert np.abs(Phi - P2[:, :model.n, :model.n]).max() < 1e-4 * np.abs(P2).max()
    np.testing.assert_allclose(Gam, P2[:, :model.n, model.n:], rtol=1e-9, atol=1e-15)
    d = np.sqrt(np.einsum("kii->ki", Q2[:, :model.n, :model.n]))
    for k in range(3, 10):                   # velocity and attitude noise (position is ~1e-3, Van Loan's round-off)
        np.testing.assert_allclose(Qd[:, k, k], Q2[:, k, k], rtol=1e-6)
    assert d.shape == (30, model.n)


def test_gsensitive_injection_formula(hdf):
    model = load_imu_grade("kimu").to_model()
    x0 = np.zeros((1, model.n))
    k = 1000 * PPM_G
    kw = dict(t0=12.0, duration=2.0, nodes=quadrature_nodes(hdf, 400.0))
    plain = ImuSimulator(hdf, 400.0, errors=SensorErrors(model, x0, noise=False), **kw).record()
    fault = ImuSimulator(hdf, 400.0, errors=GSensitiveErrors(model, x0, noise=False, gsens=((2, 0, k),)),
                         **kw).record()
    expect = plain.dtheta[0, :, 2] * (1.0 + k * plain.dv[0, :, 0] / plain.dt)
    np.testing.assert_allclose(fault.dtheta[0, :, 2], expect, rtol=1e-12)
    np.testing.assert_array_equal(fault.dtheta[0, :, :2], plain.dtheta[0, :, :2])
    with pytest.raises(ValueError, match=r"axes must be 0, 1 or 2, got \(3, 0, 0\.1\)"):
        GSensitiveErrors(model, x0, gsens=((3, 0, 0.1),))


# --------------------------------------------------------------------------
# the linear world: data drawn from the difference model itself
# --------------------------------------------------------------------------


def _linear_data(model, M, rng, c=None, feedback=None):
    """Draw X0 ~ P0, X_{j+1} = Φ X_j + w_j (+ Γ c), z = H X + v."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _draw(model, M, rng, c, feedback)


def _draw(model, M, rng, c, feedback):
    def chol(P):
        w, V = np.linalg.eigh(0.5 * (P + P.T))
        return V * np.sqrt(np.clip(w, 0.0, None))

    J1 = model.t.size
    X = rng.standard_normal((M, model.n)) @ chol(model.P0).T
    z = np.empty((M, J1, model.m))
    Lr = chol(model.R)
    noise = [rng.standard_normal((M, model.n)) @ chol(model.Qd[j]).T for j in range(J1 - 1)]
    meas = [rng.standard_normal((M, model.m)) @ Lr.T for j in range(J1)]
    for j in range(J1):
        z[:, j] = X @ model.H[j].T + meas[j]
        if feedback is not None:                 # correct the truth by the filter's estimates
            feedback.update(j, z[:, j])
            dm, dk = feedback.take_navigation()
            X[:, :10] -= dm
            X[:, model.n_main:model.n_main + 10] -= dk
            if j < J1 - 1:
                feedback.predict(j)
        if j < J1 - 1:
            X = X @ model.Phi[j].T + noise[j]
            if c is not None:
                X = X + model.Gamma[j] @ c
    return z


@pytest.fixture(scope="module")
def linear_model(short_study):
    m = short_study.fault_free[0].model
    return dataclasses.replace(m, Hphi=None)     # the linear world has no second-order term


def test_innovations_are_white_chi2(linear_model):
    m = linear_model
    z = _linear_data(m, 400, np.random.default_rng(11))
    inn = innovations(m, z)
    # NIS ~ χ²(m) independent: the mean of 400×J values has sd sqrt(2m/N)
    N = inn.nis.size
    assert abs(inn.nis.mean() - m.m) < 4 * math.sqrt(2 * m.m / N)
    L = np.linalg.cholesky(inn.S)
    w = np.einsum("jab,Mjb->Mja", np.linalg.inv(L), inn.nu)
    assert abs(w.var() - 1.0) < 0.05
    lag1 = np.mean(w[:, 1:] * w[:, :-1])
    assert abs(lag1) < 4 / math.sqrt(w[:, 1:].size)
    stat, thr, flagged = window_test(inn.nis, m.m, 5, 0.05)
    assert flagged.any(axis=1).mean() <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / 400)


def test_feedback_leaves_innovations_unchanged(linear_model):
    """Correcting the errors by the estimates (seed 002 eq (10)) changes nothing linear."""
    m = linear_model
    z_open = _linear_data(m, 20, np.random.default_rng(5))
    w = Whitener(m, 20)
    _linear_data(m, 20, np.random.default_rng(5), feedback=w)   # the Whitener runs inside, one BLAS thread
    closed = w.result()
    open_ = innovations(m, z_open)
    scale = np.sqrt(np.einsum("jii->ji", open_.S))
    np.testing.assert_allclose(closed.nu / scale, open_.nu / scale, atol=1e-6)


def test_gls_estimate_is_unbiased_with_predicted_sigma(linear_model):
    m = linear_model
    k = m.candidates.index((2, 0))
    c = np.zeros(len(m.candidates))
    c[k] = 3000 * PPM_G
    z = _linear_data(m, 300, np.random.default_rng(8), c=c)
    est = gsens_estimates(innovations(m, z), m.candidates, 0.01)
    e = (est.estimate[:, k] - c[k]) / est.sigma[k]
    assert abs(e.mean()) < 4 / math.sqrt(300)
    assert e.std() == pytest.approx(1.0, abs=0.15)
    assert est.detected.all() and (est.identified == k).all()


# --------------------------------------------------------------------------
# end to end on the short flight (nonlinear strapdown, seed 001 Table 2 grades)
# --------------------------------------------------------------------------


def test_short_flight_acceptance(short_study, capsys):
    """Acceptance 3 on a short flight: no excess false alarms; the fault is found and estimated."""
    s = short_study.summary.set_index("item")["value"]
    free = short_study.tables["fault_free_runs"]
    fault = short_study.tables["fault_runs"]
    with capsys.disabled():
        print(f"\nshort flight: false alarms {int(free['window alarm'].sum())}/{len(free)} (window), "
              f"{int(free['g-sensitivity detected'].sum())}/{len(free)} (GLR); mean NIS {s['mean NIS per epoch']:.2f}"
              f"; estimates {np.round(fault['estimate [ppm/g]'].to_numpy())} ppm/g (true 3000)")
    assert len(free) == 30 and len(fault) == 8
    assert s["mean NIS per epoch"] == pytest.approx(6.0, abs=0.5)
    assert (free["window alarm"] | free["g-sensitivity detected"]).sum() <= 2      # design 2 × 1 % per flight
    assert fault["correctly identified"].all()
    assert fault["window alarm"].all()
    assert np.abs(fault["error [%]"]).max() < 20.0
    sig = fault["1sigma [ppm/g]"].iloc[0]
    assert np.abs(fault["estimate [ppm/g]"] - 3000).max() < 4 * sig


def test_short_flight_gaps_are_reported(short_study):
    """Acceptance 4: every bridged interval, with its predicted and actual error."""
    gaps = short_study.tables["gaps"]
    assert list(gaps["imu"]) == ["main", "kimu"]
    assert list(gaps["samples bridged"]) == [3, 8]
    np.testing.assert_allclose(gaps["after [s]"], [13.0, 8.0])
    np.testing.assert_allclose(gaps["before [s]"], [13.04, 8.0225])
    for ax in "xyz":
        pred, act = gaps[f"predicted att {ax} [urad]"], gaps[f"actual RMS att {ax} [urad]"]
        assert (act < 5 * pred).all()
    assert short_study.summary.set_index("item").loc["bridged gaps", "value"] == 2


def test_study_writes_outputs(short_study, tmp_path):
    from covtool.io.writers import write_outputs

    files = write_outputs(short_study, tmp_path / "out", figures=True)
    names = {p.name for p in files}
    assert {"summary.csv", "gaps.csv", "fault_runs.csv", "fault_free_runs.csv", "history.csv",
            "difference_envelope.png", "window_test.png", "gsens_estimates.png", "short_dual.xlsx"} <= names


# --------------------------------------------------------------------------
# gaps
# --------------------------------------------------------------------------


def test_bridging_policies_on_linear_rates():
    h = 0.01
    t = h * np.arange(1, 201)
    rate = np.column_stack([0.1 + 0.5 * t, -0.2 + 0.0 * t, 0.3 * t])
    x = rate * h                                   # increments of a linearly varying rate (mid-point exact)
    keep = np.ones(200, bool)
    keep[100:106] = False
    for policy, expect_exact in (("interpolate", True), ("hold", False), ("propagate", False)):
        b = bridge_gaps(t[keep], x[keep], x[keep], h, policy, imu="kimu", window=5)
        np.testing.assert_allclose(b.t, t, atol=1e-12)
        assert b.bridged.sum() == 6 and b.bridged[100:106].all()
        err = b.dtheta[100:106].sum(axis=0) - x[100:106].sum(axis=0)
        (rep,) = b.gaps
        assert (rep.imu, rep.samples, rep.policy) == ("kimu", 6, policy)
        assert rep.after == pytest.approx(t[99]) and rep.before == pytest.approx(t[106])
        if expect_exact:
            np.testing.assert_allclose(err, 0.0, atol=1e-15)
        else:
            # hold and propagate lag the ramp: ~ n (n/2 + offset) h² × slope, and the trials see the same
            assert np.abs(err[0]) > 1e-5
            assert rep.sigma_attitude[0] == pytest.approx(abs(err[0]), rel=0.5)


def test_gap_prediction_covers_white_noise():
    """Noise only: the trial bridges predict the actual bridging error statistically."""
    rng = np.random.default_rng(4)
    h, M = 0.0025, 200
    t = h * np.arange(1, 4001)
    x = 1e-5 * rng.standard_normal((M, 4000, 3))
    keep = np.ones(4000, bool)
    keep[2000:2016] = False
    b = bridge_gaps(t[keep], x[:, keep], x[:, keep], h, "interpolate", window=10, arw=1e-5 / math.sqrt(h))
    (rep,) = b.gaps
    actual = np.sqrt(np.mean((b.dtheta[:, 2000:2016].sum(axis=1) - x[:, 2000:2016].sum(axis=1)) ** 2, axis=0))
    np.testing.assert_allclose(rep.sigma_attitude, actual, rtol=0.25)
    assert rep.trials == 2 * 8 * M
    assert (rep.sigma_attitude >= 1e-5 * math.sqrt(16) * 0.99).all()     # at least the lost white noise


def test_gap_errors():
    t = 0.01 * np.arange(1, 31)
    x = np.zeros((30, 3))
    keep = np.ones(30, bool)
    keep[10:12] = False
    with pytest.raises(InputError, match=r"log: gap policy: 'guess' is not one of hold, interpolate"):
        bridge_gaps(t, x, x, 0.01, "guess", where="log")
    with pytest.raises(InputError, match=r"log: column 't \[s\]': 2 samples missing between t = 0\.1 s and 0\.13 s "
                                         r"\(gap policy 'refuse'\); 1 gap\(s\) in all"):
        bridge_gaps(t[keep], x[keep], x[keep], 0.01, "refuse", where="log")
    with pytest.raises(InputError, match=r"log: column 't \[s\]': gap of 2 samples after t = 0\.1 s: fewer than 20 "
                                         r"valid samples on each side"):
        bridge_gaps(t[keep], x[keep], x[keep], 0.01, "interpolate", window=20, where="log")
    tj = t.copy()
    tj[5] += 0.004
    with pytest.raises(InputError, match=r"log: column 't \[s\]': row 6: step 0\.014 s after t = 0\.05 s is not a "
                                         r"whole number of sample periods"):
        find_gaps(tj, 0.01, "log")
    assert find_gaps(t[keep], 0.01) == [(9, 2)]
    b = bridge_gaps(t, x, x, 0.01, "refuse")
    assert b.gaps == [] and not b.bridged.any()


# --------------------------------------------------------------------------
# numeric errors
# --------------------------------------------------------------------------


def test_monitor_errors(linear_model):
    m = linear_model
    with pytest.raises(ValueError, match=r"window of 99 epochs does not fit 20 epochs"):
        window_test(np.zeros((1, 20)), 6, 99, 0.01)
    with pytest.raises(ValueError, match=r"false-alarm probability must be in \(0, 1\), got 1\.5"):
        window_test(np.zeros((1, 20)), 6, 5, 1.5)
    inn = innovations(m, np.zeros((m.t.size, m.m)))
    with pytest.raises(ValueError, match="no g-sensitivity candidates"):
        gsens_estimates(inn, (), 0.01)
    with pytest.raises(ValueError, match=r"false-alarm probability must be in \(0, 1\), got 0"):
        gsens_estimates(inn, m.candidates, 0.0)
    dead = dataclasses.replace(inn, rho=np.zeros_like(inn.rho))
    with pytest.raises(ValueError, match=r"candidates x/x, .* have no signature in this flight"):
        gsens_estimates(dead, m.candidates, 0.01)
    soft = gsens_estimates(dead, m.candidates, 0.01, strict=False)
    assert np.isnan(soft.estimate).all() and np.isinf(soft.sigma).all() and not soft.detected.any()
    with pytest.raises(ValueError, match=r"z must have shape \(M, 21, 6\), got \(1, 3, 6\)"):
        innovations(m, np.zeros((3, 6)))
    assert flagged_intervals(np.array([False, True, True, False, True]), np.arange(10.0), 3) == [(1.0, 6.0)]


def _static_log(rate, seconds, t0=0.0):
    from covtool.nav.trajectory.profiles import static

    traj = static(seconds + 1.0, lat=0.6, lon=2.2, h=50.0, heading=0.5, dt=1.0)
    rec = ideal_increments(traj, rate, t0=t0, duration=seconds)
    return BridgedLog(rec.t, rec.dtheta, rec.dv, rec.dt, [], np.zeros(rec.t.size, bool))


@pytest.fixture(scope="module")
def setup_static():
    decl = short_decl(0, 0, gaps=False)
    del decl["simulation"]["fault"]
    decl["imu"] = {}                                         # the static logs have no mounting rotation
    cfg = parse_study(decl, "s")
    return make_setup(cfg, {"lat": 0.6, "lon": 2.2, "h": 50.0, "heading": 0.5}, "s")


def test_run_dual_errors(setup_static):
    setup = setup_static
    main, kimu = _static_log(100.0, 20.0), _static_log(400.0, 20.0)
    r = run_dual(main, kimu, setup)                      # at rest, error-free: the two agree
    assert np.abs(r.z[0, :, 3:6]).max() < 1e-9 and np.abs(r.z[0, :, 6:]).max() < 1e-9
    assert r.unused == {"main": (0, 0), "kimu": (0, 0)}
    # a KIMU log that starts 0.5 s late and a main log 0.37 s longer: the unused samples are counted
    r = run_dual(_static_log(100.0, 20.37), _static_log(400.0, 19.5, t0=0.5), setup)
    assert r.t[0] == pytest.approx(5.5) and r.unused == {"main": (50, 87), "kimu": (0, 200)}   # whole epochs end at 19.5 s
    late = dataclasses.replace(kimu, t=kimu.t + 30.0)
    with pytest.raises(InputError, match=r"logs: the main log \[0, 20\] s and the KIMU log \[30, 50\] s share no "
                                         r"main interval"):
        run_dual(main, late, setup)
    with pytest.raises(InputError, match=r"KIMU log: delivers 2 samples per main interval, the study declares a rate "
                                         r"ratio of 4"):
        run_dual(main, _static_log(200.0, 20.0), setup)
    holey = dataclasses.replace(kimu, t=np.delete(kimu.t, 500), dtheta=np.delete(kimu.dtheta, 500, axis=0),
                                dv=np.delete(kimu.dv, 500, axis=0))
    with pytest.raises(InputError, match=r"KIMU log: main interval 125 .* holds 3 samples, expected 4"):
        run_dual(main, holey, setup)
    with pytest.raises(InputError, match=r"alignment time: 5\.005 s is not a whole number of main samples"):
        run_dual(main, kimu, dataclasses.replace(setup, align_time=5.005))
    with pytest.raises(InputError, match=r"logs: 2 s of data after the 5 s alignment is shorter than one comparison "
                                         r"window \(5 s\)"):
        run_dual(_static_log(100.0, 7.0), _static_log(400.0, 7.0), setup)
    with pytest.raises(ValueError, match="compare_every must be a multiple of substep, and substep even"):
        run_dual(main, kimu, dataclasses.replace(setup, substep=3))


def test_difference_model_errors(short_study):
    r = short_study.fault_free[0]
    gm = load_imu_grade("main_imu").to_model()
    ctx = Context(np.zeros(3), np.zeros(3), np.zeros((3, 3)), np.tile([1.0, 0, 0, 0], (3, 1)), np.zeros((3, 3)),
                  np.zeros((3, 3)))
    lin = ImuLinearization(gm, ctx, np.tile([1.0, 0, 0, 0], (3, 4)), ctx, 5.0, 0.0)
    t = np.arange(3.0)
    with pytest.raises(ValueError, match=r"main: context has 3 steps, expected 50"):
        difference_model(lin, lin, t_epochs=t, lat_epochs=t, h_epochs=t, substeps_per_epoch=25, dt_sub=0.04,
                            heading_sigma=0.0)
    with pytest.raises(ValueError, match=r"products must have shape \(3, 3, 3\) for the fault candidates"):
        difference_model(lin, lin, t_epochs=np.arange(2.0), lat_epochs=t, h_epochs=t, substeps_per_epoch=3,
                            dt_sub=0.04, heading_sigma=0.0, candidates=((0, 0),))
    assert r.model.n == 92


# --------------------------------------------------------------------------
# study file, logs and the command line
# --------------------------------------------------------------------------


def _bad(path_keys, value):
    decl = short_decl(1, 1)
    d = decl
    for k in path_keys[:-1]:
        d = d.setdefault(k, {})
    if value is _DELETE:
        del d[path_keys[-1]]
    else:
        d[path_keys[-1]] = value
    return decl


_DELETE = object()


@pytest.mark.parametrize("keys, value, match", [
    (("extra",), 1, r"s: unknown key 'extra'"),
    (("study", "author"), "x", r"s: \[study\]: unknown key 'author'"),
    (("imu", "spare"), {}, r"s: \[imu\]: unknown key 'spare'"),
    (("imu", "main", "ratio"), 4, r"s: \[imu\.main\]: unknown key 'ratio'"),
    (("imu", "main", "grade"), "nope", r"s: \[imu\.main\] grade: nope: no such IMU grade"),
    (("imu", "kimu", "mounting"), ["1 deg"], r"s: \[imu\.kimu\] mounting: expected \[roll, pitch, yaw\]"),
    (("imu", "kimu", "mounting"), ["1 deg", "1 m", "0 deg"], r"s: \[imu\.kimu\] mounting\[1\]: '1 m' is not an angle"),
    (("imu", "kimu", "ratio"), 0, r"s: \[imu\.kimu\] ratio: 0 is not an integer in 1\.\.1000"),
    (("imu", "kimu", "ratio"), 2,
     r"s: \[imu\.kimu\] ratio: 2 does not match the grades' rates \(400 Hz / 100 Hz = 4\)"),
    (("alignment", "duration"), "-1 s", r"s: \[alignment\] duration: '-1 s' must be positive"),
    (("alignment", "tilt"), "1 deg", r"s: \[alignment\]: unknown key 'tilt'"),
    (("comparison", "interval"), "1.005 s", r"s: \[comparison\] interval: 1\.005 s is not a whole number of main"),
    (("comparison", "model_step"), "0.03 s", r"s: \[comparison\] model_step: 0\.03 s must be an even number"),
    (("comparison", "components"), ["heading"], r"s: \[comparison\] components: unknown component 'heading'"),
    (("comparison", "noise"), {"gravity": "1 mg"}, r"s: \[comparison\] noise: unknown key 'gravity'"),
    (("comparison", "noise"), {"velocity": "1 mrad"}, r"s: \[comparison\] noise\.velocity: '1 mrad' is not a velocity"),
    (("monitor", "window"), "2.5 s", r"s: \[monitor\] window: 2\.5 s is not a whole number of comparison intervals"),
    (("monitor", "false_alarm"), 0.0, r"s: \[monitor\] false_alarm: 0\.0 is not a number > 0 and < 1 \(a probability\)"),
    (("monitor", "candidates"), "some", r"s: \[monitor\] candidates: 'some': expected 'all' or a list"),
    (("monitor", "candidates"), ["z-x"], r"s: \[monitor\] candidates\[0\]: 'z-x' is not 'gyro axis/accel axis'"),
    (("monitor", "candidates"), ["z/q"], r"s: \[monitor\] candidates\[0\]: 'q' is not one of: 'x', 'y', 'z'"),
    (("monitor", "candidates"), ["z/x", "z/x"], r"s: \[monitor\] candidates: lists a candidate twice"),
    (("monitor", "candidates"), ["y/z"], r"s: \[simulation\.fault\]: the injected z/x is not among \[monitor\]"),
    (("gaps", "policy"), "drop", r"s: \[gaps\] policy: 'drop' is not one of: 'hold', 'interpolate', 'propagate', 'refuse'"),
    (("gaps", "window"), 0, r"s: \[gaps\] window: 0 is not an integer in 1\.\.100_000"),
    (("simulation", "runs"), -1, r"s: \[simulation\] runs: -1 is not an integer in 0\.\.10_000"),
    (("simulation", "fault"), _DELETE, r"s: \[simulation\]: fault_runs = 1 needs a \[simulation\.fault\] table"),
    (("simulation", "fault", "gyro"), _DELETE, r"s: \[simulation\.fault\]: missing required key 'gyro'"),
    (("simulation", "fault", "coefficient"), "3 deg/h",
     r"s: \[simulation\.fault\] coefficient: '3 deg/h' is not a scale factor per g"),
    (("simulation", "fault", "coefficient"), 3, r"s: \[simulation\.fault\] coefficient: 3 is not a quantity"),
    (("simulation", "gap"), {"imu": "kimu"}, r"s: \[simulation\] gap: expected an array of tables"),
    (("simulation", "gap"), [{"imu": "ins"}], r"s: \[\[simulation\.gap\]\]\[0\] imu: 'ins' is not one of: 'main', 'kimu'"),
    (("simulation", "gap"), [{"imu": "kimu", "start": "1 s"}], r"s: \[\[simulation\.gap\]\]\[0\]: missing required"),
])
def test_study_file_errors(keys, value, match):
    with pytest.raises(StudyFileError, match=match):
        parse_study(_bad(keys, value), "s")


def test_flight_study_file_parses_and_round_trips():
    """studies/dual_imu_flight.toml: load → dump → load gives the same validated study."""
    import tomllib
    from pathlib import Path

    import tomli_w

    path = Path(__file__).resolve().parents[1] / "studies" / "dual_imu_flight.toml"
    decl = tomllib.loads(path.read_text(encoding="utf-8"))
    a = parse_study(decl, str(path))
    b = parse_study(tomllib.loads(tomli_w.dumps(decl)), str(path))
    for field in dataclasses.fields(a):
        va, vb = getattr(a, field.name), getattr(b, field.name)
        if field.name == "grades":
            assert {k: g.gyro for k, g in va.items()} == {k: g.gyro for k, g in vb.items()}
        elif field.name == "mounting":
            assert all(np.array_equal(va[k], vb[k]) for k in va)
        elif isinstance(va, np.ndarray):
            np.testing.assert_array_equal(va, vb)
        else:
            assert va == vb, field.name
    assert a.fault == (2, 0, pytest.approx(1000 * PPM_G)) and a.runs == 1000 and len(a.gaps) == 3
    assert a.initial["heading"] == pytest.approx(math.radians(45.0))


def test_study_grade_without_rate(tmp_path):
    grade = tmp_path / "norate.toml"
    grade.write_text('[imu]\nname = "norate"\n[gyro]\nbias = "1 deg/h"\n', encoding="utf-8")
    with pytest.raises(StudyFileError, match=r"s: \[imu\.kimu\] grade: IMU grade 'norate' declares no rate"):
        parse_study(_bad(("imu", "kimu", "grade"), str(grade)), "s")


def test_study_needs_a_stand_for_alignment_and_initial_for_logs():
    decl = short_decl(1, 0, gaps=False)
    decl["alignment"]["duration"] = "8 s"
    with pytest.raises(StudyFileError, match=r"<study>: \[alignment\] duration: 8 s: the flight must start with a "
                                             r"stand at least as long as the alignment"):
        run_study(decl)
    cfg = parse_study(short_decl(1, 1), "s")
    with pytest.raises(StudyFileError, match=r"s: \[alignment\]: missing 'heading': the logs need the input position"):
        make_setup(cfg, {"lat": 0.6, "lon": 2.2, "h": 0.0}, "s")
    assert gsens_coefficient("1000 ppm/g", "x") == pytest.approx(1e-3 / G)


@pytest.fixture(scope="module")
def log_files(tmp_path_factory):
    """One simulated flight (g-sensitivity injected) written as two CSV logs with telemetry gaps."""
    from covtool.io.imu_log import save_imu_log

    decl = short_decl(1, 1)
    cfg = parse_study(decl, "s")
    traj = flight_from_config(decl["trajectory"], where="t", dt=0.1)
    logs, removed = simulate_logs(traj, cfg, 1, np.random.default_rng(21), fault=cfg.fault)
    d = tmp_path_factory.mktemp("logs")
    paths = {}
    for key in ("main", "kimu"):
        t, th, dv, _ = logs[key]
        paths[key] = d / f"{key}.csv"
        save_imu_log(paths[key], t, th[0], dv[0])
    import tomli_w

    study = d / "dual.toml"
    study.write_text(tomli_w.dumps(decl), encoding="utf-8")
    return paths, study, removed


def _parser():
    from covtool.cli import add_dualnav_parser as add_parser

    p = argparse.ArgumentParser(prog="covtool")
    add_parser(p.add_subparsers(dest="command", required=True))
    return p


def test_cli_dualnav_on_logs_with_gaps(log_files, tmp_path, capsys):
    """Acceptance 4 and the one-command comparison of two recorded logs."""
    (paths, study, removed) = log_files
    out = tmp_path / "out"
    args = _parser().parse_args(["dualnav", str(paths["main"]), str(paths["kimu"]), "--study", str(study),
                                 "--out", str(out), "--no-figures"])
    assert args.func(args) == 0
    text = capsys.readouterr().out
    assert "bridged gaps:" in text and "g-sensitivity detected" in text
    import pandas as pd

    gaps = pd.read_csv(out / "gaps.csv")
    assert list(gaps["imu"]) == ["main", "kimu"]
    assert list(gaps["samples bridged"]) == [len(removed["main"][0][0]), len(removed["kimu"][0][0])] == [3, 8]
    np.testing.assert_allclose(gaps["after [s]"], [13.0, 8.0])
    summary = pd.read_csv(out / "summary.csv").set_index("item")["value"]
    assert summary["g-sensitivity detected"] == "True"
    assert summary["most likely candidate"] == "z/x"
    assert float(summary["its coefficient"]) == pytest.approx(3000.0, rel=0.2)
    assert (out / "intervals.csv").is_file() and (out / "history.csv").is_file()


def test_cli_dualnav_errors(log_files, tmp_path):
    (paths, study, _) = log_files
    p = _parser()
    bad = tmp_path / "bad.csv"
    bad.write_text("t [s],dtheta_x [rad]\n1,0\n2,0\n", encoding="utf-8")
    args = p.parse_args(["dualnav", str(bad), str(paths["kimu"]), "--study", str(study), "--out", str(tmp_path / "o")])
    with pytest.raises(InputError, match=r"bad\.csv: missing column 'dtheta_y \[rad\]'"):
        args.func(args)
    other = tmp_path / "other.toml"
    other.write_text('[study]\nkind = "pure_ins"\n', encoding="utf-8")
    args = p.parse_args(["dualnav", str(paths["main"]), str(paths["kimu"]), "--study", str(other), "--out", "o"])
    with pytest.raises(StudyFileError, match=r"other\.toml: \[study\] kind: 'pure_ins': covtool dualnav needs a "
                                             r"'dual_imu' study"):
        args.func(args)
    args = p.parse_args(["dualnav", str(paths["kimu"]), str(paths["kimu"]), "--study", str(study), "--out", "o"])
    with pytest.raises(InputError, match=r"kimu\.csv: column 't \[s\]': median sample period 0\.0025 s does not "
                                         r"match the main grade's rate 100 Hz"):
        args.func(args)


def test_cli_dualnav_refuses_an_output_directory_in_use(log_files, tmp_path):
    """Two comparisons never write one directory at once (the lock of `covtool run`)."""
    import os
    import socket
    import subprocess
    import sys

    from covtool.io.lock import OutputLockedError

    (paths, study, _) = log_files
    out = tmp_path / "out"
    hold = ("import sys, time\nfrom covtool.io.lock import DirLock\n"
            "DirLock(sys.argv[1], command='holder').acquire()\nprint('locked', flush=True)\ntime.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", hold, str(out)], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    try:
        assert proc.stdout.readline() == "locked\n"
        args = _parser().parse_args(["dualnav", str(paths["main"]), str(paths["kimu"]), "--study", str(study),
                                     "--out", str(out), "--no-figures"])
        with pytest.raises(OutputLockedError, match=rf"^{out}: in use by another covtool run \(PID {proc.pid} "
                                                    rf"on host {socket.gethostname()}, "):
            args.func(args)
        assert sorted(p.name for p in out.iterdir()) == [".covtool.lock"]        # nothing written
    finally:
        proc.kill()
        proc.wait()


# --------------------------------------------------------------------------
# issue 9 case 9: recorded times kept, clock rates measured, the right log named
# --------------------------------------------------------------------------

PPM = 200.0


def _clocked(rate, seconds, ppm, where):
    """A static log whose recorded times run ``ppm`` slow of the nominal period."""
    log = _static_log(rate, seconds)
    return dataclasses.replace(log, t=log.t * (1.0 + ppm * 1e-6), where=where)


def test_bridging_keeps_recorded_times_with_a_200_ppm_clock(setup_static):
    """Before: kept times re-snapped to the nominal grid (0.5 period off after 2500 samples), then
    'KIMU log: main interval 0 … holds 3 samples' blamed the KIMU; after: times kept, the run goes through."""
    main = _clocked(100.0, 20.0, PPM, "main.csv")
    kimu = _clocked(400.0, 20.0, PPM, "kimu.csv")           # synchronised to the main IMU: the same clock
    keep = np.ones(main.t.size, bool)
    keep[1000:1003] = False
    b = bridge_gaps(main.t[keep], main.dtheta[keep], main.dv[keep], 0.01, "interpolate", imu="main",
                       where="main.csv")
    np.testing.assert_array_equal(b.t[~b.bridged], main.t[keep])          # recorded times, exactly
    assert b.bridged.sum() == 3 and b.bridged[1000:1003].all()
    # inserted samples evenly between the recorded neighbours: the drifting grid itself, to rounding
    np.testing.assert_allclose(b.t[1000:1003], main.t[1000:1003], rtol=0, atol=1e-12)
    assert b.t[-1] - 0.01 * 2000 == pytest.approx(PPM * 1e-6 * 20.0, rel=1e-9)     # 4 ms = 0.4 period off nominal
    assert b.clock_ppm == pytest.approx(PPM, abs=CLOCK_PPM_TOL)
    assert b.where == "main.csv"
    r = run_dual(b, bridge_gaps(kimu.t, kimu.dtheta, kimu.dv, 0.0025, "interpolate", where="kimu.csv"),
                    setup_static)
    assert r.clock["main"] == pytest.approx(PPM, abs=CLOCK_PPM_TOL)
    assert r.clock["kimu"] == pytest.approx(PPM, abs=CLOCK_PPM_TOL)
    assert abs(r.clock["mismatch"]) < CLOCK_PPM_TOL
    assert np.abs(r.z[0, :, 3:6]).max() < 1e-9                             # at rest, error-free: they agree


def test_clock_rate_is_measured_across_gaps():
    t = 0.0025 * np.arange(1, 8001) * (1.0 + PPM * 1e-6)
    keep = np.ones(t.size, bool)
    keep[[100, 4000, 4001, 4002]] = False
    period, ppm = clock_rate(t[keep], 0.0025)
    assert period == pytest.approx(0.0025 * (1 + PPM * 1e-6), rel=1e-12)
    assert ppm == pytest.approx(PPM, abs=CLOCK_PPM_TOL)
    assert ppm_text(-1e-9) == "+0.0" and ppm_text(199.96) == "+200.0"


@pytest.mark.parametrize("late, match", [
    ("kimu", r"kimu\.csv: its clock runs \+200\.0 ppm off its nominal rate \(main\.csv: \+0\.0 ppm\), so the logs "
             r"drift apart by -200\.0 ppm and cannot be paired sample by sample \(main interval \d+ .* holds 3"),
    ("main", r"main\.csv: its clock runs \+200\.0 ppm off its nominal rate \(kimu\.csv: \+0\.0 ppm\), so the logs "
             r"drift apart by \+200\.0 ppm"),
])
def test_clock_mismatch_names_the_log_whose_clock_is_off(setup_static, late, match):
    main = _clocked(100.0, 20.0, PPM if late == "main" else 0.0, "main.csv")
    kimu = _clocked(400.0, 20.0, PPM if late == "kimu" else 0.0, "kimu.csv")
    with pytest.raises(InputError, match=match):
        run_dual(main, kimu, setup_static)


def test_a_kimu_gap_names_the_kimu_log_file(setup_static):
    main, kimu = _static_log(100.0, 20.0), _static_log(400.0, 20.0)
    holey = dataclasses.replace(kimu, t=np.delete(kimu.t, 500), dtheta=np.delete(kimu.dtheta, 500, axis=0),
                                dv=np.delete(kimu.dv, 500, axis=0), where="flight/kimu.csv")
    with pytest.raises(InputError, match=r"^flight/kimu\.csv: main interval 125 .* holds 3 samples, expected 4"):
        run_dual(main, holey, setup_static)
    late = dataclasses.replace(kimu, t=kimu.t + 30.0, where="k.csv")
    with pytest.raises(InputError, match=r"logs: the main log \[0, 20\] s and the KIMU log k\.csv \[30, 50\] s share"):
        run_dual(main, late, setup_static)


def test_nan_statistics_are_never_a_negative_detection(linear_model):
    """Before: a 1e300 in a log gave 'g-sensitivity detected: False' with GLR nan; now a NaN stops the test."""
    from covtool.errors import NumericalError

    m = linear_model
    inn = innovations(m, np.zeros((m.t.size, m.m)))
    bad = dataclasses.replace(inn, nu=np.where(np.arange(inn.nu.shape[1])[None, :, None] == 3, np.nan, inn.nu))
    with pytest.raises(NumericalError, match=r"g-sensitivity test: the GLR statistic of run 0 is not finite"):
        gsens_estimates(bad, m.candidates, 0.01)
    nis = np.ones((2, 20))
    nis[1, 7] = np.nan
    with pytest.raises(NumericalError, match=r"window test: the normalised innovation of run 1 at epoch 7 is not "
                                             r"finite"):
        window_test(nis, 6, 5, 0.01)


def _edited_log(src, dst, edit):
    lines = src.read_text(encoding="utf-8").splitlines()
    dst.write_text("\n".join(edit(lines)) + "\n", encoding="utf-8")
    return dst


def test_cli_refuses_a_non_physical_value_naming_log_row_column(log_files, tmp_path):
    """Before: 1e300 in the KIMU log → NaN statistics, 'g-sensitivity detected: False', exit 0."""
    from covtool.cli import main as cli_main

    (paths, study, _) = log_files

    def put(lines):
        cells = lines[4000].split(",")             # data row 4000 (line 0 is the header)
        cells[4] = "1e300"
        lines[4000] = ",".join(cells)
        return lines

    bad = _edited_log(paths["kimu"], tmp_path / "kimu_1e300.csv", put)
    args = _parser().parse_args(["dualnav", str(paths["main"]), str(bad), "--study", str(study),
                                 "--out", str(tmp_path / "o"), "--no-figures"])
    # 50 g × 2.5 ms × 1.1 (hand): the largest dv a KIMU sample can hold
    bound = 1.1 * 50 * G * 0.0025
    with pytest.raises(InputError, match=rf"kimu_1e300\.csv: column 'dv_x \[m/s\]': row 4000: 1e\+300 m/s is beyond "
                                         rf"what the kimu grade can output \(1\.1 × its specific-force range 50 g × "
                                         rf"0\.0025 s = {bound:.6g} m/s\)"):
        args.func(args)
    assert not (tmp_path / "o").exists()
    assert cli_main(["dualnav", str(paths["main"]), str(bad), "--study", str(study), "--out",
                     str(tmp_path / "o"), "--no-figures", "--quiet"]) == 2


def test_cli_refuses_a_header_that_labels_the_wrong_columns(log_files, tmp_path):
    """A header with Δθ and Δv swapped but the data not: refused at the alignment, not read as is."""
    (paths, study, _) = log_files
    from covtool.io.imu_log import LOG_COLUMNS

    swapped = [LOG_COLUMNS[0], *LOG_COLUMNS[4:7], *LOG_COLUMNS[1:4]]

    def relabel(lines):
        return [",".join(swapped)] + lines[1:601]           # the 6 s stand: every value within the ranges

    bad = _edited_log(paths["main"], tmp_path / "main_swapped.csv", relabel)
    args = _parser().parse_args(["dualnav", str(bad), str(paths["kimu"]), "--study", str(study),
                                 "--out", str(tmp_path / "o"), "--no-figures"])
    with pytest.raises(InputError, match=r"main_swapped\.csv: columns 'dv_x \[m/s\]'\.\.'dv_z \[m/s\]': rows 1-500: "
                                         r"the mean specific force over the 5 s alignment is .* m/s², not gravity "
                                         r"9\.79\d* m/s² within 10 %: the vehicle was not at rest, or the header "
                                         r"labels the wrong columns"):
        args.func(args)
    # the whole flight: the boost's Δv read as Δθ is beyond the gyro range
    bad = _edited_log(paths["main"], tmp_path / "main_swapped.csv", lambda lines: [",".join(swapped)] + lines[1:])
    with pytest.raises(InputError, match=r"main_swapped\.csv: column 'dtheta_x \[rad\]': row \d+: .* rad is beyond "
                                         r"what the main grade can output .*: a corrupted value, or a header that "
                                         r"labels the wrong columns"):
        args.func(args)
    # the columns in another order with their own names: matched by name, the same comparison
    from covtool.io.imu_log import load_imu_log

    order = [6, 0, 3, 1, 5, 2, 4]

    def permute(lines):
        return [",".join(line.split(",")[i] for i in order) for line in lines]

    perm = load_imu_log(_edited_log(paths["main"], tmp_path / "main_perm.csv", permute))
    ref = load_imu_log(paths["main"])
    for key in ("t", "dtheta", "dv"):
        np.testing.assert_array_equal(getattr(perm, key), getattr(ref, key))


def test_run_dual_reuses_a_difference_model(setup_static):
    """A model built once serves later batches: same logs give identical innovations; other epochs are refused."""
    setup = setup_static
    main, kimu = _static_log(100.0, 20.0), _static_log(400.0, 20.0)
    r = run_dual(main, kimu, setup)
    again = run_dual(main, kimu, setup, model=r.model)
    assert again.model is r.model
    np.testing.assert_array_equal(again.inn.nis, r.inn.nis)
    np.testing.assert_array_equal(again.z, r.z)
    with pytest.raises(ValueError, match="the given difference model has other epochs than these logs"):
        run_dual(_static_log(100.0, 30.0), _static_log(400.0, 30.0), setup, model=r.model)
