"""Truth under a filter's gains with general scheduled measurements (issue 15).

Generalises the ZUPT run of :func:`covtool.lincov.reference.propagate_with_filter`
(seed 002, eq (6)–(8), (15)–(16)) to updates whose H, R and dimension change
from one update to the next, and to measurements with their own error states
(:mod:`covtool.lincov.measurements`):

* the truth state is ``[x_INS (n₀); e (n_e)]``: the INS truth model and the
  measurements' error states, each a scalar process independent of the INS
  (random constant, Gauss–Markov, random walk), propagated exactly
  (:func:`covtool.lincov.discretize.scalar.transition`);
* the filter state is ``[x_f (n_f0); e_f]``: a reduced filter keeps, by
  name, any subset of the measurement-error states, like any other state;
  ``D`` maps filter states onto truth states (eq (10));
* at an update the truth H (:meth:`Measurement.jacobian`, including the
  error-state columns) and the true R enter eq (16); the filter uses
  ``H_f = H D`` and its own R_f, widened by the variance of every dropped
  measurement-error state it sees (:func:`build_epochs`).

Several measurements at one epoch are **stacked** (one update, block-
diagonal R).  Processing them one after the other gives the same truth and
filter covariances whenever ``H_f = H D`` and R_f is block-diagonal across
kinds: after the first feedback correction ``x ← x − D K₁ z₁`` the second
residual is ``z₂ − H₂ D x̂₁ = z₂ − H_f2 x̂₁``, the residual of the stacked
filter.  ``sequential=True`` does it that way; the tests compare the two.

Pure numeric core: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from covtool.errors import NumericalError
from covtool.lincov.kalman import check_system, covariance_status, scale_groups, symmetrize, time_text
from covtool.lincov.measurements import place, transition
from covtool.lincov.measurements.base import nav_point
from covtool.lincov.reference import filter_loop


@dataclass
class Epoch:
    """The stacked update at one grid step.

    Attributes
    ----------
    step : int
        Grid index.
    H : ndarray, shape (m, n)
        Truth measurement matrix over the augmented truth states.
    R : ndarray, shape (m, m)
        True measurement noise (eq (16)).
    Hf : ndarray, shape (m, n_f)
        The filter's measurement matrix (``H D``).
    Rf : ndarray, shape (m, m)
        Noise the filter assumes (eq (7)), with its dropped error states.
    rows : tuple of (str, slice)
        The rows of each measurement (for sequential processing).
    """

    step: int
    H: np.ndarray
    R: np.ndarray
    Hf: np.ndarray
    Rf: np.ndarray
    rows: tuple


def error_processes(states, dt_steps) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(φ, q_d, P0)`` of the measurement-error states on a grid.

    Parameters
    ----------
    states : sequence of covtool.lincov.model.spec.State
    dt_steps : ndarray, shape (N,)
        Step lengths. [s]

    Returns
    -------
    phi, qd : ndarray, shape (N, n_e)
        Exact scalar transition and noise of each state per step.
    P0 : ndarray, shape (n_e, n_e)
        ``diag σ²``.
    """
    dt_steps = np.asarray(dt_steps, float)
    phi = np.ones((dt_steps.size, len(states)))
    qd = np.zeros((dt_steps.size, len(states)))
    for j, s in enumerate(states):
        pairs = {float(d): transition(s, float(d)) for d in np.unique(dt_steps)}
        phi[:, j] = [pairs[float(d)][0] for d in dt_steps]
        qd[:, j] = [pairs[float(d)][1] for d in dt_steps]
    return phi, qd, np.diag([s.sigma**2 for s in states])


