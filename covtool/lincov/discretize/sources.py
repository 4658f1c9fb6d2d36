"""Per-source ``Q_d``: the exact integral of each noise source.

:func:`per_source` returns ``Q_d`` of each column of a low-rank
``Q_c = G diag(psd) Gᵀ`` (Van Loan's integral, seed 002, eq (6c)–(6d)),
for the error budget and the equivalent white noise (seed 002,
eq (11)–(13)), exact for any step.
"""
from __future__ import annotations

import numpy as np

from covtool.errors import NumericalError
from covtool.lincov.discretize.series import (
    MAX_TERMS, UNIT_ROUNDOFF, _balanced, _not_converged, _series, balancing, reach, scaling)
from covtool.lincov.discretize.steps import _dedup, _prepare, _step_where, check_qd


def _hilbert(m: int) -> np.ndarray:
    a = np.arange(m)
    return 1.0 / (a[:, None] + a[None, :] + 1.0)


def per_source(F: np.ndarray, G: np.ndarray, psd: np.ndarray, dt, *, what: str = "",
               times=None, groups=None) -> np.ndarray:
    """Exact ``Q_d`` of each column of a low-rank ``Q_c``, any step.

    Parameters
    ----------
    F : ndarray, shape (N, n, n)
    G : ndarray, shape (N, n, k)
    psd : ndarray, shape (N, k)
    dt : float or ndarray, shape (N,)
        Step lengths. [s]
    what : str
        Names the system in error messages.
    times : ndarray, shape (N,), optional
        Start time of each step, for error messages. [s]
    groups : array_like of int, shape (J,), optional
        Increasing first columns of ``J`` groups of columns (as
        ``np.add.reduceat``): return the ``Q_d`` of each group, summed
        without forming the per-column matrices (the same convergence
        rule, column by column).

    Returns
    -------
    ndarray, shape (N, k, n, n), or (N, J, n, n) with ``groups``
        ``Q_d`` of each column ``G[:, :, p]`` with PSD ``psd[:, p]`` (or of
        each group of columns); they sum to the ``Q_d`` of
        ``Q_c = G diag(psd) Gᵀ``.

    Raises
    ------
    NumericalError
        Non-finite input or result, a series that does not converge, or a
        total ``Q_d`` that is not PSD, naming the step.

    Notes
    -----
    ``Q_d = ∫₀^Δt e^{Fs} G W Gᵀ e^{Fᵀs} ds`` (the Van Loan integral).  With
    ``Ŷ_a = F^a G h^a / a!`` and ``e^{Fs} G = Σ_a Ŷ_a (s/h)^a``::

        Q_d(h) = h Σ_{a,b} Ŷ_a W Ŷ_bᵀ / (a + b + 1)

    which collects the terms of seed 002 eq (6c)–(6d) (``C_{i−1} h^i/i!``
    with ``C_{i−1} = Σ_{a+b=i−1} binom(i−1, a) F^a Q_c Fᵀ^b``) by source
    column instead of by order.  It is linear in ``W`` term by term, costs
    ``n × k`` products instead of ``n × n`` per order, and, the coefficient
    matrix being a Hilbert (Gram) matrix, is positive semi-definite for any
    truncation.  It is evaluated as :func:`covtool.lincov.discretize.taylor` does
    (module notes there): on the balanced system, at ``h = Δt/2^s`` with
    ``νh ≤ θ``, each column summed until the tail of ``Σ_a Ŷ_a`` is provably
    small (``‖Ŷ_{a+1}‖ ≤ ‖Ŷ_a‖ νh/(a+1)``): below ``2⁻⁵³ √(min_r Q_rr/(wh))/2``
    over the states ``r`` the column reaches, which bounds every element's
    error by ``2⁻⁵³ √(Q_ii Q_jj)``; then doubled ``s`` times with
    ``Q_j(2h) = Φ(h) Q_j(h) Φ(h)ᵀ + Q_j(h)``.
    """
    return _dedup(lambda F_, G_, p_, dt_, t_: _per_source(F_, G_, p_, dt_, what, t_, groups), F,
                  [(G, 2), (psd, 1)], dt, times, lambda Q, inv: Q[inv])


