"""Resources of a study, checked before any computation: steps, peak memory, the memory limit, progress."""

from __future__ import annotations

import math
import os
from pathlib import Path

from covtool.errors import InputError, StudyFileError, UnitError
from covtool.io.config import number
from covtool.lincov.model.spec import Model
from covtool.units import from_si, parse_quantity


def progress_bar(total: int, desc: str, enabled: bool, unit: str = "step"):
    """A bar shown only if the work lasts longer than about one second (:func:`covtool.progress.progress_bar`)."""
    from covtool.progress import progress_bar as bar

    return bar(total, desc, enabled, unit=unit)


# ---------------------------------------------------------------------------
# resources: step count and peak memory, checked before any computation
# ---------------------------------------------------------------------------

#: steps discretised at once by :func:`covtool.studies.grid.discretize_chunked` (bounds its workspace)
DISCRETIZE_CHUNK = 150

#: steps the covariance guard tests at once (covtool.lincov.guard._CHUNK, restated so that the estimate is made
#: before the numeric core is imported; tests/test_memory_streaming.py checks they agree)
GUARD_CHUNK = 512

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
                    extra: float = 0.0, parallel: int = 1, records: int | None = None, composed=(),
                    intervals: int | None = None, extra_late: bool = False) -> dict:
    """Peak memory of a study on the propagation grid (an upper estimate).

    This is the one place that knows what the covariance code keeps for a
    whole grid; change it together with :func:`truth_system`,
    :func:`discretize_chunked`,
    :meth:`covtool.studies.zupt_setup.ZuptSetup.filter_system`,
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
        State counts of the ``records·m²`` covariance histories held at once
        (``propagate``: the truth; ``propagate_with_filter``: truth and filter;
        :func:`covtool.lincov.batch.run_batch`: the kept block of each).
    noise : int, optional
        Noise-source columns of the truth model (:func:`noise_columns`;
        default ``n``).
    extra : float
        Kind-specific bytes outside these arrays (a composed noise stack, a
        batch of cases).
    parallel : int
        Copies held at once (worker processes each building one system).
    records : int, optional
        Points of each history (default ``N + 1``: every grid time).
    composed : sequence of int
        State counts of the systems composed on an event grid
        (:class:`covtool.lincov.batch.System`: Φ and Q per interval) held at
        once.
    intervals : int, optional
        Intervals of that event grid (default ``records``).
    extra_late : bool
        ``extra`` is allocated after every discretisation (like the
        histories and the composed systems), so after the discretisation
        workspace is freed.

    Returns
    -------
    dict
        ``bytes`` (total), ``steps`` and ``parts`` (label -> bytes).

    Notes
    -----
    Per step, in doubles: the truth keeps F, Q_c, Φ, Q_d (4 n²) and the
    noise-source matrices G (n × columns); every other truth dynamics
    another F (its Q_c and G are the truth's); every filter F_f, Q_c,f, Φ_f, Q_d,f (4 n_f²) and,
    while it is built, the (N, n_f, n) slice of F it is cut from; every
    history (N+1) m² (or ``records`` m²), every composed system 2 K m².
    The discretisation works on :data:`DISCRETIZE_CHUNK` steps at a time
    (about five n × n stacks, the random constants folded out), freed
    before the histories are allocated, so only the larger of the two
    counts; the guard works on :data:`GUARD_CHUNK` steps (two n × n
    stacks), on Q_d and later on the histories, so it counts throughout.  Against ``tracemalloc`` peaks of the shipped studies the
    estimate is high by 5-15 % (``tests/test_input_validation.py`` keeps it
    an upper bound within 30 %).
    """
    N = int(steps)
    c = n if noise is None else int(noise)
    parts = {
        "truth F, Q_c, G, Phi, Q_d": (4 * n * n + n * c) * N * _F8,
        # the exact discretisation folds out the random constants (covtool.lincov.discretize.methods): about
        # five n x n stacks of one chunk
        "discretisation workspace": 5 * DISCRETIZE_CHUNK * n * n * _F8,
        # the guard tests Q_d, and later the covariance histories, by GUARD_CHUNK steps: two n x n stacks each
        "guard workspace": 2 * min(N, GUARD_CHUNK) * n * n * _F8,
        "trajectory and grid": _GRID_FLOATS * (N + 1) * _F8,
    }
    if dynamics > 1:
        # another F only: the options change its navigation block, Q_c and G are shared (with_nav_options)
        parts["other truth dynamics"] = (dynamics - 1) * n * n * N * _F8
    if len(filters):
        parts["filter F, Q_c, Phi, Q_d"] = sum(4 * N * m * m * _F8 for m in filters) + N * max(filters) * n * _F8
    rec = N + 1 if records is None else int(records)
    if len(histories):
        parts["covariance histories"] = sum(rec * m * m * _F8 for m in histories)
    if len(composed):
        K = rec if intervals is None else int(intervals)
        # Φ and Q per interval, and the composition's gathers of the step stacks (as large again)
        parts["composed systems"] = sum(2 * K * m * m * _F8 for m in composed) + 2 * K * max(composed) ** 2 * _F8
    if extra:
        parts["other"] = float(extra)
    # the Van Loan workspace is freed before the histories (and the other late arrays) are allocated
    late = parts.get("covariance histories", 0.0) + parts.get("composed systems", 0.0) + \
        (parts.get("other", 0.0) if extra_late else 0.0)
    total = sum(parts.values()) - min(parts["discretisation workspace"], late)
    if parallel > 1:
        parts = {k: v * parallel for k, v in parts.items()}
        total *= parallel
    return {"bytes": float(total), "steps": N, "parts": parts, "parallel": int(parallel)}


