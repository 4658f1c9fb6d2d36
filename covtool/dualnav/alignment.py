"""Alignment of each IMU on its own (seed 001 §2.3.2): TRIAD levelling and the input heading.

Levelling from the IMU's accelerometers, heading from the input heading
through the declared mounting (:func:`triad_alignment`), its Jacobian with
respect to the inputs (:func:`alignment_jacobian`) and the second-order
mean and covariance of the alignment error (:func:`alignment_second_order`).
"""

from __future__ import annotations

import numpy as np

from covtool.lincov.kalman import symmetrize
from covtool.nav import attitude as quat

__all__ = [
    "triad_alignment", "alignment_jacobian", "alignment_second_order",
]


# --------------------------------------------------------------------------
# alignment
# --------------------------------------------------------------------------


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
    return quat.from_dcm(C)


def small_angle(q_hat, q):
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
            args.append(small_angle(triad_alignment(ff, pp, mounting)[0], q0))
        A[:, k] = (args[0] - args[1]) / (2.0 * h)
    return A


# --------------------------------------------------------------------------
# linear model of the difference
# --------------------------------------------------------------------------


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
    w, V = np.linalg.eigh(symmetrize(np.asarray(cov_u, float)))
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
    phi = small_angle(triad_alignment(f + U[:, :3], heading + U[:, 3], mounting), q0)
    phi = phi.reshape(4, 4, 4, 3)
    G = (phi[:, :, 0] - phi[:, :, 1] - phi[:, :, 2] + phi[:, :, 3]) / (4.0 * h * h)   # (a, b, i)
    G = np.moveaxis(G, -1, 0)                                                    # (i, a, b)
    mean = 0.5 * np.trace(G, axis1=1, axis2=2)
    cov = 0.5 * np.einsum("iab,jba->ij", G, G)
    return mean, symmetrize(cov)
