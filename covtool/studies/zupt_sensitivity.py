"""ZUPT filter trade: sensitivity, cost, performance (seed 002).

Seed 002 §3.1–3.3.

Reproduces seed 002 Fig 8 (the 30-min RMS navigation error as each filter's
assumed P_f(0), Q_f and R_f is scaled from ×1/100 to ×100, fitted by least
squares) and Table 4 (the cost of one filter cycle), and puts the paper's
three design criteria (performance, sensitivity, computation) side by side
in the ``summary`` table.

Study file (everything a ``zupt_filter_order`` study takes, plus)::

    [study]
    kind = "zupt_sensitivity"
    discretization = "taylor"     # truth Φ, Q_d: eq (6b)-(6d) (adaptive) or "van_loan"

    [sweep]
    parameters = ["P0", "Q", "R"]                 # scaled one at a time
    scales = {from = 0.01, to = 100, per_decade = 4}
    fit_degree = 5           # polynomial in log10(scale) fitted to log10(error)
    discretization = "declared"   # the filters' Φ_f, Q_f: "declared" | "van_loan" | "taylor"

    [cost]
    measure = true           # time one cycle with numpy on this machine
    repeats = 7              # timeit repeats (median)
    taylor_order = "auto"    # N_t of eq (6b)-(6d) in the FLOP count, or an integer ≥ 2
    paper_seconds = {A = 22.62, B3 = 0.74, C = 0.29, D = 0.08}   # seed 002 Table 4

What is computed
----------------
* The truth (its Φ, Q_d, P0, H, R) is never scaled; only the filter's
  assumed P_f(0), Q_f (its whole discrete Q, equivalent noise included) and
  R_f are, so only its gains change (seed 002 eq (7)).
* Every case of one filter runs in one batched engine call
  (:func:`covtool.analysis.sensitivity.run_sweep`, B = 1 + 3·(n_scales − 1): the
  nominal case is shared by the three parameters).  Only the report times
  are recorded.
* The filters are independent: on two cores or more a forked process
  builds and sweeps about half of them (:meth:`ZuptSetup.filter_shares`; the truth
  copy stays in this process) while this one does the rest; the numbers
  are the same as in one process (one BLAS thread each, the same calls).
* Errors at each report time: horizontal RMS ``sqrt(σ_N² + σ_E²)`` and
  altitude RMS ``σ_D`` (the paper's "RMS navigation error"), plus CEP, PE and
  azimuth.  Fits, sensitivities and figures use the last report time.
* Fit: ``log10 e = Σ_k c_k (log10 s)^k`` by least squares
  (:func:`covtool.analysis.sensitivity.fit_loglog`).
* Sensitivity (primary): ``max(e(s_max), e(s_min))/e(1) − 1``; the ratio of
  the largest filter's (58-state A) sensitivity to each reduced filter's is
  the paper's "about 2×" comparison (``sensitivity_ratio`` table).
* Cost: closed-form FLOPs of one on-board cycle (:mod:`covtool.analysis.cost`),
  the measured numpy time per cycle, and the paper's 8086/8087 seconds.

Discretisation.  ``[sweep] discretization`` overrides the filters' declared
method for the whole sweep (``"declared"`` keeps it).  When a filter has
exactly the truth's F and Q_c and the same method as the truth (filter A
with ``[study] discretization = "taylor"`` and the declared Taylor series, or
both Van Loan), its Φ_f, Q_f are taken from the truth's instead of being
recomputed: an identity, checked element by element.  The shipped study
discretises the truth by the adaptive eq (6b)-(6d) series (converged to
1e-16), half the cost of Van Loan; its errors agree with the flagship's Van
Loan truth to about 1e-11 (tested to 1e-8).
"""

from __future__ import annotations

import time
from functools import partial
import warnings

import numpy as np
import pandas as pd

from covtool.analysis.cost import cycle_flops, PAPER_TABLE4_SECONDS, power_law, taylor_terms, time_cycle
from covtool.analysis.metrics import first_invalid, nav_metrics, validity_text
from covtool.analysis.sensitivity import (fit_loglog, LogLogFit, PARAMETERS, run_sweep, scale_grid,
                                          sensitivity_figures, sweep_cases)
from covtool.errors import FlaggedCaseWarning, StudyFileError
from covtool.io.config import boolean, check_keys, choice, integer, LIMITS, names, number, table
from covtool.lincov.batch import events
from covtool.lincov.reduced import zupt_matrices
from covtool.plotting.sensitivity import fig8_figure
from covtool.results import ZuptSensitivityResult
from covtool.studies.inputs import length_unit, LENGTH_UNITS, study_inputs
from covtool.studies.resources import composed_memory_estimate, noise_columns, progress_bar, resource_provenance
from covtool.studies.tables import case_validity
from covtool.studies.zupt_setup import setup
from covtool.forked import can_split, Forked
from covtool.units import ARCMIN, FT


