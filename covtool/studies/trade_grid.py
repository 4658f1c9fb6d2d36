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

import copy
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
from covtool.io.config import boolean, check_keys, file_sha256, LIMITS, number, quantity, string, table
from covtool.io.filters import load_filters
from covtool.io.names import check_name
from covtool.lincov.batch import events, run_batch, System
from covtool.lincov.reduced import zupt_matrices
from covtool.plotting.trade_grid import trade_figure
from covtool.results import TradeGridResult
from covtool.studies.grid import check_step_motion, time_grid
from covtool.studies.inputs import (load_trajectory, load_truth, output_options, study_header, study_inputs,
                                    trajectory_csv_sha256)
from covtool.studies.resources import (check_memory, memory_estimate, noise_columns, resource_provenance,
                                       run_in_chunks, steps_of, store_checks)
from covtool.studies.tables import summary_row
from covtool.studies.zupt_setup import filter_cases, filter_dynamics, filters_file, setup, zupt_schedule
from covtool.units import ARCMIN, FT
from covtool.version import __version__


#: truth-model block kinds a grade does not scale (they are not IMU errors)
UNSCALED_KINDS = ("navigation", "gravity_disturbance")

GRID_KEYS = ("zupt_interval", "zupt_sigma", "p0_scale", "q_scale", "r_scale", "cruise_speed")
GRADE_KEYS = ("name", "scale", "description", "override", "arw", "vrw")


# --------------------------------------------------------------------------
# declaration -> plan (validated in the parent, before any work is sent out)
# --------------------------------------------------------------------------

from covtool.studies.config import si_text as _si_text   # one home: the typed configurations' dump


def grade_truth(truth_decl: dict, grade: dict, model) -> dict:
    """``[truth]`` table of one IMU grade.

    Parameters
    ----------
    truth_decl : dict
        The study's ``[truth]`` table.
    grade : dict
        A validated ``[[grade]]`` table (``scale`` a float).
    model : covtool.lincov.model.spec.Model
        The study's truth model (with its own overrides applied).

    Returns
    -------
    dict
        A ``[truth]`` table whose ``override`` sets every scaled sensor
        state explicitly (SI strings that parse back exactly), then the
        grade's own overrides, ``arw`` and ``vrw``.
    """
    from covtool.io.model_file import _RW_DIM

    k = grade["scale"]
    out = copy.deepcopy(truth_decl)
    ov = {nm: dict(v) for nm, v in (out.get("override") or {}).items()}
    if k != 1.0:
        for s in model.states:
            if s.kind in UNSCALED_KINDS:
                continue
            entry = ov.setdefault(s.name, {})
            entry["sigma"] = _si_text(s.sigma * k, s.dimension)
            if s.rw:
                entry["rw"] = _si_text(s.rw * k, _RW_DIM.get(s.dimension, s.dimension))
        out["arw"] = _si_text(model.arw * k, "angle_random_walk")
        out["vrw"] = _si_text(model.vrw * k, "velocity_random_walk")
    for nm, v in (grade.get("override") or {}).items():
        ov.setdefault(nm, {}).update(v)
    if ov:
        out["override"] = ov
    # the designer is assumed to know the grade's IMU (module docstring): filters follow the grade
    out["override_filters"] = True
    for key in ("arw", "vrw"):
        if key in grade:
            out[key] = grade[key]
    return out


def _axis(cfg: dict, key: str, where: str, default, parse):
    vals = cfg.get(key, default)
    w = f"{where}: [grid] {key}"
    if not isinstance(vals, list) or not vals:
        raise StudyFileError(w, "expected a non-empty list")
    lim = LIMITS["grid_axis"]
    if len(vals) > lim.hi:
        raise StudyFileError(w, f"{len(vals)} values; at most {lim.hi:g} ({lim.reason})")
    out = [parse(v, f"{w}[{i}]") for i, v in enumerate(vals)]
    if len(set(out)) != len(out):
        raise StudyFileError(w, f"repeated values in {vals!r}")
    return vals, out


def _scale(v, w):
    b = LIMITS["filter_scale"]
    return number(v, w, StudyFileError, lo=b.lo, hi=b.hi, why=b.reason)


