"""Reduced-order filters declared as projections of the truth model (seed 002, Table 1).

A filter keeps a subset of the truth states *by name*, may simplify the
navigation equations (decoupled vertical channel, no Coriolis terms), and
replaces every truth state it drops by an equivalent white noise
(seed 002, eq (11)–(13)) mapped onto its kept states through the truth
coupling ``F_kept,dropped``.

Filter file (``models/filters/*.toml``)::

    [[filter]]
    name = "B1"
    truth = "sdins58"                 # the truth model it is a projection of: a library name, or a
                                      # path relative to this file ("../sdins58.toml")
    description = "22 states, eq (14)"
    keep = ["nav", "acc_bias", "gyro_bias", "acc_sf", "gyro_sf"]   # blocks or states
    # base = "B1"; drop = [...]       # or derive from another filter
    decouple_vertical = false         # B2
    coriolis = true                   # B3: false
    equivalent_noise = "interval"     # eq (11)-(13) for the dropped states (or "pointwise", "matched", false)
    discretization = "taylor"         # eq (6b)-(6d); or "van_loan"
    taylor_order = 12                 # optional: terms of eq (6b), 2..40 (default: until converged)
    update = "joseph"                 # or "standard" (eq (8))
    zupt_sigma = "0.01 ft/s"          # optional: the ZUPT 1σ the filter assumes (> 0)
    [filter.P0]                       # optional overrides of the kept states' 1σ
    acc_bias_z = "30 ug"
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from covtool.discretize import discretize
from covtool.dynamics import Context, ErrorDynamics, NavOptions, NoiseSource, error_dynamics
from covtool.errors import ModelFileError
from covtool.io.config import (boolean, check_keys, choice, integer, is_library_name, load_toml, names, quantity,
                        resolve_input, string, table)
from covtool.io.names import check_name
from covtool.model.blocks import NAV_STATES
from covtool.model.spec import Model

_FILTER_KEYS = {"name", "truth", "description", "keep", "base", "drop", "decouple_vertical", "coriolis",
                "equivalent_noise", "discretization", "taylor_order", "update", "P0", "zupt_sigma", "source"}

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


def load_filters(path, truth: Model) -> dict[str, FilterSpec]:
    """Load every ``[[filter]]`` of a filter file, validated against ``truth``.

    Raises
    ------
    ModelFileError
        Unknown key, unknown truth state, a filter declared for another truth
        model, a P0 override of a state the filter does not keep, a filter
        without the velocity states that ZUPT measures, ...
    """
    decl = load_toml(path, ModelFileError)
    return filters_from_dict(decl, truth, path=str(path))


#: a filter name: it becomes a case label, a column header and part of a sheet name
#: equivalent_noise values; true and "eq11-13" mean "interval" (seed 002 eq (11)-(13), interval-matched)
_EWN = (False, True, "eq11-13", "interval", "pointwise", "matched")


def filters_from_dict(decl: dict, truth: Model, *, path: str = "<dict>") -> dict[str, FilterSpec]:
    """Validate filter declarations; see :func:`load_filters`.

    A ``truth`` given as a path (``"../sdins58.toml"``) resolves against the
    directory of the filter file and must be the study's truth model file.
    """
    check_keys(decl, {"filter"}, path, ModelFileError)
    raw = decl.get("filter", [])
    if not isinstance(raw, list) or not raw:
        raise ModelFileError(path, "no [[filter]] declared")
    base_dir = Path(path).parent if path != "<dict>" else None
    by_name: dict[str, dict] = {}
    out: dict[str, FilterSpec] = {}
    for i, f in enumerate(raw):
        where = f"{path}: filter {f.get('name', i + 1)!r}" if isinstance(f, dict) else f"{path}: filter {i + 1}"
        check_keys(f, _FILTER_KEYS, where, ModelFileError)
        if "name" not in f:
            raise ModelFileError(where, "missing required key 'name'")
        name = check_name(f["name"], f"{path}: filter {i + 1}: name", ModelFileError, what="filter name")
        if name in by_name:
            raise ModelFileError(where, "duplicate filter name")
        if "base" in f:
            if not isinstance(f["base"], str) or f["base"] not in by_name:
                raise ModelFileError(f"{where}: base", f"unknown base filter {f['base']!r} (declare it first)")
            merged = copy.deepcopy(by_name[f["base"]])
            merged.pop("drop", None)
            merged.pop("description", None)
            base_keep = merged["keep"]
            merged.update({k: v for k, v in f.items() if k not in ("base",)})
            merged["keep"] = f.get("keep", base_keep)
            f = merged
        out[name] = _spec(f, truth, where, path, base_dir)
        resolved = {k: v for k, v in f.items() if k != "drop"}
        resolved["keep"] = list(out[name].kept)
        by_name[name] = resolved
    return out


def _check_truth(tname, truth: Model, where: str, base_dir) -> None:
    """The filter's ``truth``: a library name equal to the study's, or a path to the same file."""
    w = f"{where}: truth"
    string(tname, w, ModelFileError, nonempty=True)
    if is_library_name(tname):
        if tname != truth.name:
            raise ModelFileError(w, f"filter was declared for truth model {tname!r}, "
                                 f"but the study's truth model is {truth.name!r}")
        return
    from covtool.model.loader import load_model

    p = resolve_input(tname, base_dir, w, ModelFileError, what="truth model file")
    same = Path(truth.path).is_file() and os.path.samefile(p, truth.path)
    if not same and load_model(p).sha256 != truth.sha256:
        raise ModelFileError(w, f"filter was declared for truth model file {str(p)!r}, but the study's truth "
                             f"model is {truth.path!r} ({truth.name!r}), a different declaration")


def _spec(f: dict, truth: Model, where: str, path: str, base_dir=None) -> FilterSpec:
    _check_truth(f.get("truth", truth.name), truth, where, base_dir)
    for key in ("description", "source"):
        if key in f:
            string(f[key], f"{where}: {key}", ModelFileError)
    keep = f.get("keep", "all")
    if isinstance(keep, str) and keep != "all":
        keep = [keep]
    if keep != "all":
        names(keep, f"{where}: keep", ModelFileError, what="truth state or block")
    drop = names(f.get("drop", []), f"{where}: drop", ModelFileError, nonempty=False,
                 what="truth state or block")
    try:
        kept = truth.names if keep == "all" else truth.states_of(keep)
        dropped = set(truth.states_of(drop))
    except KeyError as exc:
        raise ModelFileError(f"{where}: keep/drop", f"unknown truth state or block {exc.args[0]!r} "
                             f"(truth model {truth.name!r})") from None
    kept_set = set(kept) - dropped
    kept = tuple(nm for nm in truth.names if nm in kept_set)   # truth order
    for v in NAV_STATES:
        if v not in kept_set:
            raise ModelFileError(f"{where}: keep", f"a ZUPT filter must keep the navigation state {v!r} "
                                 "(the 10 states of seed 002 eq (14))")
    P0 = {}
    for nm, val in table(f.get("P0") or {}, f"{where}: P0", ModelFileError).items():
        if nm not in truth.index:
            raise ModelFileError(f"{where}: P0", f"unknown truth state {nm!r}")
        if nm not in kept_set:
            raise ModelFileError(f"{where}: P0", f"state {nm!r} is not kept by this filter")
        st = truth.states[truth.index[nm]]
        P0[nm] = quantity(val, st.dimension, f"{where}: P0: {nm}", ModelFileError, nonnegative=True)
    disc = choice(f.get("discretization", "taylor"), ("taylor", "van_loan"), f"{where}: discretization",
                  ModelFileError)
    upd = choice(f.get("update", "joseph"), ("joseph", "standard"), f"{where}: update", ModelFileError)
    order = None
    if "taylor_order" in f:
        if disc != "taylor":
            raise ModelFileError(f"{where}: taylor_order", f"applies only to discretization 'taylor'; this filter "
                                 f"uses {disc!r}")
        order = integer(f["taylor_order"], f"{where}: taylor_order", ModelFileError, limit="taylor_order")
    zs = None
    if "zupt_sigma" in f:
        # R_f = 0 makes S = H P_f H^T + R_f of eq (7) singular as soon as P_f's velocity block is
        # (a previous zero-noise ZUPT leaves it exactly zero): the gain is undefined
        zs = quantity(f["zupt_sigma"], "velocity", f"{where}: zupt_sigma", ModelFileError, positive=True)
    options = {key: boolean(f[key], f"{where}: {key}", ModelFileError)
               for key in ("decouple_vertical", "coriolis") if key in f}
    ewn = choice(f.get("equivalent_noise", "interval"), _EWN, f"{where}: equivalent_noise", ModelFileError)
    if ewn is True or ewn == "eq11-13":
        ewn = "interval"
    return FilterSpec(
        name=f["name"], truth=truth.name, kept=kept,
        options=NavOptions(coriolis=options.get("coriolis", True),
                           couple_vertical=not options.get("decouple_vertical", False)),
        equivalent_noise=ewn, discretization=disc,
        taylor_order=order, update=upd, P0_sigma=P0, zupt_sigma=zs,
        description=f.get("description", ""), path=path, decl=copy.deepcopy(f))


# ---------------------------------------------------------------------------
# equivalent white noise, seed 002 eq (11)-(13)
# ---------------------------------------------------------------------------

#: ways of applying eq (11)-(13) (``equivalent_noise`` in a filter file); see docs/equivalent_noise.md
EWN_MODES = ("interval", "pointwise", "matched")


def equivalent_white_noise(state, dt_s: float, mean_speed: float | None = None) -> tuple[float, str]:
    """Equivalent white-noise PSD of a dropped state (seed 002, eq (11)–(13)).

    The scalar rule as printed: the PSD for a *constant* unit coupling over
    one full ZUPT interval.  ``equivalent_noise = "pointwise"`` injects it
    through the coupling at every step; the default (``"interval"``,
    :func:`equivalent_noise_source`) applies the same matching rule over
    each actual ZUPT interval.

    Parameters
    ----------
    state : covtool.model.spec.State
    dt_s : float
        ZUPT interval Δt_s. [s]
    mean_speed : float, optional
        Mean speed while moving, for Markov-in-distance states (τ = d/v̄). [m/s]

    Returns
    -------
    q_eq : float
        PSD of the equivalent white noise. [SI²·s]
    rule : str
        The rule applied, for the record.

    Notes
    -----
    * first-order Markov, eq (11): ``Q_eq = 2 τ P0`` (the low-frequency PSD of
      the Markov process).  Seed 002 §2.3 states it for a source whose band
      is wider than the system's; a Markov process with ``τ > Δt_s/2`` is
      nearly constant over one ZUPT interval, so eq (12) applies instead.
      Together: ``Q_eq = P0 · min(2τ, Δt_s)``, continuous at ``τ = Δt_s/2``.
      Markov-in-distance states use ``τ = d / v̄`` with the mean moving speed;
    * random constant, eq (12): ``Q_eq = P0 Δt_s`` (a white noise whose
      integral over Δt_s has the same variance as that of the constant,
      ``P0 Δt_s²``);
    * random walk, eq (13) ``Q_eq = P0 Δt_s²`` as printed is dimensionally an
      PSD only if ``P0`` is the walk's diffusion rate ``q_rw`` [unit²/s]; covtool
      reads it so, and adds the eq (12) term for the walk's initial σ:
      ``Q_eq = σ0² Δt_s + q_rw Δt_s²``.
    """
    P0 = state.sigma**2
    regime, tau, kind = ewn_regime(state, dt_s, mean_speed)
    if regime == "markov":
        return 2.0 * tau * P0, f"eq (11) {kind}: 2*tau*P0 (tau = {tau:g} s <= dt_s/2)"
    if regime == "random_walk":
        return P0 * dt_s + state.rw**2 * dt_s**2, "eq (12)+(13) random walk: sigma0^2*dt_s + q_rw*dt_s^2"
    if tau is not None:
        return P0 * dt_s, (f"eq (12) {kind} with tau = {tau:g} s > dt_s/2: constant over a ZUPT interval, "
                           "P0*dt_s")
    if kind:
        return P0 * dt_s, f"eq (12) random constant ({kind}): P0*dt_s"
    return P0 * dt_s, "eq (12) random constant: P0*dt_s"


def ewn_regime(state, dt_s: float, mean_speed: float | None = None) -> tuple[str, float | None, str]:
    """Which of eq (11)–(13) a dropped state falls under.

    Returns
    -------
    regime : {"markov", "constant", "random_walk"}
        ``"markov"``: eq (11), a Markov source with ``τ ≤ Δt_s/2`` that
        decorrelates within a ZUPT interval; ``"constant"``: eq (12), a
        random constant or a Markov source that stays (nearly) constant over
        an interval; ``"random_walk"``: eq (13).
    tau : float or None
        Correlation time (``d / v̄`` for Markov-in-distance states). [s]
    kind : str
        Description for the rule text.
    """
    tau, kind = None, ""
    if state.process == "markov":
        tau, kind = state.tau, "Markov"
    elif state.process == "markov_distance":
        if not mean_speed:
            return "constant", None, "vehicle never moves"
        tau = state.distance / mean_speed
        kind = f"Markov in distance (tau = d/v_mean = {tau:.0f} s)"
    elif state.process == "random_walk":
        return "random_walk", None, "random walk"
    if tau is not None and 2.0 * tau <= dt_s:
        return "markov", tau, kind
    return "constant", tau, kind


def uses_constant_rule(state, dt_s: float, mean_speed: float | None = None) -> bool:
    """True if the state falls under eq (12), the random-constant rule (:func:`ewn_regime`)."""
    return ewn_regime(state, dt_s, mean_speed)[0] == "constant"


def zupt_intervals(update_steps, t: np.ndarray, interval: float) -> np.ndarray:
    """Grid indices bounding the ZUPT intervals of a schedule.

    Parameters
    ----------
    update_steps : array_like of int
        Grid indices of the ZUPT updates.
    t : ndarray, shape (N+1,)
        Time grid. [s]
    interval : float
        Declared ZUPT interval Δt_s (only to tell one stop's window from
        evenly spaced single updates). [s]

    Returns
    -------
    ndarray of int, shape (K+1,)
        ``0``, the last update of every stop's group, and ``N``: interval
        ``i`` is the propagation steps ``bounds[i] … bounds[i+1]−1``.

    Notes
    -----
    The updates of one stop form a group (a window at ``rate``); an interval
    runs from the end of one group to the end of the next, so the regular
    intervals are Δt_s long whatever the window, the first runs from t = 0 to
    the first stop (``[zupt] first``), and a tail after the last update is an
    interval of its own.  Groups are separated by gaps larger than 1.5× the
    smallest gap; if the updates are evenly spaced, each is its own group
    when the spacing is at least Δt_s/2 (one update per stop), else they
    are all one window.
    """
    t = np.asarray(t, float)
    N = t.size - 1
    u = np.unique(np.asarray(update_steps, int))
    u = u[(u > 0) & (u <= N)]
    if u.size == 0:
        return np.array([0, N])
    gaps = np.diff(t[u])
    if gaps.size and gaps.max() > 1.5 * gaps.min():
        brk = gaps > 1.5 * gaps.min()
    else:
        brk = gaps >= 0.5 * interval
    ends = u[np.r_[brk, True]]
    return np.unique(np.r_[0, ends, N]).astype(int)


def _interval_index(bounds: np.ndarray, n_steps: int) -> np.ndarray:
    """Interval number of every propagation step."""
    return np.searchsorted(bounds, np.arange(n_steps), side="right") - 1


def interval_mean(col: np.ndarray, dt_steps: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interval-mean coupling and interval length of every step.

    Parameters
    ----------
    col : ndarray, shape (N, n_f)
        Coupling ``c(t)`` of a dropped state into the kept states.
    dt_steps : ndarray, shape (N,)
        Step lengths. [s]
    bounds : ndarray of int
        :func:`zupt_intervals`.

    Returns
    -------
    cbar : ndarray, shape (N, n_f)
        ``c̄_i = (1/Δt_i) ∫_i c dt`` of the interval each step lies in.
    dti : ndarray, shape (N,)
        ``Δt_i`` of that interval. [s]
    """
    N = col.shape[0]
    k = _interval_index(bounds, N)
    integ = np.zeros((len(bounds) - 1, col.shape[1]))
    np.add.at(integ, k, col * dt_steps[:, None])
    length = np.bincount(k, weights=dt_steps, minlength=len(bounds) - 1)
    safe = np.where(length > 0, length, 1.0)
    return (integ / safe[:, None])[k], length[k]


