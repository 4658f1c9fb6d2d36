"""Block-triangular (sensor-state) discretisation, any step.

The sensor states (random constants, Markov and random-walk states) are
driven by nothing but themselves: ordered after the navigation states,
``F = [[A, M], [0, diag(d)]]`` and the series of seed 002, eq (6b)–(6d) is
summed by blocks (:func:`block_triangular`), ``O(k² m)`` per term instead of
``O(n³)``.  :func:`_exact` chooses the block or the dense path.
"""
from __future__ import annotations

import numpy as np

from covtool.lincov.discretize.series import (
    MAX_TERMS, UNIT_ROUNDOFF, _balanced, _finish, _not_converged, _series, balancing, reach, scaling,
    sensor_states)
from covtool.lincov.discretize.steps import _dedup, _expand_phi_qd, _prepare
from covtool.lincov.discretize.limits import BLOCK_FRACTION
from covtool.lincov.stacks import gather


def _exact(F, Qc, dt, what, times):
    F, Qc, dt, times = _prepare(F, Qc, dt, what, times)
    sens = sensor_states(F, Qc)
    k = int(np.count_nonzero(~sens))
    if 1 <= k and sens.sum() >= BLOCK_FRACTION * F.shape[1]:
        # the same converged series by blocks (O(k² m) per term instead of O(n³)); exact
        p = np.r_[np.flatnonzero(~sens), np.flatnonzero(sens)]
        if np.array_equal(p, np.arange(p.size)):
            # the sensor states already follow the others (every model of the library): no gathers
            return _block_triangular(F, Qc, dt, k, what, times)
        ip = np.argsort(p)
        Phi, Qd, inf = _block_triangular(gather(F, p), gather(Qc, p), dt, k, what, times)
        return gather(Phi, ip), gather(Qd, ip), inf
    d = balancing(F)
    B, Qb, nu = _balanced(F, Qc, d)
    s, h = scaling(nu, dt)
    E, Qd, terms, done = _series(B, Qb, h, nu, minus_identity=True)
    _not_converged(done, what, dt, times, nu, h)
    return _finish(E, Qd, s, d, terms, nu, dt, what, times)


