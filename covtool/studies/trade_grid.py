"""Trade grid: ZUPT interval × filter × IMU grade × tuning.

Seed 002 §3-4 (issue 4).  Thousands of truth-under-filter cases, grouped
so that the cases sharing a truth system and a filter run in one batched
engine call (:func:`covtool.lincov.batch.run_batch`), chunked over an execution
backend (:mod:`covtool.parallel`) and stored incrementally, so that an
interrupted grid resumes where it stopped.

Study file::

    [study]
    kind = "trade_grid"
    duration = "30 min"
    dt = "1 s"

    [trajectory]                 # builtin land_vehicle: period, cycles and
    builtin = "land_vehicle"     # distance are set per ZUPT interval
    stop_duration = "60 s"

    [truth]
    model = "sdins58"

    [filters]
    cases = ["A", "B1", "B2", "B3", "C", "D"]

    [zupt]                       # as zupt_filter_order, without 'interval'
    duration = "30 s"
    rate = "1 Hz"
    sigma = "0.01 ft/s"          # nominal ZUPT σ (the pivot tables' column)

    [grid]
    zupt_interval = ["3 min", "5 min", "10 min"]
    zupt_sigma = ["0.003 ft/s", "0.01 ft/s"]   # true ZUPT σ, assumed alike by the filter
    q_scale = [0.3, 1, 3]        # filter Q_f × (also p0_scale, r_scale)
    cruise_speed = "45 km/h"     # land_vehicle: same cruise speed for every interval

    [[grade]]
    name = "navigation"
    scale = 1                    # × every sensor σ, random walk, ARW and VRW

    [[grade]]
    name = "tactical"
    scale = 30
    override = {gyro_bias_z = {sigma = "1 deg/h"}}   # then explicit changes

Cases are the product grade × interval × filter × zupt_sigma × p0_scale ×
q_scale × r_scale.  One *chunk* is one (grade, interval) truth system with
all its cases: building the system (Φ, Q_d of the truth and of every filter)
costs more than propagating all its cases, so a chunk is never split.

IMU grade
---------
A grade scales the 1σ, random-walk intensities and ARW/VRW of every sensor
state of the truth model (every block except ``navigation`` and
``gravity_disturbance``) by ``scale``; ``override``, ``arw`` and ``vrw``
then set values explicitly, as ``[truth.override]`` does.  Each filter is
built from the graded truth, so its P0 and equivalent noise (eq (11)-(13))
follow the grade: the designer is assumed to know the IMU.  Initial
navigation errors are not scaled (override them per grade if the alignment
differs).
"""

from __future__ import annotations

import itertools
import math
import os
from pathlib import Path
import time
from functools import partial
import warnings

import numpy as np
import pandas as pd

from covtool.analysis.metrics import first_invalid, nav_metrics
from covtool.errors import FlaggedCaseWarning, InputError, StudyFileError, ValidityWarning
from covtool.io.config import file_sha256, LIMITS
from covtool.io.filters import load_filters
from covtool.lincov.batch import events, run_batch
from covtool.lincov.reduced import zupt_matrices
from covtool.plotting.trade_grid import trade_figure
from covtool.results import TradeGridResult
from covtool.studies.grid import check_step_motion, time_grid
from covtool.studies.inputs import (load_trajectory, load_truth, output_options, study_config, study_header,
                                    study_inputs, trajectory_csv_sha256)
from covtool.studies.resources import (check_memory, composed_memory_estimate, noise_columns,
                                       resource_provenance, run_in_chunks, scaled_estimate, steps_of, store_checks)
from covtool.studies.tables import summary_row
from covtool.studies.zupt_setup import filter_cases, filter_dynamics, filters_file, setup, zupt_schedule
from covtool.units import ARCMIN, FT
from covtool.version import __version__




# --------------------------------------------------------------------------
# declaration -> plan (validated in the parent, before any work is sent out)
# --------------------------------------------------------------------------

