"""The numpy reference mechanization: one navigation interval.

:func:`step` advances every run by one interval: body increments with the
n-sample + 1-previous coning and sculling of seed 001, eq (1)–(4)
(:mod:`covtool.nav.coning`), then the second-order navigation-frame update
of :func:`_nav_core` (the algorithm in the notes of
:mod:`covtool.nav.strapdown`).  :func:`_nav_core` is the reference the
compiled kernels of :mod:`covtool.nav.strapdown.kernels` are tested against.
"""
from __future__ import annotations

import numpy as np

from covtool.nav import earth
from covtool.nav.coning import body_increments, body_position_increment, MAX_SAMPLES
from covtool.nav.strapdown.state import NavState, _pack, _unpack


def _rotvec_quat(phi):
    """Quaternion of rotation vectors, shape (M, 4) (series near zero)."""
    a2 = np.einsum("...k,...k->...", phi, phi)
    small = a2 < 1e-8
    a = np.sqrt(a2)
    c = np.cos(0.5 * a)
    s = np.where(small, 0.5 - a2 / 48.0, np.sin(0.5 * a) / np.where(small, 1.0, a))
    out = np.empty(phi.shape[:-1] + (4,))
    out[..., 0] = c
    out[..., 1:] = s[..., None] * phi
    return out


def _nav_core(x, qb, u, r, T):
    """One navigation-frame update on component arrays (module notes).

    ``x = (L, l, h, v_N, v_E, v_D, q0, q1, q2, q3)``, ``qb`` the components
    of ``exp(φ/2)``, ``u`` those of ``Δv_b`` and ``r`` those of the
    position-weighted increment (:func:`body_position_increment`); each an
    array of shape (M,).  Written out component by component because the
    run loop is dominated by per-call overhead on small arrays.
    """
    lat, lon, h, vn, ve, vd, q0, q1, q2, q3 = x
    b0, b1, b2, b3 = qb
    W, E2, A = earth.OMEGA_IE, earth.E2, earth.A

    def rotate(ux, uy, uz):
        # C(q) u = u + q0 t + qv × t, t = 2 qv × u
        tx = 2.0 * (q2 * uz - q3 * uy)
        ty = 2.0 * (q3 * ux - q1 * uz)
        tz = 2.0 * (q1 * uy - q2 * ux)
        return (ux + q0 * tx + (q2 * tz - q3 * ty), uy + q0 * ty + (q3 * tx - q1 * tz),
                uz + q0 * tz + (q1 * ty - q2 * tx))

    nx, ny, nz = rotate(*u)

    def rates_at(la, hh):
        sl, cl = np.sin(la), np.cos(la)
        s2 = sl * sl
        w = 1.0 - E2 * s2
        sw = np.sqrt(w)
        rnh = A / sw + hh
        rmh = A * (1.0 - E2) / (w * sw) + hh
        g0 = earth.GAMMA_E * (1.0 + earth.K_SOMIGLIANA * s2) / sw
        g = g0 * (1.0 - 2.0 * hh / A * (1.0 + earth.F + earth.M_RATIO - 2.0 * earth.F * s2)
                  + 3.0 * hh * hh / (A * A))
        return sl, cl, rnh, rmh, g

    def gravity_coriolis(sl, cl, rnh, rmh, g, wn_, we_, wd_):
        # ζ = ω_in T from the transport-rate velocity w*_, and [g − (2ω_ie + ω_en) × w] T
        t_ = sl / cl
        zn = (W * cl + we_ / rnh) * T
        ze = (-wn_ / rmh) * T
        zd = (-W * sl - we_ * t_ / rnh) * T
        cn, ce, cd = zn + W * cl * T, ze, zd - W * sl * T
        return (zn, ze, zd), (-(ce * wd_ - cd * we_), -(cd * wn_ - cn * wd_), -(cn * we_ - ce * wn_) + g * T)

    def velocity(z, gc):
        zn, ze, zd = z
        return (vn + nx - 0.5 * (ze * nz - zd * ny) + gc[0],
                ve + ny - 0.5 * (zd * nx - zn * nz) + gc[1],
                vd + nz - 0.5 * (zn * ny - ze * nx) + gc[2])

    # predictor with the start-of-interval rates
    sl, cl, rnh, rmh, g = rates_at(lat, h)
    v1n, v1e, v1d = velocity(*gravity_coriolis(sl, cl, rnh, rmh, g, vn, ve, vd))
    lat_m = lat + 0.25 * T * (vn + v1n) / rmh
    h_m = h - 0.25 * T * (vd + v1d)
    # corrector with the mid-interval rates
    sl, cl, rnh, rmh, g = rates_at(lat_m, h_m)
    z, gc = gravity_coriolis(sl, cl, rnh, rmh, g, 0.5 * (vn + v1n), 0.5 * (ve + v1e), 0.5 * (vd + v1d))
    zn, ze, zd = z
    v1n, v1e, v1d = velocity(z, gc)
    # position: ∫v dt = T [v0 + C r − ⅙ ζ × C Δv_b + ½ Δv_g/cor]: the specific force weighted
    # within the interval, its body rotation (in r) and the navigation-frame rotation
    rn_, re_, rd_ = rotate(*r)
    rn_ = rn_ - (ze * nz - zd * ny) / 6.0
    re_ = re_ - (zd * nx - zn * nz) / 6.0
    rd_ = rd_ - (zn * ny - ze * nx) / 6.0
    dN = T * (vn + rn_ + 0.5 * gc[0])
    dE = T * (ve + re_ + 0.5 * gc[1])
    dD = T * (vd + rd_ + 0.5 * gc[2])
    lat1 = lat + dN / rmh
    lon1 = lon + dE / (rnh * cl)
    h1 = h - dD
    # attitude: p = q ⊗ exp(φ/2), then exp(−ζ/2) ⊗ p (|ζ| ~ 1e-6: two-term series)
    p0 = q0 * b0 - q1 * b1 - q2 * b2 - q3 * b3
    p1 = q0 * b1 + q1 * b0 + q2 * b3 - q3 * b2
    p2 = q0 * b2 - q1 * b3 + q2 * b0 + q3 * b1
    p3 = q0 * b3 + q1 * b2 - q2 * b1 + q3 * b0
    r0 = 1.0 - (zn * zn + ze * ze + zd * zd) / 8.0
    rn_, re_, rd_ = -0.5 * zn, -0.5 * ze, -0.5 * zd
    s0 = r0 * p0 - rn_ * p1 - re_ * p2 - rd_ * p3
    s1 = r0 * p1 + rn_ * p0 + re_ * p3 - rd_ * p2
    s2 = r0 * p2 - rn_ * p3 + re_ * p0 + rd_ * p1
    s3 = r0 * p3 + rn_ * p2 - re_ * p1 + rd_ * p0
    k = 1.0 / np.sqrt(s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3)
    return (lat1, lon1, h1, v1n, v1e, v1d, s0 * k, s1 * k, s2 * k, s3 * k)


