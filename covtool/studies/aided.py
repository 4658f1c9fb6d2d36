"""Aided-navigation study: reduced filters against the truth with declared measurements (issue 15).

The truth model (plus every measurement's own error states) runs under the
gains of each filter (seed 002, eq (15)–(16)) with the declared measurements
(:mod:`covtool.lincov.measurements`) on their schedules
(:class:`covtool.lincov.measurements.Schedule`); filter variants drop
measurement-error states by name, and the cost is tabulated.

Study file::

    [study]
    kind = "aided"
    duration = "2 h"
    dt = "1 s"

    [trajectory]
    builtin = "land_vehicle"

    [truth]
    model = "sdins58"

    [filters]
    file = "../models/filters/zupt_filters.toml"   # default: the library's
    cases = ["A", "B1", "C"]
    pure_ins = true
    ewn_interval = "5 min"    # Δt_s of eq (11)-(13) for dropped INS states (default: duration / epochs)

    [[filters.variant]]       # a filter that drops measurement-error states
    name = "B1 no odo SF"
    base = "B1"
    drop = ["odo_scale_factor"]

    [[measurement]]
    name = "odo"
    kind = "odometer"         # zupt, cupt, odometer, nhc, gnss_position, gnss_velocity, baro, heading
    sigma = "0.02 m/s"        # one value, or one per component
    lever_arm = ["0 m", "0.8 m", "1.2 m"]
    schedule = {period = "1 s", when = "moving"}   # start, end, when, outages = [["10 min", "11 min"]], at
    [measurement.errors.scale_factor]
    sigma = "1000 ppm"
    process = "constant"      # or "markov" with tau

    [[grade]]                 # optional: IMU grades, as in the trade grid (every sensor error × scale)
    name = "tactical"
    scale = 30.0

    [output]
    history_every = "10 s"
    report_times = ["30 min", "2 h"]
"""

from __future__ import annotations

import re
import time
from functools import partial

import numpy as np
import pandas as pd

from covtool.analysis.metrics import nav_metrics
from covtool.errors import StudyFileError
from covtool.io.config import (check_keys, choice, names, number, quantity, quantity_list, require,
                               string, table)
from covtool.io.filters import load_filters
from covtool.lincov.aided import augment, build_epochs, error_processes, Jacobians, propagate_aided
from covtool.lincov.kalman import check_system
from covtool.lincov.measurements import KINDS, Schedule, WHEN
from covtool.lincov.measurements.base import error_state
from covtool.lincov.reduced import build_filter
from covtool.lincov.reference import propagate
from covtool.lincov.streamed import ChunkPool
from covtool.nav.strapdown import NAV_STATES
from covtool.plotting.aided import aided_history_figure, aided_sweep_figure
from covtool.results import StudyResult
from covtool.studies.aided_sweep import _sweep_table, parse_sweep, scaled_plan
from covtool.studies.config import MEASUREMENT_NAME
from covtool.studies.grid import (discretize_chunked, discretize_steps, initial_covariance, time_grid,
                                  truth_stream)
from covtool.studies.inputs import load_trajectory, load_truth, output_options, study_header, study_inputs
from covtool.studies.resources import (check_memory, HELD_CHUNKS, memory_estimate, noise_columns,
                                       resource_provenance, steps_of)
from covtool.studies.tables import case_validity, history_frame, summary_row
from covtool.studies.zupt_setup import filter_cases, filters_file, truth_copy
from covtool.units import ARCMIN

MEAS_KEYS = {"name", "kind", "sigma", "filter_sigma", "lever_arm", "errors", "schedule"}
SCHEDULE_KEYS = {"period", "rate", "start", "end", "when", "outages", "at"}
ERROR_KEYS = {"sigma", "process", "tau"}
#: a measurement with at most this many updates (survey points, stops) gets its before/after table
SPARSE_UPDATES = 50
#: states recorded of every run: the navigation block (what the tables and figures show)
NAV = len(NAV_STATES)
_NAME = MEASUREMENT_NAME                # one rule, declared with the typed [[measurement]] section


# --------------------------------------------------------------------------
# declaration
# --------------------------------------------------------------------------

