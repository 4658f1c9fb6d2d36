"""Measurement library (issue 15): every kind's H against the Jacobian of its nonlinear function.

Acceptance 1: the truth H (navigation columns and the measurement's own
error-state columns) equals the central-difference Jacobian of the nonlinear
residual ``M (predict(x + δx) − sensor(x, e))`` at many trajectory points,
to 1e-6 relative to the largest entry of the column block.  The land-vehicle
route gives turns, hills (pitch), stops and all four headings; lever arms of
metres on all three axes make every attitude column non-zero.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from covtool.lincov.measurements import KINDS, nav_point, place
from covtool.lincov.measurements.base import error_state
from covtool.lincov.reduced import zupt_matrices
from covtool.nav.trajectory.profiles import land_vehicle

LEVER = np.array([1.2, -0.7, 0.9])
#: error-state values of the order of their σ (the Jacobian is taken at e = 0)
SIGMA = {"length": 3.0, "dimensionless": 1e-3, "angle": 1e-2}


def measurement(kind: str):
    cls = KINDS[kind]
    states = tuple(error_state(kind, kind, sfx, SIGMA[dim], "markov", tau=100.0)
                   for sfx, (dim, _) in cls.ERRORS.items())
    return cls(name=kind, sigma=np.ones(len(cls.COMPONENTS)), states=states,
               lever_arm=LEVER if cls.LEVER else np.zeros(3))


@pytest.fixture(scope="module")
def points():
    traj = land_vehicle(dt=1.0)
    # every 37 s: cruising, turning, climbing, braking and standing, all headings
    return [nav_point(traj, k) for k in range(0, traj.n, 37)]


#: central-difference steps per navigation component (rad, rad, m, m/s ×3, quaternion ×4)
STEP = np.array([1e-7, 1e-7, 1e-2, 1e-3, 1e-3, 1e-3, 1e-5, 1e-5, 1e-5, 1e-5])


#: central-difference steps of the error states: a length enters a position of 6.4e6 m (radians × R), so a
#: smaller step drowns in the round-off of the latitude (1e-16 × 0.6 rad against step / R)
ERR_STEP = {"length": 1.0, "dimensionless": 1e-6, "angle": 1e-6}


def numerical_jacobian(meas, x, w):
    n_e = len(meas.states)
    e0 = np.zeros(n_e)
    J_nav = np.empty((meas.m, 10))
    for i in range(10):
        d = np.zeros(10)
        d[i] = STEP[i]
        J_nav[:, i] = (meas.residual(x, w, d, e0) - meas.residual(x, w, -d, e0)) / (2 * STEP[i])
    J_err = np.empty((meas.m, n_e))
    for j, s in enumerate(meas.states):
        h = ERR_STEP[s.dimension]
        ep, em = e0.copy(), e0.copy()
        ep[j], em[j] = h, -h
        J_err[:, j] = (meas.residual(x, w, np.zeros(10), ep) - meas.residual(x, w, np.zeros(10), em)) / (2 * h)
    return J_nav, J_err


def rel(a, b):
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_H_equals_numerical_jacobian(kind, points):
    meas = measurement(kind)
    worst_nav = worst_err = 0.0
    for x, w in points:
        H_nav, H_err = meas.jacobian(x, w)
        J_nav, J_err = numerical_jacobian(meas, x, w)
        assert H_nav.shape == (meas.m, 10) and H_err.shape == (meas.m, len(meas.states))
        worst_nav = max(worst_nav, rel(H_nav, J_nav))
        if meas.states:
            worst_err = max(worst_err, rel(H_err, J_err))
    assert worst_nav <= 1e-6, f"{kind}: navigation columns off by {worst_nav:.2e} (relative)"
    assert worst_err <= 1e-6, f"{kind}: error-state columns off by {worst_err:.2e} (relative)"


def test_every_kind_is_exercised_with_its_error_states():
    """The kinds with own error states have them all in the test (odometer 4, GNSS position 3, baro 2, heading 1)."""
    counts = {k: len(measurement(k).states) for k in KINDS}
    assert counts == {"zupt": 0, "cupt": 0, "odometer": 4, "nhc": 0, "gnss_position": 3, "gnss_velocity": 0,
                      "baro": 2, "heading": 1}


def test_zupt_H_is_seed_002_velocity_rows(points):
    """The generalised ZUPT's truth H over the 58-state names equals covtool's ZUPT matrix."""
    from covtool.studies.inputs import load_truth
    truth = load_truth({"truth": {"model": "sdins58"}}, "<test>", None)
    meas = measurement("zupt")
    x, w = points[5]
    H = place(*meas.jacobian(x, w), meas, truth.names)
    np.testing.assert_array_equal(H, zupt_matrices(truth.names))


def test_filter_H_is_truth_H_restricted_by_name(points):
    """A filter that drops the odometer scale factor has H_f = H D (its columns removed, others equal)."""
    meas = measurement("odometer")
    names = [f"n{i}" for i in range(10)] + meas.state_names
    kept = names[:10] + [s for s in meas.state_names if not s.endswith("_scale_factor")]
    x, w = points[3]
    H = place(*meas.jacobian(x, w), meas, names)
    Hf = place(*meas.jacobian(x, w), meas, kept)
    D = np.array([[1.0 if a == b else 0.0 for b in kept] for a in names])
    np.testing.assert_array_equal(Hf, H @ D)


def test_odometer_scale_factor_column_is_speed(points):
    """Closed form: ∂(sensor)/∂s = along-track speed; at a stop it vanishes (the scale factor is unobservable)."""
    meas = measurement("odometer")
    traj = land_vehicle(dt=1.0)
    for k in (100, 250):                      # cruising at 47.4 km/h; standing (stop on [210, 300] s)
        x, w = nav_point(traj, k)
        _, H_err = meas.jacobian(x, w)
        speed = np.linalg.norm(traj.v_n[k])
        j = meas.state_names.index("odometer_scale_factor")
        assert H_err[0, j] == pytest.approx(-speed, rel=1e-3, abs=1e-4)   # lever-arm rate ω × l < 1e-3 of it


def test_gnss_position_error_columns_are_minus_identity(points):
    """Residual in NED metres: the Markov NED error enters with −I (M M⁻¹ = I)."""
    meas = measurement("gnss_position")
    _, H_err = meas.jacobian(*points[7])
    np.testing.assert_allclose(H_err, -np.eye(3), atol=1e-15)


def test_error_state_declaration_refusals():
    with pytest.raises(ValueError, match="odometer has no error state 'bias'"):
        error_state("odo", "odometer", "bias", 1.0)
    with pytest.raises(ValueError, match="process 'markov_distance' is not one of"):
        error_state("baro", "baro", "bias", 1.0, "markov_distance")
    with pytest.raises(ValueError, match="a Markov state needs a positive correlation time"):
        error_state("baro", "baro", "bias", 1.0, "markov")


def test_heading_residual_wraps():
    """A heading residual across ±180° is the short way round."""
    meas = measurement("heading")
    q = np.array([math.cos(math.radians(179.5) / 2), 0, 0, math.sin(math.radians(179.5) / 2)])
    x = np.concatenate([[0.6, 2.2, 10.0, 0, 0, 0], q])
    dx = np.zeros(10)
    q2 = np.array([math.cos(math.radians(-179.5) / 2), 0, 0, math.sin(math.radians(-179.5) / 2)])
    dx[6:] = q2 - q
    r = meas.residual(x, np.zeros(3), dx, np.zeros(1))
    assert r[0] == pytest.approx(math.radians(1.0), rel=1e-9)


def test_residual_on_strapdown_states_is_linear_to_second_order():
    """With the strapdown's own error definition (nav_errors: computed − true, δq = q̂ − q), the nonlinear
    residual of a perturbed navigation solution is H δx to second order: halving the error halves the
    residual and quarters the departure from H δx (for every kind, errors of 100 m, 0.3 m/s, 2 mrad)."""
    from covtool.nav import attitude as quat, strapdown as sd
    traj = land_vehicle(dt=1.0)
    k = 130                                                   # in the first turn: every term is active
    truth = sd.truth_state(traj, [traj.t[k]])
    x, w = nav_point(traj, k)
    dpos = np.array([100.0 / 6.4e6, -80.0 / 6.4e6, 30.0])
    dv = np.array([0.3, -0.2, 0.1])
    rot = quat.from_rotvec(np.array([2e-3, -1.5e-3, 2e-3]))
    for kind in sorted(KINDS):
        meas = measurement(kind)
        e = np.zeros(len(meas.states))
        departures = []
        for scale in (1.0, 0.5):
            q_hat = quat.mul(rot if scale == 1.0 else quat.from_rotvec(0.5 * quat.to_rotvec(rot)), truth.q[0])
            est = truth.replace(lat=truth.lat + scale * dpos[0], lon=truth.lon + scale * dpos[1],
                                h=truth.h + scale * dpos[2], v_n=truth.v_n + scale * dv, q=q_hat[None, :])
            dx = sd.nav_errors(est, truth)[0]
            r = meas.residual(x, w, dx, e)
            x_hat = np.concatenate([[est.lat[0], est.lon[0], est.h[0]], est.v_n[0], est.q[0]])
            np.testing.assert_allclose(r, meas.scale(x) @ (meas.predict(x_hat, w) - meas.sensor(x, w, e)),
                                       rtol=1e-12, atol=1e-12)
            H_nav, _ = meas.jacobian(x, w)
            departures.append((np.linalg.norm(r - H_nav @ dx), np.linalg.norm(H_nav @ dx)))
        (d1, l1), (d2, l2) = departures
        assert d1 < 0.05 * l1, f"{kind}: the linearisation is off by {d1 / l1:.1e} at these errors"
        if d1 > 1e-9 * l1:
            assert 0.2 < d2 / d1 < 0.3, f"{kind}: second-order ratio {d2 / d1:.3f}, expected 1/4"


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_stacked_innovation_equals_each_points_own(kind, points):
    """``innovation`` of a stack of estimates (a Monte Carlo's runs, covtool.validation.aided) equals the
    residual of each estimate alone, for every kind, with error states of the order of their σ."""
    meas = measurement(kind)
    rng = np.random.default_rng(7)
    for x, w in points[::5]:
        M = 9
        xh = x + rng.standard_normal((M, 10)) * STEP * 30.0
        e = rng.standard_normal((M, len(meas.states))) * np.array([SIGMA[s.dimension] for s in meas.states])
        z = meas.innovation(x, w, xh, e)
        assert z.shape == (M, meas.m)
        # the innovation is a small difference of large readings: round-off is relative to the readings
        size = max(1.0, float(np.abs(meas.predict(x, w) @ meas.scale(x).T).max()))
        for m in range(M):
            own = meas.residual(x, w, xh[m] - x, e[m])
            np.testing.assert_allclose(z[m], own, rtol=1e-12, atol=4e-15 * size)
        assert np.all(np.ptp(z, axis=0) > 0)                          # the runs differ


def test_stacked_heading_innovation_wraps():
    """A Monte Carlo run whose computed heading is across ±180° from the truth takes the short way round."""
    meas = measurement("heading")
    q = np.array([math.cos(math.radians(179.5) / 2), 0, 0, math.sin(math.radians(179.5) / 2)])
    x = np.concatenate([[0.6, 2.2, 10.0, 0, 0, 0], q])
    xh = np.tile(x, (3, 1))
    for m, deg in enumerate((-179.5, 179.0, 178.0)):
        xh[m, 6:] = [math.cos(math.radians(deg) / 2), 0, 0, math.sin(math.radians(deg) / 2)]
    z = meas.innovation(x, np.zeros(3), xh, np.zeros((3, 1)))
    np.testing.assert_allclose(z[:, 0], np.radians([1.0, -0.5, -1.5]), rtol=1e-9)