SWEEP_KEYS = {"parameters", "scales", "fit_degree", "discretization"}
COST_KEYS = {"measure", "repeats", "taylor_order", "paper_seconds"}
METRICS = {"horizontal": ("horizontal RMS", "sigma_horizontal"), "altitude": ("altitude RMS", "sigma_down")}
PARAM_LABEL = {"P0": "P_f(0)", "Q": "Q_f", "R": "R_f"}
#: every n-th step on which the adaptive Taylor term count is evaluated (``taylor_order = "auto"``)
TAYLOR_STRIDE = 10
#: shortest timeit repeat of the on-board cycle [s]: the median of 7 such repeats varies as much from one
#: call to the next at 2 ms as at 5 ms on the 2-core machine (interquartile range 3-13 % of the median over
#: 15 calls, filters A, B1 and D, against 5-40 %), at 40 % of the time (0.03 s per filter instead of 0.065)
CYCLE_MIN_TIME = 0.002


def _scale_end(v, w) -> float:
    b = LIMITS["filter_scale"]
    return number(v, w, StudyFileError, lo=b.lo, hi=b.hi, why=b.reason)


def sweep_options(cfg: dict, where: str) -> dict:
    """Validate ``[sweep]`` and return its resolved options."""
    w = f"{where}: [sweep]"
    table(cfg, w, StudyFileError)
    check_keys(cfg, SWEEP_KEYS, w, StudyFileError)
    params = names(cfg.get("parameters", list(PARAMETERS)), f"{w} parameters", StudyFileError,
                   known=list(PARAMETERS), what="parameter")
    sc = table(cfg.get("scales", {"from": 0.01, "to": 100, "per_decade": 4}), f"{w} scales", StudyFileError)
    check_keys(sc, {"from", "to", "per_decade"}, f"{w} scales", StudyFileError)
    for k in ("from", "to", "per_decade"):
        if k not in sc:
            raise StudyFileError(f"{w} scales", f"missing key {k!r}")
    lo, hi = _scale_end(sc["from"], f"{w} scales from"), _scale_end(sc["to"], f"{w} scales to")
    per = integer(sc["per_decade"], f"{w} scales per_decade", StudyFileError, limit="per_decade")
    points = per * np.log10(hi / lo) + 1 if hi >= lo else 0
    if points > LIMITS["sweep_points"].hi:
        raise StudyFileError(f"{w} scales", f"{points:.0f} scales; at most {LIMITS['sweep_points'].hi:g} "
                             f"({LIMITS['sweep_points'].reason})")
    try:
        scales = scale_grid(lo, hi, per)
    except ValueError as exc:
        raise StudyFileError(f"{w} scales", str(exc)) from None
    deg = integer(cfg.get("fit_degree", 5), f"{w} fit_degree", StudyFileError, limit="fit_degree")
    if scales.size < deg + 2:
        raise StudyFileError(f"{w} fit_degree", f"a degree-{deg} fit needs at least {deg + 2} scales "
                             f"(the grid has {scales.size}); add points per decade or lower the degree")
    disc = choice(cfg.get("discretization", "declared"), ("declared", "van_loan", "taylor"),
                  f"{w} discretization", StudyFileError)
    return {"parameters": tuple(params), "scales": scales, "per_decade": per, "fit_degree": deg,
            "discretization": disc}


def cost_options(cfg: dict, where: str) -> dict:
    """Validate ``[cost]`` (filter names are checked after setup)."""
    w = f"{where}: [cost]"
    table(cfg, w, StudyFileError)
    check_keys(cfg, COST_KEYS, w, StudyFileError)
    measure = boolean(cfg.get("measure", True), f"{w} measure", StudyFileError)
    rep = integer(cfg.get("repeats", 7), f"{w} repeats", StudyFileError, limit="repeats")
    order = cfg.get("taylor_order", "auto")
    lim = LIMITS["taylor_order"]
    if order != "auto" and (type(order) is not int or not lim.lo <= order <= lim.hi):
        raise StudyFileError(f"{w} taylor_order", f"{order!r} is not 'auto' or an integer in {lim.lo}..{lim.hi} "
                             f"({lim.reason})")
    paper = table(cfg.get("paper_seconds", dict(PAPER_TABLE4_SECONDS)), f"{w} paper_seconds",
                  StudyFileError)
    for k, v in paper.items():
        number(v, f"{w} paper_seconds {k}", StudyFileError, lo=0.0, lo_open=True)
    return {"measure": measure, "repeats": rep, "taylor_order": order, "paper_seconds": dict(paper)}