def parse_measurement(cfg, i: int, where: str):
    """One ``[[measurement]]`` table -> ``(Measurement, Schedule)``; one-line errors.

    Raises
    ------
    StudyFileError
        Unknown key or kind, missing or bad σ (unit of the kind), a lever
        arm that is not three lengths (or on a kind without one), an
        unknown error state, a missing error σ, a bad process, a bad schedule.
    """
    w = f"{where}: [[measurement]] #{i + 1}"
    cfg = table(cfg, w, StudyFileError)
    name = string(require(cfg, "name", w, StudyFileError), f"{w} name", StudyFileError, nonempty=True)
    if not _NAME.match(name):
        raise StudyFileError(f"{w} name", f"{name!r} must start with a letter and hold only letters, digits and _")
    w = f"{where}: [[measurement]] {name!r}"
    check_keys(cfg, MEAS_KEYS, w, StudyFileError)
    kind = require(cfg, "kind", w, StudyFileError)
    if kind not in KINDS:
        raise StudyFileError(f"{w} kind", f"unknown measurement kind {kind!r} (one of: {', '.join(sorted(KINDS))})")
    cls = KINDS[kind]
    m = len(cls.COMPONENTS)

    def sig(key):
        v = cfg[key]
        vals = v if isinstance(v, list) else [v] * m
        if len(vals) != m:
            raise StudyFileError(f"{w} {key}", f"{len(vals)} values for the {m} components "
                                 f"({', '.join(cls.COMPONENTS)}) of {_a(kind)}")
        return np.array([quantity(x, cls.DIMENSION, f"{w} {key}" + (f"[{j}]" if isinstance(v, list) else ""),
                                  StudyFileError, positive=True) for j, x in enumerate(vals)])
    if "sigma" not in cfg:
        raise StudyFileError(f"{w} sigma", f"missing: the {kind}'s white-noise 1σ (a {cls.DIMENSION})")
    sigma = sig("sigma")
    fsigma = sig("filter_sigma") if "filter_sigma" in cfg else None
    lever = np.zeros(3)
    if "lever_arm" in cfg:
        if not cls.LEVER:
            raise StudyFileError(f"{w} lever_arm", f"{_a(kind)} takes no lever arm")
        v = cfg["lever_arm"]
        if not isinstance(v, list) or len(v) != 3:
            raise StudyFileError(f"{w} lever_arm", f"expected three lengths (body x, y, z), got {v!r}")
        lever = np.array([quantity(x, "length", f"{w} lever_arm[{j}]", StudyFileError) for j, x in enumerate(v)])
    states = []
    errs = table(cfg.get("errors", {}), f"{w} errors", StudyFileError)
    for sfx, ecfg in errs.items():
        we = f"{w} errors.{sfx}"
        if sfx not in cls.ERRORS:
            raise StudyFileError(we, f"{_a(kind)} has no error state {sfx!r} (known: "
                                 f"{', '.join(cls.ERRORS) or 'none'})")
        ecfg = table(ecfg, we, StudyFileError)
        check_keys(ecfg, ERROR_KEYS, we, StudyFileError)
        dim = cls.ERRORS[sfx][0]
        if "sigma" not in ecfg:
            raise StudyFileError(f"{we} sigma", f"missing: the initial 1σ (a {dim})")
        s = quantity(ecfg["sigma"], dim, f"{we} sigma", StudyFileError, nonnegative=True)
        proc = choice(ecfg.get("process", "constant"), ("constant", "markov"), f"{we} process", StudyFileError)
        tau = None
        if proc == "markov":
            tau = quantity(require(ecfg, "tau", we, StudyFileError), "time", f"{we} tau", StudyFileError,
                           positive=True)
        elif "tau" in ecfg:
            raise StudyFileError(f"{we} tau", "only a markov state has a correlation time")
        unit = ecfg["sigma"].split(None, 1)[1] if isinstance(ecfg["sigma"], str) and " " in ecfg["sigma"] else ""
        states.append(error_state(name, kind, sfx, s, proc, tau=tau, unit=unit))
    meas = cls(name=name, sigma=sigma, states=tuple(states), lever_arm=lever, filter_sigma=fsigma)
    return meas, parse_schedule(cfg.get("schedule", {}), f"{w} schedule")


def _a(word: str) -> str:
    return f"{'an' if word[0] in 'aeiou' else 'a'} {word}"


def parse_schedule(cfg, w: str) -> Schedule:
    """``schedule = {period | rate, start, end, when, outages, at}`` -> :class:`Schedule`."""
    cfg = table(cfg, w, StudyFileError)
    check_keys(cfg, SCHEDULE_KEYS, w, StudyFileError)
    if "period" in cfg and "rate" in cfg:
        raise StudyFileError(w, "give period or rate, not both")
    period = (1.0 / quantity(cfg["rate"], "frequency", f"{w} rate", StudyFileError, positive=True) if "rate" in cfg
              else quantity(cfg.get("period", "1 s"), "time", f"{w} period", StudyFileError, positive=True))
    start = quantity(cfg.get("start", "0 s"), "time", f"{w} start", StudyFileError)
    end = quantity(cfg["end"], "time", f"{w} end", StudyFileError) if "end" in cfg else None
    when = choice(cfg.get("when", "always"), WHEN, f"{w} when", StudyFileError)
    outages = []
    for j, o in enumerate(cfg.get("outages", [])):
        if not isinstance(o, list) or len(o) != 2:
            raise StudyFileError(f"{w} outages[{j}]", f"expected [start, end], got {o!r}")
        outages.append(tuple(quantity(x, "time", f"{w} outages[{j}]", StudyFileError) for x in o))
    at = tuple(quantity_list(cfg["at"], "time", f"{w} at", StudyFileError)) if "at" in cfg else ()
    return Schedule(period=period, start=start, end=end, when=when, outages=tuple(outages), at=at)