def tail_integral(col: np.ndarray, dt_steps: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """``∫_t^{t_end} c ds`` from each step's mid-point to the end of its interval.

    Returns
    -------
    ndarray, shape (N, n_f)
    """
    w = col * dt_steps[:, None]
    out = np.empty_like(col)
    for i in range(len(bounds) - 1):
        a, b = bounds[i], bounds[i + 1]
        rev = np.cumsum(w[a:b][::-1], axis=0)[::-1]          # ∫ from the step's start to the end
        out[a:b] = rev - 0.5 * w[a:b]
    return out


def pointwise_overstatement(col: np.ndarray, dt_steps: np.ndarray, bounds: np.ndarray,
                            dt_s: float) -> tuple[float, float]:
    """How far the pointwise form overstates eq (12)'s matching rule.

    Per interval the pointwise noise integrates to ``P0 Δt_s ∫|c|² dt`` where
    the rule asks for ``P0 |∫c dt|²``.

    Returns
    -------
    overall : float
        ``Σ_i Δt_s ∫_i |c|² / Σ_i |∫_i c|²`` (inf if the coupling integrates to 0).
    worst : float
        Largest ratio of one interval with a non-zero coupling.
    """
    N = col.shape[0]
    k = _interval_index(bounds, N)
    K = len(bounds) - 1
    integ = np.zeros((K, col.shape[1]))
    np.add.at(integ, k, col * dt_steps[:, None])
    sq = np.bincount(k, weights=np.sum(col**2, axis=1) * dt_steps, minlength=K)
    num = dt_s * sq
    den = np.sum(integ**2, axis=1)
    tot = float(num.sum() / den.sum()) if den.sum() > 0 else (np.inf if num.sum() > 0 else 1.0)
    on = num > 0
    with np.errstate(divide="ignore"):
        r = np.where(den[on] > 0, num[on] / np.where(den[on] > 0, den[on], 1.0), np.inf)
    return tot, float(r.max()) if r.size else 1.0


def equivalent_noise_source(state, col: np.ndarray, dt_steps: np.ndarray, bounds: np.ndarray, *,
                            dt_s: float, mean_speed: float | None = None,
                            mode: str = "interval") -> tuple[NoiseSource, str]:
    """Equivalent white noise of one dropped state as a driving-noise source.

    Parameters
    ----------
    state : covtool.model.spec.State
    col : ndarray, shape (N, n_f)
        ``F_kept,j(t)``: how the dropped state drives the kept states (for
        ``"matched"``: the residual after absorption).
    dt_steps : ndarray, shape (N,)
        Step lengths. [s]
    bounds : ndarray of int
        ZUPT intervals (:func:`zupt_intervals`).
    dt_s : float
        Declared ZUPT interval (regime of eq (11); the pointwise PSD). [s]
    mean_speed : float, optional
        Mean moving speed (Markov-in-distance states). [m/s]
    mode : {"interval", "pointwise", "matched"}

    Returns
    -------
    source : covtool.dynamics.NoiseSource
        ``Q_c += G diag(psd) Gᵀ`` with ``G`` of shape ``(N, n_f, k)``.
    rule : str

    Notes
    -----
    Seed 002 eq (12) matches the white noise's integral over a ZUPT interval
    to that of the dropped random constant, ``P0 (∫c dt)(∫c dt)ᵀ``.  Over
    interval ``i`` of length Δt_i, a white noise of PSD ``q = P0 Δt_i``
    injected through the interval-mean coupling ``c̄_i`` integrates to
    ``q Δt_i c̄_i c̄_iᵀ = P0 (∫_i c)(∫_i c)ᵀ``: the rule holds exactly for any
    ``c(t)``, and for a constant ``c`` on a full interval this is the
    printed ``P0 Δt_s c cᵀ``.  Markov sources with ``τ ≤ Δt_s/2``
    (eq (11)) decorrelate within the interval, so the pointwise
    ``2τP0 c(t)c(t)ᵀ`` is their local white-noise equivalent.  A random
    walk (eq (13)) splits into its value at the interval start (variance
    ``σ0² + q_rw t_a``, eq (12) through ``c̄_i``) and the increment since,
    whose integrated effect ``∫ C(s) dW`` with ``C(s) = ∫_s^{t_b} c`` is a
    white noise of PSD ``q_rw`` through ``C``.  Derivation:
    ``docs/equivalent_noise.md``.
    """
    N, nf = col.shape
    P0 = state.sigma**2
    if mode == "pointwise":
        q, rule = equivalent_white_noise(state, dt_s, mean_speed)
        return NoiseSource(state.name, col[:, :, None].copy(), np.full((N, 1), q)), rule + "; pointwise"
    regime, tau, kind = ewn_regime(state, dt_s, mean_speed)
    if regime == "markov":
        return (NoiseSource(state.name, col[:, :, None].copy(), np.full((N, 1), 2.0 * tau * P0)),
                f"eq (11) {kind}: 2*tau*P0 through c(t) (tau = {tau:g} s <= dt_s/2: decorrelates within "
                "the interval)")
    cbar, dti = interval_mean(col, dt_steps, bounds)
    if regime == "random_walk":
        t0 = np.r_[0.0, np.cumsum(dt_steps)][bounds[_interval_index(bounds, N)]]
        G = np.stack([cbar, tail_integral(col, dt_steps, bounds)], axis=2)
        psd = np.stack([(P0 + state.rw**2 * t0) * dti, np.full(N, state.rw**2)], axis=1)
        return (NoiseSource(state.name, G, psd),
                "eq (12)+(13) random walk, interval-matched: (sigma0^2 + q_rw t_a)*dt_i through the "
                "interval-mean coupling + q_rw through the tail integral of c")
    what = "random constant" if tau is None else f"{kind}, tau = {tau:g} s > dt_s/2"
    if kind == "vehicle never moves":
        what = "random constant (vehicle never moves)"
    return (NoiseSource(state.name, cbar[:, :, None], (P0 * dti)[:, None]),
            f"eq (12) {what}, interval-matched: P0*dt_i through the interval-mean coupling")


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
    ewn_noise : list of covtool.dynamics.NoiseSource
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
    truth_dynamics : ErrorDynamics, optional
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
    kidx = truth.idx(spec.kept)
    kset = set(kidx.tolist())
    dropped = [i for i in range(truth.n) if i not in kset]
    F = dyn.F[:, kidx][:, :, kidx]
    Qc_kept = dyn.Qc[:, kidx][:, :, kidx].copy()
    Qc = Qc_kept.copy()
    rows, sources, absorb_by = [], [], {}
    absorb = np.zeros((len(kidx), len(kidx)))
    mode = spec.equivalent_noise
    if mode:
        sens = [k for k, i in enumerate(kidx) if i >= 10]          # kept sensor/environment states
        B = F[:, :, sens]                                         # (N, n_f, n_s) their couplings
        for j in dropped:
            st = truth.states[j]
            col = dyn.F[:, kidx, j]                                   # F_kept,dropped
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
                Qc += src.qc()
                sources.append(src)
            rows.append({"filter": spec.name, "dropped state": st.name, "block": st.block, "process": st.process,
                         "rule": rule, "mode": mode, "P0 [SI]": st.sigma**2, "q_eq [SI^2 s]": q_eq,
                         "pointwise / interval-matched (eq (12) states) [-]": over,
                         "pointwise / interval-matched, worst interval [-]": worst,
                         "absorbed by": ", ".join(f"{spec.kept[sens[k]]} ({alpha[k]:+.3g})"
                                                  for k in np.argsort(-np.abs(alpha))[:3] if abs(alpha[k]) > 0)})
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
        columns=["filter", "dropped state", "block", "process", "rule", "P0 [SI]", "q_eq [SI^2 s]"])
    return FilterModel(spec, list(spec.kept), D, F, Qc, P0, table, Qc_kept=Qc_kept, ewn_noise=sources,
                       ewn_absorb=absorb_by, bounds=bounds)


