"""Batched covariance engine: many filter cases against one truth in a few large GEMMs.

Every case of a sweep (a filter with its P_f(0), Q_f or R_f scaled) shares the
truth's Φ(t) and Q(t); only the gains differ.  The engine

1. composes Φ and Q_d over the intervals between *events* (measurement and
   record steps) once per system, because between measurements the truth
   and the filter covariances obey the same linear recursion for every case
   (seed 002, eq (6a) and (15))::

       Φ_{a→b} = Φ_{b−1} ⋯ Φ_a,   Q_{a→b} = Σ_k Φ_{k+1→b} Q_k Φ_{k+1→b}ᵀ

2. propagates all cases at once across each interval with two GEMMs of
   shape ``(n × n)·(n × B n)`` (:func:`sandwich`);
3. applies the filters' updates (eq (7), (8)/Joseph) and the truth update
   eq (16) batched over cases.

A Q_f scale multiplies the composed filter noise (Q_{a→b} is linear in Q),
so one composition serves every Q scale.  Results are identical to
:func:`covtool.covariance.propagate_with_filter` up to round-off (tested).

Pure numeric core: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits


def sandwich(A: np.ndarray, P: np.ndarray) -> np.ndarray:
    """``A P_b Aᵀ`` for every ``b``: one large and one batched GEMM.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    P : ndarray, shape (B, n, n)

    Returns
    -------
    ndarray, shape (B, n, n)

    Notes
    -----
    ``[P_1; P_2; …] Aᵀ`` is one ``(B n × n)·(n × n)`` GEMM on a view of the
    stack; ``A (P_b Aᵀ)`` is then a batched GEMM over ``b``.  No operand is
    transposed or copied, which matters for the medium sizes (n ≤ 58) where
    copies cost as much as the products.
    """
    B, n, _ = P.shape
    V = (np.ascontiguousarray(P).reshape(B * n, n) @ A.T).reshape(B, n, n)   # P_b Aᵀ, stacked
    return np.matmul(A, V)


def events(n_steps: int, update_steps, record_steps) -> np.ndarray:
    """Sorted event grid indices: 0, every update and record step, and N."""
    ev = {0, int(n_steps)}
    ev.update(int(k) for k in update_steps)
    ev.update(int(k) for k in record_steps)
    return np.array(sorted(ev))


def compose(Phi: np.ndarray, Qd: np.ndarray, ev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Transition and noise over each interval ``[ev_i, ev_{i+1})``.

    Parameters
    ----------
    Phi, Qd : ndarray, shape (N, n, n)
    ev : ndarray of int, shape (K+1,)

    Returns
    -------
    Phi_c, Q_c : ndarray, shape (K, n, n)
    """
    K = len(ev) - 1
    n = Phi.shape[1]
    Pc = np.empty((K, n, n))
    Qc = np.empty((K, n, n))
    eye = np.eye(n)
    for i in range(K):
        A = eye
        Q = np.zeros((n, n))
        for k in range(ev[i], ev[i + 1]):
            A = Phi[k] @ A
            Q = Phi[k] @ Q @ Phi[k].T + Qd[k]
        Pc[i] = A
        Qc[i] = 0.5 * (Q + Q.T)
    return Pc, Qc


@dataclass
class System:
    """A composed linear system on an event grid.

    Attributes
    ----------
    ev : ndarray of int, shape (K+1,)
        Event grid indices.
    Phi, Q : ndarray, shape (K, n, n)
        Composed transition and noise per interval.
    """

    ev: np.ndarray
    Phi: np.ndarray
    Q: np.ndarray

    @classmethod
    def from_steps(cls, Phi, Qd, ev) -> "System":
        Pc, Qc = compose(Phi, Qd, ev)
        return cls(np.asarray(ev), Pc, Qc)

    @property
    def n(self) -> int:
        return self.Phi.shape[1]


@dataclass
class BatchResult:
    """Histories of a batch at the record steps.

    Attributes
    ----------
    record_steps : ndarray of int
    P_truth : ndarray, shape (B, n_rec, k, k)
        Truth covariance (the ``keep`` sub-block) at each record step.
    P_filter : ndarray, shape (B, n_rec, k_f, k_f) or None
        The filters' own covariance (the same sub-block).
    gains : ndarray, shape (B, n_upd, n_f, m) or None
        Filter gains at the update steps (for fixed-gain runs such as budgets).
    update_steps : ndarray of int
    """

    record_steps: np.ndarray
    P_truth: np.ndarray
    P_filter: np.ndarray | None
    gains: np.ndarray | None
    update_steps: np.ndarray