def _block_series(A, M, dd, QA, q, h, nu, rch):
    """The adaptive series of :func:`_series` for ``[[A, M], [0, diag(dd)]]`` by blocks.

    ``Q_c = blockdiag(QA, diag(q))``.  ``T_i`` and ``C_i`` keep the block
    form: ``T = [[TA, TM], [0, diag(TD)]]``, ``C = [[CA, CX], [CXᵀ, diag(CS)]]``
    with ``TA' = A TA``, ``TM' = A TM + M diag(TD)``, ``TD' = d TD`` (times
    ``h/i``) and ``CA' = (A CA + M CXᵀ) + (·)ᵀ``, ``CX' = A CX + M CS + CX D``,
    ``CS' = 2 d CS``.  Same stopping rule, with the norms taken by blocks.

    The rule is evaluated in stages, cheapest bound first: each stage is a
    maximum over some of the blocks, so it is a lower bound of the full
    norm and a step that fails it fails the rule.  The later stages are
    taken only while some step may still pass, which spares the Q_d test
    (the larger part of the cost) over the first terms, where nothing
    converges; the decisions, hence the terms and the sums, are the same
    as with the full test on every term.
    """
    N, k, _ = A.shape
    m = dd.shape[1]
    hw = h[:, None, None]
    TA = np.broadcast_to(np.eye(k), (N, k, k)).copy()
    TM = np.zeros((N, k, m))
    TD = np.ones((N, m))
    CA, CX, CS = QA.copy(), np.zeros((N, k, m)), q.copy()
    # the sums start from the i = 1 terms: Φ − I (see _square); every row of `out` is
    # written, at its step's stopping term or at the end
    work = [np.zeros(s) for s in ((N, k, k), (N, k, m), (N, m), (N, k, k), (N, k, m), (N, m))]
    out = [np.empty_like(x) for x in work]
    coef = hw.copy()
    a = nu * h
    phi_floor = UNIT_ROUNDOFF * (2.0 - np.exp(np.minimum(a, 1.0)))
    terms = np.zeros(N, int)
    done = np.zeros(N, bool)
    idx = np.arange(N)
    Aw, Mw, dw = A, M, dd
    # no noise (a transition alone): every C_i is zero, the Q_d sums stay zero (as in _series)
    noise = bool(np.any(QA) or np.any(q))
    for i in range(1, MAX_TERMS):
        f = hw / i
        # in place on the fresh products: the same operations, fewer temporaries
        TM = Aw @ TM
        TM += Mw * TD[:, None, :]
        TM *= f
        TA = Aw @ TA
        TA *= f
        TD = TD * dw * f[:, :, 0]
        for x, y in zip(work[:3], (TA, TM, TD)):
            x += y
        if noise:
            QtA, QtX, QtS = CA * coef, CX * coef, CS * coef[:, :, 0]
            for x, y in zip(work[3:], (QtA, QtX, QtS)):
                x += y
            AC = Aw @ CA
            AC += Mw @ np.swapaxes(CX, 1, 2)
            CXn = Aw @ CX
            CXn += Mw * CS[:, None, :]
            CXn += CX * dw[:, None, :]
            CX = CXn
            CA = AC + np.swapaxes(AC, 1, 2)
            CS = 2.0 * dw * CS
        coef = coef * hw / (i + 1)
        ai = a[idx]
        rp, rq = ai / (i + 1), 2.0 * ai / (i + 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            # the rule on rq < 1 is kept without noise: the same terms, the same Φ
            ok = rq < 1.0
            floor = phi_floor[idx]
            # Φ: the columns of [TA; 0] first, then those of [TM; diag(TD)]
            col = np.einsum("kij,kij->kj", TA, TA).max(axis=1)
            ok &= np.sqrt(col) * rp / (1.0 - rp) <= floor
            if ok.any():
                col = np.maximum(col, (np.einsum("kij,kij->kj", TM, TM) + TD**2).max(axis=1, initial=0.0))
                ok &= np.sqrt(col) * rp / (1.0 - rp) <= floor
            if noise and ok.any():
                ok &= _block_q_tail_ok(work[3], work[5], QtA, QtX, QtS, rch[idx], rq, k)
            ok |= hw[:, 0, 0] == 0.0                        # h = 0 (Δt = 0): every term past i = 0 is zero
        if ok.any():
            fin = idx[ok]
            for x, y in zip(out, work):
                x[fin] = y[ok]
            terms[fin], done[fin] = i + 1, True
            keep = ~ok
            idx = idx[keep]
            if idx.size == 0:
                break
            work = [x[keep] for x in work]
            Aw, Mw, dw, hw, coef, TA, TM, TD, CA, CX, CS = (
                x[keep] for x in (Aw, Mw, dw, hw, coef, TA, TM, TD, CA, CX, CS))
    if idx.size:
        for x, y in zip(out, work):
            x[idx] = y
    PA, PM, PD, SA, SX, SS = out
    n = k + m
    Phi = np.zeros((N, n, n))
    Q = np.zeros((N, n, n))
    Phi[:, :k, :k], Phi[:, :k, k:] = PA, PM
    Q[:, :k, :k], Q[:, :k, k:], Q[:, k:, :k] = SA, SX, np.swapaxes(SX, 1, 2)
    Phi[:, k:, k:] = PD[:, :, None] * np.eye(m)      # off the diagonal PD·0: −0.0 where PD < 0, as before
    Q[:, k:, k:] = SS[:, :, None] * np.eye(m)
    return Phi, Q, terms, done        # Φ − I (the sums start from the i = 1 terms)


def _block_q_tail_ok(SA, SS, QtA, QtX, QtS, rc, rq, k):
    """The Q_d rule of :func:`_series` by blocks: sums ``SA, SS``, last terms ``QtA, QtX, QtS``.

    In stages as the Φ rule: the sensor diagonal ``QtS`` first, then
    ``QtA``, then ``QtX``, each stage only while some step may still pass.
    """
    dg = np.concatenate([np.einsum("kii->ki", SA), SS], axis=1)
    ok = np.all(~rc | (dg > 0), axis=1)             # started
    if not ok.any():
        return ok
    sd = np.sqrt(np.where(rc, np.maximum(dg, 1e-32 * dg.sum(axis=1, keepdims=True)), 1.0))
    sa, ss = sd[:, :k], sd[:, k:]
    X = (np.abs(QtS) / ss**2).max(axis=1, initial=0.0)
    ok &= X * rq / (1.0 - rq) <= UNIT_ROUNDOFF
    for Xb in (lambda: (np.abs(QtA) / sa[:, :, None] / sa[:, None, :]).max(axis=(1, 2)),
               lambda: (np.abs(QtX) / sa[:, :, None] / ss[:, None, :]).max(axis=(1, 2), initial=0.0)):
        if not ok.any():
            break
        X = np.maximum(X, Xb())
        ok &= X * rq / (1.0 - rq) <= UNIT_ROUNDOFF
    return ok


def is_block_triangular(F, Qc, k: int) -> bool:
    """True if ``F = [[A, M], [0, diag(d)]]`` and ``Q_c = blockdiag(Q_A, diag(q))`` after ``k`` states."""
    F = np.asarray(F)
    Qc = np.asarray(Qc)
    n = F.shape[-1]
    off = ~np.eye(n - k, dtype=bool)
    return not (np.any(F[:, k:, :k]) or np.any(F[:, k:, k:][:, off]) or np.any(Qc[:, :k, k:])
                or np.any(Qc[:, k:, k:][:, off]))


def block_triangular(F, Qc, dt, k: int, *, what: str = "", times=None, info: bool = False):
    """Exact ``Φ, Q_d`` of a navigation block driven by scalar sensor states.

    The adaptive series of :func:`taylor` (exact for any step, module
    notes) with its products done by blocks: ``O(k² m)`` per term instead
    of ``O(n³)`` (five times faster for a 10 + 36-state IMU grade model).

    Parameters
    ----------
    F : ndarray, shape (N, n, n)
        ``[[A, M], [0, diag(d)]]``: ``k`` navigation states, ``n − k``
        random-constant, random-walk or first-order Markov sensor states.
    Qc : ndarray, shape (N, n, n)
        ``blockdiag(Q_A, diag(q))``.
    dt : float or ndarray, shape (N,)
        Step lengths. [s]
    k : int
        Navigation states (the first ones).
    what, times, info
        As :func:`taylor`.

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)
    info : StepInfo
        Only with ``info=True``.

    Raises
    ------
    ValueError
        ``F`` or ``Qc`` does not have this structure
        (:func:`is_block_triangular`).
    NumericalError
        As :func:`taylor`.
    """
    Phi, Qd, inf = _dedup(lambda F_, Q_, dt_, t_: _block_triangular(F_, Q_, dt_, k, what, t_), F, [(Qc, 2)], dt,
                          times, _expand_phi_qd)
    return (Phi, Qd, inf) if info else (Phi, Qd)


def _block_triangular(F, Qc, dt, k, what, times):
    F, Qc, dt, times = _prepare(F, Qc, dt, what, times)
    if not is_block_triangular(F, Qc, k):
        raise ValueError(f"F, Q_c are not block triangular with a diagonal sensor block after {k} states")
    d = balancing(F)
    B, Qb, nu = _balanced(F, Qc, d)
    s, h = scaling(nu, dt)
    rch = reach(B, np.einsum("kii->ki", Qb) > 0)
    E, Qd, terms, done = _block_series(B[:, :k, :k], B[:, :k, k:], np.einsum("kii->ki", B[:, k:, k:]),
                                       Qb[:, :k, :k], np.einsum("kii->ki", Qb[:, k:, k:]), h, nu, rch)
    _not_converged(done, what, dt, times, nu, h)
    return _finish(E, Qd, s, d, terms, nu, dt, what, times)
