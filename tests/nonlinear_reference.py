"""Independent nonlinear navigation equations with injected errors (test oracle).

Written directly from the navigation equations (Titterton & Weston 2004, §3.7)
and the sensor error equations of seed 002, eq (3) and (5), in explicit matrix
form, without using covtool.lincov.dynamics.  Used by the Jacobian and
linear-vs-nonlinear tests.
"""

from __future__ import annotations

import numpy as np

from covtool.nav import earth
from covtool.nav import attitude as quat


def _vals(model, x, prefix, n):
    ix = model.index
    return np.array([x[ix[f"{prefix}_{s}"]] if f"{prefix}_{s}" in ix else 0.0 * x[0] for s in n])


def corrupt(model, x, f, w):
    """Measured specific force and rate from true ones and error states ``x``."""
    ax = ("x", "y", "z")
    b = _vals(model, x, "acc_bias", ax) + _vals(model, x, "acc_markov", ax)
    K = np.diag(_vals(model, x, "acc_sf", ax))
    Ka = _vals(model, x, "acc_asym", ax)
    Ma = np.zeros((3, 3), dtype=x.dtype)
    Mg = np.zeros((3, 3), dtype=x.dtype)
    for i, a in enumerate(ax):
        for j, c in enumerate(ax):
            if i != j:
                Ma[i, j] = _vals(model, x, "acc_mis", [a + c])[0]
                Mg[i, j] = _vals(model, x, "gyro_mis", [a + c])[0]
    ad = _vals(model, x, "acc_ad", ax)
    tau_ad = np.array([s.tau for s in model.states if s.kind == "ad_reset_velocity"] or [1.0, 1.0, 1.0])
    f_hat = f + K @ f + Ma @ f + b + Ka * np.abs(f) - ad / tau_ad
    wd = _vals(model, x, "gyro_bias", ax) + _vals(model, x, "gyro_markov", ax)
    T = np.diag(_vals(model, x, "gyro_sf", ax))
    gs = _vals(model, x, "gyro_gs", ["xx", "xy", "yy", "yz", "zz", "zx"])
    an = _vals(model, x, "gyro_aniso", ax)
    spin = [1, 2, 0]
    g_sens = np.array([gs[2 * i] * f[i] + gs[2 * i + 1] * f[spin[i]] for i in range(3)])
    aniso = np.array([an[i] * f[i] * f[spin[i]] for i in range(3)])
    w_hat = w + T @ w + Mg @ w + wd + g_sens + aniso
    return f_hat, w_hat


def dcm(q):
    """C_b^n of the normalised quaternion, written out (complex-step safe)."""
    q = q / np.sqrt(np.sum(q * q))
    q0, q1, q2, q3 = q
    return np.array([
        [q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3, 2 * (q1 * q2 - q0 * q3), 2 * (q1 * q3 + q0 * q2)],
        [2 * (q1 * q2 + q0 * q3), q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3, 2 * (q2 * q3 - q0 * q1)],
        [2 * (q1 * q3 - q0 * q2), 2 * (q2 * q3 + q0 * q1), q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3],
    ])


def nav_rates(lat, lon, h, v, q, f_b, w_b, dist_n=np.zeros(3)):
    """(L̇, l̇, ḣ, v̇, q̇) of the navigation equations."""
    pr = earth.position_rates(lat, h, v)
    w_ie = earth.earth_rate_n(lat)
    w_en = earth.transport_rate_n(lat, h, v)
    C = dcm(q)
    vdot = C @ f_b - np.cross(2 * w_ie + w_en, v) + earth.gravity_n(lat, h) + dist_n
    qdot = 0.5 * quat.mul(q, np.r_[0.0, w_b]) - 0.5 * quat.mul(np.r_[0.0, w_ie + w_en], q)
    return np.concatenate([pr, vdot, qdot])


