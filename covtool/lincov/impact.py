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
and summed per member.  Filters with the same navigation options share the
truth transition, its composition over the event grid, and every source
composed on the states it reaches (:class:`covtool.lincov.noise.ComposedCache`,
kept on the study setup): filters C and D take most of theirs from B3's run.

Pure numeric core: a :class:`~covtool.studies.zupt_setup.ZuptSetup` in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from covtool.lincov.batch import events, run_batch, System
from covtool.lincov.discretize import van_loan
from covtool.lincov.stacks import gather
from covtool.lincov.noise import (CombinedNoise, ComposedCache, compose_noise, compose_scan, compose_transition,
                                  restricted_noise)


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
        noise and the filter's own composed ``Q_f`` (the nominal member).
    """

    filter: str
    variants: list
    record_steps: np.ndarray
    P: np.ndarray
    noise_check: float


def dropped_blocks(truth, kept) -> list[str]:
    """Blocks of ``truth`` with at least one state not in ``kept``, in truth order."""
    ks = set(kept)
    return [b for b in truth.block_names() if any(s.block == b and s.name not in ks for s in truth.states)]


def _transition(dyn, dt):
    """Φ = e^{FΔt} per step (the truth F under the filter's options), by :func:`covtool.lincov.discretize.van_loan`.

    ``dyn`` (:class:`~covtool.lincov.dynamics.ErrorDynamics`) gives F one
    chunk of steps at a time (:meth:`~covtool.lincov.dynamics.ErrorDynamics.F_steps`):
    the whole F under the options is never built.  Returns shape (N, n, n).
    """
    dt = np.asarray(dt, float)
    N, n = dt.shape[0], len(dyn.names)
    out = np.empty((N, n, n))
    zero = np.zeros((n, n))
    for a in range(0, N, TRANSITION_CHUNK):
        b = min(N, a + TRANSITION_CHUNK)
        out[a:b] = van_loan(dyn.F_steps(a, b), zero, dt[a:b],
                            what="impact: Φ under the filter's navigation options")[0]
    return out


def impact_run(S, name: str, record_steps, *, truth_system: System | None = None) -> ImpactRun:
    """All variants of one reduced filter in one batched pass.

    Parameters
    ----------
    S : covtool.studies.zupt_setup.ZuptSetup
    name : str
        A declared filter that drops truth states.
    record_steps : array_like of int
        Grid steps at which the truth covariance is recorded.
    truth_system : covtool.lincov.batch.System, optional
        The truth composed on ``events(N, S.update_steps, record_steps)``
        (shared between filters; built if omitted).

    Returns
    -------
    ImpactRun
    """
    from covtool.lincov.dynamics import dyn_key

    truth = S.truth
    fm, Phi_f, Qd_f = S.filter_model(name)
    spec = fm.spec
    n = truth.n
    N = S.t.size - 1
    dt = np.diff(S.t)
    rec = np.asarray(record_steps, int)
    ev = events(N, S.update_steps, rec)
    if truth_system is None:
        truth_system = System.from_steps(S.Phi, S.Qd, ev)
    dyn = S.options_dynamics(spec.options)
    tkey = ("impact transition", dyn_key(spec.options))
    if dyn is S.dyn and S.hdr["discretization"] == "van_loan":
        Phi_pad = S.Phi                                   # the truth's own e^{FΔt}, of these very F
    else:
        # filters that share navigation options share this transition: computed once per study
        if tkey not in S._dyn_cache:
            S._dyn_cache[tkey] = _transition(dyn, dt)
        Phi_pad = S._dyn_cache[tkey]
    # so do the sources' composed noises: a source composed on the states it reaches is the same in
    # every filter of these options that holds them (the kept navigation states, a dropped block's own)
    cache = S._dyn_cache.setdefault(("impact noise",), ComposedCache())
    shared = dict(cache=cache, system=(tkey, Phi_pad is S.Phi, ev.tobytes()))
    kidx = truth.idx(fm.names)
    kset = set(kidx.tolist())
    blocks = dropped_blocks(truth, fm.names)
    block_states = {b: [i for i, s in enumerate(truth.states) if s.block == b] for b in blocks}
    state_block = {s.name: s.block for s in truth.states}
    # --- filter-noise components in the filter's own space
    PhiX = gather(Phi_pad, kidx)
    FX = dyn.F_block(kidx)
    factors = [restricted_noise("kept", dyn.noise, kidx)]
    ewn_of = {b: [src for src in fm.ewn_noise if state_block[src.name] == b] for b in blocks}
    ewn_blocks = [b for b in blocks if ewn_of[b]]
    # the equivalent noises already live in the filter's space (rows = its kept states in order),
    # not the truth's: restricting them by kidx was right only while the kept states led the truth
    factors += [restricted_noise(f"ewn {b}", ewn_of[b], np.arange(len(kidx))) for b in ewn_blocks]
    own_noise = {b: [src for src in dyn.noise if src.name in {truth.states[i].name for i in block_states[b]}]
                 for b in blocks}
    noisy = [b for b in blocks if own_noise[b]]
    factors += [restricted_noise(f"noise {b} on kept", own_noise[b], kidx) for b in noisy]
    QX = compose_noise(PhiX, FX, factors, dt, ev, rows=kidx, **shared)
    components = [(QX[c], kidx) for c in range(len(factors))]
    ci_kept, ci_ewn = 0, {b: 1 + k for k, b in enumerate(ewn_blocks)}
    ci_own_kept = {b: 1 + len(ewn_blocks) + k for k, b in enumerate(noisy)}
    ci_own_full = {}
    # every noisy block's own noise on (kept ∪ that block): in one pass over the union of those rows
    # when no noisy block drives another (no kept state drives a dropped one, F_dropped,kept = 0), for
    # then each source's composed noise on the union is its noise on (kept ∪ its block) bordered by
    # zeros; else one pass per block
    apart = all(not np.any(dyn.F_block(block_states[c], block_states[b]))
                and not np.any(gather(Phi_pad, block_states[c], block_states[b]))
                for b in noisy for c in noisy if c != b)
    for group in ([noisy] if apart else [[b] for b in noisy]) if noisy else []:
        urows = np.array(sorted(kset.union(*(block_states[b] for b in group))))
        Qu = compose_noise(gather(Phi_pad, urows), dyn.F_block(urows),
                           [restricted_noise(f"noise {b}", own_noise[b], urows) for b in group], dt, ev,
                           rows=urows, **shared)
        for j, b in enumerate(group):
            rows = np.array(sorted(kset | set(block_states[b])))
            sub = np.searchsorted(urows, rows)
            ci_own_full[b] = len(components)
            components.append((Qu[j][:, sub[:, None], sub[None, :]], rows))
    # the summed sources against the filter's own composed Q_f
    ref = compose_scan(Phi_f, Qd_f, ev)[1]
    tot = QX[0] + sum(QX[ci_ewn[b]] for b in ewn_blocks)
    d = np.sqrt(np.clip(np.einsum("kii->ki", ref), 0, None))
    den = d[:, :, None] * d[:, None, :]
    m = den > 0
    noise_check = float((np.abs(tot - ref)[m] / den[m]).max()) if m.any() else 0.0
    # --- members
    P0t = S.P0
    P0f = np.zeros((n, n))
    P0f[np.ix_(kidx, kidx)] = fm.P0
    absorb = {b: sum((truth.states[truth.index[nm]].sigma ** 2 * np.outer(a, a)
                      for nm, a in fm.ewn_absorb.items() if state_block[nm] == b), np.zeros((len(kidx),) * 2))
              for b in blocks}

    def embed(M):
        out = np.zeros((n, n))
        out[np.ix_(kidx, kidx)] = M
        return out

    all_absorb = embed(sum(absorb.values(), np.zeros((len(kidx),) * 2)))
    variants, P0s, coefs = [], [], []

    def member(variant, block, P0, coef):
        variants.append((variant, block))
        P0s.append(P0)
        c = np.zeros(len(components))
        for k, v in coef.items():
            c[k] += v
        coefs.append(c)

    base = {ci_kept: 1.0}
    member(NOMINAL, None, P0f, {**base, **{ci_ewn[b]: 1.0 for b in ewn_blocks}})
    member(NONE, None, P0f - all_absorb, base)
    for b in blocks:
        only = dict(base)
        if b in ci_ewn:
            only[ci_ewn[b]] = 1.0
        member(ONLY, b, P0f - all_absorb + embed(absorb[b]), only)
        back = {**base, **{ci_ewn[x]: 1.0 for x in ewn_blocks if x != b}}
        if b in ci_own_full:
            back[ci_own_kept[b]] = back.get(ci_own_kept[b], 0.0) - 1.0
            back[ci_own_full[b]] = 1.0
        P = P0f - embed(absorb[b])
        bi = np.array(block_states[b])
        P[np.ix_(bi, bi)] = P0t[np.ix_(bi, bi)]
        if not spec.P0_sigma:
            P[np.ix_(bi, kidx)] = P0t[np.ix_(bi, kidx)]
            P[np.ix_(kidx, bi)] = P0t[np.ix_(kidx, bi)]
        member(BACK, b, P, back)
    # the embedded filters of one transition share its composition over the event grid
    ckey = ("impact composed transition", shared["system"])
    if ckey not in S._dyn_cache:
        # under the truth's own options that is the truth's composed transition, already at hand
        same = Phi_pad is S.Phi and np.array_equal(truth_system.ev, ev)
        S._dyn_cache[ckey] = truth_system.Phi if same else compose_transition(Phi_pad, ev)
    Phi_c = S._dyn_cache[ckey]
    filt = System(ev, Phi_c, np.zeros((len(ev) - 1, 0, 0)))
    fQ = CombinedNoise(components, np.array(coefs), n)
    res = run_batch(truth_system, P0t, S.H, S.R, np.eye(n), S.update_steps, rec, filt=filt,
                    Pf0=np.array(P0s), Hf=S.H, Rf=S.filter_R(name)[None], filter_Q=fQ, form=spec.update)
    check_members(res.P_truth, S.nodes.q_nb[res.record_steps], S.t[res.record_steps],
                  [f"impact: filter {name}: {v}" + (f" ({b})" if b else "") for v, b in variants])
    return ImpactRun(name, variants, res.record_steps, res.P_truth, noise_check)


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
    """
    from covtool.lincov.dynamics import physical_nav
    from covtool.lincov.kalman import check_covariance

    for b, lab in enumerate(labels):
        Pp = physical_nav(P[b], q)
        for k in range(Pp.shape[0]):
            check_covariance(Pp[k], f"{lab}: t = {t[k]:g} s")
