"""Error budget: the truth covariance split exactly by source.

With the filter gains held fixed (those of the nominal filter run, SOFE
style), the truth recursion of seed 002 eq (15)–(16)::

    P_{k+1} = Φ_k P_k Φ_kᵀ + Q_k
    P⁺      = (I − D K H) P (I − D K H)ᵀ + D K R Kᵀ Dᵀ

is linear in the triple (P0, Q, R).  Splitting

    P0 = Σ_g P0_g + P0_cross,   Q_k = Σ_j Q_k,j,   R

and propagating each piece alone (the others zero) gives contributions
``P_b(t)`` that sum to the total ``P(t)`` up to round-off.  Every piece is a
member of one batched run (:func:`covtool.lincov.batch.run_batch`), so the budget
costs one pass with B = number of sources, not B runs.

Sources (``resolution = "block"``):

* initial conditions: one per block of the truth model; the navigation block
  is split into position, velocity, tilt and azimuth (the quaternion σ are
  declared for the body aligned with NED, seed 002 Table 2, so δq1, δq2 are
  the tilts and δq3 the azimuth there);
* initial cross-covariances between groups, if the model declares any;
* process noise: ARW, VRW and the driving noise of each Markov/random-walk
  block;
* the ZUPT measurement noise R.

``resolution = "state"`` gives one initial source per state and one noise
source per :class:`covtool.lincov.dynamics.NoiseSource`.

Pure numeric core (models and arrays in, arrays out).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from covtool.analysis.metrics import ned_position_covariance
from covtool.lincov.batch import run_batch, System
from covtool.lincov.dynamics import attitude_errors, NoiseSource, physical_nav
from covtool.lincov.kalman import symmetrize
from covtool.lincov.noise import MemberNoise


#: groups of the navigation block (seed 002 eq (14)), in reference-attitude quaternion components
NAV_GROUPS = {
    "position": ("dL", "dl", "dh"),
    "velocity": ("dvN", "dvE", "dvD"),
    "tilt": ("dq1", "dq2"),
    "azimuth": ("dq3",),
    "quaternion norm": ("dq0",),
}

#: navigation errors a budget is reported for, with their paper unit
ERRORS = ("horizontal", "altitude", "azimuth")

RESOLUTIONS = ("block", "state")

#: kinds of source
INITIAL, CORRELATION, PROCESS, MEASUREMENT = "initial", "correlation", "process", "measurement"


@dataclass
class Source:
    """One contribution of the budget.

    Attributes
    ----------
    name : str
        Label, e.g. ``"initial azimuth"``, ``"acc_markov noise"``.
    kind : {"initial", "correlation", "process", "measurement"}
    states : tuple of str
        Truth states whose initial σ or driving noise this source is.
    P0 : ndarray, shape (n, n), or None
        Initial covariance of this source alone.
    noise : int or None
        Index into the per-source noise factors (:func:`compose_noise`).
    R : ndarray, shape (m, m), or None
        True measurement noise of this source alone.
    """

    name: str
    kind: str
    states: tuple
    P0: np.ndarray | None = None
    noise: int | None = None
    R: np.ndarray | None = None


# ---------------------------------------------------------------------------
# sources


def initial_groups(model, resolution: str = "block") -> dict[str, tuple]:
    """Groups of truth states whose initial errors form one source.

    Parameters
    ----------
    model : covtool.lincov.model.spec.Model
    resolution : {"block", "state"}

    Returns
    -------
    dict of str to tuple of str
        Group label -> state names.  Every state is in exactly one group.
    """
    if resolution not in RESOLUTIONS:
        raise ValueError(f"unknown budget resolution {resolution!r} (one of: {', '.join(RESOLUTIONS)})")
    if resolution == "state":
        nav_group = {x: g for g, st in NAV_GROUPS.items() for x in st}
        return {(f"{s.name} ({nav_group[s.name]})" if s.kind == "navigation" and s.name in nav_group else s.name):
                (s.name,) for s in model.states}
    out = {}
    names = set(model.names)
    nav_block = {s.block for s in model.states if s.kind == "navigation"}
    for block in model.block_names():
        members = tuple(s.name for s in model.states if s.block == block)
        if block in nav_block:
            for g, st in NAV_GROUPS.items():
                sel = tuple(x for x in st if x in names and x in members)
                if sel:
                    out[g] = sel
            rest = tuple(x for x in members if not any(x in st for st in NAV_GROUPS.values()))
            if rest:
                out[block] = rest
        else:
            out[block] = members
    return out


def split_initial(model, groups: dict, q0=None) -> tuple[list, np.ndarray | None]:
    """Split the truth P0 into group pieces plus the cross terms.

    Parameters
    ----------
    model : covtool.lincov.model.spec.Model
    groups : dict of str to tuple of str
        From :func:`initial_groups`.
    q0 : array_like, shape (4,), optional
        Initial attitude (see :meth:`Model.initial_covariance`).

    Returns
    -------
    pieces : list of (str, ndarray of shape (n, n))
        Groups with a non-zero initial covariance, in model order.
    cross : ndarray, shape (n, n), or None
        ``P0 − Σ pieces`` if the model correlates states of different
        groups, else None.

    Notes
    -----
    Each piece is the model's own P0 with every σ outside the group set to
    zero, so its correlations inside the group are kept and the rotation of
    the quaternion block to ``q0`` (a congruence, linear in P0) is applied
    by the model itself.  The cross piece may be indefinite: its
    contributions can be negative.
    """
    P0 = model.initial_covariance(q0)
    pieces = []
    for g, members in groups.items():
        keep = set(members)
        states = [s if s.name in keep else dataclasses.replace(s, sigma=0.0) for s in model.states]
        if not any(s.sigma != 0.0 for s in states):
            continue
        Pg = model.replace_states(states).initial_covariance(q0)
        pieces.append((g, Pg))
    group_of = {nm: g for g, members in groups.items() for nm in members}
    sig = {s.name: s.sigma for s in model.states}
    crossing = [c for c in model.correlations
                if group_of[c[0]] != group_of[c[1]] and c[2] != 0 and sig[c[0]] != 0 and sig[c[1]] != 0]
    cross = None
    if crossing:
        cross = P0 - sum(P for _, P in pieces)
        cross = symmetrize(cross)
    return pieces, cross


def noise_factors(model, noise, resolution: str = "block") -> list[NoiseSource]:
    """Group the truth's driving noises into budget sources.

    Parameters
    ----------
    model : covtool.lincov.model.spec.Model
    noise : list of covtool.lincov.dynamics.NoiseSource
        The truth dynamics' noise sources (``ErrorDynamics.noise``).
    resolution : {"block", "state"}
        ``"block"``: the noises of one block's states form one source (ARW
        and VRW are sources of their own); ``"state"``: one per NoiseSource.

    Returns
    -------
    list of NoiseSource
        Concatenating a block's columns keeps ``Σ G diag(psd) Gᵀ`` exact.
    """
    if resolution not in RESOLUTIONS:
        raise ValueError(f"unknown budget resolution {resolution!r} (one of: {', '.join(RESOLUTIONS)})")
    block_of = {s.name: s.block for s in model.states}
    groups: dict[str, list] = {}
    for src in noise:
        key = src.name if resolution == "state" else block_of.get(src.name, src.name)
        groups.setdefault(key, []).append(src)
    out = []
    for key, srcs in groups.items():
        G = np.concatenate([s.G for s in srcs], axis=2)
        psd = np.concatenate([s.psd for s in srcs], axis=1)
        out.append(NoiseSource(key, G, psd))
    return out


def budget_sources(model, noise, q0, R=None, *, resolution: str = "block") -> tuple[list, list]:
    """All sources of a budget: initial groups, cross terms, noises, R.

    Parameters
    ----------
    model : covtool.lincov.model.spec.Model
        The truth model.
    noise : list of covtool.lincov.dynamics.NoiseSource
    q0 : array_like, shape (4,)
        Initial attitude.
    R : ndarray, shape (m, m), optional
        True measurement noise; None for a pure INS.
    resolution : {"block", "state"}

    Returns
    -------
    sources : list of Source
    factors : list of NoiseSource
        Indexed by ``Source.noise``.
    """
    groups = initial_groups(model, resolution)
    pieces, cross = split_initial(model, groups, q0)
    sources = [Source(f"initial {g}", INITIAL, groups[g], P0=P) for g, P in pieces]
    if cross is not None:
        sources.append(Source("initial cross-correlations", CORRELATION,
                              tuple(sorted({a for c in model.correlations for a in c[:2]})), P0=cross))
    factors = noise_factors(model, noise, resolution)
    block_states = {}
    for s in model.states:
        block_states.setdefault(s.block, []).append(s.name)
    for j, f in enumerate(factors):
        states = tuple(block_states.get(f.name, [f.name])) if f.name not in ("arw", "vrw") else ()
        if resolution == "state" and f.name in model.index:
            states = (f.name,)
        sources.append(Source(f"{f.name} noise", PROCESS, states, noise=j))
    if R is not None:
        sources.append(Source("ZUPT measurement noise", MEASUREMENT, ("dvN", "dvE", "dvD"), R=np.asarray(R, float)))
    return sources, factors


# ---------------------------------------------------------------------------
# the one-pass budget run


@dataclass
class BudgetRun:
    """Contributions of every source at the record steps.

    Attributes
    ----------
    sources : list of Source
    record_steps : ndarray of int
    P : ndarray, shape (B, n_rec, k, k)
        Contribution of each source (the ``keep`` sub-block).
    P_total : ndarray, shape (n_rec, k, k)
        The run with every source at once (same gains, same per-source
        ``Q_d`` summed), carried in the same batch.
    """

    sources: list
    record_steps: np.ndarray
    P: np.ndarray
    P_total: np.ndarray


def run_budget(truth: System, sources: list, Qn: np.ndarray, P0: np.ndarray, H: np.ndarray, R: np.ndarray,
               D: np.ndarray, gains: np.ndarray | None, update_steps, record_steps, *,
               keep=slice(0, 10), label: str = "error budget", names=None,
               times=None) -> BudgetRun:
    """Every source alone, and the total, in one batched pass.

    Parameters
    ----------
    truth : System
        Composed truth Φ on the event grid (its ``Q`` is not used).
    sources : list of Source
    Qn : ndarray, shape (J, K, n, n)
        Composed per-source noise (:func:`compose_noise`).
    P0 : ndarray, shape (n, n)
        Total initial covariance (for the total member).
    H : ndarray, shape (m, n)
    R : ndarray, shape (m, m)
        Total true measurement noise (for the total member).
    D : ndarray, shape (n, n_f)
    gains : ndarray, shape (1, n_upd, n_f, m), or None
        The nominal filter's gains at ``update_steps``; None for a pure INS.
    update_steps, record_steps : iterable of int
        Event indices of ``truth.ev``.
    keep : slice or index array
        Recorded sub-block (default: the navigation states).
    label : str
        Names the budget in messages; ``names`` (truth state names) and
        ``times`` (grid times [s]) name the state and the time.

    Returns
    -------
    BudgetRun

    Raises
    ------
    NumericalError
        A source's input (P0 piece, per-source Q_d, R) or its contribution
        is not finite and symmetric, or not PSD (every source but the
        cross-covariance piece, which may be indefinite, and the total),
        naming the source, the time and the state
        (:func:`covtool.lincov.batch.run_batch`).
    """
    n = truth.n
    m = H.shape[0]
    upd = [int(k) for k in update_steps]
    if gains is None:
        if upd:
            raise ValueError("update steps given without gains")
        D = np.eye(n)
        gains = np.zeros((1, 0, n, m))
    B = len(sources) + 1
    P0s = np.zeros((B, n, n))
    Rs = np.zeros((B, m, m))
    arrays = []
    for b, s in enumerate(sources):
        if s.P0 is not None:
            P0s[b] = s.P0
        if s.R is not None:
            Rs[b] = s.R
        arrays.append(Qn[s.noise] if s.noise is not None else None)
    P0s[-1] = P0
    Rs[-1] = R
    arrays.append(Qn.sum(axis=0) if len(Qn) else None)
    K = len(truth.ev) - 1
    psd = np.array([s.kind != CORRELATION for s in sources] + [True])
    res = run_batch(truth, P0s, H, Rs, D, upd, record_steps, gains=gains, truth_Q=MemberNoise(arrays, K, n),
                    keep=keep, label=label, cases=[s.name for s in sources] + ["total"],
                    names=names, times=times, psd_cases=psd, scale_case=len(sources))
    return BudgetRun(list(sources), res.record_steps, res.P_truth[:-1], res.P_truth[-1])


# ---------------------------------------------------------------------------
# navigation errors


def nav_variances(P: np.ndarray, lat, h, q) -> dict:
    """Variances of the reported navigation errors (linear in P).

    Parameters
    ----------
    P : ndarray, shape (..., n_rec, 10, 10)
        Navigation block of seed 002 eq (14).
    lat, h : ndarray, shape (n_rec,)
    q : ndarray, shape (n_rec, 4)

    Returns
    -------
    dict of ndarray, shape (..., n_rec)
        ``horizontal``: σ_N² + σ_E² (the squared horizontal RMS radial
        error) [m²]; ``altitude``: σ_D² [m²]; ``azimuth``: σ_ψ² [rad²].
    """
    Pn = ned_position_covariance(P[..., :3, :3], lat, h)
    Pphi = attitude_errors(P[..., 6:10, 6:10], q)
    return {"horizontal": Pn[..., 0, 0] + Pn[..., 1, 1], "altitude": Pn[..., 2, 2], "azimuth": Pphi[..., 2, 2]}


def relative_residual(P_sum: np.ndarray, P_ref: np.ndarray, q) -> float:
    """Largest ``|ΔP_ij| / √(P_ii P_jj)`` of the physical nav block.

    Parameters
    ----------
    P_sum, P_ref : ndarray, shape (n_rec, 10, 10)
    q : ndarray, shape (n_rec, 4)

    Returns
    -------
    float
        Entries whose reference variances are both exactly zero (e.g. the
        position at t = 0) count only if the sum is not exactly zero there.
    """
    a = physical_nav(P_sum, q)
    r = physical_nav(P_ref, q)
    d = np.sqrt(np.clip(np.einsum("kii->ki", r), 0.0, None))
    den = d[:, :, None] * d[:, None, :]
    diff = np.abs(a - r)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(den > 0, diff / den, np.where(diff > 0, np.inf, 0.0))
    return float(rel.max()) if rel.size else 0.0


# ---------------------------------------------------------------------------
# budgets with declared measurements (issue 15)

#: kind of the source made of a measurement's own error state (initial σ and driving noise)
MEASUREMENT_ERROR = "measurement error"


def aided_sources(model, noise, q0, states, measurements, *, resolution: str = "block") -> tuple[list, list]:
    """The sources of a budget with declared measurements.

    Parameters
    ----------
    model : covtool.lincov.model.spec.Model
        The INS truth model.
    noise : list of covtool.lincov.dynamics.NoiseSource
    q0 : array_like, shape (4,)
        Initial attitude.
    states : sequence of covtool.lincov.model.spec.State
        The measurement-error states appended to the truth (order kept).
    measurements : sequence of str
        The measurements' names: one white-noise (R) source each.
    resolution : {"block", "state"}
        For the INS sources (:func:`budget_sources`).

    Returns
    -------
    sources : list of Source
        The INS sources of :func:`budget_sources` (their ``P0`` over the
        INS states), then one ``"measurement error"`` source per error
        state (its initial σ and its driving noise) and one
        ``"measurement"`` source per measurement's R.
    factors : list of NoiseSource
    """
    sources, factors = budget_sources(model, noise, q0, None, resolution=resolution)
    sources += [Source(s.name, MEASUREMENT_ERROR, (s.name,)) for s in states]
    sources += [Source(f"{m} noise (R)", MEASUREMENT, ()) for m in measurements]
    return sources, factors


def grid_noise(F, factors):
    """The ``noise`` of :func:`run_aided_budget` from whole-grid stacks: ``noise(a, b)`` slices them.

    Parameters
    ----------
    F : ndarray, shape (N, n₀, n₀)
        INS truth dynamics matrix.
    factors : list of NoiseSource
        Their ``G`` of shape (N, n₀, k), ``psd`` of shape (N, k).

    Returns
    -------
    callable
        ``noise(a, b) -> (F[a:b], factors over the steps a … b−1)``.
    """
    def noise(a, b):
        return F[a:b], [NoiseSource(f.name, f.G[a:b], f.psd[a:b]) for f in factors]

    return noise


def run_aided_budget(Phi, noise, dt, sources, states, measurements, D, epochs, gains, record, *,
                     err=None, keep=slice(0, 10), label: str = "error budget", names=None,
                     times=None, chunk: int = 64) -> BudgetRun:
    """Every source of an aided run alone, under the nominal gains.

    The truth is ``[x_INS; e]`` (:mod:`covtool.lincov.aided`); the gains
    are those of the nominal run at every epoch.  Linearity of seed 002
    eq (15)–(16) in (P0, Q_d, R) makes the contributions sum to the
    nominal run.

    Parameters
    ----------
    Phi : ndarray, shape (N, n₀, n₀), or a streamed stack
        INS truth transition, read one step at a time (``Phi[k]``: a
        :class:`~covtool.lincov.streamed.StreamedSystem`'s serves).
    noise : callable
        ``noise(a, b) -> (F, factors)``: the INS truth's dynamics matrix,
        shape ``(b − a, n₀, n₀)``, and its noise factors
        (:func:`aided_sources`, the same names and columns for every span)
        over the steps ``a … b−1``; called once per ``chunk`` steps, in
        order, so F and the factors are never held over the grid.  Their
        per-step ``Q_d`` are the exact Van Loan integral
        (:func:`covtool.lincov.discretize.per_source`).  :func:`grid_noise`
        makes one from whole-grid stacks.
    dt : ndarray, shape (N,)
        Step lengths. [s]
    sources : list of Source
        From :func:`aided_sources`.
    states : sequence of State
        Measurement-error states (the order of the truth's ``e``).
    measurements : sequence of str
        Measurement names (the ``R`` sources, in order).
    D : ndarray, shape (n, n_f)
    epochs : list of covtool.lincov.aided.Epoch
    gains : dict of int to ndarray
        The nominal run's gains at every epoch.
    record : array_like of int
    err : tuple (phi, qd) of ndarray, shape (N, n_e), optional
        The error states' exact processes.
    keep : slice or index array
        Recorded sub-block (default: the navigation states).
    label, names, times
        For messages.
    chunk : int
        Steps whose per-source ``Q_d`` are held at once.

    Returns
    -------
    BudgetRun
        ``P_total`` is the sum of the contributions (compare it with the
        nominal run).

    Raises
    ------
    NumericalError
        A contribution is not finite, symmetric or PSD (the cross piece
        may be indefinite), naming the source, time and state.
    ValueError
        ``noise`` gives factors other than those of its first span (names
        or columns), or spans of another length.
    """
    from covtool.lincov.aided import budget_members
    from covtool.lincov.discretize.sources import per_source

    N, n0, _ = Phi.shape
    ne = len(states)
    n = n0 + ne
    B = len(sources)
    P0s = np.zeros((B, n, n))
    ew = np.zeros((B, ne))
    rw = np.zeros((B, len(measurements)))
    enames = [s.name for s in states]
    layout = None                                   # the factors' names and columns, from the first span
    member = None
    for b, s in enumerate(sources):
        if s.P0 is not None:
            P0s[b, :n0, :n0] = s.P0
        if s.kind == MEASUREMENT_ERROR:
            i = enames.index(s.states[0])
            P0s[b, n0 + i, n0 + i] = states[i].sigma**2
            ew[b, i] = 1.0
        elif s.kind == MEASUREMENT:
            rw[b, list(measurements).index(s.name[:-len(" noise (R)")])] = 1.0
    dt = np.broadcast_to(np.asarray(dt, float), (N,))
    cache = {"a": -1, "Q": None}

    def qd(k):
        nonlocal layout, member
        a = (k // chunk) * chunk
        if cache["a"] != a:
            b = min(N, a + chunk)
            F, factors = noise(a, b)
            here = [(f.name, f.G.shape[2]) for f in factors]
            if layout is None:
                layout = here
                member = np.full(len(factors), -1)
                for m, s in enumerate(sources):
                    if s.noise is not None:
                        member[s.noise] = m
            elif here != layout:
                raise ValueError(f"{label}: the noise factors of steps {a} … {b - 1} are not those of the first "
                                 "steps (names or columns differ)")
            if np.shape(F)[0] != b - a or any(f.G.shape[0] != b - a for f in factors):
                raise ValueError(f"{label}: noise({a}, {b}) gave spans of another length than {b - a} steps")
            if factors:
                G = np.concatenate([f.G for f in factors], axis=2)
                psd_ = np.concatenate([f.psd for f in factors], axis=1)
                starts = np.r_[0, np.cumsum([f.G.shape[2] for f in factors])[:-1]]
                Q = per_source(F, G, psd_, dt[a:b], groups=starts, what=f"{label}: per-source Q_d")
            else:
                Q = None
            cache["a"], cache["Q"] = a, Q
        out = np.zeros((B, n0, n0))
        if cache["Q"] is None:
            return out
        Qj = cache["Q"][k - a]                                     # (J, n0, n0)
        used = member >= 0
        out[member[used]] = Qj[used]
        return out

    keep_ix = np.arange(n)[keep]
    P = budget_members(Phi, P0s, D, epochs, gains, qd=qd, r_weights=rw, meas_names=list(measurements),
                       record=record, keep=keep_ix, err=err, err_weights=ew,
                       psd=[s.kind != CORRELATION for s in sources], label=label,
                       members=[s.name for s in sources], names=names, times=times)
    return BudgetRun(list(sources), np.unique(np.asarray(record, int)), P, P.sum(axis=0))