#: steps per chunk of a study that streams in time (covtool.lincov.dynamics.STREAM_CHUNK, restated here so
#: that the estimate is made before the numeric core is imported; test_memory checks they agree)
STREAM_CHUNK = 600
#: bytes of the reduced filters' Φ_f chunks a streamed study keeps from its propagation for its
#: equivalent-noise table (covtool.studies.zupt_setup.ZuptSetup.stream, StreamedTransitions): a 30-min study
#: keeps all of them, a long one its first chunks and computes the others again
KEPT_TRANSITIONS = 64 * 2**20
#: bytes of Φ, Q_d chunks an aided study holds for its later runs (covtool.lincov.streamed.ChunkPool, one per
#: grade): a study up to about 2 h of the 58-state truth at 1 s holds them all and discretises each step once;
#: a longer one holds its first chunks and makes the others again for each filter
HELD_CHUNKS = 512 * 2**20
#: float64 per step and per equivalent-noise source held by a streamed filter: the 3 or 4 rows its
#: dropped state drives, times up to 2 columns (interval-matched), and its PSD (CompactNoiseSource)
_EWN_FLOATS = 10


def stream_memory_estimate(steps: int, n: int, *, filters=(), dropped=(), dynamics: int = 1, histories=(),
                           noise: int | None = None, records: int | None = None, intervals: int | None = None,
                           chunk: int = STREAM_CHUNK) -> dict:
    """Peak memory of a study that streams in time (an upper estimate).

    The counterpart of :func:`memory_estimate` for
    :meth:`covtool.studies.zupt_setup.ZuptSetup.stream`: F, Q_c, Φ, Q_d and
    their composition exist for one chunk of ``chunk`` steps at a time;
    over the grid only the trajectory, the filters' equivalent-noise
    sources and the histories are held.

    Parameters
    ----------
    steps : int
        Propagation steps N.
    n : int
        Truth states.
    filters : sequence of int
        States of every filter with its own system (not sharing the truth's).
    dropped : sequence of int
        Truth states each of those filters drops (an equivalent-noise source each).
    dynamics : int
        Truth error dynamics built per chunk (one per distinct set of navigation options).
    histories : sequence of int
        State counts of the ``records·m²`` histories held at once.
    noise : int, optional
        Noise-source columns of the truth model (default ``n``).
    records, intervals : int, optional
        Points of each history and intervals of the event grid (default N + 1 and N).
    chunk : int
        Steps per chunk.

    Returns
    -------
    dict
        ``bytes`` (total), ``steps`` and ``parts`` (label -> bytes), as
        :func:`memory_estimate`.

    Notes
    -----
    Per chunk, in doubles: every truth dynamics F, Q_c, G (``2n² + n·c``),
    the truth Φ, Q_d (``2n²``) and each filter's F_f, Q_c,f, Φ_f, Q_d,f
    (``4 n_f²``) per step; the composed systems, Φ and Q per interval of
    the chunk (``2 K_c m²``, ``K_c`` at most ``chunk``) and the
    composition's gathers; the discretisation workspace (as
    :func:`memory_estimate`).  Over the grid: the trajectory
    (:data:`_GRID_FLOATS` per step), :data:`_EWN_FLOATS` per step and
    equivalent-noise source, the histories, and the transient of building
    the largest reduced filter (eq (11)–(13) gathers the couplings
    ``F_kept,·`` over the grid: ``N n_f n``, and a few ``(N, n_f)``
    temporaries) or of its navigation-effect table (``2 N n_dropped
    (n_f + 1)``: the stacked noise columns and their PSD).
    """
    N = int(steps)
    c = n if noise is None else int(noise)
    L = min(int(chunk), max(N, 1))
    K = N if intervals is None else int(intervals)
    Kc = min(L, int(math.ceil(K * L / max(N, 1))) + 2)        # intervals in one chunk (events spread evenly)
    comp = [n] + list(filters)
    parts = {
        "trajectory and grid": _GRID_FLOATS * (N + 1) * _F8,
        "one chunk of F, Q_c, G, Phi, Q_d": (dynamics * (2 * n * n + n * c) + 2 * n * n
                                             + sum(4 * m * m for m in filters)) * L * _F8,
        "one chunk of composed systems": (sum(2 * Kc * m * m for m in comp) + 2 * Kc * max(comp) ** 2) * _F8,
        # the series of eq (6b)-(6d) on DISCRETIZE_CHUNK steps: about ten n x n stacks (sums, terms, the
        # balanced F and Q_c, temporaries); no 2n x 2n Van Loan matrix is formed
        "discretisation workspace": 10 * DISCRETIZE_CHUNK * n * n * _F8,
    }
    if len(dropped):
        parts["equivalent-noise sources"] = _EWN_FLOATS * N * sum(dropped) * _F8
    red = [(m, d) for m, d in zip(filters, dropped) if d]
    if red:
        # the couplings gathered over the grid (N m n) and a few (N, m) temporaries of the eq (11)-(13) rules;
        # the navigation-effect table stacks every source's 2 columns (N m 2d) and their PSD (N 2d)
        parts["filter build (largest)"] = max(max(N * m * (n + 4), 2 * N * d * (m + 1)) for m, d in red) * _F8
        parts["kept filter transitions"] = min(KEPT_TRANSITIONS, sum(N * m * m for m, _ in red) * _F8)
    rec = N + 1 if records is None else int(records)
    if len(histories):
        parts["covariance histories"] = sum(rec * m * m * _F8 for m in histories)
    total = sum(parts.values())
    return {"bytes": float(total), "steps": N, "parts": parts, "parallel": 1}