def parse_variants(fcfg: dict, specs: dict, states: list, where: str) -> dict:
    """``[[filters.variant]]``: name -> (base filter, dropped measurement-error states)."""
    out = {}
    known = [s.name for s in states]
    for j, v in enumerate(fcfg.get("variant", [])):
        w = f"{where}: [[filters.variant]] #{j + 1}"
        v = table(v, w, StudyFileError)
        check_keys(v, {"name", "base", "drop"}, w, StudyFileError)
        nm = string(require(v, "name", w, StudyFileError), f"{w} name", StudyFileError, nonempty=True)
        if nm in specs or nm in out:
            raise StudyFileError(f"{w} name", f"{nm!r} is already a filter")
        base = choice(require(v, "base", w, StudyFileError), list(specs), f"{w} base", StudyFileError)
        drop = names(require(v, "drop", w, StudyFileError), f"{w} drop", StudyFileError, known=known,
                     what="measurement-error state")
        out[nm] = (base, drop)
    return out


def parse_grades(decl: dict, where: str) -> list:
    """``[[grade]]`` (name, scale, description); default one grade, the truth as declared."""
    grades = decl.get("grade")
    if grades is None:
        return [{"name": "as declared", "scale": 1.0}]
    if not isinstance(grades, list) or not grades:
        raise StudyFileError(f"{where}: [[grade]]", "expected a non-empty list of tables")
    out = []
    for j, g in enumerate(grades):
        w = f"{where}: [[grade]] #{j + 1}"
        g = table(g, w, StudyFileError)
        check_keys(g, {"name", "scale", "description"}, w, StudyFileError)
        out.append({"name": string(require(g, "name", w, StudyFileError), f"{w} name", StudyFileError, nonempty=True),
                    "scale": number(require(g, "scale", w, StudyFileError), f"{w} scale", StudyFileError, lo=1e-3,
                                    hi=1e3, why="a grade scales every sensor error"),
                    "description": g.get("description", "")})
    if len({g["name"] for g in out}) != len(out):
        raise StudyFileError(f"{where}: [[grade]]", "grade names must be unique")
    return out


# --------------------------------------------------------------------------
# run
# --------------------------------------------------------------------------

def parse_measurements(mdecl, where: str, empty: str = "expected a non-empty list of [[measurement]] tables"):
    """The ``[[measurement]]`` tables -> ``(plan, states)``, names unique.

    Returns
    -------
    plan : list of (Measurement, Schedule)
    states : list of State
        Every measurement's own error states, in order.

    Raises
    ------
    StudyFileError
        Not a non-empty list (``empty`` says why), a bad table, a name used twice.
    """
    if not isinstance(mdecl, list) or not mdecl:
        raise StudyFileError(f"{where}: [[measurement]]", empty)
    plan = [parse_measurement(c, i, where) for i, c in enumerate(mdecl)]
    mnames = [m.name for m, _ in plan]
    dup = next((n for j, n in enumerate(mnames) if n in mnames[:j]), None)
    if dup is not None:
        raise StudyFileError(f"{where}: [[measurement]] {dup!r}", "the name is used twice")
    return plan, [s for m, _ in plan for s in m.states]


def check_error_state_names(plan, states, truth, where: str) -> None:
    """Refuse a measurement-error state named like a truth-model state or block (StudyFileError)."""
    clash = [s.name for s in states if s.name in truth.index or s.name in {x.block for x in truth.states}]
    if clash:
        meas = next(m.name for m, _ in plan if clash[0] in m.state_names)
        raise StudyFileError(f"{where}: [[measurement]] {meas!r} name", f"its error state {clash[0]!r} has the name "
                             f"of a truth-model state or block; rename the measurement")


def measurement_steps(plan, t: np.ndarray, nodes, where: str) -> tuple[list, np.ndarray]:
    """Each measurement's update steps on the grid, checked against the trajectory.

    Parameters
    ----------
    plan : list of (Measurement, Schedule)
    t : ndarray, shape (N+1,)
        The grid. [s]
    nodes : object
        The trajectory at ``t``.
    where : str
        The study file, for messages.

    Returns
    -------
    steps : list of ndarray of int
        Per measurement, its update steps.
    all_steps : ndarray of int
        Every step with an update, sorted, unique.

    Raises
    ------
    StudyFileError
        A schedule outside the trajectory, or no update inside the study.
    """
    steps = []
    for meas, sch in plan:
        p = sch.problem(t, nodes)
        if p is not None:
            raise StudyFileError(f"{where}: [[measurement]] {meas.name!r} schedule", p)
        steps.append(sch.steps(t, nodes))
    all_steps = np.unique(np.concatenate(steps))
    if all_steps.size == 0:
        raise StudyFileError(f"{where}: [[measurement]]", "no update falls inside the study (check the outages)")
    return steps, all_steps


