"""Step-by-step covariance propagation: pure INS and the truth under a filter's gains.

The reference implementation of seed 002, eq (6)–(8), (15)–(16), one step at
a time; the batched engine (:mod:`covtool.lincov.batch`) is tested against it.

Time grid: ``t_0 … t_N``; ``Φ_k, Q_k`` propagate ``t_k → t_{k+1}``.  A
measurement flagged at ``t_k`` is processed at ``t_k`` before propagating on.
Histories store the *posterior* covariance at each grid time (and the prior at
update times separately, for the saw-tooth plots).

Pure numeric core: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from covtool.errors import NumericalError, SystemCheckError
from covtool.lincov.kalman import (check_covariance, check_system, covariance_status, filter_update,
                                   kalman_gain, running_scale, scale_groups, symmetrize, time_text,
                                   truth_update)


def propagate(Phi: np.ndarray, Qd: np.ndarray, P0: np.ndarray, *, check: bool = True, label: str = "pure INS",
              names=None, times=None, system_checked: bool = False, record=None, keep: int | None = None,
              all_steps: int | None = None):
    """Pure propagation ``P_{k+1} = Φ_k P_k Φ_kᵀ + Q_k`` (seed 002, eq (15)).

    Parameters
    ----------
    Phi, Qd : ndarray, shape (N, n, n)
    P0 : ndarray, shape (n, n)
    check : bool
        Guard the inputs (P0, Φ, Q_d) and every covariance of the history
        (:func:`check_covariance`).
    label : str
        Names the run in error messages.
    names : sequence of str, optional
        State names, for error messages.
    times : ndarray, shape (N+1,), optional
        Grid times, for error messages. [s]
    system_checked : bool
        Φ and Q_d were already guarded by the caller (:func:`check_system`,
        e.g. once for a truth shared by several runs); P0 and the history
        are still checked.
    record : array_like of int, optional
        Grid indices to return (default: all ``N + 1``).  Every covariance
        is still guarded, in blocks of :data:`GUARD_STEPS`, with the same
        running scale as the whole history's; the memory does not grow with
        N × n² (``Phi``, ``Qd`` may be streamed,
        :class:`covtool.lincov.streamed.StreamedSystem`).
    keep : int, optional
        Return only the leading ``keep`` states (the navigation block:
        ``keep = 10``) of the recorded steps; every covariance is still
        guarded whole.  Implies ``record`` (default: every step).
    all_steps : int, optional
        Also return the leading ``all_steps`` states of *every* step (the
        navigation block, ``all_steps = 10``, for metrics at every step
        beside a full covariance at the record steps).  Implies ``record``.

    Returns
    -------
    ndarray, shape (N+1, n, n), or (len(unique(record)), k, k) with ``k = keep or n``
        With ``all_steps``: that array and the ``(N+1, all_steps, all_steps)`` one.

    Raises
    ------
    ValueError
        A record step outside ``0 … N``, or ``keep`` or ``all_steps`` below 1.

    Raises
    ------
    NumericalError
        An input or a propagated covariance is not finite, symmetric and
        PSD; the message gives the first time and the state.
    """
    if check:
        check_system(label, Phi=None if system_checked else Phi, Qd=None if system_checked else Qd, P0=P0,
                     names=names, times=times)
    N, n, _ = Phi.shape
    if record is not None or keep is not None or all_steps is not None:
        rec, _ = record_plan(np.arange(N + 1) if record is None else record, N, label, keep=keep,
                             all_steps=all_steps)
        out, every = _propagate_recorded(Phi, Qd, P0, rec, n if keep is None else min(int(keep), n),
                                         None if all_steps is None else min(int(all_steps), n), check=check,
                                         label=label, names=names, times=times)
        return out if all_steps is None else (out, every)
    out = np.empty((N + 1, n, n))
    P = out[0] = symmetrize(np.asarray(P0, float))
    with np.errstate(over="ignore", invalid="ignore"):      # a blow-up is reported by the guard below
        for k in range(N):
            P = Phi[k] @ P @ Phi[k].T + Qd[k]
            out[k + 1] = P = symmetrize(P)
    if check:
        check_covariance(out, label, names=names, times=times, scale=running_scale(out))
    return out


#: covariances of a recorded pure propagation guarded at once (:func:`propagate` with ``record``)
GUARD_STEPS = 512


def record_plan(record, N: int, label: str, **states) -> tuple[np.ndarray, dict]:
    """The steps a recorded run keeps, checked: ``(steps, slot)``, ``slot[k]`` the row of grid step ``k``.

    The one check of every recorded run (:func:`propagate`,
    :func:`propagate_with_filter`, :meth:`covtool.validation.feedback.FeedbackFilter.design`).

    Parameters
    ----------
    record : array_like of int
        Grid indices (any order, repeats allowed).
    N : int
        Steps of the grid (indices ``0 … N``).
    label : str
        Names the run in the messages.
    **states : int or None
        State counts the run keeps (``keep``, ``all_steps``): each at least 1.

    Raises
    ------
    ValueError
        A step outside ``0 … N``, or a state count below 1.
    """
    rec = np.unique(np.asarray(record, int))
    if rec.size and (rec[0] < 0 or rec[-1] > N):
        raise ValueError(f"{label}: record steps must lie in 0 … {N}, got {rec[0]} … {rec[-1]}")
    for what, v in states.items():
        if v is not None and int(v) < 1:
            raise ValueError(f"{label}: {what} must be a positive number of states, got {v}")
    return rec, {int(k): i for i, k in enumerate(rec)}


def _propagate_recorded(Phi, Qd, P0, rec, k, k_all, *, check, label, names, times):
    """:func:`propagate` keeping the leading ``k`` states of the steps ``rec`` (and the leading ``k_all`` of
    every step, unless None); every step guarded, in blocks.  Returns ``(out, every)``."""
    N, n, _ = Phi.shape
    out = np.empty((rec.size, k, k))
    every = None if k_all is None else np.empty((N + 1, k_all, k_all))
    slot = {int(k): i for i, k in enumerate(rec)}
    block = np.empty((min(GUARD_STEPS, N + 1), n, n))
    sigma = np.zeros(n)                                      # the running scale carried between blocks
    t = None if times is None else np.asarray(times, float)

    def flush(k0, m):
        nonlocal sigma
        if not check or m == 0:
            return
        B = block[:m]
        scale = np.maximum(running_scale(B), sigma)
        sigma = scale[-1]
        check_covariance(B, label, names=names, times=None if t is None else t[k0:k0 + m], scale=scale)

    P = symmetrize(np.asarray(P0, float))
    j, k0 = 0, 0
    with np.errstate(over="ignore", invalid="ignore"):      # a blow-up is reported by the guard
        for i in range(N + 1):
            if i:
                P = symmetrize(Phi[i - 1] @ P @ Phi[i - 1].T + Qd[i - 1])
            block[j] = P
            if i in slot:
                out[slot[i]] = P[:k, :k]
            if every is not None:
                every[i] = P[:k_all, :k_all]
            j += 1
            if j == block.shape[0]:
                flush(k0, j)
                j, k0 = 0, i + 1
    flush(k0, j)
    return out, every


@dataclass
class FilterRun:
    """Histories of a truth-under-filter covariance run.

    Attributes
    ----------
    P_truth : ndarray, shape (N+1, n, n)
        Truth covariance (posterior at update times), eq (15)–(16); with
        ``record_steps``, shape (J, n, n) at those steps.
    P_filter : ndarray, shape (N+1, n_f, n_f)
        The filter's own covariance, eq (6a)–(8); (J, n_f, n_f) with
        ``record_steps``.
    prior_truth, prior_filter : dict of int to ndarray
        Priors at the update steps (empty for a recorded run: checked, not kept).
    record_steps : ndarray of int, shape (J,), or None
        Grid indices of the recorded rows (None: every step).
    every_truth, every_filter : ndarray, shape (N+1, a, a), or None
        The leading ``a`` states (the navigation block) of every step.
    gains : dict of int to ndarray, shape (n_f, m)
        Filter gains at the update steps, eq (7).
    times : ndarray, shape (N+1,) or None
        Time of each step [s] (``None``: steps of 1 s).
    names, filter_names : tuple of str or None
        Truth and filter state names (rows of ``P_truth``, ``P_filter``).
    """

    P_truth: np.ndarray
    P_filter: np.ndarray
    prior_truth: dict
    prior_filter: dict
    gains: dict
    times: np.ndarray | None = None
    names: tuple | None = None
    filter_names: tuple | None = None
    #: grid indices of the rows of ``P_truth``, ``P_filter`` (None: every step); with
    #: :func:`propagate_with_filter`'s ``record``
    record_steps: np.ndarray | None = None
    #: the leading ``all_steps`` states of every step, shape (N+1, a, a) (``all_steps``), else None
    every_truth: np.ndarray | None = None
    every_filter: np.ndarray | None = None

    def _times(self):
        return np.arange(self.P_truth.shape[0], dtype=float) if self.times is None else np.asarray(self.times)

    def _history(self, P, priors, names, label):
        from covtool.lincov.history import CovarianceHistory

        steps = sorted(priors)
        t = self._times()
        names = tuple(names) if names is not None else tuple(f"x{i}" for i in range(P.shape[1]))
        prior = np.array([priors[k] for k in steps]) if steps else np.zeros((0,) + P.shape[1:])
        return CovarianceHistory(t, names, P, t[steps] if steps else np.zeros(0), prior, label)

    def _whole(self, what: str) -> None:
        if self.record_steps is not None:
            raise ValueError(f"{what}: a recorded run keeps the covariances of record_steps only (and the "
                             "leading states of every step in every_truth, every_filter), not a history")

    def truth_history(self):
        """The truth covariance as a :class:`~covtool.lincov.history.CovarianceHistory` (priors kept).

        Raises
        ------
        ValueError
            A recorded run (``record_steps``): it holds no history.
        """
        self._whole("truth_history")
        return self._history(self.P_truth, self.prior_truth, self.names, "truth")

    def filter_history(self):
        """The filter's own covariance as a :class:`~covtool.lincov.history.CovarianceHistory`.

        Raises
        ------
        ValueError
            A recorded run (``record_steps``): it holds no history.
        """
        self._whole("filter_history")
        return self._history(self.P_filter, self.prior_filter, self.filter_names, "filter-claimed")

    def gain_table(self):
        """Gains with their times and names.

        Returns
        -------
        dict
            ``{"times": ndarray (U,) [s], "filter_names": tuple (n_f),
            "K": ndarray (U, n_f, m)}``, in time order.
        """
        steps = sorted(self.gains)
        K = np.array([self.gains[k] for k in steps]) if steps else np.zeros((0, self.P_filter.shape[1], 0))
        return {"times": self._times()[steps] if steps else np.zeros(0), "filter_names": self.filter_names, "K": K}


def propagate_with_filter(Phi, Qd, P0, Phi_f, Qd_f, Pf0, H, Hf, D, R, update_steps,
                          *, Rf=None, form: str = "joseph", check: bool = True, label: str = "filter",
                          times=None, names=None, filter_names=None, system_checked: bool = False,
                          record=None, all_steps: int | None = None) -> FilterRun:
    """Truth covariance under a (reduced) filter's gains with feedback.

    Parameters
    ----------
    Phi, Qd : ndarray, shape (N, n, n)
        Truth transition and noise (eq (15)).
    P0 : ndarray, shape (n, n)
    Phi_f, Qd_f : ndarray, shape (N, n_f, n_f)
        The filter's own model (eq (6a)–(6d)).
    Pf0 : ndarray, shape (n_f, n_f)
    H : ndarray, shape (m, n)
        Truth measurement matrix (velocity-error rows for ZUPT).
    Hf : ndarray, shape (m, n_f)
        The filter's measurement matrix.
    D : ndarray, shape (n, n_f)
        Map of filter states onto truth states (eq (10)).
    R : ndarray, shape (m, m)
        True measurement noise (enters eq (16)).
    update_steps : iterable of int
        Grid indices k at which a measurement is processed.
    Rf : ndarray, shape (m, m), optional
        Measurement noise the filter assumes (eq (7)); default ``R``.
    form : {"joseph", "standard"}
        Filter covariance update form (eq (8) is ``"standard"``).
    check : bool
        Guard the inputs (P0, P_f(0), Φ, Q_d, Φ_f, Q_f, R, R_f) and every
        truth and filter covariance, prior and posterior, at every step
        (:func:`check_covariance`).
    label : str
        Names the filter in error messages.
    times : ndarray, shape (N+1,), optional
        Grid times, for error messages.
    names, filter_names : sequence of str, optional
        Truth and filter state names, for error messages.
    system_checked : bool
        Φ, Q_d, Φ_f and Q_f were already guarded by the caller
        (:func:`check_system`, e.g. once for a truth shared by several
        filters); P0, P_f(0), R, R_f and every covariance are still checked.
        Required with streamed systems (:class:`covtool.lincov.streamed.StreamedSystem`,
        guarded as they are made).
    record : array_like of int, optional
        Grid indices whose full truth and filter covariances are returned
        (``P_truth``, ``P_filter`` of shape (J, ·, ·)); every covariance,
        prior and posterior, is still guarded, in blocks of
        :data:`GUARD_STEPS`, and the priors are not kept: the memory does
        not grow with N × n² (``Phi``, ``Qd``, ``Phi_f``, ``Qd_f`` may be
        streamed).
    all_steps : int, optional
        Also keep the leading ``all_steps`` states of every step
        (``every_truth``, ``every_filter``: the navigation block,
        ``all_steps = 10``).  Implies ``record`` (default: none).

    Returns
    -------
    FilterRun

    Raises
    ------
    NumericalError
        The first input or covariance that is not finite, symmetric and
        PSD, with the time and the state (the same message with or without
        ``record``); a gain that cannot be formed.
    SystemCheckError
        A streamed system's chunk failed its own guard as it was made (its
        message names the step), passed through unchanged.
    ValueError
        ``record`` steps outside ``0 … N``, ``all_steps`` below 1, or a
        streamed system without ``system_checked``.

    Notes
    -----
    Between measurements the feedback filter's estimate is zero (eq (9)–(10)),
    so only covariances are propagated.  At a measurement the filter computes
    ``K`` from its own ``P_f`` (eq (7)), updates ``P_f`` (eq (8) or Joseph), and
    the truth is corrected by eq (16): only the truth states the filter
    estimates (rows of ``D``) are reset; unmodelled states keep running.
    The histories (every step) and the priors are checked once, batched,
    after the loop (with ``record``, a block of :data:`GUARD_STEPS` steps at a
    time); a blow-up in the loop is reported at the first step where a
    covariance went bad.  The guard costs about 12 % of the flagship's CPU
    time (studies/zupt_filter_order.toml).
    """
    N, n, _ = Phi.shape
    nf = Phi_f.shape[1]
    Rf = R if Rf is None else Rf
    if check:
        sys_ = {} if system_checked else {"truth": (Phi, Qd), "filter": (Phi_f, Qd_f)}
        check_system(f"{label} (truth)", *sys_.get("truth", ()), P0=P0, R=R, names=names, times=times)
        check_system(f"{label} (filter)", *sys_.get("filter", ()), P0=Pf0, R=Rf, names=filter_names, times=times)
    if record is not None or all_steps is not None:
        return _filter_recorded(Phi, Qd, P0, Phi_f, Qd_f, Pf0, H, Hf, D, R, Rf, update_steps, form, check, label,
                                times, names, filter_names, record, all_steps)
    PT = np.full((N + 1, n, n), np.nan)
    PF = np.full((N + 1, nf, nf), np.nan)
    prior_t, prior_f, gains = {}, {}, {}

    def keep(k, stage, P, Pf, K):
        if stage == "prior":
            prior_t[k], prior_f[k] = P, Pf
        else:
            PT[k], PF[k] = P, Pf
            if K is not None:
                gains[k] = K

    def fail(k, exc):
        if check:
            _check_run(label, PT[:k], PF[:k], prior_t, prior_f, form, names, filter_names, times)
        raise NumericalError(f"{label}: gain at {_when(k, times)}: {exc}") from None

    part = ((H, R, Hf, Rf),)
    filter_loop(N, P0, Pf0, lambda k, P: Phi[k] @ P @ Phi[k].T + Qd[k],
                lambda k, Pf: Phi_f[k] @ Pf @ Phi_f[k].T + Qd_f[k],
                {int(k): part for k in update_steps}, D, form, keep, fail)
    if check:
        _check_run(label, PT, PF, prior_t, prior_f, form, names, filter_names, times)
    return FilterRun(PT, PF, prior_t, prior_f, gains, None if times is None else np.asarray(times, float),
                     None if names is None else tuple(names),
                     None if filter_names is None else tuple(filter_names))


def _filter_recorded(Phi, Qd, P0, Phi_f, Qd_f, Pf0, H, Hf, D, R, Rf, update_steps, form, check, label, times,
                     names, filter_names, record, all_steps) -> FilterRun:
    """:func:`propagate_with_filter` keeping the covariances of the steps ``record`` (and the leading
    ``all_steps`` states of every step), every covariance guarded a block of :data:`GUARD_STEPS` at a time."""
    N, n, _ = Phi.shape
    nf = Phi_f.shape[1]
    rec, slot = record_plan([] if record is None else record, N, label, all_steps=all_steps)
    out_t, out_f = np.empty((rec.size, n, n)), np.empty((rec.size, nf, nf))
    a_t = a_f = None
    every_t = every_f = None
    if all_steps is not None:
        a_t, a_f = min(int(all_steps), n), min(int(all_steps), nf)
        every_t, every_f = np.empty((N + 1, a_t, a_t)), np.empty((N + 1, a_f, a_f))
    m = min(GUARD_STEPS, N + 1)
    BT, BF = np.full((m, n, n), np.nan), np.full((m, nf, nf), np.nan)
    prior_t, prior_f, gains = {}, {}, {}
    block = {"k0": 0, "j": 0}

    def flush(inside: bool = False):
        j, k0 = block["j"], block["k0"]
        if check and j:
            try:
                _check_run(label, BT[:j], BF[:j], prior_t, prior_f, form, names, filter_names, times, first=k0)
            except NumericalError as exc:
                if inside:
                    raise _BlockFailed(exc) from None
                raise
        prior_t.clear()
        prior_f.clear()
        block["k0"], block["j"] = k0 + j, 0

    def keep(k, stage, P, Pf, K):
        if stage == "prior":
            prior_t[k - block["k0"]], prior_f[k - block["k0"]] = P, Pf
            return
        j = block["j"]
        BT[j], BF[j] = P, Pf
        if K is not None:
            gains[k] = K
        if k in slot:
            out_t[slot[k]], out_f[slot[k]] = P, Pf
        if every_t is not None:
            every_t[k], every_f[k] = P[:a_t, :a_t], Pf[:a_f, :a_f]
        block["j"] = j + 1
        if block["j"] == m:
            flush(inside=True)

    def fail(k, exc):
        flush_to = k - block["k0"]
        if check:
            _check_run(label, BT[:flush_to], BF[:flush_to], prior_t, prior_f, form, names, filter_names, times,
                       first=block["k0"])
        raise NumericalError(f"{label}: gain at {_when(k, times)}: {exc}") from None

    part = ((H, R, Hf, Rf),)
    try:
        filter_loop(N, P0, Pf0, lambda k, P: Phi[k] @ P @ Phi[k].T + Qd[k],
                    lambda k, Pf: Phi_f[k] @ Pf @ Phi_f[k].T + Qd_f[k],
                    {int(k): part for k in update_steps}, D, form, keep, fail)
    except _BlockFailed as failed:       # a block's guard inside the loop: its own message, not a gain's
        raise failed.error from None
    flush()
    # a recorded run keeps its grid's times (steps of 1 s when none are given): its rows are record_steps
    tt = np.arange(N + 1, dtype=float) if times is None else np.asarray(times, float)
    return FilterRun(out_t, out_f, {}, {}, gains, tt, None if names is None else tuple(names),
                     None if filter_names is None else tuple(filter_names), rec, every_t, every_f)


class _BlockFailed(Exception):
    """A recorded run's block guard failed inside :func:`filter_loop` (carries the guard's error).

    Not a :class:`NumericalError`, so the loop does not take it for a gain that cannot be formed.
    """

    def __init__(self, error: NumericalError):
        super().__init__(str(error))
        self.error = error


def filter_loop(N: int, P0, Pf0, step_truth, step_filter, updates: dict, D, form: str, on_state, on_fail) -> None:
    """The one truth-under-filter loop with a measurement hook.

    Every truth-under-filter run (ZUPT, :func:`propagate_with_filter`, and
    the scheduled general measurements of :mod:`covtool.lincov.aided`)
    goes through this loop; callers supply the propagation, the updates
    and what to keep.

    Parameters
    ----------
    N : int
        Number of steps (grid indices ``0 … N``).
    P0 : ndarray, shape (n, n)
        Initial truth covariance.
    Pf0 : ndarray, shape (n_f, n_f)
        The filter's initial covariance.
    step_truth, step_filter : callable ``(k, P) -> P``
        Propagation ``t_k → t_{k+1}`` of the truth (eq (15)) and of the
        filter's own covariance (eq (6a)); symmetrised here.
    updates : dict of int to sequence of (H, R, Hf, Rf)
        The measurement events: at grid index k, the parts processed one
        after the other (one part: a stacked update).  ``H`` (m, n), ``R``
        (m, m): truth matrix and true noise (eq (16)); ``Hf`` (m, n_f),
        ``Rf`` (m, m): what the filter uses (eq (7)).
    D : ndarray, shape (n, n_f)
        Filter states onto truth states (eq (10)).
    form : {"joseph", "standard"}
        Filter covariance update (eq (8) is ``"standard"``).
    on_state : callable ``(k, stage, P, Pf, K)``
        Called with ``stage = "prior"`` before an update (``K`` None) and
        ``"posterior"`` after the update or at a step without one (``K``
        the gains, shape (n_f, m), or None).
    on_fail : callable ``(k, exc)``
        Called when a gain cannot be formed (:class:`NumericalError` from
        :func:`kalman_gain`); must raise.

    Notes
    -----
    Between measurements the feedback filter's estimate is zero (eq (9)–(10)),
    so only covariances are propagated.  At a measurement the filter computes
    ``K`` from its own ``P_f`` (eq (7)), updates ``P_f`` (eq (8) or Joseph), and
    the truth is corrected by eq (16): only the truth states the filter
    estimates (rows of ``D``) are reset; unmodelled states keep running.
    Overflow is not raised here: the callers' guards report the first bad
    covariance.
    """
    P = symmetrize(np.asarray(P0, float))
    Pf = symmetrize(np.asarray(Pf0, float))
    k = 0
    try:
        with np.errstate(over="ignore", invalid="ignore"):   # a blow-up is reported by the guard
            for k in range(N + 1):
                parts = updates.get(k)
                K = None
                if parts:
                    on_state(k, "prior", P, Pf, None)
                    Ks = []
                    for H, R, Hf, Rf in parts:
                        Kp = kalman_gain(Pf, Hf, Rf)
                        Pf = filter_update(Pf, Kp, Hf, Rf, form)
                        P = truth_update(P, D, Kp, H, R)
                        Ks.append(Kp)
                    K = Ks[0] if len(Ks) == 1 else np.hstack(Ks)
                on_state(k, "posterior", P, Pf, K)
                if k < N:
                    P = symmetrize(step_truth(k, P))
                    Pf = symmetrize(step_filter(k, Pf))
    except SystemCheckError:
        raise                                   # a streamed system's own guard: its message names the step
    except NumericalError as exc:
        on_fail(k, exc)
        raise


def _when(k, times):
    return time_text(float(times[k])) if times is not None else f"step {k}"


def _check_run(label, PT, PF, prior_t, prior_f, form, names, filter_names, times, first: int = 0):
    """Check a reference run's histories and priors; raise for the earliest bad one.

    ``PT[i]``, ``PF[i]`` and ``prior_*[i]`` are those of grid step ``first + i`` (a block of a recorded run).
    """
    stages = []
    steps = np.array(sorted(prior_t), int)
    for hist, priors, what, nm in ((PT, prior_t, "truth", names),
                                   (PF, prior_f, "filter", filter_names)):
        st = covariance_status(hist, groups=scale_groups(nm, hist.shape[-1]))
        bad = np.flatnonzero(~st.ok)
        if bad.size:
            k = int(bad[0])
            step = (f"after the {'eq (16)' if nm is names else form} update" if k in prior_t
                    else "after the propagation")
            stages.append((k, 1, f"{label}: {what} {step} at {_when(first + k, times)}: {st.problem(k, nm)}"))
        if steps.size:
            sp = covariance_status(np.stack([priors[int(s)] for s in steps]), groups=scale_groups(nm, hist.shape[-1]))
            bad = np.flatnonzero(~sp.ok)
            if bad.size:
                k = int(steps[bad[0]])
                stages.append((k, 0, f"{label}: {what} before the update (prior) at {_when(first + k, times)}: "
                                     f"{sp.problem(int(bad[0]), nm)}"))
    if stages:
        raise NumericalError(min(stages)[2])
