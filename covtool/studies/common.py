"""Shared study plumbing: header, truth model with overrides, grid, dynamics, tables."""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np
import pandas as pd

from ..discretize import discretize
from ..dynamics import Context, NavOptions, error_dynamics
from ..errors import InputError, StudyFileError, UnitError
from ..io.config import (check_keys, choice, file_sha256, names, number, quantity, quantity_list, resolve_input,
                         string, table)
from ..io.names import check_study_name
from ..model.library import load_model_by_name
from ..model.spec import Model
from ..units import from_si, parse_quantity

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
    if out["dt"] > out["duration"]:
        raise StudyFileError(f"{w} dt", f"{out['dt']:g} s is longer than the study ({out['duration']:g} s)")
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
    from ..model.loader import _PROCESS_KEYS, _RW_DIM

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
    :func:`covtool.covariance.propagate` and
    :func:`~covtool.covariance.propagate_with_filter`.

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


def time_grid(duration: float, dt: float) -> np.ndarray:
    """Grid ``0, dt, …, duration`` (the last step shortened if needed)."""
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


def discretize_chunked(F, Qc, dt, method, order=None, *, progress=False, desc="discretising",
                       chunk=DISCRETIZE_CHUNK):
    """Discretise in chunks (bounded memory) with a progress bar.

    BLAS is limited to one thread: for these 58–116-wide matrices OpenBLAS's
    thread pool was measured 3–10× slower on a loaded 2-core machine.
    """
    from threadpoolctl import threadpool_limits

    N = F.shape[0]
    Phi = np.empty_like(F)
    Qd = np.empty_like(F)
    dt = np.broadcast_to(np.asarray(dt, float), (N,))
    with threadpool_limits(limits=1, user_api="blas"), progress_bar(N, desc, progress) as bar:
        for a in range(0, N, chunk):
            b = min(N, a + chunk)
            Phi[a:b], Qd[a:b] = discretize(F[a:b], Qc[a:b], dt[a:b], method, order)
            bar.update(b - a)
    return Phi, Qd


def truth_system(model: Model, traj, t: np.ndarray, method: str, *, options=NavOptions(), progress=False):
    """Truth Φ, Q_d along the grid, plus the mid-point context and dynamics."""
    ctx = midpoint_context(traj, t)
    dyn = error_dynamics(model, ctx, options)
    Phi, Qd = discretize_chunked(dyn.F, dyn.Qc, np.diff(t), method, progress=progress, desc="truth Φ, Q")
    return ctx, dyn, Phi, Qd


def history_frame(case: str, t: np.ndarray, m: dict, every: float | None = None) -> pd.DataFrame:
    """History table with SI and paper units in the headers."""
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
    return df


def summary_row(case: str, m: dict, k: int, t: float, distance: float | None) -> dict:
    """Table 3 columns at grid index ``k``."""
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


__all__ = ["study_header", "load_truth", "time_grid", "truth_system", "history_frame", "summary_row",
           "parse_quantity", "from_si", "UnitError", "FT", "ARCMIN", "ARCSEC"]
