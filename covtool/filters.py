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
    equivalent_noise = true           # eq (11)-(13) for the dropped states
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
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from .discretize import discretize
from .dynamics import Context, ErrorDynamics, NavOptions, error_dynamics
from .errors import ModelFileError
from .io.config import (boolean, check_keys, choice, integer, is_library_name, load_toml, names, quantity,
                        resolve_input, string, table)
from .model.blocks import NAV_STATES
from .model.spec import Model

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
    equivalent_noise : {False, "eq11-13", "matched"}
        ``"eq11-13"``: every dropped state becomes eq (11)–(13) white noise
        through its whole coupling (seed 002 as printed).  ``"matched"``: a
        dropped state on the random-constant rule is first projected onto
        the kept sensor states (:func:`absorbed_coupling`; the absorbed part
        widens their P0) and the residual coupling gets eq (12) with Δt_s
        replaced by the coupling's effective duration in each interval
        (:func:`effective_duration`).
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
    equivalent_noise: object = "eq11-13"
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
_FILTER_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+-]{0,30}$")
_EWN = (False, True, "eq11-13", "matched")


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
        name = f["name"]
        if not isinstance(name, str) or not _FILTER_NAME.match(name):
            raise ModelFileError(f"{where}: name", f"{name!r} is not a filter name (1-31 letters, digits, "
                                 "'_', '.', '+', '-')")
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
    from .model.loader import load_model

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
    ewn = choice(f.get("equivalent_noise", "eq11-13"), _EWN, f"{where}: equivalent_noise", ModelFileError)
    if ewn is True:
        ewn = "eq11-13"
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

def equivalent_white_noise(state, dt_s: float, mean_speed: float | None = None) -> tuple[float, str]:
    """Equivalent white-noise PSD of a dropped state (seed 002, eq (11)–(13)).

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
    tau = None
    if state.process == "markov":
        tau, kind = state.tau, "Markov"
    elif state.process == "markov_distance":
        if not mean_speed:
            return P0 * dt_s, "eq (12) random constant (vehicle never moves): P0*dt_s"
        tau, kind = state.distance / mean_speed, f"Markov in distance (tau = d/v_mean = {state.distance / mean_speed:.0f} s)"
    if tau is not None:
        if 2.0 * tau <= dt_s:
            return 2.0 * tau * P0, f"eq (11) {kind}: 2*tau*P0 (tau = {tau:g} s <= dt_s/2)"
        return P0 * dt_s, (f"eq (12) {kind} with tau = {tau:g} s > dt_s/2: constant over a ZUPT interval, "
                           "P0*dt_s")
    if state.process == "random_walk":
        return P0 * dt_s + state.rw**2 * dt_s**2, "eq (12)+(13) random walk: sigma0^2*dt_s + q_rw*dt_s^2"
    return P0 * dt_s, "eq (12) random constant: P0*dt_s"


def uses_constant_rule(state, dt_s: float, mean_speed: float | None = None) -> bool:
    """True if :func:`equivalent_white_noise` treats the state as a random constant (eq (12))."""
    return equivalent_white_noise(state, dt_s, mean_speed)[1].startswith("eq (12)") and \
        state.process != "random_walk"


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
        One row per dropped truth state: process, rule, q_eq and its
        time-mean contribution to the filter's Q diagonal.
    """

    spec: FilterSpec
    names: list
    D: np.ndarray
    F: np.ndarray
    Qc: np.ndarray
    P0: np.ndarray
    ewn_table: pd.DataFrame

    def discretize(self, dt):
        """Φ_f and Q_f by the filter's declared method (eq (6b)–(6d) by default)."""
        return discretize(self.F, self.Qc, dt, self.spec.discretization, self.spec.taylor_order)