def _memory(n_cases: int):
    """What a sweep of ``n_cases`` cases per filter holds at its peak (an upper estimate).

    The truth's and the filters' systems are made chunk by chunk and composed
    on the events (:meth:`~covtool.studies.zupt_setup.ZuptSetup.composed_filter`)
    in this process and the forked one
    (:func:`~covtool.studies.resources.composed_memory_estimate`).
    """

    def memory(steps, truth, filters, dynamics, *, records=None, intervals=None, shared=0, distinct=None,
               updates=0, reports=1):
        own = list(filters if distinct is None else distinct)
        return composed_memory_estimate(steps, truth.n, filters=own, dynamics=dynamics, noise=noise_columns(truth),
                                        updates=updates, reports=reports, batch=n_cases, processes=2)

    memory.records = True           # setup() passes the record and interval counts, and the updates
    memory.updates = True
    return memory


def run(decl: dict, *, path=None, progress: bool = False, config=None) -> ZuptSensitivityResult:
    """Run the sensitivity / compute-cost trade (module docstring)."""
    t_start, c_start = time.perf_counter(), time.process_time()
    where = str(path) if path else "<study>"
    sw = sweep_options(decl.get("sweep", {}), where)
    co = cost_options(decl.get("cost", {}), where)
    if isinstance(decl.get("filters", {}), dict) and "pure_ins" in decl.get("filters", {}):
        raise StudyFileError(f"{where}: [filters] pure_ins", "not used by a zupt_sensitivity study; remove it")
    timing = {}
    tic = time.perf_counter()
    cases = sweep_cases(sw["parameters"], sw["scales"])
    S = setup(decl if config is None else config, path=path, progress=progress, extra_sections=("sweep", "cost"),
              memory=_memory(cases.n_cases))
    timing["setup (trajectory, truth Phi/Qd)"] = time.perf_counter() - tic
    for k in co["paper_seconds"]:
        if k not in S.specs:
            raise StudyFileError(f"{where}: [cost] paper_seconds {k}",
                                 f"unknown filter {k!r} (declared in {', '.join(map(str, S.filter_files))}: {', '.join(S.specs)})")
    t = S.t
    N = t.size - 1
    rec = sorted({int(np.argmin(np.abs(t - tr))) for tr in S.report_times})
    # the events (ZUPTs, report times) and the stream's chunk boundaries: the truth's and every filter's
    # Φ, Q_d exist one chunk at a time, composed on these events as they are made (ZuptSetup.composed_truth)
    ev = S.stream_grid(events(N, S.update_steps, rec))
    tic = time.perf_counter()
    truth_sys = S.composed_truth(ev)
    timing["compose truth"] = time.perf_counter() - tic
    B = cases.n_cases
    results, fmodels, reused, statuses = {}, {}, {}, {}
    # summed over the filters, in whichever process each ran (CPU-like: more than the wall time when forked)
    timing.update({"filter systems (made and composed chunk by chunk)": 0.0, "batched runs": 0.0})

    sweep = partial(_sweep_filters, S, sw=sw, co=co, truth_sys=truth_sys, ev=ev, rec=rec, cases=cases, where=where)
    # the filters' builds and sweeps are independent: a forked process takes about half of them while
    # this one does the rest (each filter's numbers are the same wherever it runs: one BLAS thread)
    forked, own = S.filter_shares(S.cases) if can_split() else ([], list(S.cases))
    job = Forked(sweep, forked) if forked else None
    with progress_bar(len(S.cases), "filters", progress) as bar:
        done = sweep(own, bar=bar)
        if job is not None:
            done |= job.result()
            bar.update(len(forked))
    cost_inputs = {}
    for c in S.cases:                                        # in the declared order
        fmodels[c], reused[c], results[c], statuses[c], dts, cost_inputs[c] = done[c]
        for key, dt_ in zip(("filter systems (made and composed chunk by chunk)", "batched runs"), dts):
            timing[key] += dt_
    t_sweep, c_sweep = time.perf_counter() - t_start, time.process_time() - c_start

    tic = time.perf_counter()
    cost_rows = _cost(S, fmodels, co, cost_inputs)
    timing["compute-cost (FLOPs, timing)"] = time.perf_counter() - tic

    tic = time.perf_counter()
    rt = [t[k] for k in rec]
    _warn(cases, results, statuses, rt)
    # [output] units: the fits, their table and the Fig 8 sheets and figures in the chosen length unit
    unit = length_unit(decl if config is None else config, where)
    sweep_df, fits = _sweep_table(S, cases, results, fmodels, rt, sw["fit_degree"], statuses, unit)
    fits_df = _fits_table(fits, sw["fit_degree"], unit)
    sens_df = _sensitivity_table(cases, results, fits, fmodels)
    ratio_df = _ratio_table(sens_df, fmodels)
    cost_df, scaling_df = _cost_tables(cost_rows)
    summary = _summary(S, cases, results, fmodels, sens_df, cost_df, rt, statuses)
    fine = scale_grid(cases.scales[0], cases.scales[-1], 2 * sw["per_decade"])
    chart_sheets, charts = _chart_sheets(cases, results, fits, fine, unit)
    timing["tables and fits"] = time.perf_counter() - tic
    elapsed = time.perf_counter() - t_start

    tables = {"summary": summary, "sweep": sweep_df, "fits": fits_df, "sensitivity": sens_df,
              "sensitivity_ratio": ratio_df, "cost": cost_df, "cost_scaling": scaling_df, **chart_sheets}
    tables["timing"] = pd.DataFrame({"phase": list(timing), "wall time [s]": list(timing.values())})
    provenance = {
        **study_inputs(path, decl, S.truth, S.filter_files), "truth_model": S.truth.name,
        "truth_model_sha256": S.truth.sha256, **resource_provenance(S.resources),
        "zupt_updates": int(len(S.update_steps)), "zupt_interval_s": S.zupt_interval,
        "zupt_sigma_m_s": S.zupt_sigma, "truth_discretization": S.hdr["discretization"],
        "filter_discretization": sw["discretization"],
        "filters_swept_in_a_forked_process": ", ".join(forked) or "none",
        "filters_reusing_truth_phi_qd": ", ".join(c for c, r in reused.items() if r) or "none",
        "sweep_scales": ", ".join(f"{s:.6g}" for s in cases.scales), "batched_cases_per_filter": B,
        "fit_model": f"log10(error [{unit}]) = sum_k c_k log10(scale)^k, k = 0..{sw['fit_degree']}, least squares",
        "sensitivity_definition": "max(e(s_max), e(s_min)) / e(1) - 1 at the last report time",
        "blas_threads": 1, "sweep_seconds": f"{t_sweep:.2f}", "sweep_cpu_seconds": f"{c_sweep:.2f}",
        "compute_seconds": f"{elapsed:.2f}",
    }
    result = ZuptSensitivityResult(
        name=S.hdr["name"], kind="zupt_sensitivity", tables=tables,
        resolved={**decl, "study": {**decl["study"], "name": S.hdr["name"]}}, provenance=provenance,
        charts=charts,
        filter_models=fmodels, setup=S,
        scales=np.asarray(cases.scales), parameters=list(cases.parameters), filters=list(results),
        curves={(c, p, m): _curve(cases, results, c, p, m) for c in results for p in cases.parameters
                for m in METRICS},
        fits=fits, report_time=rt[-1], length_unit=unit,
        labels={"metrics": {m: v[0] for m, v in METRICS.items()}, "params": dict(PARAM_LABEL)})
    result.figures = {"fig8_1_horizontal": partial(fig8_figure, result, "horizontal"),
                      "fig8_2_altitude": partial(fig8_figure, result, "altitude")}
    return result


