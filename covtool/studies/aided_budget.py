"""Error budget with declared measurements (issue 15): the ``error_budget`` kind with ``[[measurement]]``.

An ``error_budget`` study that declares ``[[measurement]]`` tables (the same
declaration as the ``aided`` kind, :mod:`covtool.studies.aided`) instead of
``[zupt]`` runs here.  The truth ``[x_INS; e]`` (the INS truth model and the
measurements' own error states) under each filter's gains is split exactly
into its sources (:func:`covtool.analysis.budget.aided_sources`):

* the INS sources of the ZUPT budget (initial errors by block, process
  noises);
* each measurement-error state (odometer scale factor, GNSS Markov position
  error, baro bias, ...): its initial σ and its driving noise;
* each measurement's white noise R.

With the nominal gains fixed, seed 002, eq (15)–(16) is linear in (P0, Q_d,
R): the contributions sum to the nominal run (the summary's residual
columns).  Every filter keeps every measurement-error state.

Study file::

    [study]
    kind = "error_budget"
    duration = "30 min"

    [filters]
    cases = ["pure_ins", "A", "B1"]

    [[measurement]]          # as in the aided kind
    name = "gnss"
    kind = "gnss_position"
    sigma = "1 m"
    schedule = {period = "1 s", outages = [["10 min", "15 min"]]}
    [measurement.errors.N]
    sigma = "1.5 m"
    process = "markov"
    tau = "10 min"

    [budget]
    resolution = "block"
"""

from __future__ import annotations

import time
from functools import partial
from types import SimpleNamespace

import numpy as np

from covtool.analysis.budget import (aided_sources, MEASUREMENT, MEASUREMENT_ERROR, nav_variances,
                                     noise_factors, run_aided_budget)
from covtool.analysis.metrics import nav_metrics
from covtool.errors import StudyFileError
from covtool.io.config import check_keys, table
from covtool.io.filters import load_filters
from covtool.lincov.aided import error_processes, Jacobians
from covtool.lincov.streamed import ChunkPool
from covtool.lincov.reference import propagate
from covtool.plotting.budget import budget_figure
from covtool.results import ErrorBudgetResult
from covtool.studies.aided import (_measurement_table, _streamed_memory, check_error_state_names, filter_run,
                                   filter_system, measurement_steps, NAV, parse_measurements, update_rows)
from covtool.studies.error_budget import (_residuals, _source_table, _tables, budget_cases, budget_charts,
                                          budget_options, PURE, report_record_steps)
from covtool.studies.grid import initial_covariance, time_grid, truth_stream
from covtool.studies.inputs import (length_unit, load_trajectory, load_truth, output_options, study_header,
                                    study_inputs)
from covtool.studies.resources import (check_memory, HELD_CHUNKS, noise_columns, progress_bar, resource_provenance,
                                       steps_of)
from covtool.studies.tables import case_validity
from covtool.studies.zupt_setup import filter_cases, filters_file


#: steps whose per-source Q_d a budget run holds at once (:func:`covtool.analysis.budget.run_aided_budget`'s ``chunk``)
BUDGET_CHUNK = 64