def system_config(cfg, interval_s: float, cruise_speed: float, duration: float, where: str, shown: str):
    """The ``zupt_filter_order`` configuration of one truth system (one ZUPT interval).

    Varied from the trade grid's configuration by ``model_copy``, in SI:
    ``[zupt] interval`` is the grid's interval, ``[filters] pure_ins`` is
    off, and a ``land_vehicle`` route gets ``period`` = interval, the
    cycles that cover the study and the distance that gives ``[grid]
    cruise_speed`` (its other parameters as declared, with their declared
    defaults).

    Raises
    ------
    StudyFileError
        An interval not longer than the stop plus a speed change.
    """
    from covtool.studies.config import LandVehicle, ZuptFilterOrderConfig

    traj = cfg.trajectory
    if isinstance(traj, LandVehicle):
        stop, acc = traj.stop_duration, traj.accel_duration
        cycles = max(1, math.ceil(duration / interval_s - 1e-9))
        drive = interval_s - stop - acc
        if drive <= 0:
            raise StudyFileError(f"{where}: [grid] zupt_interval {shown!r}",
                                 f"shorter than the stop ({stop:g} s) plus a speed change ({acc:g} s)")
        traj = traj.model_copy(update={"period": interval_s, "cycles": cycles,
                                       "distance": cruise_speed * cycles * drive})
    return ZuptFilterOrderConfig(
        study=cfg.study.model_copy(update={"kind": "zupt_filter_order", "max_memory": None}),
        trajectory=traj, truth=cfg.truth, filters=cfg.filters.model_copy(update={"pure_ins": False}),
        zupt=cfg.zupt.model_copy(update={"interval": interval_s}), output=cfg.output)