def _grades(decl: dict, where: str) -> list[dict]:
    gs = decl.get("grade", [{"name": "nominal", "scale": 1.0}])
    if not isinstance(gs, list) or not gs:
        raise StudyFileError(f"{where}: [[grade]]", "expected an array of tables ([[grade]] name = ..., scale = ...)")
    lim = LIMITS["grid_axis"]
    if len(gs) > lim.hi:
        raise StudyFileError(f"{where}: [[grade]]", f"{len(gs)} grades; at most {lim.hi:g} ({lim.reason})")
    out, seen = [], set()
    for i, g in enumerate(gs):
        w = f"{where}: [[grade]] #{i + 1}"
        table(g, w, StudyFileError)
        check_keys(g, set(GRADE_KEYS), w, StudyFileError)
        if "name" not in g:
            raise StudyFileError(w, "missing 'name' (a non-empty string)")
        name = check_name(g["name"], f"{w} name", StudyFileError, what="grade name")
        if name in seen:
            raise StudyFileError(f"{w} name", f"grade {name!r} is declared twice")
        seen.add(name)
        ov = g.get("override", {})
        if not isinstance(ov, dict) or not all(isinstance(v, dict) for v in ov.values()):
            raise StudyFileError(f"{w} override", "expected a table of state tables, e.g. "
                                 "override = {gyro_bias_z = {sigma = \"1 deg/h\"}}")
        b = LIMITS["grade_scale"]
        scale = number(g.get("scale", 1.0), f"{w} scale", StudyFileError, lo=b.lo, hi=b.hi, why=b.reason)
        out.append({**g, "scale": scale,
                    "description": string(g.get("description", ""), f"{w} description", StudyFileError)})
    return out


def _lv_default(key):
    """A land-vehicle route parameter's declared default [SI] (covtool.studies.config.LandVehicle)."""
    from covtool.studies.config import LandVehicle

    return getattr(LandVehicle(), key)


def system_decl(decl: dict, grade_truth_decl: dict, interval: str, interval_s: float, cruise_speed: float,
                duration: float, where: str) -> dict:
    """The ``zupt_filter_order``-style declaration of one truth system."""
    sub = {k: copy.deepcopy(v) for k, v in decl.items() if k in ("trajectory", "filters", "zupt", "output")}
    st = decl["study"]
    sub["study"] = {k: st[k] for k in ("name", "description", "duration", "dt", "discretization") if k in st}
    sub["study"]["kind"] = "zupt_filter_order"
    sub["truth"] = grade_truth_decl
    sub.setdefault("filters", {})["pure_ins"] = False
    sub.setdefault("zupt", {})["interval"] = interval
    traj = sub.setdefault("trajectory", {"builtin": "land_vehicle"})
    if traj.get("builtin") == "land_vehicle":
        w = f"{where}: [trajectory]"
        stop = quantity(traj.get("stop_duration", f"{_lv_default('stop_duration')} s"), "time", f"{w} stop_duration",
                        StudyFileError, positive=True)
        acc = quantity(traj.get("accel_duration", f"{_lv_default('accel_duration')} s"), "time",
                       f"{w} accel_duration", StudyFileError, positive=True)
        cycles = max(1, math.ceil(duration / interval_s - 1e-9))
        drive = interval_s - stop - acc
        if drive <= 0:
            raise StudyFileError(f"{where}: [grid] zupt_interval {interval!r}",
                                 f"shorter than the stop ({stop:g} s) plus a speed change ({acc:g} s)")
        traj["period"] = interval
        traj["cycles"] = cycles
        traj["distance"] = f"{cruise_speed * cycles * drive!r} m"
    return sub