def run(decl: dict, *, path=None, progress: bool = False) -> ErrorBudgetResult:
    """Run an error budget with declared measurements; see the module docstring.

    Raises
    ------
    StudyFileError
        ``[zupt]`` next to ``[[measurement]]``, an unknown key, a bad
        measurement declaration (:func:`covtool.studies.aided.parse_measurement`),
        a schedule outside the trajectory, or no update inside the study.
    """
    t_start = time.perf_counter()
    where = str(path) if path else "<study>"
    base_dir = path.parent if path else None
    if "zupt" in decl:
        raise StudyFileError(f"{where}: [zupt]", "a budget with [[measurement]] declares its ZUPTs as a "
                             "measurement (kind = \"zupt\"), not in [zupt]")
    check_keys(decl, {"study", "trajectory", "truth", "filters", "measurement", "budget", "output"}, where,
               StudyFileError)
    opts = budget_options(decl, where)
    fcases, want_pure = budget_cases(decl, where)
    hdr = study_header(decl, where)
    every, rtimes = output_options(decl, where, hdr["duration"])
    plan, states = parse_measurements(decl["measurement"], where)
    mnames = [m.name for m, _ in plan]
    fcfg = table(decl.get("filters", {}), f"{where}: [filters]", StudyFileError)
    check_keys(fcfg, {"file", "cases"}, f"{where}: [filters]", StudyFileError)
    truth = load_truth(decl, where, base_dir)
    ffile = filters_file(fcfg, where, base_dir)
    specs = load_filters(ffile, truth)
    cases = filter_cases({**fcfg, "cases": fcases} if fcases is not None else fcfg, specs, ffile, where)
    check_error_state_names(plan, states, truth, where)
    est = check_memory(_memory(hdr, truth, specs, cases, states, every, plan), where, hdr["max_memory"],
                       "a larger [study] dt or history_every, a shorter duration or fewer [filters] cases")
    traj = load_trajectory(decl, where, base_dir, hdr["dt"], hdr["duration"])
    t = time_grid(hdr["duration"], hdr["dt"], where)
    nodes = traj.sample(t)
    steps, all_steps = measurement_steps(plan, t, nodes, where)   # every schedule, before any computation
    ewn_dt = float(t[-1]) / all_steps.size
    rec = report_record_steps(t, every, rtimes)
    moving = t[-1] - sum(max(0.0, min(b, t[-1]) - max(a, 0.0)) for a, b in traj.stationary)
    mean_speed = float(nodes.distance[-1] / moving) if moving > 0 else None
    meas_pairs = list(zip([m for m, _ in plan], steps))
    dt_steps = np.diff(t)

    # streamed in time (as the aided kind): Φ, Q_d made chunk by chunk and held for the later cases while the
    # pool has room; F and the noise factors made per budget chunk (run_aided_budget), never over the grid
    pool = ChunkPool(HELD_CHUNKS)
    ctx, dyn, tsys = truth_stream(truth, traj, t, hdr["discretization"], pool=pool, where=where)
    Phi, Qd = tsys.Phi, tsys.Qd
    P0 = initial_covariance(truth, nodes, where)
    names_all = list(truth.names) + [s.name for s in states]
    err = error_processes(states, dt_steps)[:2]
    q0 = nodes.q_nb[0]

    def noise(a, b):
        """F and the noise factors of the steps a … b−1 (aided_sources' factors: the stream gives every span
        the whole span's sources, so every span has the same factors)."""
        d = dyn.chunk(a, b)
        return d.F, noise_factors(truth, d.noise, opts["resolution"])

    sources, factors = aided_sources(truth, dyn.chunk(0, 1).noise, q0, states, mnames,
                                     resolution=opts["resolution"])
    lat, h, q = nodes.lat[rec], nodes.h[rec], nodes.q_nb[rec]
    runs, var, nominal, residuals, first = {}, {}, {}, {}, {}
    jac = Jacobians(nodes)                 # the measurement Jacobians, shared by every case
    # a discretisation chunk at a time, inside the runs: the bar counts the cases (each a nominal run and its budget)
    order = ([PURE] if want_pure else []) + list(cases)
    with progress_bar(len(order), "budget cases", progress) as bar:
        for c in order:
            label = f"{where}: {'pure INS' if c == PURE else 'filter ' + c} error budget"
            if c == PURE:                      # no update: the measurements' sources are zero, left out
                src = [s for s in sources if s.kind not in (MEASUREMENT, MEASUREMENT_ERROR)]
                nominal[c] = propagate(Phi, Qd, P0, label=f"{where}: pure INS", names=truth.names, times=t,
                                       system_checked=True, record=rec, keep=NAV)
                runs[c] = run_aided_budget(Phi, noise, dt_steps, src, [], mnames,
                                           np.zeros((truth.n, 0)), [], {}, rec, label=label, names=truth.names,
                                           times=t, chunk=BUDGET_CHUNK)
            else:
                fm, Phi_f, Qd_f = filter_system(specs[c], truth, ctx, dyn, Phi, Qd, hdr, t, nodes, ewn_dt=ewn_dt,
                                                mean_speed=mean_speed, update_steps=all_steps, where=where, pool=pool)
                r, _, D, epochs = filter_run(fm, Phi, Qd, Phi_f, Qd_f, P0, states, [s.name for s in states],
                                             meas_pairs, nodes, names_all, err, rec, form=specs[c].update,
                                             label=f"{where}: filter {c} (nominal run)", all_gains=True,
                                             jacobians=jac, keep=NAV)
                nominal[c] = r.P_truth[:, :10, :10]
                runs[c] = run_aided_budget(Phi, noise, dt_steps, sources, states, mnames, D, epochs, r.gains,
                                           rec, err=err, label=label, names=names_all, times=t, chunk=BUDGET_CHUNK)
                del r, Phi_f, Qd_f
            var[c] = nav_variances(runs[c].P, lat, h, q)
            residuals[c] = _residuals(runs[c], nominal[c], lat, h, q)
            first[c] = case_validity(c, nav_metrics(nominal[c], lat, h, q), t[rec])
            bar.update(1)
    elapsed = time.perf_counter() - t_start
    cases = list(runs)
    tables = _tables(cases, runs, var, nominal, residuals, t, rec,
                     SimpleNamespace(report_times=rtimes, nodes=nodes), lat, h, first)
    tables["sources"] = _source_table(sources, factors)
    tables["measurements"] = _measurement_table(plan, steps, t)
    provenance = {"truth_model": truth.name, "truth_model_file": truth.path, "truth_model_sha256": truth.sha256,
                  "resolution": opts["resolution"], "sources": len(sources),
                  "measurement_states": ", ".join(s.name for s in states),
                  "updates": int(all_steps.size), "equivalent_noise_interval_s": f"{ewn_dt:g}",
                  **resource_provenance(est), "compute_seconds": f"{elapsed:.2f}"}
    provenance.update(study_inputs(path, decl, truth, ffile))
    for c in cases:
        provenance[f"{c}: sum vs nominal run residual"] = f"{residuals[c]['nominal']:.3g}"
    stops = tuple((max(a, t[0]), min(b, t[-1])) for a, b in traj.stationary if b > t[0] and a < t[-1])
    result = ErrorBudgetResult(
        name=hdr["name"], kind="error_budget", tables=tables, charts=budget_charts(cases, runs, var, opts["top"]),
        resolved={**decl, "study": {**decl["study"], "name": hdr["name"]},
                  "budget": {**decl.get("budget", {}), **opts}},
        provenance=provenance,
        runs=runs, residuals=residuals, record_steps=rec,
        times=t[rec], length_unit=length_unit(decl, where), update_times=t[all_steps], stops=stops,
        variances=var, sources={c: [s.name for s in runs[c].sources] for c in cases},
        source_order=[s.name for s in sources], top=opts["top"])
    result.figures = {f"budget_{c}": partial(budget_figure, result, c) for c in cases}
    return result