class TradePlan:
    """The validated grid: one chunk per truth system, with its cases."""

    def __init__(self, decl, path, config=None):
        self.path = Path(path) if path else None
        where = self.where = str(path) if path else "<study>"
        base_dir = self.path.parent if self.path else None
        # parsed once (or given by run_study); every chunk's configuration is varied from it
        cfg = self.config = config if config is not None else study_config(decl, where)
        self.hdr = study_header(cfg, where)
        self.report_times = output_options(cfg, where, self.hdr["duration"])[1]
        raw_grid = decl.get("grid", {}) if isinstance(decl, dict) else {}
        self.intervals = list(cfg.grid.zupt_interval)
        self.interval_text = list(raw_grid.get("zupt_interval") or [f"{s / 60:g} min" for s in self.intervals])
        self.sigmas = list(cfg.grid.zupt_sigma or (cfg.zupt.sigma,))
        self.nominal_sigma = cfg.zupt.sigma if cfg.zupt.sigma in self.sigmas else self.sigmas[0]
        self.p0_scales, self.q_scales, self.r_scales = (list(cfg.grid.p0_scale), list(cfg.grid.q_scale),
                                                        list(cfg.grid.r_scale))
        self.cruise_speed = cfg.grid.cruise_speed
        self.grade_entries = cfg.grade
        self.grades = [{"name": g.name_, "scale": g.scale, "description": g.description, "override": g.override,
                        **{k: v for k, v in (("arw", g.arw), ("vrw", g.vrw)) if v is not None}} for g in cfg.grade]
        # the aiding mix axis (issue 15): measurements added to the ZUPTs; absent, the grid is ZUPT-only as before
        from covtool.studies.aided_trade import aiding_problem, parse_aiding
        self.aiding_axis = "aiding" in raw_grid
        if not self.aiding_axis and isinstance(decl, dict) and "aiding" in decl:
            raise StudyFileError(f"{where}: [[aiding]]", "declared but not used: list it in [grid] aiding")
        self.aidings = parse_aiding(decl, raw_grid["aiding"], where) if self.aiding_axis else [{"name": None,
                                                                                                 "measurement": []}]

        # truth model, filters, grades: validated here so that workers never fail on input
        truth = load_truth(cfg, where, base_dir)
        self.truth_sha256 = truth.sha256
        self.filter_file = filters_file(cfg.filters, where, base_dir)
        specs = load_filters(self.filter_file, truth)
        self.filters = filter_cases(cfg.filters, specs, self.filter_file, where, nonempty=True)
        self.states = {c: specs[c].n for c in self.filters}
        n_cases = len(self.grades) * len(self.intervals) * len(self.filters) * len(self.sigmas) * \
            len(self.p0_scales) * len(self.q_scales) * len(self.r_scales) * len(self.aidings)
        lim = LIMITS["grid_cases"]
        if n_cases > lim.hi:
            raise StudyFileError(f"{where}: [grid]", f"{n_cases:,} cases; at most {lim.hi:,} ({lim.reason}); "
                                 "split the grid into several studies")
        self.n_truth = truth.n
        self.dynamics = filter_dynamics(specs, self.filters)
        self.truth_decl = truth
        for g in self.grade_entries:
            load_truth(cfg, where, base_dir, grade=g)

        # one trajectory and ZUPT schedule per interval (cheap; the Φ, Q_d are built by the workers)
        t = time_grid(self.hdr["duration"], self.hdr["dt"])
        self.configs = {}
        self.updates = {}
        for ii, (text, s) in enumerate(zip(self.interval_text, self.intervals)):
            sub = system_config(cfg, s, self.cruise_speed, self.hdr["duration"], where, text)
            try:
                tr = load_trajectory(sub, where, base_dir, self.hdr["dt"])
                if tr.t[-1] < self.hdr["duration"] - 1e-9:
                    raise StudyFileError(f"{where}: [study] duration",
                                         f"{self.hdr['duration']:g} s is longer than the trajectory ({tr.t[-1]:g} s)")
                self.updates[text] = len(zupt_schedule(sub.zupt, where, t, tr)[0])
            except InputError as exc:
                raise StudyFileError(f"{where}: [grid] zupt_interval = {text!r}", str(exc)) from None
            check_step_motion(tr, t, where)
            for a in self.aidings:
                if a["measurement"]:
                    aiding_problem(a, t, tr.sample(t), f"{where}: [grid] zupt_interval = {text!r}")
            self.configs[ii] = sub

        # cases, in the order grade, interval, filter, zupt_sigma, p0, q, r
        self.chunks = []
        n = 0
        for gi, g in enumerate(self.grades):
            for ii, s in enumerate(self.intervals):
                for ai, aid in enumerate(self.aidings):
                    cases = []
                    for f, sig, p0, q, r in itertools.product(self.filters, self.sigmas, self.p0_scales,
                                                              self.q_scales, self.r_scales):
                        cases.append({"case": n, "grade": g["name"], "grade scale": g["scale"],
                                      "ZUPT interval [min]": s / 60.0,
                                      **({"aiding": aid["name"]} if self.aiding_axis else {}),
                                      "filter": f, "states": self.states[f],
                                      "ZUPT sigma [ft/s]": float(f"{sig / FT:.12g}"), "P0 scale": p0,
                                      "Q scale": q, "R scale": r,
                                      "_sigma": sig})
                        n += 1
                    # the store key names the aiding mix: a resumed grid never mixes two mixes' chunks
                    self.chunks.append({"key": f"g{gi:02d}-i{ii:02d}" + (f"-a{ai:02d}" if self.aiding_axis else ""),
                                        "config": self.configs[ii], "grade": self.grade_entries[gi], "aiding": aid,
                                        "path": str(self.path) if self.path else None, "cases": cases})
        self.n_cases = n

    def memory(self, workers: int) -> dict:
        """Peak memory of the grid: one (grade, interval) system per worker at a time.

        A ZUPT-only chunk makes the truth's and each filter's systems chunk
        by chunk in time, composed on the events
        (:func:`~covtool.studies.resources.composed_memory_estimate`), and
        runs a filter's cases in one batch (per case the truth and filter
        covariances and the gains of every update).  A chunk with an aiding
        mix streams too (:meth:`~covtool.studies.zupt_setup.ZuptSetup.streamed_system`):
        on top of one chunk of every system it holds the chunks its pool
        keeps (at most :data:`~covtool.studies.resources.HELD_CHUNKS`), the
        mix's measurement Jacobians, one run's epochs, the aided guard's
        block and the measurement-error processes (:meth:`_aided_memory`).
        """
        steps = steps_of(self.hdr["duration"], self.hdr["dt"])
        n = self.n_truth
        per = len(self.sigmas) * len(self.p0_scales) * len(self.q_scales) * len(self.r_scales)
        updates = max(self.updates.values(), default=0)
        parallel = max(1, min(workers, len(self.chunks)))
        streamed = composed_memory_estimate(steps, n, filters=list(self.states.values()), dynamics=self.dynamics,
                                            noise=noise_columns(self.truth_decl), updates=updates,
                                            reports=len(self.report_times), batch=per)
        if any(a["measurement"] for a in self.aidings):
            parts = streamed["parts"]
            parts.update(max((self._aided_memory(a, steps, updates) for a in self.aidings if a["measurement"]),
                             key=lambda d: sum(d.values())))
            streamed["bytes"] = float(sum(parts.values()))
        return scaled_estimate(streamed, parallel)

    def _aided_memory(self, aiding: dict, steps: int, zupt_updates: int) -> dict:
        """What one worker holds for an aiding mix beyond the ZUPT-only chunk's parts (bytes per part).

        :func:`covtool.studies.aided.aided_run_memory` for the truth and
        every filter streamed, the mix's measurements and the ZUPTs (as
        scheduled); the cases run one at a time and record the navigation
        block at the report times only (their priors and gains there too).
        """
        from covtool.studies.aided import aided_run_memory, parse_measurement, update_rows

        plan = [parse_measurement(m, i, f"{self.where}: [[aiding]] {aiding['name']!r}")
                for i, m in enumerate(aiding["measurement"])]
        nfs = list(self.states.values())
        rows = [(3, zupt_updates)] + update_rows(plan, steps, self.hdr["duration"])
        parts = aided_run_memory(steps, self.n_truth, nfs, max(nfs), sum(len(m.states) for m, _ in plan), rows)
        return {f"{k} (aiding mix)": v for k, v in parts.items()}

    def manifest(self, decl: dict) -> dict:
        """What identifies this sweep for a resumed run (its fingerprint is the plan key).

        The study declaration, the truth model, the filter file and a
        trajectory CSV (by SHA-256), the covtool version and the chunk plan.
        """
        return {"kind": "trade_grid", "covtool_version": __version__, "study": decl,
                "truth_model_sha256": self.truth_sha256,
                "filter_file_sha256": [file_sha256(p) for p in self.filter_file],
                "trajectory_csv_sha256": trajectory_csv_sha256(decl, self.path.parent if self.path else None),
                "chunks": [c["key"] for c in self.chunks], "cases": self.n_cases}



