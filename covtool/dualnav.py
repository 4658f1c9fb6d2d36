"""Dual navigation and IMU verification in flight (seed 001, method II).

Pure numeric core: arrays in, arrays out.  A development IMU (the KIMU) flies
beside the main IMU; both navigate at once on the main interval (the KIMU at
``r`` samples per interval, seed 001 §2.3, Figs 7–10), each after its own
alignment, and the two solutions are compared after the mounting
misalignment between the IMUs is compensated.  This module

* aligns each IMU on its own (:func:`triad_alignment`): levelling from its
  accelerometers, heading from the input heading through the declared
  mounting (seed 001 §2.3.2);
* forms the navigation difference main − KIMU (:func:`nav_difference`);
* predicts its covariance by linear covariance analysis: the two INS error
  states, each from its grade's :class:`~covtool.lincov.model.spec.Model`,
  propagated independently along the flight with covtool's error dynamics,
  correlated only through the shared input heading
  (:func:`difference_model`);
* whitens the difference with the Kalman filter of that model and flags the
  windows whose normalised innovations leave the predicted χ² envelope
  (:func:`innovations`, :func:`window_test`);
* detects a g-sensitive gyro scale-factor error of the KIMU and estimates its
  coefficient by generalised least squares on the fault signatures
  (:func:`gsens_estimates`, Willsky & Jones 1976);
* bridges telemetry gaps by a declared policy and predicts the extra error
  each bridge costs (:func:`bridge_gaps`).

Conventions: SI; error = computed − true; attitude differences are NED
small angles ``φ`` with ``Ĉ_b^n = (I − [φ×]) C_b^n``; the difference vector
``z`` is ``[δN, δE, δD, δv_N, δv_E, δv_D, δφ_N, δφ_E, δφ_D]`` of main minus
KIMU (:data:`DIFF_NAMES`).

References
----------
A. S. Willsky and H. L. Jones, "A generalized likelihood ratio approach to
the detection and estimation of jumps in linear systems", IEEE Trans.
Automatic Control 21(1), 1976.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2
from threadpoolctl import threadpool_limits

from covtool.nav import earth
from covtool.nav import attitude as quat
from covtool.nav import strapdown as sd
from covtool.lincov.discretize import block_triangular, is_block_triangular, taylor
from covtool.lincov.kalman import (check_covariance, check_finite, filter_update, innovation_covariance,
                                   kalman_gain, symmetrize, time_text)
from covtool.lincov.dynamics import Context, error_dynamics
from covtool.errors import InputError, NumericalError
from covtool.nav.imu.simulator import ImuRecord
from covtool.validation.sensor_errors import SensorErrors
from covtool.lincov.model.spec import Model

__all__ = [
    "DIFF_NAMES", "COMPONENTS", "AXES", "GAP_POLICIES", "GSensitiveErrors", "triad_alignment",
    "alignment_jacobian", "alignment_second_order", "nav_difference", "ImuLinearization", "DifferenceModel",
    "difference_model",
    "Innovations", "Whitener", "innovations", "window_test", "flagged_intervals", "GsensEstimate", "gsens_estimates",
    "GapReport", "BridgedLog", "find_gaps", "bridge_gaps", "clock_rate", "ppm_text", "DualSetup", "DualRun", "run_dual",
    "candidate_label", "G0",
]

#: standard gravity [m/s²]
G0 = 9.80665
AXES = "xyz"
#: components of the difference vector z (main − KIMU)
DIFF_NAMES = ("pos_N", "pos_E", "pos_D", "vel_N", "vel_E", "vel_D", "att_N", "att_E", "att_D")
#: groups of difference components
COMPONENTS = {"position": (0, 1, 2), "velocity": (3, 4, 5), "attitude": (6, 7, 8)}
#: gap bridging policies
GAP_POLICIES = ("hold", "interpolate", "propagate", "refuse")
_EPS = np.zeros((3, 3, 3))
_EPS[0, 1, 2] = _EPS[1, 2, 0] = _EPS[2, 0, 1] = 1.0
_EPS[0, 2, 1] = _EPS[2, 1, 0] = _EPS[1, 0, 2] = -1.0


def _serial_blas(fn):
    """Run ``fn`` with one BLAS thread.

    Every matrix here is small (≤ 110 rows): threads only add contention,
    up to 70× slower on a loaded two-core machine.
    """
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)
    return wrapper


def candidate_label(pair) -> str:
    """``"z/x"``: g-sensitive scale factor of gyro z driven by f_x."""
    return f"{AXES[pair[0]]}/{AXES[pair[1]]}"


# --------------------------------------------------------------------------
# fault injection
# --------------------------------------------------------------------------


class GSensitiveErrors(SensorErrors):
    """Sensor errors plus a g-sensitive gyro scale-factor error.

    Parameters
    ----------
    model, x0, rng, **kw
        As for :class:`covtool.validation.sensor_errors.SensorErrors`.
    gsens : sequence of (int, int, float)
        ``(i, j, k)``: the scale factor of gyro ``i`` changes by ``k f_j``,
        ``δω_i = k f_j ω_i`` (seed 001, Fig 16 and ref [9]: a parallel-plate
        sense electrode moved by the acceleration along it). ``k`` in
        [1/(m/s²)].

    Notes
    -----
    The term is added per sample from the true sample means
    ``f̄ = Δv/h``, ``ω̄ = Δθ/h``: ``δΔθ_i = k (Δv_j/h) Δθ_i``.
    """

    def __init__(self, model: Model, x0, rng=None, *, gsens=(), **kw):
        super().__init__(model, x0, rng, **kw)
        out = []
        for item in gsens:
            i, j, k = item
            if int(i) not in (0, 1, 2) or int(j) not in (0, 1, 2):
                raise ValueError(f"g-sensitive scale factor axes must be 0, 1 or 2, got {item!r}")
            out.append((int(i), int(j), float(k)))
        self.gsens = tuple(out)

    def increment_errors(self, t0, h, dtheta, dv, **kw):
        """Sensor-error increments plus the g-sensitive term."""
        ddth, ddv = super().increment_errors(t0, h, dtheta, dv, **kw)
        for i, j, k in self.gsens:
            ddth[..., i] += k * (dv[..., j] / h) * dtheta[..., i]
        return ddth, ddv


# --------------------------------------------------------------------------
# alignment
# --------------------------------------------------------------------------


def _dcm_to_quat(C):
    """Unit quaternion (scalar first) of DCMs ``C_b^n``, shape (M, 4)."""
    C = np.asarray(C, float)
    tr = np.trace(C, axis1=-2, axis2=-1)
    cand = np.stack([tr, C[..., 0, 0], C[..., 1, 1], C[..., 2, 2]], axis=-1)
    k = np.argmax(cand, axis=-1)
    q = np.empty(C.shape[:-2] + (4,))
    for case in range(4):
        m = k == case
        if not m.any():
            continue
        c = C[m]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[m])
            qq = [0.25 * s, (c[:, 2, 1] - c[:, 1, 2]) / s, (c[:, 0, 2] - c[:, 2, 0]) / s, (c[:, 1, 0] - c[:, 0, 1]) / s]
        elif case == 1:
            s = 2.0 * np.sqrt(1.0 + c[:, 0, 0] - c[:, 1, 1] - c[:, 2, 2])
            qq = [(c[:, 2, 1] - c[:, 1, 2]) / s, 0.25 * s, (c[:, 0, 1] + c[:, 1, 0]) / s, (c[:, 0, 2] + c[:, 2, 0]) / s]
        elif case == 2:
            s = 2.0 * np.sqrt(1.0 + c[:, 1, 1] - c[:, 0, 0] - c[:, 2, 2])
            qq = [(c[:, 0, 2] - c[:, 2, 0]) / s, (c[:, 0, 1] + c[:, 1, 0]) / s, 0.25 * s, (c[:, 1, 2] + c[:, 2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + c[:, 2, 2] - c[:, 0, 0] - c[:, 1, 1])
            qq = [(c[:, 1, 0] - c[:, 0, 1]) / s, (c[:, 0, 2] + c[:, 2, 0]) / s, (c[:, 1, 2] + c[:, 2, 1]) / s, 0.25 * s]
        q[m] = np.stack(qq, axis=-1)
    return quat.normalize(q)


def triad_alignment(f_mean, heading, mounting=None) -> np.ndarray:
    """Attitude of an IMU at rest from its accelerometers and heading.

    Parameters
    ----------
    f_mean : array_like, shape (M, 3) or (3,)
        Mean specific force over the alignment window, sensor axes. [m/s²]
    heading : float or array_like, shape (M,)
        Input heading of the vehicle body x axis (its horizontal projection).
        [rad]
    mounting : array_like, shape (4,), optional
        Declared ``q_bs`` of the sensor frame in the vehicle body.

    Returns
    -------
    ndarray, shape (M, 4)
        ``q_ns`` of the sensor frame (scalar first, non-negative scalar).

    Notes
    -----
    TRIAD with gravity as the primary vector (seed 001 §2.3.2: the initial
    values and each IMU's accelerometers): down ``d = −f̄/|f̄|``; the body x
    axis ``x^s = C_b^s e_x`` projected on the horizontal,
    ``h = (x − (x·d) d)/|…|``, points along the input heading.  The IMU's
    tilt error is then its accelerometer error divided by g (the classic
    levelling result) and its heading error the input heading error.
    """
    f = np.atleast_2d(np.asarray(f_mean, float))
    M = f.shape[0]
    psi = np.broadcast_to(np.asarray(heading, float), (M,))
    d = -f / np.linalg.norm(f, axis=-1, keepdims=True)
    Cbs = np.eye(3) if mounting is None else quat.dcm(np.asarray(mounting, float))
    x = np.broadcast_to(Cbs[0], (M, 3))
    hs = x - np.sum(x * d, axis=-1, keepdims=True) * d
    hs = hs / np.linalg.norm(hs, axis=-1, keepdims=True)
    es = np.cross(d, hs)
    z = np.zeros(M)
    hn = np.stack([np.cos(psi), np.sin(psi), z], -1)
    en = np.stack([-np.sin(psi), np.cos(psi), z], -1)
    dn = np.broadcast_to([0.0, 0.0, 1.0], (M, 3))
    C = (hn[:, :, None] * hs[:, None, :] + en[:, :, None] * es[:, None, :] + dn[:, :, None] * d[:, None, :])
    return _dcm_to_quat(C)


def _small_angle(q_hat, q):
    """``φ`` with ``Ĉ = (I − [φ×]) C``: ``−rotvec(q̂ ⊗ q*)``, shape (..., 3)."""
    return -quat.to_rotvec(quat.mul(q_hat, quat.conj(q)))


def alignment_jacobian(f_mean, heading, mounting=None, step=(1e-4, 1e-6)) -> np.ndarray:
    """Linear map of the alignment errors onto the attitude error.

    Parameters
    ----------
    f_mean : array_like, shape (3,)
        Mean specific force at rest, sensor axes (the linearisation point).
        [m/s²]
    heading : float
        Input heading. [rad]
    mounting : array_like, shape (4,), optional
    step : tuple of float
        Central-difference steps for ``δf`` [m/s²] and ``δψ`` [rad].

    Returns
    -------
    ndarray, shape (3, 4)
        ``∂φ/∂[δf^s, δψ]``: the NED attitude error of :func:`triad_alignment`
        caused by a specific-force error ``δf^s`` and an input heading error
        ``δψ`` (central differences of the nonlinear alignment; truncation
        ~1e-10 relative).
    """
    f = np.asarray(f_mean, float).reshape(3)
    q0 = triad_alignment(f, heading, mounting)[0]
    A = np.empty((3, 4))
    for k in range(4):
        h = step[0] if k < 3 else step[1]
        args = []
        for s in (h, -h):
            ff, pp = f.copy(), float(heading)
            if k < 3:
                ff[k] += s
            else:
                pp += s
            args.append(_small_angle(triad_alignment(ff, pp, mounting)[0], q0))
        A[:, k] = (args[0] - args[1]) / (2.0 * h)
    return A


# --------------------------------------------------------------------------
# the navigation difference
# --------------------------------------------------------------------------


def nav_difference(main: sd.NavHistory, kimu: sd.NavHistory, mount_main=None, mount_kimu=None) -> np.ndarray:
    """Main − KIMU navigation difference after mounting compensation.

    Parameters
    ----------
    main, kimu : covtool.nav.strapdown.NavHistory
        Solutions at the same output times (S, M); each navigates its own
        sensor frame.
    mount_main, mount_kimu : array_like, shape (4,), optional
        Declared ``q_bs`` of each sensor frame in the vehicle body.

    Returns
    -------
    ndarray, shape (S, M, 9)
        ``[δN, δE, δD]`` [m] (north/east/down metres at the main solution),
        ``δv^n`` [m/s] and ``δφ`` [rad] with
        ``δφ = −rotvec(q̂_b,main ⊗ q̂_b,KIMU*)``, ``q̂_b = q̂_s ⊗ q_bs*``
        (the vehicle-body attitude each IMU implies).
    """
    if main.t.shape != kimu.t.shape or not np.allclose(main.t, kimu.t, atol=1e-9):
        raise ValueError("the two solutions must be given at the same output times")
    rm, rn = earth.radii(main.lat)
    dN = (main.lat - kimu.lat) * (rm + main.h)
    dE = np.angle(np.exp(1j * (main.lon - kimu.lon))) * (rn + main.h) * np.cos(main.lat)
    dD = -(main.h - kimu.h)

    def body(q, mount):
        return q if mount is None else quat.mul(q, quat.conj(np.asarray(mount, float)))

    phi = _small_angle(body(main.q, mount_main), body(kimu.q, mount_kimu))
    return np.concatenate([np.stack([dN, dE, dD], -1), main.v_n - kimu.v_n, phi], axis=-1)


# --------------------------------------------------------------------------
# linear model of the difference
# --------------------------------------------------------------------------


@_serial_blas
def alignment_second_order(f_mean, heading, mounting, cov_u, step: float = 0.05):
    """Second-order alignment error for Gaussian input errors.

    Parameters
    ----------
    f_mean : array_like, shape (3,)
        Rest specific force, sensor axes. [m/s²]
    heading : float
        Input heading. [rad]
    mounting : array_like, shape (4,) or None
    cov_u : array_like, shape (4, 4)
        Covariance of ``u = [δf^s, δψ]``.
    step : float
        Finite-difference step in units of the input σ.

    Returns
    -------
    mean : ndarray, shape (3,)
        ``E[φ − A u]``. [rad]
    cov : ndarray, shape (3, 3)
        ``Cov(φ − A u)``. [rad²]

    Notes
    -----
    With ``u = L w``, ``w ~ N(0, I)`` and the Hessians ``G_i = Lᵀ ∇²φ_i L``
    (central differences of :func:`triad_alignment`), the quadratic term
    ``½ wᵀ G_i w`` has mean ``½ tr G_i`` and covariance ``½ tr(G_i G_j)``,
    and it is uncorrelated with the linear term.  At the Table 2 biases
    (5 mg, 2 mg) it is ~2.6e-5 rad and ~5e-6 rad of tilt, as large as the
    levelling noise, so the linear model carries it as independent initial
    attitude noise (the mean, ~1e-6 rad, is dropped).
    """
    f = np.asarray(f_mean, float).reshape(3)
    w, V = np.linalg.eigh(0.5 * (np.asarray(cov_u, float) + np.asarray(cov_u, float).T))
    L = V * np.sqrt(np.clip(w, 0.0, None))
    q0 = triad_alignment(f, heading, mounting)[0]
    h = float(step)
    dirs = []
    for a in range(4):
        for b in range(4):
            for sa, sb in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                e = np.zeros(4)
                e[a] += sa * h
                e[b] += sb * h
                dirs.append(e)
    W = np.array(dirs)
    U = W @ L.T
    phi = _small_angle(triad_alignment(f + U[:, :3], heading + U[:, 3], mounting), q0)
    phi = phi.reshape(4, 4, 4, 3)
    G = (phi[:, :, 0] - phi[:, :, 1] - phi[:, :, 2] + phi[:, :, 3]) / (4.0 * h * h)   # (a, b, i)
    G = np.moveaxis(G, -1, 0)                                                    # (i, a, b)
    mean = 0.5 * np.trace(G, axis1=1, axis2=2)
    cov = 0.5 * np.einsum("iab,jba->ij", G, G)
    return mean, 0.5 * (cov + cov.T)


@dataclass
class ImuLinearization:
    """One IMU's linear error model along the flight.

    Attributes
    ----------
    model : Model
        Its error-state model (:meth:`covtool.io.imu_grade.ImuGrade.to_model`).
    ctx : Context
        Its own sensor-frame quantities at the mid-points of the propagation
        steps (mean ``f``, ``ω`` over each step, attitude at the mid-point).
    q_epochs : ndarray, shape (J+1, 4)
        Its attitude at the comparison epochs.
    rest_ctx : Context
        The rest condition of the alignment (one sample: position, aligned
        attitude, mean ``f`` and ``ω`` over the window).
    align_time : float
        Length of the alignment window. [s]
    heading : float
        The input heading used by the alignment. [rad]
    mounting : ndarray, shape (4,) or None
        Declared ``q_bs``.
    """

    model: Model
    ctx: Context
    q_epochs: np.ndarray
    rest_ctx: Context
    align_time: float
    heading: float
    mounting: np.ndarray | None = None

    def initial_map(self, heading_sigma: float = 0.0):
        """Map of the sensor states, the levelling noise and δψ onto x0.

        Parameters
        ----------
        heading_sigma : float
            1σ of the input heading. [rad]

        Returns
        -------
        T_s : ndarray, shape (n, n - 10)
            ``x0`` per unit sensor state (identity on the sensor states, the
            levelling attitude error on ``δq``).
        T_noise : ndarray, shape (n, 3)
            Per unit specific-force noise averaged over the window.
        T_psi : ndarray, shape (n,)
            Per unit input heading error.
        P_res : ndarray, shape (n, n)
            Covariance of the second-order alignment residual
            (:func:`alignment_second_order`), on ``δq``.

        Notes
        -----
        ``δf^s = Cᵀ (F_{v,s} x_s)`` at rest (the velocity rows of F are
        ``C_b^n S_a``), ``φ0 = A [δf^s; δψ]`` (:func:`alignment_jacobian`)
        and ``δq0 = −½ R(q) φ0`` (:func:`covtool.nav.attitude.attitude_error_matrix`
        inverted on the unit-norm complement).  The accelerometer Markov
        states enter with their value at the end of the window, a ~T/(2τ)
        approximation of their window mean.
        """
        m = self.model
        n = m.n
        dyn = error_dynamics(m, self.rest_ctx)
        C = self.rest_ctx.C[0]
        Sf = C.T @ dyn.F[0, 3:6, 10:]                  # δf^s per sensor state
        q0 = self.rest_ctx.q[0]
        f0 = self.rest_ctx.f_b[0]
        Rq = -0.5 * quat.R_matrix(q0)                  # δq = Rq φ
        A = alignment_jacobian(f0, self.heading, self.mounting)
        T_s = np.zeros((n, n - 10))
        T_s[10:, :] = np.eye(n - 10)
        T_s[6:10, :] = Rq @ A[:, :3] @ Sf
        T_noise = np.zeros((n, 3))
        T_noise[6:10, :] = Rq @ A[:, :3]
        T_psi = np.zeros(n)
        T_psi[6:10] = Rq @ A[:, 3]
        cov_u = np.zeros((4, 4))
        cov_u[:3, :3] = Sf @ m.initial_covariance()[10:, 10:] @ Sf.T + np.eye(3) * m.vrw**2 / self.align_time
        cov_u[3, 3] = heading_sigma**2
        _, cov_r = alignment_second_order(f0, self.heading, self.mounting, cov_u)
        P_res = np.zeros((n, n))
        P_res[6:10, 6:10] = Rq @ cov_r @ Rq.T
        return T_s, T_noise, T_psi, P_res


@dataclass
class DifferenceModel:
    """Joint linear model of the two INS errors at the epochs.

    Attributes
    ----------
    t : ndarray, shape (J+1,)
        Comparison epochs. [s]
    names : list of str
        Joint state names (``main:…``, ``kimu:…``).
    n_main : int
        States of the main IMU (the KIMU's follow).
    Phi, Qd : ndarray, shape (J, n, n)
        Transition and process noise from epoch j to j+1 (block diagonal).
    Gamma : ndarray, shape (J, n, n_c)
        Response at epoch j+1 to a unit g-sensitive scale-factor
        coefficient of each candidate acting over epoch interval j.
    H : ndarray, shape (J+1, m, n)
        Map of the joint state onto the compared components of ``z``.
    P0 : ndarray, shape (n, n)
    R : ndarray, shape (m, m)
        Comparison noise (quantisation and algorithm differences).
    components : tuple of int
        Indices into :data:`DIFF_NAMES` of the compared components.
    candidates : tuple of (int, int)
        ``(gyro axis, accel axis)`` of every g-sensitivity hypothesis.
    Hphi : ndarray, shape (J+1, 2, 3, n), optional
        Maps of the joint state onto the attitude errors ``φ`` of main and
        KIMU, for the second-order term of the attitude difference
        (:class:`Whitener`).
    """

    t: np.ndarray
    names: list
    n_main: int
    Phi: np.ndarray
    Qd: np.ndarray
    Gamma: np.ndarray
    H: np.ndarray
    P0: np.ndarray
    R: np.ndarray
    components: tuple
    candidates: tuple
    Hphi: np.ndarray | None = None

    @property
    def n(self) -> int:
        """Joint states."""
        return self.P0.shape[0]

    @property
    def m(self) -> int:
        """Compared components."""
        return len(self.components)

    def open_loop(self) -> np.ndarray:
        """Predicted covariance of the compared difference (open loop).

        ``P_z = H P Hᵀ + R`` with ``P`` propagated without any comparison:
        the envelope the difference should stay in.
        """
        P = self.P0
        out = np.empty((self.t.size, self.m, self.m))
        with np.errstate(over="ignore", invalid="ignore"):    # a blow-up is reported by the guard
            for j in range(self.t.size):
                out[j] = self.H[j] @ P @ self.H[j].T + self.R
                if j < self.t.size - 1:
                    P = symmetrize(self.Phi[j] @ P @ self.Phi[j].T + self.Qd[j])
        check_covariance(out, "dual-IMU open-loop difference", times=self.t,
                         names=[DIFF_NAMES[c] for c in self.components])
        return out


def _measurement_rows(lat, h, q):
    """Rows of the 9 difference components for one IMU's nav states."""
    rm, rn = earth.radii(lat)
    Hm = np.zeros((9, 10))
    Hm[0, 0] = rm + h
    Hm[1, 1] = (rn + h) * np.cos(lat)
    Hm[2, 2] = -1.0
    Hm[3:6, 3:6] = np.eye(3)
    Hm[6:9, 6:10] = quat.attitude_error_matrix(q)
    return Hm


def _discretize(F, Qc, dt, Fc=None, chunk=200, nav=10):
    """Φ, Q_d and the fault response of every step, exploiting the structure.

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)
        Dynamics and noise PSD, constant over each step.
    dt : float
        Step. [s]
    Fc : ndarray, shape (N, n, n_c), optional
        Columns of constant augmented states (faults), navigation rows only.
    chunk : int
        Steps of the general fallback at once.
    nav : int
        Navigation states (the first ones).

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)
    Gamma : ndarray, shape (N, n, n_c)

    Notes
    -----
    A grade model is ``F = [[A, B], [0, D]]``: the navigation block ``A``
    driven by sensor states that are random constants, random walks or
    first-order Markov (``D`` diagonal, independent noise).  The faults are
    more random constants (zero rows, no noise), so the system augmented
    with them keeps that form and :func:`covtool.lincov.discretize.block_triangular`
    gives ``Φ``, ``Q_d`` and the fault response ``Γ = ∫_0^Δ Φ(Δ−u) F_c du``
    (the fault columns of the augmented ``Φ``) exactly, with its products
    done by blocks.  Any other structure falls back to the exact
    discretisation of the whole augmented system.
    """
    N, n, _ = F.shape
    nc = 0 if Fc is None else Fc.shape[-1]
    if nc:
        Fa = np.zeros((N, n + nc, n + nc))
        Fa[:, :n, :n] = F
        Fa[:, :n, n:] = Fc
        Qa = np.zeros_like(Fa)
        Qa[:, :n, :n] = Qc
    else:
        Fa, Qa = F, Qc
    what = "dual-IMU linear model"
    if is_block_triangular(Fa, Qa, nav):
        Phi, Qd = block_triangular(Fa, Qa, dt, nav, what=what)
    else:
        Phi = np.empty_like(Fa)
        Qd = np.empty_like(Fa)
        for a in range(0, N, chunk):
            b = min(N, a + chunk)
            Phi[a:b], Qd[a:b] = taylor(Fa[a:b], Qa[a:b], dt, what=what)
    return Phi[:, :n, :n], Qd[:, :n, :n], Phi[:, :n, n:]


@_serial_blas
def difference_model(main: ImuLinearization, kimu: ImuLinearization, *, t_epochs, lat_epochs, h_epochs,
                     substeps_per_epoch: int, dt_sub: float, heading_sigma: float, products=None,
                     candidates=(), components=tuple(range(9)), noise=None, extra_noise=None,
                     chunk: int = 200) -> DifferenceModel:
    """Linear model of the main − KIMU difference (seed 001 method II).

    Parameters
    ----------
    main, kimu : ImuLinearization
        The two IMUs along the flight (contexts of N = J·substeps_per_epoch
        propagation steps).
    t_epochs, lat_epochs, h_epochs : ndarray, shape (J+1,)
        Comparison epochs and the position there. [s], [rad], [m]
    substeps_per_epoch : int
        Propagation steps per comparison interval.
    dt_sub : float
        Propagation step. [s]
    heading_sigma : float
        1σ of the input heading both alignments share. [rad]
    products : ndarray, shape (N, 3, 3), optional
        Step means of ``ω_i f_j`` of the KIMU (``[i, j]``), the regressors
        of the g-sensitive scale-factor candidates. [rad/s · m/s²]
    candidates : sequence of (int, int)
        ``(gyro axis i, accel axis j)`` hypotheses.
    components : sequence of int
        Compared components (indices into :data:`DIFF_NAMES`).
    noise : array_like, shape (9,), optional
        1σ comparison noise per component (default zero).
    extra_noise : sequence of (str, int, ndarray, ndarray), optional
        ``(imu, epoch interval j, σ_φ (3,), σ_v (3,))``: white errors added
        by a bridged telemetry gap, sensor axes ([rad], [m/s]).
    chunk : int
        Steps discretised at once.

    Returns
    -------
    DifferenceModel

    Notes
    -----
    Each block is ``ẋ_i = F_i(t) x_i + w_i`` (:func:`covtool.lincov.dynamics.error_dynamics`
    along the IMU's own context), discretised by Van Loan per step and
    chained over the epoch interval.  The fault of candidate ``(i, j)``
    adds the column ``½ Q(q) e_i ⟨ω_i f_j⟩`` to the KIMU's quaternion rows
    (a g-sensitive scale factor is ``δω_i = k f_j ω_i``), discretised with
    the same exponential (the augmented state is a random constant with no
    noise).  ``z = H_main x_main − H_kimu x_kimu``.
    """
    cands = tuple((int(i), int(j)) for i, j in candidates)
    comps = tuple(int(c) for c in components)
    J = t_epochs.size - 1
    N = J * int(substeps_per_epoch)
    for imu, lin in (("main", main), ("kimu", kimu)):
        if lin.ctx.n != N:
            raise ValueError(f"{imu}: context has {lin.ctx.n} steps, expected {N}")
    if cands and (products is None or products.shape != (N, 3, 3)):
        raise ValueError(f"products must have shape ({N}, 3, 3) for the fault candidates")
    blocks = []
    k = int(substeps_per_epoch)
    for idx, lin in enumerate((main, kimu)):
        model = lin.model
        n = model.n
        dyn = error_dynamics(model, lin.ctx)
        Fc = None
        if idx == 1 and cands:
            halfQ = 0.5 * quat.Q_matrix(lin.ctx.q)                   # (N, 4, 3)
            Fc = np.zeros((N, n, len(cands)))
            for c, (i, j) in enumerate(cands):
                Fc[:, 6:10, c] = halfQ[:, :, i] * products[:, i, j][:, None]
        Phi_s, Qd_s, Gam_s = _discretize(dyn.F, dyn.Qc, dt_sub, Fc, chunk)
        nc = Gam_s.shape[-1]
        Phi = np.empty((J, n, n))
        Qd = np.empty((J, n, n))
        Gam = np.zeros((J, n, nc))
        for jj in range(J):
            P = np.eye(n)
            Q = np.zeros((n, n))
            G = np.zeros((n, nc))
            for s in range(jj * k, (jj + 1) * k):
                Ps = Phi_s[s]
                P = Ps @ P
                Q = Ps @ Q @ Ps.T + Qd_s[s]
                G = Ps @ G + Gam_s[s]
            Phi[jj], Qd[jj], Gam[jj] = P, 0.5 * (Q + Q.T), G
        blocks.append((Phi, Qd, Gam))
    nm, nk = main.model.n, kimu.model.n
    n = nm + nk
    Phi = np.zeros((J, n, n))
    Qd = np.zeros((J, n, n))
    Gamma = np.zeros((J, n, len(cands)))
    Phi[:, :nm, :nm], Qd[:, :nm, :nm] = blocks[0][0], blocks[0][1]
    Phi[:, nm:, nm:], Qd[:, nm:, nm:] = blocks[1][0], blocks[1][1]
    Gamma[:, nm:, :] = blocks[1][2]
    for imu, jj, s_phi, s_v in (extra_noise or ()):
        off = 0 if imu == "main" else nm
        lin = main if imu == "main" else kimu
        s = int(jj) * int(substeps_per_epoch)
        q = lin.ctx.q[min(s, N - 1)]
        G = 0.5 * quat.Q_matrix(q)
        C = quat.dcm(q)
        Qd[jj, off + 6:off + 10, off + 6:off + 10] += G @ np.diag(np.square(s_phi)) @ G.T
        Qd[jj, off + 3:off + 6, off + 3:off + 6] += C @ np.diag(np.square(s_v)) @ C.T
    # initial covariance: sensor states, levelling noise and the shared heading
    Ts_m, Tn_m, Tp_m, Pr_m = main.initial_map(heading_sigma)
    Ts_k, Tn_k, Tp_k, Pr_k = kimu.initial_map(heading_sigma)
    Ps_m = main.model.initial_covariance()[10:, 10:]
    Ps_k = kimu.model.initial_covariance()[10:, 10:]
    T = np.zeros((n, (nm - 10) + (nk - 10) + 7))
    c0 = 0
    T[:nm, c0:c0 + nm - 10] = Ts_m
    c0 += nm - 10
    T[nm:, c0:c0 + nk - 10] = Ts_k
    c0 += nk - 10
    T[:nm, c0:c0 + 3] = Tn_m
    T[nm:, c0 + 3:c0 + 6] = Tn_k
    T[:nm, c0 + 6] = Tp_m
    T[nm:, c0 + 6] = Tp_k
    Su = np.zeros((T.shape[1], T.shape[1]))
    Su[:nm - 10, :nm - 10] = Ps_m
    Su[nm - 10:nm + nk - 20, nm - 10:nm + nk - 20] = Ps_k
    for lin, a in ((main, c0), (kimu, c0 + 3)):
        Su[a:a + 3, a:a + 3] = np.eye(3) * lin.model.vrw**2 / lin.align_time
    Su[c0 + 6, c0 + 6] = heading_sigma**2
    P0 = T @ Su @ T.T
    P0[:nm, :nm] += Pr_m
    P0[nm:, nm:] += Pr_k
    P0 = 0.5 * (P0 + P0.T)
    H = np.zeros((J + 1, len(comps), n))
    Hphi = np.zeros((J + 1, 2, 3, n))
    for jj in range(J + 1):
        rows_m = _measurement_rows(lat_epochs[jj], h_epochs[jj], main.q_epochs[jj])
        rows_k = _measurement_rows(lat_epochs[jj], h_epochs[jj], kimu.q_epochs[jj])
        H[jj, :, :10] = rows_m[list(comps)]
        H[jj, :, nm:nm + 10] = -rows_k[list(comps)]
        Hphi[jj, 0, :, :10] = rows_m[6:9]
        Hphi[jj, 1, :, nm:nm + 10] = rows_k[6:9]
    sig = np.zeros(9) if noise is None else np.asarray(noise, float)
    R = np.diag(sig[list(comps)] ** 2)
    names = [f"main:{s}" for s in main.model.names] + [f"kimu:{s}" for s in kimu.model.names]
    return DifferenceModel(np.asarray(t_epochs, float), names, nm, Phi, Qd, Gamma, H, P0, R, comps, cands, Hphi)


# --------------------------------------------------------------------------
# whitening, envelope test and g-sensitivity estimation
# --------------------------------------------------------------------------


@dataclass
class Innovations:
    """Innovations of the difference under the no-fault model.

    Attributes
    ----------
    nu : ndarray, shape (M, J+1, m)
        Innovations ``z_j − H_j x̂_j⁻``.
    S : ndarray, shape (J+1, m, m)
        Their predicted covariance ``H P⁻ Hᵀ + R``.
    nis : ndarray, shape (M, J+1)
        Normalised innovation squared ``νᵀ S⁻¹ ν`` (χ²(m) per epoch).
    rho : ndarray, shape (J+1, m, n_c)
        Fault signatures: the innovation mean per unit coefficient of each
        candidate.
    """

    nu: np.ndarray
    S: np.ndarray
    nis: np.ndarray
    rho: np.ndarray


class Whitener:
    """Kalman filter of a DifferenceModel, one epoch at a time.

    Parameters
    ----------
    model : DifferenceModel
    n_runs : int
        Runs M whitened at once (they share the gains).

    Notes
    -----
    :meth:`update` forms the innovation of epoch j and the fault
    signatures (Willsky & Jones 1976): a constant fault ``c`` adds
    ``ρ_j c`` to the innovations with ``ρ_j = H_j μ_j``,
    ``μ_{j+1} = Φ_j (I − K_j H_j) μ_j + Γ_j``, ``μ_0 = 0``.
    :meth:`take_navigation` hands the estimated navigation errors over for
    feedback (seed 002, eq (10): ``x ← x − x̂``) and zeroes them in the
    estimate; in the linear model this leaves the innovations unchanged, and
    it keeps the two solutions close to their linearisation so that the
    second-order terms (``½ φ×(φ×f)`` at 10–20 g) stay negligible.
    Gain and Joseph-form update by :func:`covtool.lincov.kalman.kalman_gain`
    and :func:`~covtool.lincov.kalman.filter_update`; the model (P0, Φ, Q_d,
    R) is checked on entry and the covariance after every update and
    prediction (:func:`~covtool.lincov.kalman.check_covariance`), naming the
    epoch time and the joint state.

    Raises
    ------
    NumericalError
        A model matrix or a covariance is not finite, symmetric and PSD.
    """

    def __init__(self, model: DifferenceModel, n_runs: int):
        J1, m, nc = model.t.size, model.m, len(model.candidates)
        what = "dual-IMU whitener"
        check_covariance(model.P0, f"{what}: P0", names=model.names)
        check_finite(model.Phi, f"{what}: Φ of the epoch interval", names=model.names, times=model.t)
        check_covariance(model.Qd, f"{what}: Q_d of the epoch interval", names=model.names,
                         times=model.t)
        check_covariance(model.R, f"{what}: comparison noise R")
        self.model = model
        self.P = model.P0.copy()
        self.x = np.zeros((int(n_runs), model.n))
        self.mu = np.zeros((model.n, nc))
        self.nu = np.empty((int(n_runs), J1, m))
        self.S = np.empty((J1, m, m))
        self.nis = np.empty((int(n_runs), J1))
        self.rho = np.empty((J1, m, nc))

    def update(self, j: int, z) -> np.ndarray:
        """Process epoch ``j``'s compared difference (M, m); return ν."""
        model = self.model
        H = model.H[j]
        P = self.P
        R = model.R.copy()
        zhat = self.x @ H.T
        att = [i for i, c in enumerate(model.components) if c >= 6]
        if att and model.Hphi is not None:
            # z_att = φ_m − φ_k + ½ φ_m × φ_k: Gaussian second-order mean and covariance
            ax = [model.components[i] - 6 for i in att]
            Hm, Hk = model.Hphi[j, 0], model.Hphi[j, 1]
            a, b = self.x @ Hm.T, self.x @ Hk.T
            Pa, Pb, Pab = Hm @ P @ Hm.T, Hk @ P @ Hk.T, Hm @ P @ Hk.T
            mean = 0.5 * (np.cross(a, b) + np.einsum("ijk,jk->i", _EPS, Pab))
            cov = 0.25 * (np.einsum("ijk,lmn,jm,kn->il", _EPS, _EPS, Pa, Pb)
                          + np.einsum("ijk,lmn,jn,mk->il", _EPS, _EPS, Pab, Pab))
            zhat[:, att] += mean[:, ax]
            R[np.ix_(att, att)] += cov[np.ix_(ax, ax)]
        S = innovation_covariance(P, H, R)
        K = kalman_gain(P, H, R, S=S)
        v = np.asarray(z, float) - zhat
        self.nu[:, j] = v
        self.S[j] = S
        self.nis[:, j] = np.einsum("mi,mi->m", v, np.linalg.solve(S, v.T).T)
        self.rho[j] = H @ self.mu
        self.x = self.x + v @ K.T
        self.P = filter_update(P, K, H, R, "joseph")
        self._check(j, "after the update")
        self.mu = self.mu - K @ (H @ self.mu)                # (I − K H) μ
        return v

    def _check(self, j: int, step: str) -> None:
        check_covariance(self.P, f"dual-IMU whitener: {step} at "
                         f"{time_text(float(self.model.t[j]))}", names=self.model.names)

    def take_navigation(self):
        """Hand over the navigation-error estimates (M, 10) each."""
        nm = self.model.n_main
        dm = self.x[:, :10].copy()
        dk = self.x[:, nm:nm + 10].copy()
        self.x[:, :10] = 0.0
        self.x[:, nm:nm + 10] = 0.0
        return dm, dk

    def predict(self, j: int) -> None:
        """Propagate from epoch ``j`` to ``j + 1``."""
        model = self.model
        Phi = model.Phi[j]
        self.x = self.x @ Phi.T
        self.P = symmetrize(Phi @ self.P @ Phi.T + model.Qd[j])
        self._check(j + 1, "after the prediction")
        self.mu = Phi @ self.mu + model.Gamma[j]

    def result(self) -> "Innovations":
        """The innovations processed so far."""
        return Innovations(self.nu, self.S, self.nis, self.rho)


@_serial_blas
def innovations(model: DifferenceModel, z) -> Innovations:
    """Whiten open-loop differences with the model's Kalman filter.

    Parameters
    ----------
    model : DifferenceModel
    z : array_like, shape (M, J+1, m) or (J+1, m)
        Compared components of the difference at the epochs.

    Returns
    -------
    Innovations
        Under the model ``ν_j ~ N(0, S_j)``, independent over j.

    Raises
    ------
    ValueError
        ``z`` does not have one row per epoch and one column per compared
        component.
    """
    z = np.asarray(z, float)
    if z.ndim == 2:
        z = z[None]
    M, J1, m = z.shape
    if J1 != model.t.size or m != model.m:
        raise ValueError(f"z must have shape (M, {model.t.size}, {model.m}), got {z.shape}")
    w = Whitener(model, M)
    for j in range(J1):
        w.update(j, z[:, j])
        if j < J1 - 1:
            w.predict(j)
    return w.result()


def window_test(nis, dof: int, window: int, false_alarm: float):
    """Sliding-window χ² test of the normalised innovations.

    Parameters
    ----------
    nis : ndarray, shape (M, J+1)
        Normalised innovations squared, χ²(dof) each under the model.
    dof : int
        Degrees of freedom per epoch (compared components m).
    window : int
        Epochs per window.
    false_alarm : float
        Design probability of one or more alarms in a fault-free flight.

    Returns
    -------
    stat : ndarray, shape (M, N_w)
        Window sums ``Σ νᵀS⁻¹ν`` (χ²(dof·window) each under the model).
    threshold : float
        ``χ²⁻¹(1 − α/N_w; dof·window)``: Bonferroni over the N_w windows,
        so that P(any alarm | no fault) ≤ α.
    flagged : ndarray of bool, shape (M, N_w)

    Raises
    ------
    ValueError
        The window is longer than the record or α is not in (0, 1).
    """
    nis = np.atleast_2d(np.asarray(nis, float))
    J1 = nis.shape[1]
    window = int(window)
    if not 1 <= window <= J1:
        raise ValueError(f"window of {window} epochs does not fit {J1} epochs")
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f"false-alarm probability must be in (0, 1), got {false_alarm!r}")
    if not np.isfinite(nis).all():
        m, j = np.argwhere(~np.isfinite(nis))[0]
        raise NumericalError(f"window test: the normalised innovation of run {m} at epoch {j} is not finite (the "
                             "navigation or the filter diverged); no alarm decision can be reported")
    c = np.concatenate([np.zeros((nis.shape[0], 1)), np.cumsum(nis, axis=1)], axis=1)
    stat = c[:, window:] - c[:, :-window]
    Nw = stat.shape[1]
    thr = float(chi2.isf(false_alarm / Nw, dof * window))
    return stat, thr, stat > thr


def flagged_intervals(flagged, t_epochs, window: int):
    """Merge flagged windows into time intervals.

    Parameters
    ----------
    flagged : ndarray of bool, shape (N_w,)
        Window w covers epochs ``w … w + window − 1``.
    t_epochs : ndarray, shape (J+1,)
    window : int

    Returns
    -------
    list of (float, float)
        ``(start, end)`` times of the merged flagged spans. [s]
    """
    out = []
    for w in np.flatnonzero(flagged):
        a, b = float(t_epochs[w]), float(t_epochs[w + window - 1])
        if out and a <= out[-1][1] + 1e-9:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


@dataclass
class GsensEstimate:
    """GLS estimates of the g-sensitive scale-factor candidates.

    Attributes
    ----------
    candidates : tuple of (int, int)
    estimate : ndarray, shape (M, n_c)
        Single-fault estimates ``ĉ = bᵀ/A_cc``. [1/(m/s²)]
    sigma : ndarray, shape (n_c,)
        Their 1σ from the predicted covariance, ``A_cc^{-1/2}``.
    glr : ndarray, shape (M, n_c)
        Generalised likelihood ratios ``b_c²/A_cc`` (χ²(1) with no fault).
    threshold : float
        ``χ²⁻¹(1 − α/n_c; 1)``.
    detected : ndarray of bool, shape (M,)
        Largest GLR above the threshold.
    identified : ndarray of int, shape (M,)
        Candidate with the largest GLR.
    information : ndarray, shape (n_c, n_c)
        ``A = Σ ρᵀ S⁻¹ ρ`` (joint Fisher information).
    """

    candidates: tuple
    estimate: np.ndarray
    sigma: np.ndarray
    glr: np.ndarray
    threshold: float
    detected: np.ndarray
    identified: np.ndarray
    information: np.ndarray


@_serial_blas
def gsens_estimates(inn: Innovations, candidates, false_alarm: float, *, strict: bool = True) -> GsensEstimate:
    """Detect and estimate a g-sensitive scale factor (GLR/GLS).

    Parameters
    ----------
    inn : Innovations
    candidates : sequence of (int, int)
    false_alarm : float
        Design probability of a detection in a fault-free flight
        (Bonferroni over the candidates).
    strict : bool
        Raise if a candidate has no signature; otherwise its estimate is
        NaN, its σ infinite and its GLR 0.

    Returns
    -------
    GsensEstimate

    Notes
    -----
    With ``ν_j = ν_j⁰ + ρ_j c`` and ``ν_j⁰ ~ N(0, S_j)`` white, the GLS
    estimate of a single candidate is ``ĉ = Σ ρᵀS⁻¹ν / Σ ρᵀS⁻¹ρ`` with
    variance ``1/Σ ρᵀS⁻¹ρ``; the GLR ``(Σ ρᵀS⁻¹ν)²/Σ ρᵀS⁻¹ρ`` is χ²(1)
    without a fault.  The nuisance errors (biases, scale factors, mass
    unbalance …) are estimated along by the filter, so their correlation
    with the fault is accounted for.
    """
    cands = tuple(candidates)
    nc = len(cands)
    if nc == 0:
        raise ValueError("no g-sensitivity candidates")
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f"false-alarm probability must be in (0, 1), got {false_alarm!r}")
    Sinv_rho = np.linalg.solve(inn.S, inn.rho)                         # (J, m, nc)
    A = np.einsum("jmc,jmd->cd", inn.rho, Sinv_rho)
    b = np.einsum("Mjm,jmc->Mc", inn.nu, Sinv_rho)
    diag = np.diag(A).copy()
    dead = diag <= 0
    if strict and dead.any():
        bad = [candidate_label(cands[i]) for i in np.flatnonzero(dead)]
        raise ValueError(f"g-sensitivity candidates {', '.join(bad)} have no signature in this flight "
                         "(the product ω_i f_j is zero throughout)")
    safe = np.where(dead, 1.0, diag)
    est = np.where(dead, np.nan, b / safe)
    sigma = np.where(dead, np.inf, 1.0 / np.sqrt(safe))
    glr = np.where(dead, 0.0, b**2 / safe)
    if not np.isfinite(glr).all():
        m = int(np.argwhere(~np.isfinite(glr))[0, 0])
        raise NumericalError(f"g-sensitivity test: the GLR statistic of run {m} is not finite (the navigation or "
                             "the filter diverged); no detection can be reported")
    thr = float(chi2.isf(false_alarm / nc, 1))
    best = np.argmax(glr, axis=1)
    detected = glr[np.arange(glr.shape[0]), best] > thr
    return GsensEstimate(cands, est, sigma, glr, thr, detected, best, A)


