"""The ZUPT study setup shared by every ZUPT study kind: schedule, truth, filters on one grid.

:func:`setup` validates the ``[study]``, ``[trajectory]``, ``[truth]``,
``[filters]`` and ``[zupt]`` tables once and builds a :class:`ZuptSetup`
(the grid and the trajectory on it, the ZUPT update steps, the filters'
models), used by the filter-order, sensitivity, budget, Monte Carlo,
trade-grid and magnitude-sweep runners.

Two ways to get the systems (seed 002, eq (6b)–(6d)):

* whole grid: :attr:`ZuptSetup.Phi`, :attr:`ZuptSetup.Qd` and
  :meth:`ZuptSetup.filter_system` build ``(N, n, n)`` stacks on first use
  (the studies that index them over the whole time);
* streamed in time: :meth:`ZuptSetup.stream` yields the truth's and the
  filters' systems composed on the event grid, chunk by chunk of
  :data:`~covtool.lincov.dynamics.STREAM_CHUNK` steps, so that memory is set
  by the cases and the history spacing, not by duration × n²
  (:class:`~covtool.lincov.batch.BatchRun` carries every case's P and P_f
  across the chunks).  The filter-order study streams;
* composed chunk by chunk: :meth:`ZuptSetup.composed_truth` and
  :meth:`ZuptSetup.composed_filters` make the same chunks and keep only
  their composition on the event grid (:class:`~covtool.lincov.batch.System`
  over the whole time, a few matrices per event), for the kinds that run
  batches of cases on composed systems: the sensitivity sweep, the ZUPT
  error budget, the trade grid's ZUPT-only chunks and the magnitude sweep;
* streamed for step-by-step runs: :meth:`ZuptSetup.streamed_system` gives
  ``Phi[k]``, ``Qd[k]`` made a chunk at a time (a
  :class:`~covtool.lincov.streamed.StreamedSystem`), for the aided engine
  of the trade grid's aiding mixes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from covtool.errors import StudyFileError
from covtool.io.config import is_library_name, names, resolve_input
from covtool.io.filters import default_filter_file, load_filters
from covtool.lincov.batch import compose, System
from covtool.lincov.dynamics import Context, DynamicsStream, dyn_key, error_dynamics, ErrorDynamics, NavOptions, \
    STREAM_CHUNK, with_nav_options
from covtool.lincov.model.spec import Model
from covtool.lincov.reduced import FilterSpec
from covtool.nav.trajectory.core import Trajectory
from covtool.lincov.kalman import check_system
from covtool.lincov.reduced import build_filter, system_key, zupt_matrices  # noqa: F401 (system_key: also from here)
from covtool.studies import grid as _grid
from covtool.studies.grid import (check_step_motion, discretize_chunked, initial_covariance, midpoint_context,
                                  time_grid)
from covtool.studies.inputs import load_trajectory, load_truth, output_options, study_config, study_header
from covtool.studies.resources import (check_memory, KEPT_TRANSITIONS, memory_estimate, memory_limit, noise_columns,
                                       steps_of, stream_memory_estimate)


def zupt_options(cfg, where: str, dt: float, duration: float) -> dict:
    """Validate ``[zupt]`` against the grid step ``dt`` and the study ``duration`` [s].

    ``cfg`` is the ``[zupt]`` table or its :class:`~covtool.studies.config.ZuptSection`.

    Raises
    ------
    StudyFileError
        Unknown key, bad unit or sign, a window not shorter than the
        interval, an interval shorter than ``dt``, a rate above ``1/dt``
        (at most one update per propagation step) or a first ZUPT after the
        end of the study.
    """
    from covtool.studies.config import ZuptSection, parse_section

    w = f"{where}: [zupt]"
    # σ = 0 makes S = H P_f Hᵀ + R of eq (7) singular once P_f's velocity block is (a previous
    # exact ZUPT leaves it zero): the gain is undefined, so the noise must be positive (declared so)
    z = cfg if isinstance(cfg, ZuptSection) else parse_section(ZuptSection, cfg, where, "zupt")
    o = {"interval": z.interval, "duration": z.duration, "rate": z.rate, "sigma": z.sigma,
         "first": z.interval if z.first is None else z.first}
    if o["duration"] >= o["interval"]:
        raise StudyFileError(f"{w} duration", f"the ZUPT window ({o['duration']:g} s) must be shorter than the "
                             "interval")
    if o["interval"] < dt * (1 - 1e-9):
        raise StudyFileError(f"{w} interval", f"{o['interval']:g} s is shorter than the propagation step dt = "
                             f"{dt:g} s")
    if o["rate"] * dt > 1 + 1e-9:
        raise StudyFileError(f"{w} rate", f"{o['rate']:g} Hz is more than one update per propagation step "
                             f"(dt = {dt:g} s, at most {1 / dt:g} Hz)")
    if o["first"] > duration + 1e-9:
        raise StudyFileError(f"{w} first", f"the first ZUPT ({o['first']:g} s) is after the end of the study "
                             f"({duration:g} s): nothing would be aided")
    return o


def zupt_update_count(o: dict, duration: float) -> int:
    """Number of ZUPT updates of validated :func:`zupt_options` ``o`` in a study of ``duration`` [s]."""
    if o["first"] > duration + 1e-9:
        return 0
    windows = int(np.floor((duration - o["first"]) / o["interval"] + 1e-9)) + 1
    return windows * (int(np.floor(o["duration"] * o["rate"] + 1e-9)) + 1)


def zupt_schedule(cfg, where: str, t: np.ndarray, traj) -> tuple[np.ndarray, float, float]:
    """Grid indices of the ZUPT updates, the interval Δt_s and R's σ.

    Raises
    ------
    StudyFileError
        Bad keys, units or ranges (:func:`zupt_options`), update times off
        the grid, or an update outside the trajectory's stationary intervals
        (the message names the time and the nearest stationary interval).
    """
    w = f"{where}: [zupt]"
    dt = t[1] - t[0]
    o = zupt_options(cfg, where, dt, t[-1])
    interval, dur, rate, sigma, first = o["interval"], o["duration"], o["rate"], o["sigma"], o["first"]
    ends = np.arange(first, t[-1] + 1e-9, interval)
    times = []
    for e in ends:
        n = int(np.floor(dur * rate + 1e-9))
        times.extend(e - np.arange(n, -1, -1) / rate)
    times = np.array(times)
    idx = np.round(times / dt).astype(int)
    if np.any(np.abs(idx * dt - times) > 1e-6 * dt) or np.any(idx >= t.size) or np.any(idx < 0):
        bad = times[np.argmax(np.abs(idx * dt - times) + (idx < 0) * dt)]
        raise StudyFileError(f"{w} rate", f"update time {bad:g} s is not on the {dt:g} s propagation grid; "
                             "choose a rate that divides 1/dt")
    stat = traj.stationary_mask(times)
    if not np.all(stat):
        bad = times[~stat][0]
        iv = traj.stationary
        near = min(iv, key=lambda ab: min(abs(bad - ab[0]), abs(bad - ab[1]))) if iv else None
        hint = f"nearest stationary interval [{near[0]:g}, {near[1]:g}] s" if near else "the trajectory never stops"
        raise StudyFileError(w, f"ZUPT at t = {bad:g} s is outside the trajectory's stationary intervals ({hint})")
    return idx, interval, sigma


def filters_file(cfg, where, base_dir) -> tuple[Path, ...]:
    """The study's filter files: ``[filters] file``, one or a list (default: the library's).

    Each entry is a path relative to the study file (never the current
    directory) or a bare name of the library's ``filters/`` folder
    (``"zupt_filters"``).  A filter's ``base`` may name a filter of any of
    them (:func:`covtool.io.filters.filters_from_files`).

    Raises
    ------
    StudyFileError
        Not a string or a non-empty list of strings, a file named twice, or
        no such file.
    """
    value = cfg.get("file") if isinstance(cfg, dict) else cfg.file
    if value is None:
        return (default_filter_file(),)
    w = f"{where}: [filters] file"
    many = isinstance(value, list)
    if many and not value:
        raise StudyFileError(w, "expected a filter file or a non-empty list of filter files, got []")
    out = []
    for i, v in enumerate(value if many else [value]):
        wi = f"{w}[{i}]" if many else w
        if isinstance(v, str) and is_library_name(v):
            from covtool.io.library import default_model_dir

            p = default_model_dir() / "filters" / f"{v}.toml"
            if not p.is_file():
                raise StudyFileError(wi, f"no filter file {v!r} in the library ({p.parent}); give a path "
                                     "relative to the study file (\"my_filters.toml\")")
        else:
            # relative to the study file that names it, never the current directory
            p = resolve_input(v, base_dir, wi, StudyFileError, what="filter file")
        if p in out:
            raise StudyFileError(wi, f"{str(p)!r} is named twice")
        out.append(p)
    return tuple(out)


def filter_cases(fcfg, specs: dict, ffile, where: str, *, nonempty: bool = False) -> list:
    """``[filters] cases``: declared filter names, each once (default: every filter).

    ``fcfg`` is the ``[filters]`` table or its section.  An empty list is
    allowed unless ``nonempty`` (a pure-INS-only run).
    """
    cases = fcfg.get("cases") if isinstance(fcfg, dict) else fcfg.cases
    if cases is None:
        return list(specs)
    return names(list(cases), f"{where}: [filters] cases", StudyFileError, known=list(specs), nonempty=nonempty,
                 what="filter")


#: (N, n, n) stacks of the filters' own model when it is not the truth (``[truth] override_filters = false``
#: with overrides): its F, Q_c, noise G (n × columns ≤ n × n) and the dropped-state impact's transition e^{FΔt}
#: under it (the truth's Φ serves only a filter with the truth's own dynamics, covtool.lincov.impact)
SEPARATE_MODEL_STACKS = 4


def filter_dynamics(specs: dict, cases, separate_model: bool = False) -> int:
    """Truth dynamics the cases need, in (N, n, n) stacks for :func:`covtool.studies.resources.memory_estimate`.

    The truth's own and one F per other set of navigation options; with
    ``separate_model`` (the filters are built from the truth without the
    study's overrides, :attr:`ZuptSetup.filter_truth`) also that model's own
    dynamics (:data:`SEPARATE_MODEL_STACKS`).
    """
    options = len({dyn_key(None)} | {dyn_key(specs[c].options) for c in cases})
    return options + (SEPARATE_MODEL_STACKS if separate_model and len(cases) else 0)


@dataclass
class ZuptSetup:
    """Everything a ZUPT study shares between its cases (truth system, schedule, filters).

    Built by :func:`setup`; used by the filter-order, sensitivity, budget and
    trade-grid studies.  Filter models and their discretisation are built on
    demand and cached (:meth:`filter_model`); the truth's whole-grid
    :attr:`dyn`, :attr:`Phi` and :attr:`Qd` too.  :meth:`stream` builds
    them chunk by chunk instead; :meth:`release` frees the caches.
    Shapes: N grid steps, n truth states; times in s.
    """

    #: ``[study]`` as validated (:func:`covtool.studies.inputs.study_header`)
    hdr: dict
    #: the study file, for messages
    where: str
    #: time grid, shape (N+1,) [s]
    t: np.ndarray
    #: the trajectory sampled on ``t``
    nodes: Trajectory
    truth: Model
    #: the trajectory at the propagation mid-points
    ctx: Context
    #: the truth's initial covariance, shape (n, n)
    P0: np.ndarray
    #: ZUPT measurement matrix, shape (3, n), and its true noise, shape (3, 3)
    H: np.ndarray
    R: np.ndarray
    #: grid indices of the ZUPT updates
    update_steps: np.ndarray
    #: Δt_s of eq (11)-(13) [s] and the true ZUPT 1σ [m/s]
    zupt_interval: float
    zupt_sigma: float
    #: declared filters by name, and the cases run
    specs: dict[str, FilterSpec]
    cases: list[str]
    #: mean moving speed [m/s] (None: the trajectory never moves)
    mean_speed: float | None
    #: the filter files, as resolved
    filter_files: tuple[Path, ...]
    #: ``[output] history_every`` [s] and ``report_times`` [s]
    every: float
    report_times: list[float]
    resources: dict = field(default_factory=dict)
    #: the model the filters are built from: the truth, or the truth without the study's
    #: overrides (``[truth] override_filters = false``, :func:`covtool.studies.inputs.load_truth`)
    filter_truth: Model | None = None
    #: the trajectory's stationary intervals holding a ZUPT, ``((start, end), ...)`` [s] (figures shade them)
    stops: tuple = ()
    #: the truth's discretisation method (``[study] discretization``)
    method: str = "van_loan"
    _dyn_cache: dict = field(default_factory=dict)
    _filters: dict = field(default_factory=dict)
    #: (system key, first step, Φ_f) of a reduced filter over one stream chunk, up to KEPT_TRANSITIONS bytes
    _kept: list = field(default_factory=list)
    _dyn: ErrorDynamics | None = None
    _Phi: np.ndarray | None = None
    _Qd: np.ndarray | None = None
    _streams: dict = field(default_factory=dict)

    # -- the whole grid, built on first use (studies that hold it); the flagship streams instead (stream)
    @property
    def dyn(self) -> ErrorDynamics:
        """The truth's F and Q_c along the whole grid, shape (N, n, n) (built on first use)."""
        if self._dyn is None:
            self._dyn = error_dynamics(self.truth, self.ctx)
        return self._dyn

    @property
    def Phi(self) -> np.ndarray:
        """The truth's transition of every step, shape (N, n, n) (built on first use)."""
        self._whole_truth()
        return self._Phi

    @property
    def Qd(self) -> np.ndarray:
        """The truth's process noise of every step, shape (N, n, n) (built on first use)."""
        self._whole_truth()
        return self._Qd

    def _whole_truth(self) -> None:
        if self._Phi is None:
            self._Phi, self._Qd = self._discretise_truth(self.dyn, 0, self.t.size - 1)

    def _discretise_truth(self, dyn, a: int, b: int):
        """Truth Φ, Q_d of the steps ``a … b−1`` from their dynamics ``dyn``, guarded (:func:`truth_system`)."""
        what = f"{self.where}: truth model {self.truth.name!r}"
        # through the module, as truth_system does (one place to instrument the truth's discretisation);
        # guarded once here, the runs that share them are told so (system_checked)
        return _grid.discretize_steps(dyn.F, dyn.Qc, self.t, a, b, self.method, what=what, label=what,
                                      names=self.truth.names)

    def release(self) -> None:
        """Free the whole-grid arrays, the filters' systems and the kept stream chunks (rebuilt on demand)."""
        self._dyn = self._Phi = self._Qd = None
        self._dyn_cache.clear()
        self._filters.clear()
        self._streams.clear()
        self._kept.clear()

    # -- streaming in time: nothing of size N × n² is held
    def filter_stream(self, name: str):
        """``(FilterModel, reused)`` of a declared filter for :meth:`stream`, cached.

        The model holds no ``F``, ``Q_c`` over the grid (``fm.F is None``)
        unless the whole-grid system is already built (:meth:`filter_system`);
        ``reused``: the filter's Φ_f, Q_f are the truth's (all the truth's
        states in its order, its options, no equivalent noise, an exact
        discretisation: :func:`truth_copy`).
        """
        if (name, None) in self._filters:
            fm, _, _, reused = self._filters[(name, None)]
            return fm, reused
        if name not in self._streams:
            spec = self.specs[name]
            # a filter that differs from one already built only in what it assumes at the update (R_f, the
            # update form) has the same F_f, Q_c,f, P_f(0) and D: that system is shared, not built again
            twin = next((v for v in self._streams.values() if system_key(v[0].spec) == system_key(spec)), None)
            if twin is not None:
                self._streams[name] = (dataclasses.replace(twin[0], spec=spec), twin[1])
                return self._streams[name]
            ftruth = self.filter_truth if self.filter_truth is not None else self.truth
            fm = build_filter(spec, ftruth, self.ctx, zupt_interval=self.zupt_interval, q0=self.nodes.q_nb[0],
                              truth_dynamics=self.dynamics_stream(spec.options), mean_speed=self.mean_speed,
                              dt_steps=np.diff(self.t), update_steps=self.update_steps)
            reused = (truth_copy(spec, self.truth, self.filter_truth) and not fm.ewn_noise
                      and np.array_equal(self.truth.idx(spec.kept), np.arange(self.truth.n)))
            self._streams[name] = (fm, reused)
        return self._streams[name]

    def dynamics_stream(self, options=None) -> DynamicsStream:
        """The truth's F, Q_c under ``options`` (None: its own), chunk by chunk (:class:`DynamicsStream`)."""
        key = self._stream_key(options)
        if key not in self._dyn_cache:
            model = self.truth if key[1] == "truth" else self.filter_truth
            self._dyn_cache[key] = DynamicsStream(model, self.ctx, options or NavOptions())
        return self._dyn_cache[key]

    def _stream_key(self, options):
        """Cache key of a dynamics stream: the truth's own, or a filter's (the filters' model and options)."""
        if options is None or (self.filter_truth is None and dyn_key(options) == dyn_key(None)):
            return ("stream", "truth")
        return ("stream", "filter" if self.filter_truth is not None else "truth") + dyn_key(options)

    def stream_grid(self, ev, chunk: int = STREAM_CHUNK) -> np.ndarray:
        """The event grid ``ev`` with the chunk boundaries of :meth:`stream` added (multiples of ``chunk``)."""
        N = self.t.size - 1
        return np.union1d(np.asarray(ev, int), np.r_[np.arange(0, N, int(chunk)), N])

    def stream(self, ev, cases, *, chunk: int = STREAM_CHUNK):
        """The truth's and the filters' systems composed on ``ev``, chunk by chunk in time.

        Parameters
        ----------
        ev : ndarray of int
            Event grid holding the chunk boundaries (:meth:`stream_grid`).
        cases : sequence of str
            Declared filters.
        chunk : int
            Steps per chunk (a multiple of
            :data:`~covtool.studies.resources.DISCRETIZE_CHUNK`: every step is
            discretised in the same batch as on the whole grid).

        Yields
        ------
        truth : covtool.lincov.batch.System
            Composed on the chunk's events (global step indices).
        filters : dict of str to System
            Per case, on the same events (the truth's for a reused filter).

        Notes
        -----
        F, Q_c (:class:`~covtool.lincov.dynamics.DynamicsStream`), Φ, Q_d and
        their composition exist for one chunk at a time, so the memory does
        not grow with the duration.  Where the whole-grid arrays are already
        built (a study that also needs them) they are sliced instead.
        """
        for a, b, cev in self.chunks(ev, chunk):
            dyn_of = self.chunk_dynamics(a, b)
            Phi, Qd = self.truth_chunk(a, b, dyn_of)
            tsys = System(cev, *compose(Phi, Qd, cev - a))
            del Phi, Qd
            fsys, shared = {}, []
            for c in cases:
                fm, reused = self.filter_stream(c)
                if reused:
                    fsys[c] = tsys
                    continue
                key = system_key(fm.spec)
                twin = next((v for k, v in shared if k == key), None)
                if twin is not None and (c, None) not in self._filters:
                    fsys[c] = twin                           # the same F_f, Q_c,f (filter_stream)
                    continue
                Phi_f, Qd_f = self.filter_chunk(c, a, b, dyn_of)
                if (c, None) not in self._filters and fm.spec.n < self.truth.n:
                    self._keep(key, a, Phi_f)                 # for the equivalent-noise table
                fsys[c] = System(cev, *compose(Phi_f, Qd_f, cev - a))
                shared.append((key, fsys[c]))
            yield tsys, fsys

    def streamed_system(self, name: str | None = None):
        """Φ, Q_d of the truth (``name`` None) or of a declared filter for step-by-step consumers, made a chunk at a time.

        For runs that walk the grid one step at a time (the aided engine,
        :func:`covtool.lincov.aided.propagate_aided`: a trade grid's aiding
        mixes).  Each chunk of :data:`STREAM_CHUNK` steps is made from the
        chunk's truth dynamics (built once per chunk for every system that
        reads it) and guarded as :meth:`stream` makes it: the same values as
        the whole-grid stacks, which are served as they are where already
        built.  Chunks are held while the setup's pool of
        :data:`~covtool.studies.resources.HELD_CHUNKS` has room; beyond it,
        every run makes them again.  A filter that reuses the truth's system
        (:meth:`filter_stream`) gets the truth's, and filters that differ
        only in the update (:func:`system_key`) share one.  Cached.

        Parameters
        ----------
        name : str, optional
            Declared filter; None: the truth.

        Returns
        -------
        covtool.lincov.streamed.StreamedSystem or types.SimpleNamespace
            ``.Phi[k]``, ``.Qd[k]``, shape ``(n, n)`` (the filter's states),
            and ``.shape``-carrying stacks (``Phi.shape == (N, n, n)``).

        Raises
        ------
        SystemCheckError
            On the read that makes a chunk: Φ or Q_d of a step is not finite
            (Q_d: symmetric, PSD), naming the system, the step's time and the
            state (:class:`~covtool.errors.NumericalError`).
        """
        from types import SimpleNamespace

        from covtool.lincov.streamed import ChunkPool, StreamedSystem
        from covtool.studies.resources import HELD_CHUNKS

        reused = name is not None and self.filter_stream(name)[1]
        if name is None or reused:
            if self._Phi is not None:
                return SimpleNamespace(Phi=self._Phi, Qd=self._Qd)
            key = None
        else:
            if (name, None) in self._filters:
                _, Phi_f, Qd_f, _ = self._filters[(name, None)]
                return SimpleNamespace(Phi=Phi_f, Qd=Qd_f)
            fm = self.filter_stream(name)[0]
            key = system_key(fm.spec)                          # compared by equality (it holds a dict)
        made = self._dyn_cache.setdefault(("streamed systems",), [])
        found = next((v for k, v in made if k == key), None)
        if found is not None:
            return found
        pool = self._dyn_cache.setdefault(("streamed pool",), ChunkPool(HELD_CHUNKS))
        if key is None:
            def make(a, b):
                return self.truth_chunk(a, b, self._streamed_dynamics(a, b))

            n = self.truth.n
        else:
            def make(a, b):
                return self._discretise_filter(name, self._streamed_dynamics(a, b)(fm.spec.options), a, b)

            n = len(fm.names)
        made.append((key, StreamedSystem(make, self.t.size - 1, n, pool=pool)))
        return made[-1][1]

    def hold_chunks(self, budget: float) -> None:
        """Set the bytes of chunks :meth:`streamed_system` holds for later reads (default
        :data:`~covtool.studies.resources.HELD_CHUNKS`); before the first streamed system is made.

        A study that reads its systems many times and whose memory check allows
        them all (the Monte Carlo's analyses) holds every chunk: each is made once.

        Raises
        ------
        RuntimeError
            A streamed system already exists (its pool is set).
        """
        from covtool.lincov.streamed import ChunkPool

        if ("streamed pool",) in self._dyn_cache:
            raise RuntimeError("hold_chunks: the streamed systems' pool is already in use")
        self._dyn_cache[("streamed pool",)] = ChunkPool(budget)

    def _streamed_dynamics(self, a: int, b: int):
        """:meth:`chunk_dynamics` of the steps ``a … b−1``, kept for the next system made over the same chunk."""
        last = self._dyn_cache.get(("streamed dynamics",))
        if last is None or last[:2] != (a, b):
            last = (a, b, self.chunk_dynamics(a, b))
            self._dyn_cache[("streamed dynamics",)] = last
        return last[2]

    def chunks(self, ev, chunk: int = STREAM_CHUNK):
        """``(a, b, cev)`` of every chunk of :meth:`stream`: its steps ``a … b−1`` and the events in ``[a, b]``.

        Raises
        ------
        ValueError
            ``ev`` lacks a chunk boundary (:meth:`stream_grid` adds them).
        """
        ev = np.asarray(ev, int)
        N = self.t.size - 1
        for a in range(0, N, int(chunk)):
            b = min(N, a + int(chunk))
            cev = ev[(ev >= a) & (ev <= b)]
            if cev[0] != a or cev[-1] != b:
                raise ValueError(f"the event grid lacks the chunk boundaries {a}, {b} (use stream_grid)")
            yield a, b, cev

    def truth_chunk(self, a: int, b: int, dyn_of):
        """The truth's Φ, Q_d of the steps ``a … b−1``, shape (b − a, n, n).

        Sliced from the whole grid if built, else made from ``dyn_of(None)``
        (the chunk's dynamics, :meth:`chunk_dynamics`) and guarded.

        Raises
        ------
        NumericalError
            A step's F, Φ or Q_d is not finite (Q_d: symmetric, PSD), naming the truth model and the step's
            time (and the state, or the grid step where it was discretised).
        """
        if self._Phi is not None:
            return self._Phi[a:b], self._Qd[a:b]
        return self._discretise_truth(dyn_of(None), a, b)

    def filter_chunk(self, name: str, a: int, b: int, dyn_of, *, make: bool = True, on_chunk=None):
        """Filter ``name``'s own Φ_f, Q_f of the steps ``a … b−1``, shape (b − a, n_f, n_f), or None.

        Sliced from the whole-grid system if built (:meth:`filter_system`), else made from the chunk's
        truth dynamics under the filter's options (``dyn_of``, :meth:`chunk_dynamics`) and guarded, or,
        with ``make`` False, None.  ``on_chunk(a, F_f, Q_cf)``, if given, sees the chunk's F_f and Q_c,f
        (seed 002 eq (11)–(13)) the system is made from (the whole grid's slices where it is held).

        Raises
        ------
        NumericalError
            A step's F_f, Φ_f or Q_f is not finite (Q_f: symmetric, PSD), naming the filter (and its file
            where it was discretised) and the step's time (and the state, or the grid step).
        """
        whole = self._filters.get((name, None))
        if whole is not None:
            if on_chunk is not None:
                on_chunk(a, whole[0].F[a:b], whole[0].Qc[a:b])
            return whole[1][a:b], whole[2][a:b]
        if not make:
            return None
        return self._discretise_filter(name, dyn_of(self.filter_stream(name)[0].spec.options), a, b,
                                       on_chunk=on_chunk)

    def truth_transition_serves(self, options) -> bool:
        """Whether the truth's own Φ is e^{FΔt} of the filters' model under ``options``.

        True for the truth's own options when the filters' model is the truth
        and the study discretises it exactly (``van_loan``): then the truth's
        Φ serves as the transition under those options (the dropped-state
        impact), else it must be discretised from that F.
        """
        return self._stream_key(options) == ("stream", "truth") and self.method == "van_loan"

    def composed_cache(self):
        """The study's :class:`covtool.lincov.noise.ComposedCache` (per-source compositions shared between calls)."""
        from covtool.lincov.noise import ComposedCache

        return self._dyn_cache.setdefault(("impact noise",), ComposedCache())

    def chunk_dynamics(self, a: int, b: int):
        """``dyn_of(options)``: the truth's dynamics of the steps ``a … b−1`` under ``options`` (None: its own),
        built on first use and shared by every system of those options in the chunk."""
        dyns = {}

        def dyn_of(options=None):
            key = self._stream_key(options)
            if key not in dyns:
                dyns[key] = self.dynamics_stream(options).chunk(a, b)
            return dyns[key]

        return dyn_of

    def composed_truth(self, ev, *, chunk: int = STREAM_CHUNK, on_chunk=None) -> System:
        """The truth's system composed on the event grid ``ev``, built chunk by chunk in time.

        Parameters
        ----------
        ev : ndarray of int
            Event grid holding the chunk boundaries (:meth:`stream_grid`).
        on_chunk : callable, optional
            ``on_chunk(a, cev, dyn, Phi)`` for each chunk in turn: its first
            step, its events, its truth dynamics (F, Q_c and the noise
            sources of the steps ``a …``) and its Φ, shape (L, n, n).

        Returns
        -------
        covtool.lincov.batch.System
            Φ, Q over each interval of ``ev``, shape (K, n, n): the same
            products as :meth:`stream` yields, joined (:meth:`System.concat`).

        Notes
        -----
        The truth's F, Q_c, Φ and Q_d (seed 002, eq (6b)–(6d)) exist for one
        chunk at a time: memory is set by the events, not by duration × n².
        """
        parts = []
        for a, b, cev in self.chunks(ev, chunk):
            dyn_of = self.chunk_dynamics(a, b)
            Phi, Qd = self.truth_chunk(a, b, dyn_of)
            parts.append(System(cev, *compose(Phi, Qd, cev - a)))
            if on_chunk is not None:
                on_chunk(a, cev, dyn_of(None), Phi)
            del Phi, Qd
        return System.concat(parts)

    def composed_filter(self, name: str, ev, discretization: str | None = None, *, truth: System | None = None,
                        on_chunk=None, chunk: int = STREAM_CHUNK):
        """``(FilterModel, System, reused)`` of one declared filter on the event grid ``ev``, chunk by chunk.

        :meth:`composed_filters` of ``[name]``; ``on_chunk(a, F_f, Q_cf)`` is
        that filter's callback.
        """
        cb = None if on_chunk is None else {name: on_chunk}
        return self.composed_filters([name], ev, discretization, truth=truth, on_chunk=cb, chunk=chunk)[name]

    def composed_filters(self, names, ev, discretization: str | None = None, *, truth: System | None = None,
                         on_chunk: dict | None = None, chunk: int = STREAM_CHUNK) -> dict:
        """``{name: (FilterModel, System, reused)}`` of declared filters on the event grid ``ev``, chunk by chunk.

        The chunks are the outer loop: the truth's dynamics of a chunk under
        each set of navigation options are built once for every filter of
        those options, and filters that differ only in what the update
        assumes (:func:`system_key`: R_f, the update form) share one system.

        Parameters
        ----------
        names : sequence of str
            Declared filters.
        ev : ndarray of int
            Event grid holding the chunk boundaries (:meth:`stream_grid`).
        discretization : {None, "declared", "taylor", "van_loan"}
            Override of the filters' declared discretisation (sweeps).
        truth : System, optional
            The truth's system on ``ev`` (:meth:`composed_truth`), returned
            for a filter that reuses it; composed here if needed and omitted.
        on_chunk : dict of str to callable, optional
            Per filter, ``on_chunk[name](a, F_f, Q_cf)`` with its F_f and
            Q_c,f of the steps ``a …`` (shape (L, n_f, n_f); seed 002,
            eq (11)–(13)), for each chunk in turn (the truth's own for a
            reused filter).

        Returns
        -------
        dict of str to tuple
            ``fm``: the :class:`~covtool.lincov.reduced.FilterModel` without
            F, Q_c over the grid (:meth:`filter_stream`), its spec carrying
            the discretisation used; ``system``: Φ_f, Q_f composed on
            ``ev``; ``reused``: its Φ_f, Q_f are the truth's (``system`` is
            ``truth``).
        """
        on_chunk = on_chunk or {}
        models = {}
        for name in names:
            fm, reused = self.filter_stream(name)
            if discretization not in (None, "declared"):
                spec = dataclasses.replace(fm.spec, discretization=discretization)
                fm = dataclasses.replace(fm, spec=spec)
                reused = reused and truth_copy(spec, self.truth, self.filter_truth)
            models[name] = (fm, reused)
        own = [c for c in names if not models[c][1]]
        # one system per key (the first filter of it makes it), the others of the key share it
        # (specs hold dicts: compared, not hashed)
        keys = []
        maker = {}
        for c in own:
            key = system_key(models[c][0].spec)
            first = next((m for k, m in keys if k == key), None)
            if first is None:
                keys.append((key, c))
            maker[c] = first or c
        parts = {c: [] for c in own if maker[c] == c}
        watched = [c for c in names if c in on_chunk and (models[c][1] or maker[c] != c)]
        if own or watched:
            for a, b, cev in self.chunks(ev, chunk):
                dyn_of = self.chunk_dynamics(a, b)
                for c in parts:
                    fm = models[c][0]
                    Phi_f, Qd_f = self._discretise_filter(c, dyn_of(fm.spec.options), a, b, spec=fm.spec,
                                                          on_chunk=on_chunk.get(c))
                    parts[c].append(System(cev, *compose(Phi_f, Qd_f, cev - a)))
                    del Phi_f, Qd_f
                for c in watched:                        # a reused filter, or one whose system another made
                    fm, reused = models[c]
                    if reused:
                        d = dyn_of(None)
                        on_chunk[c](a, d.F, d.Qc)
                    else:
                        on_chunk[c](a, *fm.chunk(dyn_of(fm.spec.options), a, b))
        if any(r for _, r in models.values()) and truth is None:
            truth = self.composed_truth(ev, chunk=chunk)
        systems = {c: System.concat(p) for c, p in parts.items()}
        return {c: (fm, truth if reused else systems[maker[c]], reused) for c, (fm, reused) in models.items()}

    def _keep(self, key, a: int, Phi_f: np.ndarray) -> None:
        """Hold Φ_f of the chunk from step ``a`` (read only) while the kept chunks stay within the budget.

        ``key`` is the filter's :func:`system_key` (filters of one key share the chunk); the budget is
        :data:`~covtool.studies.resources.KEPT_TRANSITIONS` bytes.
        """
        if self.kept_transition(key, a) is None \
                and sum(P.nbytes for _, _, P in self._kept) + Phi_f.nbytes <= KEPT_TRANSITIONS:
            Phi_f.flags.writeable = False
            self._kept.append((key, a, Phi_f))

    def kept_transition(self, key, a: int):
        """Φ_f the stream kept for system ``key`` over the chunk from step ``a`` (:meth:`_keep`), or None."""
        return next((P for k, a_, P in self._kept if a_ == a and k == key), None)

    def _discretise_filter(self, name: str, dyn, a: int, b: int, *, spec=None, on_chunk=None):
        """Φ_f, Q_f of filter ``name`` over the steps ``a … b−1`` from the chunk's truth dynamics, guarded.

        ``spec`` overrides the filter's discretisation (:meth:`composed_filter`); ``on_chunk(a, F_f, Q_cf)``
        sees the chunk's F_f, Q_c,f before they are discretised.
        """
        fm, _ = self.filter_stream(name)
        spec = fm.spec if spec is None else spec
        F_f, Qc_f = fm.chunk(dyn, a, b)
        if on_chunk is not None:
            on_chunk(a, F_f, Qc_f)
        return _grid.discretize_steps(F_f, Qc_f, self.t, a, b, spec.discretization, spec.taylor_order,
                                      what=f"{spec.path}: filter {name!r}", label=f"{self.where}: filter {name}",
                                      names=fm.names)

    def filter_transitions(self, name: str):
        """Φ_f of every step of filter ``name``: the whole-grid stack if built, else :class:`StreamedTransitions`."""
        if (name, None) in self._filters:
            return self._filters[(name, None)][1]
        return StreamedTransitions(self, name)

    @property
    def filter_file(self) -> Path:
        """The first of :attr:`filter_files` (the only one in most studies)."""
        return self.filter_files[0]

    def filter_system(self, name: str, discretization: str | None = None):
        """``(FilterModel, Φ_f, Q_f, reused)`` of a declared filter, cached.

        Parameters
        ----------
        name : str
            Declared filter.
        discretization : {None, "declared", "taylor", "van_loan"}
            Override of the filter's declared discretisation (sweeps).

        Notes
        -----
        A filter with exactly the truth's F and Q_c, discretised exactly
        (``van_loan``, or ``taylor`` without a fixed order: the same converged
        series as the truth's), has the truth's Φ and Q_d: they are returned
        as they are (``reused = True``), not computed again.
        """
        ckey = (name, None if discretization == "declared" else discretization)
        if ckey not in self._filters:
            fm = self.filter_build(name, ckey[1])
            spec = fm.spec
            # the truth is discretised exactly (van_loan, or taylor without an order: the same
            # converged series, covtool.lincov.discretize); so is a filter with either
            same_method = spec.discretization == "van_loan" or spec.taylor_order is None
            if fm.F.shape == self.dyn.F.shape and np.array_equal(fm.F, self.dyn.F) \
                    and np.array_equal(fm.Qc, self.dyn.Qc):
                # equal arrays: hold the truth's, not a second (N, n, n) copy of each (exact)
                if fm.Qc_kept is not None and np.array_equal(fm.Qc_kept, fm.Qc):
                    fm.Qc_kept = self.dyn.Qc
                fm.F, fm.Qc = self.dyn.F, self.dyn.Qc
            if same_method and fm.F is self.dyn.F and fm.Qc is self.dyn.Qc:
                self._filters[ckey] = (fm, self.Phi, self.Qd, True)
            else:
                Phi_f, Qd_f = discretize_chunked(fm.F, fm.Qc, np.diff(self.t), spec.discretization,
                                                 spec.taylor_order, what=f"{spec.path}: filter {name!r}",
                                                 times=self.t[:-1])
                # guarded once here; the runs that use them are told so (system_checked)
                check_system(f"{self.where}: filter {name}", Phi_f, Qd_f, names=fm.names, times=self.t)
                self._filters[ckey] = (fm, Phi_f, Qd_f, False)
        return self._filters[ckey]

    def filter_build(self, name: str, discretization: str | None = None):
        """The :class:`~covtool.lincov.reduced.FilterModel` of a declared filter (seed 002, eq (11)–(13)), not cached.

        Its F_f, Q_f along the grid, D and P_f(0), as :meth:`filter_system` builds
        them before discretising (``discretization`` overrides the declared one).
        """
        spec = self.specs[name]
        if discretization not in (None, "declared"):
            spec = dataclasses.replace(spec, discretization=discretization)
        ftruth = self.filter_truth if self.filter_truth is not None else self.truth
        return build_filter(spec, ftruth, self.ctx, zupt_interval=self.zupt_interval,
                            q0=self.nodes.q_nb[0], truth_dynamics=self.options_dynamics(spec.options),
                            mean_speed=self.mean_speed, dt_steps=np.diff(self.t),
                            update_steps=self.update_steps)

    def options_dynamics(self, options=None):
        """F and Q_c along the whole grid of the model the filters are built from, under ``options``.

        The filters' model is the truth itself, or (``[truth]
        override_filters = false`` with overrides) the truth without the
        study's overrides (:attr:`filter_truth`).  Its own dynamics for its
        own options (:attr:`dyn` when it is the truth), else its dynamics
        with the navigation block of ``options``
        (:func:`covtool.lincov.dynamics.with_nav_options`; F built on first
        use), cached per options: every filter with these options, and
        every analysis of it (the dropped-state impact, the magnitude
        sweep), uses this one.

        Parameters
        ----------
        options : covtool.nav.NavOptions, optional
            The filter's navigation options (None: the model's own).

        Returns
        -------
        covtool.lincov.dynamics.ErrorDynamics
        """
        key = dyn_key(options)
        if key not in self._dyn_cache:
            # the options change only F's navigation block: derived from the model's own dynamics
            ftruth = self.filter_truth if self.filter_truth is not None else self.truth
            if ftruth is not self.truth and ("filter truth",) not in self._dyn_cache:
                self._dyn_cache[("filter truth",)] = error_dynamics(ftruth, self.ctx)
            base = self.dyn if ftruth is self.truth else self._dyn_cache[("filter truth",)]
            self._dyn_cache[key] = with_nav_options(base, self.ctx, options)
        return self._dyn_cache[key]

    def filter_shares(self, names) -> tuple[list, list]:
        """``(forked, own)``: the filters of ``names`` a forked process builds, and those left to this one.

        A filter that is the truth itself (:func:`truth_copy`: it reuses the
        truth's Φ, Q_d and holds its F, Q_c) stays here: its arrays would
        cost more to send back than to build.
        The others are balanced by a cost estimate of each build, the square
        of the filter's states, the heaviest first to the lighter side; both
        lists keep the order of ``names``.
        """
        names = list(names)
        own = [c for c in names if truth_copy(self.specs[c], self.truth, self.filter_truth)]
        load, share = [0.0, 0.0], ([], [])
        for c in sorted((c for c in names if c not in own), key=lambda c: self.specs[c].n, reverse=True):
            k = int(load[1] < load[0])
            share[k].append(c)
            load[k] += float(self.specs[c].n) ** 2
        forked = [c for c in names if c in share[1]]
        return forked, [c for c in names if c not in forked]

    def filter_model(self, name: str):
        """``(FilterModel, Φ_f, Q_f)`` of a declared filter, cached (see :meth:`filter_system`)."""
        return self.filter_system(name)[:3]

    def filter_R(self, name: str) -> np.ndarray:
        """The measurement noise the filter assumes (its ``zupt_sigma`` or the study's)."""
        zs = self.specs[name].zupt_sigma
        return np.eye(3) * (zs if zs is not None else self.zupt_sigma) ** 2


def setup(decl, *, path=None, progress: bool = False, extra_sections=(), memory=None,
          shrink: str = "a larger [study] dt, a shorter duration or fewer [filters] cases", grade=None) -> ZuptSetup:
    """Validate a ZUPT study declaration and build the shared truth system.

    Parameters
    ----------
    decl : dict or covtool.studies.config.ZuptStudyConfig
        The declaration (parsed here, once, into its kind's configuration)
        or the configuration itself (the trade grid varies one by
        ``model_copy``).
    extra_sections : tuple of str
        Unused: the kind's configuration declares its sections (kept for
        callers).
    memory : callable, optional
        ``memory(steps, truth, filter_sizes, dynamics) -> dict`` from
        :func:`covtool.studies.resources.memory_estimate`: what the calling
        study holds at its peak.  Checked against the memory limit before
        anything is built; ``None`` skips the check (a worker of a plan
        that was checked as a whole).
    shrink : str
        The options that shrink the study, for the refusal message.
    grade : covtool.studies.config.GradeEntry, optional
        An IMU grade applied to the truth (:func:`covtool.studies.inputs.load_truth`).
    """
    where = str(path) if path else "<study>"
    base_dir = path.parent if path else None
    cfg = study_config(decl, where)
    hdr = study_header(cfg, where)
    every, rtimes = output_options(cfg, where, hdr["duration"])
    zupt_options(cfg.zupt, where, hdr["dt"], hdr["duration"])
    truth, ftruth = load_truth(cfg, where, base_dir, for_filters=True, grade=grade)
    ffile = filters_file(cfg.filters, where, base_dir)
    specs = load_filters(ffile, truth)
    cases = filter_cases(cfg.filters, specs, ffile, where)
    est = {}
    if memory is not None:
        steps = steps_of(hdr["duration"], hdr["dt"])
        kw = {}
        if getattr(memory, "records", False):
            zo = zupt_options(cfg.zupt, where, hdr["dt"], hdr["duration"])
            kw = dict(zip(("records", "intervals"), history_records(
                steps, hdr["dt"], every, rtimes, zupt_update_count(zo, hdr["duration"]))))
            kw["shared"] = sum(1 for c in cases if truth_copy(specs[c], truth, ftruth))
            keys = []
            for c in cases:
                if not truth_copy(specs[c], truth, ftruth) and system_key(specs[c]) not in keys:
                    keys.append(system_key(specs[c]))
            kw["distinct"] = [k.n for k in keys]            # streamed: one system per distinct key
            if getattr(memory, "updates", False):
                kw["updates"], kw["reports"] = zupt_update_count(zo, hdr["duration"]), len(rtimes)
            if getattr(memory, "limit", False):
                kw["max_memory"] = hdr["max_memory"]
                kw["option_sets"] = len({dyn_key(None)} | {dyn_key(specs[c].options) for c in cases})
        est = check_memory(memory(steps, truth, [specs[c].n for c in cases],
                                  filter_dynamics(specs, cases, ftruth is not truth), **kw),
                           where, hdr["max_memory"], shrink)
    traj = load_trajectory(cfg, where, base_dir, hdr["dt"], hdr["duration"])
    t = time_grid(hdr["duration"], hdr["dt"], where)
    upd, dt_s, zsig = zupt_schedule(cfg.zupt, where, t, traj)
    check_step_motion(traj, t, where)
    ctx = midpoint_context(traj, t)
    nodes = traj.sample(t)
    P0 = initial_covariance(truth, nodes, where)
    moving = t[-1] - t[0] - sum(max(0.0, min(b, t[-1]) - max(a, t[0])) for a, b in traj.stationary)
    mean_speed = float(nodes.distance[-1] / moving) if moving > 0 else None
    H = zupt_matrices(truth.names)
    R = np.eye(3) * zsig**2
    tu = t[upd]
    stops = tuple((max(a, t[0]), min(b, t[-1])) for a, b in traj.stationary
                  if np.any((tu >= a - 1e-9) & (tu <= b + 1e-9)))
    return ZuptSetup(hdr, where, t, nodes, truth, ctx, P0, H, R, upd, dt_s, zsig, specs, cases,
                     mean_speed, ffile, every, rtimes, est, None if ftruth is truth else ftruth, stops=stops,
                     method=hdr["discretization"])


class StreamedTransitions:
    """Φ_f[k] of a filter computed on demand by chunks of :data:`STREAM_CHUNK` steps (the last two kept).

    A chunk the propagation's stream held (:meth:`ZuptSetup.stream`, up to
    :data:`~covtool.studies.resources.KEPT_TRANSITIONS` bytes) is taken as it is.

    Stands for the ``(N, n_f, n_f)`` stack where a consumer reads the steps
    in runs (:func:`covtool.lincov.reduced.ewn_navigation_effect` walks each
    ZUPT interval backwards); values equal the whole-grid stack's.
    """

    def __init__(self, S: ZuptSetup, name: str, chunk: int = STREAM_CHUNK):
        fm, reused = S.filter_stream(name)
        self.S, self.name, self.chunk, self.reused = S, name, int(chunk), reused
        self.shape = (S.t.size - 1, len(fm.names), len(fm.names))
        self._cache: dict = {}

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, k):
        k = int(k)
        if k < 0:
            k += self.shape[0]
        m = k // self.chunk
        if m not in self._cache:
            a, b = m * self.chunk, min(self.shape[0], (m + 1) * self.chunk)
            S = self.S
            fm, _ = S.filter_stream(self.name)
            kept = None if self.reused else S.kept_transition(system_key(fm.spec), a)
            if kept is not None:                                 # held from the propagation's stream
                self._cache[m] = kept
            elif self.reused:
                self._cache[m] = S._discretise_truth(S.dynamics_stream(None).chunk(a, b), a, b)[0]
            else:
                self._cache[m] = S._discretise_filter(self.name, S.dynamics_stream(fm.spec.options).chunk(a, b), a,
                                                      b)[0]
            while len(self._cache) > 2:
                self._cache.pop(next(iter(self._cache)))
        return self._cache[m][k - m * self.chunk]