def run(decl: dict, *, path=None, progress: bool = False) -> StudyResult:
    """Run an aided-navigation study; see the module docstring."""
    t_start = time.perf_counter()
    where = str(path) if path else "<study>"
    base_dir = path.parent if path else None
    check_keys(decl, {"study", "trajectory", "truth", "filters", "measurement", "grade", "output", "sweep"}, where,
               StudyFileError)
    hdr = study_header(decl, where)
    every, rtimes = output_options(decl, where, hdr["duration"])
    plan, states = parse_measurements(decl.get("measurement"), where, "an aided study needs at least one measurement")
    fcfg = table(decl.get("filters", {}), f"{where}: [filters]", StudyFileError)
    check_keys(fcfg, {"file", "cases", "pure_ins", "ewn_interval", "variant"}, f"{where}: [filters]", StudyFileError)
    grades = parse_grades(decl, where)
    truth0 = load_truth(decl, where, base_dir)
    ffile = filters_file(fcfg, where, base_dir)
    specs = load_filters(ffile, truth0)
    cases = filter_cases(fcfg, specs, ffile, where, nonempty=True)
    check_error_state_names(plan, states, truth0, where)
    variants = parse_variants(fcfg, specs, states, where)
    for v, (b, _) in variants.items():
        if b not in cases:
            raise StudyFileError(f"{where}: [[filters.variant]] {v!r} base", f"{b!r} is not one of the [filters] "
                                 f"cases ({', '.join(cases)}): a variant is tabulated against its base, which must run")
    sweep = parse_sweep(decl["sweep"], [m for m, _ in plan], where) if "sweep" in decl else None
    est = check_memory(_streamed_memory(hdr, truth0, specs, cases, variants, states, every, plan),
                       where, hdr["max_memory"], "a larger [study] dt or history_every, a shorter duration or fewer "
                       "[filters] cases")
    traj = load_trajectory(decl, where, base_dir, hdr["dt"], hdr["duration"])
    t = time_grid(hdr["duration"], hdr["dt"], where)
    nodes = traj.sample(t)
    steps, all_steps = measurement_steps(plan, t, nodes, where)   # every schedule, before any computation
    ewn_dt = (quantity(fcfg["ewn_interval"], "time", f"{where}: [filters] ewn_interval", StudyFileError,
                       positive=True) if "ewn_interval" in fcfg else float(t[-1]) / all_steps.size)
    windows = {}                           # one row per outage window, naming the measurements it silences
    for m, sch in plan:
        for a, b in sch.outages:
            windows.setdefault((a, b), []).append(m.name)
    outage_marks = [(", ".join(v), a, b) for (a, b), v in sorted(windows.items())]
    # sparse measurements (survey points, stops): the error just before and after each update is tabulated
    sparse = [(m.name, st) for (m, _), st in zip(plan, steps) if 0 < st.size <= SPARSE_UPDATES]
    rec = np.union1d(_record_steps(t, every, rtimes, outage_marks),
                     np.concatenate([st for _, st in sparse]) if sparse else np.zeros(0, int))
    moving = t[-1] - sum(max(0.0, min(b, t[-1]) - max(a, 0.0)) for a, b in traj.stationary)
    mean_speed = float(nodes.distance[-1] / moving) if moving > 0 else None
    meas_pairs = list(zip([m for m, _ in plan], steps))
    names_all = None
    metrics, claimed, nstates, at_updates, swept = {}, {}, {}, [], {}
    dt_steps = np.diff(t)
    err = error_processes(states, dt_steps)[:2]
    jac = Jacobians(nodes)                 # the measurement Jacobians: the same in every grade, filter and scale
    for g in grades:
        truth = load_truth(decl, where, base_dir, grade=g) if g["scale"] != 1.0 else truth0
        # streamed in time: Φ, Q_d made chunk by chunk, held for the grade's later runs while the pool has room
        pool = ChunkPool(HELD_CHUNKS)
        ctx, dyn, tsys = truth_stream(truth, traj, t, hdr["discretization"], pool=pool, where=where)
        Phi, Qd = tsys.Phi, tsys.Qd
        P0 = initial_covariance(truth, nodes, where)
        names_all = list(truth.names) + [s.name for s in states]
        gl = g["name"]
        if fcfg.get("pure_ins", True):
            P = propagate(Phi, Qd, P0, label=f"{where}: {gl}: pure INS", names=truth.names, times=t,
                          system_checked=True, record=rec, keep=NAV)
            metrics[(gl, "pure_ins")] = _metrics(P, nodes, rec)
            nstates[(gl, "pure_ins")] = truth.n
            del P
        built = {}
        specs_g = load_filters(ffile, truth)
        runs = [(c, c, []) for c in cases] + [(v, b, d) for v, (b, d) in variants.items()]
        for label, base, drop in runs:
            if base not in built:
                built[base] = filter_system(specs_g[base], truth, ctx, dyn, Phi, Qd, hdr, t, nodes, ewn_dt=ewn_dt,
                                            mean_speed=mean_speed, update_steps=all_steps, where=where, pool=pool)
            fm, Phi_f, Qd_f = built[base]
            kept = [s.name for s in states if s.name not in drop]
            r, fnames, _, _ = filter_run(fm, Phi, Qd, Phi_f, Qd_f, P0, states, kept, meas_pairs, nodes, names_all,
                                         err, rec, form=specs_g[base].update, label=f"{where}: {gl}: filter {label}",
                                         jacobians=jac, keep=NAV)
            metrics[(gl, label)] = _metrics(r.P_truth, nodes, rec)
            if sweep is not None and not drop:     # the same filter with the swept measurement's σ scaled
                for sc in sweep["scales"]:
                    pairs = scaled_plan(meas_pairs, sweep, sc)
                    rs = r if sc == 1.0 else filter_run(
                        fm, Phi, Qd, Phi_f, Qd_f, P0, states, kept, pairs, nodes, names_all, err, rec,
                        form=specs_g[base].update, label=f"{where}: {gl}: filter {label}, {sweep['measurement']} "
                                                         f"{sweep['what']} x{sc:g}", jacobians=jac, keep=NAV)[0]
                    swept[(gl, label, sc)] = (next(m for m, _ in pairs if m.name == sweep["measurement"]),
                                              _metrics(rs.P_truth, nodes, rec),
                                              _metrics(rs.P_filter[:, :10, :10], nodes, rec))
            claimed[(gl, label)] = _metrics(r.P_filter[:, :10, :10], nodes, rec)
            nstates[(gl, label)] = len(fnames)
            pos = {int(k): i for i, k in enumerate(r.steps)}
            for mname, st in sparse:
                before = _metrics(np.stack([r.prior_truth[int(k)][:10, :10] for k in st]), nodes, st)
                after = _metrics(r.P_truth[[pos[int(k)] for k in st]], nodes, st)
                for j, k in enumerate(st):
                    at_updates.append({"grade": gl, "case": label, "measurement": mname, "t [min]": t[k] / 60,
                                       "CEP before [m]": before["cep"][j], "CEP after [m]": after["cep"][j],
                                       "alt PE before [m]": before["alt_pe"][j],
                                       "alt PE after [m]": after["alt_pe"][j],
                                       "azimuth before [arcmin]": before["sigma_azimuth"][j] / ARCMIN,
                                       "azimuth after [arcmin]": after["sigma_azimuth"][j] / ARCMIN})
        # the last run's systems too: a streamed Φ_f (the truth's, for filter A) holds its grade's chunks
        del Phi, Qd, tsys, built, pool
        fm = Phi_f = Qd_f = r = rs = None
    elapsed = time.perf_counter() - t_start
    tr = t[rec]
    summary = _summary(metrics, claimed, nstates, tr, nodes, rec, rtimes)
    tables = {"summary": summary,
              "history": pd.concat([_history(k, tr, m, every) for k, m in metrics.items()], ignore_index=True),
              "measurements": _measurement_table(plan, steps, t),
              "truth_states": truth0.state_table()}
    if outage_marks:
        tables["outages"] = _outage_table(metrics, outage_marks, tr)
    if at_updates:
        tables["sparse_updates"] = pd.DataFrame(at_updates)
    if sweep is not None:
        tables["measurement_sweep"] = _sweep_table(swept, sweep, tr, rtimes)
    if variants:
        tables["measurement_state_impact"] = _variant_table(metrics, claimed, variants, tr, rtimes, grades)
    # partials of the plotting module's makers, over the data they draw: they pickle (the figure server)
    figures = {f"aided_{_slug(g['name'])}": partial(aided_history_figure, hdr["name"], g["name"], metrics, tr,
                                                    outage_marks) for g in grades}
    if sweep is not None:
        figures["measurement_sweep"] = partial(aided_sweep_figure, hdr["name"], tables["measurement_sweep"], sweep)
    return StudyResult(
        name=hdr["name"], kind="aided", tables=tables, figures=figures,
        resolved={**decl, "study": {**decl["study"], "name": hdr["name"]}},
        provenance={**study_inputs(path, decl, truth0), "truth_model": truth0.name,
                    "truth_model_sha256": truth0.sha256, "measurement_states": ", ".join(s.name for s in states),
                    "equivalent_noise_interval_s": f"{ewn_dt:g}", **resource_provenance(est),
                    "compute_seconds": f"{elapsed:.2f}"},
    )