# --------------------------------------------------------------------------
# telemetry gaps
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class GapReport:
    """One bridged gap.

    Attributes
    ----------
    imu : str
    after : float
        Time of the last sample before the gap. [s]
    before : float
        Time of the first sample after the gap. [s]
    samples : int
        Samples bridged.
    policy : str
    sigma_attitude : ndarray, shape (3,)
        Predicted extra error of the summed angle increments per sensor
        axis (1σ). [rad]
    sigma_velocity : ndarray, shape (3,)
        Predicted extra error of the summed velocity increments (1σ). [m/s]
    trials : int
        Trial bridges the prediction rests on (0: the lost white noise
        only).
    """

    imu: str
    after: float
    before: float
    samples: int
    policy: str
    sigma_attitude: np.ndarray
    sigma_velocity: np.ndarray
    trials: int = 0


@dataclass
class BridgedLog:
    """An IMU log after gap bridging.

    Attributes
    ----------
    t : ndarray, shape (K,)
        Sample end times: the recorded times of the kept samples, exactly;
        bridged samples evenly between their recorded neighbours. [s]
    dtheta, dv : ndarray, shape (K, 3) or (M, K, 3)
    dt : float
        Nominal sample period (the grade's). [s]
    gaps : list of GapReport
    bridged : ndarray of bool, shape (K,)
        True for the samples the policy filled in.
    where : str
        The log (its file) named in every message.
    period : float or None
        Sample period measured from the recorded times
        (:func:`clock_rate`). [s]
    """

    t: np.ndarray
    dtheta: np.ndarray
    dv: np.ndarray
    dt: float
    gaps: list = field(default_factory=list)
    bridged: np.ndarray | None = None
    where: str = ""
    period: float | None = None

    @property
    def clock_ppm(self) -> float:
        """Measured period's offset from the nominal one. [ppm]"""
        period = self.period if self.period is not None else clock_rate(self.t, self.dt)[0]
        return (period / self.dt - 1.0) * 1e6