#: bytes up to which a filter-order study with the dropped-state impact table holds its systems over the whole
#: grid (its estimate, :func:`order_memory`, also within the memory limit): made once, before the impact's
#: process is forked, and read by both (up to about 85 min of the flagship at 1 s; its 30 min run about 10 %
#: faster than streamed, at 0.71 against 0.54 GB summed over both processes); beyond, every chunk is made where
#: it is read (:meth:`ZuptSetup.stream`, :func:`covtool.lincov.impact.impact_runs`), the truth's in both processes
WHOLE_GRID_BYTES = 1.5 * 2**30


def order_memory(pure: bool, impact: bool | int = True):
    """What a filter-order study holds: the system, every filter and every history (pure INS, truth, filter).

    Parameters
    ----------
    pure : bool
        The study runs the pure INS too.
    impact : bool or int
        The study has a dropped-state impact table: True, of every reduced case; an integer, of that many
        (counted as the largest reduced cases); False or 0, none.

    Returns
    -------
    callable
        ``memory(steps, truth, filters, dynamics, *, records, intervals, shared, distinct, updates, reports,
        max_memory, option_sets) -> dict`` (:func:`setup` passes the keywords): ``filters`` the cases'
        state counts, ``dynamics`` the truth-dynamics stacks (:func:`filter_dynamics`), ``option_sets`` the
        sets of navigation options among the truth and the cases, ``max_memory`` the study's limit [bytes]
        or None.  The dict is :func:`~covtool.studies.resources.memory_estimate`'s with ``layout``.

    The study streams in time (:meth:`ZuptSetup.stream`,
    :func:`~covtool.studies.resources.stream_memory_estimate`), except one
    with the dropped-state impact table (``impact``) whose whole-grid
    systems fit :data:`WHOLE_GRID_BYTES` and the memory limit
    (``max_memory``, :func:`~covtool.studies.resources.memory_limit`): it
    holds them (:func:`~covtool.studies.resources.memory_estimate`), so that
    the truth is discretised once for both of its processes.  The returned
    dict's ``layout`` says which (``"whole grid"`` or ``"streamed"``).

    The histories are navigation blocks (10 × 10) at the record steps
    (``records``: the history spacing and the report times); the truth's
    system composed on the event grid (``intervals``: the records and the
    ZUPTs) is held throughout, one filter's at a time.  The impact table
    works on one chunk of its systems at a time in each of its two
    processes and holds every noise component composed over its event
    grid (``updates`` and ``reports``; :func:`impact_stream_memory`), in
    either layout.
    """

    def memory(steps, truth, filters, dynamics, *, records=None, intervals=None, shared=0, distinct=None,
               updates=None, reports=None, max_memory=None, option_sets=None):
        n = truth.n
        hist = [min(n, 10)] * ((1 if pure else 0) + 2 * len(filters))
        own = sorted(filters)[:len(filters) - shared] if shared else filters
        reduced = sorted((m for m in filters if m < n), reverse=True) if impact else []
        if impact is not True and not isinstance(impact, bool):
            reduced = reduced[:int(impact)]
        K = None if updates is None else int(updates) + int(reports or 0)
        sets = dynamics if option_sets is None else option_sets

        def impact_parts(whole, beside=0.0):
            return impact_stream_memory(steps, truth, reduced, sets, intervals if K is None else K, whole=whole,
                                        beside=beside) if reduced else {}

        if reduced:
            # `shared` filters hold the truth's own F, Q_c, Φ, Q_d (ZuptSetup.filter_system): nothing more; the
            # impact's two processes work on one chunk at a time besides (impact_stream_memory)
            whole = memory_estimate(steps, n, filters=own, dynamics=dynamics, histories=hist,
                                    noise=noise_columns(truth), records=records,
                                    composed=[n] + ([max(filters)] if filters else []), intervals=intervals)
            extra = impact_parts(True)
            whole["parts"].update(extra)
            whole["bytes"] += float(sum(extra.values()))
            # held only where it fits both WHOLE_GRID_BYTES and the memory limit (else the streamed layout may)
            if whole["bytes"] <= min(WHOLE_GRID_BYTES, memory_limit(max_memory)[0]):
                return {**whole, "layout": "whole grid"}
        # streamed in time (ZuptSetup.stream): one chunk of every distinct system (filters that differ
        # only in R_f or the update form share one), the equivalent-noise sources and the histories;
        # a filter of m states drops n - m truth states
        own = own if distinct is None else distinct
        est = stream_memory_estimate(steps, n, filters=own, dropped=[n - m for m in own], dynamics=dynamics,
                                     histories=hist, noise=noise_columns(truth), records=records,
                                     intervals=intervals)
        if reduced:
            est["parts"].update(impact_parts(False, est["parts"]["one chunk of F, Q_c, G, Phi, Q_d"]))
            est["bytes"] = float(sum(est["parts"].values()))
        return {**est, "layout": "streamed"}
    memory.records = True           # setup() passes the record and interval counts
    memory.updates = True           # and the update and report counts (the impact's events)
    memory.limit = True             # and [study] max_memory (the layout must fit the limit)
    return memory