def augment(P0: np.ndarray, D0: np.ndarray, states, kept) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Truth P0, filter P_f(0)'s error block and D over ``[x; e]``.

    Parameters
    ----------
    P0 : ndarray, shape (n₀, n₀)
        INS truth initial covariance.
    D0 : ndarray, shape (n₀, n_f0)
        The filter's map onto the INS truth (eq (10)).
    states : sequence of State
        The measurement-error states appended to the truth (order kept).
    kept : sequence of str
        The error states the filter keeps (a subset of ``states`` by name).

    Returns
    -------
    P0_aug : ndarray, shape (n₀ + n_e, n₀ + n_e)
    Pf0_err : ndarray, shape (n_fe, n_fe)
        ``diag σ²`` of the kept error states (the filter's initial belief).
    D : ndarray, shape (n₀ + n_e, n_f0 + n_fe)

    Raises
    ------
    ValueError
        A kept name that is not a measurement-error state.
    """
    names = [s.name for s in states]
    unknown = [k for k in kept if k not in names]
    if unknown:
        raise ValueError(f"{unknown[0]!r} is not a measurement-error state (known: {', '.join(names) or 'none'})")
    n0, nf0 = D0.shape
    ne, nfe = len(states), len(kept)
    P = np.zeros((n0 + ne, n0 + ne))
    P[:n0, :n0] = P0
    P[n0:, n0:] = np.diag([s.sigma**2 for s in states])
    D = np.zeros((n0 + ne, nf0 + nfe))
    D[:n0, :nf0] = D0
    for j, k in enumerate(kept):
        D[n0 + names.index(k), nf0 + j] = 1.0
    Pf_e = np.diag([states[names.index(k)].sigma**2 for k in kept]) if kept else np.zeros((0, 0))
    return P, Pf_e, D


def error_variance(state, t: float) -> float:
    """Variance of an error state at time ``t`` [s] from its start (σ² + rw² t for a random walk)."""
    return state.sigma**2 + (state.rw**2 * t if state.process == "random_walk" else 0.0)


class Jacobians:
    """The truth's measurement Jacobians ``(H_nav, H_err)`` at the grid steps, each computed once.

    :meth:`Measurement.jacobian <covtool.lincov.measurements.base.Measurement.jacobian>`
    at step ``k`` depends on the trajectory there and on what the
    measurement is (:meth:`~covtool.lincov.measurements.base.Measurement.geometry_key`),
    not on the filter, the grade or the noise 1σ: the filter runs of one
    study share one instance (:func:`build_epochs`), and so do the scaled
    copies of a σ sweep.  Holds ``m × (10 + n_e)`` numbers per measurement
    and update step.  A measurement's key is taken at its first use: the
    measurements are frozen dataclasses, and an array field changed in
    place afterwards is not seen.

    Parameters
    ----------
    nodes : covtool.nav.trajectory.core.Trajectory
        The trajectory sampled on the grid.
    """

    def __init__(self, nodes):
        self.nodes = nodes
        self._keys: dict = {}
        self._points: dict = {}
        self._values: dict = {}

    def point(self, k: int):
        """``(x, w)`` of grid step ``k`` (:func:`covtool.lincov.measurements.base.nav_point`)."""
        if k not in self._points:
            self._points[k] = nav_point(self.nodes, k)
        return self._points[k]

    def __call__(self, meas, k: int):
        """``(H_nav, H_err)`` of ``meas`` at grid step ``k``, shapes (m, 10) and (m, n_e); read only."""
        key = self._keys.get(id(meas))
        if key is None or key[0] is not meas:                    # the measurement itself pins its id
            key = self._keys[id(meas)] = (meas, meas.geometry_key())
        hit = self._values.get((key[1], k))
        if hit is None:
            H_nav, H_err = meas.jacobian(*self.point(k))
            H_nav.flags.writeable = H_err.flags.writeable = False
            hit = self._values[(key[1], k)] = (H_nav, H_err)
        return hit


def build_epochs(plan, nodes, names, filter_names, *, absorb: bool = True,
                 jacobians: Jacobians | None = None) -> list[Epoch]:
    """Stack the measurements due at each grid step.

    Parameters
    ----------
    plan : sequence of (Measurement, ndarray of int)
        Each measurement and its update steps (:meth:`Schedule.steps`).
    nodes : Trajectory
        The trajectory sampled on the grid (``nodes.t`` the grid times).
    names, filter_names : sequence of str
        Truth and filter state names (augmented with the error states).
    absorb : bool
        Widen R_f by ``H_e σ_e² H_eᵀ`` for every error state the filter
        drops (the state's variance at the epoch, replaced by white
        measurement noise: the measurement counterpart of seed 002,
        eq (11)–(13), which replace a dropped state coupling through F by
        white process noise).  False: the filter ignores them.
    jacobians : Jacobians, optional
        The measurement Jacobians of ``nodes``, shared between calls (the
        filters of a study); a new one by default.

    Returns
    -------
    list of Epoch, in time order

    Raises
    ------
    ValueError
        ``jacobians`` belongs to another trajectory.
    """
    fset = set(filter_names)
    due: dict[int, list] = {}
    for meas, steps in plan:
        for k in np.asarray(steps, int):
            due.setdefault(int(k), []).append(meas)
    jac = Jacobians(nodes) if jacobians is None else jacobians
    if jac.nodes is not nodes:
        raise ValueError("build_epochs: the Jacobians are of another trajectory")
    out = []
    for k in sorted(due):
        Hs, Hfs, Rs, Rfs, rows, r0 = [], [], [], [], [], 0
        for meas in due[k]:
            H_nav, H_err = jac(meas, k)
            Hs.append(place(H_nav, H_err, meas, names))
            Hfs.append(place(H_nav, H_err, meas, filter_names))
            Rs.append(meas.R())
            Rf = meas.Rf()
            if absorb:
                for j, s in enumerate(meas.states):
                    if s.name not in fset:
                        Rf = Rf + error_variance(s, float(nodes.t[k])) * np.outer(H_err[:, j], H_err[:, j])
            Rfs.append(Rf)
            rows.append((meas.name, slice(r0, r0 + meas.m)))
            r0 += meas.m
        out.append(Epoch(k, np.vstack(Hs), _blockdiag(Rs), np.vstack(Hfs), _blockdiag(Rfs), tuple(rows)))
    return out


def _blockdiag(mats):
    m = sum(a.shape[0] for a in mats)
    out = np.zeros((m, m))
    i = 0
    for a in mats:
        out[i:i + a.shape[0], i:i + a.shape[0]] = a
        i += a.shape[0]
    return out


def _propagate(P, Phi, Qd, phi, qd):
    """One step of ``[x_INS; e]``: ``blockdiag(Φ, diag φ)`` and ``blockdiag(Q_d, diag q_d)``.

    ``P`` may be a stack (..., n, n), with ``Q_d`` (..., n₀, n₀) and ``q_d``
    (..., n_e) per member (the error-budget members).
    """
    n0 = Phi.shape[0]
    if P.shape[-1] == n0:
        return symmetrize(Phi @ P @ Phi.T + Qd)
    out = np.empty_like(P)
    out[..., :n0, :n0] = Phi @ P[..., :n0, :n0] @ Phi.T + Qd
    out[..., :n0, n0:] = (Phi @ P[..., :n0, n0:]) * phi
    out[..., n0:, :n0] = np.swapaxes(out[..., :n0, n0:], -1, -2)
    out[..., n0:, n0:] = P[..., n0:, n0:] * np.outer(phi, phi) + np.asarray(qd)[..., None] * np.eye(phi.size)
    return symmetrize(out)


@dataclass
class AidedRun:
    """Histories of an aided truth-under-filter run at the recorded steps.

    Attributes
    ----------
    steps : ndarray of int, shape (r,)
        Recorded grid indices.
    P_truth : ndarray, shape (r, n, n)
        Truth covariance over ``[x_INS; e]`` (posterior at update steps), eq (15)–(16);
        its leading ``keep`` states only when :func:`propagate_aided` was given ``keep``.
    P_filter : ndarray, shape (r, n_f, n_f)
        The filter's own covariance, eq (6a)–(8) (likewise).
    prior_truth, prior_filter : dict of int to ndarray
        Priors at the recorded update steps.
    gains : dict of int to ndarray, shape (n_f, m)
        Filter gains at the recorded update steps, eq (7).
    """

    steps: np.ndarray
    P_truth: np.ndarray
    P_filter: np.ndarray
    prior_truth: dict
    prior_filter: dict
    gains: dict


#: covariances checked at once by the guard of :func:`propagate_aided` (bounds its memory)
GUARD_BLOCK = 256


def propagate_aided(Phi, Qd, P0, Phi_f, Qd_f, Pf0, D, epochs, *, err=None, err_f=None, record=None,
                    all_gains: bool = False, sequential: bool = False, form: str = "joseph", check: bool = True,
                    label: str = "filter", times=None, names=None, filter_names=None,
                    system_checked: bool = False, keep: int | None = None) -> AidedRun:
    """Truth covariance under a filter's gains with scheduled general measurements.

    Parameters
    ----------
    Phi, Qd : ndarray, shape (N, n₀, n₀)
        INS truth transition and noise (eq (15)).
    P0 : ndarray, shape (n, n)
        Initial truth covariance over ``[x_INS; e]`` (``n = n₀ + n_e``).
    Phi_f, Qd_f : ndarray, shape (N, n_f0, n_f0)
        The filter's INS model (eq (6a)–(6d)).
    Pf0 : ndarray, shape (n_f, n_f)
    D : ndarray, shape (n, n_f)
        Filter states onto truth states, by name (eq (10)).
    epochs : list of Epoch
        The updates (:func:`build_epochs`).
    err, err_f : tuple of ndarray (phi, qd), each shape (N, n_e) or (N, n_fe), optional
        Exact transitions of the truth's and the filter's measurement-error
        states (:func:`error_processes`); None when there are none.
    record : array_like of int, optional
        Grid indices to keep (default: every one).  Every covariance is
        guarded whether it is kept or not.
    all_gains : bool
        Keep the gains of every update, recorded or not (for a fixed-gain
        error budget, :func:`budget_members`).
    sequential : bool
        Process the measurements of an epoch one after the other instead
        of stacked (the same result when ``H_f = H D``; see the module notes).
    form : {"joseph", "standard"}
        Filter covariance update (eq (8) is ``"standard"``).
    check : bool
        Guard the inputs and every truth and filter covariance, prior and
        posterior (:func:`covtool.lincov.kalman.covariance_status`), in
        blocks of :data:`GUARD_BLOCK`.
    label, times, names, filter_names
        For error messages.
    system_checked : bool
        Φ, Q_d, Φ_f, Q_f were guarded by the caller.  Required when they are
        streamed (:class:`covtool.lincov.streamed.StreamedSystem`, read one
        step at a time: each chunk is guarded when it is made).
    keep : int, optional
        Record only the leading ``keep`` states of the truth and of the
        filter (the navigation block: ``keep = 10``) in ``P_truth``,
        ``P_filter`` and the priors; default all.  Every covariance is still
        guarded whole.

    Returns
    -------
    AidedRun

    Raises
    ------
    ValueError
        Inconsistent sizes, or ``keep < 1``.
    NumericalError
        The first input or covariance that is not finite, symmetric and PSD,
        with the time, the stage and the state.
    """
    N, n0, _ = Phi.shape
    nf0 = Phi_f.shape[1]
    n, nf = P0.shape[0], Pf0.shape[0]
    e_phi, e_qd = err if err is not None else (np.ones((N, 0)), np.zeros((N, 0)))
    f_phi, f_qd = err_f if err_f is not None else (np.ones((N, 0)), np.zeros((N, 0)))
    if n != n0 + e_phi.shape[1] or nf != nf0 + f_phi.shape[1] or D.shape != (n, nf):
        raise ValueError(f"{label}: inconsistent sizes: truth {n0}+{e_phi.shape[1]} vs P0 {n}, filter "
                         f"{nf0}+{f_phi.shape[1]} vs P_f(0) {nf}, D {D.shape}")
    if check:
        sys_ = {} if system_checked else {"truth": (Phi, Qd), "filter": (Phi_f, Qd_f)}
        check_system(f"{label} (truth)", *sys_.get("truth", ()), P0=P0, names=names, times=times)
        check_system(f"{label} (filter)", *sys_.get("filter", ()), P0=Pf0, names=filter_names, times=times)
        # every epoch's R and R_f, stacked by row layout (one guard pass per layout, not per epoch); the
        # flagged epochs are checked again alone, in time order, for the message of the first bad one (a
        # stack flags every matrix its epoch alone would, and may flag one more at the PSD tolerance)
        bad = ~(_noise_ok(epochs, "R") & _noise_ok(epochs, "Rf"))
        for ep in (epochs[i] for i in np.flatnonzero(bad)):
            comps = _components(ep.rows)
            check_system(f"{label} (truth) at {_when(ep.step, times)}", R=ep.R, measurement_names=comps)
            check_system(f"{label} (filter) at {_when(ep.step, times)}", R=ep.Rf, measurement_names=comps)
    rec = np.arange(N + 1) if record is None else np.unique(np.asarray(record, int))
    slot = {int(k): i for i, k in enumerate(rec)}
    by_step = {ep.step: ep for ep in epochs}
    if keep is not None and int(keep) < 1:
        raise ValueError(f"{label}: keep must be a positive number of states, got {keep}")
    kt, kf = (n, nf) if keep is None else (min(int(keep), n), min(int(keep), nf))
    PT = np.full((rec.size, kt, kt), np.nan)
    PF = np.full((rec.size, kf, kf), np.nan)
    prior_t, prior_f, gains = {}, {}, {}
    guard = _Guard(label, names, filter_names, times, check)

    def on_state(k, stage, P, Pf, K):
        if stage == "prior":
            guard.add(k, P, Pf, prior=True)
            if k in slot:
                prior_t[k], prior_f[k] = (P, Pf) if keep is None else (P[:kt, :kt].copy(), Pf[:kf, :kf].copy())
            return
        guard.add(k, P, Pf, after_update=k in by_step)
        if k in slot:
            PT[slot[k]], PF[slot[k]] = P[:kt, :kt], Pf[:kf, :kf]
        if K is not None and (all_gains or k in slot):
            gains[k] = K

    def fail(k, exc):
        guard.flush()
        raise NumericalError(f"{label}: gain at {_when(k, times)}: {exc}") from None

    filter_loop(N, P0, Pf0, lambda k, P: _propagate(P, Phi[k], Qd[k], e_phi[k], e_qd[k]),
                lambda k, Pf: _propagate(Pf, Phi_f[k], Qd_f[k], f_phi[k], f_qd[k]),
                {k: _parts(ep, sequential) for k, ep in by_step.items()}, D, form, on_state, fail)
    guard.flush()
    return AidedRun(rec, PT, PF, prior_t, prior_f, gains)


def _parts(ep: Epoch, sequential: bool) -> tuple:
    """The ``(H, R, H_f, R_f)`` parts of an epoch: one stacked part, or one per measurement."""
    rows = [sl for _, sl in ep.rows] if sequential else [slice(0, ep.H.shape[0])]
    return tuple((ep.H[sl], ep.R[sl, sl], ep.Hf[sl], ep.Rf[sl, sl]) for sl in rows)


def _components(rows) -> list[str]:
    """``name[i]`` of every row of a stacked update (:attr:`Epoch.rows`)."""
    return [f"{nm}[{i}]" for nm, sl in rows for i in range(sl.stop - sl.start)]


def _noise_ok(epochs, attr: str) -> np.ndarray:
    """Per epoch, whether its ``R`` or ``R_f`` (``attr``) is a covariance, as :func:`check_system` tests it.

    Epochs of one row layout are tested as one stack (:func:`covariance_status`, the components
    scaled in the groups of their names).  Returns shape (len(epochs),), bool.
    """
    ok = np.ones(len(epochs), bool)
    layouts: dict = {}
    for i, ep in enumerate(epochs):
        layouts.setdefault(tuple((nm, sl.start, sl.stop) for nm, sl in ep.rows), []).append(i)
    for idx in layouts.values():
        R = np.stack([getattr(epochs[i], attr) for i in idx])
        ok[idx] = covariance_status(R, groups=scale_groups(_components(epochs[idx[0]].rows), R.shape[-1])).ok
    return ok


def _when(k, times):
    return time_text(float(times[k])) if times is not None else f"step {k}"


class _Guard:
    """Checks every truth and filter covariance (prior and posterior) in blocks; raises for the first bad one."""

    def __init__(self, label, names, filter_names, times, active):
        self.label, self.names, self.fnames, self.times, self.active = label, names, filter_names, times, active
        self.items = []

    def add(self, k, P, Pf, prior=False, after_update=False):
        if not self.active:
            return
        stage = ("before the update (prior)" if prior else
                 "after the update" if after_update else "after the propagation")
        self.items.append((k, stage, P, Pf))
        if len(self.items) >= GUARD_BLOCK:
            self.flush()

    def flush(self):
        if not self.items:
            return
        items, self.items = self.items, []
        for j, (what, nm) in enumerate((("truth", self.names), ("filter", self.fnames))):
            stack = np.stack([it[2 + j] for it in items])
            st = covariance_status(stack, groups=scale_groups(nm, stack.shape[-1]))
            if not np.all(st.ok):
                bad = int(np.flatnonzero(~st.ok)[0])
                k, stage = items[bad][0], items[bad][1]
                raise NumericalError(f"{self.label}: {what} {stage} at {_when(k, self.times)}: "
                                     f"{st.problem(bad, nm)}")


def budget_members(Phi, P0s, D, epochs, gains, *, qd, r_weights, meas_names, record, keep, err=None,
                   err_weights=None, psd=None, label: str = "error budget", members=None, names=None,
                   times=None) -> np.ndarray:
    """Truth covariance of several sources under fixed gains (error budget).

    With the gains of a nominal run held fixed, the truth recursion of
    seed 002, eq (15)–(16), is linear in (P0, Q_d, R): each member is the
    truth run with one source alone, and the members sum to the nominal
    run (:mod:`covtool.analysis.budget`).

    Parameters
    ----------
    Phi : ndarray, shape (N, n₀, n₀)
        INS truth transition.
    P0s : ndarray, shape (B, n, n)
        Each member's initial covariance over ``[x_INS; e]``.
    D : ndarray, shape (n, n_f)
    epochs : list of Epoch
        The updates (:func:`build_epochs`), processed stacked.
    gains : dict of int to ndarray, shape (n_f, m)
        The nominal run's gain at every epoch (``propagate_aided(...,
        all_gains=True)``).
    qd : callable ``k -> ndarray (B, n₀, n₀)``
        Each member's INS process noise over step ``k``.
    r_weights : ndarray, shape (B, n_meas)
        Member ``b`` takes measurement ``j``'s white noise R times
        ``r_weights[b, j]`` (0 or 1).
    meas_names : sequence of str, length n_meas
        The measurements (names of ``Epoch.rows``) of the columns of
        ``r_weights``.
    err : tuple of ndarray (phi, qd), each shape (N, n_e), optional
        Exact transition and driving noise of the measurement-error states
        (:func:`error_processes`).
    err_weights : ndarray, shape (B, n_e), optional
        Member ``b`` takes error state ``i``'s driving noise times
        ``err_weights[b, i]`` (default: none).
    record : array_like of int
        Grid indices kept.
    keep : index array
        Recorded sub-block (e.g. the navigation states).
    psd : array_like of bool, shape (B,), optional
        Members that must be PSD (default all; a cross-covariance piece
        may be indefinite).
    label, members, names, times
        For error messages: the run, the members' (sources') names, the
        truth state names, the grid times.

    Returns
    -------
    ndarray, shape (B, r, k, k)
        Each member's ``keep`` block at the recorded steps.

    Raises
    ------
    ValueError
        An epoch without a gain.
    NumericalError
        A member's recorded covariance is not finite and symmetric, or not
        PSD (members flagged in ``psd``), naming the member, time and state.
    """
    N, n0, _ = Phi.shape
    B, n, _ = P0s.shape
    ne = n - n0
    e_phi, e_qd = err if err is not None else (np.ones((N, ne)), np.zeros((N, ne)))
    ew = np.zeros((B, ne)) if err_weights is None else np.asarray(err_weights, float)
    r_weights = np.asarray(r_weights, float)
    col = {m: j for j, m in enumerate(meas_names)}
    rec = np.unique(np.asarray(record, int))
    slot = {int(k): i for i, k in enumerate(rec)}
    keep = np.asarray(keep)
    out = np.full((B, rec.size, keep.size, keep.size), np.nan)
    by_step = {ep.step: ep for ep in epochs}
    missing = [ep.step for ep in epochs if ep.step not in gains]
    if missing:
        raise ValueError(f"{label}: no gain at {_when(missing[0], times)}")
    P = symmetrize(np.asarray(P0s, float))
    eye = np.eye(n)
    with np.errstate(over="ignore", invalid="ignore"):          # a blow-up is reported by the check below
        for k in range(N + 1):
            ep = by_step.get(k)
            if ep is not None:
                DK = D @ gains[k]
                A = eye - DK @ ep.H
                # each member's share of the stacked R: its measurements' rows (R is block-diagonal by kind)
                w = np.zeros((B, ep.H.shape[0]))
                for nm, sl in ep.rows:
                    w[:, sl] = r_weights[:, col[nm]:col[nm] + 1]
                Rb = ep.R * (w[:, :, None] * w[:, None, :])
                # seed 002, eq (16) with the nominal gain, every member at once
                P = symmetrize(A @ P @ A.T + DK @ Rb @ DK.T)
            if k in slot:
                out[:, slot[k]] = P[:, keep[:, None], keep[None, :]]
            if k < N:
                P = _propagate(P, Phi[k], qd(k), e_phi[k], e_qd[k] * ew)
    psd = np.ones(B, bool) if psd is None else np.asarray(psd, bool)
    kept = None if names is None else [names[i] for i in keep]
    # a contribution is judged against the σ of the sum of all of them (its own σ may be round-off)
    scale = np.sqrt(np.abs(np.einsum("...ii->...i", out.sum(axis=0))))
    for b in range(B):
        st = covariance_status(out[b], psd=bool(psd[b]), scale=scale, groups=scale_groups(kept, keep.size))
        if not np.all(st.ok):
            i = int(np.flatnonzero(~st.ok)[0])
            who = repr(members[b]) if members is not None else f"#{b + 1}"
            raise NumericalError(f"{label}: source {who} at {_when(int(rec[i]), times)}: {st.problem(i, kept)}")
    return out