#: resolution of :func:`clock_rate` on recorded times exact to 17 digits [ppm]
CLOCK_PPM_TOL = 0.1


def clock_rate(t, dt: float) -> tuple[float, float]:
    """Sample period of a log measured from its recorded times.

    Parameters
    ----------
    t : array_like, shape (K,)
        Recorded sample end times, strictly increasing, possibly with
        missing samples. [s]
    dt : float
        Nominal sample period. [s]

    Returns
    -------
    period : float
        Least-squares slope of ``t`` against the sample number (missing
        samples counted from the median step). [s]
    ppm : float
        ``(period / dt − 1) · 10⁶``: how far the log's clock runs from its
        nominal rate. [ppm]
    """
    t = np.asarray(t, float)
    if t.size < 2:
        return float(dt), 0.0
    step = np.diff(t)
    n = np.concatenate([[0.0], np.cumsum(np.maximum(np.rint(step / np.median(step)), 1.0))])
    tc = t - t[0]
    nc = n - n.mean()
    period = float(nc @ (tc - tc.mean()) / (nc @ nc))
    return period, (period / dt - 1.0) * 1e6


def find_gaps(t, dt: float, where: str = "IMU log"):
    """Locate missing samples on a nominal sample grid.

    Parameters
    ----------
    t : array_like, shape (K,)
        Sample end times, strictly increasing. [s]
    dt : float
        Nominal sample period. [s]
    where : str
        Names the log in error messages.

    Returns
    -------
    list of (int, int)
        ``(k, n)``: ``n`` samples are missing between samples ``k`` and
        ``k + 1``.

    Raises
    ------
    InputError
        A step that is not a whole number of periods (within 10 %): the log
        is not on one sample grid, so no gap can be bridged reliably.
    """
    t = np.asarray(t, float)
    steps = np.diff(t) / dt
    whole = np.rint(steps)
    bad = (np.abs(steps - whole) > 0.1) | (whole < 1)
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(f"{where}: column 't [s]'", f"row {k + 2}: step {t[k + 1] - t[k]:.9g} s after "
                         f"t = {t[k]:.9g} s is not a whole number of sample periods ({dt:.9g} s); "
                         "the log is not on one sample grid")
    return [(int(k), int(whole[k]) - 1) for k in np.flatnonzero(whole > 1)]