def impact_stream_memory(steps: int, truth: Model, filters, option_sets: int, events=None, *,
                         whole: bool = False, beside: float = 0.0) -> dict:
    """Parts (label -> bytes) of the dropped-state impact table, streamed in time in its two processes.

    Parameters
    ----------
    steps : int
        Propagation steps N.
    truth : Model
        The truth model (its states, blocks and noise columns).
    filters : sequence of int
        States of each filter of the table.
    option_sets : int
        Sets of navigation options among the truth and the filters (a chunk's F, G and transition are built
        once per set, in the process that runs its filters).
    events : int, optional
        ZUPTs and report times (default every step); the chunk boundaries are added.
    whole : bool
        The study holds the truth's and the filters' systems over the whole grid (sliced, not made).
    beside : float
        Bytes of this process's own chunk of the propagation's stream, which its impact share follows
        and does not overlap (streamed layout): its impact chunk counts only beyond it.

    Returns
    -------
    dict
        Per chunk (:data:`~covtool.studies.resources.STREAM_CHUNK` steps): F and G under each set of options
        and its transition (streamed, also its Q_c), each in one process; in each process the gathers of Φ
        and F on a filter's kept states and on (kept ∪ the largest block) and, streamed, the truth's Φ, Q_d,
        F, Q_c and G and the filters' own F_f, Q_c,f, Φ_f, Q_f (the noise check).  In each process, the per-source series workspace
        (:data:`covtool.lincov.noise.COMPOSE_WORKSPACE`).  Over the event grid: the truth's composed system
        and, per filter of ``m`` states, every noise component (one for the kept states and two per dropped
        block on them, ``m²``; one per dropped block on the kept states and the largest block).
    """
    from covtool.lincov.noise import COMPOSE_WORKSPACE
    from covtool.studies.resources import STREAM_CHUNK

    n, N = truth.n, int(steps)
    L = min(STREAM_CHUNK, max(N, 1))
    c = noise_columns(truth)
    K = min(N, (N if events is None else int(events)) + N // STREAM_CHUNK + 2)
    sizes = {}
    for st in truth.states:
        sizes[st.block] = sizes.get(st.block, 0) + 1
    big = max(sizes.values(), default=0)
    blocks = [min(len(sizes), n - m) for m in filters]
    comp = sum((1 + 2 * nb) * m * m + nb * min(n, m + big) ** 2 for m, nb in zip(filters, blocks)) * K
    m = max(filters, default=0)
    u = min(n, m + big)
    sets = max(1, int(option_sets))
    # each set of options is built in the process that runs its filters: once over both processes
    per_set = sets * ((2 * n * n + n * c) + (0 if whole else n * n)) * L
    per_process = 2 * L * (m * m + u * u) + (0 if whole else (4 * n * n + n * c) * L + 4 * L * m * m)
    return {"impact: one chunk of each set of options": per_set * 8,
            "impact: one chunk's gathers in the forked process": per_process * 8,
            "impact: one chunk's gathers in this process (beyond its stream's)":
                max(0.0, per_process * 8 - float(beside)),
            "impact: per-source series workspace (2 processes)": 2 * COMPOSE_WORKSPACE,
            "impact: composed noise components and truth": (comp + 2 * K * n * n) * 8}


def truth_copy(spec: FilterSpec, truth: Model, ftruth: Model | None = None) -> bool:
    """True if filter ``spec`` is the truth itself: all states, the truth's options, an exact discretisation.

    Such a filter's F, Q_c, Φ and Q_d are the truth's arrays
    (:meth:`ZuptSetup.filter_system`); the memory estimate counts them once.
    """
    return (spec.n == truth.n and (ftruth is None or ftruth is truth) and dyn_key(spec.options) == dyn_key(None)
            and (spec.discretization == "van_loan" or spec.taylor_order is None))


def history_records(steps: int, dt: float, every: float | None, report_times, updates: int) -> tuple[int, int]:
    """``(records, intervals)``: upper counts of the record steps and of the event-grid intervals.

    Parameters
    ----------
    steps : int
        Propagation steps N.
    dt, every : float
        Grid step and ``[output] history_every`` (None: every step). [s]
    report_times : sequence of float
        Report times. [s]
    updates : int
        Measurement updates (each one an event).
    """
    rec = steps + 1 if not every else min(steps + 1, int(steps * dt / every) + 2 + len(report_times))
    return rec, min(steps, rec + updates)
