"""Shared study plumbing: header, truth model with overrides, grid, dynamics, tables."""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from covtool.nav import earth, attitude as quat
from covtool.lincov.discretize import discretize
from covtool.lincov.dynamics import Context, error_dynamics, NavOptions
from covtool.errors import InputError, StudyFileError, UnitError, ValidityWarning
from covtool.io.config import (check_keys, choice, file_sha256, names, number, quantity, quantity_list, resolve_input,
                         string, table)
from covtool.io.names import check_study_name
from covtool.lincov.kalman import check_covariance, check_system
from covtool.analysis.metrics import first_invalid, nav_metrics, validity, validity_text
from covtool.io.library import load_model_by_name
from covtool.lincov.model.spec import Model
from covtool.units import from_si, parse_quantity

FT = 0.3048
ARCMIN = np.pi / 180 / 60
ARCSEC = ARCMIN / 60


def progress_bar(total: int, desc: str, enabled: bool):
    """A tqdm bar shown only if the work lasts longer than about one second."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, disable=not enabled, delay=1.0, leave=False, unit="step")


def study_header(decl: dict, where: str, extra_keys=()) -> dict:
    """Validate ``[study]``: name, kind, duration, dt, discretization, max_memory."""
    st = table(decl["study"], f"{where}: [study]", StudyFileError)
    check_keys(st, {"kind", "name", "description", "duration", "dt", "discretization", "max_memory", *extra_keys},
               f"{where}: [study]", StudyFileError)
    w = f"{where}: [study]"
    out = {
        "kind": st["kind"],
        "name": check_study_name(st, where, StudyFileError, default=st["kind"]),
        "description": string(st.get("description", ""), f"{w} description", StudyFileError),
        "duration": quantity(st.get("duration", "30 min"), "time", f"{w} duration", StudyFileError, positive=True),
        "dt": quantity(st.get("dt", "1 s"), "time", f"{w} dt", StudyFileError, positive=True),
        "discretization": choice(st.get("discretization", "van_loan"), ("van_loan", "taylor"),
                                 f"{w} discretization", StudyFileError),
        "max_memory": (parse_bytes(st["max_memory"], f"{w} max_memory", StudyFileError)
                       if "max_memory" in st else None),
    }
    if out["dt"] > out["duration"] * (1 + 1e-12):
        raise StudyFileError(f"{w} dt", f"{st.get('dt', '1 s')!r} is longer than the duration "
                             f"({out['duration']:g} s): one step would hold F constant over the whole study")
    return out


def load_truth(decl: dict, where: str, base_dir) -> Model:
    """The study's truth model with ``only`` and per-state ``override`` applied.

    ``[truth]`` keys: ``model`` (library name, or a path relative to the
    study file), ``only`` (list of sources to keep, see :meth:`Model.only`),
    ``[truth.override.<state>]`` with ``sigma`` and the parameter of the
    state's own process (``tau`` for ``markov``, ``distance`` for
    ``markov_distance``, ``rw`` for ``random_walk``) in datasheet units, and
    ``arw``/``vrw``.

    Raises
    ------
    StudyFileError
        Unknown key or state, a bad value, or a process parameter on a state
        whose process does not use it (it would be ignored).
    ModelFileError
        The model file itself is invalid or missing.
    """
    from covtool.io.model_file import _PROCESS_KEYS, _RW_DIM

    tr = table(decl.get("truth", {}), f"{where}: [truth]", StudyFileError)
    check_keys(tr, {"model", "only", "override", "arw", "vrw"}, f"{where}: [truth]", StudyFileError)
    name = tr.get("model", "sdins58")
    model = load_model_by_name(name, base_dir=base_dir, where=f"{where}: [truth] model")
    states = list(model.states)
    ix = model.index
    for nm, ov in table(tr.get("override") or {}, f"{where}: [truth.override]", StudyFileError).items():
        w = f"{where}: [truth.override.{nm}]"
        if nm not in ix:
            raise StudyFileError(w, f"unknown state {nm!r} of truth model {model.name!r}")
        check_keys(ov, {"sigma", "tau", "distance", "rw"}, w, StudyFileError)
        s = states[ix[nm]]
        for key, needs in _PROCESS_KEYS.items():
            if key in ov and s.process != needs:
                raise StudyFileError(f"{w} {key}", f"'{key}' applies only to process {needs!r}; state {nm!r} "
                                     f"follows process {s.process!r}")
        ch = {}
        if "sigma" in ov:
            ch["sigma"] = quantity(ov["sigma"], s.dimension, f"{w} sigma", StudyFileError, nonnegative=True)
            if s.dimension == "quaternion" and ch["sigma"] > 1.0:
                raise StudyFileError(f"{w} sigma", f"{ov['sigma']!r} is above 1; a unit quaternion's component "
                                     "cannot exceed 1")
        if "tau" in ov:
            ch["tau"] = quantity(ov["tau"], "time", f"{w} tau", StudyFileError, positive=True)
        if "distance" in ov:
            ch["distance"] = quantity(ov["distance"], "length", f"{w} distance", StudyFileError, positive=True)
        if "rw" in ov:
            ch["rw"] = quantity(ov["rw"], _RW_DIM.get(s.dimension, s.dimension), f"{w} rw", StudyFileError,
                                nonnegative=True)
        states[ix[nm]] = dataclasses.replace(s, **ch)
    changes = {}
    if "arw" in tr:
        changes["arw"] = quantity(tr["arw"], "angle_random_walk", f"{where}: [truth] arw", StudyFileError,
                                  nonnegative=True)
    if "vrw" in tr:
        changes["vrw"] = quantity(tr["vrw"], "velocity_random_walk", f"{where}: [truth] vrw", StudyFileError,
                                  nonnegative=True)
    model = model.replace_states(states, **changes)
    if "only" in tr:
        only = names(tr["only"], f"{where}: [truth] only", StudyFileError, what="state or block name")
        try:
            model = model.only(only)
        except KeyError as exc:
            raise StudyFileError(f"{where}: [truth] only",
                                 f"unknown state or block {exc.args[0]!r} of truth model {model.name!r}") from None
    return model


def input_file(label: str, path) -> dict:
    """Provenance rows of one input file: its absolute path and SHA-256."""
    p = Path(os.path.abspath(path))
    return {f"{label}_file": str(p), f"{label}_file_sha256": file_sha256(p)}


def study_inputs(path, decl: dict, truth: Model | None = None, filter_file=None) -> dict:
    """Provenance rows of every input file of a study: absolute path and SHA-256.

    The study file, the truth model file, the filter file and a trajectory
    CSV, each as resolved (relative paths against the study file).
    """
    rows = {}
    if path is not None:
        rows.update(input_file("study", path))
    if truth is not None and Path(truth.path).is_file():
        rows.update(input_file("truth_model", truth.path))
    if filter_file is not None:
        rows.update(input_file("filter", filter_file))
    traj = decl.get("trajectory")
    if isinstance(traj, dict) and isinstance(traj.get("csv"), str):
        base = Path(path).parent if path is not None else None
        rows.update(input_file("trajectory", resolve_input(traj["csv"], base, "[trajectory] csv", StudyFileError)))
    return rows


# ---------------------------------------------------------------------------
# resources: step count and peak memory, checked before any computation
# ---------------------------------------------------------------------------

_F8 = 8                 # bytes of one float64
#: float64 per grid step outside the matrices: trajectory samples, mid-point context, metrics, history table
_GRID_FLOATS = 800


def steps_of(duration: float, dt: float) -> int:
    """Number of propagation steps of :func:`time_grid` (without building it)."""
    return int(math.ceil(duration / dt - 1e-9))


def noise_columns(model: Model) -> int:
    """Columns of the noise-source matrices G of ``model``: ARW and VRW (3 each), one per driven state."""
    return 6 + sum(1 for st in model.states if st.process not in ("constant", "navigation"))


def memory_estimate(steps: int, n: int, *, filters=(), dynamics: int = 1, histories=(), noise: int | None = None,
                    extra: float = 0.0, parallel: int = 1) -> dict:
    """Peak memory of a study on the propagation grid (an upper estimate).

    This is the one place that knows what the covariance code keeps for a
    whole grid; change it together with :func:`truth_system`,
    :func:`discretize_chunked`,
    :meth:`covtool.studies.zupt.ZuptSetup.filter_system`,
    :func:`covtool.lincov.reference.propagate` and
    :func:`~covtool.lincov.reference.propagate_with_filter`.

    Parameters
    ----------
    steps : int
        Propagation steps N.
    n : int
        Truth states.
    filters : sequence of int
        States of every filter whose system is built (and cached) at once.
    dynamics : int
        Truth error dynamics built: one per distinct set of navigation
        options among the truth and the filters (``error_dynamics``).
    histories : sequence of int
        State counts of the ``(N+1)·m²`` covariance histories held at once
        (``propagate``: the truth; ``propagate_with_filter``: truth and filter).
    noise : int, optional
        Noise-source columns of the truth model (:func:`noise_columns`;
        default ``n``).
    extra : float
        Kind-specific bytes outside these arrays (a composed noise stack, a
        batch of cases).
    parallel : int
        Copies held at once (worker processes each building one system).

    Returns
    -------
    dict
        ``bytes`` (total), ``steps`` and ``parts`` (label -> bytes).

    Notes
    -----
    Per step, in doubles: the truth keeps F, Q_c, Φ, Q_d (4 n²) and the
    noise-source matrices G (n × columns); every other truth dynamics
    another F, Q_c, G; every filter F_f, Q_c,f, Φ_f, Q_d,f (4 n_f²) and,
    while it is built, the (N, n_f, n) slice of F it is cut from; every
    history (N+1) m².  Van Loan works on :data:`DISCRETIZE_CHUNK` steps of
    2n × 2n at a time (about five such stacks inside ``expm``), freed
    before the histories are allocated, so only the larger of the two
    counts.  Against ``tracemalloc`` peaks of the shipped studies the
    estimate is high by 5-15 % (``tests/test_input_validation.py`` keeps it
    an upper bound within 30 %).
    """
    N = int(steps)
    c = n if noise is None else int(noise)
    parts = {
        "truth F, Q_c, G, Phi, Q_d": (4 * n * n + n * c) * N * _F8,
        "discretisation workspace": 5 * DISCRETIZE_CHUNK * (2 * n) ** 2 * _F8,
        "trajectory and grid": _GRID_FLOATS * (N + 1) * _F8,
    }
    if dynamics > 1:
        parts["other truth dynamics"] = (dynamics - 1) * (2 * n * n + n * c) * N * _F8
    if len(filters):
        parts["filter F, Q_c, Phi, Q_d"] = sum(4 * N * m * m * _F8 for m in filters) + N * max(filters) * n * _F8
    if len(histories):
        parts["covariance histories"] = sum((N + 1) * m * m * _F8 for m in histories)
    if extra:
        parts["other"] = float(extra)
    # the Van Loan workspace is freed before the histories are allocated
    total = sum(parts.values()) - min(parts["discretisation workspace"], parts.get("covariance histories", 0.0))
    if parallel > 1:
        parts = {k: v * parallel for k, v in parts.items()}
        total *= parallel
    return {"bytes": float(total), "steps": N, "parts": parts, "parallel": int(parallel)}


def parse_bytes(value, where: str, error=StudyFileError) -> float:
    """A memory size in bytes: ``"6 GB"``, ``"512 MiB"`` or a bare number of bytes.

    Raises
    ------
    InputError
        (``error``) Not a positive, finite memory size.
    """
    if isinstance(value, bool):
        raise error(where, f"{value!r} is not a memory size such as '6 GB'")
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            try:
                x = from_si(parse_quantity(value, "memory", where=where), "B")
            except UnitError as exc:
                raise error(where, f"{value!r} is not a memory size such as '6 GB' or '512 MiB' "
                                   f"({exc.problem})") from None
            if not x > 0:
                raise error(where, f"{value!r} must be a positive memory size")
            return x
    return number(value, where, error, lo=0.0, lo_open=True)


def _meminfo(key: str) -> float | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _read_number(path) -> float | None:
    try:
        text = Path(path).read_text().strip()
    except OSError:
        return None
    return float(text) if text.isdigit() else None


def memory_limit(max_memory: float | None = None) -> tuple[float, str]:
    """Memory a study may use, and where the figure comes from.

    ``[study] max_memory`` wins, then ``$COVTOOL_MAX_MEMORY``; otherwise the
    smallest of the memory available on the machine (``MemAvailable``), the
    address-space limit (``ulimit -v``) less what this process already maps,
    and the cgroup limit less its usage.
    """
    if max_memory is not None:
        return float(max_memory), "[study] max_memory"
    env = os.environ.get("COVTOOL_MAX_MEMORY")
    if env:
        return parse_bytes(env, "COVTOOL_MAX_MEMORY", InputError), "COVTOOL_MAX_MEMORY"
    cands = []
    avail = _meminfo("MemAvailable")
    if avail is None:
        try:
            avail = float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            avail = None
    if avail is not None:
        cands.append((avail, "available on this machine"))
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft != resource.RLIM_INFINITY:
            used = 0.0
            try:
                for line in Path("/proc/self/status").read_text().splitlines():
                    if line.startswith("VmSize:"):
                        used = float(line.split()[1]) * 1024
            except OSError:
                pass
            cands.append((soft - used, "left under the address-space limit (ulimit -v)"))
    except (ImportError, ValueError, OSError):
        pass
    cg_max, cg_cur = _read_number("/sys/fs/cgroup/memory.max"), _read_number("/sys/fs/cgroup/memory.current")
    if cg_max is not None:
        cands.append((cg_max - (cg_cur or 0.0), "left under the cgroup memory limit"))
    if not cands:
        return math.inf, "unknown"
    return min(cands)


def _size(x: float) -> str:
    for unit, f in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if x >= f:
            return f"{x / f:.3g} {unit}"
    return f"{x / 1e3:.3g} kB"


def check_memory(estimate: dict, where: str, max_memory: float | None, shrink: str) -> dict:
    """Refuse a study whose estimated peak memory exceeds the limit.

    Parameters
    ----------
    estimate : dict
        From :func:`memory_estimate`.
    where : str
        The study file.
    max_memory : float or None
        ``[study] max_memory`` [bytes].
    shrink : str
        The options that shrink this study, for the message.

    Returns
    -------
    dict
        ``estimate`` with ``limit`` and ``limit_source`` added.

    Raises
    ------
    StudyFileError
        One line: the estimate and its largest parts, the limit and where it
        comes from, and the options that shrink the study.
    """
    limit, source = memory_limit(max_memory)
    out = {**estimate, "limit": limit, "limit_source": source}
    if estimate["bytes"] > limit:
        top = sorted(estimate["parts"].items(), key=lambda kv: -kv[1])[:3]
        parts = ", ".join(f"{k} {_size(v)}" for k, v in top)
        par = f" in {estimate['parallel']} workers" if estimate.get("parallel", 1) > 1 else ""
        raise StudyFileError(f"{where}: [study]",
                             f"needs about {_size(estimate['bytes'])} of memory{par} ({estimate['steps']:,} steps; "
                             f"{parts}), more than the {_size(limit)} {source}; shrink it with {shrink}, "
                             "or set [study] max_memory (or COVTOOL_MAX_MEMORY) if more is available")
    return out


def resource_provenance(est: dict) -> dict:
    """Provenance rows of a resource estimate."""
    return {"steps": est["steps"], "estimated_peak_memory": _size(est["bytes"]),
            "memory_limit": f"{_size(est['limit'])} ({est['limit_source']})" if math.isfinite(est["limit"])
            else "unknown"}


def time_grid(duration: float, dt: float, where: str = "<study>") -> np.ndarray:
    """Grid ``0, dt, …, duration`` (the last step shortened if needed).

    Parameters
    ----------
    duration, dt : float
        Span and step. [s]
    where : str
        File named in error messages.

    Returns
    -------
    ndarray, shape (N+1,)
        ``duration`` or ``dt`` not finite and positive, or ``dt > duration``.
    """
    for key, x in (("duration", duration), ("dt", dt)):
        if not (np.isfinite(x) and x > 0):
            raise StudyFileError(f"{where}: [study] {key}", f"{x!r} s must be finite and positive")
    if dt > duration * (1 + 1e-12):
        raise StudyFileError(f"{where}: [study] dt", f"{dt:g} s is longer than the duration ({duration:g} s)")
    n = int(np.floor(duration / dt + 1e-9))
    t = np.arange(n + 1) * dt
    if duration - t[-1] > 1e-9 * dt:
        t = np.append(t, duration)
    return t


def midpoint_context(traj, t: np.ndarray) -> Context:
    """Trajectory at the step mid-points (F is held constant over a step)."""
    tm = 0.5 * (t[:-1] + t[1:])
    return Context.from_trajectory(traj.sample(tm))


#: steps discretised at once by :func:`discretize_chunked` (bounds its workspace)
DISCRETIZE_CHUNK = 150


#: largest rotation of the vehicle (body relative to the navigation frame) F may be held over: 0.1 rad
MAX_STEP_ROTATION = 0.1
#: largest change of the specific force ``f^n`` within a step, relative to g, F may be held over
MAX_STEP_FORCE_CHANGE = 0.1


@dataclass(frozen=True)
class StepMotion:
    """Motion inside each step of a grid (what holding F constant ignores).

    Attributes
    ----------
    rotation : ndarray, shape (N,)
        ``Δt × max |ω_nb|`` over the step: the most the body can turn
        relative to the navigation frame within it. [rad]
    force : ndarray, shape (N,)
        ``max |f^n(t) − f^n(t_mid)| / g`` over the step. [-]
    peak_rate : float
        Largest ``|ω_nb|`` along the grid's span. [rad/s]
    peak_force_rate : float
        Largest ``|ḟ^n|/g`` along the span (finite differences). [1/s]
    """

    rotation: np.ndarray
    force: np.ndarray
    peak_rate: float
    peak_force_rate: float

    def largest_dt(self) -> float:
        """Largest step that meets both limits anywhere on the span. [s]

        ``Δθ ≤ Δt max|ω_nb|`` and ``|f^n(t) − f^n(t_m)| ≤ max|ḟ^n| Δt/2``.
        """
        dts = [MAX_STEP_ROTATION / self.peak_rate if self.peak_rate > 0 else np.inf,
               2.0 * MAX_STEP_FORCE_CHANGE / self.peak_force_rate if self.peak_force_rate > 0 else np.inf]
        return float(min(dts))


def step_motion(traj, t: np.ndarray, *, resolution: float = 0.25) -> StepMotion:
    """Rotation and specific-force change inside each step of ``t``.

    Parameters
    ----------
    traj : Trajectory
    t : ndarray, shape (N+1,)
        Grid. [s]
    resolution : float
        Largest spacing of the samples inside a step (at least 8 per step;
        the trajectory's own samples are added). [s]

    Returns
    -------
    StepMotion
    """
    t = np.asarray(t, float)
    dt = np.diff(t)
    span = t[-1] - t[0]
    res = max(resolution, span / 2e5)
    k = np.maximum(8, np.ceil(dt / res)).astype(int)
    k += k % 2                                             # the mid-point is a sample
    pieces = [t[i] + dt[i] * np.arange(k[i]) / k[i] for i in range(dt.size)]
    own = traj.t[(traj.t > t[0]) & (traj.t < t[-1])]
    s = np.unique(np.concatenate(pieces + [own, t[-1:]]))
    smp = traj.sample(s)
    C = quat.dcm(smp.q_nb)                                 # C_b^n
    w_in = earth.earth_rate_n(smp.lat) + earth.transport_rate_n(smp.lat, smp.h, smp.v_n)
    w_nb = smp.w_ib_b - np.einsum("kji,kj->ki", C, w_in)
    rate = np.linalg.norm(w_nb, axis=1)
    f_n = np.einsum("kij,kj->ki", C, smp.f_b)
    g = earth.gravity(smp.lat, smp.h)
    first = np.searchsorted(s, t[:-1])
    last = np.searchsorted(s, t[1:])                       # the step's end sample (shared)
    mid = np.searchsorted(s, 0.5 * (t[:-1] + t[1:]))
    seg = np.repeat(np.arange(dt.size), last - first + 1)
    pos = np.concatenate([np.arange(a, b + 1) for a, b in zip(first, last)])
    rot = np.zeros(dt.size)
    np.maximum.at(rot, seg, rate[pos])
    df = np.linalg.norm(f_n[pos] - f_n[mid][seg], axis=1) / g[mid][seg]
    force = np.zeros(dt.size)
    np.maximum.at(force, seg, df)
    jerk = np.linalg.norm(np.diff(f_n, axis=0), axis=1) / np.diff(s) / g[1:]
    return StepMotion(rot * dt, force, float(rate.max()), float(jerk.max(initial=0.0)))


def check_step_motion(traj, t: np.ndarray, where: str = "<study>") -> StepMotion:
    """Refuse a grid whose steps hold F constant over too much motion.

    Parameters
    ----------
    traj : Trajectory
    t : ndarray, shape (N+1,)
        Grid. [s]
    where : str
        File named in the error message.

    Returns
    -------
    StepMotion

    Raises
    ------
    StudyFileError
        ``[study] dt``: one line with the time of the first offending step,
        the rotation (or specific-force change) in it and the largest
        acceptable ``dt``.

    Notes
    -----
    F is evaluated at the step mid-point ``t_m`` and held over the step
    (:func:`truth_system`).  Over a step in which the body turns through
    ``Δθ = Δt max|ω_nb|`` (:class:`StepMotion`):

    * the quaternion-error block ``½Ω(ω_ib)`` rotates ``δq`` through
      ``ω(t_m)Δt`` instead of ``∫ω dt``, an error ``ε ≤ Δθ`` (a rate step
      inside the step; ``ε = O(ω̈Δt³)`` for smooth rates).  The attitude
      error is rotated off the ``q``-orthogonal subspace by ``ε/2``, and a
      fraction ``sin²(ε/2) ≤ (Δθ/2)²`` of its variance about that axis
      moves into the quaternion-norm direction, where no attitude error is
      seen: an unaided azimuth σ shrinks (0.099′ instead of 9.98′ at 5 min
      with 60 s steps on the land-vehicle route);
    * the sensor-error columns ``C_b^n`` and the body-frame specific force
      and rate are off by ``|C(t) − C(t_m)| ≤ Δθ`` relative within the step
      (``Δθ²/24`` on average for a steady turn);
    * the tilt-to-velocity coupling ``f^n ×`` is off by
      ``|f^n(t) − f^n(t_m)|/g`` relative to the Schuler coupling ``g``.
      Velocity-direction terms (transport rate, Coriolis) are 1e-4 of that
      and are not checked.

    With ``Δθ ≤ 0.1 rad`` (5.7°) and ``|Δf^n| ≤ 0.1 g`` per step the
    worst-case (rate or force step inside a step) errors are below
    ``(Δθ/2)² = 0.25 %`` of the attitude variance leaking out per step and
    10 % of that step's sensor and force coupling.  What remains on smooth
    motion is the rotation mismatch ``ε ≈ |Δω̇| Δt²/8`` at the kinks of the
    rate profile, which turns part of the (large) azimuth error into tilt.
    Measured on the land-vehicle route (5°/s turns with 3-s ramps, so
    ``dt ≤ 1.14 s``), pure INS at 5 min against ``dt = 0.1 s``, every
    accepted step tried (0.3 … 1.14 s): azimuth within 5e-6, CEP within
    2e-4, tilt within 1.7e-3 (relative; the 58-state model at 1 s: 1e-8,
    5e-5, 2e-5).  Refused steps: 5 s loses 2 % of the azimuth, 60 s 99 %.
    Splitting a 1.14-s step into ten brings the tilt error to 2e-6.
    """
    m = step_motion(traj, t)
    bad_r = m.rotation > MAX_STEP_ROTATION * (1 + 1e-9)
    bad_f = m.force > MAX_STEP_FORCE_CHANGE * (1 + 1e-9)
    if bad_r.any() or bad_f.any():
        k = int(np.argmax(bad_r | bad_f))
        dt = t[k + 1] - t[k]
        ok = m.largest_dt()
        e = 10.0 ** (np.floor(np.log10(ok)) - 2)           # rounded down to 3 significant digits
        ok = np.floor(ok / e * (1 + 1e-12)) * e
        if bad_r[k]:
            what = (f"the vehicle turns by up to {np.degrees(m.rotation[k]):.3g}° in the step from "
                    f"{t[k]:g} s to {t[k + 1]:g} s (peak rate {np.degrees(m.rotation[k] / dt):.3g}°/s), more than "
                    f"{np.degrees(MAX_STEP_ROTATION):.3g}° per step")
        else:
            what = (f"the specific force changes by {m.force[k]:.3g} g in the step from {t[k]:g} s to "
                    f"{t[k + 1]:g} s, more than {MAX_STEP_FORCE_CHANGE:g} g per step")
        raise StudyFileError(f"{where}: [study] dt",
                             f"{dt:g} s holds the error dynamics F constant over too much motion: {what}; "
                             f"the largest acceptable dt is {ok:.3g} s")
    return m


def discretize_chunked(F, Qc, dt, method, order=None, *, progress=False, desc="discretising", chunk=DISCRETIZE_CHUNK,
                       what="", times=None):
    """Discretise in chunks (bounded memory) with a progress bar.

    BLAS is limited to one thread: for these 58–116-wide matrices OpenBLAS's
    thread pool was measured 3–10× slower on a loaded 2-core machine.
    ``what`` and ``times`` (start time of each step [s]) name the system
    and the step in error messages.
    """
    from threadpoolctl import threadpool_limits

    N = F.shape[0]
    Phi = np.empty_like(F)
    Qd = np.empty_like(F)
    dt = np.broadcast_to(np.asarray(dt, float), (N,))
    with threadpool_limits(limits=1, user_api="blas"), progress_bar(N, desc, progress) as bar:
        for a in range(0, N, chunk):
            b = min(N, a + chunk)
            Phi[a:b], Qd[a:b] = discretize(F[a:b], Qc[a:b], dt[a:b], method, order, what=what,
                                           times=None if times is None else times[a:b])
            bar.update(b - a)
    return Phi, Qd


def truth_system(model: Model, traj, t: np.ndarray, method: str, *, options=NavOptions(), progress=False,
                 where: str = "<study>"):
    """Truth Φ, Q_d along the grid, plus the mid-point context and dynamics.

    The grid is first checked against the motion (:func:`check_step_motion`);
    ``where`` names the study file in that error.

    Raises
    ------
    NumericalError
        Φ or Q_d of a step is not finite (Q_d: symmetric, PSD), naming the
        study ``where``, the step's time and the state.
    """
    check_step_motion(traj, t, where)
    ctx = midpoint_context(traj, t)
    dyn = error_dynamics(model, ctx, options)
    Phi, Qd = discretize_chunked(dyn.F, dyn.Qc, np.diff(t), method, progress=progress, desc="truth Φ, Q",
                                 what=f"{where}: truth model {model.name!r}", times=t[:-1])
    # guarded once here; the runs that share them are told so (system_checked)
    check_system(f"{where}: truth model {model.name!r}", Phi, Qd, names=model.names, times=t)
    return ctx, dyn, Phi, Qd


def initial_covariance(truth: Model, nodes, where: str) -> np.ndarray:
    """The truth P0 at the first trajectory node, guarded.

    Parameters
    ----------
    truth : Model
    nodes : covtool.nav.trajectory.core.Trajectory
        The trajectory sampled on the study grid.
    where : str
        The study file, for messages.

    Returns
    -------
    ndarray, shape (n, n)

    Raises
    ------
    NumericalError
        P0 is not finite, symmetric and PSD (names the state).
    StudyFileError
        P0 is already outside the linear error model's domain
        (:func:`covtool.analysis.metrics.validity`), e.g. an initial azimuth 1σ of 83°.
    """
    P0 = truth.initial_covariance(nodes.q_nb[0])
    check_covariance(P0, f"{where}: truth model {truth.name!r}: P0", names=truth.names)
    m = nav_metrics(P0[None], nodes.lat[:1], nodes.h[:1], nodes.q_nb[:1])
    first = first_invalid(m, [0.0])
    if first:
        text = validity_text(first)
        sig = (f" (initial 1sigma: azimuth {np.degrees(m['sigma_azimuth'][0]):.3g} deg, tilts "
               f"{np.degrees(m['sigma_tilt_n'][0]):.3g}/{np.degrees(m['sigma_tilt_e'][0]):.3g} deg, "
               f"position {max(m['sigma_north'][0], m['sigma_east'][0]):.4g} m, altitude {m['sigma_down'][0]:.4g} m)")
        raise StudyFileError(f"{where}: [truth]", "the initial covariance of truth model "
                             f"{truth.name!r} is outside the linear error model's domain: "
                             + text.replace(" from t = 0.0 min", "") + sig)
    return P0


def case_validity(case: str, m: dict, t: np.ndarray, *, warn: bool = True) -> dict:
    """First times a case leaves the linear model's domain; warn once.

    Parameters
    ----------
    case : str
        Case name (in the warning).
    m : dict of ndarray, shape (N,)
        :func:`covtool.analysis.metrics.nav_metrics` along the case's history.
    t : ndarray, shape (N,)
        Times of the history. [s]
    warn : bool
        Issue one :class:`covtool.errors.ValidityWarning` naming the case and
        the first time of each failed test.

    Returns
    -------
    dict of str to float
        :func:`covtool.analysis.metrics.first_invalid`.
    """
    first = first_invalid(m, t)
    if first and warn:
        warnings.warn(f"{case}: outside the linear error model's domain: {validity_text(first)}",
                      ValidityWarning, stacklevel=2)
    return first


def history_frame(case: str, t: np.ndarray, m: dict, every: float | None = None) -> pd.DataFrame:
    """History table with SI and paper units in the headers.

    The ``validity`` column names the domain tests that fail at each time
    (:func:`covtool.analysis.metrics.validity`), empty where the linear model holds.
    """
    sel = np.ones(t.shape, bool)
    if every:
        k = np.round(t / every)
        sel = np.isclose(t, k * every) | (np.arange(t.size) == t.size - 1)
    df = pd.DataFrame({
        "case": case,
        "t [s]": t[sel],
        "t [min]": t[sel] / 60.0,
        "sigma_N [m]": m["sigma_north"][sel],
        "sigma_E [m]": m["sigma_east"][sel],
        "sigma_D [m]": m["sigma_down"][sel],
        "CEP [m]": m["cep"][sel],
        "CEP [ft]": m["cep"][sel] / FT,
        "alt PE [m]": m["alt_pe"][sel],
        "alt PE [ft]": m["alt_pe"][sel] / FT,
        "sigma_vN [m/s]": m["sigma_vn"][sel],
        "sigma_vE [m/s]": m["sigma_ve"][sel],
        "sigma_vD [m/s]": m["sigma_vd"][sel],
        "tilt_N [arcsec]": m["sigma_tilt_n"][sel] / ARCSEC,
        "tilt_E [arcsec]": m["sigma_tilt_e"][sel] / ARCSEC,
        "azimuth [arcmin]": m["sigma_azimuth"][sel] / ARCMIN,
    })
    if "cep_pct_distance" in m:
        df["CEP/distance [%]"] = m["cep_pct_distance"][sel]
    flags = validity(m)
    df["validity"] = [", ".join(name for name, f in flags.items() if f[i]) or "ok" for i in np.flatnonzero(sel)]
    return df


def summary_row(case: str, m: dict, k: int, t: float, distance: float | None, *, first: dict | None = None,
                status: str | None = None) -> dict:
    """Table 3 columns at grid index ``k``.

    Parameters
    ----------
    case : str
    m : dict of ndarray
        :func:`covtool.analysis.metrics.nav_metrics`.
    k : int
        Index into ``m``.
    t : float
        Time of index ``k``. [s]
    distance : float or None
        Distance travelled by then. [m]
    first : dict, optional
        :func:`covtool.analysis.metrics.first_invalid` of the case; the ``validity``
        column lists the tests failed by ``t`` with their first time.  By
        default the tests at index ``k`` alone.
    status : str, optional
        Adds a ``status`` column (``"ok"`` or the guard's message) for
        studies that flag a failed case instead of stopping.
    """
    row = {
        "case": case,
        "t [min]": t / 60.0,
        "CEP [ft]": m["cep"][k] / FT,
        "CEP [m]": m["cep"][k],
        "alt PE [ft]": m["alt_pe"][k] / FT,
        "alt PE [m]": m["alt_pe"][k],
        "azimuth 1sigma [arcmin]": m["sigma_azimuth"][k] / ARCMIN,
        "tilt N 1sigma [arcsec]": m["sigma_tilt_n"][k] / ARCSEC,
        "tilt E 1sigma [arcsec]": m["sigma_tilt_e"][k] / ARCSEC,
        "CEP rule 0.589(s1+s2) [m]": m["cep_rule"][k],
    }
    if distance:
        row["distance [km]"] = distance / 1000.0
        row["CEP/distance [%]"] = 100.0 * m["cep"][k] / distance
    if first is None:
        first = {name: t for name, f in validity(m).items() if f[k]}
    row["validity"] = validity_text(first, until=t)
    if status is not None:
        row["status"] = status or "ok"
    return row


def report_times(decl_out: dict, where: str, duration: float) -> list[float]:
    """``[output] report_times`` in seconds, each within the study (default: the end)."""
    if "report_times" not in decl_out:
        return [duration]
    w = f"{where}: [output] report_times"
    out = quantity_list(decl_out["report_times"], "time", w, StudyFileError, limit="report_times",
                        nonnegative=True)
    for i, (v, x) in enumerate(zip(decl_out["report_times"], out)):
        if x > duration + 1e-9:
            raise StudyFileError(f"{w}[{i}]", f"{v!r} is after the end of the study ({duration:g} s)")
    if len(set(out)) != len(out):
        raise StudyFileError(w, f"a time is listed twice in {decl_out['report_times']!r}")
    return out


__all__ = ["study_header", "load_truth", "time_grid", "truth_system", "check_step_motion", "step_motion",
           "history_frame", "summary_row", "initial_covariance", "case_validity",
           "parse_quantity", "from_si", "UnitError", "FT", "ARCMIN", "ARCSEC"]
