"""Linear error model against nonlinear strapdown propagation (issue 2, item 4).

Deterministic injection, one error source at a time, on the 30-min land
vehicle route (pyins ``test_propagate_errors`` in spirit):

* **truth**: the route itself, exact at any time (``Trajectory.sample``);
* **computed**: the full nonlinear navigation equations (position, velocity
  with the vertical channel, quaternion; :mod:`nonlinear_reference`) driven
  by the corrupted ``f̂, ω̂`` of :func:`nonlinear_reference.corrupt` and
  started from the true state plus the initial error, integrated by
  classical RK4 at 0.2 s with the IMU sampled exactly at the stage times;
* **linear**: ``x(t) = Φ(t, 0) x0`` with Φ the product of covtool's Van Loan
  transitions at 1 s (``truth_system``: F at the step mid-points).

Each source is injected at its 1σ value of ``models/sdins58.toml``: small
enough that the second-order terms stay below 0.2 %, large enough that the
RK4 error (measured on an uncorrupted run: 0.8 mm after 30 min) is < 0.05 %
of every compared error (the smallest, 12.9 m).

Compared at 30 min (errors = computed − true):

* horizontal position error vector [m]: ``|e_nl − e_lin| ≤ 2 % |e_lin|``;
* altitude error, where it exceeds 10 m (the 1σ sources below that only
  reach the vertical channel through second-order terms);
* azimuth error, where it exceeds 0.1 arcmin.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import nonlinear_reference as nr
from covtool.nav import earth
from covtool.nav import attitude as quat
from covtool.io.model_file import load_model
from covtool.studies.grid import time_grid, truth_system
from covtool.nav.trajectory.profiles import land_vehicle

SDINS58 = Path(__file__).resolve().parents[1] / "models" / "sdins58.toml"

DURATION = 1800.0
RK4_DT = 0.2
LINEAR_DT = 1.0
TOL = 0.02
ALT_MEANINGFUL = 10.0                      # [m]
AZ_MEANINGFUL = np.radians(0.1 / 60.0)     # [rad]
ARCMIN = np.radians(1.0 / 60.0)

#: case -> (state, multiple of its 1σ); dq states are declared for the body
#: aligned with NED and carried to the initial attitude (Model.initial_covariance)
SOURCES = {
    "accel bias x": ("acc_bias_x", 1.0),
    "accel bias z": ("acc_bias_z", 1.0),
    "gyro bias x": ("gyro_bias_x", 1.0),
    "gyro bias z": ("gyro_bias_z", 1.0),
    "accel scale factor z": ("acc_sf_z", 1.0),
    "gyro scale factor z": ("gyro_sf_z", 1.0),
    "accel misalignment xz": ("acc_mis_xz", 1.0),
    "gyro misalignment xz": ("gyro_mis_xz", 1.0),
    "gyro misalignment yz": ("gyro_mis_yz", 1.0),
    "gyro g-sensitivity zz": ("gyro_gs_zz", 1.0),
    "initial azimuth": ("dq3", 1.0),
    "initial tilt": ("dq1", 1.0),
}
#: a 50σ (4.2 deg) initial azimuth error: the linear model must visibly break
LARGE = {"initial azimuth x50": ("dq3", 50.0)}


@pytest.fixture(scope="module")
def model():
    return load_model(SDINS58)


@pytest.fixture(scope="module")
def route():
    return land_vehicle(dt=1.0)


def _initial_error(model, state, k, q0):
    x = np.zeros(model.n)
    sigma = model.states[model.index[state]].sigma
    assert sigma > 0
    if state.startswith("dq"):
        ref = np.zeros(4)
        ref[int(state[2])] = k * sigma
        x[6:10] = quat.mul(ref, q0)
    else:
        x[model.index[state]] = k * sigma
    return x


def _ned(dy, lat, h):
    """(δL, δl, δh) → north, east, down error [m]."""
    rm, rn = earth.radii(lat)
    return np.stack([dy[..., 0] * (rm + h), dy[..., 1] * (rn + h) * np.cos(lat), -dy[..., 2]], -1)


def _attitude_error(q_hat, q):
    """φ (north tilt, east tilt, azimuth) with Ĉ = (I − [φ×]) C: q̂ ⊗ q* = (1, −φ/2)."""
    d = quat.mul(q_hat / np.linalg.norm(q_hat, axis=-1, keepdims=True), quat.conj(q))
    d = np.where(d[..., :1] < 0, -d, d)
    return -2.0 * d[..., 1:] / d[..., :1]


@pytest.fixture(scope="module")
def runs(model, route):
    """Nonlinear and linear errors of every case at the 1-s grid."""
    cases = {**SOURCES, **LARGE}
    K = int(round(DURATION / RK4_DT))
    stage_t = np.linspace(0.0, DURATION, 2 * K + 1)
    imu = route.sample(stage_t)
    q0 = imu.q_nb[0]
    X0 = np.array([_initial_error(model, s, k, q0) for s, k in cases.values()])
    # corrupted IMU of each case, plus one clean run that measures the RK4 error
    f_hat = np.empty((len(cases) + 1, stage_t.size, 3))
    w_hat = np.empty_like(f_hat)
    for c, x in enumerate(X0):
        f_hat[c], w_hat[c] = nr.corrupt_many(model, x, imu.f_b, imu.w_ib_b)
    f_hat[-1], w_hat[-1] = imu.f_b, imu.w_ib_b
    y_true0 = np.r_[imu.lat[0], imu.lon[0], imu.h[0], imu.v_n[0], q0]
    Y0 = np.tile(y_true0, (len(cases) + 1, 1))
    Y0[:-1] += X0[:, :10]
    Y = nr.integrate_nav(Y0, f_hat, w_hat, RK4_DT)
    # sub-sample to the 1-s grid of the linear model
    t = time_grid(DURATION, LINEAR_DT)
    step = int(round(LINEAR_DT / RK4_DT))
    Y = Y[::step]
    truth = route.sample(t)
    y_true = np.column_stack([truth.lat, truth.lon, truth.h, truth.v_n, truth.q_nb])
    lat, h = truth.lat[:, None], truth.h[:, None]
    nl_pos = _ned(Y[:, :-1] - y_true[:, None, :], lat, h)
    nl_att = _attitude_error(Y[:, :-1, 6:10], truth.q_nb[:, None, :])
    clean = _ned(Y[:, -1] - y_true, truth.lat, truth.h)
    # linear: x_{k+1} = Φ_k x_k
    _, _, Phi, _ = truth_system(model.only([]), route, t, "van_loan")
    X = np.empty((t.size, model.n, len(cases)))
    X[0] = X0.T
    for k in range(t.size - 1):
        X[k + 1] = Phi[k] @ X[k]
    X = np.swapaxes(X, 1, 2)
    lin_pos = _ned(X[..., :3], lat, h)
    lin_att = np.einsum("tij,tcj->tci", quat.attitude_error_matrix(truth.q_nb), X[..., 6:10])
    names = list(cases)
    return {"names": names, "t": t, "nl_pos": nl_pos, "lin_pos": lin_pos, "nl_att": nl_att,
            "lin_att": lin_att, "clean": clean, "X0": X0}


def _case(runs, name):
    c = runs["names"].index(name)
    return {k: runs[k][:, c] for k in ("nl_pos", "lin_pos", "nl_att", "lin_att")}


def test_corrupt_many_matches_corrupt(model):
    """The vectorised sensor corruption equals the per-sample reference."""
    rng = np.random.default_rng(7)
    x = np.zeros(model.n)
    x[10:] = rng.normal(size=model.n - 10) * np.array([s.sigma for s in model.states[10:]])
    f = rng.normal(size=(5, 3)) * 5.0
    w = rng.normal(size=(5, 3)) * 0.1
    fm, wm = nr.corrupt_many(model, x, f, w)
    for k in range(5):
        fk, wk = nr.corrupt(model, x, f[k], w[k])
        np.testing.assert_allclose(fm[k], fk, rtol=0, atol=1e-15 * np.abs(f[k]).max())
        np.testing.assert_allclose(wm[k], wk, rtol=0, atol=1e-15 * np.abs(w[k]).max())


def test_integration_error_is_negligible(runs):
    """RK4 at 0.2 s reproduces the exact route to < 1 cm after 30 min (uncorrupted run)."""
    assert np.max(np.abs(runs["clean"])) < 0.01
    smallest = min(np.linalg.norm(_case(runs, n)["lin_pos"][-1, :2]) for n in SOURCES)
    # measured 0.8 mm against a smallest compared error of 12.9 m (6e-5)
    assert np.max(np.abs(runs["clean"])) < 5e-4 * smallest


@pytest.mark.parametrize("name", list(SOURCES))
def test_horizontal_position_error_at_30_min(runs, name):
    """Horizontal position error vector: nonlinear = linear within 2 % at 30 min.

    Measured at 30 min: initial azimuth 0.155 %, gyro scale factor z 0.060 %,
    every other source ≤ 0.02 %.  Over the whole run the difference also
    stays within 2 % of the largest linear error so far plus 1 cm (RK4 and
    1-s discretisation allowance); measured ≤ 1.1 % (gyro scale factor z,
    early in the run).
    """
    c = _case(runs, name)
    e_nl, e_lin = c["nl_pos"][:, :2], c["lin_pos"][:, :2]
    dev = np.linalg.norm(e_nl[-1] - e_lin[-1]) / np.linalg.norm(e_lin[-1])
    assert dev <= TOL, f"{name}: {100 * dev:.3f} % (|e_lin| = {np.linalg.norm(e_lin[-1]):.2f} m)"
    running = np.maximum.accumulate(np.linalg.norm(e_lin, axis=1))
    assert np.all(np.linalg.norm(e_nl - e_lin, axis=1) <= TOL * running + 0.01)
    assert np.linalg.norm(e_lin[-1]) > 1.0          # a real, resolvable error


@pytest.mark.parametrize("name", list(SOURCES))
def test_altitude_error_at_30_min(runs, name):
    """Altitude error (vertical channel included) within 2 % where it exceeds 10 m.

    Measured: accel bias z (1029 m) 0.005 %, accel scale factor z (1199 m)
    0.006 %, initial tilt (219 m) 0.011 %, gyro misalignment yz (96 m)
    0.043 %, gyro bias x (12 m) 0.015 %, accel misalignment xz (13 m)
    0.010 %.
    """
    c = _case(runs, name)
    d_nl, d_lin = c["nl_pos"][-1, 2], c["lin_pos"][-1, 2]
    if abs(d_lin) < ALT_MEANINGFUL:
        # second-order only: below 1 m absolute disagreement
        assert abs(d_nl - d_lin) < 1.0
        return
    dev = abs(d_nl - d_lin) / abs(d_lin)
    assert dev <= TOL, f"{name}: {100 * dev:.3f} % (δh_lin = {-d_lin:.1f} m)"


@pytest.mark.parametrize("name", list(SOURCES))
def test_azimuth_error_at_30_min(runs, name):
    """Azimuth error within 2 % where it exceeds 0.1 arcmin.

    Measured: initial azimuth (9.9') 0.008 %, gyro bias z (0.75') 0.001 %,
    gyro scale factor z (0.74') 0.007 %, initial tilt (0.59') 0.003 %,
    gyro g-sensitivity zz (0.30') 0.002 %, gyro misalignment yz (0.21')
    0.016 %.
    """
    c = _case(runs, name)
    a_nl, a_lin = c["nl_att"][-1, 2], c["lin_att"][-1, 2]
    if abs(a_lin) < AZ_MEANINGFUL:
        assert abs(a_nl - a_lin) < 0.01 * ARCMIN
        return
    dev = abs(a_nl - a_lin) / abs(a_lin)
    assert dev <= TOL, f"{name}: {100 * dev:.3f} % (ψ_lin = {a_lin / ARCMIN:.3f} arcmin)"


def test_every_kind_of_source_is_covered(runs, model):
    """Accel, gyro, scale factor, misalignment and initial attitude are all tested."""
    kinds = {model.states[model.index[s]].kind for s, _ in SOURCES.values()}
    assert {"accel_bias", "gyro_bias", "accel_scale_factor", "gyro_scale_factor", "accel_misalignment",
            "gyro_misalignment", "navigation"} <= kinds
    # the vertical channel is exercised: two sources drive it past 1 km
    big = [n for n in SOURCES if abs(_case(runs, n)["lin_pos"][-1, 2]) > 1000.0]
    assert len(big) >= 2


def test_large_error_breaks_linearity(runs):
    """The comparison can fail: a 4.2° initial azimuth error is visibly nonlinear.

    Its second-order terms (∝ ψ²) exceed the 2 % tolerance at 30 min
    (measured 7.1 %), while the 1σ (5 arcmin) case agrees to 0.16 %.
    """
    c = _case(runs, "initial azimuth x50")
    dev = np.linalg.norm(c["nl_pos"][-1, :2] - c["lin_pos"][-1, :2]) / np.linalg.norm(c["lin_pos"][-1, :2])
    assert dev > TOL