def _fill(prev, nxt, n: int, policy: str):
    """Increments for ``n`` missing samples from the samples around them.

    ``prev`` (…, w, 3) are the valid samples just before the gap, ``nxt``
    (…, w, 3) those just after (w ≥ 1, oldest first).
    """
    w = prev.shape[-2]
    if policy == "hold":
        return np.repeat(prev[..., -1:, :], n, axis=-2)
    a = prev.mean(axis=-2)
    if policy == "propagate":
        return np.repeat(a[..., None, :], n, axis=-2)
    # interpolate: a straight line through the window means at their mid-times
    b = nxt.mean(axis=-2)
    ta, tb = -(w + 1) / 2.0, n + (w - 1) / 2.0
    u = (np.arange(n) - ta) / (tb - ta)
    return a[..., None, :] + u[:, None] * (b - a)[..., None, :]


def _trial_errors(x, stretches, n, policy, w, max_trials):
    """Errors of the summed increments of trial bridges in valid data."""
    errs = []
    for s0, s1 in stretches:                  # valid samples s0 … s1 (inclusive), no gap inside
        first, last = s0 + w - 1, s1 - n - w  # the trial gap covers a+1 … a+n
        if last < first:
            continue
        for a in np.linspace(first, last, min(max_trials, last - first + 1)).astype(int):
            fill = _fill(x[..., a + 1 - w:a + 1, :], x[..., a + n + 1:a + n + 1 + w, :], n, policy)
            errs.append((fill.sum(axis=-2) - x[..., a + 1:a + n + 1, :].sum(axis=-2)).reshape(-1, 3))
    return np.concatenate(errs) if errs else np.zeros((0, 3))