def build_filter(spec: FilterSpec, truth: Model, ctx: Context, *, zupt_interval: float, q0=None,
                 truth_dynamics: ErrorDynamics | None = None, mean_speed: float | None = None,
                 dt_steps=None) -> FilterModel:
    """Evaluate a filter along a trajectory.

    Parameters
    ----------
    spec : FilterSpec
    truth : Model
    ctx : Context
        Trajectory at the propagation mid-points.
    zupt_interval : float
        Δt_s of eq (12)–(13). [s]
    q0 : ndarray, shape (4,), optional
        Initial attitude (rotates the δq block of P0).
    truth_dynamics : ErrorDynamics, optional
        Truth dynamics with the filter's :class:`NavOptions`; computed if omitted.
    mean_speed : float, optional
        Mean moving speed (Markov-in-distance states). [m/s]
    dt_steps : ndarray, shape (N,), optional
        Step lengths of the grid ``ctx`` was sampled on (``"matched"`` mode). [s]
    """
    if dt_steps is None:
        dt_steps = np.ones(ctx.n)
    dyn = truth_dynamics if truth_dynamics is not None else error_dynamics(truth, ctx, spec.options)
    kidx = truth.idx(spec.kept)
    dropped = [i for i in range(truth.n) if i not in set(kidx.tolist())]
    F = dyn.F[:, kidx][:, :, kidx]
    Qc_full = dyn.Qc
    Qc = Qc_full[:, kidx][:, :, kidx].copy()
    rows = []
    absorb = np.zeros((len(kidx), len(kidx)))
    if spec.equivalent_noise:
        sens = [k for k, i in enumerate(kidx) if i >= 10]          # kept sensor/environment states
        B = F[:, :, sens]                                         # (N, n_f, n_s) their couplings
        for j in dropped:
            st = truth.states[j]
            q_eq, rule = equivalent_white_noise(st, zupt_interval, mean_speed)
            col = dyn.F[:, kidx, j]                                   # F_kept,dropped
            alpha = np.zeros(len(sens))
            matched = spec.equivalent_noise == "matched" and uses_constant_rule(st, zupt_interval, mean_speed)
            if matched and sens:
                alpha, resid = absorbed_coupling(col, B)
                col = resid
            if q_eq <= 0 and not alpha.any():
                continue
            qt = np.full(col.shape[0], q_eq)
            if matched:
                qt = st.sigma**2 * effective_duration(col, dt_steps, zupt_interval)
                rule += "; matched: dt_s -> (int c)^2/int c^2 per interval"
            contrib = qt[:, None, None] * col[:, :, None] * col[:, None, :]
            Qc += contrib
            if alpha.any():
                a = np.zeros(len(kidx))
                a[sens] = alpha
                absorb += st.sigma**2 * np.outer(a, a)
            mean_diag = np.mean(np.einsum("tii->ti", contrib), axis=0)
            row = {"filter": spec.name, "dropped state": st.name, "process": st.process, "rule": rule,
                   "mode": spec.equivalent_noise if spec.equivalent_noise is not True else "eq11-13",
                   "P0 [SI]": st.sigma**2, "q_eq [SI^2 s]": q_eq,
                   "absorbed by": ", ".join(f"{spec.kept[sens[k]]} ({alpha[k]:+.3g})"
                                            for k in np.argsort(-np.abs(alpha))[:3] if abs(alpha[k]) > 0)}
            for nm, v in zip(spec.kept, mean_diag):
                if nm in ("dvN", "dvE", "dvD", "dq0", "dq1", "dq2", "dq3", "dh"):
                    row[f"mean dQ {nm} [SI^2/s]"] = v
            rows.append(row)
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
        columns=["filter", "dropped state", "process", "rule", "P0 [SI]", "q_eq [SI^2 s]"])
    return FilterModel(spec, list(spec.kept), D, F, Qc, P0, table)


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


def effective_duration(col: np.ndarray, dt_steps: np.ndarray, interval: float) -> np.ndarray:
    """Effective Δt of eq (12) for a time-varying coupling, per ZUPT interval.

    Eq (12) chooses the white-noise PSD so that the integrated effect of a
    random constant over one ZUPT interval has the right variance:
    ``P0 (∫c dt)² = q ∫c² dt``.  For a constant coupling ``c`` that gives
    ``q = P0 Δt_s`` (eq (12) as printed); in general
    ``q = P0 · ‖∫c dt‖² / ∫‖c‖² dt`` (Cauchy–Schwarz: ≤ ``P0 Δt_s``), e.g. the
    21 s of a turn for a gyro misalignment driven by the yaw rate.

    Parameters
    ----------
    col : ndarray, shape (N, n_f)
        Coupling ``c(t)`` of a dropped state into the kept states.
    dt_steps : ndarray, shape (N,)
    interval : float
        ZUPT interval Δt_s. [s]

    Returns
    -------
    ndarray, shape (N,)
        Δt_eff for the interval each step belongs to. [s]
    """
    t_end = np.cumsum(dt_steps)
    k = np.floor((t_end - 0.5 * dt_steps) / interval).astype(int)
    scale = np.sqrt(np.mean(col**2, axis=0))
    c = col / np.where(scale > 0, scale, 1.0)
    out = np.zeros(col.shape[0])
    for kk in np.unique(k):
        m = k == kk
        num = np.sum(np.sum(c[m] * dt_steps[m, None], axis=0) ** 2)
        den = np.sum(np.sum(c[m] ** 2, axis=1) * dt_steps[m])
        out[m] = num / den if den > 0 else 0.0
    return out


def zupt_matrices(names) -> np.ndarray:
    """ZUPT measurement matrix: the velocity-error rows, shape ``(3, len(names))``."""
    names = list(names)
    H = np.zeros((3, len(names)))
    for r, v in enumerate(VELOCITY_STATES):
        H[r, names.index(v)] = 1.0
    return H


def default_filter_file() -> Path:
    """The library's ZUPT filter declarations."""
    from .model.library import default_model_dir

    return default_model_dir() / "filters" / "zupt_filters.toml"
