"""Reduced-order filters as projections of the truth model (seed 002, Table 1).

A filter keeps a subset of the truth states *by name*, may simplify the
navigation equations (decoupled vertical channel, no Coriolis terms), and
replaces every truth state it drops by an equivalent white noise
(seed 002, eq (11)–(13), :mod:`covtool.lincov.equivalent_noise`) mapped onto
its kept states through the truth coupling ``F_kept,dropped``.
:func:`build_filter` turns a :class:`FilterSpec` (read from a filter file by
:mod:`covtool.io.filters`) into the filter's model on a time grid.

Pure numeric core: models and arrays in, arrays out.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from covtool.lincov.discretize import discretize
from covtool.lincov.dynamics import (Context, dyn_key, DynamicsStream, error_dynamics, ErrorDynamics, nav_error_matrix,
                                     NavOptions)
from covtool.lincov.equivalent_noise import (absorbed_coupling, equivalent_noise_source,
                                             equivalent_white_noise, pointwise_overstatement,
                                             uses_constant_rule, zupt_intervals)
from covtool.lincov.model.spec import Model
from covtool.lincov.stacks import gather
from covtool.nav.strapdown import NAV_STATES
from covtool.units import ARCSEC, FT, si_unit


VELOCITY_STATES = ("dvN", "dvE", "dvD")


@dataclass(frozen=True)
class FilterSpec:
    """A validated filter declaration.

    Attributes
    ----------
    name : str
    truth : str
        Name of the truth model this filter projects.
    kept : tuple of str
        Kept truth state names, in truth order.
    options : NavOptions
        Simplifications of the navigation block.
    equivalent_noise : {False, "interval", "pointwise", "matched"}
        How each dropped state becomes eq (11)–(13) white noise
        (:func:`build_filter`).  ``"interval"`` (default; ``true`` and
        ``"eq11-13"`` mean it): the integrated effect over every ZUPT
        interval of the schedule matches the dropped source's.
        ``"pointwise"``: the printed PSD through the coupling at every step.
        ``"matched"``: a dropped random constant is first projected onto
        the kept sensor states (:func:`absorbed_coupling`; the absorbed part
        widens their P0) and the residual is matched over each interval.
        ``False``: dropped states are ignored.
    discretization : str
        ``"taylor"`` (eq (6b)–(6d)) or ``"van_loan"``.
    taylor_order : int or None
    update : str
        ``"joseph"`` or ``"standard"`` (eq (8)).
    P0_sigma : dict of str to float
        Overrides of the kept states' initial 1σ. [SI]
    zupt_sigma : float or None
        ZUPT 1σ the filter assumes [m/s]; default: the study's.
    description, path : str
    """

    name: str
    truth: str
    kept: tuple
    options: NavOptions = NavOptions()
    equivalent_noise: object = "interval"
    discretization: str = "taylor"
    taylor_order: int | None = None
    update: str = "joseph"
    P0_sigma: dict = field(default_factory=dict)
    zupt_sigma: float | None = None
    description: str = ""
    path: str = ""
    decl: dict = field(default_factory=dict, compare=False)

    @property
    def n(self) -> int:
        return len(self.kept)


def system_key(spec: FilterSpec) -> FilterSpec:
    """``spec`` without what only the update uses (name, R_f, update form, texts).

    Equal keys: equal F_f, Q_c,f, P_f(0) and D (one system serves both).
    """
    return dataclasses.replace(spec, name="", zupt_sigma=None, update="joseph", description="", path="", decl={})


@dataclass
class FilterModel:
    """A filter evaluated along a trajectory: its F_f, Q_f, D and P_f(0).

    Attributes
    ----------
    spec : FilterSpec
    names : list of str
    D : ndarray, shape (n_truth, n_f)
        Truth × filter map by state name (eq (10), (16)).
    F : ndarray, shape (N, n_f, n_f)
    Qc : ndarray, shape (N, n_f, n_f)
        Continuous Q including the equivalent white noise.
    P0 : ndarray, shape (n_f, n_f)
    ewn_table : DataFrame
        One row per dropped truth state: block, process, rule applied,
        q_eq, and, for states on eq (12), the pointwise form's overstatement
        of its matching rule (:func:`pointwise_overstatement`; NaN for the
        other rules).
    Qc_kept : ndarray, shape (N, n_f, n_f), optional
        The truth's driving noise on the kept states (``Qc`` without the
        equivalent noise).
    ewn_noise : list of covtool.lincov.dynamics.NoiseSource
        The equivalent noise of each dropped state (name = state name);
        ``Qc = Qc_kept + Σ G diag(psd) Gᵀ``.
    ewn_absorb : dict of str to ndarray, shape (n_f,)
        ``"matched"``: the kept states absorb dropped state j as
        ``P0 += σ_j² a aᵀ``.
    bounds : ndarray of int
        The ZUPT intervals the noise was matched over (:func:`zupt_intervals`).
    """

    spec: FilterSpec
    names: list
    D: np.ndarray
    F: np.ndarray
    Qc: np.ndarray
    P0: np.ndarray
    ewn_table: pd.DataFrame
    Qc_kept: np.ndarray | None = None
    ewn_noise: list = field(default_factory=list)
    ewn_absorb: dict = field(default_factory=dict)
    bounds: np.ndarray | None = None

    def discretize(self, dt):
        """Φ_f and Q_f by the filter's declared method (eq (6b)–(6d) by default)."""
        return discretize(self.F, self.Qc, dt, self.spec.discretization, self.spec.taylor_order)

    def chunk(self, dyn: ErrorDynamics, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """``(F_f, Q_c,f)`` of the steps ``a … b−1`` from the truth dynamics of those steps.

        ``dyn`` is the chunk's truth :class:`ErrorDynamics` under the
        filter's options (:meth:`covtool.lincov.dynamics.DynamicsStream.chunk`);
        the equivalent noise of eq (11)–(13) is added as in
        :func:`build_filter` (same values as its whole-span ``F``, ``Qc``).

        Raises
        ------
        ValueError
            ``dyn`` was built under other navigation options than the filter declares.
        """
        if dyn_key(dyn.options) != dyn_key(self.spec.options):
            raise ValueError(f"filter {self.spec.name!r}: the chunk's truth dynamics were built under {dyn.options}, "
                             f"but the filter declares {self.spec.options} (seed 002 eq (1), (4))")
        kidx = np.argmax(self.D, axis=0)
        F = gather(dyn.F, kidx)
        Qc = gather(dyn.Qc, kidx)
        for src in self.ewn_noise:
            src.add_qc(Qc, a, b)
        return F, Qc


def build_filter(spec: FilterSpec, truth: Model, ctx: Context, *, zupt_interval: float, q0=None,
                 truth_dynamics: ErrorDynamics | None = None, mean_speed: float | None = None,
                 dt_steps=None, update_steps=None) -> FilterModel:
    """Evaluate a filter along a trajectory.

    Parameters
    ----------
    spec : FilterSpec
    truth : Model
    ctx : Context
        Trajectory at the propagation mid-points.
    zupt_interval : float
        Δt_s of eq (11)–(13). [s]
    q0 : ndarray, shape (4,), optional
        Initial attitude (rotates the δq block of P0).
    truth_dynamics : ErrorDynamics or DynamicsStream, optional
        Truth dynamics with the filter's :class:`NavOptions`; computed if omitted.
    mean_speed : float, optional
        Mean moving speed (Markov-in-distance states). [m/s]
    dt_steps : ndarray, shape (N,), optional
        Step lengths of the grid ``ctx`` was sampled on (default 1 s). [s]
    update_steps : array_like of int, optional
        The ZUPT schedule (grid indices): eq (11)–(13) is matched over its
        intervals (:func:`zupt_intervals`).  Without it the intervals are
        taken as ``[kΔt_s, (k+1)Δt_s)`` from t = 0 (stops at multiples of
        Δt_s, ``[zupt] first`` = ``interval``).

    Returns
    -------
    FilterModel

    Raises
    ------
    ValueError
        ``truth_dynamics`` was built under other navigation options than
        the filter declares (its F_f would silently keep the truth's
        Coriolis terms or vertical coupling).

    Notes
    -----
    ``equivalent_noise`` (seed 002 eq (11)–(13), :func:`equivalent_noise_source`):
    ``"interval"`` (default) matches each dropped state's integrated effect
    over every ZUPT interval; ``"pointwise"`` injects the printed PSD
    through ``c(t)`` at every step; ``"matched"`` first folds the part of a
    random constant the kept sensor states can represent into their P0
    (:func:`absorbed_coupling`) and matches the residual over each interval.
    """
    if dt_steps is None:
        dt_steps = np.ones(ctx.n)
    dt_steps = np.asarray(dt_steps, float)
    t = np.r_[0.0, np.cumsum(dt_steps)]
    if update_steps is not None:
        bounds = zupt_intervals(update_steps, t, zupt_interval)
    else:
        bounds = np.unique(np.r_[np.searchsorted(t, np.arange(0.0, t[-1], zupt_interval) - 1e-9 * zupt_interval),
                                 ctx.n]).astype(int)
    dyn = truth_dynamics if truth_dynamics is not None else error_dynamics(truth, ctx, spec.options)
    if dyn_key(dyn.options) != dyn_key(spec.options):
        raise ValueError(f"filter {spec.name!r}: its truth dynamics were built under {dyn.options}, but the filter "
                         f"declares {spec.options} (seed 002 eq (1), (4))")
    kidx = truth.idx(spec.kept)
    kset = set(kidx.tolist())
    dropped = [i for i in range(truth.n) if i not in kset]
    mode = spec.equivalent_noise
    sens = [k for k, i in enumerate(kidx) if i >= 10]              # kept sensor/environment states
    if isinstance(dyn, DynamicsStream):
        # streamed in time: F_f and Q_c,f are built per chunk (FilterModel.chunk); only the couplings
        # eq (11)-(13) needs are gathered over the span
        F = Qc_kept = Qc = None
        Fx = dyn.columns(kidx, dropped + [int(kidx[k]) for k in sens]) if mode else None
        # views laid out as the whole-grid slices below (time fastest): the same round-off downstream
        cols = {j: Fx[c].T for c, j in enumerate(dropped)} if mode else {}
        B = Fx[len(dropped):].transpose(2, 1, 0) if mode else None
    else:
        # a filter keeping every state in truth order has the truth's F and Q_c themselves (neither is
        # written to: Q_c is copied below if equivalent noise is added); the others are gathered
        # C-contiguous (as FilterModel.chunk does), the couplings laid out time fastest as the streamed
        # columns are (DynamicsStream.columns): the same round-off either way
        whole = np.array_equal(kidx, np.arange(truth.n))
        F = dyn.F if whole else dyn.F_block(kidx)
        Qc_kept = dyn.Qc if whole else gather(dyn.Qc, kidx)
        Qc = Qc_kept
        # (N, n_f, n_s) their couplings
        B = np.ascontiguousarray(dyn.F_block(kidx, kidx[sens]).transpose(2, 1, 0)).transpose(2, 1, 0) \
            if mode else None
        if mode and dropped:
            # F_kept,dropped of every dropped state in one gather; each (N, n_f), time fastest as the
            # per-state slices dyn.F[:, kidx, j] and the streamed columns are
            Fd = np.ascontiguousarray(dyn.F_block(kidx, dropped).transpose(2, 1, 0))
            cols = {j: Fd[c].T for c, j in enumerate(dropped)}
        else:
            cols = {}
    rows, sources, absorb_by = [], [], {}
    absorb = np.zeros((len(kidx), len(kidx)))
    units: dict = {}

    def unit(u, *a, **k):
        key = (u, a, tuple(k.items()))
        if key not in units:
            units[key] = si_unit(u, *a, **k)
        return units[key]

    if mode:
        for j in dropped:
            st = truth.states[j]
            col = cols[j]                                             # F_kept,dropped
            over, worst = pointwise_overstatement(col, dt_steps, bounds, zupt_interval) \
                if uses_constant_rule(st, zupt_interval, mean_speed) else (np.nan, np.nan)
            alpha = np.zeros(len(sens))
            if mode == "matched" and sens and uses_constant_rule(st, zupt_interval, mean_speed):
                alpha, col = absorbed_coupling(col, B)
            q_eq, _ = equivalent_white_noise(st, zupt_interval, mean_speed)
            src, rule = equivalent_noise_source(st, col, dt_steps, bounds, dt_s=zupt_interval,
                                                mean_speed=mean_speed, mode="pointwise" if mode == "pointwise"
                                                else "interval")
            if alpha.any():
                rule += "; matched: constant part absorbed by the kept sensor states"
                a = np.zeros(len(kidx))
                a[sens] = alpha
                absorb += st.sigma**2 * np.outer(a, a)
                absorb_by[st.name] = a
            if np.any(src.psd > 0) and np.any(src.G != 0):
                sources.append(src.compact() if F is None else src)
            rows.append({"filter": spec.name, "dropped state": st.name, "block": st.block, "process": st.process,
                         "rule": rule, "mode": mode, "P0, SI value": st.sigma**2,
                         "P0 SI unit": unit(st.unit, 2), "q_eq, SI value": q_eq,
                         "q_eq SI unit": unit(st.unit, 2, seconds=1),
                         "pointwise / interval-matched (eq (12) states) [-]": over,
                         "pointwise / interval-matched, worst interval [-]": worst,
                         "absorbed by": ", ".join(f"{spec.kept[sens[k]]} ({alpha[k]:+.3g})"
                                                  for k in np.argsort(-np.abs(alpha))[:3] if abs(alpha[k]) > 0)})
        if Qc is not None and sources:                                # whole grid (streamed: per chunk)
            Qc = equivalent_noise_qc(sources, Qc.shape, out=Qc_kept.copy())
    D = np.zeros((truth.n, len(kidx)))
    D[kidx, np.arange(len(kidx))] = 1.0
    P0t = truth.initial_covariance(q0)
    P0 = P0t[np.ix_(kidx, kidx)].copy() + absorb
    for nm, sig in spec.P0_sigma.items():
        i = spec.kept.index(nm)
        old = np.sqrt(P0[i, i])
        if old > 0:
            P0[i, :] *= sig / old
            P0[:, i] *= sig / old
        else:
            P0[i, i] = sig**2
    table = pd.DataFrame(rows) if rows else pd.DataFrame(
        columns=["filter", "dropped state", "block", "process", "rule", "P0, SI value", "P0 SI unit",
                 "q_eq, SI value", "q_eq SI unit"])
    return FilterModel(spec, list(spec.kept), D, F, Qc, P0, table, Qc_kept=Qc_kept, ewn_noise=sources,
                       ewn_absorb=absorb_by, bounds=bounds)


def equivalent_noise_qc(sources: list, shape: tuple, out: np.ndarray | None = None) -> np.ndarray:
    """``Σ_j G_j diag(psd_j) G_jᵀ`` of the equivalent noises, on their rows.

    Parameters
    ----------
    sources : list of covtool.lincov.dynamics.NoiseSource
        ``G`` of shape ``(N, n_f, k_j)``, ``psd`` of shape ``(N, k_j)``.
    shape : tuple
        ``(N, n_f, n_f)``.
    out : ndarray, shape (N, n_f, n_f), optional
        Added into (source after source), and returned.

    Returns
    -------
    ndarray, shape (N, n_f, n_f)
        Their contribution to ``Q_c`` (seed 002, eq (11)–(13)): the sum of
        each source's :meth:`~covtool.lincov.dynamics.NoiseSource.qc`, each
        formed on the rows it drives only (the velocity or quaternion rows
        a dropped sensor state couples into).
    """
    out = np.zeros(shape) if out is None else out
    for src in sources:
        # each source on its own non-zero rows, added in turn: the same sums as src.qc(), element by element
        nz = np.flatnonzero((src.G != 0).any(axis=(0, 2)))
        Gz = src.G[:, nz, :]
        out[:, nz[:, None], nz[None, :]] += (Gz * src.psd[:, None, :]) @ np.swapaxes(Gz, 1, 2)
    return out


def ewn_navigation_effect(fm: FilterModel, Phi_f: np.ndarray, t: np.ndarray, lat, h, q) -> pd.DataFrame:
    """What each dropped state's equivalent noise does to the navigation errors.

    Each state's equivalent noise is propagated alone through the filter's
    own dynamics (Φ_f, no updates) over every ZUPT interval, and the
    covariance it builds up by the interval's end is expressed in the
    physical errors: position N/E/D, velocity N/E/D, north/east tilt and
    azimuth (:func:`covtool.lincov.dynamics.nav_error_matrix`).

    Parameters
    ----------
    fm : FilterModel
    Phi_f : ndarray, shape (N, n_f, n_f)
        The filter's transition matrices.
    t : ndarray, shape (N+1,)
        Time grid. [s]
    lat, h : ndarray, shape (N+1,)
        Trajectory latitude [rad] and height [m] on the grid.
    q : ndarray, shape (N+1, 4)
        Attitude on the grid.

    Returns
    -------
    DataFrame
        One row per dropped state with an equivalent noise: the 1σ it adds
        per ZUPT interval (RMS over the run's intervals) in ft, ft/s,
        arcsec and arcmin, and its share of the equivalent noise's
        horizontal-position, altitude, tilt and azimuth variance.

    Notes
    -----
    Within a step the noise is taken to enter, on average, half-way
    through it (trapezoid rule on ``Φ``): for 1 s steps this is well
    below 1 % of the interval's accumulation.
    """
    if not fm.ewn_noise:
        return pd.DataFrame()
    if tuple(fm.names[:10]) != NAV_STATES:
        raise ValueError("the filter's first ten states must be the navigation states")
    N, nf, _ = Phi_f.shape
    dt = np.diff(t)
    cols, owner = [], []
    for j, src in enumerate(fm.ewn_noise):
        for c in range(src.G.shape[2]):
            cols.append((src.G[:, :, c], src.psd[:, c]))
            owner.append(j)
    G = np.stack([c[0] for c in cols], axis=2)                  # (N, nf, J')
    psd = np.stack([c[1] for c in cols], axis=1)                # (N, J')
    owner = np.array(owner)
    J = len(fm.ewn_noise)
    b = fm.bounds
    K = len(b) - 1
    lat, h = np.asarray(lat), np.asarray(h)
    ends = np.asarray(b[1:], int)
    T = np.zeros((K, 9, nf))
    for i, end in enumerate(ends):
        T[i, :, :10] = nav_error_matrix(q[end], lat[end], h[end])
    w = psd * dt[:, None]                                       # (N, J') PSD × step
    acc = np.zeros((K, 9, G.shape[2]))
    if isinstance(Phi_f, np.ndarray):
        # every interval walked back from its end at once: step j of each interval in one batched product
        M = T.copy()
        length = ends - np.asarray(b[:-1], int)
        for j in range(int(length.max(initial=0))):
            act = np.flatnonzero(length > j)
            k = ends[act] - 1 - j
            Gk, Pk = G[k], Phi_f[k]
            Y = M[act] @ (0.5 * (Gk + Pk @ Gk))                 # (act, 9, J')
            acc[act] += Y**2 * w[k][:, None, :]
            M[act] = M[act] @ Pk
    else:
        # a streamed Φ_f (covtool.studies.zupt_setup.StreamedTransitions) is read in runs, interval by interval
        for i in range(K):
            M = T[i]
            for k in range(ends[i] - 1, b[i] - 1, -1):
                Gk = G[k]
                Y = M @ (0.5 * (Gk + Phi_f[k] @ Gk))             # (9, J')
                acc[i] += Y**2 * w[k][None, :]
                M = M @ Phi_f[k]
    var = np.zeros((K, J, 9))
    for jj in range(J):
        var[:, jj] = acc[:, :, owner == jj].sum(axis=2)
    ms = var.mean(axis=0)                                       # (J, 9) mean variance per interval
    tot = ms.sum(axis=0)

    def share(v, total):
        return 100.0 * v / total if total > 0 else np.nan

    rows = []
    for jj, src in enumerate(fm.ewn_noise):
        m = ms[jj]
        hz, alt, tilt, az = m[0] + m[1], m[2], m[6] + m[7], m[8]
        rows.append({
            "filter": fm.spec.name, "dropped state": src.name,
            "horizontal position [ft]": np.sqrt(hz) / FT, "altitude [ft]": np.sqrt(alt) / FT,
            "vN [ft/s]": np.sqrt(m[3]) / FT, "vE [ft/s]": np.sqrt(m[4]) / FT, "vD [ft/s]": np.sqrt(m[5]) / FT,
            "tilt N [arcsec]": np.sqrt(m[6]) / ARCSEC, "tilt E [arcsec]": np.sqrt(m[7]) / ARCSEC,
            "azimuth [arcmin]": np.sqrt(m[8]) / (60 * ARCSEC),
            "horizontal share [%]": share(hz, tot[0] + tot[1]), "altitude share [%]": share(alt, tot[2]),
            "tilt share [%]": share(tilt, tot[6] + tot[7]), "azimuth share [%]": share(az, tot[8]),
        })
    return pd.DataFrame(rows)


def zupt_matrices(names) -> np.ndarray:
    """ZUPT measurement matrix: the velocity-error rows, shape ``(3, len(names))``."""
    names = list(names)
    H = np.zeros((3, len(names)))
    for r, v in enumerate(VELOCITY_STATES):
        H[r, names.index(v)] = 1.0
    return H
