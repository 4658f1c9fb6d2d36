"""Quaternions and the 4x4/4x3 product matrices of seed 002, eq (2).

Convention: ``q = [q0, q1, q2, q3]`` with scalar first, Hamilton product, and
``q`` the attitude of the body frame with respect to the navigation frame, so
that ``C_b^n = dcm(q)`` maps body vectors to NED.  Kinematics (seed 002,
eq (1) unperturbed)::

    q̇ = ½ [ω_ib^b] q − ½ [ω_in^n] q  =  ½ q ⊗ ω_ib^b − ½ ω_in^n ⊗ q

All functions broadcast over leading axes.
"""

from __future__ import annotations

import numpy as np


def _arr(x):
    """Array of float or complex (complex-step differentiation passes through)."""
    a = np.asarray(x)
    return a if np.iscomplexobj(a) else a.astype(float)


def mul(p, q):
    """Hamilton product ``p ⊗ q``, shape ``(..., 4)``."""
    p, q = _arr(p), _arr(q)
    p0, p1, p2, p3 = np.moveaxis(p, -1, 0)
    q0, q1, q2, q3 = np.moveaxis(q, -1, 0)
    return np.stack([
        p0 * q0 - p1 * q1 - p2 * q2 - p3 * q3,
        p0 * q1 + p1 * q0 + p2 * q3 - p3 * q2,
        p0 * q2 - p1 * q3 + p2 * q0 + p3 * q1,
        p0 * q3 + p1 * q2 - p2 * q1 + p3 * q0,
    ], axis=-1)


def conj(q):
    """Quaternion conjugate."""
    q = _arr(q)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def normalize(q):
    """Unit quaternion with non-negative scalar part."""
    q = _arr(q)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def dcm(q):
    """Direction cosine matrix ``C_b^n`` of a unit quaternion, shape ``(..., 3, 3)``.

    The quaternion is normalised first: seed 002 assumes the attitude
    algorithm normalises, so the quaternion's scale error does not enter (§2.1).
    """
    q = _arr(q)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q0, q1, q2, q3 = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3, 2 * (q1 * q2 - q0 * q3), 2 * (q1 * q3 + q0 * q2)], -1),
        np.stack([2 * (q1 * q2 + q0 * q3), q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3, 2 * (q2 * q3 - q0 * q1)], -1),
        np.stack([2 * (q1 * q3 - q0 * q2), 2 * (q2 * q3 + q0 * q1), q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3], -1),
    ], -2)


def from_euler(roll, pitch, yaw):
    """Quaternion of the 3-2-1 (yaw, pitch, roll) Euler angles [rad]."""
    cr, sr = np.cos(np.asarray(roll) / 2), np.sin(np.asarray(roll) / 2)
    cp, sp = np.cos(np.asarray(pitch) / 2), np.sin(np.asarray(pitch) / 2)
    cy, sy = np.cos(np.asarray(yaw) / 2), np.sin(np.asarray(yaw) / 2)
    return np.stack([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ], axis=-1)