def _curve(cases, results, c, p, metric, j=-1):
    """Error [m] of filter ``c`` along ``p``'s sweep at report ``j``."""
    i = cases.parameters.index(p)
    return results[c][0][METRICS[metric][1]][cases.index[i], j]


def _warn(cases, results, statuses, rt):
    """One warning per filter for its flagged cases and for the nominal case's validity."""
    labels = cases.labels()
    for c, st in statuses.items():
        bad = [b for b, s in enumerate(st) if s]
        if bad:
            warnings.warn(f"{len(bad)} of {len(st)} cases of filter {c} failed the covariance guard; their "
                          f"numbers are NaN (status column): {', '.join(labels[b] for b in bad[:5])}"
                          f"{' …' if len(bad) > 5 else ''}; first: {st[bad[0]]}", FlaggedCaseWarning, stacklevel=3)
        case_validity(f"filter {c} (nominal tuning)", {k: v[0] for k, v in results[c][0].items()}, rt)


def _fit(scales, err, degree):
    """:func:`fit_loglog` on the finite points (a flagged case is NaN); NaN if too few remain."""
    ok = np.isfinite(err) & (err > 0)
    if ok.sum() < degree + 1:
        nan = float("nan")
        return LogLogFit(np.full(degree + 1, nan), nan, nan, nan)
    return fit_loglog(scales[ok], err[ok], degree)