def _per_source(F, G, psd, dt, what, times, groups=None):
    F, _, dt, times = _prepare(F, None, dt, what, times)     # no Q_c: the noise is G, psd
    N, n, _ = F.shape
    G = np.asarray(G, float)
    psd = np.asarray(psd, float)
    for name, X in (("G", G), ("psd", psd)):
        bad = ~np.isfinite(X.reshape(N, -1)).all(axis=1)
        if bad.any():
            k = int(np.argmax(bad))
            raise NumericalError(f"{_step_where(what, k, dt, times)}: {name} has non-finite entries")
    d = balancing(F)
    B, _, nu = _balanced(F, None, d)
    s, h = scaling(nu, dt)
    hw = h[:, None, None]
    k = G.shape[2]
    # The terms Ŷ_a and their Hilbert-weighted sums are written in place into two buffers of
    # MAX_TERMS rows, the rows never reached never touched: on these small stacks a fresh
    # (N, n, k) array per term and fresh (m, N, n, k) stacks per pass cost more (in page faults
    # of new memory) than their arithmetic.  The arithmetic is unchanged.
    Zbuf = np.empty((MAX_TERMS, N, n, k))
    ZHbuf = np.empty_like(Zbuf)
    Y = np.divide(G, d[None, :, None], out=Zbuf[0])
    m = 1                                                # terms in Zbuf[:m]
    c0 = np.sqrt(np.einsum("kip,kip->kp", Y, Y))       # (N, k) column norms
    last = c0                                            # column norms of Zbuf[m - 1]
    a = (nu * h)[:, None]
    rch = reach(B, Y != 0)                               # (N, n, k)
    eps = UNIT_ROUNDOFF * c0                             # first pass: relative to ‖Ŷ_0‖

    def extend(eps):
        nonlocal m, last
        while m < MAX_TERMS:
            i = m - 1
            r = a / (i + 1)
            with np.errstate(divide="ignore", invalid="ignore"):
                tail = last * r / (1.0 - r)
            done = np.all((r < 1.0) & (tail <= eps), axis=1)
            if done.all():
                return done
            T = np.matmul(B, Zbuf[i], out=Zbuf[m])
            T *= hw / (i + 1)
            m += 1
            last = np.sqrt(np.einsum("kip,kip->kp", T, T))
        return done

    def weighted():
        Z, ZH = Zbuf[:m], ZHbuf[:m]                         # (m, N, n, k): one GEMM with the Hilbert matrix
        np.matmul(_hilbert(m), Z.reshape(m, -1), out=ZH.reshape(m, -1))
        ZH *= (psd * h[:, None])[None, :, None, :]
        return Z, ZH

    def assemble(Z, ZH):
        # Q_j = Σ_{p ∈ j} w_p Z_p H Z_pᵀ: one (n, m·|j|) × (m·|j|, n) product per group (column) and step
        bounds = np.r_[np.arange(k) if groups is None else np.asarray(groups, int), k]
        Q = np.empty((N, len(bounds) - 1, n, n))
        m = Z.shape[0]
        # (N, n, k, m): a group's columns are one view.  Zt is always a copy (ascontiguousarray would
        # return Z itself when the transpose is contiguous), so that ZHt can take Z's memory
        Zt = Z.transpose(1, 2, 3, 0).copy()
        ZHt = Z.reshape(N, n, k, m)                             # Z's memory, free once copied: no new memory
        np.copyto(ZHt, ZH.transpose(1, 2, 3, 0))
        for j, (a0, b0) in enumerate(zip(bounds[:-1], bounds[1:])):
            A = ZHt[:, :, a0:b0].reshape(N, n, (b0 - a0) * m)
            Bz = Zt[:, :, a0:b0].reshape(N, n, (b0 - a0) * m)
            Qj = A @ np.swapaxes(Bz, 1, 2)
            Q[:, j] = 0.5 * (Qj + np.swapaxes(Qj, 1, 2))
        return Q

    m_done = 0
    for _ in range(3):
        done = extend(eps)
        _not_converged(done, what, dt, times, nu, h)
        if m == m_done:                                     # no new term: the same Q_d, converged
            break
        m_done = m
        Z, ZH = weighted()
        dg = np.einsum("akip,akip->kpi", ZH, Z)             # diagonal of each column's Q_d
        # correlation scaling: ‖δ(s)‖ ≤ tail on [0, h] gives |ΔQ_ij| ≤ tail √(wh) (√Q_ii + √Q_jj) + …
        qmin = np.where(np.swapaxes(rch, 1, 2), dg, np.inf).min(axis=2)
        wh = np.where(psd > 0, psd, 1.0) * h[:, None]
        with np.errstate(invalid="ignore"):
            need = 0.5 * UNIT_ROUNDOFF * np.sqrt(np.maximum(np.where(np.isfinite(qmin), qmin, 0.0) / wh,
                                                            1e-32 * c0**2))
        # no noise in a column, or a step of Δt = 0 (its Q_d is exactly zero): nothing to refine
        need = np.where((psd > 0) & (h[:, None] > 0), need, np.inf)
        if np.all(need >= eps):
            break
        eps = np.minimum(eps, need)
    Q = assemble(Z, ZH)
    del Z, ZH, Y                   # assemble reused Z's memory (Zbuf) for ZHᵀ: no longer the terms
    if s.any():
        sq = s > 0
        Phi, _, _, ok = _series(B[sq], np.zeros_like(B[sq]), h[sq], nu[sq])
        _not_converged(ok, what, dt[sq], None if times is None else times[sq], nu[sq], h[sq])
        Qs = Q[sq]
        for j in range(int(s.max())):
            mj = s[sq] > j
            P = Phi[mj][:, None]
            with np.errstate(over="ignore", invalid="ignore"):
                X = P @ Qs[mj] @ np.swapaxes(P, -1, -2) + Qs[mj]
                Qs[mj] = 0.5 * (X + np.swapaxes(X, -1, -2))
                Phi[mj] = Phi[mj] @ Phi[mj]
        Q[sq] = Qs
    Q *= (d[:, None] * d[None, :])
    tot = Q.sum(axis=1)
    bad = ~np.isfinite(tot).all(axis=(1, 2))
    if bad.any():
        k = int(np.argmax(bad))
        raise NumericalError(f"{_step_where(what, k, dt, times)}: Q_d overflows (νΔt = {nu[k] * dt[k]:.4g})")
    check_qd(tot, what, dt=dt, times=times)
    return Q
