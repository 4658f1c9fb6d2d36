"""Dropped-state impact: what each block a reduced filter drops costs it.

The state-deletion analysis of D'Appolito (seed 002 ref [13]): for a reduced
filter and every truth block it drops, the filter's *true* error (the truth
covariance under its gains, seed 002 eq (15)–(16)) is computed

* ``"nominal"``: as declared (equivalent noise of every dropped block);
* ``"no equivalent noise"``: the dropped states ignored;
* ``"noise from <block> only"``: eq (11)–(13) noise of that block alone;
* ``"<block> put back"``: that block kept as filter states (its truth P0
  and driving noise), the other dropped blocks still as equivalent noise.

All variants of one filter run in one batched engine call
(:func:`covtool.lincov.batch.run_batch`).  Every variant is embedded in the truth's
state space: the filter carries all 58 states with the truth's F under the
filter's :class:`~covtool.lincov.dynamics.NavOptions`, and the states a variant does
not keep have zero P_f(0) and zero noise.  Because no kept state drives a
sensor or environment state (``F_dropped,kept = 0``), those states keep zero
covariance and zero gain, and the kept block of the transition is exactly the
reduced filter's own: the embedding changes nothing but the bookkeeping.  The
members differ only in P_f(0) and in the filter noise, which is linear in its
sources and therefore composed once per source (:func:`covtool.lincov.noise.compose_noise`)
and summed per member.

The compositions stream in time (:func:`impact_runs`): one chunk of
:data:`~covtool.lincov.dynamics.STREAM_CHUNK` steps at a time, each composed on
its own events (the ZUPTs, the records and the chunk boundaries) and joined,
so memory is set by the events, not by duration × n².  Filters with the same
navigation options share each chunk's truth transition under them, and every
source composed on the states it reaches (:class:`covtool.lincov.noise.ComposedCache`,
kept on the study setup): filters C and D take most of theirs from B3's run.

Pure numeric core: a :class:`~covtool.studies.zupt_setup.ZuptSetup` in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from covtool.lincov.batch import events, run_batch, System
from covtool.errors import NumericalError
from covtool.lincov.discretize import van_loan
from covtool.lincov.discretize.steps import on_grid
from covtool.lincov.stacks import gather
from covtool.lincov.reduced import system_key
from covtool.lincov.noise import CombinedNoise, compose_noise, compose_scan, compose_transition, \
    restricted_noise


#: steps discretised at once by :func:`_transition` (bounds its workspace)
TRANSITION_CHUNK = 150

NOMINAL, NONE, ONLY, BACK = "nominal", "no equivalent noise", "noise from block only", "block put back"


@dataclass
class ImpactRun:
    """Truth covariance of every variant of one filter.

    Attributes
    ----------
    filter : str
    variants : list of (str, str or None)
        ``(variant, block)`` per member, ``block`` None for the nominal and
        no-noise members.
    record_steps : ndarray of int
    P : ndarray, shape (B, n_rec, 10, 10)
        Truth navigation covariance per member.
    noise_check : float
        Largest relative difference between the summed per-source filter
        noise and the filter's own composed ``Q_f`` (the nominal member),
        relative to ``√(Q_f,ii Q_f,jj)``; NaN until checked
        (:func:`check_filter_noise`).
    events : ndarray of int, shape (K+1,)
        The event grid the noise was composed on.
    noise_total : ndarray, shape (K, n_f, n_f)
        That summed filter noise over each interval of ``events`` (the
        filter's kept states).
    """

    filter: str
    variants: list
    record_steps: np.ndarray
    P: np.ndarray
    noise_check: float
    events: np.ndarray | None = None
    noise_total: np.ndarray | None = None


def check_filter_noise(run: ImpactRun, Phi_f, Qd_f) -> ImpactRun:
    """Set ``run.noise_check`` against the filter's own Φ_f, Q_f (seed 002 eq (6b)–(6d), (11)–(13)).

    Parameters
    ----------
    run : ImpactRun
        With its ``events`` and ``noise_total``.
    Phi_f, Qd_f : ndarray, shape (N, n_f, n_f)
        The filter's own discretisation over the grid (or any object whose
        slices ``[a:b]`` give it), composed here on ``run.events``.

    Returns
    -------
    ImpactRun
        ``run``, its ``noise_check`` set (the largest over the intervals,
        relative to ``√(Q_f,ii Q_f,jj)``).
    """
    Qf = compose_scan(Phi_f, Qd_f, run.events)[1]
    run.noise_check = _noise_difference(run.noise_total, Qf)
    return run


def _noise_difference(tot: np.ndarray, Qf: np.ndarray) -> float:
    """Largest ``|tot − Q_f|_ij / √(Q_f,ii Q_f,jj)`` over the intervals (0 where Q_f has no variance)."""
    d = np.sqrt(np.clip(np.einsum("kii->ki", Qf), 0, None))
    den = d[:, :, None] * d[:, None, :]
    m = den > 0
    return float((np.abs(tot - Qf)[m] / den[m]).max()) if m.any() else 0.0


def dropped_blocks(truth, kept) -> list[str]:
    """Blocks of ``truth`` with at least one state not in ``kept``, in truth order."""
    ks = set(kept)
    return [b for b in truth.block_names() if any(s.block == b and s.name not in ks for s in truth.states)]


def _transition(F, dt, *, what: str = "", times=None, first: int = 0):
    """Φ = e^{FΔt} per step of ``F`` (the truth's F under a filter's options), by :func:`covtool.lincov.discretize.van_loan`.

    ``F`` has shape (L, n, n) (one chunk of steps from grid step ``first``),
    ``dt`` and ``times`` (start time of each step [s]) shape (L,);
    discretised :data:`TRANSITION_CHUNK` steps at a time (bounds the
    workspace).  Returns shape (L, n, n).

    Raises
    ------
    covtool.errors.NumericalError
        Non-finite F or a Φ that is not representable, naming ``what``, the
        grid step and its time.
    """
    dt = np.asarray(dt, float)
    L, n = F.shape[0], F.shape[1]
    out = np.empty((L, n, n))
    zero = np.zeros((n, n))
    for a in range(0, L, TRANSITION_CHUNK):
        b = min(L, a + TRANSITION_CHUNK)
        try:
            out[a:b] = van_loan(F[a:b], zero, dt[a:b], what=what,
                                times=None if times is None else times[a:b])[0]
        except NumericalError as e:
            on_grid(e, first + a)
            raise
    return out


class _FilterImpact:
    """One reduced filter's variants: the structure once, the compositions chunk by chunk in time.

    The components of the members' filter noise (module notes) are each
    composed over the event intervals of one chunk at a time
    (:meth:`add_chunk`) and joined in time by :meth:`finish`, which runs
    every member in one batched pass.  Nothing of size N × n² is held.
    """

    def __init__(self, S, name: str):
        truth = S.truth
        self.name = name
        self.fm = fm = S.filter_stream(name)[0]
        self.spec = fm.spec
        self.kidx = kidx = truth.idx(fm.names)
        self.kset = set(kidx.tolist())
        self.blocks = blocks = dropped_blocks(truth, fm.names)
        self.block_states = {b: [i for i, s in enumerate(truth.states) if s.block == b] for b in blocks}
        state_block = {s.name: s.block for s in truth.states}
        self.state_block = state_block
        # the equivalent noises live in the filter's space (rows = its kept states in order), not the truth's
        self.ewn_of = {b: [src for src in fm.ewn_noise if state_block[src.name] == b] for b in blocks}
        self.ewn_blocks = [b for b in blocks if self.ewn_of[b]]
        # a dropped block's own driving noise, by source name (the same sources in every chunk)
        stream = S.dynamics_stream(self.spec.options)
        names = {b: {truth.states[i].name for i in self.block_states[b]} for b in blocks}
        self.own_names = {b: [nm for nm in sorted(stream.sources) if nm in names[b]] for b in blocks}
        self.noisy = [b for b in blocks if self.own_names[b]]
        e, m = len(self.ewn_blocks), len(self.noisy)
        self.ci_ewn = {b: 1 + k for k, b in enumerate(self.ewn_blocks)}
        self.ci_own_kept = {b: 1 + e + k for k, b in enumerate(self.noisy)}
        self.ci_own_full = {b: 1 + e + m + k for k, b in enumerate(self.noisy)}
        self.own_rows = {b: np.array(sorted(self.kset | set(self.block_states[b]))) for b in self.noisy}
        self.parts = [[] for _ in range(1 + e + 2 * m)]      # per component: its composed noise per chunk
        self.transitions = []                                 # the embedded filter's Φ per chunk's intervals
        self.totals = []                                      # its summed own noise per chunk's intervals
        self.noise_check = 0.0

    def add_chunk(self, a: int, cev, dyn, Phi_pad, dt, cache, system, Phi_c, ref):
        """Compose the chunk's noise components and transition over its event intervals.

        Parameters
        ----------
        a : int
            First grid step of the chunk.
        cev : ndarray of int
            The chunk's events (grid steps, ``cev[0] == a``).
        dyn : covtool.lincov.dynamics.ErrorDynamics
            The chunk's truth dynamics under the filter's options (its own
            model's: :meth:`~covtool.studies.zupt_setup.ZuptSetup.chunk_dynamics`).
        Phi_pad : ndarray, shape (L, n, n)
            e^{FΔt} of those dynamics per step.
        dt : ndarray, shape (L,)
        cache : ComposedCache
        system : hashable
            Names ``Phi_pad`` and ``dyn`` for ``cache`` (with the chunk).
        Phi_c : ndarray, shape (K_c, n, n) or None
            ``Phi_pad`` composed over the chunk's intervals, if already at hand.
        ref : tuple of ndarray, or None
            The filter's own Φ_f, Q_f of the chunk's steps (the noise check);
            None: checked later (:func:`check_filter_noise`).
        """
        ev = np.asarray(cev, int) - a
        kidx, kset = self.kidx, self.kset
        bs = self.block_states
        shared = dict(cache=cache, system=system)
        own = {b: [src for src in dyn.noise if src.name in set(self.own_names[b])] for b in self.noisy}
        PhiX = gather(Phi_pad, kidx)
        FX = gather(dyn.F, kidx)
        factors = [restricted_noise("kept", dyn.noise, kidx)]
        factors += [restricted_noise(f"ewn {b}", [src.steps(a, a + len(dt)) for src in self.ewn_of[b]],
                                     np.arange(len(kidx))) for b in self.ewn_blocks]
        factors += [restricted_noise(f"noise {b} on kept", own[b], kidx) for b in self.noisy]
        QX = compose_noise(PhiX, FX, factors, dt, ev, rows=kidx, **shared)
        for c in range(len(factors)):
            self.parts[c].append(QX[c])
        # every noisy block's own noise on (kept ∪ that block): in one pass over the union of those rows
        # when no noisy block drives another (no kept state drives a dropped one, F_dropped,kept = 0), for
        # then each source's composed noise on the union is its noise on (kept ∪ its block) bordered by
        # zeros; else one pass per block
        noisy = self.noisy
        apart = True
        if len(noisy) > 1:
            # one pass over the noisy blocks' states, then each pair's block of that pattern
            u = np.concatenate([bs[b] for b in noisy])
            at = np.cumsum([0] + [len(bs[b]) for b in noisy])
            drives = (gather(dyn.F, u) != 0).any(axis=0) | (gather(Phi_pad, u) != 0).any(axis=0)
            apart = all(not drives[at[i]:at[i + 1], at[k]:at[k + 1]].any()
                        for i in range(len(noisy)) for k in range(len(noisy)) if k != i)
        for group in ([noisy] if apart else [[b] for b in noisy]) if noisy else []:
            urows = np.array(sorted(kset.union(*(bs[b] for b in group))))
            Qu = compose_noise(gather(Phi_pad, urows), gather(dyn.F, urows),
                               [restricted_noise(f"noise {b}", own[b], urows) for b in group], dt, ev,
                               rows=urows, **shared)
            for j, b in enumerate(group):
                sub = np.searchsorted(urows, self.own_rows[b])
                self.parts[self.ci_own_full[b]].append(Qu[j][:, sub[:, None], sub[None, :]])
        # the summed sources against the filter's own composed Q_f
        tot = QX[0] + sum(QX[self.ci_ewn[b]] for b in self.ewn_blocks)
        self.totals.append(tot)
        if ref is None:
            self.noise_check = np.nan
        elif not np.isnan(self.noise_check):
            self.noise_check = max(self.noise_check, _noise_difference(tot, compose_scan(ref[0], ref[1], ev)[1]))
        self.transitions.append(compose_transition(Phi_pad, ev) if Phi_c is None else Phi_c)

    def finish(self, S, truth_system, record_steps) -> ImpactRun:
        """Every member run against ``truth_system`` (composed on the same events) in one batched pass."""
        truth, fm, spec, kidx = S.truth, self.fm, self.spec, self.kidx
        n = truth.n
        state_block = self.state_block
        rows = [kidx] * (1 + len(self.ewn_blocks) + len(self.noisy)) + [self.own_rows[b] for b in self.noisy]
        components = [(np.concatenate(p, axis=0), r) for p, r in zip(self.parts, rows)]
        self.parts = None
        P0t = S.P0
        P0f = np.zeros((n, n))
        P0f[np.ix_(kidx, kidx)] = fm.P0
        nk = len(kidx)
        absorb = {b: sum((truth.states[truth.index[nm]].sigma ** 2 * np.outer(a, a)
                          for nm, a in fm.ewn_absorb.items() if state_block[nm] == b), np.zeros((nk, nk)))
                  for b in self.blocks}

        def embed(M):
            out = np.zeros((n, n))
            out[np.ix_(kidx, kidx)] = M
            return out

        all_absorb = embed(sum(absorb.values(), np.zeros((nk, nk))))
        variants, P0s, coefs = [], [], []

        def member(variant, block, P0, coef):
            variants.append((variant, block))
            P0s.append(P0)
            c = np.zeros(len(components))
            for k, v in coef.items():
                c[k] += v
            coefs.append(c)

        ci_ewn, ci_own_kept, ci_own_full = self.ci_ewn, self.ci_own_kept, self.ci_own_full
        base = {0: 1.0}
        member(NOMINAL, None, P0f, {**base, **{ci_ewn[b]: 1.0 for b in self.ewn_blocks}})
        member(NONE, None, P0f - all_absorb, base)
        for b in self.blocks:
            only = dict(base)
            if b in ci_ewn:
                only[ci_ewn[b]] = 1.0
            member(ONLY, b, P0f - all_absorb + embed(absorb[b]), only)
            back = {**base, **{ci_ewn[x]: 1.0 for x in self.ewn_blocks if x != b}}
            if b in ci_own_full:
                back[ci_own_kept[b]] = back.get(ci_own_kept[b], 0.0) - 1.0
                back[ci_own_full[b]] = 1.0
            P = P0f - embed(absorb[b])
            bi = np.array(self.block_states[b])
            P[np.ix_(bi, bi)] = P0t[np.ix_(bi, bi)]
            if not spec.P0_sigma:
                P[np.ix_(bi, kidx)] = P0t[np.ix_(bi, kidx)]
                P[np.ix_(kidx, bi)] = P0t[np.ix_(kidx, bi)]
            member(BACK, b, P, back)
        ev = truth_system.ev
        filt = System(ev, np.concatenate(self.transitions, axis=0), np.zeros((len(ev) - 1, 0, 0)))
        self.transitions = None
        fQ = CombinedNoise(components, np.array(coefs), n)
        res = run_batch(truth_system, P0t, S.H, S.R, np.eye(n), S.update_steps, record_steps, filt=filt,
                        Pf0=np.array(P0s), Hf=S.H, Rf=S.filter_R(self.name)[None], filter_Q=fQ, form=spec.update)
        check_members(res.P_truth, S.nodes.q_nb[res.record_steps], S.t[res.record_steps],
                      [f"impact: filter {self.name}: {v}" + (f" ({b})" if b else "") for v, b in variants])
        return ImpactRun(self.name, variants, res.record_steps, res.P_truth, self.noise_check, ev,
                         np.concatenate(self.totals, axis=0))


def impact_runs(S, names, record_steps, *, own_systems: bool = True) -> list[ImpactRun]:
    """All variants of each reduced filter, streamed in time: one pass over the grid's chunks.

    Parameters
    ----------
    S : covtool.studies.zupt_setup.ZuptSetup
    names : sequence of str
        Declared filters that drop truth states.
    record_steps : array_like of int
        Grid steps at which the truth covariance is recorded.
    own_systems : bool
        Each filter's own Φ_f, Q_f for its noise check are sliced from the
        whole grid where ``S`` holds them, else made chunk by chunk; False:
        those ``S`` does not hold are not made, and their check is left to
        :func:`check_filter_noise` (a forked share whose parent holds them:
        ``noise_check`` NaN until then).

    Returns
    -------
    list of ImpactRun
        In the order of ``names``.

    Raises
    ------
    covtool.errors.NumericalError
        A chunk's truth or filter Φ or Q_d is not finite (Q_d: symmetric,
        PSD; :meth:`~covtool.studies.zupt_setup.ZuptSetup.truth_chunk`,
        :meth:`~covtool.studies.zupt_setup.ZuptSetup.filter_chunk`); the
        truth's Φ under a filter's navigation options is not (naming the
        study, every filter of this process with those options, the grid
        step and its time); or a member's recorded covariance is not (naming the filter,
        the member and the time).

    Notes
    -----
    The events are the ZUPTs, the records and the chunk boundaries of
    :meth:`~covtool.studies.zupt_setup.ZuptSetup.stream`; each chunk of
    :data:`~covtool.lincov.dynamics.STREAM_CHUNK` steps is discretised and
    composed on its own events (the truth's Φ, Q_d sliced from the whole
    grid where a study holds it), so that memory is set by the events, not
    by duration × n².  In each chunk the truth's F under each set of
    navigation options and its transition are made once for every filter
    of those options, and a source composed on the states it reaches is
    shared between them (:class:`covtool.lincov.noise.ComposedCache`, kept
    on the study setup): filters C and D take most of theirs from B3's.
    """
    from covtool.lincov.batch import compose
    from covtool.lincov.dynamics import dyn_key

    if not names:
        return []
    N = S.t.size - 1
    rec = np.asarray(record_steps, int)
    ev = S.stream_grid(events(N, S.update_steps, rec))
    dt = np.diff(S.t)
    plans = [_FilterImpact(S, name) for name in names]
    cache = S.composed_cache()
    truth_parts = []
    for a, b, cev in S.chunks(ev):
        dyn_of = S.chunk_dynamics(a, b)
        Phi_t, Qd_t = S.truth_chunk(a, b, dyn_of)
        tpart = System(cev, *compose(Phi_t, Qd_t, cev - a))
        truth_parts.append(tpart)
        transitions, refs = {}, []
        for plan in plans:
            options = plan.spec.options
            own = S.truth_transition_serves(options)        # the truth's own e^{FΔt}, of these very F
            dyn = dyn_of(options)
            okey = dyn_key(options)
            if own:
                Phi_pad, Phi_c = Phi_t, tpart.Phi
            else:
                if okey not in transitions:
                    # one transition serves every filter of these options: the message names them all
                    share = [p.name for p in plans if dyn_key(p.spec.options) == okey]
                    whose = f"filter {share[0]}: truth Φ under its" if len(share) == 1 else \
                        f"filters {', '.join(share)}: truth Φ under their"
                    Phi = _transition(dyn.F, dt[a:b], times=S.t[a:b], first=a,
                                      what=f"{S.where}: impact: {whose} navigation options")
                    transitions[okey] = Phi, compose_transition(Phi, cev - a)     # and over the intervals
                Phi_pad, Phi_c = transitions[okey]
            # the filter's own Φ_f, Q_f for its noise check (twins share them)
            key = system_key(plan.spec)
            found = [v for k, v in refs if k == key]
            ref = found[0] if found else S.filter_chunk(plan.name, a, b, dyn_of, make=own_systems)
            if not found:
                refs.append((key, ref))
            system = ("impact transition", okey, own, a, b)
            plan.add_chunk(a, cev, dyn, Phi_pad, dt[a:b], cache, system, Phi_c, ref)
        del Phi_t, Qd_t, transitions, refs
    tsys = System.concat(truth_parts)
    del truth_parts
    return [plan.finish(S, tsys, rec) for plan in plans]


def impact_run(S, name: str, record_steps) -> ImpactRun:
    """All variants of one reduced filter in one batched pass (:func:`impact_runs` of ``[name]``).

    Parameters
    ----------
    S : covtool.studies.zupt_setup.ZuptSetup
    name : str
        A declared filter that drops truth states.
    record_steps : array_like of int
        Grid steps at which the truth covariance is recorded.

    Returns
    -------
    ImpactRun
    """
    return impact_runs(S, [name], record_steps)[0]


def check_members(P: np.ndarray, q: np.ndarray, t: np.ndarray, labels) -> None:
    """Check every member's recorded navigation covariance (finite, symmetric, PSD).

    Parameters
    ----------
    P : ndarray, shape (B, n_rec, 10, 10)
    q : ndarray, shape (n_rec, 4)
        Attitude at the records (checked in physical tilt/azimuth coordinates,
        where the structurally zero quaternion-norm direction is left out).
    t : ndarray, shape (n_rec,)
    labels : list of str

    Raises
    ------
    covtool.errors.NumericalError
        Naming the member and the time.
    ValueError
        ``labels`` does not name every member.
    """
    from covtool.lincov.dynamics import physical_nav
    from covtool.lincov.guard import covariance_status, scale_groups

    # every member and record in one batched test (the test of each matrix on its own, as
    # check_covariance makes it); the first failure in member order, then time, is reported
    if len(labels) != P.shape[0]:
        raise ValueError(f"check_members: {len(labels)} labels for {P.shape[0]} members")
    Pp = physical_nav(P, q)
    st = covariance_status(Pp, groups=scale_groups(None, Pp.shape[-1]))
    if st.ok.all():
        return
    b, k = np.unravel_index(int(np.flatnonzero(~st.ok.ravel())[0]), st.code.shape)
    raise NumericalError(f"{labels[b]}: t = {t[k]:g} s: {st.problem((b, k))}")