def _sweep_table(S, cases, results, fmodels, rt, degree, statuses, unit="ft"):
    rows, fits = [], {}
    lu = LENGTH_UNITS[unit]
    last = len(rt) - 1
    for c, (mt, mf) in results.items():
        first = [first_invalid({k: v[b] for k, v in mt.items()}, rt) for b in range(cases.n_cases)]
        for i, p in enumerate(cases.parameters):
            idx = cases.index[i]
            for metric in METRICS:
                fits[(c, p, metric)] = _fit(cases.scales, _curve(cases, results, c, p, metric) / lu, degree)
            for j, tr in enumerate(rt):
                for s, b in zip(cases.scales, idx):
                    row = {"filter": c, "states [-]": fmodels[c].spec.n, "parameter": p, "scale [-]": s,
                           "log10 scale [-]": np.log10(s), "t [min]": tr / 60.0,
                           "horizontal RMS [ft]": mt["sigma_horizontal"][b, j] / FT,
                           "altitude RMS [ft]": mt["sigma_down"][b, j] / FT,
                           "horizontal RMS [m]": mt["sigma_horizontal"][b, j],
                           "altitude RMS [m]": mt["sigma_down"][b, j],
                           "CEP [ft]": mt["cep"][b, j] / FT, "alt PE [ft]": mt["alt_pe"][b, j] / FT,
                           "azimuth 1sigma [arcmin]": mt["sigma_azimuth"][b, j] / ARCMIN,
                           "filter-claimed horizontal RMS [ft]": mf["sigma_horizontal"][b, j] / FT,
                           "filter-claimed altitude RMS [ft]": mf["sigma_down"][b, j] / FT}
                    for metric, (label, _) in METRICS.items():
                        row[f"fitted {label} [{unit}]"] = float(fits[(c, p, metric)](s)) if j == last else np.nan
                    row["validity"] = validity_text(first[b], until=tr)
                    row["status"] = statuses[c][b] or "ok"
                    rows.append(row)
    return pd.DataFrame(rows), fits


def _fits_table(fits, degree, unit="ft"):
    rows = []
    for (c, p, metric), f in fits.items():
        row = {"filter": c, "parameter": p, "metric": METRICS[metric][0], "degree [-]": f.degree}
        for k in range(degree + 1):
            row[f"c{k} [log10 {unit}]" if k == 0 else f"c{k} [-]"] = f.coef[k] if k < f.coef.size else 0.0
        row.update({"residual RMS [dex]": f.resid_rms, "residual RMS [%]": 100 * np.log(10) * f.resid_rms,
                    "max |residual| [dex]": f.max_abs_resid, "R2 [-]": f.r2})
        rows.append(row)
    return pd.DataFrame(rows)


def _sensitivity_table(cases, results, fits, fmodels):
    rows = []
    s = cases.scales
    for c in results:
        for p in cases.parameters:
            for metric, (label, _) in METRICS.items():
                e = _curve(cases, results, c, p, metric) / FT
                fig = sensitivity_figures(s, e)
                f = fits[(c, p, metric)]
                fe = f(np.array([s[0], 1.0, s[-1]]))
                rows.append({"filter": c, "states [-]": fmodels[c].spec.n, "parameter": p, "metric": label,
                             f"error at x{s[0]:g} [ft]": fig["low"], "error at x1 [ft]": fig["nominal"],
                             f"error at x{s[-1]:g} [ft]": fig["high"],
                             f"relative error at x{s[0]:g} [-]": fig["rel_low"],
                             f"relative error at x{s[-1]:g} [-]": fig["rel_high"],
                             "sensitivity [-]": fig["primary"],
                             "sensitivity from fit [-]": max(fe[0], fe[2]) / fe[1] - 1.0,
                             "mean |dlog e/dlog s| [-]": fig["mean_log_slope"]})
    return pd.DataFrame(rows)


