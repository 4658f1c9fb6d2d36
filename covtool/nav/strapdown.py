"""Strapdown mechanization: the nonlinear reference of the linear model.

Quaternion/NED strapdown navigation driven by IMU increments (``Δθ``,
``Δv``), with the 4-sample + 1-previous coning and sculling compensation of
seed 001 (eq (1)–(4), Figs 9–10).  It is vectorised over an ensemble: every
array carries a leading run axis ``M``, so one :func:`step` advances all
Monte-Carlo runs at once.

Conventions are those of :mod:`covtool` (SI, NED, ``q`` scalar first and
body→NED) and of the linear error model (:mod:`covtool.lincov.dynamics`): error =
computed − true, position errors ``(δL, δl, δh)``, velocity ``δv^n`` and the
additive quaternion error ``δq = q̂ − q`` (seed 002, eq (1)), in the state
order of seed 002, eq (14) (:data:`NAV_STATES`).

Algorithm (one navigation interval ``T = t_m − t_{m−1}``)
--------------------------------------------------------
The interval holds ``n`` IMU samples ``Δθ_1 … Δθ_n``, ``Δv_1 … Δv_n``
(sample ``0`` is the last sample of the previous interval).

*Body increments*: the compensated rotation vector ``φ`` and velocity
increment ``Δv_b`` of the interval, with the n-sample + 1-previous coning
and sculling of seed 001 eq (1)–(4) (:mod:`covtool.nav.coning`).

*Navigation frame* (second order, predictor–corrector at the mid-interval)::

    ζ = (ω_ie^n + ω_en^n)(t_{m−½}) T
    q_m = exp(−ζ/2) ⊗ q_{m−1} ⊗ exp(φ/2)                        (normalised)
    Δv_gc = [g^n − (2ω_ie^n + ω_en^n) × v^n](t_{m−½}) T
    v_m = v_{m−1} + (I − ½[ζ×]) C Δv_b + Δv_gc,        C = C_b^n(t_{m−1})
    ΔR = T [v_{m−1} + C r − ⅙ ζ × C Δv_b + ½ Δv_gc]
    (L, l, h)_m = (L, l, h)_{m−1} + (ΔR_N/(R_M+h), ΔR_E/((R_N+h) cos L), −ΔR_D)   (radii at t_{m−½})

``r = Σ_i (n − i + ½)/n Δv_i + α×υ/6`` (:func:`covtool.nav.coning.body_position_increment`)
weights each sample's specific force at its mid-time, so ``∫v dt`` is
exact for a linearly varying specific force up to ``O(h²)`` rather than
the ``O(T²)`` of the trapezoid (Savage 1998 Part 2, position algorithm).
The mid-interval position and velocity come from a predictor pass with
the start-of-interval rates, so the step is self-starting and a filter may
correct the state between steps (:func:`correct`, seed 002 eq (10)).

Two IMUs at different rates (seed 001 §2.3, Figs 7–10)
------------------------------------------------------
Both navigation solutions run on the *main* interval: the main IMU's
sample period (``n = 1``, the 1-sample + 1-previous algorithm, coefficient
1/12) or a multiple of it.  A second IMU at ``r`` times the main rate
delivers ``r`` samples per interval and runs the ``r``-sample algorithm
(the KIMU of seed 001: ``r = 4``, eq (2) and (4)).  :func:`group_samples`
assigns each sample to the main interval in which its period ends and
refuses a grouping with missing or extra samples rather than dropping data
(the paper's circular queue guarantees none are lost).

References
----------
P. G. Savage, "Strapdown inertial navigation integration algorithm design,
Part 1: Attitude algorithms; Part 2: Velocity and position algorithms",
J. Guid. Control Dyn. 21(1)–(2), 1998 (seed 001 ref [6]).
M. B. Ignagni, "Efficient class of optimized coning compensation
algorithms", J. Guid. Control Dyn. 19(2), 1996.
K. M. Roscoe, "Equivalency between strapdown inertial navigation coning and
sculling integrals/algorithms", J. Guid. Control Dyn. 24(2), 2001.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
import math
from typing import Callable, Iterable

import numba
import numpy as np

from covtool.nav import attitude as quat, earth
from covtool.nav.coning import _weights, body_increments, body_position_increment, MAX_SAMPLES

__all__ = [
    "NAV_STATES", "NavState", "NavHistory", "step", "run", "iter_intervals", "correct",
    "nav_errors", "truth_state", "group_samples",
]


#: compiled kernels: cached on disk so the compile cost is paid once per installation
_njit = numba.njit(cache=True, nogil=True)
_OMEGA_IE, _E2, _A, _GAMMA_E = earth.OMEGA_IE, earth.E2, earth.A, earth.GAMMA_E
_K_SOM, _F, _M_RATIO = earth.K_SOMIGLIANA, earth.F, earth.M_RATIO

#: error-state order of the navigation block (seed 002, eq (14))
NAV_STATES = ("dL", "dl", "dh", "dvN", "dvE", "dvD", "dq0", "dq1", "dq2", "dq3")


# --------------------------------------------------------------------------
# state
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class NavState:
    """Navigation state of M runs at one time.

    Attributes
    ----------
    t : float
        Time. [s]
    lat, lon : ndarray, shape (M,)
        Geodetic latitude and longitude. [rad]
    h : ndarray, shape (M,)
        Height above the ellipsoid. [m]
    v_n : ndarray, shape (M, 3)
        NED velocity. [m/s]
    q : ndarray, shape (M, 4)
        Attitude quaternion body→NED, scalar first (kept unit-norm, sign
        not forced, so it stays continuous).
    dtheta_prev, dv_prev : ndarray, shape (M, 3)
        Last IMU sample of the previous interval (the "1-previous" of seed
        001 eq (2), (4)). [rad], [m/s]
    """

    t: float
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    q: np.ndarray
    dtheta_prev: np.ndarray
    dv_prev: np.ndarray

    @property
    def n_runs(self) -> int:
        """Number of runs M."""
        return self.lat.shape[0]

    @classmethod
    def from_trajectory(cls, traj, t0=None, *, n_runs: int = 1, errors=None,
                        mounting=None, previous=None) -> "NavState":
        """Initial state from a trajectory, optionally with initial errors.

        Parameters
        ----------
        traj : covtool.nav.trajectory.core.Trajectory
            True motion.
        t0 : float, optional
            Start time (default: the trajectory start). [s]
        n_runs : int
            Number of runs M (ignored if ``errors`` has a run axis).
        errors : ndarray, shape (M, 10) or (10,), optional
            Initial errors in the order of :data:`NAV_STATES` (computed −
            true; e.g. ``x0[:, :10]`` sampled from a model's P0).  The
            quaternion is renormalised after adding ``δq``.
        mounting : array_like, shape (4,), optional
            Quaternion ``q_bs`` of the IMU (sensor) frame relative to the
            vehicle body; the state is then the sensor frame's attitude
            ``q_nb ⊗ q_bs``.
        previous : tuple of ndarray, optional
            ``(Δθ, Δv)`` of the sample before ``t0``, shape (3,) or (M, 3);
            zeros if omitted (exact at rest, negligible otherwise).

        Returns
        -------
        NavState
        """
        t0 = float(traj.t[0]) if t0 is None else float(t0)
        s = truth_state(traj, [t0], mounting=mounting)
        if errors is not None:
            errors = np.atleast_2d(np.asarray(errors, dtype=float))
            if errors.shape[-1] != 10:
                raise ValueError(f"errors must have 10 columns ({', '.join(NAV_STATES)}), "
                                 f"got shape {errors.shape}")
            n_runs = errors.shape[0]
        M = int(n_runs)
        lat = np.repeat(s.lat, M)
        lon = np.repeat(s.lon, M)
        h = np.repeat(s.h, M)
        v = np.repeat(s.v_n, M, axis=0)
        q = np.repeat(s.q, M, axis=0)
        if errors is not None:
            lat = lat + errors[:, 0]
            lon = lon + errors[:, 1]
            h = h + errors[:, 2]
            v = v + errors[:, 3:6]
            q = q + errors[:, 6:10]
            q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        if previous is None:
            dth_p = np.zeros((M, 3))
            dv_p = np.zeros((M, 3))
        else:
            dth_p = np.broadcast_to(np.asarray(previous[0], float), (M, 3)).copy()
            dv_p = np.broadcast_to(np.asarray(previous[1], float), (M, 3)).copy()
        return cls(t0, lat, lon, h, v, q, dth_p, dv_p)

    def replace(self, **changes) -> "NavState":
        """Copy with fields changed."""
        return dataclasses.replace(self, **changes)

    def as_vector(self) -> np.ndarray:
        """``[L, l, h, v_N, v_E, v_D, q0, q1, q2, q3]``, shape (M, 10)."""
        return np.column_stack([self.lat, self.lon, self.h, self.v_n, self.q])


def truth_state(traj, t, *, mounting=None) -> NavState:
    """True navigation state at times ``t`` (one "run" per time).

    Parameters
    ----------
    traj : covtool.nav.trajectory.core.Trajectory
    t : array_like, shape (S,)
        Strictly increasing times. [s]
    mounting : array_like, shape (4,), optional
        ``q_bs`` of the IMU frame (see :meth:`NavState.from_trajectory`).

    Returns
    -------
    NavState
        Arrays of leading length S; ``t`` is the first time.
    """
    s = traj.sample(np.atleast_1d(np.asarray(t, dtype=float)))
    q = np.array(s.q_nb)
    if mounting is not None:
        q = quat.mul(q, np.asarray(mounting, dtype=float))
    S = s.t.size
    return NavState(float(s.t[0]), np.array(s.lat), np.array(s.lon), np.array(s.h), np.array(s.v_n), q,
                    np.zeros((S, 3)), np.zeros((S, 3)))


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


# --------------------------------------------------------------------------
# compiled kernel (issue 13): the navigation-frame update of many steps and runs
# --------------------------------------------------------------------------
# The same arithmetic as _nav_core, written for scalars and compiled with numba, so a
# navigation step costs tens of nanoseconds per run instead of one Python call of ~270 µs
# for the whole ensemble.  _nav_core stays the reference (tests compare the two).


@_njit
def _store_state(dst, lat, lon, h, vn, ve, vd, q0, q1, q2, q3):
    """Write one navigation state (lat, lon, h, v_NED, q_nb) into ``dst``, shape (10,)."""
    dst[0], dst[1], dst[2] = lat, lon, h
    dst[3], dst[4], dst[5] = vn, ve, vd
    dst[6], dst[7], dst[8], dst[9] = q0, q1, q2, q3


@_njit
def _nav_core_scalar(lat, lon, h, vn, ve, vd, q0, q1, q2, q3, b0, b1, b2, b3, ux, uy, uz, rx, ry, rz, T):
    W = _OMEGA_IE
    # C(q) u = u + q0 t + qv × t, t = 2 qv × u
    tx = 2.0 * (q2 * uz - q3 * uy)
    ty = 2.0 * (q3 * ux - q1 * uz)
    tz = 2.0 * (q1 * uy - q2 * ux)
    nx = ux + q0 * tx + (q2 * tz - q3 * ty)
    ny = uy + q0 * ty + (q3 * tx - q1 * tz)
    nz = uz + q0 * tz + (q1 * ty - q2 * tx)
    # predictor with the start-of-interval rates
    la, hh = lat, h
    wn_, we_, wd_ = vn, ve, vd
    for it in range(2):
        sl = math.sin(la)
        cl = math.cos(la)
        s2 = sl * sl
        w = 1.0 - _E2 * s2
        sw = math.sqrt(w)
        rnh = _A / sw + hh
        rmh = _A * (1.0 - _E2) / (w * sw) + hh
        g0 = _GAMMA_E * (1.0 + _K_SOM * s2) / sw
        g = g0 * (1.0 - 2.0 * hh / _A * (1.0 + _F + _M_RATIO - 2.0 * _F * s2) + 3.0 * hh * hh / (_A * _A))
        t_ = sl / cl
        zn = (W * cl + we_ / rnh) * T
        ze = (-wn_ / rmh) * T
        zd = (-W * sl - we_ * t_ / rnh) * T
        cn = zn + W * cl * T
        ce = ze
        cd = zd - W * sl * T
        gc0 = -(ce * wd_ - cd * we_)
        gc1 = -(cd * wn_ - cn * wd_)
        gc2 = -(cn * we_ - ce * wn_) + g * T
        v1n = vn + nx - 0.5 * (ze * nz - zd * ny) + gc0
        v1e = ve + ny - 0.5 * (zd * nx - zn * nz) + gc1
        v1d = vd + nz - 0.5 * (zn * ny - ze * nx) + gc2
        if it == 0:
            la = lat + 0.25 * T * (vn + v1n) / rmh
            hh = h - 0.25 * T * (vd + v1d)
            wn_ = 0.5 * (vn + v1n)
            we_ = 0.5 * (ve + v1e)
            wd_ = 0.5 * (vd + v1d)
    tx = 2.0 * (q2 * rz - q3 * ry)
    ty = 2.0 * (q3 * rx - q1 * rz)
    tz = 2.0 * (q1 * ry - q2 * rx)
    rn_ = rx + q0 * tx + (q2 * tz - q3 * ty)
    re_ = ry + q0 * ty + (q3 * tx - q1 * tz)
    rd_ = rz + q0 * tz + (q1 * ty - q2 * tx)
    rn_ = rn_ - (ze * nz - zd * ny) / 6.0
    re_ = re_ - (zd * nx - zn * nz) / 6.0
    rd_ = rd_ - (zn * ny - ze * nx) / 6.0
    dN = T * (vn + rn_ + 0.5 * gc0)
    dE = T * (ve + re_ + 0.5 * gc1)
    dD = T * (vd + rd_ + 0.5 * gc2)
    lat1 = lat + dN / rmh
    lon1 = lon + dE / (rnh * cl)
    h1 = h - dD
    p0 = q0 * b0 - q1 * b1 - q2 * b2 - q3 * b3
    p1 = q0 * b1 + q1 * b0 + q2 * b3 - q3 * b2
    p2 = q0 * b2 - q1 * b3 + q2 * b0 + q3 * b1
    p3 = q0 * b3 + q1 * b2 - q2 * b1 + q3 * b0
    r0 = 1.0 - (zn * zn + ze * ze + zd * zd) / 8.0
    an, ae, ad = -0.5 * zn, -0.5 * ze, -0.5 * zd
    s0 = r0 * p0 - an * p1 - ae * p2 - ad * p3
    s1 = r0 * p1 + an * p0 + ae * p3 - ad * p2
    s2_ = r0 * p2 - an * p3 + ae * p0 + ad * p1
    s3 = r0 * p3 + an * p2 - ae * p1 + ad * p0
    k = 1.0 / math.sqrt(s0 * s0 + s1 * s1 + s2_ * s2_ + s3 * s3)
    return lat1, lon1, h1, v1n, v1e, v1d, s0 * k, s1 * k, s2_ * k, s3 * k


@_njit
def _nav_loop(x, qb, ub, rb, T, every, offset, out):
    """Advance ``x`` (10, R) in place over S steps, keeping every ``every``-th.

    ``qb`` (4, Rb, S), ``ub`` and ``rb`` (3, Rb, S) with Rb = R or 1 (shared by
    the runs).  Step j is global step ``offset + j + 1``; when that is a
    multiple of ``every`` the state after it goes to ``out[:, :, i]``, i
    counting the kept steps of this call from 0.
    """
    R = x.shape[1]
    S = qb.shape[2]
    shared = qb.shape[1] == 1
    for m in range(R):
        mb = 0 if shared else m
        lat, lon, h = x[0, m], x[1, m], x[2, m]
        vn, ve, vd = x[3, m], x[4, m], x[5, m]
        q0, q1, q2, q3 = x[6, m], x[7, m], x[8, m], x[9, m]
        for j in range(S):
            lat, lon, h, vn, ve, vd, q0, q1, q2, q3 = _nav_core_scalar(
                lat, lon, h, vn, ve, vd, q0, q1, q2, q3,
                qb[0, mb, j], qb[1, mb, j], qb[2, mb, j], qb[3, mb, j],
                ub[0, mb, j], ub[1, mb, j], ub[2, mb, j], rb[0, mb, j], rb[1, mb, j], rb[2, mb, j], T)
            if (offset + j + 1) % every == 0:
                o = (offset + j + 1) // every - offset // every - 1
                _store_state(out[:, m, o], lat, lon, h, vn, ve, vd, q0, q1, q2, q3)
        _store_state(x[:, m], lat, lon, h, vn, ve, vd, q0, q1, q2, q3)


@_njit
def _strapdown_loop(x, dth, dv, prev_th, prev_dv, n, wc, T, every, offset, out):
    """The whole strapdown step (:func:`step`) over a record, compiled.

    ``x`` (10, R) advanced in place; ``dth``, ``dv`` (Rb, K, 3) with K = S·n and
    Rb = R or 1 (shared by the runs); ``prev_th``, ``prev_dv`` (R, 3) the
    sample before the record, overwritten with the last sample; ``wc`` the
    coning weights of :func:`covtool.nav.coning._weights`.  Body increments as
    :func:`covtool.nav.coning.body_increments` and
    :func:`~covtool.nav.coning.body_position_increment` (seed 001 eq (1)–(4)),
    rotation-vector quaternion as :func:`_rotvec_quat`, navigation update as
    :func:`_nav_core`; kept states as in :func:`_nav_loop`.
    """
    R = x.shape[1]
    S = dth.shape[1] // n
    shared = dth.shape[0] == 1
    for m in range(R):
        mb = 0 if shared else m
        lat, lon, h = x[0, m], x[1, m], x[2, m]
        vn, ve, vd = x[3, m], x[4, m], x[5, m]
        q0, q1, q2, q3 = x[6, m], x[7, m], x[8, m], x[9, m]
        p0x, p0y, p0z = prev_th[m, 0], prev_th[m, 1], prev_th[m, 2]
        v0x, v0y, v0z = prev_dv[m, 0], prev_dv[m, 1], prev_dv[m, 2]
        for j in range(S):
            # coning and sculling, seed 001 eq (2), (4): A, B the weighted earlier samples
            Ax, Ay, Az = wc[0] * p0x, wc[0] * p0y, wc[0] * p0z
            Bx, By, Bz = wc[0] * v0x, wc[0] * v0y, wc[0] * v0z
            al0 = al1 = al2 = 0.0
            up0 = up1 = up2 = 0.0
            r0 = r1 = r2 = 0.0
            for i in range(n):
                a0, a1, a2 = dth[mb, j * n + i, 0], dth[mb, j * n + i, 1], dth[mb, j * n + i, 2]
                u0, u1, u2 = dv[mb, j * n + i, 0], dv[mb, j * n + i, 1], dv[mb, j * n + i, 2]
                if i < n - 1:
                    Ax += wc[i + 1] * a0
                    Ay += wc[i + 1] * a1
                    Az += wc[i + 1] * a2
                    Bx += wc[i + 1] * u0
                    By += wc[i + 1] * u1
                    Bz += wc[i + 1] * u2
                al0 += a0
                al1 += a1
                al2 += a2
                up0 += u0
                up1 += u1
                up2 += u2
                wr = (n - i - 0.5) / n
                r0 += wr * u0
                r1 += wr * u1
                r2 += wr * u2
            lx, ly, lz = a0, a1, a2          # last sample of the interval
            mx, my, mz = u0, u1, u2
            phx = al0 + (Ay * lz - Az * ly)
            phy = al1 + (Az * lx - Ax * lz)
            phz = al2 + (Ax * ly - Ay * lx)
            a2s = al0 * al0 + al1 * al1 + al2 * al2
            if a2s < 1e-6:
                c1 = 0.5 - a2s / 24.0 + a2s * a2s / 720.0
                c2 = 1.0 / 6.0 - a2s / 120.0 + a2s * a2s / 5040.0
            else:
                aa = math.sqrt(a2s)
                c1 = (1.0 - math.cos(aa)) / aa ** 2
                c2 = (aa - math.sin(aa)) / aa ** 3
            xu0 = al1 * up2 - al2 * up1
            xu1 = al2 * up0 - al0 * up2
            xu2 = al0 * up1 - al1 * up0
            xx0 = al1 * xu2 - al2 * xu1
            xx1 = al2 * xu0 - al0 * xu2
            xx2 = al0 * xu1 - al1 * xu0
            ux = up0 + c1 * xu0 + c2 * xx0 + (Ay * mz - Az * my) + (By * lz - Bz * ly)
            uy = up1 + c1 * xu1 + c2 * xx1 + (Az * mx - Ax * mz) + (Bz * lx - Bx * lz)
            uz = up2 + c1 * xu2 + c2 * xx2 + (Ax * my - Ay * mx) + (Bx * ly - By * lx)
            rx = r0 + xu0 / 6.0
            ry = r1 + xu1 / 6.0
            rz = r2 + xu2 / 6.0
            # exp(φ/2)
            f2 = phx * phx + phy * phy + phz * phz
            fa = math.sqrt(f2)
            b0 = math.cos(0.5 * fa)
            sf = 0.5 - f2 / 48.0 if f2 < 1e-8 else math.sin(0.5 * fa) / fa
            lat, lon, h, vn, ve, vd, q0, q1, q2, q3 = _nav_core_scalar(
                lat, lon, h, vn, ve, vd, q0, q1, q2, q3, b0, sf * phx, sf * phy, sf * phz,
                ux, uy, uz, rx, ry, rz, T)
            p0x, p0y, p0z = lx, ly, lz
            v0x, v0y, v0z = mx, my, mz
            if (offset + j + 1) % every == 0:
                o = (offset + j + 1) // every - offset // every - 1
                _store_state(out[:, m, o], lat, lon, h, vn, ve, vd, q0, q1, q2, q3)
        _store_state(x[:, m], lat, lon, h, vn, ve, vd, q0, q1, q2, q3)
        prev_th[m, 0], prev_th[m, 1], prev_th[m, 2] = p0x, p0y, p0z
        prev_dv[m, 0], prev_dv[m, 1], prev_dv[m, 2] = v0x, v0y, v0z


def _unpack(state: NavState):
    return (state.lat, state.lon, state.h, *state.v_n.T, *state.q.T)


def _pack(t, x, dtheta_prev, dv_prev) -> NavState:
    return NavState(t, x[0], x[1], x[2], np.column_stack(x[3:6]), np.column_stack(x[6:10]),
                    dtheta_prev, dv_prev)


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


def correct(state: NavState, dx) -> NavState:
    """Feed estimated errors back into the navigation state.

    Parameters
    ----------
    state : NavState
    dx : array_like, shape (M, 10) or (10,)
        Estimated errors (computed − true) in the order of :data:`NAV_STATES`.

    Returns
    -------
    NavState
        ``x ← x − x̂`` for position, velocity and quaternion (seed 002,
        eq (10)); the quaternion is renormalised.
    """
    dx = np.asarray(dx, dtype=float)
    if dx.shape[-1] != 10 or dx.ndim > 2:
        raise ValueError(f"dx must have shape (10,) or (M, 10), got {dx.shape}")
    dx = np.broadcast_to(dx, (state.n_runs, 10))
    q = state.q - dx[:, 6:10]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return state.replace(lat=state.lat - dx[:, 0], lon=state.lon - dx[:, 1], h=state.h - dx[:, 2],
                         v_n=state.v_n - dx[:, 3:6], q=q)


def nav_errors(state: NavState, truth: NavState) -> np.ndarray:
    """Navigation errors (computed − true), shape (M, 10).

    Parameters
    ----------
    state : NavState
        Computed state of M runs.
    truth : NavState
        True state (one run broadcast, or M).

    Returns
    -------
    ndarray, shape (M, 10)
        ``[δL, δl, δh, δv_N, δv_E, δv_D, δq0…δq3]`` in the order of
        :data:`NAV_STATES`.  ``δl`` is wrapped to ±π; ``q̂`` takes the sign
        of the true quaternion before ``δq = q̂ − q`` is formed.
    """
    q = state.q
    qt = np.broadcast_to(truth.q, q.shape)
    sign = np.where(np.sum(q * qt, axis=-1) < 0, -1.0, 1.0)[:, None]
    dl = np.angle(np.exp(1j * (state.lon - truth.lon)))
    return np.column_stack([state.lat - truth.lat, dl, state.h - truth.h,
                            state.v_n - truth.v_n, sign * q - qt])


# --------------------------------------------------------------------------
# whole records
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class NavHistory:
    """Navigation solution of M runs at S output times.

    Attributes
    ----------
    t : ndarray, shape (S,)
        Output times. [s]
    lat, lon, h : ndarray, shape (S, M)
        [rad], [rad], [m]
    v_n : ndarray, shape (S, M, 3)
        [m/s]
    q : ndarray, shape (S, M, 4)
        Attitude quaternion body→NED.
    """

    t: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    q: np.ndarray

    def state(self, i: int) -> NavState:
        """The state at output index ``i`` (previous samples zero)."""
        M = self.lat.shape[1]
        return NavState(float(self.t[i]), self.lat[i], self.lon[i], self.h[i], self.v_n[i], self.q[i],
                        np.zeros((M, 3)), np.zeros((M, 3)))

    def errors(self, truth) -> np.ndarray:
        """Errors (computed − true) at every output time, shape (S, M, 10).

        Parameters
        ----------
        truth : Trajectory or object with ``truth(t) -> NavState``
            A :class:`covtool.nav.trajectory.core.Trajectory` (body frame) or an
            IMU simulator (its own frame: mounting and vibration included).
        """
        if hasattr(truth, "truth"):
            tr = truth.truth(self.t)
        else:
            tr = truth_state(truth, self.t)
        out = np.empty(self.lat.shape + (10,))
        M = self.lat.shape[1]
        for i in range(self.t.size):
            if tr.lat.ndim == 2:  # per-run truth
                ti = NavState(float(self.t[i]), tr.lat[i], tr.lon[i], tr.h[i], tr.v_n[i], tr.q[i],
                              np.zeros((M, 3)), np.zeros((M, 3)))
            else:
                ti = NavState(float(self.t[i]), tr.lat[i:i + 1], tr.lon[i:i + 1], tr.h[i:i + 1],
                              tr.v_n[i:i + 1], tr.q[i:i + 1], np.zeros((1, 3)), np.zeros((1, 3)))
            out[i] = nav_errors(self.state(i), ti)
        return out


def group_samples(t_samples, t_main, where: str = "IMU") -> np.ndarray:
    """Assign IMU samples to main navigation intervals.

    Parameters
    ----------
    t_samples : array_like, shape (K,)
        End time of each IMU sample period, increasing. [s]
    t_main : array_like, shape (S+1,)
        Main interval boundaries ``t_0 < t_1 < … < t_S``. [s]
    where : str
        Name used in error messages.

    Returns
    -------
    ndarray of int, shape (S, n)
        Sample indices of each interval, oldest first.

    Raises
    ------
    ValueError
        If the intervals do not all hold the same number of samples (a gap,
        a duplicate or a rate that is not an integer multiple), naming the
        first offending interval; samples outside ``(t_0, t_S]`` are refused
        too.  Nothing is dropped silently.

    Notes
    -----
    A sample belongs to interval m if its period ends in ``(t_{m−1}, t_m]``
    (with a tolerance of 1e-6 of the sample period), which is how seed 001
    synchronises the KIMU to the main IMU (Fig 7).
    """
    ts = np.asarray(t_samples, dtype=float)
    tm = np.asarray(t_main, dtype=float)
    if ts.ndim != 1 or tm.ndim != 1 or tm.size < 2:
        raise ValueError(f"{where}: sample times and interval boundaries must be 1-D (at least 2 boundaries)")
    tol = 1e-6 * (np.min(np.diff(ts)) if ts.size > 1 else np.min(np.diff(tm)))
    idx = np.searchsorted(tm, ts - tol, side="left")
    out_of = (idx < 1) | (idx > tm.size - 1)
    if out_of.any():
        k = int(np.argmax(out_of))
        raise ValueError(f"{where}: sample {k} (t = {ts[k]:.9g} s) lies outside the main intervals "
                         f"({tm[0]:.9g}, {tm[-1]:.9g}] s")
    counts = np.bincount(idx - 1, minlength=tm.size - 1)
    n = counts[0]
    bad = counts != n
    if bad.any() or n == 0:
        m = int(np.argmax(bad)) if bad.any() else 0
        raise ValueError(f"{where}: main interval {m} ({tm[m]:.9g}, {tm[m + 1]:.9g}] s holds {counts[m]} "
                         f"samples, expected {n or 'at least 1'} (gap, duplicate or non-integer rate ratio)")
    order = np.argsort(idx, kind="stable")
    return order.reshape(tm.size - 1, n)


def iter_intervals(imu, samples_per_step: int):
    """Navigation intervals of an IMU record, for :func:`step`.

    Parameters
    ----------
    imu : ImuRecord, ImuSimulator or iterable of ImuRecord
        As for :func:`run`.
    samples_per_step : int
        Samples per interval n.

    Yields
    ------
    dtheta, dv : ndarray, shape (n, 3) or (M, n, 3)
        The interval's samples.
    dt : float
        Interval length. [s]

    Examples
    --------
    A filter with feedback (seed 002, eq (10))::

        for dth, dv, T in iter_intervals(sim, 4):
            state = step(state, dth, dv, T)
            if zupt_now(state.t):
                state = correct(state, dx_hat)
    """
    n = int(samples_per_step)
    records = [imu] if hasattr(imu, "dtheta") else (imu.records() if hasattr(imu, "records") else imu)
    for rec in records:
        K = rec.dtheta.shape[-2]
        if K % n:
            raise ValueError(f"an IMU record of {K} samples is not a multiple of {n} samples per step")
        for j in range(K // n):
            yield rec.dtheta[..., j * n:(j + 1) * n, :], rec.dv[..., j * n:(j + 1) * n, :], n * rec.dt


def run(state: NavState, imu, samples_per_step: int, *, every: int = 1,
        callback: Callable | None = None) -> NavHistory:
    """Run the strapdown algorithm over a whole IMU record.

    Parameters
    ----------
    state : NavState
        Initial state (M runs) at the start of the record.
    imu : ImuRecord, ImuSimulator or iterable of ImuRecord
        Increments (:class:`covtool.nav.imu.simulator.ImuRecord`: ``t0``, sample period
        ``dt``, ``dtheta`` and ``dv`` of shape (K, 3) or (M, K, 3)); a
        simulator or an iterable yields consecutive records (chunks).
    samples_per_step : int
        IMU samples per navigation interval n (each record's K must be a
        multiple of n).
    every : int
        Keep every ``every``-th navigation step in the history (the initial
        and the final state are always kept).
    callback : callable, optional
        ``callback(state) -> NavState or None`` after every step, e.g. to
        apply filter feedback with :func:`correct`; a returned state
        replaces the current one.

    Returns
    -------
    NavHistory
    """
    n = int(samples_per_step)
    if not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"samples_per_step must be in 1..{MAX_SAMPLES}, got {samples_per_step!r}")
    if every < 1:
        raise ValueError(f"every must be a positive integer, got {every!r}")
    records: Iterable = [imu] if hasattr(imu, "dtheta") else (imu.records() if hasattr(imu, "records") else imu)
    M = state.n_runs
    keep = [state]
    k = 0
    last_kept = 0
    for rec in records:
        K = rec.dtheta.shape[-2]
        if K % n:
            raise ValueError(f"an IMU record of {K} samples is not a multiple of {n} samples per step")
        T = n * rec.dt
        if abs(rec.t0 - state.t) > 1e-6 * rec.dt:
            raise ValueError(f"IMU record starts at {rec.t0:.9g} s but the state is at {state.t:.9g} s")
        if rec.dtheta.ndim == 3 and rec.dtheta.shape[0] not in (1, M):
            raise ValueError(f"IMU record has {rec.dtheta.shape[0]} runs, the state has {M}")
        S = K // n
        # shared increments (no run axis) are compensated once for all runs
        shared = ((rec.dtheta.ndim == 2 or rec.dtheta.shape[0] == 1)
                  and np.all(state.dtheta_prev == state.dtheta_prev[:1])
                  and np.all(state.dv_prev == state.dv_prev[:1]))
        Mr = 1 if shared else M
        dth = np.broadcast_to(rec.dtheta, (Mr, K, 3)).reshape(Mr, S, n, 3)
        dvv = np.broadcast_to(rec.dv, (Mr, K, 3)).reshape(Mr, S, n, 3)
        xa = np.array(_unpack(state), dtype=float)                              # (10, M)
        t0 = state.t
        if callback is None:
            # all steps of the record in the compiled kernel; the kept ones written out
            js = np.flatnonzero((k + np.arange(1, S + 1)) % every == 0)
            out = np.empty((10, M, js.size))
            pth = np.array(np.broadcast_to(state.dtheta_prev, (M, 3)), dtype=float)
            pdv = np.array(np.broadcast_to(state.dv_prev, (M, 3)), dtype=float)
            _strapdown_loop(xa, np.ascontiguousarray(dth.reshape(Mr, K, 3)), np.ascontiguousarray(dvv.reshape(Mr, K, 3)),
                            pth, pdv, n, _weights(n), T, every, k, out)
            for i, j in enumerate(js):
                keep.append(_pack(t0 + (j + 1) * T, tuple(out[:, :, i]),
                                  np.broadcast_to(dth[:, j, -1], (M, 3)).copy(),
                                  np.broadcast_to(dvv[:, j, -1], (M, 3)).copy()))
            if js.size:
                last_kept = k + int(js[-1]) + 1
            k += S
            state = _pack(t0 + S * T, tuple(xa), pth, pdv)
            continue
        # with a callback the state may change between steps: one step per kernel call
        prev_th = np.concatenate([state.dtheta_prev[:Mr, None], dth[:, :-1, -1]], axis=1)
        prev_dv = np.concatenate([state.dv_prev[:Mr, None], dvv[:, :-1, -1]], axis=1)
        phi, dv_b = body_increments(dth, dvv, prev_th, prev_dv)
        qb = np.ascontiguousarray(np.moveaxis(_rotvec_quat(phi), -1, 0))      # (4, Mr, S)
        ub = np.ascontiguousarray(np.moveaxis(dv_b, -1, 0))                   # (3, Mr, S)
        rb = np.ascontiguousarray(np.moveaxis(body_position_increment(dth, dvv), -1, 0))

        def prev(j):
            return (np.broadcast_to(dth[:, j, -1], (M, 3)).copy(), np.broadcast_to(dvv[:, j, -1], (M, 3)).copy())

        one = np.empty((10, M, 1))
        for j in range(S):
            _nav_loop(xa, qb[:, :, j:j + 1], ub[:, :, j:j + 1], rb[:, :, j:j + 1], T, 1, 0, one)
            k += 1
            state = _pack(t0 + (j + 1) * T, tuple(xa.copy()), *prev(j))
            new = callback(state)
            if new is not None:
                state = new
                xa = np.array(_unpack(state), dtype=float)
            if k % every == 0:
                keep.append(state)
                last_kept = k
    if last_kept != k:
        keep.append(state)
    return NavHistory(
        t=np.array([s.t for s in keep]),
        lat=np.stack([s.lat for s in keep]), lon=np.stack([s.lon for s in keep]),
        h=np.stack([s.h for s in keep]), v_n=np.stack([s.v_n for s in keep]),
        q=np.stack([s.q for s in keep]))