def error_rates(model, x, lat, lon, h, v, q, f_b, w_b):
    """Nonlinear δẋ = rates(computed) − rates(true), plus sensor-state dynamics."""
    ix = model.index
    g = earth.gravity(lat, h)
    dist = np.zeros(3)
    if "grav_xi" in ix:
        # true gravity = normal + disturbance [−gξ, −gη, Δg]; the INS knows only normal gravity
        dist = np.array([-g * x[ix["grav_xi"]], -g * x[ix["grav_eta"]], x[ix["grav_dg"]]])
    f_hat, w_hat = corrupt(model, x, f_b, w_b)
    true = nav_rates(lat, lon, h, v, q, f_b, w_b, dist)
    comp = nav_rates(lat + x[0], lon + x[1], h + x[2], v + x[3:6], q + x[6:10], f_hat, w_hat)
    out = np.zeros(model.n, dtype=np.result_type(x, float))
    out[:10] = comp - true
    speed = np.linalg.norm(v[:2])
    for i, s in enumerate(model.states[10:], start=10):
        if s.process == "markov":
            out[i] = -x[i] / s.tau
        elif s.process == "markov_distance":
            out[i] = -speed / s.distance * x[i]
    return out


def numerical_jacobian(model, lat, lon, h, v, q, f_b, w_b, step=1e-30):
    """Complex-step Jacobian of :func:`error_rates` at x = 0.

    ``J[:, j] = Im(δẋ(i·h·e_j)) / h`` is free of subtractive cancellation, so it
    is accurate to machine precision (Squire & Trapp 1998); ``h = 1e-30``.
    """
    n = model.n
    J = np.zeros((n, n))
    for j in range(n):
        dx = np.zeros(n, dtype=complex)
        dx[j] = 1j * step
        J[:, j] = error_rates(model, dx, lat, lon, h, v, q, f_b, w_b).imag / step
    return J


# ---------------------------------------------------------------------------
# Additions for the physics-validation suite (issue 2).  Same equations as
# above, in the forms the tests need: a generic complex step, real central
# differences, the Earth-rate Coriolis term on its own, and vectorised
# corruption and navigation rates for a batched RK4 strapdown integration.
# ---------------------------------------------------------------------------


def complex_step_jacobian(fun, n, step=1e-30):
    """Complex-step Jacobian ``∂fun/∂x`` at x = 0 of ``fun: C^n → C^m``."""
    cols = []
    for j in range(n):
        dx = np.zeros(n, dtype=complex)
        dx[j] = 1j * step
        cols.append(np.asarray(fun(dx)).imag / step)
    return np.stack(cols, axis=-1)


def central_difference_jacobian(model, lat, lon, h, v, q, f_b, w_b, steps):
    """Real central-difference Jacobian of :func:`error_rates` at x = 0.

    ``J[:, j] = (δẋ(s_j e_j) − δẋ(−s_j e_j)) / (2 s_j)``; truncation error
    O(s_j²), round-off O(ε |rates| / s_j).
    """
    n = model.n
    J = np.zeros((n, n))
    for j in range(n):
        dx = np.zeros(n)
        dx[j] = steps[j]
        J[:, j] = (error_rates(model, dx, lat, lon, h, v, q, f_b, w_b)
                   - error_rates(model, -dx, lat, lon, h, v, q, f_b, w_b)) / (2.0 * steps[j])
    return J


def coriolis_error(lat, v, x):
    """Error of the Earth-rate Coriolis term ``−2 ω_ie × v`` caused by the nav errors ``x``.

    Returns the 10-vector (zero except the velocity rows) of
    ``c(L + δL, v + δv) − c(L, v)`` with ``c = −2 ω_ie^n(L) × v``: the part of
    the velocity error rate that filter B3 (``NavOptions(coriolis=False)``) drops.
    """
    c_hat = -np.cross(2.0 * earth.earth_rate_n(lat + x[0]), v + x[3:6])
    c = -np.cross(2.0 * earth.earth_rate_n(lat), v)
    out = np.zeros(10, dtype=np.result_type(x, float))
    out[3:6] = c_hat - c
    return out