def composed_memory_estimate(steps: int, n: int, *, filters=(), dynamics: int = 1, noise: int | None = None,
                             updates: int = 0, reports: int = 1, batch: int = 1, processes: int = 1,
                             chunk: int = STREAM_CHUNK) -> dict:
    """Peak memory of a study that composes its systems chunk by chunk and runs batches on them.

    The pattern of
    :meth:`~covtool.studies.zupt_setup.ZuptSetup.composed_truth` and
    :meth:`~covtool.studies.zupt_setup.ZuptSetup.composed_filters` (the
    sensitivity sweep, the ZUPT error budget, a ZUPT-only chunk of the
    trade grid, the magnitude sweep): each process makes one system's chunk
    at a time beside the chunk's truth dynamics, holds the truth's and every
    filter's systems composed on the ``K`` intervals of the event grid, and
    runs one filter's batch of cases.  An upper estimate.

    Parameters
    ----------
    steps : int
        Propagation steps N.
    n : int
        Truth states.
    filters : sequence of int
        States of every filter with its own system (equivalent-noise sources and builds: one per filter).
    dynamics : int
        Truth error dynamics per chunk (one per distinct set of navigation options).
    noise : int, optional
        Noise-source columns of the truth model (default ``n``).
    updates, reports : int
        Measurement updates and report times (events of the grid).
    batch : int
        Cases of one filter run at once.
    processes : int
        Processes of one setup that each make chunks and run batches at once
        (this one and a forked share, which reads the setup's arrays
        copy-on-write); independent workers each with their own setup
        multiply the whole estimate instead (:func:`scaled_estimate`).
    chunk : int
        Steps per chunk.

    Returns
    -------
    dict
        ``bytes``, ``steps``, ``parts`` and ``parallel``, as :func:`memory_estimate`.
    """
    N = int(steps)
    c = n if noise is None else int(noise)
    nf = max(filters, default=n)
    K = int(updates) + int(reports) + int(math.ceil(N / int(chunk))) + 1
    est = stream_memory_estimate(N, n, filters=list(filters), dropped=[n - m for m in filters],
                                 dynamics=dynamics, noise=c, records=reports, intervals=K, chunk=chunk)
    parts = dict(est["parts"])
    parts.pop("kept filter transitions", None)           # composed_filter keeps none
    L = min(int(chunk), max(N, 1))
    p = max(1, int(processes))
    # one system's chunk at a time beside the chunk's truth dynamics under each set of options
    # (ZuptSetup.composed_filters), in each process
    parts["one chunk of F, Q_c, G, Phi, Q_d"] = p * (dynamics * (2 * n * n + n * c) + 2 * n * n + 4 * nf * nf) \
        * L * _F8
    parts["one chunk of composed systems"] *= p
    parts["discretisation workspace"] *= p
    # the truth's system and every filter's, held together (composed_filters returns them at once)
    parts["composed systems on the events"] = p * 2 * K * (n * n + sum(m * m for m in filters)) * _F8
    parts["one filter's batch of cases"] = p * int(batch) * (6 * n * n + 6 * nf * nf + 3 * int(updates) * nf) * _F8
    return {"bytes": float(sum(parts.values())), "steps": N, "parts": parts, "parallel": 1}