def _check_increments(state: NavState, dtheta, dv):
    dtheta = np.asarray(dtheta, dtype=float)
    dv = np.asarray(dv, dtype=float)
    if dtheta.shape != dv.shape:
        raise ValueError(f"dtheta and dv shapes differ: {dtheta.shape} vs {dv.shape}")
    if dtheta.ndim not in (2, 3) or dtheta.shape[-1] != 3:
        raise ValueError(f"increments must have shape (n, 3) or (M, n, 3), got {dtheta.shape}")
    if dtheta.ndim == 3 and dtheta.shape[0] not in (1, state.n_runs):
        raise ValueError(f"increments have {dtheta.shape[0]} runs, the state has {state.n_runs}")
    n = dtheta.shape[-2]
    if not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"samples per interval must be in 1..{MAX_SAMPLES}, got {n}")
    M = state.n_runs
    if dtheta.ndim == 2 or dtheta.shape[0] != M:
        dtheta = np.broadcast_to(dtheta, (M,) + dtheta.shape[-2:])
        dv = np.broadcast_to(dv, (M,) + dv.shape[-2:])
    return dtheta, dv


def step(state: NavState, dtheta, dv, dt: float) -> NavState:
    """Advance every run by one navigation interval.

    Parameters
    ----------
    state : NavState
        State at ``t_{m−1}`` (M runs).
    dtheta, dv : array_like, shape (n, 3) or (M, n, 3)
        The n IMU samples of the interval, oldest first (``n = 4`` for the
        KIMU of seed 001; without a run axis they are shared by all runs).
        [rad], [m/s]
    dt : float
        Interval length T. [s]

    Returns
    -------
    NavState
        State at ``t_m = t_{m−1} + T``.

    Notes
    -----
    See the module notes; the body increments are :func:`body_increments`.
    """
    dtheta, dv = _check_increments(state, dtheta, dv)
    phi, dv_b = body_increments(dtheta, dv, state.dtheta_prev, state.dv_prev)
    r = body_position_increment(dtheta, dv)
    x = _nav_core(_unpack(state), _rotvec_quat(phi).T, dv_b.T, r.T, float(dt))
    return _pack(state.t + float(dt), x, np.array(dtheta[:, -1, :]), np.array(dv[:, -1, :]))