def _ratio_table(sens, fmodels):
    """Largest filter's sensitivity over each smaller filter's.

    The paper's "about 2×" comparison.
    """
    ref = max(fmodels, key=lambda c: fmodels[c].spec.n)
    rows = []
    for (p, metric), g in sens.groupby(["parameter", "metric"], sort=False):
        g = g.set_index("filter")
        for c in g.index:
            if fmodels[c].spec.n >= fmodels[ref].spec.n:
                continue
            sr, sc = g.loc[ref, "sensitivity [-]"], g.loc[c, "sensitivity [-]"]
            lr, lc = g.loc[ref, "mean |dlog e/dlog s| [-]"], g.loc[c, "mean |dlog e/dlog s| [-]"]
            rows.append({"parameter": p, "metric": metric, "reference": ref, "filter": c,
                         "states [-]": fmodels[c].spec.n, f"sensitivity {ref} [-]": sr, "sensitivity [-]": sc,
                         f"ratio {ref}/filter [x]": _ratio(sr, sc),
                         f"mean-slope ratio {ref}/filter [x]": _ratio(lr, lc),
                         "paper ratio [x]": 2.0})
    for metric, g in sens.groupby("metric", sort=False):
        worst = g.groupby("filter", sort=False)["sensitivity [-]"].max(skipna=False)
        slope = g.groupby("filter", sort=False)["mean |dlog e/dlog s| [-]"].max(skipna=False)
        for c in worst.index:
            if fmodels[c].spec.n >= fmodels[ref].spec.n:
                continue
            rows.append({"parameter": "max(" + ",".join(g["parameter"].unique()) + ")", "metric": metric,
                         "reference": ref, "filter": c, "states [-]": fmodels[c].spec.n,
                         f"sensitivity {ref} [-]": worst[ref], "sensitivity [-]": worst[c],
                         f"ratio {ref}/filter [x]": _ratio(worst[ref], worst[c]),
                         f"mean-slope ratio {ref}/filter [x]": _ratio(slope[ref], slope[c]),
                         "paper ratio [x]": 2.0})
    return pd.DataFrame(rows)


def _ratio(a, b):
    """``a/b``; inf for a zero ``b``, NaN if either is NaN (a flagged case)."""
    if not (np.isfinite(a) and np.isfinite(b)):
        return np.nan
    return a / b if b > 0 else np.inf


def _sweep_filters(S, names, *, sw, co, truth_sys, ev, rec, cases, where, bar=None) -> dict:
    """Build and sweep each filter of ``names`` (:func:`covtool.analysis.sensitivity.run_sweep`).

    Returns
    -------
    dict of str to tuple
        Per filter ``(FilterModel, reused, (truth metrics, filter metrics),
        status, (filter systems, sweep seconds), cost inputs)``; the
        metrics are arrays of shape (B, n_report), the cost inputs those of
        :func:`_cost` (:meth:`_CostScan.inputs`).
    """
    B, nr, t, nodes = cases.n_cases, len(rec), S.t, S.nodes
    lat, h, q = nodes.lat[rec], nodes.h[rec], nodes.q_nb[rec]

    def rep(a):
        return np.broadcast_to(a, (B,) + a.shape).reshape((B * nr,) + a.shape[1:])

    out = {}
    # every filter's Φ_f, Q_f made and composed chunk by chunk, together (the models' and the compositions'
    # seconds shared evenly); the cost inputs are gathered from the same chunks' F_f, Q_c,f
    tic = time.perf_counter()
    scans = {c: _CostScan(S, S.specs[c], co) for c in names}
    systems = S.composed_filters(names, ev, sw["discretization"], truth=truth_sys,
                                 on_chunk={c: v for c, v in scans.items() if v.needed})
    t_model = (time.perf_counter() - tic) / max(1, len(names))
    for c in names:
        scan = scans[c]
        fm, filt, reused_c = systems[c]
        tic = time.perf_counter()
        res = run_sweep(truth_sys, S.P0, S.H, S.R, fm.D, filt, fm.P0, zupt_matrices(fm.names),
                        S.filter_R(c), cases, S.update_steps, rec, form=fm.spec.update,
                        label=f"{where}: sweep of filter {c}", names=S.truth.names, filter_names=fm.names,
                        times=t)
        toc = time.perf_counter()
        mt = nav_metrics(res.P_truth.reshape(B * nr, 10, 10), rep(lat), rep(h), rep(q))
        mf = nav_metrics(res.P_filter.reshape(B * nr, 10, 10), rep(lat), rep(h), rep(q))
        metrics = ({k: v.reshape(B, nr) for k, v in mt.items()}, {k: v.reshape(B, nr) for k, v in mf.items()})
        out[c] = (fm, reused_c, metrics, res.status, (t_model, toc - tic), scan.inputs())
        if bar is not None:
            bar.update(1)
    return out