def corrupt_many(model, x, f, w):
    """:func:`corrupt` for many samples at once: ``f``, ``w`` of shape (M, 3).

    Same sensor-error equations (seed 002 eq (3), (5)) written with the time
    axis first; ``test_linear_vs_nonlinear`` checks it against :func:`corrupt`.
    """
    f = np.asarray(f, float)
    w = np.asarray(w, float)
    ax = ("x", "y", "z")
    b = _vals(model, x, "acc_bias", ax) + _vals(model, x, "acc_markov", ax)
    K = np.diag(_vals(model, x, "acc_sf", ax))
    Ka = _vals(model, x, "acc_asym", ax)
    Ma = np.zeros((3, 3))
    Mg = np.zeros((3, 3))
    for i, a in enumerate(ax):
        for j, c in enumerate(ax):
            if i != j:
                Ma[i, j] = _vals(model, x, "acc_mis", [a + c])[0]
                Mg[i, j] = _vals(model, x, "gyro_mis", [a + c])[0]
    ad = _vals(model, x, "acc_ad", ax)
    tau_ad = np.array([s.tau for s in model.states if s.kind == "ad_reset_velocity"] or [1.0, 1.0, 1.0])
    f_hat = f + f @ (K + Ma).T + b + Ka * np.abs(f) - ad / tau_ad
    wd = _vals(model, x, "gyro_bias", ax) + _vals(model, x, "gyro_markov", ax)
    T = np.diag(_vals(model, x, "gyro_sf", ax))
    gs = _vals(model, x, "gyro_gs", ["xx", "xy", "yy", "yz", "zz", "zx"])
    an = _vals(model, x, "gyro_aniso", ax)
    spin = [1, 2, 0]
    g_sens = np.stack([gs[2 * i] * f[:, i] + gs[2 * i + 1] * f[:, spin[i]] for i in range(3)], -1)
    aniso = np.stack([an[i] * f[:, i] * f[:, spin[i]] for i in range(3)], -1)
    w_hat = w + w @ (T + Mg).T + wd + g_sens + aniso
    return f_hat, w_hat


def _dcm_many(q):
    q = q / np.sqrt(np.sum(q * q, axis=-1, keepdims=True))
    q0, q1, q2, q3 = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3, 2 * (q1 * q2 - q0 * q3), 2 * (q1 * q3 + q0 * q2)], -1),
        np.stack([2 * (q1 * q2 + q0 * q3), q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3, 2 * (q2 * q3 - q0 * q1)], -1),
        np.stack([2 * (q1 * q3 - q0 * q2), 2 * (q2 * q3 + q0 * q1), q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3], -1),
    ], -2)


def nav_rates_many(y, f_b, w_b):
    """:func:`nav_rates` for a batch of navigation states.

    Parameters
    ----------
    y : ndarray, shape (S, 10)
        ``[L, l, h, v_N, v_E, v_D, q0, q1, q2, q3]`` of S systems.
    f_b, w_b : ndarray, shape (S, 3)
        Specific force and body rate each system uses.

    Returns
    -------
    ndarray, shape (S, 10)
    """
    lat, h, v, q = y[:, 0], y[:, 2], y[:, 3:6], y[:, 6:10]
    pr = earth.position_rates(lat, h, v)
    w_ie = earth.earth_rate_n(lat)
    w_en = earth.transport_rate_n(lat, h, v)
    vdot = (np.einsum("sij,sj->si", _dcm_many(q), f_b) - np.cross(2 * w_ie + w_en, v)
            + earth.gravity_n(lat, h))
    w_in = w_ie + w_en
    zero = np.zeros((y.shape[0], 1))
    qdot = 0.5 * quat.mul(q, np.hstack([zero, w_b])) - 0.5 * quat.mul(np.hstack([zero, w_in]), q)
    return np.hstack([pr, vdot, qdot])


def integrate_nav(y0, f_b, w_b, dt):
    """Classical RK4 strapdown integration of :func:`nav_rates_many`.

    Parameters
    ----------
    y0 : ndarray, shape (S, 10)
        Initial navigation states.
    f_b, w_b : ndarray, shape (S, 2K+1, 3)
        Measured specific force and rate at the step ends and mid-points
        ``t_0, t_0 + dt/2, …, t_0 + K dt`` (the RK4 stage times).
    dt : float
        Step. [s]

    Returns
    -------
    ndarray, shape (K+1, S, 10)
        States at ``t_0 + k dt``.
    """
    K = (f_b.shape[1] - 1) // 2
    out = np.empty((K + 1,) + y0.shape)
    y = out[0] = np.asarray(y0, float)
    for k in range(K):
        a, m, b = 2 * k, 2 * k + 1, 2 * k + 2
        k1 = nav_rates_many(y, f_b[:, a], w_b[:, a])
        k2 = nav_rates_many(y + 0.5 * dt * k1, f_b[:, m], w_b[:, m])
        k3 = nav_rates_many(y + 0.5 * dt * k2, f_b[:, m], w_b[:, m])
        k4 = nav_rates_many(y + dt * k3, f_b[:, b], w_b[:, b])
        y = out[k + 1] = y + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return out
