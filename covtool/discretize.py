"""Discretisation of ``ẋ = F x + G w``: exact Van Loan and seed 002's Taylor series.

Both functions take stacks of matrices (leading time axis) and return
``Φ`` and ``Q_d`` for every step at once.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm


def van_loan(F: np.ndarray, Qc: np.ndarray, dt) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretisation by the Van Loan matrix exponential.

    Parameters
    ----------
    F : ndarray, shape (N, n, n)
        Continuous dynamics matrix, constant over each step.
    Qc : ndarray, shape (N, n, n)
        Continuous noise PSD ``G W Gᵀ``.
    dt : float or ndarray, shape (N,)
        Step lengths. [s]

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)

    Notes
    -----
    Van Loan (1978): with ``M = [[−F, Qc], [0, Fᵀ]] Δt`` and
    ``expm(M) = [[·, Φ⁻¹Q_d], [0, Φᵀ]]``, ``Φ = (lower-right)ᵀ`` and
    ``Q_d = Φ (upper-right)``.  ``Q_d = ∫₀^Δt e^{Fs} Qc e^{Fᵀs} ds``.
    """
    F = np.asarray(F, float)
    N, n, _ = F.shape
    dt = np.broadcast_to(np.asarray(dt, float), (N,))
    M = np.zeros((N, 2 * n, 2 * n))
    M[:, :n, :n] = -F
    M[:, :n, n:] = Qc
    M[:, n:, n:] = np.swapaxes(F, 1, 2)
    E = expm(M * dt[:, None, None])
    Phi = np.swapaxes(E[:, n:, n:], 1, 2)
    Qd = Phi @ E[:, :n, n:]
    return Phi, 0.5 * (Qd + np.swapaxes(Qd, 1, 2))


def taylor_terms_needed(F: np.ndarray, dt, tol: float = 1e-14, max_terms: int = 30) -> int:
    """Smallest Taylor order whose next term is below ``tol`` (norm bound)."""
    a = float(np.max(np.abs(np.asarray(dt))) * np.max(np.linalg.norm(F, ord=1, axis=(1, 2))))
    term = 1.0
    for k in range(1, max_terms + 1):
        term *= a / k
        if term < tol:
            return k + 1
    return max_terms


def taylor(F: np.ndarray, Qc: np.ndarray, dt, order: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Seed 002's Taylor-series discretisation, eq (6b)–(6d).

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)
    dt : float or ndarray, shape (N,)
    order : int, optional
        Number of terms ``n`` of eq (6b) (``i = 0 … n−1``).  Default: add
        terms until the next term of both series is below 1e-16 (relative),
        at most 40.

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)

    Notes
    -----
    With the scan's Π read as Σ (see BRIEF)::

        Φ   = Σ_{i=0}^{n−1} F^i Δt^i / i!                      (6b)
        Q_d = Σ_{i=1}^{n−1} C_{i−1} Δt^i / i!                  (6c)
        C_0 = Qc,  C_i = F C_{i−1} + (F C_{i−1})ᵀ              (6d)

    ``C_{i−1}`` is the ``(i−1)``-th derivative of ``e^{Fs} Qc e^{Fᵀs}`` at
    ``s = 0``, so (6c) is the Taylor series of the Van Loan integral.
    """
    F = np.asarray(F, float)
    N, n, _ = F.shape
    dt = np.broadcast_to(np.asarray(dt, float), (N,))[:, None, None]
    adaptive = order is None
    max_order = 40 if adaptive else order
    Phi = np.broadcast_to(np.eye(n), F.shape).copy()
    term = Phi.copy()
    C = np.asarray(Qc, float).copy()
    Qd = np.zeros_like(F)
    qscale = np.max(np.abs(C)) or 1.0
    coef = dt.copy()                                   # Δt^i / i!
    for i in range(1, max_order):
        term = term @ F * (dt / i)
        Phi += term
        Qd += C * coef
        FC = F @ C
        C = FC + np.swapaxes(FC, 1, 2)
        coef = coef * dt / (i + 1)
        if adaptive and np.max(np.abs(term)) < 1e-16 and np.max(np.abs(C * coef)) < 1e-16 * qscale:
            break
    return Phi, Qd


DISCRETISATIONS = {"van_loan": van_loan, "taylor": taylor}


def discretize(F, Qc, dt, method: str = "van_loan", order: int | None = None):
    """Dispatch to :func:`van_loan` or :func:`taylor`."""
    if method == "van_loan":
        return van_loan(F, Qc, dt)
    if method == "taylor":
        return taylor(F, Qc, dt, order)
    raise ValueError(f"unknown discretisation {method!r} (one of: van_loan, taylor)")