def _sym(P):
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def _selection(D: np.ndarray):
    """``(k0, k1)`` if ``D`` selects truth states ``k0:k1``, else None."""
    n, nf = D.shape
    cols = np.flatnonzero(D[:, 0]) if nf else []
    if len(cols) != 1 or cols[0] + nf > n:
        return None
    k0 = int(cols[0])
    E = np.zeros_like(D)
    E[k0:k0 + nf] = np.eye(nf)
    return (k0, k0 + nf) if np.array_equal(D, E) else None


def _joseph(P, K, HP, S, sel=None, symmetrize=True):
    """Joseph form / eq (16) update in rank-m form, in place.

    ``(I − D K H) P (I − D K H)ᵀ + D K R Kᵀ Dᵀ``.

    Parameters
    ----------
    P : ndarray, shape (B, n, n)
        Prior covariance; overwritten (it must be owned by the caller).
    K : ndarray, shape (B, n_f, m)
        Gains.
    HP : ndarray, shape (B, m, n)
        ``H P``.
    S : ndarray, shape (B, m, m)
        ``H P Hᵀ + R``.
    sel : (int, int), optional
        ``D`` is the selection of truth states ``k0:k1`` (:func:`_selection`);
        ``None`` means ``D = I``.
    symmetrize : bool
        Also replace ``P`` by ``(P + Pᵀ)/2`` (one more pass over ``P``).

    Returns
    -------
    ndarray, shape (B, n, n)
        Exactly symmetric if ``symmetrize``.

    Notes
    -----
    With ``DK = D K`` the Joseph form (and eq (16)) equals
    ``P + X + Xᵀ`` with ``X = (DK S/2 − (HP)ᵀ) (DK)ᵀ`` for every gain (optimal
    or not): ``O(m n n_f)`` instead of ``O(n³)`` per case.  ``X`` is non-zero
    only in the columns ``k0:k1``.  Symmetrised, the result is formed as
    ``Y + Yᵀ`` with ``Y = P/2 + X``.
    """
    k0, k1 = sel if sel is not None else (0, P.shape[1])
    M = -np.swapaxes(HP, 1, 2)                                  # (B, n, m)
    M[:, k0:k1] += 0.5 * (K @ S)
    X = M @ np.swapaxes(K, 1, 2)                                # (B, n, n_f)
    if not symmetrize:
        P[:, :, k0:k1] += X
        P[:, k0:k1, :] += np.swapaxes(X, 1, 2)
        return P
    P *= 0.5
    P[:, :, k0:k1] += X
    return np.add(P, np.swapaxes(P, 1, 2))


#: updates between full symmetrisations of the covariances (the
#: propagation and the unsymmetrised update leave round-off asymmetry only)
SYMMETRIZE_EVERY = 8


def run_batch(*args, blas_threads: int | None = 1, **kwargs) -> "BatchResult":
    """Batched truth-under-filter run; see :func:`_run_batch` for the parameters.

    ``blas_threads`` limits the BLAS thread pool (default 1): the matrices are
    medium-sized (n ≤ 58, B·n ≲ 10⁴) and a second BLAS thread costs more in
    synchronisation than it gains; cases are parallelised across processes
    instead (:mod:`covtool.parallel`).  ``None`` leaves the pool alone.
    """
    if blas_threads is None:
        return _run_batch(*args, **kwargs)
    with threadpool_limits(limits=blas_threads, user_api="blas"):
        return _run_batch(*args, **kwargs)