def bridge_gaps(t, dtheta, dv, dt: float, policy: str, *, arw: float = 0.0, vrw: float = 0.0,
                imu: str = "IMU", window: int = 10, trials: int = 8, where: str = "IMU log") -> BridgedLog:
    """Bridge missing samples of an IMU log by a declared policy.

    Parameters
    ----------
    t : array_like, shape (K,)
        Sample end times. [s]
    dtheta, dv : array_like, shape (K, 3) or (M, K, 3)
        Increments. [rad], [m/s]
    dt : float
        Nominal sample period. [s]
    policy : {"hold", "interpolate", "propagate", "refuse"}
        ``hold``: repeat the last sample; ``propagate``: the mean increment
        of the ``window`` samples before the gap; ``interpolate``: a
        straight line between the means of the ``window`` samples on either
        side; ``refuse``: raise.
    arw, vrw : float
        Root-PSDs of the IMU's white noises: the noise the missing samples
        carried is lost, at least ``σ² = arw² T_gap``. [rad/√s], [m/s/√s]
    imu : str
        Name in the report.
    window : int
        Samples averaged by ``propagate`` and ``interpolate``.
    trials : int
        Trial bridges on each side of a gap for the error prediction.
    where : str
        Names the log in error messages (and in :attr:`BridgedLog.where`).

    Returns
    -------
    BridgedLog
        Kept samples keep their recorded times exactly; the ``n`` samples
        inserted in a gap get times evenly between the recorded
        neighbours.  Gaps are counted in the log's own median step, and the
        measured period (:func:`clock_rate`) is kept.  Every bridged gap is
        reported (:class:`GapReport`) with its predicted extra error: the
        RMS error of the summed increments of the same policy applied to
        trial gaps of the same length in the valid data on each side (up to
        ``trials`` per side, all runs pooled; the larger side), and never
        less than the lost white noise.

    Raises
    ------
    InputError
        Unknown policy, a gap with ``policy = "refuse"``, too few valid
        samples around a gap to bridge it, or a log not on one grid.
    """
    if policy not in GAP_POLICIES:
        raise InputError(f"{where}: gap policy", f"{policy!r} is not one of {', '.join(GAP_POLICIES)}")
    t = np.asarray(t, float)
    dtheta = np.asarray(dtheta, float)
    dv = np.asarray(dv, float)
    # gaps are counted in the log's own sample period: a clock a few hundred ppm off its nominal rate
    # would otherwise turn a long gap into a non-integer number of periods
    own = float(np.median(np.diff(t))) if t.size > 1 else float(dt)
    gaps = find_gaps(t, own, where)
    period, _ = clock_rate(t, dt)
    if gaps and policy == "refuse":
        k, n = gaps[0]
        raise InputError(f"{where}: column 't [s]'", f"{n} samples missing between t = {t[k]:.9g} s and "
                         f"{t[k + 1]:.9g} s (gap policy 'refuse'); {len(gaps)} gap(s) in all")
    if not gaps:
        return BridgedLog(t, dtheta, dv, dt, [], np.zeros(t.size, bool), where, period)
    w = max(1, int(window)) if policy != "hold" else 1
    bounds = [-1] + [k for k, _ in gaps] + [t.size - 1]
    stretches = [(bounds[i] + 1, bounds[i + 1]) for i in range(len(bounds) - 1)]
    pieces_t, pieces_th, pieces_v, flags, reports = [], [], [], [], []
    start = 0
    for g, (k, n) in enumerate(gaps):
        s_before, s_after = stretches[g], stretches[g + 1]
        if k - s_before[0] + 1 < w or s_after[1] - (k + 1) + 1 < w:
            raise InputError(f"{where}: column 't [s]'", f"gap of {n} samples after t = {t[k]:.9g} s: fewer than "
                             f"{w} valid samples on each side to bridge it with policy {policy!r}")
        pieces_t.append(t[start:k + 1])
        pieces_th.append(dtheta[..., start:k + 1, :])
        pieces_v.append(dv[..., start:k + 1, :])
        flags.append(np.zeros(k + 1 - start, bool))
        # kept samples keep their recorded times; only the inserted ones are placed, evenly between the
        # recorded neighbours (the log's own clock, whatever its rate)
        pieces_t.append(t[k] + (t[k + 1] - t[k]) * np.arange(1, n + 1) / (n + 1))
        prev = slice(k + 1 - w, k + 1)
        nxt = slice(k + 1, k + 1 + w)
        pieces_th.append(_fill(dtheta[..., prev, :], dtheta[..., nxt, :], n, policy))
        pieces_v.append(_fill(dv[..., prev, :], dv[..., nxt, :], n, policy))
        flags.append(np.ones(n, bool))
        T = n * dt
        var_att, var_vel, count = np.full(3, arw**2 * T), np.full(3, vrw**2 * T), 0
        for side in (s_before, s_after):
            # the larger side's mean square: the dynamics may change at the gap
            e_th = _trial_errors(dtheta, [side], n, policy, w, trials)
            e_v = _trial_errors(dv, [side], n, policy, w, trials)
            if len(e_th):
                var_att = np.maximum(var_att, np.mean(e_th**2, axis=0))
                var_vel = np.maximum(var_vel, np.mean(e_v**2, axis=0))
                count += len(e_th)
        reports.append(GapReport(imu, float(t[k]), float(t[k + 1]), n, policy, np.sqrt(var_att), np.sqrt(var_vel),
                                 count))
        start = k + 1
    pieces_t.append(t[start:])
    pieces_th.append(dtheta[..., start:, :])
    pieces_v.append(dv[..., start:, :])
    flags.append(np.zeros(t.size - start, bool))
    return BridgedLog(np.concatenate(pieces_t), np.concatenate(pieces_th, axis=-2), np.concatenate(pieces_v, axis=-2),
                      dt, reports, np.concatenate(flags), where, period)