def filter_run(fm, Phi, Qd, Phi_f, Qd_f, P0, states, kept, meas_pairs, nodes, names_all, err, rec, *, form,
               label, all_gains=False, P0_truth=None, jacobians=None, keep=None):
    """The truth under one filter with the declared measurements (seed 002, eq (15)–(16)).

    ``P0_truth`` (n₀ + n_e square), if given, replaces the truth's initial
    covariance over ``[x_INS; e]`` (the Monte Carlo's conditional
    prediction); the filter and its gains do not depend on it.  ``jacobians``
    (:class:`covtool.lincov.aided.Jacobians` of ``nodes``) shares the
    measurement Jacobians between the runs of a study.  ``keep`` (the
    navigation block, :data:`NAV`) records only the leading states
    (:func:`covtool.lincov.aided.propagate_aided`).  ``Phi``, ``Qd``,
    ``Phi_f``, ``Qd_f`` are whole-grid stacks or streamed
    (:func:`filter_system`), already guarded.

    Returns
    -------
    run : covtool.lincov.aided.AidedRun
    filter_names : list of str
        The filter's INS states, then the measurement-error states it keeps.
    D : ndarray, shape (n, n_f)
    epochs : list of covtool.lincov.aided.Epoch
    """
    P0a, Pf_e, D = augment(P0, fm.D, states, kept)
    P0a = P0a if P0_truth is None else P0_truth
    nf0 = fm.P0.shape[0]
    Pf0 = np.zeros((nf0 + len(kept),) * 2)
    Pf0[:nf0, :nf0], Pf0[nf0:, nf0:] = fm.P0, Pf_e
    fnames = list(fm.names) + list(kept)
    epochs = build_epochs(meas_pairs, nodes, names_all, fnames, jacobians=jacobians)
    err_f = error_processes([s for s in states if s.name in kept], np.diff(nodes.t))[:2]
    r = propagate_aided(Phi, Qd, P0a, Phi_f, Qd_f, Pf0, D, epochs, err=err, err_f=err_f, record=rec, form=form,
                        label=label, times=nodes.t, names=names_all, filter_names=fnames, system_checked=True,
                        all_gains=all_gains, keep=keep)
    return r, fnames, D, epochs