class _CostScan:
    """The inputs of :func:`_cost` for one filter, gathered chunk by chunk (``on_chunk`` of
    :meth:`~covtool.studies.zupt_setup.ZuptSetup.composed_filter`).

    ``order``: the declared Taylor order, or (``taylor_order = "auto"``) the
    most terms the adaptive eq (6b)–(6d) series takes on every
    :data:`TAYLOR_STRIDE`-th grid step; ``step``: the first step of the
    largest ``‖F_f‖₁`` (the cycle timed, :func:`covtool.analysis.cost.time_cycle`),
    with its F_f and Q_c,f.  The same values as over the whole-grid stacks.
    """

    def __init__(self, S, spec, co):
        self.declared = spec.taylor_order if co["taylor_order"] == "auto" else co["taylor_order"]
        self.auto = co["taylor_order"] == "auto" and not spec.taylor_order
        self.measure = co["measure"]
        self.needed = self.auto or self.measure
        self.dt = np.diff(S.t)
        self.terms, self.norm, self.step, self.F, self.Qc = 0, -np.inf, 0, None, None

    def __call__(self, a: int, F: np.ndarray, Qc: np.ndarray) -> None:
        L = F.shape[0]
        if self.auto:
            first = (-a) % TAYLOR_STRIDE                      # the stride counted from step 0 of the grid
            if first < L:
                sl = slice(first, L, TAYLOR_STRIDE)
                self.terms = max(self.terms, taylor_terms(F[sl], Qc[sl], self.dt[a:a + L][sl],
                                                          steps=np.arange(a + first, a + L, TAYLOR_STRIDE)))
        if self.measure:
            norms = np.linalg.norm(F, 1, axis=(1, 2))
            j = int(np.argmax(norms))
            if norms[j] > self.norm:                          # strictly: the first largest, as argmax over the grid
                self.norm, self.step, self.F, self.Qc = float(norms[j]), a + j, F[j].copy(), Qc[j].copy()

    def inputs(self) -> tuple:
        """``(order, step, F_f[step], Q_c,f[step])`` (the last two None when the cycle is not timed)."""
        return int(self.terms if self.auto else self.declared), self.step, self.F, self.Qc


def _cost(S, fmodels, co, inputs) -> dict:
    """Table 4 inputs per filter: FLOPs of one on-board cycle and its measured time (``inputs``: :class:`_CostScan`)."""
    m = S.H.shape[0]
    out = {}
    for c, fm in fmodels.items():
        n = fm.spec.n
        order, k, Fk, Qk = inputs[c]
        fl = cycle_flops(n, m, order, fm.spec.update)
        sec = np.nan
        if co["measure"]:
            sec = time_cycle(Fk, Qk, float(S.t[k + 1] - S.t[k]), fm.P0, zupt_matrices(fm.names),
                             S.filter_R(c), order, fm.spec.update, repeats=co["repeats"], min_time=CYCLE_MIN_TIME)
        out[c] = {"n": n, "m": m, "order": order, "form": fm.spec.update, "flops": fl, "seconds": sec,
                  "flops2": cycle_flops(n, m, 2, fm.spec.update)["total"],
                  "paper": co["paper_seconds"].get(c, np.nan)}
    return out


def _cost_tables(cost):
    rows = []
    ref = [c for c, v in cost.items() if np.isfinite(v["paper"])]
    ref = min(ref, key=lambda c: cost[c]["n"]) if ref else min(cost, key=lambda c: cost[c]["n"])
    for c, v in cost.items():
        fl = v["flops"]
        rows.append({"filter": c, "states [-]": v["n"], "measurements m [-]": v["m"],
                     "Taylor terms N_t [-]": v["order"], "update form": v["form"],
                     "Phi_f eq (6b) [FLOP]": fl["phi"], "Q_f eq (6c-6d) [FLOP]": fl["qd"],
                     "propagation eq (6a) [FLOP]": fl["propagation"], "gain eq (7) [FLOP]": fl["gain"],
                     "update [FLOP]": fl["update"], "total [FLOP/cycle]": fl["total"],
                     "measured [us/cycle]": v["seconds"] * 1e6,
                     "measured rate [GFLOP/s]": fl["total"] / v["seconds"] / 1e9,
                     "paper 8086/8087 [s/cycle]": v["paper"],
                     f"FLOP ratio to {ref} [x]": fl["total"] / cost[ref]["flops"]["total"],
                     f"paper time ratio to {ref} [x]": v["paper"] / cost[ref]["paper"],
                     f"(n/n_{ref})^3 [x]": (v["n"] / cost[ref]["n"]) ** 3,
                     "paper time / n^3 [us]": v["paper"] / v["n"] ** 3 * 1e6,
                     "implied 8087 rate [kFLOP/s]": fl["total"] / v["paper"] / 1e3,
                     "total at N_t = 2 [FLOP/cycle]": v["flops2"],
                     "implied 8087 rate at N_t = 2 [kFLOP/s]": v["flops2"] / v["paper"] / 1e3})
    df = pd.DataFrame(rows)
    cols = ["quantity", "exponent p [-]", "coefficient a [unit of quantity]"]
    srows = []

    def law(label, names, y):
        if len({cost[c]["n"] for c in names}) >= 2:
            p, a = power_law([cost[c]["n"] for c in names], [y(c) for c in names])
            srows.append(dict(zip(cols, (label, p, a))))

    have = [c for c, v in cost.items() if np.isfinite(v["paper"])]
    law("FLOPs/cycle (all filters)", list(cost), lambda c: cost[c]["flops"]["total"])
    law("FLOPs/cycle (filters in the paper's Table 4)", have, lambda c: cost[c]["flops"]["total"])
    law("FLOPs/cycle at N_t = 2 (filters in the paper's Table 4)", have, lambda c: cost[c]["flops2"])
    law("paper 8086/8087 time [s] (Table 4)", have, lambda c: cost[c]["paper"])
    law("measured numpy time [s] (this machine)", [c for c in cost if np.isfinite(cost[c]["seconds"])],
        lambda c: cost[c]["seconds"])
    return df, pd.DataFrame(srows, columns=cols)