# --------------------------------------------------------------------------
# the whole comparison
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class DualSetup:
    """Everything the comparison needs besides the IMU data (SI).

    Attributes
    ----------
    main_model, kimu_model : Model
        Error models of the two IMUs (:meth:`ImuGrade.to_model`).
    main_mounting, kimu_mounting : ndarray, shape (4,)
        Declared ``q_bs`` of each sensor frame in the vehicle body.
    ratio : int
        KIMU samples per main sample (seed 001: 4).
    align_time : float
        Alignment window at the start of the logs (vehicle at rest). [s]
    lat, lon, h : float
        Input position at the start. [rad], [rad], [m]
    heading : float
        Input heading of the vehicle body x axis. [rad]
    heading_sigma : float
        Its 1σ (shared by both alignments). [rad]
    substep : int
        Main intervals per step of the linear model.
    compare_every : int
        Main intervals per comparison epoch (a multiple of ``substep``).
    components : tuple of int
        Compared components (indices into :data:`DIFF_NAMES`).
    noise : ndarray, shape (9,)
        1σ comparison noise per component.
    window : int
        Epochs per window of the χ² test.
    false_alarm : float
        Design probability of a false alarm per flight, for each of the
        window test and the g-sensitivity detection.
    candidates : tuple of (int, int)
        g-sensitive scale-factor hypotheses ``(gyro axis, accel axis)``.
    """

    main_model: Model
    kimu_model: Model
    main_mounting: np.ndarray
    kimu_mounting: np.ndarray
    ratio: int
    align_time: float
    lat: float
    lon: float
    h: float
    heading: float
    heading_sigma: float
    substep: int
    compare_every: int
    components: tuple
    noise: np.ndarray
    window: int
    false_alarm: float
    candidates: tuple