def to_euler(q):
    """3-2-1 Euler angles (roll, pitch, yaw) [rad] of ``q``, shape ``(..., 3)``."""
    c = dcm(q)
    roll = np.arctan2(c[..., 2, 1], c[..., 2, 2])
    pitch = -np.arcsin(np.clip(c[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(c[..., 1, 0], c[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def from_dcm(C):
    """Unit quaternion (scalar first) of DCMs ``C_b^n``, shape (..., 4) (Shepperd's method)."""
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
    return normalize(q)


def from_rotvec(phi):
    """Quaternion of a rotation vector [rad], shape ``(..., 4)``."""
    phi = _arr(phi)
    ang = np.linalg.norm(phi, axis=-1, keepdims=True)
    half = 0.5 * ang
    # sin(x)/x with a series near zero
    small = ang < 1e-8
    k = np.where(small, 0.5 - ang**2 / 48.0, np.sin(half) / np.where(small, 1.0, ang))
    return np.concatenate([np.cos(half), k * phi], axis=-1)


def to_rotvec(q):
    """Rotation vector [rad] of a unit quaternion, shape ``(..., 3)``."""
    q = normalize(q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    ang = 2.0 * np.arctan2(s, q[..., :1])
    k = np.where(s < 1e-12, 2.0, ang / np.where(s < 1e-12, 1.0, s))
    return k * v


def omega_body(w):
    """Right-product matrix ``[ω_ib^b]`` of seed 002, eq (2): ``[ω] q = q ⊗ (0, ω)``."""
    w = _arr(w)
    x, y, z = np.moveaxis(w, -1, 0)
    o = np.zeros_like(x)
    return np.stack([
        np.stack([o, -x, -y, -z], -1),
        np.stack([x, o, z, -y], -1),
        np.stack([y, -z, o, x], -1),
        np.stack([z, y, -x, o], -1),
    ], -2)


def omega_nav(w):
    """Left-product matrix ``[ω_in^n]`` of seed 002, eq (2): ``[ω] q = (0, ω) ⊗ q``."""
    w = _arr(w)
    n, e, d = np.moveaxis(w, -1, 0)
    o = np.zeros_like(n)
    return np.stack([
        np.stack([o, -n, -e, -d], -1),
        np.stack([n, o, -d, e], -1),
        np.stack([e, d, o, -n], -1),
        np.stack([d, -e, n, o], -1),
    ], -2)


def Q_matrix(q):
    """``Q(q)`` of seed 002, eq (2): ``q ⊗ (0, v) = Q(q) v``, shape ``(..., 4, 3)``."""
    q = _arr(q)
    q0, q1, q2, q3 = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([-q1, -q2, -q3], -1),
        np.stack([q0, -q3, q2], -1),
        np.stack([q3, q0, -q1], -1),
        np.stack([-q2, q1, q0], -1),
    ], -2)


def R_matrix(q):
    """``R(q)`` of seed 002, eq (2): ``(0, v) ⊗ q = R(q) v``, shape ``(..., 4, 3)``."""
    q = _arr(q)
    q0, q1, q2, q3 = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([-q1, -q2, -q3], -1),
        np.stack([q0, q3, -q2], -1),
        np.stack([-q3, q0, q1], -1),
        np.stack([q2, -q1, q0], -1),
    ], -2)


def dcm_times_vector_jacobian(q, f):
    """Jacobian of ``dcm(q) f`` with respect to the (unnormalised) quaternion.

    The DCM is computed from the *normalised* quaternion, so the Jacobian has
    no component along ``q`` (the quaternion-scale error of seed 002 §2.1 is
    ignored because the attitude algorithm normalises).

    Parameters
    ----------
    q : ndarray, shape (..., 4)
        Unit quaternion.
    f : ndarray, shape (..., 3)
        Body-frame vector.

    Returns
    -------
    ndarray, shape (..., 3, 4)
        ``∂(C(q/|q|) f)/∂q`` evaluated at unit ``q``.

    Notes
    -----
    With ``C(q) f = (q0²−|v|²) f + 2 (v·f) v + 2 q0 (v × f)``::

        ∂/∂q0 = 2 q0 f + 2 v × f
        ∂/∂v  = 2 (v·f) I + 2 v fᵀ − 2 f vᵀ − 2 q0 [f×]

    and the normalisation adds the projection ``(I − q qᵀ)``.
    """
    q = _arr(q)
    f = _arr(f)
    q0 = q[..., 0]
    v = q[..., 1:]
    d0 = 2.0 * q0[..., None] * f + 2.0 * np.cross(v, f)
    vf = np.sum(v * f, axis=-1)
    eye = np.eye(3)
    fx = skew(f)
    dv = (2.0 * vf[..., None, None] * eye + 2.0 * v[..., :, None] * f[..., None, :]
          - 2.0 * f[..., :, None] * v[..., None, :] - 2.0 * q0[..., None, None] * fx)
    J = np.concatenate([d0[..., :, None], dv], axis=-1)
    proj = np.eye(4) - q[..., :, None] * q[..., None, :]
    return J @ proj


def skew(v):
    """Cross-product matrix ``[v×]``, shape ``(..., 3, 3)``."""
    v = _arr(v)
    x, y, z = np.moveaxis(v, -1, 0)
    o = np.zeros_like(x)
    return np.stack([
        np.stack([o, -z, y], -1),
        np.stack([z, o, -x], -1),
        np.stack([-y, x, o], -1),
    ], -2)


def attitude_error_matrix(q):
    """Map from additive quaternion error δq to the NED attitude error φ.

    Returns ``M`` with ``φ = M δq``, shape ``(..., 3, 4)``; ``M = −2 R(q)ᵀ``.

    Notes
    -----
    The computed attitude is ``q̂ = q + δq`` and the DCM error is
    ``Ĉ_b^n = (I − [φ×]) C_b^n`` (φ: north tilt, east tilt, azimuth error,
    Britting's φ-angle).  Then ``q̂ ⊗ q* = (1, −φ/2)``, i.e.
    ``δq = −½ R(q) φ`` and, because ``R(q)ᵀ R(q) = I₃`` and ``R(q)ᵀ q = 0``,
    ``φ = −2 R(q)ᵀ δq``.  The component of δq along q (the norm error) does
    not map to any attitude error.
    """
    return -2.0 * np.swapaxes(R_matrix(q), -1, -2)
