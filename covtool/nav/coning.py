"""Coning and sculling: the body increments of the strapdown algorithm.

The n-sample + 1-previous coning and sculling compensation of seed 001
(eq (1)–(4), Figs 9–10) and the position-weighted specific-force increment,
vectorised over an ensemble (leading run axis ``M``).  The algorithm
that uses them is in :mod:`covtool.nav.strapdown`.

*Body increments* (seed 001 eq (1)–(4); Savage 1998 Parts 1–2;
Ignagni 1996)::

    α = Σ Δθ_i,   υ = Σ Δv_i
    φ = α + Σ_{i=0}^{n−1} k_{n−i} (Δθ_i × Δθ_n)                      (coning)
    Δv_b = υ + c1 α×υ + c2 α×(α×υ)                        (rotation, exact for
           + Σ_{i=0}^{n−1} k_{n−i} (Δθ_i × Δv_n + Δv_i × Δθ_n)   constant rates)
                                                                     (sculling)

with ``c1 = (1−cos a)/a² ≈ ½``, ``c2 = (a − sin a)/a³ ≈ ⅙``, ``a = |α|``.
The lag coefficients ``k_L`` (``L = n − i`` samples apart) are those of
:func:`coning_coefficients`; for ``n = 4`` they are seed 001's
``(656, 262, 168, −1)/315``.  The sculling terms use the same coefficients
(Roscoe 2001, the coning/sculling equivalency, seed 001 ref [7]).
"""

from __future__ import annotations

from fractions import Fraction
from functools import lru_cache

import numpy as np

__all__ = [
    "coning_coefficients", "coning_residual", "body_increments", "body_position_increment",
]


#: largest number of samples per interval with derived coefficients
MAX_SAMPLES = 6


# --------------------------------------------------------------------------
# coning / sculling coefficients
# --------------------------------------------------------------------------