# --------------------------------------------------------------------------
# one chunk: one truth system, all its cases (runs in a worker)
# --------------------------------------------------------------------------

def compute_chunk(task: dict) -> dict:
    """Every case of one (grade, interval) truth system.

    Parameters
    ----------
    task : dict
        ``config`` (the system's ``zupt_filter_order`` configuration),
        ``grade`` (its IMU grade, applied to the truth), ``path``
        (the study file, for relative paths) and ``cases`` (dicts with
        ``case``, ``filter``, ``_sigma`` [m/s], ``P0 scale``, ``Q scale``,
        ``R scale``).

    Returns
    -------
    dict
        ``rows``: one summary row per case and report time (Table 3
        columns, truth and filter-claimed, ``validity`` and ``status``: a
        case whose covariance fails the guard is flagged there and its
        numbers are NaN, the others go on); ``reused_truth_phi``: the
        filters that share the truth's Φ, Q_d (:func:`filter_system`);
        ``timing``: seconds spent.
    """
    t0 = time.perf_counter()
    path = Path(task["path"]) if task.get("path") else None
    S = setup(task["config"], path=path, grade=task["grade"])
    t = S.t
    rec = sorted({int(np.argmin(np.abs(t - tr))) for tr in S.report_times})
    aiding = task.get("aiding") or {"measurement": []}
    # ZUPTs only: the truth's and the filters' Φ, Q_d are made chunk by chunk in time and composed on the
    # events (ZuptSetup.composed_truth, composed_filter), none of size N x n^2; an aiding mix reads them
    # step by step, made chunk by chunk too (ZuptSetup.streamed_system, covtool.studies.aided_trade)
    ev = S.stream_grid(events(t.size - 1, S.update_steps, rec))
    truth = None if aiding["measurement"] else S.composed_truth(ev)
    nodes = S.nodes
    t_setup = time.perf_counter() - t0
    t_filters = t_engine = 0.0
    by_filter: dict = {}
    for c in task["cases"]:
        by_filter.setdefault(c["filter"], []).append(c)
    rows, reused = {}, []
    # the ZUPT-only filters' systems together, chunk by chunk (one truth dynamics per chunk and options)
    systems = S.composed_filters(list(by_filter), ev, truth=truth) if truth is not None else {}
    eye = np.eye(S.H.shape[0])
    for f, cs in by_filter.items():
        a = time.perf_counter()
        if aiding["measurement"]:          # ZUPTs plus an aiding mix: the aided engine, one run per case
            _aided_rows(S, f, cs, aiding, rec, task, rows)
            t_engine += time.perf_counter() - a
            continue
        fm, filt, same = systems[f]
        spec = S.specs[f]
        if same:
            reused.append(f)
        b = time.perf_counter()
        sig = np.array([c["_sigma"] for c in cs])
        fsig = sig if spec.zupt_sigma is None else np.full_like(sig, spec.zupt_sigma)
        p0 = np.array([c["P0 scale"] for c in cs])
        q = np.array([c["Q scale"] for c in cs])
        r = np.array([c["R scale"] for c in cs])
        res = run_batch(truth, S.P0, S.H, sig[:, None, None] ** 2 * eye, fm.D, S.update_steps, rec, filt=filt,
                        Pf0=p0[:, None, None] * fm.P0, Hf=zupt_matrices(fm.names),
                        Rf=(r * fsig**2)[:, None, None] * eye, q_scale=q, form=spec.update, on_invalid="flag",
                        label=f"trade grid: {task.get('key', 'chunk')}: filter {f}",
                        cases=[str(c["case"]) for c in cs], names=S.truth.names, filter_names=fm.names, times=t)
        B, nr = len(cs), len(rec)
        tile = lambda x: np.tile(x[rec], (B,) + (1,) * (x.ndim - 1))  # noqa: E731
        geo = (tile(nodes.lat), tile(nodes.h), tile(nodes.q_nb), tile(nodes.distance))
        mt = nav_metrics(res.P_truth.reshape(B * nr, 10, 10), *geo)
        mc = nav_metrics(res.P_filter.reshape(B * nr, 10, 10), *geo)
        for i, c in enumerate(cs):
            first = first_invalid({key: v[i * nr:(i + 1) * nr] for key, v in mt.items()}, t[rec])
            for j, k in enumerate(rec):
                x = i * nr + j
                row = {key: v for key, v in c.items() if not key.startswith("_")}
                m = summary_row("", mt, x, float(t[k]), float(nodes.distance[k]), first=first,
                                status=res.status[i])
                del m["case"]
                row.update(m)
                row["filter-claimed CEP [ft]"] = mc["cep"][x] / FT
                row["filter-claimed alt PE [ft]"] = mc["alt_pe"][x] / FT
                row["filter-claimed azimuth [arcmin]"] = mc["sigma_azimuth"][x] / ARCMIN
                rows[(c["case"], j)] = {k2: (float(v) if isinstance(v, (np.floating, np.integer)) else v)
                                        for k2, v in row.items()}
        t_filters += b - a
        t_engine += time.perf_counter() - b
    ordered = [rows[key] for key in sorted(rows)]
    return {"rows": ordered, "reused_truth_phi": reused,
            "timing": {"setup": t_setup, "filters": t_filters, "engine": t_engine, "total": time.perf_counter() - t0}}


