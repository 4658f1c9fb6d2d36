"""Tests of covtool.nav.trajectory: kinematics, mechanization, I/O.

The oracle is the navigation equations themselves: the trajectory's own
position, velocity and attitude, differentiated numerically, must satisfy
them with the produced specific force and body rate.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad

from covtool.nav import earth
from covtool.nav import attitude as quat
from covtool.errors import TrajectoryError
from covtool.nav.trajectory.core import CSV_COLUMNS, Trajectory
from covtool.io.trajectory import from_segments, trajectory_from_config
from covtool.nav.trajectory.profiles import land_vehicle, static
from covtool.io.trajectory_csv import load_trajectory_csv, save_trajectory_csv

KMH = 1.0 / 3.6
INITIAL = {"lat": "36.37 deg", "lon": "127.36 deg", "h": "60 m", "heading": "0 deg"}


@pytest.fixture(scope="module")
def lv():
    return land_vehicle(dt=1.0)


#: a helical ramp: turns, speed changes and a tilted stand on a grade, so
#: that every Euler-rate term (including the roll-rate term -psi' sin theta)
#: is exercised
HELIX = [
    {"kind": "accelerate", "to_speed": "36 km/h", "duration": "15 s"},
    {"kind": "grade", "grade": "6 %", "duration": "10 s", "level_off": False},
    {"kind": "turn", "rate": "10 deg/s", "angle": "360 deg"},
    {"kind": "accelerate", "to_speed": "54 km/h", "acceleration": "0.1 g", "transition": "2 s"},
    {"kind": "turn", "angle": "-90 deg", "duration": "20 s"},
    {"kind": "decelerate", "to_speed": "0 m/s", "duration": "12 s"},
    {"kind": "stand", "duration": "10 s"},
    {"kind": "accelerate", "to_speed": "5 m/s", "duration": "8 s"},
    {"kind": "grade", "angle": "-2 deg", "duration": "20 s"},
    {"kind": "cruise", "duration": "5 s"},
]


@pytest.fixture(scope="module")
def helix():
    return from_segments(HELIX, INITIAL, dt=0.5, name="helix")


def _breakpoints(traj):
    # White-box: the piece boundaries of the generating profile, where the
    # third derivative of position jumps by design.
    src = traj._source
    return np.append(src.starts, src.span[1])


def _five_point(traj, t, h, get):
    s = [get(traj.sample(t + k * h)) for k in (-2, -1, 1, 2)]
    return (s[0] - 8.0 * s[1] + 8.0 * s[2] - s[3]) / (12.0 * h)


# --------------------------------------------------------------------------
# physics
# --------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["lv", "helix"])
def test_navigation_equations_hold(name, request):
    """Position, velocity and quaternion rates match the nav equations.

    Fourth-order central differences with h = 0.02 s at ~900 times that
    stay 0.05 s clear of the profile's piece boundaries.  Truncation and
    round-off are ~1e-7 m/s, ~4e-9 m/s^2 and ~1e-10 1/s; leaving out the
    Coriolis term would give ~2e-3 m/s^2, the transport rate ~3e-5 m/s^2,
    the Earth rate in w_ib ~4e-5 1/s.
    """
    lv = request.getfixturevalue(name)
    h = 0.02
    rng = np.random.default_rng(7)
    spacing = lv.duration / 900
    t = np.sort(np.linspace(1.0, lv.t[-1] - 1.0, 900) + rng.uniform(-0.4, 0.4, 900) * spacing)
    br = _breakpoints(lv)
    t = t[np.min(np.abs(t[:, None] - br[None, :]), axis=1) > 2.5 * h]
    assert t.size > 700
    c = lv.sample(t)

    # position: earth.position_rates (L', l', h'); residual expressed in [m/s]
    dp = np.column_stack([_five_point(lv, t, h, lambda s: s.lat),
                          _five_point(lv, t, h, lambda s: s.lon),
                          _five_point(lv, t, h, lambda s: s.h)])
    e = dp - earth.position_rates(c.lat, c.h, c.v_n)
    rm, rn = earth.radii(c.lat)
    e_m = np.column_stack([e[:, 0] * (rm + c.h), e[:, 1] * (rn + c.h) * np.cos(c.lat), e[:, 2]])
    assert np.abs(e_m).max() < 1e-6  # [m/s], 1e-7 of the cruise speed

    # velocity: seed 002 eq (4) unperturbed
    f_n = np.einsum("kij,kj->ki", quat.dcm(c.q_nb), c.f_b)
    e_v = _five_point(lv, t, h, lambda s: s.v_n) - earth.velocity_rate(c.lat, c.h, c.v_n, f_n)
    assert np.abs(e_v).max() < 1e-7  # [m/s^2], 1e-8 g

    # attitude: q' = 1/2 q (x) w_ib^b - 1/2 w_in^n (x) q (seed 002 eq (1) unperturbed)
    w_in = earth.earth_rate_n(c.lat) + earth.transport_rate_n(c.lat, c.h, c.v_n)
    z = np.zeros((t.size, 1))
    qdot = 0.5 * quat.mul(c.q_nb, np.hstack([z, c.w_ib_b])) - 0.5 * quat.mul(np.hstack([z, w_in]), c.q_nb)
    e_q = _five_point(lv, t, h, lambda s: s.q_nb) - qdot
    assert np.abs(e_q).max() < 1e-9  # [1/s], 1e-8 of the peak turn rate


@pytest.mark.parametrize("name", ["lv", "helix"])
def test_imu_outputs_continuous_at_breakpoints(name, request):
    """Smooth transitions: f_b and w_ib_b do not jump between pieces.

    Across 2e-6 s the change is bounded by jerk (< 1 m/s^3) and yaw
    acceleration (< 0.1 rad/s^2); a step in acceleration or yaw rate would
    jump by ~0.8 m/s^2 or ~0.09 rad/s.
    """
    lv = request.getfixturevalue(name)
    br = _breakpoints(lv)[1:-1]
    a, b = lv.sample(br - 1e-6), lv.sample(br + 1e-6)
    assert np.abs(a.f_b - b.f_b).max() < 1e-5
    assert np.abs(a.w_ib_b - b.w_ib_b).max() < 1e-6
    assert np.abs(a.v_n - b.v_n).max() < 1e-5


def test_static_vehicle_senses_gravity_and_earth_rate():
    lat, h, yaw = math.radians(45.0), 100.0, math.radians(30.0)
    tr = static(600.0, lat=lat, lon=0.3, h=h, heading=yaw, dt=10.0)
    c_nb = quat.dcm(quat.from_euler(0.0, 0.0, yaw)).T
    g = earth.gravity(lat, h)
    np.testing.assert_allclose(tr.f_b, np.broadcast_to(c_nb @ [0.0, 0.0, -g], tr.f_b.shape), rtol=0, atol=1e-12)
    np.testing.assert_allclose(tr.w_ib_b, np.broadcast_to(c_nb @ earth.earth_rate_n(lat), tr.w_ib_b.shape),
                               rtol=0, atol=1e-16)
    assert np.all(tr.v_n == 0) and np.all(tr.distance == 0)
    assert np.all(tr.lat == lat) and np.all(tr.h == h)
    assert tr.stationary == ((0.0, 600.0),)
    assert tr.stationary_mask(tr.t).all()


# --------------------------------------------------------------------------
# the built-in land vehicle
# --------------------------------------------------------------------------


def test_land_vehicle_statistics(lv):
    assert lv.t[0] == 0.0 and lv.t[-1] == 1800.0 and np.allclose(np.diff(lv.t), 1.0)
    assert lv.name == "land_vehicle"
    assert lv.distance[-1] == pytest.approx(15000.0, rel=0.10)
    stopped = sum(b - a for a, b in lv.stationary)
    assert lv.distance[-1] / (lv.duration - stopped) == pytest.approx(43.0 * KMH, rel=0.10)
    assert len(lv.stationary) == 6
    for k, (a, b) in enumerate(lv.stationary, start=1):
        assert a <= 300.0 * k <= b
        assert b - a == pytest.approx(90.0)
    speed = np.linalg.norm(lv.v_n, axis=1)
    mask = lv.stationary_mask(lv.t)
    assert np.all(speed[mask] == 0.0)
    assert speed[0] == 0.0 and speed[-1] == 0.0
    assert np.all(speed[1:][~mask[1:]] > 0.0)  # moving between t = 0 and the first stop
    # turns both ways, all four headings visited, hills up and down
    w_nb = lv.w_ib_b - np.einsum("kji,kj->ki", quat.dcm(lv.q_nb),
                                 earth.earth_rate_n(lv.lat) + earth.transport_rate_n(lv.lat, lv.h, lv.v_n))
    assert w_nb[:, 2].max() > math.radians(4.9) and w_nb[:, 2].min() < -math.radians(4.9)
    yaw = np.degrees(lv.euler()[:, 2]) % 360.0
    for heading in (0.0, 90.0, 180.0, 270.0):
        assert np.any(np.abs((yaw - heading + 180.0) % 360.0 - 180.0) < 1.0)
    pitch = lv.euler()[:, 1]
    assert pitch.max() == pytest.approx(math.atan(0.04), rel=1e-9)
    assert pitch.min() == pytest.approx(-math.atan(0.04), rel=1e-9)
    assert lv.h.max() - lv.h.min() > 20.0


def test_land_vehicle_parameters():
    tr = land_vehicle(stop_duration=60.0, cycles=3, period=600.0, distance=12000.0, dt=2.0)
    assert tr.duration == 1800.0
    assert tr.stationary == ((540.0, 600.0), (1140.0, 1200.0), (1740.0, 1800.0))
    assert tr.distance[-1] == pytest.approx(12000.0, rel=1e-12)
    with pytest.raises(TrajectoryError, match="land_vehicle: the drive of 10 s per cycle is too short"):
        land_vehicle(stop_duration=290.0)
    with pytest.raises(TrajectoryError, match="land_vehicle: cycles: 2.5 is not a positive integer"):
        land_vehicle(cycles=2.5)
    with pytest.raises(TrajectoryError, match="land_vehicle: distance: must be positive"):
        land_vehicle(distance=-1.0)


def test_sample_is_exact_not_interpolated(lv):
    fine = land_vehicle(dt=0.25)
    t = fine.t[1::4][:800]  # off the 1 s grid
    s = lv.sample(t)
    for key in ("lat", "lon", "h", "v_n", "q_nb", "f_b", "w_ib_b", "distance"):
        np.testing.assert_allclose(getattr(s, key), getattr(fine, key)[1::4][:800], rtol=0, atol=1e-12,
                                   err_msg=key)
    # a linear interpolation of the 1 s grid would be off by ~1e-2 m/s^2 in a turn
    assert s.sample(1800.0).t[0] == 1800.0
    assert s.stationary == ((210.0, 300.0), (510.0, 600.0))


def test_sample_rejects_bad_times(lv):
    with pytest.raises(TrajectoryError, match=r"land_vehicle.*outside the span \[0, 1800\] s"):
        lv.sample([1800.5])
    with pytest.raises(TrajectoryError, match="strictly increasing"):
        lv.sample([5.0, 4.0])
    with pytest.raises(TrajectoryError, match="finite"):
        lv.sample([np.nan])


def test_trajectory_is_immutable_and_validated(lv):
    with pytest.raises(ValueError):
        lv.v_n[0, 0] = 1.0
    with pytest.raises(TrajectoryError, match="t must be strictly increasing"):
        Trajectory(t=[0, 0], lat=[0, 0], lon=[0, 0], h=[0, 0], v_n=np.zeros((2, 3)),
                   q_nb=np.tile([1.0, 0, 0, 0], (2, 1)), f_b=np.zeros((2, 3)), w_ib_b=np.zeros((2, 3)),
                   distance=[0, 0])
    with pytest.raises(TrajectoryError, match=r"v_n has shape \(2, 2\), expected \(2, 3\)"):
        Trajectory(t=[0, 1], lat=[0, 0], lon=[0, 0], h=[0, 0], v_n=np.zeros((2, 2)),
                   q_nb=np.tile([1.0, 0, 0, 0], (2, 1)), f_b=np.zeros((2, 3)), w_ib_b=np.zeros((2, 3)),
                   distance=[0, 0])
    with pytest.raises(TrajectoryError, match="has t0 > t1"):
        Trajectory(t=[0, 1], lat=[0, 0], lon=[0, 0], h=[0, 0], v_n=np.zeros((2, 3)),
                   q_nb=np.tile([1.0, 0, 0, 0], (2, 1)), f_b=np.zeros((2, 3)), w_ib_b=np.zeros((2, 3)),
                   distance=[0, 0], stationary=((1.0, 0.0),))


def test_dataframe_columns(lv):
    df = lv.to_dataframe()
    assert list(df.columns) == list(CSV_COLUMNS) + ["distance [m]", "stationary"]
    assert df["lat [deg]"].iloc[0] == pytest.approx(36.37)
    assert df["stationary"].sum() == 6 * 91


# --------------------------------------------------------------------------
# segments
# --------------------------------------------------------------------------


def test_segment_semantics():
    segs = [
        {"kind": "stand", "duration": "90 s"},
        {"kind": "accelerate", "to_speed": "54 km/h", "duration": "20 s"},
        {"kind": "cruise", "duration": "60 s"},
        {"kind": "turn", "rate": "3 deg/s", "angle": "90 deg"},
        {"kind": "grade", "grade": "5 %", "duration": "40 s", "transition": "5 s"},
        {"kind": "turn", "rate": "-3 deg/s", "duration": "20 s", "transition": "2 s"},
        {"kind": "turn", "angle": "-45 deg", "duration": "20 s"},
        {"kind": "grade", "angle": "-3 deg", "duration": "30 s"},
        {"kind": "decelerate", "to_speed": "0 km/h", "acceleration": "0.1 g"},
        {"kind": "stand", "duration": "30 s"},
    ]
    tr = from_segments(segs, INITIAL, dt=0.5, name="x")
    # rate + angle: 90/3 = 30 s plus one 3 s transition
    t_turn = 90.0 + 20.0 + 60.0
    assert np.degrees(tr.sample(t_turn + 33.0).euler()[0, 2]) == pytest.approx(90.0, abs=1e-9)
    assert np.degrees(tr.sample(t_turn + 16.5).w_ib_b[0, 2]) == pytest.approx(3.0, abs=0.01)
    # grade: pitch = atan(5 %), climb ~ s sin(theta) (40 - 5) s
    eul = tr.sample(t_turn + 33.0 + 20.0).euler()[0]
    assert eul[1] == pytest.approx(math.atan(0.05), rel=1e-12)
    h0, h1 = tr.sample([t_turn + 33.0, t_turn + 73.0]).h
    th = math.atan(0.05)
    ramp, _ = quad(lambda u: math.sin(th * 0.5 * (1.0 - math.cos(math.pi * u))), 0.0, 1.0, epsabs=1e-14)
    assert h1 - h0 == pytest.approx(15.0 * (30.0 * math.sin(th) + 2.0 * 5.0 * ramp), rel=1e-10)
    # the rate+duration and angle+duration turns: 90 - 3*(20-2) - 45 = -9 deg
    assert np.degrees(tr.euler()[-1, 2]) == pytest.approx(-9.0, abs=1e-9)
    # deceleration at 0.1 g plateau: 15/(0.1 g) + 3 s
    t_stop = tr.stationary[1][0]
    assert tr.stationary[0] == (0.0, 90.0)
    assert tr.stationary[1][1] - t_stop == pytest.approx(30.0)
    assert tr.duration == pytest.approx(t_stop + 30.0)
    t_dec = t_stop - (15.0 / (0.1 * 9.80665) + 3.0)
    acc = np.linalg.norm(np.gradient(tr.sample(np.linspace(t_dec, t_stop, 2001)).v_n, axis=0), axis=1)
    assert acc.max() / ((t_stop - t_dec) / 2000) == pytest.approx(0.1 * 9.80665, rel=1e-4)
    assert tr.distance[-1] > 0 and np.all(np.diff(tr.distance) >= 0)


def test_helix_stays_on_grade(helix):
    """``level_off = false`` keeps the pitch through turns and a stand."""
    th = math.atan(0.06)
    t_end_climb = 15.0 + 10.0 + 39.0 + (5.0 / (0.1 * 9.80665) + 2.0) + 20.0 + 12.0 + 10.0 + 8.0
    assert helix.duration == pytest.approx(t_end_climb + 20.0 + 5.0, rel=1e-12)
    on_grade = (helix.t >= 25.0) & (helix.t <= t_end_climb)
    np.testing.assert_allclose(helix.euler()[on_grade, 1], th, rtol=1e-12)
    assert np.degrees(helix.euler()[:, 1].min()) == pytest.approx(-2.0, rel=1e-12)
    assert helix.euler()[-1, 1] == 0.0
    assert np.degrees(helix.euler()[-1, 2]) == pytest.approx(-90.0, abs=1e-9)
    # parked on the ramp: the accelerometers see tilted gravity
    (a, b), = helix.stationary
    assert b - a == pytest.approx(10.0)
    st = helix.sample([a + 5.0])
    g_b = quat.dcm(st.q_nb[0]).T @ earth.gravity_n(st.lat[0], st.h[0])
    np.testing.assert_allclose(st.f_b[0], -g_b, atol=1e-12)
    assert st.f_b[0, 0] == pytest.approx(earth.gravity(st.lat[0], st.h[0]) * math.sin(th), rel=1e-12)


def test_initial_speed_and_heading():
    tr = from_segments([{"kind": "cruise", "duration": "10 s"}],
                       {**INITIAL, "heading": "90 deg", "speed": "10 m/s"}, dt=1.0)
    np.testing.assert_allclose(tr.v_n[-1], [0.0, 10.0, 0.0], atol=1e-12)
    assert tr.distance[-1] == pytest.approx(100.0)
    assert tr.stationary == ()


# --------------------------------------------------------------------------
# position integration (Chebyshev–Picard, segments._Profile)
# --------------------------------------------------------------------------

#: an airliner for ~10 h: long cruises, a fast (30 deg/s) reversal, an hour of holding-pattern turns,
#: a climb and a descent, speed changes
AIRLINER = [
    {"kind": "cruise", "duration": "2 h"},
    {"kind": "turn", "rate": "3 deg/s", "angle": "90 deg", "transition": "2 s"},
    {"kind": "grade", "angle": "3 deg", "duration": "20 min", "transition": "20 s"},
    {"kind": "turn", "rate": "-30 deg/s", "angle": "-180 deg", "transition": "0.5 s"},
    {"kind": "turn", "rate": "1.5 deg/s", "duration": "1 h"},
    {"kind": "accelerate", "to_speed": "280 m/s", "duration": "60 s"},
    {"kind": "cruise", "duration": "3 h"},
    {"kind": "turn", "angle": "-45 deg", "duration": "30 s"},
    {"kind": "grade", "angle": "-2 deg", "duration": "30 min"},
    {"kind": "decelerate", "to_speed": "240 m/s", "acceleration": "0.5 m/s^2"},
    {"kind": "cruise", "duration": "3 h"},
]
AIRLINER_INITIAL = {"lat": "30 deg", "lon": "-100 deg", "h": "10000 m", "heading": "45 deg", "speed": "250 m/s"}


def _start(initial):
    return (math.radians(float(initial["lat"].split()[0])), math.radians(float(initial["lon"].split()[0])),
            float(initial["h"].split()[0]))


def _dop853_positions(traj, start, t, rtol=1e-13):
    """(lat, lon, h) at ``t`` by scipy's DOP853 from the declared start, piece by piece (the reference).

    The right-hand side is ``earth.position_rates`` written out in scalars,
    on the analytic kinematics of the pieces; the pieces are chained with
    DOP853's own end values, not the code under test.
    """
    from scipy.integrate import solve_ivp

    src = traj._source
    k_of = np.clip(np.searchsorted(src.starts, t, side="right") - 1, 0, len(src.pieces) - 1)
    out = np.empty((t.size, 3))
    pos = np.array(start, dtype=float)
    for k, p in enumerate(src.pieces):
        m = k_of == k
        if p.s0 == 0.0 and p.accel.a == 0.0 and p.accel.b == 0.0:   # at rest
            out[m] = pos
            continue

        def rhs(tau, y, p=p, lat_p=pos[0], h_p=pos[2]):
            s = p.s0 + p.accel.integral(tau)
            psi = p.psi0 + p.yaw_rate.integral(tau)
            th = p.pitch.value(tau)
            lat, h = lat_p + y[0], h_p + y[2]
            w = 1.0 - earth.E2 * math.sin(lat) ** 2
            rn = earth.A / math.sqrt(w)
            rm = rn * (1.0 - earth.E2) / w
            return [s * math.cos(th) * math.cos(psi) / (rm + h),
                    s * math.cos(th) * math.sin(psi) / ((rn + h) * math.cos(lat)), s * math.sin(th)]

        sol = solve_ivp(rhs, (0.0, p.T), np.zeros(3), method="DOP853", rtol=rtol, atol=(1e-18, 1e-18, 1e-11),
                        dense_output=True)
        assert sol.success
        if m.any():
            out[m] = pos + sol.sol(t[m] - p.t0).T
        pos = pos + sol.y[:, -1]
    return out


def _assert_matches_dop853(traj, start):
    """At the grid and 0.37 s after each grid time: ≤ 1e-12 rad (~6 µm) in lat, lon and ≤ 1e-5 m in h."""
    off = traj.t[traj.t + 0.37 <= traj.t[-1]] + 0.37
    for t, label in ((traj.t, "grid"), (off, "off the grid")):
        ref = _dop853_positions(traj, start, t)
        got = traj.sample(t)
        np.testing.assert_allclose(got.lat, ref[:, 0], rtol=0, atol=1e-12, err_msg=f"lat, {label}")
        np.testing.assert_allclose(got.lon, ref[:, 1], rtol=0, atol=1e-12, err_msg=f"lon, {label}")
        np.testing.assert_allclose(got.h, ref[:, 2], rtol=0, atol=1e-5, err_msg=f"h, {label}")


@pytest.mark.parametrize("name", ["lv", "helix"])
def test_position_matches_dop853(name, request):
    """The route and the helix against DOP853 at rtol = 1e-13.

    The Chebyshev–Picard positions agree to ~2e-16 rad and ~4e-12 m; taking
    R_M at the start latitude (no Picard iteration) would be off by ~3e-10
    rad on the route.
    """
    tr = request.getfixturevalue(name)
    _assert_matches_dop853(tr, _start(INITIAL))


def test_fast_long_flight_matches_dop853():
    """~10 h at 240-280 m/s with a 30 deg/s reversal, an hour of turns, a climb and a descent."""
    tr = from_segments(AIRLINER, AIRLINER_INITIAL, dt=10.0, name="airliner")
    assert tr.duration > 9.5 * 3600 and tr.distance[-1] > 8.5e6
    src = tr._source
    assert src._sub_t.size > len(src.pieces)            # the hour of turning is cut into sub-intervals
    _assert_matches_dop853(tr, _start(AIRLINER_INITIAL))


def test_near_polar_rhumb_line_matches_dop853():
    """From 70 deg N at heading 10 deg to 89.2 deg N: the longitude integrand (1/cos L) is halved."""
    init = {"lat": "70 deg", "lon": "0 deg", "h": "10000 m", "heading": "10 deg", "speed": "250 m/s"}
    tr = from_segments([{"kind": "cruise", "duration": "8700 s"}], init, dt=10.0)
    assert math.degrees(tr.lat[-1]) > 89.1 and math.degrees(tr.lon[-1]) > 30.0
    assert tr._source._sub_t.size > 1                   # one piece, cut where 1/cos L steepens
    _assert_matches_dop853(tr, _start(init))


def test_due_east_cruise_closed_form():
    """Due east at constant speed and height: lat constant, lon = lon0 + v t / ((R_N + h) cos lat)."""
    v, h0 = 250.0, 60.0
    tr = from_segments([{"kind": "cruise", "duration": "10 h"}],
                       {**INITIAL, "heading": "90 deg", "speed": f"{v} m/s"}, dt=60.0)
    lat0, lon0, _ = _start(INITIAL)
    t = np.linspace(0.0, tr.t[-1], 777)
    s = tr.sample(t)
    _, rn = earth.radii(lat0)
    np.testing.assert_allclose(s.lat, lat0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(s.lon, lon0 + v * t / ((rn + h0) * math.cos(lat0)), rtol=0, atol=1e-14)
    np.testing.assert_allclose(s.h, h0, rtol=0, atol=1e-12)


def test_constant_pitch_climb_closed_form():
    """Due east on a 10-deg climb at 200 m/s after a 20-s pitch-up.

    After the pitch-up: ``h = h_r + v (t − t_r) sin θ`` and
    ``lon = lon_r + cot θ / cos L · ln((R_N + h)/(R_N + h_r))``; over the
    pitch-up ``h_r − h0 = v T_r ∫_0^1 sin(θ S(u)) du`` (quadrature).
    """
    v, th, t_r, h0 = 200.0, math.radians(10.0), 20.0, 60.0
    tr = from_segments([{"kind": "grade", "angle": "10 deg", "duration": "20 min", "transition": "20 s",
                         "level_off": False}], {**INITIAL, "heading": "90 deg", "speed": f"{v} m/s"}, dt=1.0)
    lat0, lon0, _ = _start(INITIAL)
    ramp, _ = quad(lambda u: math.sin(th * 0.5 * (1.0 - math.cos(math.pi * u))), 0.0, 1.0, epsabs=1e-15,
                   epsrel=1e-15)
    r = tr.sample([t_r])
    assert r.h[0] - h0 == pytest.approx(v * t_r * ramp, rel=1e-13, abs=0)
    t = np.linspace(t_r, tr.t[-1], 555)
    s = tr.sample(t)
    assert s.h[-1] > 4e4
    np.testing.assert_allclose(s.h, r.h[0] + v * (t - t_r) * math.sin(th), rtol=0, atol=1e-9)
    _, rn = earth.radii(lat0)
    lon = r.lon[0] + math.cos(th) / (math.sin(th) * math.cos(lat0)) * np.log((rn + s.h) / (rn + r.h[0]))
    np.testing.assert_allclose(s.lon, lon, rtol=0, atol=1e-14)
    np.testing.assert_allclose(s.lat, lat0, rtol=0, atol=1e-15)


def test_due_north_cruise_meridian_arc():
    """Due north at 250 m/s for 2 h: the meridian arc ∫(R_M(φ) + h) dφ to lat(t) is v t (quadrature)."""
    v, h0 = 250.0, 60.0
    tr = from_segments([{"kind": "cruise", "duration": "2 h"}],
                       {**INITIAL, "heading": "0 deg", "speed": f"{v} m/s"}, dt=60.0)
    lat0, lon0, _ = _start(INITIAL)
    t = np.linspace(0.0, tr.t[-1], 61) + np.r_[0.0, np.full(59, 0.37), 0.0]
    s = tr.sample(t)
    assert math.degrees(s.lat[-1] - lat0) > 16.0
    # the arc as (R_M(lat0) + h)(L − lat0) + ∫(R_M(φ) − R_M(lat0)) dφ: the quadrature sees only the ~1e4 m/rad
    # variation of R_M, to ~1e-10 m
    rm0 = earth.radii(lat0)[0]
    arc = np.array([(rm0 + h0) * (L - lat0) + quad(lambda p: earth.radii(p)[0] - rm0, lat0, L, epsabs=1e-10,
                                                   epsrel=1e-13)[0] for L in s.lat])
    np.testing.assert_allclose(arc, v * t, rtol=0, atol=1e-6)          # [m]: ~1.6e-13 rad
    np.testing.assert_array_equal(s.lon, lon0)
    np.testing.assert_array_equal(s.h, h0)


def test_turns_without_the_first_cut_are_resolved_by_halving(monkeypatch):
    """10 h of turning (1885 rad of heading): the tail test alone splits the aliased piece.

    With the first cut off, halving stops where the series are resolved and
    gives the same positions to 1e-14 rad; capped at 4 halvings it refuses,
    naming the piece.
    """
    import covtool.nav.trajectory.segments as seg

    segs = [{"kind": "turn", "rate": "3 deg/s", "duration": "10 h"}]
    init = {"lat": "45 deg", "lon": "10 deg", "h": "10000 m", "speed": "250 m/s"}
    cut = from_segments(segs, init, dt=10.0)
    monkeypatch.setattr(seg, "_MAX_TURN", math.inf)
    halved = from_segments(segs, init, dt=10.0)
    assert halved._source._sub_t.size > 200
    for key, tol in (("lat", 1e-14), ("lon", 1e-14), ("h", 1e-9)):
        np.testing.assert_allclose(getattr(halved, key), getattr(cut, key), rtol=0, atol=tol, err_msg=key)
    monkeypatch.setattr(seg, "_SPLIT_MAX", 4)
    with pytest.raises(TrajectoryError, match=r"^turns: piece 1 \(t = 3 to 35997 s\): the kinematics are not "
                                              r"resolved to round-off by Chebyshev series of degree 32 after 4 "
                                              r"halvings"):
        from_segments(segs, init, dt=10.0, where="turns")


def test_position_not_converged_names_the_piece(monkeypatch):
    import covtool.nav.trajectory.segments as seg

    monkeypatch.setattr(seg, "_PICARD_MAX", 1)
    with pytest.raises(TrajectoryError, match=r"^land_vehicle: piece 0 \(t = 0 to 3 s\): the latitude did not "
                                              r"converge in 1 Picard iteration\(s\) \(last change 1\.6\de-07 rad"):
        land_vehicle()


def test_latitude_beyond_the_pole_is_refused():
    # a rhumb line from 60 deg N at heading 30 deg reaches the pole after ~3500 km
    with pytest.raises(TrajectoryError, match=r"^polar: piece 0 \(t = 0 to 36000 s\): the latitude reaches "
                                              r"1\d\d\.\d+ deg, beyond ±89\.9 deg"):
        from_segments([{"kind": "cruise", "duration": "10 h"}],
                      {"lat": "60 deg", "lon": "0 deg", "h": "10000 m", "heading": "30 deg", "speed": "250 m/s"},
                      where="polar")


def test_profile_pickles_and_samples_the_same(lv):
    import pickle

    copy = pickle.loads(pickle.dumps(lv))
    t = np.linspace(0.0, 1800.0, 4001)[1:-1] + 0.01
    a, b = lv.sample(t), copy.sample(t)
    for key in ("lat", "lon", "h", "v_n", "f_b", "w_ib_b"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
    assert len(pickle.dumps(lv._source)) < 400_000


def test_building_a_profile_does_not_import_scipy_integrate():
    import os
    from pathlib import Path
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    code = ("import sys; from covtool.nav.trajectory.profiles import land_vehicle; land_vehicle(); "
            "print('scipy.integrate' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root,
                         env=dict(os.environ, PYTHONPATH=str(root)))
    assert out.stdout.strip() == "False", out.stdout + out.stderr



# --------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------


def test_config_sources(tmp_path, lv):
    tr = trajectory_from_config({"builtin": "land_vehicle"}, where="s.toml", base_dir=None, dt=1.0)
    np.testing.assert_array_equal(tr.f_b, lv.f_b)
    tr = trajectory_from_config({"builtin": "land_vehicle", "stop_duration": "1 min", "name": "lv60"},
                                where="s.toml", base_dir=None, dt=5.0)
    assert tr.name == "lv60" and tr.stationary[0] == (240.0, 300.0)
    st = trajectory_from_config({"builtin": "static", "duration": "30 min", "lat": "45 deg", "lon": "0 deg",
                                 "h": "0 m", "heading": "10 deg"}, where="s.toml", base_dir=None, dt=10.0)
    assert st.stationary == ((0.0, 1800.0),) and st.n == 181
    seg = trajectory_from_config({"segment": [{"kind": "stand", "duration": "90 s"}], "initial": INITIAL},
                                 where="s.toml", base_dir=None, dt=1.0)
    assert seg.duration == 90.0
    save_trajectory_csv(lv, tmp_path / "route.csv")
    csv = trajectory_from_config({"csv": "route.csv"}, where="s.toml", base_dir=tmp_path, dt=1.0)
    np.testing.assert_array_equal(csv.t, lv.t)
    assert csv.name == "route"


SEG = [{"kind": "stand", "duration": "90 s"}]


@pytest.mark.parametrize("cfg, match", [
    ({"builtin": "land_vehicle", "stops": 3}, r"s\.toml: builtin 'land_vehicle': unknown key 'stops'"),
    ({"builtin": "flight"}, r"s\.toml: builtin: unknown builtin 'flight'"),
    ({"builtin": "land_vehicle", "csv": "x.csv"}, "give exactly one of 'builtin', 'segment' and 'csv'"),
    ({}, r"give exactly one of .* \(got none\)"),
    ({"builtin": "land_vehicle", "stop_duration": "90 m"}, "stop_duration: '90 m' is not a time"),
    ({"builtin": "land_vehicle", "stop_duration": "-90 s"}, "stop_duration: must be positive"),
    ({"builtin": "land_vehicle", "cycles": "6"}, "cycles: '6' is not an integer in 1..1000"),
    ({"builtin": "land_vehicle", "lat": "90 deg"}, "lat: 90 deg is not within"),
    ({"builtin": "land_vehicle", "speed": "9 furlongs"}, "unknown key 'speed'"),
    ({"builtin": "static", "lat": "45 deg", "lon": "0 deg"}, "static': missing required key 'h'"),
    ({"builtin": "static", "duration": "-1 min", "lat": "45 deg", "lon": "0 deg", "h": "0 m"},
     "static': duration: must be positive"),
    ({"segment": SEG}, "missing required key 'initial'"),
    ({"segment": SEG, "initial": {"lat": "45 deg", "lon": "0 deg"}}, "initial: missing required key 'h'"),
    ({"segment": SEG, "initial": {**INITIAL, "alt": "3 m"}}, "initial: unknown key 'alt'"),
    ({"segment": SEG, "initial": {**INITIAL, "lat": "45 m"}}, "initial: lat: '45 m' is not an angle"),
    ({"segment": SEG, "initial": {**INITIAL, "speed": "-1 m/s"}}, "initial: speed: -1 m/s must not be negative"),
    ({"segment": SEG, "initial": {**INITIAL, "h": "200 km"}}, r"initial: h: 200000 m is outside"),
    ({"segment": [], "initial": INITIAL}, "segment: expected a non-empty list"),
    ({"segment": [{"kind": "hover", "duration": "1 s"}], "initial": INITIAL},
     r"segment\[0\]: unknown segment kind 'hover'"),
    ({"segment": ["stand"], "initial": INITIAL}, r"segment\[0\]: expected a table"),
    ({"segment": [{"kind": "stand", "duration": "-5 s"}], "initial": INITIAL},
     r"segment\[0\] \(stand\): duration: must be positive"),
    ({"segment": [{"kind": "stand"}], "initial": INITIAL}, "missing required key 'duration'"),
    ({"segment": [{"kind": "stand", "duration": "5 s", "speed": "1 m/s"}], "initial": INITIAL},
     r"segment\[0\] \(stand\): unknown key 'speed'"),
    ({"segment": [{"kind": "stand", "duration": "5 furlongs"}], "initial": INITIAL},
     r"segment\[0\] \(stand\): duration: '5 furlongs'"),
    ({"segment": [{"kind": "cruise", "duration": "5 s"}], "initial": INITIAL},
     "cruise at zero speed"),
    ({"segment": [{"kind": "accelerate", "to_speed": "5 m/s", "duration": "5 s"},
                  {"kind": "stand", "duration": "5 s"}], "initial": INITIAL},
     r"segment\[1\] \(stand\): the vehicle is moving \(5 m/s\)"),
    ({"segment": [{"kind": "accelerate", "to_speed": "5 m/s"}], "initial": INITIAL},
     "exactly one of 'duration' and 'acceleration'"),
    ({"segment": [{"kind": "accelerate", "to_speed": "5 m/s", "duration": "5 s", "acceleration": "1 m/s^2"}],
      "initial": INITIAL}, "exactly one of 'duration' and 'acceleration'"),
    ({"segment": [{"kind": "accelerate", "duration": "5 s"}], "initial": INITIAL},
     "missing required key 'to_speed'"),
    ({"segment": [{"kind": "accelerate", "to_speed": "-5 m/s", "duration": "5 s"}], "initial": INITIAL},
     "to_speed: -5 m/s must not be negative"),
    ({"segment": [{"kind": "accelerate", "to_speed": "0 m/s", "duration": "5 s"}], "initial": INITIAL},
     "to_speed: equals the current speed"),
    ({"segment": [{"kind": "decelerate", "to_speed": "5 m/s", "duration": "5 s"}], "initial": INITIAL},
     r"segment\[0\] \(decelerate\): to_speed: 5 m/s is not below the current speed"),
    ({"segment": [{"kind": "accelerate", "to_speed": "5 m/s", "acceleration": "-1 m/s^2"}],
      "initial": INITIAL}, "acceleration: must be positive"),
    ({"segment": [{"kind": "turn", "rate": "3 deg/s", "angle": "90 deg", "duration": "30 s"}],
      "initial": INITIAL}, "give exactly two of 'rate', 'angle' and 'duration'"),
    ({"segment": [{"kind": "turn", "rate": "3 deg/s", "angle": "-90 deg"}], "initial": INITIAL},
     "opposite signs"),
    ({"segment": [{"kind": "turn", "rate": "0 deg/s", "duration": "9 s"}], "initial": INITIAL},
     "rate: must not be zero"),
    ({"segment": [{"kind": "turn", "rate": "3 deg", "duration": "9 s"}], "initial": INITIAL},
     "rate: '3 deg' is not an angular rate"),
    ({"segment": [{"kind": "turn", "angle": "90 deg", "duration": "9 s", "transition": "0 s"}],
      "initial": INITIAL}, "transition: must be positive"),
    ({"segment": [{"kind": "grade", "grade": "5 %", "duration": "9 s"}], "initial": INITIAL},
     "grade at zero speed"),
    ({"segment": [{"kind": "grade", "grade": "5 %", "angle": "3 deg", "duration": "9 s"}],
      "initial": INITIAL}, "give exactly one of 'grade' and 'angle'"),
    ({"segment": [{"kind": "grade", "angle": "3 deg"}], "initial": {**INITIAL, "speed": "1 m/s"}},
     "missing required key 'duration'"),
    ({"segment": [{"kind": "grade", "angle": "3 deg", "duration": "9 s", "level_off": "no"}],
      "initial": {**INITIAL, "speed": "1 m/s"}}, "level_off: 'no' is not true or false"),
    ({"segment": [{"kind": "grade", "angle": "95 deg", "duration": "9 s"}],
      "initial": {**INITIAL, "speed": "1 m/s"}}, "not within ±90 deg"),
    ({"segment": SEG, "initial": INITIAL, "dt": "1 s"}, "unknown key 'dt'"),
    ({"csv": 3}, "csv: 3 is not a file name"),
    ({"csv": "missing.csv"}, r"s\.toml: .*missing\.csv: file not found"),
    ({"builtin": "land_vehicle", "name": 3}, "name: 3 is not a string"),
])
def test_config_errors(cfg, match, tmp_path):
    with pytest.raises(TrajectoryError, match=match):
        trajectory_from_config(cfg, where="s.toml", base_dir=tmp_path, dt=1.0)


def test_config_error_not_a_table():
    with pytest.raises(TrajectoryError, match="s.toml: expected a table, got list"):
        trajectory_from_config([], where="s.toml", base_dir=None, dt=1.0)


# --------------------------------------------------------------------------
# CSV
# --------------------------------------------------------------------------


def test_csv_round_trip(tmp_path, lv):
    path = tmp_path / "lv.csv"
    save_trajectory_csv(lv, path)
    back = load_trajectory_csv(path)
    np.testing.assert_array_equal(back.t, lv.t)
    # deg <-> rad and the quaternion renormalisation cost at most an ulp or two
    for key in ("lat", "lon"):
        np.testing.assert_allclose(getattr(back, key), getattr(lv, key), rtol=1e-15, atol=0, err_msg=key)
    np.testing.assert_allclose(back.q_nb, lv.q_nb, rtol=0, atol=3e-16)
    for key in ("h", "v_n", "f_b", "w_ib_b", "distance"):
        np.testing.assert_array_equal(getattr(back, key), getattr(lv, key), err_msg=key)
    assert back.stationary == lv.stationary
    assert back.name == "lv"


def test_csv_sample_interpolates(tmp_path, lv):
    path = tmp_path / "lv.csv"
    save_trajectory_csv(lv, path)
    back = load_trajectory_csv(path)
    t = np.arange(0.5, 1800.0, 1.0)
    s, exact = back.sample(t), lv.sample(t)
    np.testing.assert_allclose(s.v_n, 0.5 * (lv.v_n[:-1] + lv.v_n[1:]), rtol=0, atol=1e-12)
    # slerp is exact at constant rate; in the yaw-rate ramps (peak yaw
    # acceleration 5 deg/s * pi/(2*3 s)) the midpoint angle error is
    # psi'' dt^2/8, i.e. psi'' dt^2/16 in the quaternion
    bound = math.radians(5.0) * math.pi / 6.0 / 16.0
    err = np.abs(s.q_nb - exact.q_nb).max()
    assert 0.5 * bound < err < 1.05 * bound
    np.testing.assert_allclose(np.linalg.norm(s.q_nb, axis=1), 1.0, atol=1e-15)
    assert back.sample(back.t).stationary == lv.stationary
    with pytest.raises(TrajectoryError, match="outside the span"):
        back.sample([-1.0])


def test_csv_infers_stationary_and_distance(tmp_path, lv):
    path = tmp_path / "bare.csv"
    lv.to_dataframe()[list(CSV_COLUMNS)].to_csv(path, index=False, float_format="%.17g")
    back = load_trajectory_csv(path)
    assert back.stationary == lv.stationary
    assert back.distance[-1] == pytest.approx(lv.distance[-1], rel=1e-3)


def test_csv_fixes_quaternion_sign(tmp_path, lv):
    df = lv.to_dataframe()
    df.loc[100, ["q0", "q1", "q2", "q3"]] *= -1.0
    path = tmp_path / "flip.csv"
    df.to_csv(path, index=False, float_format="%.17g")
    np.testing.assert_allclose(load_trajectory_csv(path).q_nb, lv.q_nb, atol=1e-15)


def _write_bad(tmp_path, lv, edit):
    df = lv.sample(lv.t[:10]).to_dataframe().astype(object)
    df = edit(df)
    path = tmp_path / "bad.csv"
    df.to_csv(path, index=False)
    return path


@pytest.mark.parametrize("edit, match", [
    (lambda df: df.drop(columns=["v_E [m/s]"]), r"bad\.csv: missing column 'v_E \[m/s\]'"),
    (lambda df: df.rename(columns={"h [m]": "h [ft]"}), r"missing column 'h \[m\]'"),
    (lambda df: df.assign(extra=1.0), r"bad\.csv: unknown column 'extra'"),
    (lambda df: df.assign(**{"h [m]": ["60"] * 4 + ["abc"] + ["60"] * 5}),
     r"bad\.csv: column 'h \[m\]': row 5: 'abc' is not a number"),
    (lambda df: df.assign(**{"f_x [m/s^2]": [0.0] * 7 + [""] + [0.0] * 2}),
     r"column 'f_x \[m/s\^2\]': row 8: is empty"),
    (lambda df: df.assign(**{"q2": [0.0] * 2 + ["nan"] + [0.0] * 7}), r"column 'q2': row 3: 'nan' is not finite"),
    (lambda df: df.assign(**{"t [s]": [0, 1, 2, 3, 3, 5, 6, 7, 8, 9]}),
     r"column 't \[s\]': row 5: time 3 s is not after the previous row's 3 s"),
    (lambda df: df.assign(**{"t [s]": [0, 1, 2, 3, 4, 5, 6, 7, 8, 1]}), r"row 10: time 1 s is not after"),
    (lambda df: df.assign(q0=[1.0] * 5 + [0.9] + [1.0] * 4), r"columns 'q0'..'q3': row 6: \|q\| = 0\.9"),
    (lambda df: df.assign(stationary=[1] * 9 + [2]), r"column 'stationary': row 10: 2 is not 0 or 1"),
    (lambda df: df.assign(**{"lat [deg]": [90.0] * 10}), r"column 'lat \[deg\]': row 1: 90 deg is not within"),
    (lambda df: df.iloc[:1], "needs at least 2 data rows, found 1"),
])
def test_csv_errors(tmp_path, lv, edit, match):
    path = _write_bad(tmp_path, lv, edit)
    with pytest.raises(TrajectoryError, match=match):
        load_trajectory_csv(path)


def test_csv_missing_or_empty_file(tmp_path):
    with pytest.raises(TrajectoryError, match=r"nope\.csv: file not found"):
        load_trajectory_csv(tmp_path / "nope.csv")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(TrajectoryError, match=r"empty\.csv: not a readable CSV file"):
        load_trajectory_csv(tmp_path / "empty.csv")


# --------------------------------------------------------------------------
# issue 9 case 9: longitude, gaps, stationary flags; issue 10 cases 5-6
# --------------------------------------------------------------------------

_ROW = "0,0,-9.80665,0,0,0"        # f_x..f_z, w_x..w_z of a level, unaccelerated vehicle


def _antimeridian_csv(tmp_path, lons=(179.9999, -179.9999, -179.9997)):
    """Three rows one second apart, heading east at 21.9 m/s across the antimeridian."""
    header = ",".join(CSV_COLUMNS)
    rows = [f"{k},10.3,{lon!r},50,0,21.9,0,1,0,0,0,{_ROW}" for k, lon in enumerate(lons)]
    path = tmp_path / "dateline.csv"
    path.write_text(header + "\n" + "\n".join(rows) + "\n", encoding="utf-8")
    return path


def test_csv_longitude_interpolates_across_the_antimeridian(tmp_path):
    """Before: lon 0.0° at t = 0.5 s (the long way round); after: ±180°."""
    import covtool.nav.strapdown as sd
    from covtool.nav.trajectory.core import wrap_longitude

    traj = load_trajectory_csv(_antimeridian_csv(tmp_path))
    s = traj.sample([0.5, 1.5])
    # hand value: halfway between 179.9999° and 180.0001° (= −179.9999°) is 180°, then 180.0002°
    np.testing.assert_allclose(np.degrees(s.lon), [180.0, 180.0002], rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.degrees(wrap_longitude(s.lon)), [-180.0, -179.9998], rtol=0, atol=1e-9)
    # the step agrees with the east velocity: 21.9 m/s over (R_N + h) cos L
    _, rn = earth.radii(math.radians(10.3))
    assert math.degrees(traj.lon[1] - traj.lon[0]) == pytest.approx(
        math.degrees(21.9 / ((rn + 50.0) * math.cos(math.radians(10.3)))), rel=0.01)
    # files and reports see the wrapped angle; the Monte Carlo truth and the nav errors see the short way
    df = s.to_dataframe()
    assert (df["lon [deg]"] >= -180.0).all() and (df["lon [deg]"] < 180.0).all()
    truth = sd.truth_state(traj, [0.5])
    assert abs(math.degrees(truth.lon[0]) - 180.0) < 1e-9
    nav = truth.replace(lon=truth.lon - 2.0 * math.pi)           # the same place, written the other way
    assert abs(sd.nav_errors(nav, truth)[0, 1]) < 1e-12


def test_csv_longitude_round_trips_wrapped(tmp_path):
    traj = load_trajectory_csv(_antimeridian_csv(tmp_path))
    path = tmp_path / "again.csv"
    save_trajectory_csv(traj, path)
    text = path.read_text(encoding="utf-8")
    assert "180.0001" not in text                        # written wrapped
    back = load_trajectory_csv(path)
    np.testing.assert_allclose(back.lon, traj.lon, rtol=0, atol=1e-15)


def test_wrap_longitude():
    from covtool.nav.trajectory.core import wrap_longitude

    x = np.array([0.1, -math.pi, math.pi, 3 * math.pi / 2, -7.0])
    np.testing.assert_allclose(wrap_longitude(x), [0.1, -math.pi, -math.pi, -math.pi / 2, -7.0 + 2 * math.pi],
                               atol=1e-15)
    inside = np.linspace(-math.pi, math.pi, 1001)[:-1]
    np.testing.assert_array_equal(wrap_longitude(inside), inside)          # bit for bit


def test_flight_across_the_antimeridian_navigates_the_short_way():
    """A declared flight east across 180°: continuous inside, wrapped in files, nav error tiny."""
    import covtool.nav.strapdown as sd
    from covtool.nav.trajectory.flight import Segment, flight
    from covtool.nav.imu.simulator import ideal_increments

    segs = [Segment("stand", 2.0), Segment("fly", 20.0, to_speed=250.0, transition=2.0)]
    traj = flight(segs, lat=math.radians(60.0), lon=math.radians(179.98), h=1000.0, heading=math.radians(90.0),
                  dt=0.5)
    assert traj.lon[-1] > math.pi                                       # crossed, continuously
    assert np.all(np.diff(traj.lon) >= 0)
    df = traj.to_dataframe()
    assert df["lon [deg]"].iloc[-1] < -179.9 and df["lon [deg]"].iloc[0] == pytest.approx(179.98)
    hist = sd.run(sd.NavState.from_trajectory(traj), ideal_increments(traj, 100.0), 2, every=100)
    truth = sd.truth_state(traj, hist.t)
    for k in range(hist.t.size):
        err = sd.nav_errors(hist.state(k), sd.NavState(truth.t, truth.lat[k:k + 1], truth.lon[k:k + 1],
                                                         truth.h[k:k + 1], truth.v_n[k:k + 1], truth.q[k:k + 1],
                                                         np.zeros((1, 3)), np.zeros((1, 3))))
        _, rn = earth.radii(truth.lat[k])
        assert abs(err[0, 1]) * rn < 1e-3                               # < 1 mm east


def _holey(tmp_path, lv, start, stop, name="holey.csv"):
    df = lv.to_dataframe()
    keep = (df["t [s]"] <= start) | (df["t [s]"] >= stop)
    path = tmp_path / name
    df[keep].to_csv(path, index=False, float_format="%.17g")
    return path


def test_csv_gap_is_refused_with_file_row_and_gap(tmp_path, lv):
    """Before: a 100 s hole interpolated silently (pure INS azimuth 9.98′ → 7.06′ at 5 min); after: refused."""
    path = _holey(tmp_path, lv, 100.0, 200.0)
    with pytest.raises(TrajectoryError, match=r"holey\.csv: column 't \[s\]': row 102: a gap of 100 s after "
                                              r"t = 100 s, more than 1\.5 × the file's median step 1 s; 1 gap\(s\) "
                                              r"in all \(declare \[trajectory\] max_gap"):
        load_trajectory_csv(path)
    # one missing row is a gap too
    with pytest.raises(TrajectoryError, match=r"row 500: a gap of 2 s after t = 498 s"):
        load_trajectory_csv(_holey(tmp_path, lv, 498.0, 500.0, "one.csv"))
    # declared: interpolated, and still refused beyond the declared bound
    back = load_trajectory_csv(path, max_gap=100.0)
    assert back.n == lv.n - 99
    with pytest.raises(TrajectoryError, match=r"a gap of 100 s after t = 100 s, more than the declared max_gap 50 s"):
        load_trajectory_csv(path, max_gap=50.0)


def test_csv_gap_refused_by_a_study_before_computing(tmp_path, lv):
    from covtool.studies import run_study

    path = _holey(tmp_path, lv, 100.0, 200.0)
    decl = {"study": {"kind": "pure_ins", "name": "h", "duration": "5 min", "dt": "1 s"},
            "trajectory": {"csv": str(path)}, "truth": {"model": "sdins58"}}
    with pytest.raises(TrajectoryError, match=r"\[trajectory\]: .*holey\.csv: column 't \[s\]': row 102: a gap "
                                              r"of 100 s"):
        run_study(decl)
    decl["trajectory"]["max_gap"] = "-1 s"
    with pytest.raises(TrajectoryError, match=r"\[trajectory\]: max_gap: must be positive"):
        run_study(decl)


def test_csv_stationary_flag_must_match_the_motion(tmp_path, lv):
    """Before: stationary = 1 at 13 m/s accepted (ZUPTs applied); after: refused with the row."""
    df = lv.to_dataframe()
    r = int(np.argmax(np.abs(np.linalg.norm(lv.v_n, axis=1) - 13.0) < 0.5))      # a row at ~13 m/s
    speed = float(np.linalg.norm(lv.v_n[r]))
    df.loc[r, "stationary"] = 1
    path = tmp_path / "flag.csv"
    df.to_csv(path, index=False, float_format="%.17g")
    with pytest.raises(TrajectoryError, match=rf"flag\.csv: column 'stationary': row {r + 1}: flagged stationary "
                                              rf"\(1\) while the vehicle moves: speed {speed:.6g} m/s "
                                              r"\(tolerance 0\.01 m/s\); 1 such row\(s\)"):
        load_trajectory_csv(path)
    # turning on the spot: speed 0 but a yaw rate of 0.1 rad/s
    df = lv.to_dataframe()
    k = int(np.flatnonzero(df["stationary"] == 1)[5])
    df.loc[k, ["w_x [rad/s]", "w_y [rad/s]", "w_z [rad/s]"]] = [0.0, 0.0, -0.1]
    df.to_csv(path, index=False, float_format="%.17g")
    # at rest the gyros measure the Earth rate [Ω cos L, 0, −Ω sin L]:
    # |ω_nb| = |(−Ω cos L cos ψ, Ω cos L sin ψ, −0.1 + Ω sin L)| at any heading ψ (level)
    lat = math.radians(36.37)
    rate = math.hypot(earth.OMEGA_IE * math.cos(lat), 0.1 - earth.OMEGA_IE * math.sin(lat))
    with pytest.raises(TrajectoryError, match=rf"row {k + 1}: flagged stationary \(1\) while the vehicle moves: "
                                              rf"body rate w\.r\.t\. NED {rate:.6g} rad/s \(tolerance 0\.001 rad/s\)"):
        load_trajectory_csv(path)


def _good_lines(lv, n=6):
    text = lv.sample(lv.t[:n]).to_dataframe()[list(CSV_COLUMNS)].to_csv(index=False, float_format="%.17g")
    return text.splitlines()


@pytest.mark.parametrize("edit, match", [
    (lambda ls: ls[:4] + [ls[4].rsplit(",", 3)[0]] + ls[5:],
     r"bad\.csv: column 'w_x \[rad/s\]': row 4: missing: the line has 14 of the 17 cells of the header "
     r"\(truncated line\?\)"),
    (lambda ls: ls[:3] + [ls[3] + ",7"] + ls[4:], r"bad\.csv: row 3: the line has 18 cells, the header has 17"),
    (lambda ls: ls[:3] + [""] + ls[3:], r"bad\.csv: row 3: empty line"),
    (lambda ls: ls[:2] + [ls[2].replace(",", ";", 1)] + ls[3:],
     r"bad\.csv: column 'w_z \[rad/s\]': row 2: missing: the line has 16 of the 17"),
    (lambda ls: ls[:5] + [ls[5].replace("1", "1x", 1)] + ls[6:], r"bad\.csv: column '.*': row 5: '.*1x.*' is not a "
                                                                   r"number"),
])
def test_csv_line_errors_name_file_row_column(tmp_path, lv, edit, match):
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(edit(_good_lines(lv))) + "\n", encoding="utf-8")
    with pytest.raises(TrajectoryError, match=match):
        load_trajectory_csv(path)


def test_csv_truncated_last_line(tmp_path, lv):
    """Before: a file cut in the middle of its last number was read (issue 10 case 6)."""
    lines = _good_lines(lv)
    path = tmp_path / "cut.csv"
    path.write_text("\n".join(lines)[:-3], encoding="utf-8")
    with pytest.raises(TrajectoryError, match=r"cut\.csv: row 6: the last line has no line end: the file looks "
                                              r"truncated"):
        load_trajectory_csv(path)


def test_csv_size_limit_is_checked_before_reading(tmp_path, lv, monkeypatch):
    """A file over the limit is refused with its size and the limit, before any byte is parsed."""
    import covtool.io.csv_table as ct

    path = tmp_path / "lv.csv"
    save_trajectory_csv(lv, path)
    size = path.stat().st_size

    def no_read(*args, **kwargs):
        raise AssertionError("the file was read")

    monkeypatch.setattr(ct, "_scan", no_read)
    with pytest.raises(TrajectoryError, match=rf"lv\.csv: the file is .* \({size} bytes\), larger than the 100 kB "
                                              r"\(100000 bytes\) covtool reads; split or decimate it"):
        load_trajectory_csv(path, max_bytes=100_000)
    monkeypatch.setattr(ct, "MAX_BYTES", 1000)
    with pytest.raises(TrajectoryError, match=r"larger than the 1 kB \(1000 bytes\) covtool reads"):
        load_trajectory_csv(path)


def test_csv_reader_streams_in_blocks(tmp_path, lv, monkeypatch):
    """Blocks of a few rows give the same arrays as one block (the reader never holds the text)."""
    import covtool.io.csv_table as ct

    path = tmp_path / "lv.csv"
    save_trajectory_csv(lv, path)
    whole = load_trajectory_csv(path)
    monkeypatch.setattr(ct, "CHUNK_ROWS", 7)
    blocks = load_trajectory_csv(path)
    for key in ("t", "lat", "lon", "h", "v_n", "q_nb", "f_b", "w_ib_b", "distance"):
        np.testing.assert_array_equal(getattr(blocks, key), getattr(whole, key), err_msg=key)
    # an error in a late block still names its row
    lines = path.read_text(encoding="utf-8").splitlines()
    lines[1234] = lines[1234].replace(",", ",abc", 1)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    with pytest.raises(TrajectoryError, match=r"column 'lat \[deg\]': row 1234: 'abc.*' is not a number"):
        load_trajectory_csv(path)


def test_csv_file_level_errors(tmp_path):
    with pytest.raises(TrajectoryError, match=r"dir\.csv: is a directory, not a CSV file"):
        (tmp_path / "dir.csv").mkdir()
        load_trajectory_csv(tmp_path / "dir.csv")
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00t [s]\n\x00\x01\n")
    with pytest.raises(TrajectoryError, match=r"bin\.csv: not a readable CSV file \(not UTF-8 text: byte 0xff at "
                                              r"byte 0 in the header\)"):
        load_trajectory_csv(tmp_path / "bin.csv")
    header = ",".join(CSV_COLUMNS).encode() + b"\n"
    row = b",".join([b"1"] * 17) + b"\n"                # valid rows fill the first blocks
    (tmp_path / "latin.csv").write_bytes(header + row * 70000 + b"0,\xe9\n")
    with pytest.raises(TrajectoryError, match=rf"latin\.csv: not a readable CSV file \(not UTF-8 text: byte 0xe9 at "
                                              rf"byte {len(header) + len(row) * 70000 + 2} in row 70001\)"):
        load_trajectory_csv(tmp_path / "latin.csv")


def test_csv_longitude_out_of_range(tmp_path):
    path = _antimeridian_csv(tmp_path, lons=(179.9999, 540.0, 541.0))
    with pytest.raises(TrajectoryError, match=r"dateline\.csv: column 'lon \[deg\]': row 2: 540 deg is not within "
                                              r"±360 deg"):
        load_trajectory_csv(path)