@dataclass
class DualRun:
    """Outcome of one comparison (M runs of the same flight).

    Attributes
    ----------
    t : ndarray, shape (J+1,)
        Comparison epochs. [s]
    z : ndarray, shape (M, J+1, 9)
        Differences main − KIMU (all nine components).
    model : DifferenceModel
    envelope : ndarray, shape (J+1, m)
        Predicted 1σ of each compared component (open loop).
    inn : Innovations
    window_stat : ndarray, shape (M, N_w)
    window_threshold : float
    flagged : ndarray of bool, shape (M, N_w)
    intervals : list of list of (float, float)
        Flagged spans of every run.
    gsens : GsensEstimate
    main, kimu : covtool.nav.strapdown.NavHistory
        The two solutions at the epochs.
    unused : dict of str to (int, int)
        Samples of each log before and after the compared span (outside the
        common span of the logs, or after the last whole comparison
        interval): reported, never silently dropped.
    clock : dict of str to float
        ``main``, ``kimu``: each log's measured clock offset from its
        nominal rate; ``mismatch``: the main period over ``ratio`` KIMU
        periods, minus one. [ppm]
    """

    t: np.ndarray
    z: np.ndarray
    model: DifferenceModel
    envelope: np.ndarray
    inn: Innovations
    window_stat: np.ndarray
    window_threshold: float
    flagged: np.ndarray
    intervals: list
    gsens: GsensEstimate
    main: sd.NavHistory
    kimu: sd.NavHistory
    unused: dict = field(default_factory=dict)
    clock: dict = field(default_factory=dict)


def _runs(x):
    x = np.asarray(x)
    return x if x.ndim == 3 else x[None]


def _subsample(hist: sd.NavHistory, idx) -> sd.NavHistory:
    return sd.NavHistory(hist.t[idx], hist.lat[idx], hist.lon[idx], hist.h[idx], hist.v_n[idx], hist.q[idx])


def _final_state(hist: sd.NavHistory, rec: ImuRecord) -> sd.NavState:
    """Last state of a run, with the record's last sample as "previous"."""
    return sd.NavState(float(hist.t[-1]), hist.lat[-1], hist.lon[-1], hist.h[-1], hist.v_n[-1], hist.q[-1],
                       np.array(rec.dtheta[:, -1]), np.array(rec.dv[:, -1]))


def _closed_loop(model, rec_m, rec_k, sm, sk, r, ce, setup, q_ref_m, q_ref_k) -> Innovations:
    """Whiten with the navigation-error estimates fed back at every epoch."""
    J1 = model.t.size
    M = max(sm.n_runs, sk.n_runs, rec_m.dtheta.shape[0], rec_k.dtheta.shape[0])
    w = Whitener(model, M)
    comps = list(setup.components)

    def signed(state, q_ref):
        # δq is defined against the reference quaternion's sign
        flip = np.sum(state.q * q_ref, axis=-1) < 0
        return state.replace(q=np.where(flip[:, None], -state.q, state.q)) if flip.any() else state

    for j in range(J1):
        if j:
            a = (j - 1) * ce
            rm = rec_m.slice(a, a + ce)
            rk = rec_k.slice(a * r, (a + ce) * r)
            sm = _final_state(sd.run(sm, rm, 1, every=ce), rm)
            sk = _final_state(sd.run(sk, rk, r, every=ce), rk)
        hm_ = sd.NavHistory(np.array([sm.t]), sm.lat[None], sm.lon[None], sm.h[None], sm.v_n[None], sm.q[None])
        hk_ = sd.NavHistory(np.array([sk.t]), sk.lat[None], sk.lon[None], sk.h[None], sk.v_n[None], sk.q[None])
        z = nav_difference(hm_, hk_, setup.main_mounting, setup.kimu_mounting)[0][:, comps]
        w.update(j, z)
        dm, dk = w.take_navigation()
        sm = sd.correct(signed(sm, q_ref_m[j]), dm)
        sk = sd.correct(signed(sk, q_ref_k[j]), dk)
        if j < J1 - 1:
            w.predict(j)
    return w.result()