# --------------------------------------------------------------------------
# the study
# --------------------------------------------------------------------------

def run(decl: dict, *, path=None, progress: bool = False, backend=None, store=None,
        resume: bool = False, config=None) -> TradeGridResult:
    """Run a trade grid; see the module docstring.

    Parameters
    ----------
    decl : dict
        The study declaration.
    path : Path, optional
        The study file (relative paths and messages).
    progress : bool
        Show a progress bar of cases done and the time left.
    backend : backend or str, optional
        :mod:`covtool.parallel` backend (default in-process), or one of
        ``"serial"``, ``"processes"``, ``"dask"``.
    store : path, optional
        Directory of the incremental result store (one file per finished
        chunk).  Without it results are kept in memory only.
    resume : bool
        Reuse the chunks already in ``store`` (an interrupted run).
    config : TradeGridConfig, optional
        ``decl`` parsed (by :func:`covtool.run_study`); parsed here if not given.
    """
    t_start = time.perf_counter()
    plan = TradePlan(decl, path, config)
    est = check_memory(plan.memory(_local_workers(backend)), plan.where, plan.hdr["max_memory"],
                       "a larger [study] dt, a shorter duration, fewer [grid] values per interval or fewer "
                       "--workers")
    results, stats, rs = run_in_chunks(
        compute_chunk, plan.chunks, [c["key"] for c in plan.chunks], [[k["case"] for k in c["cases"]] for c in plan.chunks],
        backend=backend, store=store, manifest=lambda: plan.manifest(decl), resume=resume, progress=progress,
        desc="trade grid")
    elapsed = time.perf_counter() - t_start
    summary = pd.DataFrame([row for res in results for row in res["rows"]])
    _warn(summary)
    unit = plan.config.output.units
    tables = {"summary": summary, **pivot_tables(summary, plan, unit), "grades": _grade_table(plan),
              "grid": _grid_table(plan)}
    timing = pd.DataFrame([{"chunk": c["key"], **res["timing"]} for c, res in zip(plan.chunks, results)])
    provenance = {**study_inputs(path, decl, plan.truth_decl, plan.filter_file), **resource_provenance(est),
                  "truth_model_sha256": plan.truth_sha256,
                  "cases": plan.n_cases, "chunks": len(plan.chunks), "backend": stats["backend"],
                  "chunks_computed": stats["computed"], "chunks_reused": stats["reused"],
                  "compute_seconds": f"{elapsed:.2f}",
                  "chunk_seconds_total": f"{timing['total'].sum():.2f}",
                  "filters_reusing_truth_phi_qd": ", ".join(sorted({f for r in results
                                                                   for f in r.get("reused_truth_phi", [])})) or "none",
                  "result_store": str(store) if store is not None else "",
                  "result_store_checks": store_checks(rs, stats)}
    result = TradeGridResult(
        name=plan.hdr["name"], kind="trade_grid", tables=tables,
        resolved={**decl, "study": {**decl["study"], "name": plan.hdr["name"]}}, provenance=provenance,
        nominal=nominal(summary, plan), grades=[{"name": g["name"], "scale": g["scale"]} for g in plan.grades],
        filters=list(plan.filters), duration=plan.hdr["duration"], length_unit=unit)
    result.figures = {"trade_grid": partial(trade_figure, result)}
    if plan.aiding_axis:                   # one figure per aiding mix (the figure's lines run over the intervals)
        import dataclasses
        nom = result.nominal
        result.figures = {f"trade_grid_{a['name']}": partial(trade_figure, dataclasses.replace(
            result, nominal=nom[nom["aiding"] == a["name"]])) for a in plan.aidings}
    return result