def _summary(S, cases, results, fmodels, sens, cost_df, rt, statuses):
    rows = []
    nom = 0                                         # the shared nominal case
    cost_i = cost_df.set_index("filter")
    for c, (mt, _) in results.items():
        row = {"filter": c, "states [-]": fmodels[c].spec.n, "t [min]": rt[-1] / 60.0,
               "CEP [ft]": mt["cep"][nom, -1] / FT, "alt PE [ft]": mt["alt_pe"][nom, -1] / FT,
               "azimuth 1sigma [arcmin]": mt["sigma_azimuth"][nom, -1] / ARCMIN,
               "horizontal RMS [ft]": mt["sigma_horizontal"][nom, -1] / FT,
               "altitude RMS [ft]": mt["sigma_down"][nom, -1] / FT}
        g = sens[sens["filter"] == c].set_index(["metric", "parameter"])["sensitivity [-]"]
        for metric, (label, _) in METRICS.items():
            for p in cases.parameters:
                row[f"sensitivity {metric} {p} [-]"] = g.loc[(label, p)]
            row[f"max sensitivity {metric} [-]"] = float(np.max([g.loc[(label, p)] for p in cases.parameters]))
        row["FLOPs/cycle [FLOP]"] = cost_i.loc[c, "total [FLOP/cycle]"]
        row["measured [us/cycle]"] = cost_i.loc[c, "measured [us/cycle]"]
        row["paper 8086/8087 [s/cycle]"] = cost_i.loc[c, "paper 8086/8087 [s/cycle]"]
        row["validity"] = validity_text(first_invalid({k: v[nom] for k, v in mt.items()}, rt))
        bad = [s for s in statuses[c] if s]
        row["status"] = (f"{len(bad)} of {len(statuses[c])} sweep cases flagged (NaN); first: {bad[0]}"
                         if bad else "ok")
        rows.append(row)
    return pd.DataFrame(rows)


def _chart_sheets(cases, results, fits, fine, unit="ft"):
    """Wide sheets and specs for the native Fig 8 charts (log-log, as the PNGs).

    The fitted curves fill a grid twice as fine (``scale [-]``); the swept
    points are listed at their own scales (``swept scale [-]``) in the first
    rows, so that every charted cell holds a number and a log axis never
    meets a text cell.  One series per filter and kind (points, fit).
    """
    sheets, charts = {}, []
    n = len(cases.scales)
    lu = LENGTH_UNITS[unit]

    def pad(v):
        out = np.full(fine.size, np.nan)
        out[:n] = v
        return out

    for num, metric in ((1, "horizontal"), (2, "altitude")):
        label = METRICS[metric][0]
        name = f"fig8_{num}_{metric}"
        df = pd.DataFrame({"scale [-]": fine, "swept scale [-]": pad(cases.scales)})
        for p in cases.parameters:
            for c in results:
                df[f"{p} {c} swept [{unit}]"] = pad(_curve(cases, results, c, p, metric) / lu)
                df[f"{p} {c} fit [{unit}]"] = fits[(c, p, metric)](fine)
        sheets[name] = df
        for k, p in enumerate(cases.parameters):
            ys = [f"{p} {c} {kind} [{unit}]" for c in results for kind in ("swept", "fit")]
            series = {f"{p} {c} swept [{unit}]": {"x": "swept scale [-]", "rows": n, "marker": "circle", "line": False}
                      for c in results}
            charts.append({"sheet": name, "x": "scale [-]", "y": ys, "log_x": True, "log_y": True,
                           "series": series,
                           "title": f"Fig 8.{num} ({PARAM_LABEL[p]}): {label} vs scale (points: swept, "
                                    f"lines: fit)",
                           "x_title": f"{PARAM_LABEL[p]} scale [-]", "y_title": f"{label} [{unit}]",
                           "anchor": f"A{fine.size + 4 + 20 * k}"})
    return sheets, charts