def ewn_navigation_effect(fm: FilterModel, Phi_f: np.ndarray, t: np.ndarray, lat, h, q) -> pd.DataFrame:
    """What each dropped state's equivalent noise does to the navigation errors.

    Each state's equivalent noise is propagated alone through the filter's
    own dynamics (Φ_f, no updates) over every ZUPT interval, and the
    covariance it builds up by the interval's end is expressed in the
    physical errors: position N/E/D, velocity N/E/D, north/east tilt and
    azimuth (``φ = −2R(q)ᵀδq``, :func:`covtool.nav.attitude.attitude_error_matrix`).

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
    from covtool.nav import earth
    from covtool.nav.attitude import attitude_error_matrix

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
    var = np.zeros((K, J, 9))
    rm, rn = earth.radii(np.asarray(lat))
    for i in range(K):
        end = b[i + 1]
        T = np.zeros((9, nf))
        T[0, 0] = rm[end] + h[end]
        T[1, 1] = (rn[end] + h[end]) * np.cos(lat[end])
        T[2, 2] = -1.0
        T[3:6, 3:6] = np.eye(3)
        T[6:9, 6:10] = attitude_error_matrix(q[end])
        M = T
        acc = np.zeros((9, G.shape[2]))
        for k in range(end - 1, b[i] - 1, -1):
            Gk = G[k]
            Y = M @ (0.5 * (Gk + Phi_f[k] @ Gk))                 # (9, J')
            acc += Y**2 * (psd[k] * dt[k])[None, :]
            M = M @ Phi_f[k]
        for jj in range(J):
            var[i, jj] = acc[:, owner == jj].sum(axis=1)
    ms = var.mean(axis=0)                                       # (J, 9) mean variance per interval
    FT, ARCSEC = 0.3048, np.pi / 180 / 3600
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


def absorbed_coupling(col: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a dropped state's coupling into a part the kept states absorb and a residual.

    Parameters
    ----------
    col : ndarray, shape (N, n_f)
        ``F_kept,j(t)``: how dropped state ``j`` drives the kept states.
    B : ndarray, shape (N, n_f, n_s)
        Couplings of the kept sensor states.

    Returns
    -------
    alpha : ndarray, shape (n_s,)
        Constant least-squares coefficients: over the trajectory,
        ``F_kept,j(t) ≈ B(t) α``.  A random constant ``x_j`` then acts exactly
        like the kept states shifted by ``α x_j``.
    resid : ndarray, shape (N, n_f)
        ``F_kept,j(t) − B(t) α``: the part no kept state can represent; only
        this part is turned into equivalent white noise.

    Notes
    -----
    Example: an accelerometer misalignment ``m_xz`` couples as
    ``C_b^n [f_z, 0, 0]ᵀ``; on a level land vehicle ``f_z ≈ −g``, so it is the
    x-bias coupling times ``−g`` and is absorbed by ``B_x`` with α ≈ −g.
    Rows are scaled by their RMS so velocity and quaternion rows weigh alike.
    """
    N, nf, ns = B.shape
    scale = np.sqrt(np.mean(B**2, axis=(0, 2)) + np.mean(col**2, axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    A = (B / scale[None, :, None]).reshape(N * nf, ns)
    y = (col / scale[None, :]).reshape(N * nf)
    alpha, *_ = np.linalg.lstsq(A, y, rcond=1e-10)
    resid = col - np.einsum("tfs,s->tf", B, alpha)
    return alpha, resid


def zupt_matrices(names) -> np.ndarray:
    """ZUPT measurement matrix: the velocity-error rows, shape ``(3, len(names))``."""
    names = list(names)
    H = np.zeros((3, len(names)))
    for r, v in enumerate(VELOCITY_STATES):
        H[r, names.index(v)] = 1.0
    return H


def default_filter_file() -> Path:
    """The library's ZUPT filter declarations."""
    from covtool.model.library import default_model_dir

    return default_model_dir() / "filters" / "zupt_filters.toml"