def _aided_rows(S, f, cs, aiding, rec, task, rows) -> None:
    """Summary rows of one filter's cases with an aiding mix (:func:`covtool.studies.aided_trade.trade_cases`)."""
    from covtool.studies.aided_trade import trade_cases

    t, nodes = S.t, S.nodes
    res = trade_cases(S, f, cs, aiding, rec, f"trade grid: {task.get('key', 'chunk')}: filter {f}")
    geo = (nodes.lat[rec], nodes.h[rec], nodes.q_nb[rec], nodes.distance[rec])
    for c, (PT, PF, status) in zip(cs, res):
        mt, mc = nav_metrics(PT, *geo), nav_metrics(PF, *geo)
        first = first_invalid(mt, t[rec])
        for j, k in enumerate(rec):
            row = {key: v for key, v in c.items() if not key.startswith("_")}
            m = summary_row("", mt, j, float(t[k]), float(nodes.distance[k]), first=first, status=status)
            del m["case"]
            row.update(m)
            row["filter-claimed CEP [ft]"] = mc["cep"][j] / FT
            row["filter-claimed alt PE [ft]"] = mc["alt_pe"][j] / FT
            row["filter-claimed azimuth [arcmin]"] = mc["sigma_azimuth"][j] / ARCMIN
            rows[(c["case"], j)] = {k2: (float(v) if isinstance(v, (np.floating, np.integer)) else v)
                                    for k2, v in row.items()}


def _local_workers(backend) -> int:
    """Worker processes on this machine that each hold one chunk (a remote Dask cluster: none here)."""
    if backend is None or backend == "serial":
        return 1
    if isinstance(backend, str):
        return os.cpu_count() or 1
    if hasattr(backend, "client") and getattr(backend, "_cluster", None) is None:
        return 1
    return int(getattr(backend, "workers", 1) or 1)