def _memory(hdr, truth, specs, cases, states, every, plan) -> dict:
    """Peak memory of an error budget with measurements, which streams in time (an upper estimate).

    The aided kind's streamed estimate (:func:`covtool.studies.aided._streamed_memory`:
    one chunk of every system, the held chunks, the Jacobians, one run's
    epochs) plus what a budget adds: the nominal run's gain at every
    update, the members' covariances (one per source, ``4 B (n + n_e)²``
    with the products of an update), the per-source ``Q_d`` of one budget
    chunk and its series (:func:`covtool.lincov.discretize.per_source`: about
    25 terms of ``n × k`` per step) and the recorded contributions.  The
    sources are counted from above: one per state and noise column, one per
    measurement.
    """
    N = steps_of(hdr["duration"], hdr["dt"])
    filters = [c for c in cases if c != PURE]
    est = _streamed_memory(hdr, truth, specs, filters, {}, states, every, plan)
    parts = est["parts"]
    n, ne, k = truth.n, len(states), noise_columns(truth)
    sources = n + k + ne + len(plan)
    rec = N / max(1.0, every / hdr["dt"]) + 64
    nf = max([specs[c].n for c in filters] or [n])
    parts["nominal gains"] = sum(m * u for m, u in update_rows(plan, N, hdr["duration"])) * (nf + ne) * 8.0
    parts["budget members"] = 4 * sources * (n + ne) ** 2 * 8.0
    parts["per-source Q_d of a budget chunk"] = BUDGET_CHUNK * (2 * k * n * n + 3 * 25 * n * k) * 8.0
    parts["recorded contributions"] = 2 * sources * rec * NAV * NAV * 8.0
    est["bytes"] = float(sum(parts.values()))
    return est