def _run_batch(truth: System, P0: np.ndarray, H: np.ndarray, R: np.ndarray, D: np.ndarray,
              update_steps, record_steps, *, filt: System | None = None, Pf0: np.ndarray | None = None,
              Hf: np.ndarray | None = None, Rf: np.ndarray | None = None, q_scale=None,
              gains: np.ndarray | None = None, truth_Q: np.ndarray | None = None,
              filter_Q=None, form: str = "joseph", keep=slice(0, 10)) -> BatchResult:
    """Truth covariance of B cases under their filters' gains, batched (eq (6)–(8), (15)–(16)).

    Either the filters run alongside (``filt``, ``Pf0``, ``Hf``, ``Rf``, ``q_scale``)
    and compute their gains, or fixed ``gains`` are given (error budgets).

    Parameters
    ----------
    truth : System
        Composed truth Φ and Q on the event grid.
    P0 : ndarray, shape (B, n, n) or (n, n)
        Truth initial covariance per case (broadcast if 2-D).
    H : ndarray, shape (m, n)
    R : ndarray, shape (B, m, m) or (m, m)
        True measurement noise per case.
    D : ndarray, shape (n, n_f)
    update_steps, record_steps : iterable of int
        Must be event indices of ``truth.ev`` (and ``filt.ev``).
    filt : System, optional
        Composed filter Φ_f, Q_f (unscaled).
    Pf0 : ndarray, shape (B, n_f, n_f)
    Hf : ndarray, shape (m, n_f)
    Rf : ndarray, shape (B, m, m)
        Filter-assumed measurement noise per case.
    q_scale : ndarray, shape (B,), optional
        Scale of the filter's Q per case (default 1).
    gains : ndarray, shape (B or 1, n_upd, n_f, m), optional
        Fixed gains instead of a running filter.
    truth_Q : ndarray, shape (B, K, n, n), optional
        Per-case truth noise per interval (default: ``truth.Q`` for all).
    filter_Q : ndarray-like, shape (B, K, n_f, n_f), optional
        Per-case filter noise per interval, indexed ``filter_Q[:, i]``
        (default: ``filt.Q`` for all, times ``q_scale``).
    form : {"joseph", "standard"}
        Filter update form.
    keep : slice or index array
        Sub-block of the covariances to record (default: the 10 navigation states).

    Returns
    -------
    BatchResult
    """
    ev = truth.ev
    n = truth.n
    upd = [int(k) for k in update_steps]
    rec = [int(k) for k in record_steps]
    upd_set = set(upd)
    rec_set = set(rec)
    pos = {int(k): i for i, k in enumerate(ev)}
    for k in upd + rec:
        if k not in pos:
            raise ValueError(f"step {k} is not on the event grid")
    P0 = np.asarray(P0, float)
    B = P0.shape[0] if P0.ndim == 3 else (Pf0.shape[0] if Pf0 is not None else gains.shape[0])
    P = np.broadcast_to(P0, (B, n, n)).copy()
    R = np.broadcast_to(np.asarray(R, float), (B,) + H.shape[:1] * 2).copy()
    running = filt is not None
    if running:
        Pf = np.array(Pf0, float, copy=True)
        nf = Pf.shape[1]
        Rf = np.broadcast_to(np.asarray(Rf, float), (B,) + R.shape[1:]).copy()
        qs = np.ones(B) if q_scale is None else np.asarray(q_scale, float)
        if not np.array_equal(filt.ev, ev):
            raise ValueError("truth and filter event grids differ")
    else:
        nf = D.shape[1]
        gains = np.broadcast_to(gains, (B,) + gains.shape[1:])
    m = H.shape[0]
    sel = _selection(np.asarray(D, float))
    idx = np.arange(n)[keep]
    out_t = np.empty((B, len(rec), idx.size, idx.size))
    out_f = None
    if running:
        fidx = np.arange(nf)[keep] if isinstance(keep, slice) else np.asarray(keep)[np.asarray(keep) < nf]
        out_f = np.empty((B, len(rec), fidx.size, fidx.size))
    out_g = np.empty((B, len(upd), nf, m))
    ui = ri = 0
    for i, k in enumerate(ev):
        if k in upd_set:
            sym = ui % SYMMETRIZE_EVERY == SYMMETRIZE_EVERY - 1 or ui == len(upd) - 1
            if running:
                HPf = Hf @ Pf                                             # (B, m, nf)
                S = HPf @ Hf.T + Rf                                       # (B, m, m)
                K = np.swapaxes(np.linalg.solve(S, HPf), 1, 2)            # eq (7), (B, nf, m)
                if form == "joseph":
                    Pf = _joseph(Pf, K, HPf, S, symmetrize=sym)
                else:
                    Pf = Pf - K @ HPf                                     # eq (8)
                    Pf = _sym(Pf) if sym else Pf
            else:
                K = gains[:, ui]
            out_g[:, ui] = K
            HP = H @ P
            if sel is not None:
                P = _joseph(P, K, HP, HP @ H.T + R, sel, symmetrize=sym)  # eq (16), D a selection
            else:
                P = _joseph(P, D @ K, HP, HP @ H.T + R, symmetrize=sym)   # eq (16)
            ui += 1
        if k in rec_set:
            out_t[:, ri] = _sym(P[:, idx[:, None], idx[None, :]])
            if running:
                out_f[:, ri] = _sym(Pf[:, fidx[:, None], fidx[None, :]])
            ri += 1
        if i < len(ev) - 1:
            # eq (15) and (6a); symmetry is restored every SYMMETRIZE_EVERY updates and when recorded
            P = sandwich(truth.Phi[i], P)
            P += truth.Q[i] if truth_Q is None else truth_Q[:, i]
            if running:
                Pf = sandwich(filt.Phi[i], Pf)
                Pf += qs[:, None, None] * (filt.Q[i] if filter_Q is None else filter_Q[:, i])
    return BatchResult(np.array(rec), out_t, out_f, out_g if upd else None, np.array(upd))