def filter_system(spec, truth, ctx, dyn, Phi, Qd, hdr, t, nodes, *, ewn_dt, mean_speed, update_steps,
                  where="<study>", pool=None):
    """A base filter evaluated on the grid: ``(FilterModel, Φ_f, Q_f)``.

    Δt_s of seed 002, eq (11)–(13) is ``ewn_dt``; the filter's F_f is the
    truth's under the filter's own navigation options (seed 002 eq (1), (4)
    with or without the Coriolis terms and the vertical coupling); a filter
    equal to the truth (filter A) reuses the truth's Φ, Q_d.

    Parameters
    ----------
    spec : FilterSpec
    truth : Model
    ctx : Context
        The trajectory at the step mid-points.
    dyn : ErrorDynamics or DynamicsStream
        The truth's dynamics under its own options: whole-grid
        (:func:`covtool.studies.grid.truth_system`; Φ_f, Q_f are then
        whole-grid stacks) or streamed (:func:`covtool.studies.grid.truth_stream`;
        Φ_f, Q_f are then a :class:`~covtool.lincov.streamed.StreamedSystem`'s,
        made chunk by chunk and held in ``pool``).
    Phi, Qd : ndarray, shape (N, n, n), or streamed
        The truth's (reused by a filter equal to it).
    pool : covtool.lincov.streamed.ChunkPool, optional
        Budget of held chunks (streamed only).

    Raises
    ------
    NumericalError
        Φ_f or Q_f of a step is not finite (Q_f: symmetric, PSD); streamed,
        when its chunk is made.
    """
    from covtool.lincov.dynamics import DynamicsStream, dyn_key, with_nav_options
    from covtool.lincov.streamed import StreamedSystem

    dt_steps = np.diff(t)
    what = f"{spec.path}: filter {spec.name!r}"
    streamed = isinstance(dyn, DynamicsStream)
    if streamed:
        fdyn = dyn if dyn_key(spec.options) == dyn_key(dyn.options) else DynamicsStream(truth, ctx, spec.options)
    else:
        fdyn = with_nav_options(dyn, ctx, spec.options)
    fm = build_filter(spec, truth, ctx, zupt_interval=ewn_dt, q0=nodes.q_nb[0], truth_dynamics=fdyn,
                      mean_speed=mean_speed, dt_steps=dt_steps, update_steps=update_steps)
    if streamed:
        same = (spec.discretization == hdr["discretization"] and truth_copy(spec, truth) and not fm.ewn_noise
                and np.array_equal(truth.idx(spec.kept), np.arange(truth.n)))
    else:
        same = (spec.discretization == hdr["discretization"] and fm.F.shape == dyn.F.shape
                and (spec.discretization == "van_loan" or spec.taylor_order is None)
                and np.array_equal(fm.F, dyn.F) and np.array_equal(fm.Qc, dyn.Qc))
    if same:                   # the truth itself (filter A): its Φ, Q_d, not computed again
        return fm, Phi, Qd
    if streamed:
        def make(a, b):
            F_f, Qc_f = fm.chunk(fdyn.chunk(a, b), a, b)
            return discretize_steps(F_f, Qc_f, t, a, b, spec.discretization, spec.taylor_order, what=what,
                                    label=f"{where}: filter {spec.name}", names=fm.names)

        fsys = StreamedSystem(make, t.size - 1, len(fm.names), pool=pool)
        return fm, fsys.Phi, fsys.Qd
    Phi_f, Qd_f = discretize_chunked(fm.F, fm.Qc, dt_steps, spec.discretization, spec.taylor_order,
                                     what=what, times=t[:-1])
    check_system(f"{where}: filter {spec.name}", Phi_f, Qd_f, names=fm.names, times=t)
    return fm, Phi_f, Qd_f


