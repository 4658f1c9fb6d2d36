"""Front ends: Van Loan, seed 002's Taylor series, :func:`discretize`.

:func:`van_loan` and the adaptive :func:`taylor` (seed 002, eq (6b)–(6d))
are exact for any step; ``taylor(order=N_t)`` is the paper's fixed-order
series; :func:`taylor_terms` reports the terms used; :func:`discretize`
dispatches by name.
"""
from __future__ import annotations

import numpy as np

from covtool.errors import InputError
from covtool.lincov.discretize.series import (MAX_ORDER, _balanced, _series, _unbalance, balancing,
                                             random_constants)
from covtool.lincov.discretize.steps import StepInfo, _check_result, _dedup, _expand_phi_qd, _prepare
from covtool.lincov.discretize.structured import _exact
from covtool.lincov.stacks import gather


# ---------------------------------------------------------------------------
# public


def van_loan(F: np.ndarray, Qc: np.ndarray, dt, *, what: str = "", times=None, info: bool = False):
    """Exact discretisation: Van Loan's ``Φ`` and ``Q_d`` for any step.

    Parameters
    ----------
    F : ndarray, shape (N, n, n)
        Continuous dynamics matrix, constant over each step.
    Qc : ndarray, shape (N, n, n)
        Continuous noise PSD ``G W Gᵀ``.
    dt : float or ndarray, shape (N,)
        Step lengths. [s]
    what : str
        Names the computation in error messages.
    times : ndarray, shape (N,), optional
        Start time of each step, for error messages. [s]
    info : bool
        Also return a :class:`StepInfo`.

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)
    info : StepInfo
        Only with ``info=True``.

    Raises
    ------
    NumericalError
        Non-finite input, or ``Φ``/``Q_d`` not representable (overflow of an
        unstable mode), naming the step.

    Notes
    -----
    ``Φ = e^{FΔt}`` and ``Q_d = ∫₀^Δt e^{Fs} Q_c e^{Fᵀs} ds`` (Van Loan 1978),
    computed by balancing, scaling, the converged series and squaring
    (module notes); the same numbers as ``taylor(order=None)``.
    """
    exact = _exact_info if info else _exact_constants
    Phi, Qd, inf = _dedup(lambda F_, Q_, dt_, t_: exact(F_, Q_, dt_, what, t_), F, [(Qc, 2)], dt, times,
                          _expand_phi_qd)
    return (Phi, Qd, inf) if info else (Phi, Qd)


def taylor(F: np.ndarray, Qc: np.ndarray, dt, order: int | None = None, *, what: str = "", times=None,
           info: bool = False):
    """Seed 002's Taylor-series discretisation, eq (6b)–(6d).

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)
    dt : float or ndarray, shape (N,)
        Step lengths. [s]
    order : int, optional
        Number of terms ``N_t`` of eq (6b) (``i = 0 … N_t−1``), the paper's
        truncation over the whole step.  Default: the adaptive series, exact
        for any step (module notes).
    what : str
        Names the filter or system in error messages.
    times : ndarray, shape (N,), optional
        Start time of each step, for error messages. [s]
    info : bool
        Also return a :class:`StepInfo` (the terms used per step).

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)
    info : StepInfo
        Only with ``info=True``.

    Raises
    ------
    InputError
        A fixed ``order`` whose series diverges at some step
        (``2νΔt ≥ N_t``, module notes), naming the step, ``νΔt`` and what to
        change; an ``order`` that is not an integer in ``1 … 100``.
    NumericalError
        Non-finite input or result, naming the step.

    Notes
    -----
    With the scan's Π read as Σ (see BRIEF)::

        Φ   = Σ_{i=0}^{n−1} F^i Δt^i / i!                      (6b)
        Q_d = Σ_{i=1}^{n−1} C_{i−1} Δt^i / i!                  (6c)
        C_0 = Qc,  C_i = F C_{i−1} + (F C_{i−1})ᵀ              (6d)

    ``C_{i−1}`` is the ``(i−1)``-th derivative of ``e^{Fs} Qc e^{Fᵀs}`` at
    ``s = 0``, so (6c) is the Taylor series of the Van Loan integral.  The
    adaptive series sums them at ``h = Δt/2^s`` until the tail bound is
    below ``2⁻⁵³`` and doubles ``s`` times.
    """
    if order is None:
        exact = _exact_info if info else _exact_constants
        Phi, Qd, inf = _dedup(lambda F_, Q_, dt_, t_: exact(F_, Q_, dt_, what, t_), F, [(Qc, 2)], dt, times,
                              _expand_phi_qd)
        return (Phi, Qd, inf) if info else (Phi, Qd)
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or not 1 <= order <= MAX_ORDER:
        raise InputError(f"{what + ': ' if what else ''}taylor_order",
                         f"{order!r} is not an integer from 1 to {MAX_ORDER}")
    Phi, Qd, inf = _dedup(lambda F_, Q_, dt_, t_: _taylor_fixed(F_, Q_, dt_, order, what, t_), F, [(Qc, 2)], dt,
                          times, _expand_phi_qd)
    return (Phi, Qd, inf) if info else (Phi, Qd)