@_serial_blas
def run_dual(main: BridgedLog, kimu: BridgedLog, setup: DualSetup, *, heading=None,
             gap_noise=True, feedback=True) -> DualRun:
    """Align, navigate, compare and test the two IMUs.

    Parameters
    ----------
    main, kimu : BridgedLog
        The two logs on their grids, from the start of the alignment
        window (the vehicle at rest); increments of shape (K, 3) or
        (M, K, 3).  The KIMU's samples are assigned to the main intervals by
        :func:`covtool.nav.strapdown.group_samples` (seed 001 Fig 7).
    setup : DualSetup
    heading : array_like, shape (M,), optional
        Per-run input heading (simulated input errors); default
        ``setup.heading``.
    gap_noise : bool
        Add each bridged gap's predicted extra error to the process noise.
    feedback : bool
        Whiten with the estimated navigation errors fed back into both
        solutions at every epoch (:class:`Whitener`); False whitens the
        open-loop difference (exact only while the errors are small enough
        for the linear model).

    Returns
    -------
    DualRun
        ``z`` is always the open-loop difference (what seed 001 Figs 13–15
        compare); the innovations come from the feedback pass.

    Raises
    ------
    InputError
        The logs do not overlap, are too short for the alignment and one
        comparison window, the alignment is not a whole number of main
        samples, or the KIMU does not deliver ``ratio`` samples per main
        interval (named by :func:`~covtool.nav.strapdown.group_samples`).  Each
        message names the log it is about (:attr:`BridgedLog.where`); when
        the logs cannot be paired because their clocks drift apart by more
        than :data:`CLOCK_PPM_TOL`, the one further from its nominal rate is
        named with both measured rates.
    ValueError
        ``compare_every`` not a multiple of ``substep``, or ``substep`` odd.
    """
    r = int(setup.ratio)
    hm = main.dt
    clock = _clocks(main, kimu, r)
    name_m = main.where or "main log"
    name_k = kimu.where or "KIMU log"
    # main intervals (t_k − h, t_k]: keep those the KIMU log covers entirely (h the main log's own period)
    edges = np.concatenate([[main.t[0] - (main.period or hm)], main.t])
    tol = 1e-6 * kimu.dt
    e0 = int(np.searchsorted(edges, kimu.t[0] - kimu.dt - tol, side="left"))
    e1 = int(np.searchsorted(edges, kimu.t[-1] + tol, side="right")) - 1
    if e1 - e0 < 1:
        def label(log, what):
            return f"the {what} log {log.where} " if log.where else f"the {what} log "

        raise InputError("logs", f"{label(main, 'main')}[{edges[0]:.9g}, {edges[-1]:.9g}] s and "
                         f"{label(kimu, 'KIMU')}[{kimu.t[0] - kimu.dt:.9g}, {kimu.t[-1]:.9g}] s share no main interval")
    sel = (kimu.t > edges[e0] + tol) & (kimu.t <= edges[e1] + tol)
    try:
        groups = sd.group_samples(kimu.t[sel], edges[e0:e1 + 1], where="KIMU log")
    except ValueError as exc:
        problem = str(exc).removeprefix("KIMU log: ")
        if abs(clock["mismatch"]) > CLOCK_PPM_TOL:
            # the logs drift apart: blame the one whose clock is further from its nominal rate
            main_worse = abs(clock["main"]) >= abs(clock["kimu"])
            culprit, other = (name_m, name_k) if main_worse else (name_k, name_m)
            ppm_c, ppm_o = (clock["main"], clock["kimu"]) if main_worse else (clock["kimu"], clock["main"])
            raise InputError(culprit, f"its clock runs {ppm_text(ppm_c)} ppm off its nominal rate ({other}: "
                             f"{ppm_text(ppm_o)} ppm), so the logs drift apart by {ppm_text(clock['mismatch'])} ppm "
                             f"and cannot be paired sample by sample ({problem})") from None
        raise InputError(name_k, problem) from None
    if groups.shape[1] != r:
        raise InputError(name_k, f"delivers {groups.shape[1]} samples per main interval, the study declares "
                         f"a rate ratio of {r}")
    k_idx = np.flatnonzero(sel)[groups.ravel()]
    m_th = _runs(main.dtheta)[:, e0:e1]
    m_dv = _runs(main.dv)[:, e0:e1]
    k_th = _runs(kimu.dtheta)[:, k_idx]
    k_dv = _runs(kimu.dv)[:, k_idx]
    Mr = max(m_th.shape[0], k_th.shape[0])
    t_start = float(edges[e0])
    n_align = int(round(setup.align_time / hm))
    if abs(n_align * hm - setup.align_time) > 1e-6 * hm:
        raise InputError("alignment time", f"{setup.align_time:g} s is not a whole number of main samples "
                         f"({hm:g} s)")
    ce, sub = int(setup.compare_every), int(setup.substep)
    if ce % sub or sub % 2:
        raise ValueError("compare_every must be a multiple of substep, and substep even")
    n_nav = ((m_th.shape[1] - n_align) // ce) * ce
    if n_nav < setup.window * ce:
        raise InputError("logs", f"{(m_th.shape[1] - n_align) * hm:.3g} s of data after the {setup.align_time:g} s "
                         f"alignment is shorter than one comparison window ({setup.window * ce * hm:g} s)")
    hk = hm / r
    # each IMU aligns on its own: levelling + the input heading through its declared mounting
    psi = np.broadcast_to(np.asarray(setup.heading if heading is None else heading, float), (Mr,))
    f_m = m_dv[:, :n_align].sum(axis=1) / setup.align_time
    f_k = k_dv[:, :n_align * r].sum(axis=1) / setup.align_time
    q_m0 = triad_alignment(np.broadcast_to(f_m, (Mr, 3)), psi, setup.main_mounting)
    q_k0 = triad_alignment(np.broadcast_to(f_k, (Mr, 3)), psi, setup.kimu_mounting)
    t_nav0 = t_start + n_align * hm

    def state0(q, prev_th, prev_dv):
        M = q.shape[0]
        z3 = np.zeros((M, 3))
        return sd.NavState(t_nav0, np.full(M, setup.lat), np.full(M, setup.lon), np.full(M, setup.h), z3, q,
                           np.broadcast_to(prev_th, (M, 3)).copy(), np.broadcast_to(prev_dv, (M, 3)).copy())

    rec_m = ImuRecord(t_nav0, hm, m_th[:, n_align:n_align + n_nav], m_dv[:, n_align:n_align + n_nav])
    rec_k = ImuRecord(t_nav0, hk, k_th[:, n_align * r:(n_align + n_nav) * r],
                      k_dv[:, n_align * r:(n_align + n_nav) * r])
    half = sub // 2
    hist_m = sd.run(state0(q_m0, m_th[:, n_align - 1], m_dv[:, n_align - 1]), rec_m, 1, every=half)
    hist_k = sd.run(state0(q_k0, k_th[:, n_align * r - 1], k_dv[:, n_align * r - 1]), rec_k, r, every=half)
    ep = np.arange(0, hist_m.t.size, ce // half)
    mid = np.arange(1, hist_m.t.size, 2)
    em, ek = _subsample(hist_m, ep), _subsample(hist_k, ep)
    z = np.swapaxes(nav_difference(em, ek, setup.main_mounting, setup.kimu_mounting), 0, 1)   # (M, J+1, 9)
    # linearisation along run 0: each IMU's own attitude and mean rates over every step
    N = n_nav // sub
    T = sub * hm

    def mean_rates(th, dv, per):
        return (th[0].reshape(N, per, 3).sum(axis=1) / T, dv[0].reshape(N, per, 3).sum(axis=1) / T)

    w_m, f_ms = mean_rates(rec_m.dtheta, rec_m.dv, sub)
    w_k, f_ks = mean_rates(rec_k.dtheta, rec_k.dv, sub * r)
    wk_s = rec_k.dtheta[0].reshape(N, sub * r, 3) / hk
    fk_s = rec_k.dv[0].reshape(N, sub * r, 3) / hk
    products = np.einsum("nsi,nsj->nij", wk_s, fk_s) / (sub * r)
    lat_mid, h_mid, v_mid = hist_m.lat[mid, 0], hist_m.h[mid, 0], hist_m.v_n[mid, 0]
    # one attitude reference for both IMUs (the main solution, carried to the KIMU frame through the
    # declared mountings): references that differ by the open-loop difference itself would put
    # (difference × common error × f) terms into the model
    def to_kimu(q):
        out = q if setup.main_mounting is None else quat.mul(q, quat.conj(np.asarray(setup.main_mounting, float)))
        return out if setup.kimu_mounting is None else quat.mul(out, np.asarray(setup.kimu_mounting, float))

    q_ref_m, q_ref_k = em.q[:, 0], to_kimu(em.q[:, 0])
    ctx_m = Context(lat_mid, h_mid, v_mid, hist_m.q[mid, 0], f_ms, w_m)
    ctx_k = Context(lat_mid, h_mid, v_mid, to_kimu(hist_m.q[mid, 0]), f_ks, w_k)
    rest = []
    for q0, f0, th, per in ((q_m0, f_m, m_th, 1), (q_k0, f_k, k_th, r)):
        w0 = th[0, :n_align * per].sum(axis=0) / setup.align_time
        rest.append(Context([setup.lat], [setup.h], np.zeros((1, 3)), q0[:1], f0[:1], w0[None]))
    lin_m = ImuLinearization(setup.main_model, ctx_m, q_ref_m, rest[0], setup.align_time, float(psi[0]),
                             setup.main_mounting)
    lin_k = ImuLinearization(setup.kimu_model, ctx_k, q_ref_k, rest[1], setup.align_time, float(psi[0]),
                             setup.kimu_mounting)
    extra = []
    if gap_noise:
        for log, name in ((main, "main"), (kimu, "kimu")):
            for g in log.gaps:
                jj = int(np.floor((g.after - t_nav0) / (ce * hm)))
                if g.before <= t_nav0:
                    continue   # bridged inside the alignment window: in the levelling mean only
                extra.append((name, min(max(jj, 0), em.t.size - 2), g.sigma_attitude, g.sigma_velocity))
    model = difference_model(lin_m, lin_k, t_epochs=em.t, lat_epochs=em.lat[:, 0], h_epochs=em.h[:, 0],
                             substeps_per_epoch=ce // sub, dt_sub=T, heading_sigma=setup.heading_sigma,
                             products=products, candidates=setup.candidates, components=setup.components,
                             noise=setup.noise, extra_noise=extra)
    if feedback:
        inn = _closed_loop(model, rec_m, rec_k, state0(q_m0, m_th[:, n_align - 1], m_dv[:, n_align - 1]),
                           state0(q_k0, k_th[:, n_align * r - 1], k_dv[:, n_align * r - 1]), r, ce, setup,
                           q_ref_m, q_ref_k)
    else:
        inn = innovations(model, z[..., list(setup.components)])
    stat, thr, flagged = window_test(inn.nis, model.m, setup.window, setup.false_alarm)
    intervals = [flagged_intervals(f, em.t, setup.window) for f in flagged]
    gs = gsens_estimates(inn, setup.candidates, setup.false_alarm, strict=False)
    env = np.sqrt(np.diagonal(model.open_loop(), axis1=1, axis2=2))
    used_k = k_idx[:(n_align + n_nav) * r]
    unused = {"main": (e0, main.t.size - (e0 + n_align + n_nav)),
              "kimu": (int(used_k[0]), kimu.t.size - int(used_k[-1]) - 1)}
    return DualRun(em.t, z, model, env, inn, stat, thr, flagged, intervals, gs, em, ek, unused, clock)


def ppm_text(x: float) -> str:
    """Clock offset as signed text, 0.1 ppm resolution.

    ``+200.0``; a value that rounds to zero is ``+0.0``, never ``-0.0``.
    """
    return f"{round(float(x), 1) + 0.0:+.1f}"


def _clocks(main: BridgedLog, kimu: BridgedLog, ratio: int) -> dict:
    """Each log's clock offset from its nominal rate, and their mismatch. [ppm]"""
    p_m = main.period if main.period is not None else clock_rate(main.t, main.dt)[0]
    p_k = kimu.period if kimu.period is not None else clock_rate(kimu.t, kimu.dt)[0]
    return {"main": (p_m / main.dt - 1.0) * 1e6, "kimu": (p_k / kimu.dt - 1.0) * 1e6,
            "mismatch": (p_m / (ratio * p_k) - 1.0) * 1e6}