def _memory(hdr, truth, specs, cases, variants, states, every, pure) -> dict:
    """Peak memory with whole-grid systems (the aided Monte Carlo): the truth system, every base
    filter's system, the pure-INS history, the recorded histories."""
    steps = steps_of(hdr["duration"], hdr["dt"])
    bases = list(dict.fromkeys([*cases, *(b for b, _ in variants.values())]))
    n, ne = truth.n, len(states)
    rec = steps / max(1.0, every / hdr["dt"]) + 64
    recorded = sum(rec * ((n + ne) ** 2 + (specs[b].n + ne) ** 2) * 8.0 for b in bases)
    return memory_estimate(steps, n, filters=[specs[b].n for b in bases], histories=[n] if pure else [],
                           noise=noise_columns(truth), extra=recorded + 2.0 * steps * ne * 8.0)


def _streamed_memory(hdr, truth, specs, cases, variants, states, every, plan) -> dict:
    """Peak memory of the aided kind, which streams in time (an upper estimate).

    :func:`~covtool.studies.resources.stream_memory_estimate` (one chunk of
    every system, the discretisation workspace, the filters' builds and
    equivalent-noise sources), plus what this kind holds over the grid:
    the chunks the pool keeps (at most :data:`~covtool.studies.resources.HELD_CHUNKS`),
    the measurement Jacobians (``m (10 + n_e)`` per update,
    :class:`~covtool.lincov.aided.Jacobians`), one filter run's epochs
    (``H``, ``H_f``, ``R``, ``R_f`` per update), the guard's block of
    covariances, the measurement-error processes and the recorded
    navigation blocks.  Updates are counted at each schedule's period over
    the whole duration (an upper count: outages and ``when`` are not
    known before the trajectory).
    """
    from covtool.lincov.dynamics import dyn_key
    from covtool.studies.resources import stream_memory_estimate

    N = steps_of(hdr["duration"], hdr["dt"])
    bases = list(dict.fromkeys([*cases, *(b for b, _ in variants.values())]))
    n, ne = truth.n, len(states)
    own = [specs[b] for b in bases
           if not (truth_copy(specs[b], truth) and specs[b].discretization == hdr["discretization"])]
    keys = {dyn_key(None)} | {dyn_key(s.options) for s in own}
    rec = N / max(1.0, every / hdr["dt"]) + 64
    est = stream_memory_estimate(N, n, filters=[s.n for s in own], dropped=[n - s.n for s in own],
                                 dynamics=len(keys), noise=noise_columns(truth), records=rec, intervals=0)
    parts = est["parts"]
    parts.pop("kept filter transitions", None)             # the filter-order stream's, not kept here
    parts.update(aided_run_memory(N, n, [s.n for s in own], max([specs[b].n for b in bases] or [n]), ne,
                                  update_rows(plan, N, hdr["duration"])))
    parts["recorded navigation blocks"] = rec * 2 * NAV * NAV * 8.0 * (len(cases) + len(variants) + 1)
    est["bytes"] = float(sum(parts.values()))
    return est


def update_rows(plan, steps: int, duration: float) -> list:
    """``(m, u)`` per measurement of ``plan``: its rows per update and an upper count of its updates.

    Counted at the schedule's period over the whole ``duration`` (outages
    and ``when`` are not known before the trajectory), plus its ``at`` times,
    at most one per grid index (``steps + 1``).
    """
    return [(len(m.COMPONENTS), min(steps + 1, duration / sch.period + 1) + len(sch.at)) for m, sch in plan]


def aided_run_memory(steps: int, n: int, filters, nf: int, ne: int, rows) -> dict:
    """What the aided engine holds beyond one chunk of every system (bytes per part), an upper estimate.

    The one home of these terms (the aided kind, its error budget and the
    trade grid's aiding mixes):

    * the chunks a study's :class:`~covtool.lincov.streamed.ChunkPool` holds:
      the truth's and each streamed filter's Φ, Q_d, at most
      :data:`~covtool.studies.resources.HELD_CHUNKS`;
    * the measurement Jacobians, ``m (10 + n_e)`` per update
      (:class:`~covtool.lincov.aided.Jacobians`);
    * one run's epochs: ``H``, ``H_f``, ``R`` and ``R_f`` per update;
    * the guard's block of truth and filter covariances
      (:data:`~covtool.lincov.aided.GUARD_BLOCK`);
    * the measurement-error processes (four ``(N, n_e)`` arrays).

    Parameters
    ----------
    steps : int
        Grid steps ``N``.
    n : int
        INS truth states.
    filters : sequence of int
        States of each filter system streamed besides the truth's.
    nf : int
        The largest filter's INS states.
    ne : int
        Measurement-error states.
    rows : list of (int, float)
        :func:`update_rows` (and any other measurement's, as ``(m, u)``).

    Returns
    -------
    dict of str to float
    """
    from covtool.lincov.aided import GUARD_BLOCK

    per_step = 2 * n * n + sum(2 * k * k for k in filters)
    return {"held chunks": min(float(HELD_CHUNKS), steps * per_step * 8.0),
            "measurement Jacobians": sum(u * m * (10 + ne) for m, u in rows) * 8.0,
            "one run's epochs": sum(u * (m * (n + ne) + m * (nf + ne) + 2 * m * m) for m, u in rows) * 8.0,
            "aided guard block": 2 * GUARD_BLOCK * ((n + ne) ** 2 + (nf + ne) ** 2) * 8.0,
            "measurement-error processes": 4 * steps * ne * 8.0}


