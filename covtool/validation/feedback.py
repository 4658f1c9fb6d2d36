"""The feedback filter of the Monte Carlo ensemble (seed 002, Fig 1, eq (6)–(10)).

*Covariance and gain.*  The filter propagates its covariance with its own
model, ``P_f ← Φ_f P_f Φ_fᵀ + Q_f`` (eq (6a)–(6d)), and at a ZUPT computes
``K = P_f H_fᵀ (H_f P_f H_fᵀ + R_f)⁻¹`` (eq (7)) and updates ``P_f`` (eq (8)
or Joseph) with the kernel (:mod:`covtool.lincov.kalman`).  ``F_f`` is
evaluated along the **reference trajectory**, not along each run's own
navigation solution.  The two differ by the navigation errors (feet,
arcminutes), a second-order change of the gains; with the reference the
covariance and the gains are the same for every run, so they are computed
once for the whole ensemble (:meth:`FeedbackFilter.design`), and the
ensemble tests exactly what the linear analysis assumes (eq (16) takes
``K`` from one filter covariance history).

*Measurement.*  At a ZUPT the vehicle is known to stand still, so the
measurement is the INS velocity itself, ``z = v̂^n − 0 + ν``, ``ν ~ N(0, R)``
with the *study's* (true) ``R``; the filter's gain may assume another
``R_f``.  The estimate is ``x̂ = K z``: the filter's prior estimate is zero
because every earlier estimate was fed back (eq (9)).

*Feedback* (eq (10), ``x ← x − D x̂``):

* navigation states: :func:`covtool.nav.strapdown.correct` subtracts
  ``(δL̂, δl̂, δĥ, δv̂, δq̂)`` from the navigation state (quaternion
  renormalised);
* sensor and environment states: every run keeps an accumulated estimate
  ``ĉ`` of each sensor state its filter carries (:class:`SensorFeedback`);
  an update adds ``x̂_s`` to ``ĉ``.  Every IMU sample is then compensated
  through the same block sensitivities that inject the errors
  (:mod:`covtool.lincov.model.blocks`, :class:`covtool.validation.sensor_errors.SensorErrors`)::

      Δθ_c = Δθ − h S_g(f̄, ω̄) ĉ_g,     Δv_c = Δv − h S_a(f̄, ω̄) ĉ_a
             − h C_n^b diag(g, g, −1) ĉ_grav − Δĉ_AD

  with ``f̄ = Δv/h``, ``ω̄ = Δθ/h`` the raw measured sample means (what an
  on-board system has).  The residual sensor error is then
  ``S (x − ĉ)`` to first order: the truth state after feedback is
  ``x − ĉ``, exactly the ``x ← x − x̂`` of eq (10).
* Between updates ``ĉ`` follows the *mean* dynamics of its state, so that
  ``x − ĉ`` obeys the truth model's ``ẋ = F x + w``: random constants and
  random walks stay, first-order Markov states decay as ``e^{−Δt/τ}``
  (in distance: ``e^{−Δd/d}``).  The AD-reset state is a velocity error
  whose rate is a specific-force error, so only the *change* of ``ĉ``
  between updates is subtracted from the increments, never its jump at an
  update.  The gravity term is rotated with the reference attitude (an
  on-board system would use its own; the difference is arcmin × µGal).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numba
import numpy as np

from covtool.errors import NumericalError
from covtool.lincov.kalman import (check_covariance, check_system, filter_update, kalman_gain, symmetrize,
                                   time_text)
from covtool.lincov.model.blocks import BLOCK_KINDS, gravity_sensitivity
from covtool.nav import attitude as quat, earth
from covtool.nav.strapdown import NAV_STATES

__all__ = [
    "FeedbackFilter", "SensorFeedback", "RecordContext", "compensate_cases", "gain_steps",
]


def gain_steps(update_steps, N: int) -> list[int]:
    """The steps of a grid of ``N`` steps at which :meth:`FeedbackFilter.design` computes a gain.

    Parameters
    ----------
    update_steps : iterable of int
        Grid indices of the updates.
    N : int
        Grid steps (indices ``0 … N``).

    Returns
    -------
    list of int
        The distinct update steps in ``0 … N``, in increasing order (the keys
        of :attr:`FeedbackFilter.gains`).
    """
    return sorted({int(k) for k in update_steps if 0 <= int(k) <= N})


# --------------------------------------------------------------------------
# the filter (covariance and gains: the same for every run)
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class FeedbackFilter:
    """A ZUPT feedback filter's gain schedule and claimed covariance.

    Attributes
    ----------
    name : str
    names : tuple of str
        The filter's states (truth state names, seed 002 eq (14) order first).
    gains : dict of int to ndarray, shape (n_f, 3)
        ``K`` at each update grid index (eq (7)).
    P : ndarray, shape (N+1, n_f, n_f)
        The filter's own (claimed) covariance at every grid time, posterior
        at update times; with ``record_steps``, shape (J, n_f, n_f) at those
        grid indices.
    record_steps : ndarray of int, shape (J,), or None
        Grid indices of the rows of ``P`` (None: every step).
    every : ndarray, shape (N+1, a, a), or None
        The leading ``a`` states (the navigation block) at every grid time.
    """

    name: str
    names: tuple
    gains: dict
    P: np.ndarray
    record_steps: np.ndarray | None = None
    every: np.ndarray | None = None

    @classmethod
    def design(cls, name, names, Phi_f, Qd_f, P0, Rf, update_steps, *, form: str = "joseph",
               times=None, record=None, all_steps: int | None = None,
               system_checked: bool = False) -> "FeedbackFilter":
        """Run the filter's covariance recursion (seed 002, eq (6)–(8)).

        Parameters
        ----------
        name : str
        names : sequence of str
            Filter state names (must contain the velocity states).
        Phi_f, Qd_f : ndarray, shape (N, n_f, n_f)
            The filter's own transition and noise along the reference
            trajectory (eq (6b)–(6d)).
        P0 : ndarray, shape (n_f, n_f)
        Rf : ndarray, shape (3, 3)
            Measurement noise the filter assumes.
        update_steps : iterable of int
            Grid indices of the ZUPT updates.
        form : {"joseph", "standard"}
        times : ndarray, shape (N+1,), optional
            Grid times, for error messages. [s]
        record : array_like of int, optional
            Grid indices whose covariance ``P`` keeps (shape (J, n_f, n_f));
            every covariance is still guarded, a block of
            :data:`covtool.lincov.reference.GUARD_STEPS` at a time, so the
            memory does not grow with N × n_f² (``Phi_f``, ``Qd_f`` may be
            streamed).
        all_steps : int, optional
            Also keep the leading ``all_steps`` states of every step
            (``every``; the navigation block: 10).  Implies ``record``.
        system_checked : bool
            Φ_f and Q_f were guarded by the caller (required for a streamed
            system, :class:`covtool.lincov.streamed.StreamedSystem`); P0 and
            R_f are still checked.

        Returns
        -------
        FeedbackFilter

        Raises
        ------
        NumericalError
            An input (P0, Φ_f, Q_f, R_f) or a covariance of the history is
            not finite, symmetric and PSD (:func:`covtool.lincov.kalman.check_covariance`);
            the message names the filter, the time and the state (the same with
            or without ``record``); a gain that cannot be formed.
        SystemCheckError
            A streamed system's chunk failed its own guard as it was made,
            passed through unchanged.
        ValueError
            ``record`` steps outside ``0 … N``, ``all_steps`` below 1, ``names``
            not matching ``Phi_f``, or a streamed system without ``system_checked``.

        Notes
        -----
        The operations are those of
        :func:`covtool.lincov.reference.propagate_with_filter`, in the same order,
        so ``P`` and ``gains`` equal its ``P_filter`` and ``gains`` bit for bit.
        """
        from covtool.lincov.reduced import zupt_matrices     # with pandas: not at a chunk worker's import

        names = tuple(names)
        Hf = zupt_matrices(names)
        N, nf, _ = Phi_f.shape
        if nf != len(names):
            raise ValueError(f"filter {name!r}: Phi_f has {nf} states, names has {len(names)}")
        from covtool.lincov.reference import GUARD_STEPS, record_plan

        label = f"Monte Carlo filter {name}"
        check_system(label, Phi=None if system_checked else Phi_f, Qd=None if system_checked else Qd_f, P0=P0,
                     R=Rf, names=names, times=times)
        upd = set(gain_steps(update_steps, N))
        recorded = record is not None or all_steps is not None
        rec, slot = record_plan([] if record is None else record, N, label, all_steps=all_steps)
        out = np.empty((rec.size, nf, nf))
        a = None if all_steps is None else min(int(all_steps), nf)
        every = None if a is None else np.empty((N + 1, a, a))
        # the history (every step), or one guard block of it at a time (recorded)
        m = min(GUARD_STEPS, N + 1) if recorded else N + 1
        P = np.full((m, nf, nf), np.nan)
        first = 0

        # the grid's times name a bad covariance; without them, its grid step (as the whole history's index)
        def at(i):
            return f"(matrix ({first + i[0]},))"

        def check(j):
            if j > 0:
                check_covariance(P[:j], label, names=names, times=None if times is None else times[first:first + j],
                                 at=None if times is not None else at)

        gains = {}
        Pf = symmetrize(np.asarray(P0, float))
        with np.errstate(over="ignore", invalid="ignore"):   # a blow-up is reported by the guard
            for k in range(N + 1):
                if k in upd:
                    try:
                        K = kalman_gain(Pf, Hf, Rf)
                        Pf_u = filter_update(Pf, K, Hf, Rf, form)
                    except NumericalError as exc:          # a gain that cannot be formed (not a system's guard)
                        check(k - first)
                        when = time_text(float(times[k])) if times is not None else f"step {k}"
                        raise NumericalError(f"{label}: gain at {when}: {exc}") from None
                    gains[k] = K
                    Pf = Pf_u
                P[k - first] = Pf
                if recorded:
                    if k in slot:
                        out[slot[k]] = Pf
                    if every is not None:
                        every[k] = Pf[:a, :a]
                    if k - first + 1 == m:
                        check(m)
                        first += m
                if k < N:
                    Pf = symmetrize(Phi_f[k] @ Pf @ Phi_f[k].T + Qd_f[k])
        check(N + 1 - first)
        if recorded:
            return cls(name, names, gains, out, rec, every)
        return cls(name, names, gains, P)


# --------------------------------------------------------------------------
# sensor-error feedback into the IMU increments
# --------------------------------------------------------------------------


@dataclass
class _Block:
    kind: str
    sensor: str
    sensitivity: object
    cols: np.ndarray        # columns within the block kept by the filter
    idx: np.ndarray         # positions in the feedback vector


class SensorFeedback:
    """Accumulated sensor-error estimates of M runs, fed back.

    Parameters
    ----------
    model : covtool.lincov.model.spec.Model
        The truth model (states, blocks, processes).
    names : sequence of str
        The filter's states; the non-navigation ones are fed back here.
    n_runs : int

    Attributes
    ----------
    names : tuple of str
        The fed-back states, in filter order.
    c : ndarray, shape (M, n_s)
        Accumulated estimate ``ĉ`` of each state at the current time.
    """

    def __init__(self, model, names, n_runs: int):
        self.names = tuple(n for n in names if n not in NAV_STATES)
        ix = model.index
        for n in self.names:
            if n not in ix:
                raise ValueError(f"filter state {n!r} is not a state of truth model {model.name!r}")
        self.c = np.zeros((int(n_runs), len(self.names)))
        pos = {n: j for j, n in enumerate(self.names)}
        self.blocks: list[_Block] = []
        for block in model.block_names():
            members = [s for s in model.states if s.block == block]
            kept = [(k, pos[s.name]) for k, s in enumerate(members) if s.name in pos]
            if not kept or members[0].kind == "navigation":
                continue
            bk = BLOCK_KINDS[members[0].kind]
            self.blocks.append(_Block(bk.kind, bk.sensor, bk.sensitivity, np.array([k for k, _ in kept]),
                                      np.array([j for _, j in kept])))
        states = [model.states[ix[n]] for n in self.names]
        self.tau = np.array([s.tau if s.process == "markov" else np.inf for s in states])
        self.dist = np.array([s.distance if s.process == "markov_distance" else np.inf for s in states])
        self.dynamic = np.isfinite(self.tau) | np.isfinite(self.dist)
        self.needs_context = any(b.sensor == "gravity" for b in self.blocks) or bool(np.isfinite(self.dist).any())

    @property
    def n(self) -> int:
        return len(self.names)

    def add(self, dx) -> None:
        """Accumulate the estimates of one update, ``ĉ ← ĉ + x̂_s``."""
        self.c = self.c + dx

    def _factors(self, t_rel, d_rel):
        """Mean-dynamics factors ``e^{−t/τ − d/D}``, shape (k, n_s)."""
        with np.errstate(divide="ignore"):
            return np.exp(-np.asarray(t_rel)[:, None] / self.tau[None, :]
                          - np.asarray(d_rel)[:, None] / self.dist[None, :])

    def compensate(self, dtheta, dv, h: float, ctx: "RecordContext | None" = None):
        """Compensated increments of one record; advances ``ĉ`` to its end.

        The compiled kernel (:func:`compensate_cases`) when every fed-back
        block is a single-entry sensitivity (:func:`_column_table`) or the
        gravity block, else :meth:`compensate_reference`; both give the
        same increments to round-off (tests).  Parameters and returns as
        :meth:`compensate_reference`.
        """
        if not self.n:
            return dtheta, dv
        return compensate_cases([self], dtheta, dv, h, ctx)

    def _table(self):
        """Entries of the compiled compensation, or None (use the reference)."""
        if getattr(self, "_tab", False) is not False:
            return self._tab
        target, rows, types, ia, ib, cidx, gcols, gidx, adcols, adidx = [], [], [], [], [], [], [], [], [], []
        tab = None
        for b in self.blocks:
            if b.sensor == "ad_reset":
                adcols += list(b.cols)
                adidx += list(b.idx)
                continue
            if b.sensor == "gravity":
                gcols += list(b.cols)
                gidx += list(b.idx)
                continue
            cols = _column_table(b.kind) if b.sensor in ("gyro", "accel") else None
            if cols is None:
                break
            for col, j in zip(b.cols, b.idx):
                r, ty, a, bb = cols[int(col)]
                target.append(0 if b.sensor == "gyro" else 1)
                rows.append(r)
                types.append(ty)
                ia.append(a)
                ib.append(bb)
                cidx.append(int(j))
        else:
            tab = tuple(np.array(v, dtype=np.int64) for v in (target, rows, types, ia, ib, cidx, gcols, gidx,
                                                                     adcols, adidx))
        self._tab = tab
        return tab

    def _plan(self):
        """The entries of :meth:`_table` as the compiled kernel takes them, or None.

        ``(fidx, cols, dyn, comp)``: per entry its feature (:data:`_FEATURES`
        order), its column of ``ĉ``, whether its state has mean dynamics and
        its correction component (0–2 gyro x, y, z, 3–5 accel x, y, z);
        within a component the entries keep the table's order.
        """
        if getattr(self, "_plan_", False) is not False:
            return self._plan_
        tab = self._table()
        plan = None
        if tab is not None:
            target, rows, types, ia, ib, cidx = tab[:6]
            out = 3 * target + rows
            # round robin over the components, table order within each: the kernel's six sums then
            # advance side by side instead of one after the other
            rank = np.zeros(out.size, np.int64)
            for o in range(6):
                rank[out == o] = np.arange(np.count_nonzero(out == o))
            order = np.lexsort((out, rank))
            fidx = np.select([types == 0, types == 1, types == 2, types == 3],
                             [0, 1 + ia, 4 + ia, 7 + ia], 10 + 3 * ia + ib).astype(np.int64)
            plan = (fidx[order], cidx[order], self.dynamic[cidx[order]].astype(np.int64), out[order])
        self._plan_ = plan
        return plan

    def compensate_reference(self, dtheta, dv, h: float, ctx: "RecordContext | None" = None):
        """Compensated increments of one record (numpy reference).

        Parameters
        ----------
        dtheta, dv : ndarray, shape (M, k, 3)
            Raw increments of the record. [rad], [m/s]
        h : float
            Sample period. [s]
        ctx : RecordContext, optional
            Reference attitude, gravity and distance in the record (needed
            for gravity-disturbance and Markov-in-distance states).

        Returns
        -------
        dtheta_c, dv_c : ndarray, shape (M, k, 3)
        """
        if not self.n:
            return dtheta, dv
        M, k, _ = dtheta.shape
        if self.needs_context and ctx is None:
            raise ValueError("gravity-disturbance and Markov-in-distance feedback need the record context")
        t_mid = (np.arange(k) + 0.5) * h
        t_edge = np.arange(k + 1) * h
        d_mid = ctx.d_mid if ctx is not None else np.zeros(k)
        d_edge = ctx.d_edge if ctx is not None else np.zeros(k + 1)
        dyn = self.dynamic.any()
        f_mid = self._factors(t_mid, d_mid) if dyn else None            # (k, n_s)
        f_edge = self._factors(t_edge, d_edge) if dyn else None         # (k+1, n_s)
        fbar = (dv / h).reshape(M * k, 3)
        wbar = (dtheta / h).reshape(M * k, 3)
        corr = {"gyro": np.zeros((M, k, 3)), "accel": np.zeros((M, k, 3))}
        ad = np.zeros((M, k, 3))
        for b in self.blocks:
            c = self.c[:, b.idx]                                       # (M, nb)
            if b.sensor == "ad_reset":
                # δΔv = Δe per sample: the change of ĉ under its mean dynamics
                step = f_edge[1:, b.idx] - f_edge[:-1, b.idx]          # (k, nb)
                for j, col in enumerate(b.cols):
                    ad[:, :, col] += c[:, j, None] * step[None, :, j]
                continue
            cs = c[:, None, :] * f_mid[None, :, b.idx] if self.dynamic[b.idx].any() else c[:, None, :]
            if b.sensor == "gravity":
                S = ctx.gravity_sensitivity[:, :, b.cols]             # (k, 3, nb)
                corr["accel"] += np.einsum("kin,mkn->mki", S, np.broadcast_to(cs, (M, k, b.idx.size)))
                continue
            S = b.sensitivity(fbar, wbar).reshape(M, k, 3, -1)[..., b.cols]
            corr[b.sensor] += np.einsum("mkin,mkn->mki", S, np.broadcast_to(cs, (M, k, b.idx.size)))
        if dyn:
            self.c = self.c * f_edge[-1][None, :]
        return dtheta - h * corr["gyro"], dv - h * corr["accel"] - ad


# --------------------------------------------------------------------------
# compiled compensation (issue 13)
# --------------------------------------------------------------------------


@lru_cache(maxsize=None)
def _column_table(kind: str):
    """Each sensitivity column of a block kind as one entry, or None.

    The sensitivities of :mod:`covtool.lincov.model.blocks` put one
    non-zero in each column: ``S[r, col] = v(f, ω)`` with ``v`` one of
    1, ``f_a``, ``ω_a``, ``|f_a|``, ``f_a f_b`` (biases, scale factors,
    misalignments, g-sensitivity, anisoelasticity).  The entry ``(r, type,
    a, b)`` is found by probing the block's own function at random points,
    so the compiled kernel evaluates exactly that function; a kind that does
    not fit (None) is compensated by the numpy reference.
    """
    fn = BLOCK_KINDS[kind].sensitivity
    if fn is None:
        return None
    rng = np.random.default_rng(20261201)
    z = rng.normal(size=(8, 6)) * rng.uniform(0.5, 3.0, size=(8, 6))
    f, w = z[:, :3], z[:, 3:]
    S = np.asarray(fn(f, w), dtype=float)                              # (8, 3, nb)
    values = {(0, 0, 0): np.ones(8)}
    for a in range(3):
        values[(1, a, 0)] = f[:, a]
        values[(2, a, 0)] = w[:, a]
        values[(3, a, 0)] = np.abs(f[:, a])
        for b in range(3):
            values[(4, a, b)] = f[:, a] * f[:, b]
    out = []
    for col in range(S.shape[2]):
        nz = [r for r in range(3) if np.any(S[:, r, col] != 0.0)]
        if len(nz) != 1:
            return None
        r = nz[0]
        match = next((key for key, v in values.items() if np.allclose(S[:, r, col], v, rtol=1e-14, atol=0.0)), None)
        if match is None:
            return None
        out.append((r, *match))
    return tuple(out)


#: features of a raw sample that the single-entry sensitivities take (:func:`_column_table`):
#: 1, f̄_a, ω̄_a, |f̄_a|, f̄_a f̄_b (a, b = x, y, z), in this order
_FEATURES = 19


def compensate_cases(feedbacks, dtheta, dv, h: float, ctx: "RecordContext | None" = None, out=None):
    """Compensated increments of several feedbacks of one record; advances each ``ĉ``.

    The feedbacks (e.g. the filter cases of an ensemble) compensate the same
    raw increments, each with its own ``ĉ``; the compiled kernel
    (:func:`_compensate_kernel`) forms the sample means once for all of them.

    Parameters
    ----------
    feedbacks : sequence of SensorFeedback
        With the same number of runs M, each with fed-back states.
    dtheta, dv : ndarray, shape (Mv, k, 3)
        Raw increments of the record (Mv = M, or 1 shared by the runs).
        [rad], [m/s]
    h : float
        Sample period. [s]
    ctx : RecordContext, optional
        As for :meth:`SensorFeedback.compensate_reference`.
    out : tuple of ndarray, optional
        ``(dtheta_c, dv_c)``, each shape (len(feedbacks)·M, k, 3), any
        strides, to write into (default: new arrays).

    Returns
    -------
    dtheta_c, dv_c : ndarray, shape (len(feedbacks)·M, k, 3)
        Feedback ``i`` in rows ``i·M … (i+1)·M − 1``.
    """
    fbs = list(feedbacks)
    M = fbs[0].c.shape[0]
    _, k, _ = dtheta.shape
    if out is None:
        out = (np.empty((len(fbs) * M, k, 3)), np.empty((len(fbs) * M, k, 3)))
    out_th, out_dv = out
    compiled = []
    for i, fb in enumerate(fbs):
        if fb.c.shape[0] != M or not fb.n:
            raise ValueError("compensate_cases: every feedback needs fed-back states and the same runs")
        if fb._plan() is None:
            th, vv = fb.compensate_reference(dtheta, dv, h, ctx)
            out_th[i * M:(i + 1) * M] = th
            out_dv[i * M:(i + 1) * M] = vv
        else:
            if fb.needs_context and ctx is None:
                raise ValueError("gravity-disturbance and Markov-in-distance feedback need the record context")
            compiled.append(i)
    if not compiled:
        return out_th, out_dv
    # the cases' tables, their ĉ and mean-dynamics factors side by side (case j's columns from off[j])
    use = [fbs[i] for i in compiled]
    off = np.cumsum([0] + [fb.n for fb in use])
    dyn = any(fb.dynamic.any() for fb in use)
    need_ad = any(fb._table()[8].size for fb in use)
    d_mid = ctx.d_mid if ctx is not None else np.zeros(k)
    d_edge = ctx.d_edge if ctx is not None else np.zeros(k + 1)
    f_mid = np.ones((k if dyn else 1, off[-1]))
    ad_step = np.zeros((k if need_ad else 1, off[-1]))
    fidx, cols, dflag, comp, estart = [], [], [], [], [0]
    gstart, gcols, gidx, astart, adcols, adidx = [0], [], [], [0], [], []
    for j, fb in enumerate(use):
        fi, cj, dj, oj = fb._plan()
        tab = fb._table()
        fidx.append(fi)
        cols.append(cj + off[j])
        dflag.append(dj)
        comp.append(oj)
        estart.append(estart[-1] + fi.size)
        gcols.append(tab[6])
        gidx.append(tab[7] + off[j])
        gstart.append(gstart[-1] + tab[6].size)
        adcols.append(tab[8])
        adidx.append(tab[9] + off[j])
        astart.append(astart[-1] + tab[8].size)
        if fb.dynamic.any():
            f_mid[:, off[j]:off[j + 1]] = fb._factors((np.arange(k) + 0.5) * h, d_mid)
        if tab[8].size:
            f_edge = fb._factors(np.arange(k + 1) * h, d_edge)
            ad_step[:, off[j]:off[j + 1]] = f_edge[1:] - f_edge[:-1]
    cat = lambda parts: np.ascontiguousarray(np.concatenate(parts), dtype=np.int64)   # noqa: E731
    gS = ctx.gravity_sensitivity if sum(g.size for g in gcols) else np.zeros((1, 3, 3))
    c = np.ascontiguousarray(np.concatenate([fb.c for fb in use], axis=1))
    rows = np.array(compiled, np.int64) * M
    _compensate_kernel(dtheta, dv, float(h), np.array(estart, np.int64), cat(fidx), cat(cols), cat(dflag),
                       cat(comp), f_mid, c,
                       np.ascontiguousarray(gS), np.array(gstart, np.int64), cat(gcols), cat(gidx),
                       np.array(astart, np.int64), cat(adcols), cat(adidx), ad_step, rows, out_th, out_dv)
    for fb in use:
        if fb.dynamic.any():
            fb.c = fb.c * fb._factors(np.array([k * h]), d_edge[-1:])[0][None, :]
    return out_th, out_dv


@numba.njit(cache=True, nogil=True)
def _compensate_kernel(dth, dv, h, estart, fidx, cols, dflag, comp, fmid, c, gS, gstart, gcols, gidx, astart,
                       adcols, adidx, ad_step, rows, out_th, out_dv):
    """``Δθ − h S_g ĉ``, ``Δv − h S_a ĉ − h C diag(g, g, −1) ĉ_grav − Δĉ_AD`` per sample, for several cases.

    ``dth``, ``dv`` (Mv, K, 3) raw (Mv = M or 1), shared by the cases; case
    i writes rows ``rows[i] + m`` of ``out_th``, ``out_dv``.  Its entries
    ``estart[i] … estart[i + 1] − 1`` each add ``F[fidx_e] ĉ[cols_e]``
    (times ``fmid[k, cols_e]`` when ``dflag_e``) to correction component
    ``comp_e`` (gyro x, y, z, accel x, y, z),
    F the :data:`_FEATURES` of the sample means ``f̄ = Δv/h``, ``ω̄ = Δθ/h``
    (:func:`_column_table`); ``c`` (M, n) the cases' ĉ side by side,
    ``fmid`` (K or 1, n) their mean-dynamics factors; ``gS`` (K, 3, 3) the
    gravity sensitivity, the case's kept columns ``gcols`` at ``gidx``
    (``gstart[i] …``); its AD-reset states ``adcols`` at ``adidx``
    (``astart[i] …``) subtract ``ĉ ad_step[k]`` (the change of their mean
    dynamics over the sample).
    """
    M = c.shape[0]
    K = dth.shape[1]
    C = rows.size
    shared = dth.shape[0] == 1
    nf = fmid.shape[0]
    # run after run, in blocks of samples that are the inner loop (vector lanes): each sample's
    # entries are added in table order, and every row of the outputs is written in sequence
    KB = 128
    F = np.empty((_FEATURES, KB))
    acc = np.empty((6, KB))
    dad = np.empty((3, KB))
    fT = np.ascontiguousarray(fmid.T)
    gT = np.ascontiguousarray(gS.transpose(1, 2, 0))
    aT = np.ascontiguousarray(ad_step.T)
    for m in range(M):
        mb = 0 if shared else m
        for k0 in range(0, K, KB):
            kn = min(KB, K - k0)
            for q in range(kn):
                k = k0 + q
                f0, f1, f2 = dv[mb, k, 0] / h, dv[mb, k, 1] / h, dv[mb, k, 2] / h
                w0, w1, w2 = dth[mb, k, 0] / h, dth[mb, k, 1] / h, dth[mb, k, 2] / h
                F[0, q] = 1.0
                F[1, q], F[2, q], F[3, q] = f0, f1, f2
                F[4, q], F[5, q], F[6, q] = w0, w1, w2
                F[7, q], F[8, q], F[9, q] = abs(f0), abs(f1), abs(f2)
                F[10, q], F[11, q], F[12, q] = f0 * f0, f0 * f1, f0 * f2
                F[13, q], F[14, q], F[15, q] = f1 * f0, f1 * f1, f1 * f2
                F[16, q], F[17, q], F[18, q] = f2 * f0, f2 * f1, f2 * f2
            for i in range(C):
                acc[:, :kn] = 0.0
                for e in range(estart[i], estart[i + 1]):
                    fi, o, j = fidx[e], comp[e], cols[e]
                    cm = c[m, j]
                    if not dflag[e]:
                        for q in range(kn):
                            acc[o, q] += F[fi, q] * cm
                    elif nf > 1:
                        for q in range(kn):
                            acc[o, q] += F[fi, q] * cm * fT[j, k0 + q]
                    else:
                        fm = fT[j, 0]
                        for q in range(kn):
                            acc[o, q] += F[fi, q] * cm * fm
                for e in range(gstart[i], gstart[i + 1]):
                    j = gidx[e]
                    gc = gcols[e]
                    cm = c[m, j]
                    for q in range(kn):
                        cj = cm * fT[j, k0 + q if nf > 1 else 0]
                        acc[3, q] += gT[0, gc, k0 + q] * cj
                        acc[4, q] += gT[1, gc, k0 + q] * cj
                        acc[5, q] += gT[2, gc, k0 + q] * cj
                dad[:, :kn] = 0.0
                for e in range(astart[i], astart[i + 1]):
                    j = adidx[e]
                    a = adcols[e]
                    cm = c[m, j]
                    for q in range(kn):
                        dad[a, q] += cm * aT[j, k0 + q]
                r = rows[i] + m
                for q in range(kn):
                    k = k0 + q
                    out_th[r, k, 0] = dth[mb, k, 0] - h * acc[0, q]
                    out_th[r, k, 1] = dth[mb, k, 1] - h * acc[1, q]
                    out_th[r, k, 2] = dth[mb, k, 2] - h * acc[2, q]
                    out_dv[r, k, 0] = dv[mb, k, 0] - h * acc[3, q] - dad[0, q]
                    out_dv[r, k, 1] = dv[mb, k, 1] - h * acc[4, q] - dad[1, q]
                    out_dv[r, k, 2] = dv[mb, k, 2] - h * acc[5, q] - dad[2, q]


@dataclass(frozen=True)
class RecordContext:
    """Reference quantities inside one record (shared by all runs).

    Attributes
    ----------
    d_mid, d_edge : ndarray, shape (k,), (k+1,)
        Distance travelled since the record start at the sample mid-points
        and edges. [m]
    gravity_sensitivity : ndarray, shape (k, 3, 3)
        ``C_n^b diag(g, g, −1)`` at the sample mid-points (reference
        attitude and normal gravity).
    """

    d_mid: np.ndarray
    d_edge: np.ndarray
    gravity_sensitivity: np.ndarray

    @classmethod
    def along(cls, traj, t0: float, h: float, k: int, mounting=None) -> "RecordContext":
        """Context of ``k`` samples of period ``h`` from ``t0``."""
        te = t0 + h * np.arange(k + 1)
        tm = t0 + h * (np.arange(k) + 0.5)
        hi = float(traj.t[-1])
        se = traj.sample(np.minimum(te, hi))
        sm = traj.sample(np.minimum(tm, hi))
        q = sm.q_nb if mounting is None else quat.mul(sm.q_nb, mounting)
        S = np.einsum("kji,kjl->kil", quat.dcm(q), gravity_sensitivity(earth.gravity(sm.lat, sm.h)))
        return cls(sm.distance - se.distance[0], se.distance - se.distance[0], S)
