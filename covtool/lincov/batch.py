"""Batched covariance engine: many filter cases against one truth in a few large GEMMs.

Every case of a sweep (a filter with its P_f(0), Q_f or R_f scaled) shares the
truth's Φ(t) and Q(t); only the gains differ.  The engine

1. composes Φ and Q_d over the intervals between *events* (measurement and
   record steps) once per system, because between measurements the truth
   and the filter covariances obey the same linear recursion for every case
   (seed 002, eq (6a) and (15))::

       Φ_{a→b} = Φ_{b−1} ⋯ Φ_a,   Q_{a→b} = Σ_k Φ_{k+1→b} Q_k Φ_{k+1→b}ᵀ

2. propagates all cases at once across each interval with two GEMMs of
   shape ``(n × n)·(n × B n)`` (:func:`sandwich`); the random-constant
   states (zero F row, no noise: ``Φ = [[Φ_dd, Γ], [0, I]]``, 36 of the
   58 truth states) are not propagated, only the dynamic rows
   (:func:`dynamic_states`), exactly;
3. applies the filters' updates (eq (7), (8)/Joseph) and the truth update
   eq (16) batched over cases.

A Q_f scale multiplies the composed filter noise (Q_{a→b} is linear in Q),
so one composition serves every Q scale.  Results are identical to
:func:`covtool.lincov.reference.propagate_with_filter` up to round-off (tested).

Pure numeric core: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from covtool.errors import NumericalError
from covtool.lincov.kalman import (check_covariance, check_finite, covariance_status, NEGATIVE_VARIANCE,
                                   NOT_PSD, scale_groups, symmetrize, time_text)
# the rank-m Joseph / eq (16) update and the selection test live in the kernel (one home)
from covtool.lincov.kalman import (gain_from_innovation, joseph_update as _joseph, selection as _selection,
                                   standard_update)


def sandwich(A: np.ndarray, P: np.ndarray, dynamic=None) -> np.ndarray:
    """``A P_b Aᵀ`` for every ``b``: one large and one batched GEMM.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    P : ndarray, shape (B, n, n)
    dynamic : (ndarray of int, ndarray of int), optional
        ``(d, c)``: the rows ``c`` of ``A`` are rows of the identity
        (random-constant states, :func:`dynamic_states`); only the blocks
        they do not fix are computed (exact, see Notes).

    Returns
    -------
    ndarray, shape (B, n, n)

    Notes
    -----
    ``[P_1; P_2; …] Aᵀ`` is one ``(B n × n)·(n × n)`` GEMM on a view of the
    stack; ``A (P_b Aᵀ)`` is then a batched GEMM over ``b``.  No GEMM operand
    is transposed or copied, which matters for the medium sizes (n ≤ 58) where
    copies cost as much as the products; the dynamic path places its blocks by
    one copy of ``P`` and whole-row scatters.

    The result is always a new array, never ``P`` or a view of it: the engine
    relies on that (after a record its ``P`` is a slot of the deferred guard's
    stack, which the next ``sandwich`` must not write).

    With ``A = [[A_dd, A_dc], [0, I]]`` (states reordered, ``d`` dynamic,
    ``c`` constant) and ``U = P A_dᵀ`` (``A_d`` the rows ``d``)::

        (A P Aᵀ)_cc = P_cc,   (A P Aᵀ)_cd = U_c,   (A P Aᵀ)_dd = A_d U,
        (A P Aᵀ)_dc = (A P Aᵀ)_cdᵀ  (P symmetric)

    ``2 n² n_d`` instead of ``4 n³`` FLOP: 3.8 times fewer for the 58-state
    model (22 dynamic states).  The identity rows multiply exactly, so the
    result equals the dense product up to the order of the sums.
    """
    B, n, _ = P.shape
    if dynamic is None:
        V = (np.ascontiguousarray(P).reshape(B * n, n) @ A.T).reshape(B, n, n)   # P_b Aᵀ, stacked
        return np.matmul(A, V)
    d, c = dynamic
    Ad = A[d]                                                                      # (n_d, n)
    U = (np.ascontiguousarray(P).reshape(B * n, n) @ Ad.T).reshape(B, n, d.size)   # P_b A_dᵀ, stacked
    # the blocks are placed by whole copies and row scatters (no 2-D fancy index over the stack: those
    # cost as much as the products): a copy of P (the block cc final), the columns d (rows c final:
    # (A P Aᵀ)_cd = U_c), then the rows d whole, [U_cᵀ | A_d U] assembled in a (B, n_d, n) buffer
    out = P.copy()
    out[:, :, d] = U
    rows = np.swapaxes(U, 1, 2).copy()                        # (A P Aᵀ)_dc = U_cᵀ
    rows[:, :, d] = np.matmul(Ad, U)                          # (A P Aᵀ)_dd
    out[:, d, :] = rows
    return out


def dynamic_states(Phi: np.ndarray, fraction: float = 0.75):
    """``(d, c)``: dynamic states and identity rows of a stack of ``Φ``.

    Parameters
    ----------
    Phi : ndarray, shape (K, n, n)
        Transitions (per step or per interval).
    fraction : float
        Return None when more than this fraction of the states are
        dynamic (the dense product is then as fast).

    Returns
    -------
    (ndarray of int, ndarray of int) or None
        ``c``: the states whose ``Φ`` row is the identity's in every
        interval (random constants: a zero ``F`` row, so
        ``Φ = [[Φ_dd, Γ], [0, I]]``, exactly); ``d``: the others.  None if
        the split does not pay.  :func:`sandwich` needs nothing else:
        ``Q`` is added whole.
    """
    Phi = np.asarray(Phi)
    if Phi.ndim != 3 or Phi.shape[0] == 0 or Phi.shape[1] != Phi.shape[2]:
        return None
    n = Phi.shape[1]
    eye = np.eye(n)
    const = np.ones(n, bool)
    for a in range(0, Phi.shape[0], 256):          # in chunks: the temporaries stay small
        # over the steps first (contiguous planes), then along the rows: 3 times faster than over axes (0, 2)
        const &= (Phi[a:a + 256] == eye).all(axis=0).all(axis=1)
        if not const.any():
            return None
    d = np.flatnonzero(~const)
    if d.size > fraction * n or d.size == 0:
        return None
    return d, np.flatnonzero(const)


def events(n_steps: int, update_steps, record_steps) -> np.ndarray:
    """Sorted event grid indices: 0, every update and record step, and N."""
    ev = {0, int(n_steps)}
    ev.update(int(k) for k in update_steps)
    ev.update(int(k) for k in record_steps)
    return np.array(sorted(ev))


#: bytes of per-step operands :func:`compose` gathers at once (a block of steps)
_COMPOSE_BLOCK = 1e6


def compose(Phi: np.ndarray, Qd: np.ndarray, ev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Transition and noise over each interval ``[ev_i, ev_{i+1})``.

    Parameters
    ----------
    Phi, Qd : ndarray, shape (N, n, n)
    ev : ndarray of int, shape (K+1,)

    Returns
    -------
    Phi_c, Q_c : ndarray, shape (K, n, n)

    Notes
    -----
    With random-constant states (:func:`dynamic_states`: ``Φ`` rows of the
    identity) and ``Q_d`` zero outside the dynamic block, the products keep
    that form, so only ``Φ_d = Φ[d, :]`` and ``Q_dd`` are composed::

        Φ_{a→k+1}[d] = Φ_k[d, d] Φ_{a→k}[d] + Φ_k[d, c] E_c,
        Q_dd ← Φ_k[d, d] Q_dd Φ_k[d, d]ᵀ + Q_d,k[d, d]

    (``E_c`` the identity rows ``c``): exact, ``(n_d/n)²`` of the work.
    """
    ev = np.asarray(ev, int)
    K = len(ev) - 1
    n = Phi.shape[1]
    eye = np.eye(n)
    if K == 0:
        return np.empty((0, n, n)), np.empty((0, n, n))
    dyn = dynamic_states(Phi[ev[0]:ev[-1]])
    if dyn is not None:
        d, c = dyn
        mask = np.ones((n, n), bool)
        mask[np.ix_(d, d)] = False
        # a non-zero (or NaN) entry at some step marks its (i, j): reduced over the steps first, contiguous
        if any(np.any((Qd[a:a + 256] != 0).any(axis=0)[mask]) for a in range(ev[0], ev[-1], 256)):
            dyn = None
    # the intervals advance together, step j of each at once (batched products over the intervals), the
    # longest first: those still running at step j are a leading slice of the stacks (no gather and
    # scatter per step), and their steps' operands are gathered once, in blocks, into that order
    order = np.argsort(-np.diff(ev), kind="stable")
    start, length = ev[:-1][order], np.diff(ev)[order]
    run, off, steps = _interval_steps(start, length)
    block = max(run[0] if run else 0, int(_COMPOSE_BLOCK // (8 * n * n)))
    if dyn is None:
        nd, d = n, None
        A = np.broadcast_to(eye, (K, n, n)).copy()
    else:
        nd = d.size
        perm = np.r_[d, c]
        A = np.broadcast_to(eye[d][:, perm], (K, nd, n)).copy()    # rows d of Φ_{a→k}, columns (d, c)
    Q = np.zeros((K, nd, nd))
    for j0, j1 in _blocks(off, block):
        ks = steps[off[j0]:off[j1]]
        if dyn is None:
            F, Qk = Phi[ks], Qd[ks]
        else:
            Fk = Phi[ks[:, None], d[None, :]]                                # rows d: (steps, n_d, n)
            F = np.ascontiguousarray(Fk[:, :, d])            # contiguous: BLAS, not numpy's own loop
            Fc = Fk[:, :, c]
            Qk = Qd[ks][:, d[:, None], d[None, :]]
        FT = np.ascontiguousarray(np.swapaxes(F, 1, 2))
        for j in range(j0, j1):
            m, p = run[j], off[j] - off[j0]
            Fj = F[p:p + m]
            if dyn is None:
                A[:m] = Fj @ A[:m]
            else:
                An = Fj @ A[:m]
                An[:, :, nd:] += Fc[p:p + m]
                A[:m] = An
            Q[:m] = Fj @ Q[:m] @ FT[p:p + m] + Qk[p:p + m]
    A[order], Q[order] = A.copy(), Q.copy()                  # back to the order of the intervals
    if dyn is None:
        return A, symmetrize(Q)
    Pc = np.broadcast_to(eye, (K, n, n)).copy()
    Pc[:, d[:, None], perm[None, :]] = A
    Qc = np.zeros((K, n, n))
    Qc[:, d[:, None], d[None, :]] = symmetrize(Q)
    return Pc, Qc


def _interval_steps(start, length):
    """Steps of intervals sorted by decreasing length, grouped by their position in the interval.

    Parameters
    ----------
    start, length : ndarray of int, shape (K,)
        First step and length of each interval, ``length`` non-increasing.

    Returns
    -------
    run : list of int
        ``run[j]``: the intervals at least ``j+1`` steps long (a leading slice).
    off : list of int
        ``off[j]``: where the steps ``start[:run[j]] + j`` begin in ``steps``.
    steps : ndarray of int
        ``start[i] + j`` for each ``j`` and ``i < run[j]``, in that order.
    """
    L = int(length[0]) if length.size else 0
    run = np.searchsorted(-length, -np.arange(L), side="left")     # count of length > j
    off = np.r_[0, np.cumsum(run)]
    i = np.arange(off[-1]) - np.repeat(off[:-1], run)
    steps = start[i] + np.repeat(np.arange(L), run)
    return run.tolist(), off.tolist(), steps


def _blocks(off, size):
    """``(j0, j1)`` ranges covering ``0 … len(off)−1``, each at most ``size`` steps of ``off`` (at least one ``j``)."""
    j0, L = 0, len(off) - 1
    while j0 < L:
        j1 = max(j0 + 1, int(np.searchsorted(off, off[j0] + size, side="right")) - 1)
        yield j0, j1
        j0 = j1


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

    @classmethod
    def concat(cls, parts) -> "System":
        """One system from consecutive ones (each starting where the previous ends: chunks in time).

        Parameters
        ----------
        parts : sequence of System
            ``parts[i].ev[-1] == parts[i+1].ev[0]``; the same ``n``.

        Raises
        ------
        ValueError
            No part, or parts that do not follow one another.
        """
        parts = list(parts)
        if not parts:
            raise ValueError("System.concat: no part")
        for p, q in zip(parts, parts[1:]):
            if int(p.ev[-1]) != int(q.ev[0]) or p.n != q.n:
                raise ValueError(f"System.concat: a part ending at step {int(p.ev[-1])} ({p.n} states) is followed "
                                 f"by one starting at step {int(q.ev[0])} ({q.n} states)")
        if len(parts) == 1:
            return parts[0]
        ev = np.concatenate([parts[0].ev] + [p.ev[1:] for p in parts[1:]])
        return cls(ev, np.concatenate([p.Phi for p in parts]), np.concatenate([p.Q for p in parts]))

    @cached_property
    def dynamic(self):
        """``(d, c)`` of :func:`dynamic_states` for the intervals, or None."""
        return dynamic_states(self.Phi)

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
    status : list of str
        Per case: ``""`` if every checked covariance was valid, else the
        guard's message for the first one that was not (``on_invalid =
        "flag"``); that case's records from then on are NaN.
    names, filter_names : tuple of str or None
        Names of the kept truth and filter states (the ``keep`` sub-block).
    times : ndarray, shape (n_rec,) or None
        Times of the record steps [s].
    update_times : ndarray, shape (n_upd,) or None
        Times of the update steps [s].
    """

    record_steps: np.ndarray
    P_truth: np.ndarray
    P_filter: np.ndarray | None
    gains: np.ndarray | None
    update_steps: np.ndarray
    status: list = field(default_factory=list)
    names: tuple | None = None
    filter_names: tuple | None = None
    times: np.ndarray | None = None
    update_times: np.ndarray | None = None

    def history(self, case: int = 0, *, label: str = ""):
        """Truth history of batch case ``case`` (:class:`~covtool.lincov.history.CovarianceHistory`).

        Raises
        ------
        ValueError
            The batch was run without state names or times.
        """
        from covtool.lincov.history import CovarianceHistory

        if self.names is None or self.times is None:
            raise ValueError("this batch was run without names= and times=: its history has no labels")
        tu = np.zeros(0) if self.update_times is None else self.update_times
        return CovarianceHistory(self.times, self.names, self.P_truth[case], tu, None, label)

    @property
    def failed(self) -> np.ndarray:
        """Boolean mask of the cases flagged by the guard, shape (B,)."""
        return np.array([bool(s) for s in self.status], bool)


#: updates between full symmetrisations of the covariances (the
#: propagation and the unsymmetrised update leave round-off asymmetry only)
SYMMETRIZE_EVERY = 8
#: record steps whose guard is batched into one call (memory: this many B·n² copies)
RECORD_CHECKS = 32


def run_batch(truth: System, P0: np.ndarray, H: np.ndarray, R: np.ndarray, D: np.ndarray,
               update_steps, record_steps, *, filt: System | None = None, Pf0: np.ndarray | None = None,
               Hf: np.ndarray | None = None, Rf: np.ndarray | None = None, q_scale=None,
               gains: np.ndarray | None = None, truth_Q: np.ndarray | None = None,
               filter_Q=None, form: str = "joseph", keep=slice(0, 10), check: bool = True, on_invalid: str = "raise",
               label: str = "batch", cases=None, names=None, filter_names=None, times=None,
               psd_cases=None, scale_case: int | None = None) -> BatchResult:
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
    check : bool
        Guard (:func:`covtool.lincov.kalman.check_covariance`): the inputs
        (P0, R, Φ and Q of every interval, P_f(0), R_f, Φ_f, Q_f, gains) on
        entry, and the full truth and filter covariances of every case at
        every record step and after every ``SYMMETRIZE_EVERY``-th and the
        last update (when they are symmetrised; a message names the time of
        the check and of the previous one).  Cost: a batched Cholesky
        factorisation per check (about 10 % of the shipped sweep's CPU time);
        the record steps' checks are batched :data:`RECORD_CHECKS` at a time
        (and before every update check), so the first failure is reported.
    on_invalid : {"raise", "flag"}
        What a covariance that fails the guard during the run does:
        ``"raise"`` a :class:`NumericalError`; ``"flag"`` the case
        (``BatchResult.status``), record NaN for it from then on and go on
        with the others (sweeps).  Bad inputs always raise.
    label : str
        Names the batch in messages (e.g. ``"sweep of filter B1"``).
    cases : sequence of str, optional
        Names of the B cases in messages.
    names, filter_names : sequence of str, optional
        Truth and filter state names in messages.
    times : ndarray, shape (N+1,), optional
        Grid times [s] in messages (default: step indices).
    psd_cases : ndarray of bool, shape (B,), optional
        Cases whose truth covariance is tested for PSD (default all); the
        others (contributions that may be indefinite, e.g. a budget's
        cross-covariance piece) are tested for finiteness and symmetry.
    scale_case : int, optional
        Normalise the guard's test of every case's truth covariance by the
        σ of this case (e.g. a budget's total, whose contributions the
        other cases are): a contribution must be PSD, and its variances
        non-negative, within ``PSD_TOL`` of the total's σ_i σ_j rather than
        of its own (a contribution of a few sources is rank-deficient and
        its own tiny variances are round-off).

    Returns
    -------
    BatchResult

    Raises
    ------
    NumericalError
        A bad input, or (``on_invalid = "raise"``) the first covariance that
        is not finite, symmetric and PSD, naming the case, time and state.
    """
    run = BatchRun(truth.ev, truth.n, P0, H, R, D, update_steps, record_steps, running=filt is not None, Pf0=Pf0,
                   Hf=Hf, Rf=Rf, q_scale=q_scale, gains=gains, form=form, keep=keep, check=check,
                   on_invalid=on_invalid, label=label, cases=cases, names=names, filter_names=filter_names,
                   times=times, psd_cases=psd_cases, scale_case=scale_case)
    if len(truth.ev) > 1:
        run.advance(truth, filt, truth_Q=truth_Q, filter_Q=filter_Q)
    return run.finish()


class BatchRun:
    """:func:`run_batch` advanced chunk by chunk (streaming in time).

    The cases' full truth covariance P (and the filters' P_f) is carried
    across the chunks, so only one chunk's composed systems are held at a
    time: memory does not grow with the duration.  The updates, the guard
    and the records are those of :func:`run_batch` (which is this class fed
    one chunk), so a streamed run equals the whole-grid run up to the
    round-off of composing Φ and Q_d over intervals split at the chunk
    boundaries.

    Parameters
    ----------
    ev : ndarray of int, shape (K+1,)
        The whole event grid (every update and record step, the first and
        the last step).
    n : int
        Truth states.
    P0, H, R, D, update_steps, record_steps
        As :func:`run_batch`.
    running : bool
        The filters run alongside (``Pf0``, ``Hf``, ``Rf``); otherwise
        fixed ``gains`` are given.
    **kw
        The other keywords of :func:`run_batch` (``Pf0``, ``Hf``, ``Rf``,
        ``q_scale``, ``gains``, ``form``, ``keep``, ``check``,
        ``on_invalid``, ``label``, ``cases``, ``names``, ``filter_names``,
        ``times``, ``psd_cases``, ``scale_case``).

    Raises
    ------
    ValueError
        (:meth:`advance`) a chunk that does not start where the previous one
        ended or whose events are not on ``ev``; (:meth:`finish`) a run
        finished before the end of ``ev``.
    NumericalError
        As :func:`run_batch`.
    """

    _DEFAULTS = dict(Pf0=None, Hf=None, Rf=None, q_scale=None, gains=None, form="joseph", keep=slice(0, 10),
                     check=True, on_invalid="raise", label="batch", cases=None, names=None, filter_names=None,
                     times=None, psd_cases=None, scale_case=None)

    def __init__(self, ev, n: int, P0, H, R, D, update_steps, record_steps, *, running: bool, **kw):
        unknown = set(kw) - set(self._DEFAULTS)
        if unknown:
            raise TypeError(f"BatchRun: unknown keywords {sorted(unknown)}")
        self._gen = _engine(ev, int(n), bool(running), P0, H, R, D, update_steps, record_steps,
                            **{**self._DEFAULTS, **kw})
        next(self._gen)                       # the inputs are checked here, before any chunk
        self._result = None

    def advance(self, truth: System, filt: System | None = None, *, truth_Q=None, filter_Q=None) -> None:
        """Propagate and update every case across one chunk of the event grid.

        Parameters
        ----------
        truth : System
            The truth's composed Φ and Q on the chunk's events
            (``truth.ev[0]`` is where the previous chunk ended).
        filt : System, optional
            The filters' (unscaled), on the same events (running filters).
        truth_Q, filter_Q : optional
            Per-case noise of the chunk's intervals (as :func:`run_batch`).
        """
        if self._result is not None:
            raise ValueError("the batch is finished")
        self._gen.send((truth, filt, truth_Q, filter_Q))

    def finish(self) -> BatchResult:
        """The last event (update, record) and the histories (:class:`BatchResult`)."""
        if self._result is None:
            try:
                self._gen.send(None)
            except StopIteration as stop:
                self._result = stop.value
        return self._result


def _engine(ev, n, running, P0, H, R, D, update_steps, record_steps, *, Pf0, Hf, Rf, q_scale, gains, form, keep,
            check, on_invalid, label, cases, names, filter_names, times, psd_cases, scale_case):
    """The state of :func:`run_batch` across chunks: a generator fed ``(truth, filt, truth_Q, filter_Q)``.

    Primed with ``next``; each chunk sent advances every case over the
    chunk's intervals (updates and records at its events but its last);
    ``None`` ends the run (the last event of ``ev``) and returns the
    :class:`BatchResult` (``StopIteration.value``).
    """
    if on_invalid not in ("raise", "flag"):
        raise ValueError(f"on_invalid must be 'raise' or 'flag', got {on_invalid!r}")
    ev = np.asarray(ev, int)
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
    psd_mask = np.ones(B, bool) if psd_cases is None else np.asarray(psd_cases, bool)

    # the guard's scale groups depend on the names only: formed once, not at every check
    groups_t = scale_groups(names, n)

    def signed(code):
        """The codes a signed piece (``psd_cases`` False) may have: ``np.isin`` of the two, without its overhead."""
        return (code == NOT_PSD) | (code == NEGATIVE_VARIANCE)

    def when(k):
        return time_text(float(times[k])) if times is not None else f"step {k}"

    def case_at(index):
        b = int(index[0]) if len(index) else 0
        return f"(case {cases[b]})" if cases is not None else (f"(case {b})" if B > 1 else "")

    chunk_ev = [ev]                                     # the event grid of the chunk being advanced

    def interval_at(index):
        return f"from {when(int(chunk_ev[0][index[0]]))}"

    if check:
        if P0.ndim == 3:
            st = covariance_status(P0, groups=groups_t)
            bad = ~st.ok & ~(signed(st.code) & ~psd_mask)                                  # signed pieces
            if bad.any():
                b = int(np.flatnonzero(bad)[0])
                raise NumericalError(f"{label} {case_at((b,))}: truth P0: "
                                     f"{st.problem(b, names)}")
        else:
            check_covariance(P0, f"{label}: truth P0", names=names)
        check_covariance(R, f"{label}: true R", at=case_at if np.ndim(R) == 3 else None)
        if running:
            check_covariance(Pf0, f"{label}: filter P_f(0)", names=filter_names, at=case_at)
            check_covariance(Rf, f"{label}: filter R_f", at=case_at)
            if q_scale is not None and not np.all(np.isfinite(q_scale) & (np.asarray(q_scale) >= 0)):
                raise NumericalError(f"{label}: Q_f scale {q_scale!r} is not finite and non-negative")
        elif gains is not None:
            check_finite(gains, f"{label}: fixed gain")
    P = np.broadcast_to(P0, (B, n, n)).copy()
    R = np.broadcast_to(np.asarray(R, float), (B,) + H.shape[:1] * 2).copy()
    if running:
        Pf = np.array(Pf0, float, copy=True)
        nf = Pf.shape[1]
        Rf = np.broadcast_to(np.asarray(Rf, float), (B,) + R.shape[1:]).copy()
        qs = np.ones(B) if q_scale is None else np.asarray(q_scale, float)
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
        groups_f = scale_groups(filter_names, nf)
    out_g = np.empty((B, len(upd), nf, m))
    status = [""] * B
    dead = np.zeros(B, bool)
    checked = [None]                                    # the last event step that passed the guard

    def guard(M, what, k, nm, groups, psd=None, scaled=False):
        """Check the B covariances M (states ``nm``, scale ``groups``); raise or flag the bad live cases."""
        scale = None
        if scaled and scale_case is not None:
            scale = np.sqrt(np.clip(np.diagonal(M[scale_case], axis1=-2, axis2=-1), 0.0, None))
        st = covariance_status(M, scale=scale, groups=groups)
        bad = ~st.ok & ~dead
        if psd is not None:                                            # signed pieces may be indefinite
            bad &= ~(signed(st.code) & ~psd)
        if not bad.any():
            return
        since = f" (it passed the guard at {when(checked[0])})" if checked[0] is not None else ""
        for b in np.flatnonzero(bad):
            msg = (f"{label}{' ' + case_at((b,)) if case_at((b,)) else ''}: {what} at {when(k)}{since}: "
                   f"{st.problem(b, nm)}")
            if on_invalid == "raise":
                raise NumericalError(msg)
            status[b] = msg
        dead[bad] = True
        # placeholders that keep the batch computable; the flagged cases record NaN from now on
        P[bad] = np.eye(n)
        if running:
            Pf[bad] = np.eye(nf)

    # the record-step guard is deferred and batched over up to RECORD_CHECKS records (one call instead of one per
    # record); it is flushed before every update guard, so the first failure is still the one reported.  The
    # records' symmetrised covariances are written straight into these stacks (none is stacked at the flush)
    pending = []                                        # (record index, step); the covariances in pend_t, pend_f
    n_pend = min(RECORD_CHECKS, len(rec)) if check else 0
    pend_t = np.empty((n_pend, B, n, n))
    pend_f = np.empty((n_pend, B, nf, nf)) if running else None

    def flush():
        if not pending:
            return
        steps = [k_ for _, k_ in pending]
        PT = pend_t[:len(pending)]
        scale = None
        if scale_case is not None:
            scale = np.sqrt(np.clip(np.diagonal(PT[:, scale_case], axis1=-2, axis2=-1), 0.0, None))[:, None, :]
        stt = covariance_status(PT, scale=scale, groups=groups_t)
        badt = ~stt.ok & ~(signed(stt.code) & ~psd_mask)
        badf = None
        if running:
            stf = covariance_status(pend_f[:len(pending)], groups=groups_f)
            badf = ~stf.ok
        for j, (rj, k_) in enumerate(pending):
            for b in range(B):
                if dead[b]:
                    continue
                if badt[j, b]:
                    what, prob = "truth", stt.problem((j, b), names)
                elif badf is not None and badf[j, b]:
                    what, prob = "filter", stf.problem((j, b), filter_names)
                else:
                    continue
                since = f" (it passed the guard at {when(checked[0])})" if checked[0] is not None else ""
                msg = (f"{label}{' ' + case_at((b,)) if case_at((b,)) else ''}: {what} at {when(k_)}{since}: {prob}")
                if on_invalid == "raise":
                    raise NumericalError(msg)
                status[b] = msg
                dead[b] = True
                out_t[b, rj:] = np.nan
                if running:
                    out_f[b, rj:] = np.nan
                P[b] = np.eye(n)                         # placeholders that keep the batch computable
                if running:
                    Pf[b] = np.eye(nf)
            checked[0] = steps[j]
        pending.clear()

    # the recorded sub-blocks, indexed once: a slice when keep is one (a view, no gather)
    if isinstance(keep, slice):
        kt = kf = (slice(None), keep, keep)
    else:
        kt = (slice(None), idx[:, None], idx[None, :])
        kf = (slice(None), fidx[:, None], fidx[None, :]) if running else None
    ui = ri = 0

    def event(k):
        """The update (eq (7), (8)/Joseph, (16)) and the record at event step ``k``."""
        nonlocal P, Pf, ui, ri
        if k in upd_set:
            # symmetrised (and then guarded) every SYMMETRIZE_EVERY updates, at the last one and at a record
            # step: the guard tests symmetry relative to σ_i σ_j, which a ZUPT shrinks by orders of magnitude,
            # so the round-off asymmetry of the unsymmetrised steps would fail it in between
            sym = ui % SYMMETRIZE_EVERY == SYMMETRIZE_EVERY - 1 or ui == len(upd) - 1 or k in rec_set
            if running:
                HPf = Hf @ Pf                                             # (B, m, nf)
                S = HPf @ Hf.T + Rf                                       # (B, m, m)
                try:
                    K = gain_from_innovation(S, HPf)                      # eq (7), (B, nf, m)
                except np.linalg.LinAlgError:
                    raise NumericalError(f"{label}: innovation covariance H P_f Hᵀ + R_f is singular at "
                                         f"{when(k)}") from None
                if form == "joseph":
                    Pf = _joseph(Pf, K, Hf, Rf, symmetrize=sym, HP=HPf)
                else:
                    Pf = standard_update(Pf, K, HPf, sym=sym)             # eq (8)
            else:
                K = gains[:, ui]
            out_g[:, ui] = K
            HP = H @ P
            if sel is not None:
                P = _joseph(P, K, H, R, sel, symmetrize=sym, HP=HP)         # eq (16), D a selection
            else:
                P = _joseph(P, D @ K, H, R, symmetrize=sym, HP=HP)          # eq (16)
            if check and sym:
                flush()
                guard(P, "truth after the eq (16) update", k, names, groups_t, psd_mask, scaled=True)
                if running:
                    guard(Pf, f"filter after the {form} update", k, filter_names, groups_f)
                checked[0] = k
            ui += 1
        elif check and k in rec_set:
            # round-off asymmetry of the sandwiches (see above); P, P_f are then the slots, guarded by flush()
            P = symmetrize(P, out=pend_t[len(pending)])
            if running:
                Pf = symmetrize(Pf, out=pend_f[len(pending)])
            pending.append((ri, k))
            if len(pending) >= RECORD_CHECKS:
                flush()
        if k in rec_set:
            out_t[:, ri] = symmetrize(P[kt])
            if running:
                out_f[:, ri] = symmetrize(Pf[kf])
            if dead.any():
                out_t[dead, ri] = np.nan
                if running:
                    out_f[dead, ri] = np.nan
            ri += 1

    if not running:
        Pf = None
    done = int(ev[0])                                   # the step the propagation has reached
    with np.errstate(over="ignore", invalid="ignore"):      # blow-ups are reported by the guard
        while True:
            item = yield
            if item is None:
                break
            truth, filt, truth_Q, filter_Q = item
            cev = np.asarray(truth.ev, int)
            chunk_ev[0] = cev
            if cev.size < 2 or int(cev[0]) != done or cev[-1] > ev[-1] or not np.all(np.isin(cev, ev)):
                raise ValueError(f"chunk from step {int(cev[0]) if cev.size else '?'} does not continue the event "
                                 f"grid at step {done}")
            if running and not np.array_equal(filt.ev, cev):
                raise ValueError("truth and filter event grids differ")
            if check:
                check_finite(truth.Phi, f"{label}: truth Φ of the interval", names=names,
                             times=[times[k] for k in cev] if times is not None else None)
                if truth_Q is None:
                    check_covariance(truth.Q, f"{label}: truth Q_d of the interval", names=names,
                                     at=interval_at)
                if running:
                    check_finite(filt.Phi, f"{label}: filter Φ_f of the interval", names=filter_names)
                    check_covariance(filt.Q, f"{label}: filter Q_f of the interval", names=filter_names,
                                     at=interval_at)
            # random-constant states (identity Φ rows): only the dynamic blocks are propagated (exact)
            tdyn = truth.dynamic
            fdyn = filt.dynamic if running else None
            for i, k in enumerate(cev[:-1]):
                event(int(k))
                # eq (15) and (6a); symmetry is restored every SYMMETRIZE_EVERY updates and when recorded
                P = sandwich(truth.Phi[i], P, tdyn)
                if truth_Q is None:
                    P += truth.Q[i]
                else:
                    Qi = truth_Q[:, i]
                    if check:
                        # per-case noise (a budget's per-source Q_d): relative to the total's, as the covariances
                        scale = (None if scale_case is None else
                                 np.sqrt(np.clip(np.diagonal(Qi[scale_case], axis1=-2, axis2=-1), 0.0, None)))
                        st = covariance_status(Qi, scale=scale, groups=groups_t)
                        if not st.ok.all():
                            b = int(np.flatnonzero(~st.ok)[0])
                            raise NumericalError(f"{label} {case_at((b,))}: truth Q_d of the interval from "
                                                 f"{when(int(k))}: {st.problem(b, names)}")
                    P += Qi
                if running:
                    Pf = sandwich(filt.Phi[i], Pf, fdyn)
                    Pf += qs[:, None, None] * (filt.Q[i] if filter_Q is None else filter_Q[:, i])
            done = int(cev[-1])
        if done != int(ev[-1]):
            raise ValueError(f"the batch was finished at step {done}, before the end of its event grid "
                             f"(step {int(ev[-1])})")
        event(int(ev[-1]))
    if check:
        flush()
    out_g[dead] = np.nan
    kept = lambda nm, ix: None if nm is None else tuple(np.asarray(nm, object)[ix])  # noqa: E731
    return BatchResult(np.array(rec), out_t, out_f, out_g if upd else None, np.array(upd), status,
                       names=kept(names, idx), filter_names=kept(filter_names, fidx) if out_f is not None else None,
                       times=None if times is None else np.asarray(times, float)[np.array(rec, int)],
                       update_times=None if times is None else np.asarray(times, float)[np.array(upd, int)])