def _record_steps(t, every, rtimes, outages) -> np.ndarray:
    dt = t[1] - t[0]
    k = max(1, int(round(every / dt)))
    extra = [np.argmin(np.abs(t - x)) for x in rtimes]
    for _, a, b in outages:
        extra += [int(np.argmin(np.abs(t - a))), int(np.argmin(np.abs(t - b)))]
    return np.unique(np.concatenate([np.arange(0, t.size, k), [t.size - 1], np.asarray(extra, int)]))


def _metrics(P, nodes, rec):
    return nav_metrics(P, nodes.lat[rec], nodes.h[rec], nodes.q_nb[rec], nodes.distance[rec])


def _summary(metrics, claimed, nstates, tr, nodes, rec, rtimes):
    rows = []
    for (g, case), m in metrics.items():
        first = case_validity(f"{g}: {case}", m, tr)
        for x in rtimes:
            i = int(np.argmin(np.abs(tr - x)))
            row = {"grade": g, **summary_row(case, m, i, tr[i], float(nodes.distance[rec[i]]), first=first),
                   "states": nstates[(g, case)]}
            if (g, case) in claimed:
                c = claimed[(g, case)]
                row["filter-claimed CEP [m]"] = c["cep"][i]
                row["filter-claimed azimuth [arcmin]"] = c["sigma_azimuth"][i] / ARCMIN
            rows.append(row)
    return pd.DataFrame(rows)


def _history(key, tr, m, every):
    df = history_frame(key[1], tr, m)
    df.insert(0, "grade", key[0])
    return df


def _measurement_table(plan, steps, t):
    rows = []
    for (m, sch), st in zip(plan, steps):
        rows.append({"measurement": m.name, "kind": m.kind, "components": ", ".join(m.COMPONENTS),
                     "sigma [SI]": ", ".join(f"{x:g}" for x in m.sigma), "lever arm [m]":
                     ", ".join(f"{x:g}" for x in m.lever_arm), "error states": ", ".join(m.state_names) or "-",
                     "updates": int(st.size), "first [s]": float(t[st[0]]) if st.size else np.nan,
                     "last [s]": float(t[st[-1]]) if st.size else np.nan,
                     "outages [s]": "; ".join(f"{a:g}-{b:g}" for a, b in sch.outages) or "-",
                     "equation": m.ref})
    return pd.DataFrame(rows)


def _outage_table(metrics, outages, tr):
    rows = []
    for (g, case), m in metrics.items():
        if case == "pure_ins":
            continue
        for name, a, b in outages:
            ia, ib = int(np.argmin(np.abs(tr - a))), int(np.argmin(np.abs(tr - b)))
            rows.append({"grade": g, "case": case, "measurements": name, "outage start [s]": a,
                         "outage [s]": b - a, "CEP at start [m]": m["cep"][ia], "CEP at end [m]": m["cep"][ib],
                         "growth [m]": m["cep"][ib] - m["cep"][ia],
                         "sigma_D at end [m]": m["sigma_down"][ib]})
    return pd.DataFrame(rows)


def _variant_table(metrics, claimed, variants, tr, rtimes, grades):
    rows = []
    for g in grades:
        gl = g["name"]
        for v, (base, drop) in variants.items():
            for x in rtimes:
                i = int(np.argmin(np.abs(tr - x)))
                mb, mv = metrics[(gl, base)], metrics[(gl, v)]
                rows.append({"grade": gl, "filter": v, "base": base, "dropped states": ", ".join(drop),
                             "t [min]": tr[i] / 60, "CEP base [m]": mb["cep"][i], "CEP [m]": mv["cep"][i],
                             "CEP cost [%]": 100 * (mv["cep"][i] / mb["cep"][i] - 1),
                             "alt PE base [m]": mb["alt_pe"][i], "alt PE [m]": mv["alt_pe"][i],
                             "azimuth base [arcmin]": mb["sigma_azimuth"][i] / ARCMIN,
                             "azimuth [arcmin]": mv["sigma_azimuth"][i] / ARCMIN,
                             "filter-claimed CEP [m]": claimed[(gl, v)]["cep"][i]})
    return pd.DataFrame(rows)


def _slug(s):
    return re.sub(r"[^A-Za-z0-9]+", "_", s).strip("_").lower() or "grade"