def scaled_estimate(est: dict, workers: int) -> dict:
    """``est`` for ``workers`` independent processes, each holding all of it (its ``parallel`` multiplied)."""
    w = max(1, int(workers))
    return {**est, "bytes": est["bytes"] * w, "parts": {k: v * w for k, v in est["parts"].items()},
            "parallel": int(est.get("parallel", 1)) * w}


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
    """Provenance rows of a resource estimate (with its ``layout``, where the study chose one)."""
    rows = {"steps": est["steps"], "estimated_peak_memory": _size(est["bytes"]),
            "memory_limit": f"{_size(est['limit'])} ({est['limit_source']})" if math.isfinite(est["limit"])
            else "unknown"}
    if "layout" in est:
        rows["memory_layout"] = est["layout"]
    return rows


def store_checks(rs, stats: dict) -> str:
    """Provenance line of the result store's verification (notes joined)."""
    if rs is None:
        return ""
    head = (f"{stats['reused']} chunks verified and reused, {stats['rejected']} rejected, "
            f"{stats['computed']} computed")
    return "; ".join([head] + rs.notes)


def run_in_chunks(fn, tasks, keys, cases, *, backend, store, manifest, resume: bool, progress: bool, desc: str):
    """Run the chunks of a study on a backend, through the verified result store.

    Parameters
    ----------
    fn : callable
        ``fn(task) -> dict`` for one chunk (picklable, JSON-serialisable result).
    tasks, keys, cases : sequences
        Per chunk: its input, its key and its list of case labels
        (:func:`covtool.parallel.run_chunks`).
    backend : backend, str or None
        :func:`covtool.parallel.make_backend`; a backend made here is closed here.
    store : path or None
        Directory of the result store (:class:`covtool.io.store.ResultStore`);
        None keeps the results in memory only.
    manifest : callable
        ``manifest() -> dict``: the store's plan (called only with a store).
    resume, progress : bool
    desc : str
        Label of the progress bar.

    Returns
    -------
    results : list
        One result per chunk, in chunk order.
    stats : dict
        Chunks reused, rejected and computed (:func:`covtool.parallel.run_chunks`).
    store : ResultStore or None
        The (closed) store, for its notes (:func:`store_checks`).
    """
    from covtool.io.store import ResultStore
    from covtool.parallel import make_backend, run_chunks

    rs = ResultStore(store, manifest(), resume=resume) if store is not None else None
    own = backend is None or isinstance(backend, str)
    try:
        be = make_backend(backend)
        try:
            results, stats = run_chunks(fn, tasks, keys, cases, backend=be, store=rs, progress=progress, desc=desc)
        finally:
            if own:
                be.close()
    finally:
        if rs is not None:
            rs.close()
    return results, stats, rs