def _exact_constants(F, Qc, dt, what, times):
    """:func:`_exact` with the random constants folded out (exact).

    A random constant ``c`` (zero ``F`` row, no noise) keeps ``Φ_cc = 1``
    and no ``Q_d``; the others, ``d``, see it through ``F_dc``, constant over
    the step, so ``Φ_dc = ∫₀^Δt e^{F_dd s} ds · F_dc = Γ F_dc``.  ``Γ`` is
    needed only on the rows ``u`` some constant drives (for an INS model
    the velocity and quaternion rows), and it is the ``Φ`` block of ``u``
    unit constants: the system ``[[F_dd, E_u], [0, 0]]`` (``E_u`` the unit
    columns of the rows ``u``).  So ``Φ`` and ``Q_d`` are those of a system
    of ``n_d + |u|`` states instead of ``n`` (29 instead of 58 for the
    58-state truth, whose 36 constants drive 7 rows), the same converged
    series of seed 002 eq (6b)–(6d), and ``Φ_dc = Φ_du F_uc``.
    """
    F = np.asarray(F, float)
    try:
        fits = F.ndim == 3 and F.shape[1] == F.shape[2] and np.broadcast_shapes(np.shape(Qc), F.shape) == F.shape
    except ValueError:
        fits = False
    if not fits:
        return _exact(F, Qc, dt, what, times)               # its checks name the problem
    Qc = np.broadcast_to(np.asarray(Qc, float), F.shape)
    rc = random_constants(F, Qc)
    dyn = np.flatnonzero(~rc)
    cst = np.flatnonzero(rc)
    N, n, _ = F.shape
    if cst.size == 0 or dyn.size == 0 or not (np.isfinite(F).all() and np.isfinite(Qc).all()):
        return _exact(F, Qc, dt, what, times)               # nothing to fold (or the checks name a bad step)
    Fdc = gather(F, dyn, cst)                               # (N, n_d, n_c)
    used = np.flatnonzero((Fdc != 0).any(axis=(0, 2)))      # the rows the constants drive
    if used.size >= cst.size:
        return _exact(F, Qc, dt, what, times)
    nd, nu = dyn.size, used.size
    Fr = np.zeros((N, nd + nu, nd + nu))
    Fr[:, :nd, :nd] = gather(F, dyn)
    Fr[:, used, nd + np.arange(nu)] = 1.0
    Qr = np.zeros_like(Fr)
    Qr[:, :nd, :nd] = gather(Qc, dyn)
    Pr, Qdr, inf = _exact(Fr, Qr, dt, what, times)
    Phi = np.zeros((N, n, n))
    Qd = np.zeros((N, n, n))
    Phi[:, dyn[:, None], dyn[None, :]] = Pr[:, :nd, :nd]
    Phi[:, dyn[:, None], cst[None, :]] = Pr[:, :nd, nd:] @ gather(Fdc, used, np.arange(cst.size))
    Phi[:, cst, cst] = 1.0
    Qd[:, dyn[:, None], dyn[None, :]] = Qdr[:, :nd, :nd]
    return Phi, Qd, inf


def _exact_info(F, Qc, dt, what, times):
    """:func:`_exact_constants`' ``Φ``, ``Q_d`` with the whole system's :class:`StepInfo`.

    The terms and squarings are those the series of the whole system takes
    (what an on-board filter computing it would do,
    :func:`taylor_terms`), not those of the folded one.
    """
    Phi, Qd, _ = _exact_constants(F, Qc, dt, what, times)
    return Phi, Qd, _exact(F, Qc, dt, what, times)[2]


def _taylor_fixed(F, Qc, dt, order, what, times):
    F, Qc, dt, times = _prepare(F, Qc, dt, what, times)
    d = balancing(F)
    B, Qb, nu = _balanced(F, Qc, d)
    a = nu * dt
    bad = 2.0 * a >= order
    if bad.any():
        k = int(np.argmax(bad))
        t = f"t = {times[k]:.6g} s, " if times is not None else ""
        raise InputError(
            f"{what + ': ' if what else ''}taylor_order",
            f"the {order}-term Taylor series of eq (6b)-(6d) diverges at step {k} ({t}Δt = {dt[k]:.6g} s): "
            f"νΔt = {a[k]:.4g} ≥ N_t/2 = {order / 2:g} (ν: balanced ‖F‖, the fastest rate of the dynamics, "
            f"{nu[k]:.4g} 1/s), its terms grow instead of shrinking; use dt < {0.5 * order / nu.max():.4g} s, "
            f"taylor_order ≥ {int(np.floor(2.0 * a.max())) + 1}, or the exact discretisation "
            "(no taylor_order, or 'van_loan')")
    Phi, Qd, terms, _ = _series(B, Qb, dt, nu, order)
    Phi, Qd = _unbalance(Phi, Qd, d)
    inf = StepInfo(terms, np.zeros(F.shape[0], int), a)
    _check_result(Phi, Qd, dt, inf, what, times, psd=False)
    return Phi, Qd, inf


def taylor_terms(F: np.ndarray, Qc: np.ndarray, dt) -> StepInfo:
    """Terms and squarings the adaptive eq (6b)–(6d) series takes per step.

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)
    dt : float or ndarray, shape (N,)
        Step lengths. [s]

    Returns
    -------
    StepInfo
    """
    return _dedup(lambda F_, Q_, dt_, t_: _exact(F_, Q_, dt_, "", t_), F, [(Qc, 2)], dt, None,
                  _expand_phi_qd)[2]


def discretize(F, Qc, dt, method: str = "van_loan", order: int | None = None, *, what: str = "", times=None):
    """Dispatch to :func:`van_loan` or :func:`taylor`.

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)
    dt : float or ndarray, shape (N,)
        Step lengths. [s]
    method : {"van_loan", "taylor"}
    order : int, optional
        Fixed number of Taylor terms (``method = "taylor"`` only).
    what : str
        Names the system in error messages.
    times : ndarray, shape (N,), optional
        Start time of each step, for error messages. [s]

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)

    Raises
    ------
    ValueError
        Unknown method.
    """
    if method == "van_loan":
        return van_loan(F, Qc, dt, what=what, times=times)
    if method == "taylor":
        return taylor(F, Qc, dt, order, what=what, times=times)
    raise ValueError(f"unknown discretisation {method!r} (one of: van_loan, taylor)")