class TradePlan:
    """The validated grid: one chunk per truth system, with its cases."""

    def __init__(self, decl: dict, path):
        self.path = Path(path) if path else None
        where = self.where = str(path) if path else "<study>"
        base_dir = self.path.parent if self.path else None
        check_keys(decl, {"study", "trajectory", "truth", "filters", "zupt", "output", "grid", "grade"}, where,
                   StudyFileError)
        self.hdr = study_header(decl, where)
        output_options(decl, where, self.hdr["duration"])
        grid = decl.get("grid")
        if not isinstance(grid, dict):
            raise StudyFileError(where, "missing [grid] table (zupt_interval = [...], ...)")
        check_keys(grid, set(GRID_KEYS), f"{where}: [grid]", StudyFileError)
        zc = decl.get("zupt", {})
        if not isinstance(zc, dict):
            raise StudyFileError(f"{where}: [zupt]", "expected a table")
        if "interval" in zc:
            raise StudyFileError(f"{where}: [zupt] interval", "the ZUPT interval is a grid axis: "
                                 "give it as [grid] zupt_interval = [...]")
        traj = decl.get("trajectory", {"builtin": "land_vehicle"})
        if isinstance(traj, dict) and traj.get("builtin") == "land_vehicle":
            for key in ("period", "cycles", "distance"):
                if key in traj:
                    raise StudyFileError(f"{where}: [trajectory] {key}", "is set per ZUPT interval by the trade "
                                         "grid (period = interval; distance from [grid] cruise_speed)")
        self.interval_text, self.intervals = _axis(
            grid, "zupt_interval", where, None,
            lambda v, w: quantity(v, "time", w, StudyFileError, positive=True))
        nominal_sigma = quantity(zc.get("sigma", "0.01 ft/s"), "velocity", f"{where}: [zupt] sigma",
                                 StudyFileError, positive=True)
        _, self.sigmas = _axis(grid, "zupt_sigma", where, [zc.get("sigma", "0.01 ft/s")],
                               lambda v, w: quantity(v, "velocity", w, StudyFileError, positive=True))
        self.nominal_sigma = nominal_sigma if nominal_sigma in self.sigmas else self.sigmas[0]
        self.p0_scales = _axis(grid, "p0_scale", where, [1.0], _scale)[1]
        self.q_scales = _axis(grid, "q_scale", where, [1.0], _scale)[1]
        self.r_scales = _axis(grid, "r_scale", where, [1.0], _scale)[1]
        self.cruise_speed = quantity(grid.get("cruise_speed", "45 km/h"), "velocity",
                                     f"{where}: [grid] cruise_speed", StudyFileError, positive=True)
        self.grades = _grades(decl, where)

        # truth model, filters, grades: validated here so that workers never fail on input
        truth = load_truth(decl, where, base_dir)
        self.truth_sha256 = truth.sha256
        fcfg = table(decl.get("filters", {}), f"{where}: [filters]", StudyFileError)
        check_keys(fcfg, {"file", "cases", "pure_ins"}, f"{where}: [filters]", StudyFileError)
        if "pure_ins" in fcfg:
            boolean(fcfg["pure_ins"], f"{where}: [filters] pure_ins", StudyFileError)
        self.filter_file = filters_file(fcfg, where, base_dir)
        specs = load_filters(self.filter_file, truth)
        self.filters = filter_cases(fcfg, specs, self.filter_file, where, nonempty=True)
        self.states = {c: specs[c].n for c in self.filters}
        n_cases = len(self.grades) * len(self.intervals) * len(self.filters) * len(self.sigmas) * \
            len(self.p0_scales) * len(self.q_scales) * len(self.r_scales)
        lim = LIMITS["grid_cases"]
        if n_cases > lim.hi:
            raise StudyFileError(f"{where}: [grid]", f"{n_cases:,} cases; at most {lim.hi:,} ({lim.reason}); "
                                 "split the grid into several studies")
        self.n_truth = truth.n
        self.dynamics = filter_dynamics(specs, self.filters)
        self.truth_decl = truth
        self.grade_truth = []
        for g in self.grades:
            td = grade_truth(decl.get("truth", {}), g, truth)
            try:
                load_truth({"truth": td}, where, base_dir)
            except InputError as exc:
                raise StudyFileError(f"{where}: [[grade]] {g['name']!r}", str(exc)) from None
            self.grade_truth.append(td)

        # one trajectory and ZUPT schedule per interval (cheap; the Φ, Q_d are built by the workers)
        t = time_grid(self.hdr["duration"], self.hdr["dt"])
        self.decls = {}
        self.updates = {}
        for ii, (text, s) in enumerate(zip(self.interval_text, self.intervals)):
            sub = system_decl(decl, self.grade_truth[0], text, s, self.cruise_speed, self.hdr["duration"], where)
            try:
                tr = load_trajectory(sub, where, base_dir, self.hdr["dt"])
                if tr.t[-1] < self.hdr["duration"] - 1e-9:
                    raise StudyFileError(f"{where}: [study] duration",
                                         f"{self.hdr['duration']:g} s is longer than the trajectory ({tr.t[-1]:g} s)")
                self.updates[text] = len(zupt_schedule(sub["zupt"], where, t, tr)[0])
            except InputError as exc:
                raise StudyFileError(f"{where}: [grid] zupt_interval = {text!r}", str(exc)) from None
            check_step_motion(tr, t, where)
            for gi, g in enumerate(self.grades):
                self.decls[(gi, ii)] = system_decl(decl, self.grade_truth[gi], text, s, self.cruise_speed,
                                                   self.hdr["duration"], where)

        # cases, in the order grade, interval, filter, zupt_sigma, p0, q, r
        self.chunks = []
        n = 0
        for gi, g in enumerate(self.grades):
            for ii, s in enumerate(self.intervals):
                cases = []
                for f, sig, p0, q, r in itertools.product(self.filters, self.sigmas, self.p0_scales, self.q_scales,
                                                          self.r_scales):
                    cases.append({"case": n, "grade": g["name"], "grade scale": g["scale"],
                                  "ZUPT interval [min]": s / 60.0, "filter": f, "states": self.states[f],
                                  "ZUPT sigma [ft/s]": float(f"{sig / FT:.12g}"), "P0 scale": p0,
                                  "Q scale": q, "R scale": r,
                                  "_sigma": sig})
                    n += 1
                self.chunks.append({"key": f"g{gi:02d}-i{ii:02d}", "decl": self.decls[(gi, ii)],
                                    "path": str(self.path) if self.path else None, "cases": cases})
        self.n_cases = n

    def memory(self, workers: int) -> dict:
        """Peak memory of the grid: one (grade, interval) system per worker at a time.

        A chunk builds the truth and every filter system on the full grid
        and runs each filter's cases in one batch (per case the truth and
        filter covariances and the gains of every update).
        """
        steps = steps_of(self.hdr["duration"], self.hdr["dt"])
        n = self.n_truth
        per = len(self.sigmas) * len(self.p0_scales) * len(self.q_scales) * len(self.r_scales)
        nf = max(self.states.values())
        updates = max(self.updates.values(), default=0)
        extra = per * (6 * n * n + 6 * nf * nf + 3 * updates * nf) * 8
        return memory_estimate(steps, n, filters=list(self.states.values()), dynamics=self.dynamics,
                               noise=noise_columns(self.truth_decl),
                               extra=extra, parallel=max(1, min(workers, len(self.chunks))))

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
        ``decl`` (the system's ``zupt_filter_order`` declaration), ``path``
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
    S = setup(task["decl"], path=path)
    t = S.t
    rec = sorted({int(np.argmin(np.abs(t - tr))) for tr in S.report_times})
    ev = events(t.size - 1, S.update_steps, rec)
    truth = System.from_steps(S.Phi, S.Qd, ev)
    nodes = S.nodes
    t_setup = time.perf_counter() - t0
    t_filters = t_engine = 0.0
    by_filter: dict = {}
    for c in task["cases"]:
        by_filter.setdefault(c["filter"], []).append(c)
    rows, reused = {}, []
    eye = np.eye(S.H.shape[0])
    for f, cs in by_filter.items():
        a = time.perf_counter()
        fm, Phi_f, Qd_f, same = S.filter_system(f)
        spec = S.specs[f]
        filt = truth if same else System.from_steps(Phi_f, Qd_f, ev)
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
        resume: bool = False) -> TradeGridResult:
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
    """
    t_start = time.perf_counter()
    plan = TradePlan(decl, path)
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
    tables = {"summary": summary, **pivot_tables(summary, plan), "grades": _grade_table(plan),
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
        filters=list(plan.filters), duration=plan.hdr["duration"])
    result.figures = {"trade_grid": partial(trade_figure, result)}
    return result


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


def pivot_tables(summary: pd.DataFrame, plan: TradePlan) -> dict:
    """Pivot tables (grade × interval by filter) and tuning spread.

    The pivots hold the nominal cases; ``tuning_spread`` gives each
    filter's CEP range over every ZUPT σ and tuning of the grid.
    """
    nom = nominal(summary, plan)
    out = {}
    for name, col in (("pivot_cep", "CEP [ft]"), ("pivot_alt_pe", "alt PE [ft]"),
                      ("pivot_azimuth", "azimuth 1sigma [arcmin]")):
        pv = nom.pivot_table(index=["grade", "ZUPT interval [min]"], columns="filter", values=col, sort=False)
        pv = pv[plan.filters]
        pv.columns = [f"{f} {col}" for f in pv.columns]
        out[name] = pv.reset_index()
    last = summary[summary["t [min]"] == summary["t [min]"].max()]
    g = last.groupby(["grade", "ZUPT interval [min]", "filter"], sort=False)["CEP [ft]"]
    spread = pd.DataFrame({"CEP min [ft]": g.min(), "CEP max [ft]": g.max()})
    spread = spread.join(nom.set_index(["grade", "ZUPT interval [min]", "filter"])["CEP [ft]"].rename(
        "CEP nominal [ft]"))
    spread["max/min [x]"] = spread["CEP max [ft]"] / spread["CEP min [ft]"]
    out["tuning_spread"] = spread.reset_index()
    return out


def _grade_table(plan: TradePlan) -> pd.DataFrame:
    return pd.DataFrame([{"grade": g["name"], "scale": g["scale"], "description": g["description"],
                          "explicit overrides": ", ".join(sorted(g.get("override", {}))),
                          "arw": g.get("arw", ""), "vrw": g.get("vrw", "")} for g in plan.grades])


def _grid_table(plan: TradePlan) -> pd.DataFrame:
    axes = [("grade", [g["name"] for g in plan.grades]), ("ZUPT interval", plan.interval_text),
            ("filter", plan.filters), ("ZUPT sigma [ft/s]", [f"{s / FT:g}" for s in plan.sigmas]),
            ("P0 scale", plan.p0_scales), ("Q scale", plan.q_scales), ("R scale", plan.r_scales)]
    rows = [{"axis": a, "values": ", ".join(map(str, v)), "count": len(v)} for a, v in axes]
    rows.append({"axis": "cases", "values": "product of the above", "count": plan.n_cases})
    return pd.DataFrame(rows)