@lru_cache(maxsize=None)
def coning_coefficients(n: int) -> tuple[Fraction, ...]:
    """Coefficients of the n-sample + 1-previous coning algorithm.

    Parameters
    ----------
    n : int
        Samples per navigation interval (1 … :data:`MAX_SAMPLES`).

    Returns
    -------
    tuple of Fraction, length n
        ``k_1 … k_n``: the weight of ``Δθ_i × Δθ_n`` for samples ``L = n − i``
        apart (``i = 0`` is the previous interval's last sample).  ``n = 1``:
        ``(1/12,)``; ``n = 4``: ``(656, 262, 168, −1)/315``, seed 001 eq (2).

    Notes
    -----
    Under classical coning (rates ``aΩ cos Ωt``, ``bΩ sin Ωt`` on two axes)
    the cross product of two sample increments ``L`` samples apart is, along
    the cone axis, ``ab·2(1 − cos λ) sin Lλ`` with ``λ = Ωh`` (Ignagni 1996);
    the exact coning term ``½∫α×ω dt`` over ``T = nh`` is
    ``ab·½(nλ − sin nλ)``.  Expanding both in odd powers of λ,
    ``2(1 − cos λ) sin Lλ = Σ_j (−1)^j λ^{2j+1}/(2j+1)! [2L^{2j+1} −
    (L+1)^{2j+1} − (L−1)^{2j+1}]``, and matching the powers ``λ³ … λ^{2n+1}``
    gives n linear equations for ``k_1 … k_n``; they are solved exactly in
    rational arithmetic.  The residual error is then ``O(λ^{2n+3})`` per
    interval (:func:`coning_residual`).
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"samples per interval must be an integer in 1..{MAX_SAMPLES}, got {n!r}")
    n = int(n)
    rows = []
    for j in range(1, n + 1):
        p = 2 * j + 1
        row = [Fraction(2 * L**p - (L + 1) ** p - (L - 1) ** p) for L in range(1, n + 1)]
        rows.append(row + [Fraction(-(n**p), 2)])
    # Gauss-Jordan elimination in exact arithmetic
    for c in range(n):
        piv = next(r for r in range(c, n) if rows[r][c] != 0)
        rows[c], rows[piv] = rows[piv], rows[c]
        for r in range(n):
            if r != c and rows[r][c] != 0:
                f = rows[r][c] / rows[c][c]
                rows[r] = [x - f * y for x, y in zip(rows[r], rows[c])]
    return tuple(rows[c][n] / rows[c][c] for c in range(n))


def coning_residual(n: int, lam, *, compensated: bool = True):
    """Residual coning error per interval under classical coning.

    Parameters
    ----------
    n : int
        Samples per interval.
    lam : float or ndarray
        ``λ = Ω h``: coning frequency times the sample period. [rad]
    compensated : bool
        False gives the error of ``φ = α`` (no coning term).

    Returns
    -------
    float or ndarray
        ``ε(λ) = ½(nλ − sin nλ) − 2(1 − cos λ) Σ_L k_L sin Lλ``: the exact
        coning term minus the algorithm's, per unit ``ab`` (``sin²β`` for a
        cone of half-angle β).  The algorithm's attitude error along the cone
        axis grows at ``−ab ε(λ)/T``.  The same function, times ``θ₀A/Ω``,
        is the sculling residual under in-phase angular (θ₀) and linear (A)
        oscillation (Roscoe 2001).
    """
    lam = np.asarray(lam, dtype=float)
    exact = 0.5 * (n * lam - np.sin(n * lam))
    if not compensated:
        return exact
    k = [float(c) for c in coning_coefficients(n)]
    alg = 2.0 * (1.0 - np.cos(lam)) * sum(kL * np.sin((L + 1) * lam) for L, kL in enumerate(k))
    return exact - alg


@lru_cache(maxsize=None)
def _weights(n: int) -> np.ndarray:
    """Weights of samples ``0 … n−1`` (0 = previous) against sample n."""
    k = coning_coefficients(n)
    return np.array([float(k[n - 1 - i]) for i in range(n)])


# --------------------------------------------------------------------------
# the algorithm
# --------------------------------------------------------------------------


def _cross(a, b):
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def body_increments(dtheta, dv, dtheta_prev, dv_prev):
    """Compensated rotation vector and body velocity increment.

    Parameters
    ----------
    dtheta, dv : ndarray, shape (M, n, 3)
        The n IMU samples of the interval. [rad], [m/s]
    dtheta_prev, dv_prev : ndarray, shape (M, 3)
        The previous interval's last sample.

    Returns
    -------
    phi : ndarray, shape (M, 3)
        Rotation vector of the body frame over the interval (seed 001
        eq (1)–(2)). [rad]
    dv_b : ndarray, shape (M, 3)
        Specific-force velocity increment in the body frame at the start of
        the interval, with rotation and sculling compensation (seed 001
        eq (3)–(4)). [m/s]

    Notes
    -----
    ``Σ_i k_{n−i} (a_i × b_n) = (Σ_i k_{n−i} a_i) × b_n``, so each term of
    eq (2) and (4) costs one weighted sum and one cross product.
    """
    n = dtheta.shape[-2]
    w = _weights(n)
    last_th = dtheta[..., -1, :]
    last_dv = dv[..., -1, :]
    A = w[0] * dtheta_prev
    B = w[0] * dv_prev
    if n > 1:
        A = A + np.einsum("i,...ik->...k", w[1:], dtheta[..., :-1, :])
        B = B + np.einsum("i,...ik->...k", w[1:], dv[..., :-1, :])
    alpha = dtheta.sum(axis=-2)
    ups = dv.sum(axis=-2)
    phi = alpha + _cross(A, last_th)
    a2 = np.einsum("...k,...k->...", alpha, alpha)
    small = a2 < 1e-6
    a = np.sqrt(a2)
    safe = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5 - a2 / 24.0 + a2 * a2 / 720.0, (1.0 - np.cos(a)) / safe**2)
    c2 = np.where(small, 1.0 / 6.0 - a2 / 120.0 + a2 * a2 / 5040.0, (a - np.sin(a)) / safe**3)
    axu = _cross(alpha, ups)
    dv_b = (ups + c1[..., None] * axu + c2[..., None] * _cross(alpha, axu)
            + _cross(A, last_dv) + _cross(B, last_th))
    return phi, dv_b


def body_position_increment(dtheta, dv):
    """Specific-force term of the position update, body frame.

    Parameters
    ----------
    dtheta, dv : ndarray, shape (..., n, 3)
        The n IMU samples of the interval. [rad], [m/s]

    Returns
    -------
    ndarray, shape (..., 3)
        ``r`` with ``∫_0^T (T − τ) C_{b(τ)}^{b(0)} f dτ ≈ T r``. [m/s]

    Notes
    -----
    Each sample's increment is weighted at its mid-time,
    ``Σ_i (n − i + ½)/n Δv_i``, and the body rotation adds ``α × υ / 6``
    (exact for constant rates; Savage 1998 Part 2, the scrolling term in
    its simplest form).  Against the trapezoid ``½T(v_{m−1} + v_m)`` this
    divides the position error of a jerk by n² (16 for seed 001's n = 4).
    """
    n = dtheta.shape[-2]
    w = (n - np.arange(n) - 0.5) / n
    alpha = dtheta.sum(axis=-2)
    ups = dv.sum(axis=-2)
    return np.einsum("i,...ik->...k", w, dv) + _cross(alpha, ups) / 6.0