def _warn(summary: pd.DataFrame) -> None:
    """One warning for the flagged cases and one for those outside the linear model's domain.

    Built from the rows (chunks may have run in other processes).
    """
    if not len(summary):
        return
    last = summary[summary["t [min]"] == summary["t [min]"].max()]
    if "status" in last:
        bad = last[last["status"].fillna("ok") != "ok"]
        if len(bad):
            warnings.warn(f"{len(bad)} of {len(last)} trade-grid cases failed the covariance guard; their numbers "
                          f"are NaN (status column); first: case {bad['case'].iloc[0]}: {bad['status'].iloc[0]}",
                          FlaggedCaseWarning, stacklevel=3)
    if "validity" in last:
        out = last[~last["validity"].fillna("ok").isin(["ok", ""])]
        if len(out):
            warnings.warn(f"{len(out)} of {len(last)} trade-grid cases are outside the linear error model's domain "
                          f"(validity column); first: case {out['case'].iloc[0]}: {out['validity'].iloc[0]}",
                          ValidityWarning, stacklevel=3)


def nominal(summary: pd.DataFrame, plan: TradePlan) -> pd.DataFrame:
    """Rows of the nominal tuning and ZUPT σ at the last report time.

    Nominal: P0, Q and R scale 1 (or the grid value nearest 1) and the
    ``[zupt] sigma`` (or the first grid value).
    """
    sel = summary["t [min]"] == summary["t [min]"].max()
    for col, vals in (("P0 scale", plan.p0_scales), ("Q scale", plan.q_scales), ("R scale", plan.r_scales)):
        v = 1.0 if 1.0 in vals else min(vals, key=lambda x: abs(math.log(x)))
        sel &= summary[col] == v
    sel &= np.isclose(summary["ZUPT sigma [ft/s]"], plan.nominal_sigma / FT, rtol=1e-9)
    return summary[sel]


def pivot_tables(summary: pd.DataFrame, plan: TradePlan, unit: str = "ft") -> dict:
    """Pivot tables (grade × interval by filter) and tuning spread.

    The pivots hold the nominal cases; ``tuning_spread`` gives each
    filter's CEP range over every ZUPT σ and tuning of the grid.  Lengths
    in ``unit`` (``[output] units``: ``"ft"`` or ``"m"``; the summary
    keeps both).
    """
    nom = nominal(summary, plan)
    out = {}
    cep = f"CEP [{unit}]"
    for name, col in (("pivot_cep", cep), ("pivot_alt_pe", f"alt PE [{unit}]"),
                      ("pivot_azimuth", "azimuth 1sigma [arcmin]")):
        pv = nom.pivot_table(index=_pivot_index(plan), columns="filter", values=col, sort=False)
        pv = pv[plan.filters]
        pv.columns = [f"{f} {col}" for f in pv.columns]
        out[name] = pv.reset_index()
    last = summary[summary["t [min]"] == summary["t [min]"].max()]
    g = last.groupby(_pivot_index(plan) + ["filter"], sort=False)[cep]
    spread = pd.DataFrame({f"CEP min [{unit}]": g.min(), f"CEP max [{unit}]": g.max()})
    spread = spread.join(nom.set_index(_pivot_index(plan) + ["filter"])[cep].rename(
        f"CEP nominal [{unit}]"))
    spread["max/min [x]"] = spread[f"CEP max [{unit}]"] / spread[f"CEP min [{unit}]"]
    out["tuning_spread"] = spread.reset_index()
    return out


def _pivot_index(plan: TradePlan) -> list:
    return ["grade", "ZUPT interval [min]"] + (["aiding"] if getattr(plan, "aiding_axis", False) else [])


def _grade_table(plan: TradePlan) -> pd.DataFrame:
    return pd.DataFrame([{"grade": g["name"], "scale": g["scale"], "description": g["description"],
                          "explicit overrides": ", ".join(sorted(g.get("override", {}))),
                          "arw": g.get("arw", ""), "vrw": g.get("vrw", "")} for g in plan.grades])


def _grid_table(plan: TradePlan) -> pd.DataFrame:
    axes = [("grade", [g["name"] for g in plan.grades]), ("ZUPT interval", plan.interval_text),
            ("filter", plan.filters), ("ZUPT sigma [ft/s]", [f"{s / FT:g}" for s in plan.sigmas]),
            ("P0 scale", plan.p0_scales), ("Q scale", plan.q_scales), ("R scale", plan.r_scales)]
    if plan.aiding_axis:
        axes.insert(2, ("aiding", [a["name"] for a in plan.aidings]))
    rows = [{"axis": a, "values": ", ".join(map(str, v)), "count": len(v)} for a, v in axes]
    rows.append({"axis": "cases", "values": "product of the above", "count": plan.n_cases})
    return pd.DataFrame(rows)
