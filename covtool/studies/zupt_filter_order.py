"""ZUPT filter-order trade: reduced filters run against the truth (seed 002, §3.1).

Study file::

    [study]
    kind = "zupt_filter_order"
    duration = "30 min"
    dt = "1 s"

    [trajectory]
    builtin = "land_vehicle"

    [truth]
    model = "sdins58"

    [filters]
    file = "../models/filters/zupt_filters.toml"   # default: the library's
    cases = ["A", "B1", "B2", "B3", "C", "D"]
    pure_ins = true

    [zupt]
    interval = "5 min"       # Δt_s: a ZUPT stop every interval (eq (12)-(13))
    duration = "30 s"        # measurement window ending at each k·interval
    rate = "1 Hz"            # updates per second inside the window
    sigma = "0.01 ft/s"      # true ZUPT noise 1σ per axis (R); filters may assume another

    [impact]                 # dropped-state impact table (covtool.lincov.impact)
    filters = ["B1", "C", "D"]   # default: every reduced filter of the run; [] for none
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np
import pandas as pd

from covtool.analysis.metrics import nav_metrics
from covtool.errors import StudyFileError
from covtool.forked import Forked
from covtool.io.config import check_keys
from covtool.lincov.impact import check_filter_noise
from covtool.lincov.kalman import running_scale
from covtool.lincov.reduced import ewn_navigation_effect, zupt_matrices
from covtool.lincov.batch import BatchRun, events
from covtool.plotting.zupt_filter_order import impact_figure
from covtool.lincov.history import CovarianceHistory
from covtool.plotting.navigation import error_history_figure
from covtool.results import ZuptFilterOrderResult
from covtool.studies.grid import record_steps  # noqa: F401  (also imported from here: benchmarks, tests)
from covtool.studies.inputs import length_unit, study_inputs
from covtool.studies.resources import progress_bar, resource_provenance
from covtool.studies.tables import case_validity, history_frame, summary_row
from covtool.studies.zupt_setup import order_memory, setup, ZuptSetup
from covtool.units import ARCMIN, FT, si_unit


def run(decl: dict, *, path=None, progress: bool = False, config=None) -> ZuptFilterOrderResult:
    """Run the filter-order trade; see the module docstring."""
    t_start = time.perf_counter()
    pure = (decl.get("filters") or {}).get("pure_ins", True) if isinstance(decl.get("filters", {}), dict) else True
    imp = decl.get("impact")
    listed = imp.get("filters") if isinstance(imp, dict) else None          # validated below (impact_filters)
    S = setup(decl if config is None else config, path=path, progress=progress, extra_sections=("impact",),
              memory=order_memory(pure is not False, len(listed) if isinstance(listed, list) else True),
              shrink="a larger [study] dt, a shorter duration, fewer [filters] cases or fewer [impact] filters")
    imp_filters = impact_filters(decl, S)
    hdr, t, nodes, truth = S.hdr, S.t, S.nodes, S.truth
    P0, H, R, upd = S.P0, S.H, S.R, S.update_steps
    cases, every, rtimes, ffile = S.cases, S.every, S.report_times, S.filter_files
    dt_s, zsig, mean_speed = S.zupt_interval, S.zupt_sigma, S.mean_speed
    fcfg = decl.get("filters", {})
    metrics, runs, fmodels, claimed, claimed_hist = {}, {}, {}, {}, {}
    # the filter-claimed values are reported at the report times only: computed there (exact CEP is costly)
    rsteps = np.array([int(np.argmin(np.abs(t - tr))) for tr in rtimes], int)
    # what the outputs need, and only that: the navigation block at the history spacing and the report
    # times (batched engine, covtool.lincov.batch: Φ, Q_d composed between these events and the ZUPTs)
    rec = record_steps(t, every, rsteps)
    pos = np.searchsorted(rec, rsteps)                   # report steps in the record grid
    tr_ = t[rec]
    nav = (nodes.lat[rec], nodes.h[rec], nodes.q_nb[rec], nodes.distance[rec])
    # the event grid with the streaming chunks' boundaries (multiples of STREAM_CHUNK steps: numbers unchanged)
    ev = S.stream_grid(events(t.size - 1, upd, rec))
    where = S.where
    # the dropped-state impact (independent of the cases' runs) is shared with a forked process: it computes
    # its part while this one builds the filters and propagates the cases, then this one computes the rest.
    # Both read the truth's and the filters' systems chunk by chunk: over the whole grid where they fit
    # (order_memory's layout: the truth's built first, split between the two cores, and inherited; the stream
    # then slices them), else each process makes its own chunks.  The forked share leaves its filters' noise
    # checks to this process, which holds their systems (whole grid), or makes them itself (streamed)
    imp_job, imp_own = None, []
    whole = S.resources.get("layout", "whole grid") == "whole grid"
    if imp_filters:
        imp_forked, imp_own = impact_shares(S, imp_filters)
        if imp_forked:
            if whole:
                S.Phi
            imp_job = Forked(impact_runs, S, imp_forked, own_systems=not whole)
    if imp_filters and whole:
        for c in cases:
            S.filter_model(c)
    # every case (and the pure INS) advances chunk by chunk in time, carrying its full P and P_f across
    # the chunks: F, Q_c, Φ, Q_d and their composition exist for one chunk at a time (ZuptSetup.stream)
    pure_run = None
    if fcfg.get("pure_ins", True):
        pure_run = BatchRun(ev, truth.n, P0[None], H, R, np.zeros((truth.n, 0)), [], rec, running=False,
                            gains=np.zeros((1, 0, 0, H.shape[0])), label=f"{where}: pure INS", names=truth.names,
                            times=t)
    batches = {}
    for c in cases:
        fm, _ = S.filter_stream(c)
        batches[c] = BatchRun(ev, truth.n, P0[None], H, R, fm.D, upd, rec, running=True, Pf0=fm.P0[None],
                              Hf=zupt_matrices(fm.names), Rf=S.filter_R(c)[None], form=S.specs[c].update,
                              label=f"{where}: filter {c}", names=truth.names, filter_names=fm.names, times=t)
        fmodels[c] = fm
    N = t.size - 1
    with progress_bar(N, "propagation", progress) as bar:
        for tsys, fsys in S.stream(ev, cases):
            if pure_run is not None:
                pure_run.advance(tsys)
            for c in cases:
                batches[c].advance(tsys, fsys[c])
            bar.update(int(tsys.ev[-1] - tsys.ev[0]))
    P_pure = None
    if pure_run is not None:
        pure_run = pure_run.finish()
        P_pure = pure_run.P_truth[0]
        metrics["pure_ins"] = nav_metrics(P_pure, *nav)
    for c in cases:
        run_ = runs[c] = batches[c].finish()
        metrics[c] = nav_metrics(run_.P_truth[0], *nav)
        Pf = run_.P_filter[0]
        claimed_hist[c] = CovarianceHistory(tr_, run_.filter_names, Pf, t[upd], label="filter-claimed")
        claimed[c] = nav_metrics(Pf[pos], *(x[pos] for x in nav), scale=running_scale(Pf)[pos])
    elapsed = time.perf_counter() - t_start

    rows = []
    for case, m in metrics.items():
        first = case_validity(case, m, tr_)
        for j, tr in enumerate(rtimes):
            k = int(rsteps[j])
            row = summary_row(case, m, int(pos[j]), t[k], float(nodes.distance[k]), first=first)
            row["states"] = truth.n if case == "pure_ins" else fmodels[case].spec.n
            if case in claimed:
                row["filter-claimed CEP [ft]"] = claimed[case]["cep"][j] / FT
                row["filter-claimed alt PE [ft]"] = claimed[case]["alt_pe"][j] / FT
                row["filter-claimed azimuth [arcmin]"] = claimed[case]["sigma_azimuth"][j] / ARCMIN
            if "pure_ins" in metrics and case != "pure_ins":
                kr = int(pos[j])
                row["position improvement over pure INS [x]"] = metrics["pure_ins"]["cep"][kr] / m["cep"][kr]
                row["altitude improvement over pure INS [x]"] = metrics["pure_ins"]["alt_pe"][kr] / m["alt_pe"][kr]
            rows.append(row)
    summary = pd.DataFrame(rows)
    order = ["case", "states"] + [c for c in summary.columns if c not in ("case", "states")]
    summary = summary[order]

    hist = pd.concat([history_frame(c, tr_, m, every) for c, m in metrics.items()], ignore_index=True)
    ewn = equivalent_noise_table(S, fmodels)
    fstates = []
    for c, fm in fmodels.items():
        sig0 = np.sqrt(np.clip(np.diag(fm.P0), 0, None))
        for nm, s0 in zip(fm.names, sig0):
            st = truth.states[truth.index[nm]]
            fstates.append({"filter": c, "state": nm, "symbol": st.symbol, "unit": st.unit,
                            "P0 1sigma, SI value": s0, "SI unit": si_unit(st.unit), "process": st.process,
                            "options": f"coriolis={fm.spec.options.coriolis}, "
                                       f"vertical_coupled={fm.spec.options.couple_vertical}"})
    tables = {"summary": summary, "history": hist, "truth_states": truth.state_table(),
              "filter_states": pd.DataFrame(fstates)}
    if len(ewn):
        tables["equivalent_noise"] = ewn
    t_imp = 0.0
    if imp_filters:
        with progress_bar(len(imp_filters), "dropped-state impact", progress) as bar:
            own, t_own = impact_runs(S, imp_own) if imp_own else ([], 0.0)
            forked, t_imp = imp_job.result() if imp_job is not None else ([], 0.0)
            for r in forked:
                if np.isnan(r.noise_check):                  # its filter's own Φ_f, Q_f are held here
                    check_filter_noise(r, *S.filter_model(r.filter)[1:])
            by_name = {r.filter: r for r in forked + own}    # each run names its filter (the shares' own order)
            imp_runs, t_imp = [by_name[n] for n in imp_filters], t_imp + t_own
            tables["impact"] = impact_table(S, imp_filters, metrics, bar, runs=imp_runs, record_steps=rec)
    provenance = {**study_inputs(path, decl, truth, ffile), "truth_model": truth.name,
                  "truth_model_sha256": truth.sha256, "zupt_updates": int(len(upd)), "zupt_interval_s": dt_s,
                  "zupt_sigma_m_s": zsig, "mean_moving_speed_m_s": mean_speed, **resource_provenance(S.resources),
                  "compute_seconds": f"{elapsed:.2f}", "impact_compute_seconds": f"{t_imp:.2f}"}
    unit = length_unit(decl, where)
    histories = {}
    if "pure_ins" in metrics:
        histories["pure_ins"] = CovarianceHistory(tr_, pure_run.names, P_pure, label="pure INS").nav()
    for c, r_ in runs.items():
        histories[c] = CovarianceHistory(tr_, r_.names, r_.P_truth[0], t[upd], label="truth").nav()
    result = ZuptFilterOrderResult(
        name=hdr["name"], kind="zupt_filter_order", tables=tables,
        resolved={**decl, "study": {**decl["study"], "name": hdr["name"]}}, provenance=provenance,
        charts=[{"sheet": "history", "x": "t [min]", "y": [f"CEP [{unit}]"], "group": "case", "log_y": True,
                 "skip": 1, "title": "Fig 6: horizontal CEP by filter model", "x_title": "time [min]",
                 "y_title": f"horizontal CEP [{unit}]", "anchor": "S2"},
                {"sheet": "history", "x": "t [min]", "y": [f"alt PE [{unit}]"], "group": "case", "log_y": True,
                 "skip": 1, "title": "Fig 7: altitude PE by filter model", "x_title": "time [min]",
                 "y_title": f"altitude PE [{unit}]", "anchor": "S22"}],
        runs=runs, filter_models=fmodels, trajectory=nodes, record_steps=rec,
        times=tr_, metrics=metrics, length_unit=unit, update_times=t[upd], stops=S.stops,
        histories=histories, claimed=claimed_hist,
        claimed_metrics=claimed, report_times=list(rtimes))
    # the impact figure first: the longest to draw (0.5-0.8 s against 0.1-0.2 s), it is taken first from the
    # figure processes' queue (covtool.io.writers.draw_in_processes)
    result.figures = {"impact_dropped_states": partial(impact_figure, result)} if "impact" in tables else {}
    result.figures |= {"fig6_horizontal_cep": partial(error_history_figure, result, "horizontal"),
                       "fig7_altitude_pe": partial(error_history_figure, result, "altitude")}
    return result


def equivalent_noise_table(S: ZuptSetup, fmodels: dict) -> pd.DataFrame:
    """The ``equivalent_noise`` sheet: rule per dropped state and what it does to navigation.

    Each filter's rows of :attr:`FilterModel.ewn_table` (rule applied,
    pointwise overstatement) joined with
    :func:`covtool.lincov.reduced.ewn_navigation_effect` (the 1σ each dropped
    state's noise adds per ZUPT interval in tilt, azimuth, velocity and
    position, and its share).
    """
    frames = []
    for c, fm in fmodels.items():
        if not len(fm.ewn_table):
            continue
        Phi_f = S.filter_transitions(c)            # streamed by chunks unless the whole grid is built
        eff = ewn_navigation_effect(fm, Phi_f, S.t, S.nodes.lat, S.nodes.h, S.nodes.q_nb)
        tab = fm.ewn_table
        if len(eff):
            tab = tab.merge(eff, on=["filter", "dropped state"], how="left")
        frames.append(tab)
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def impact_filters(decl: dict, S: ZuptSetup) -> list[str]:
    """Validated ``[impact] filters``: reduced filters of the run (default: all of them).

    Raises
    ------
    StudyFileError
        Unknown key, not a list, a filter not among the run's cases, or a
        filter that drops no truth state.
    """
    cfg = decl.get("impact", {})
    w = f"{S.where}: [impact]"
    if not isinstance(cfg, dict):
        raise StudyFileError(w, f"expected a table, got {type(cfg).__name__}")
    check_keys(cfg, {"filters"}, w, StudyFileError)
    reduced = [c for c in S.cases if S.specs[c].n < S.truth.n]
    if "filters" not in cfg:
        return reduced
    fl = cfg["filters"]
    if not isinstance(fl, list) or not all(isinstance(x, str) for x in fl):
        raise StudyFileError(f"{w} filters", "expected a list of filter names")
    for x in fl:
        if x not in S.cases:
            raise StudyFileError(f"{w} filters", f"{x!r} is not one of the run's cases ({', '.join(S.cases)})")
        if x not in reduced:
            raise StudyFileError(f"{w} filters", f"filter {x!r} keeps every truth state: it drops nothing")
    return list(fl)


#: relative cost of one filter's impact run (:func:`covtool.lincov.impact.impact_runs`), in units of a filter
#: under the truth's navigation options: under other options it also discretises the truth transition under
#: them (+0.3); a further member of its options group takes most of its noise from the first (0.2); this
#: process also propagates each case and the pure INS (0.15 each) and makes each reduced case's system
#: (0.3; a streamed forked share makes its own filters' systems for their noise checks too).  Measured on
#: the flagship's CLI timeline (3 December): B1 0.54 s, B2 0.66 s, B3, C, D 0.92 s; the propagation and the
#: equivalent-noise table 0.48 s for 7 runs; the five reduced filters' systems 0.8 s.
IMPACT_COST = {"filter": 1.0, "own transition": 0.3, "further member": 0.2, "propagated run": 0.15,
               "filter system": 0.3}


def impact_shares(S: ZuptSetup, names: list) -> tuple[list, list]:
    """``(forked, own)``: the impact filters a forked process computes and those left to this one.

    Filters with the same navigation options share the truth transition
    under those options and most composed noise sources
    (:func:`covtool.lincov.impact.impact_runs`), so they stay together.
    The groups are split so that the two processes finish together: the
    forked share's cost as close as possible to this process's, which
    also propagates the cases and makes their systems
    (:data:`IMPACT_COST`; ties go to the smaller forked share, then to the
    earlier groups).  A speed measure only: the table is the same for any
    split.
    """
    from itertools import combinations

    from covtool.lincov.dynamics import dyn_key

    groups: dict = {}
    for n in names:
        groups.setdefault(dyn_key(S.specs[n].options), []).append(n)
    truth_key = dyn_key(None)                             # the truth's own options: its Φ serves
    c = IMPACT_COST
    streamed = S.resources.get("layout", "whole grid") != "whole grid"
    cost = [c["filter"] + (c["own transition"] if k != truth_key else 0.0) + c["further member"] * (len(g) - 1)
            for k, g in groups.items()]
    forked_extra = [c["filter system"] * len(g) if streamed else 0.0 for g in groups.values()]
    reduced = sum(1 for k in S.cases if S.specs[k].n < S.truth.n)
    runs = len(S.cases) + 1                               # the cases and (by default) the pure INS
    total, here = sum(cost), c["propagated run"] * runs + c["filter system"] * reduced
    G = list(groups.values())
    best, choice = None, ()
    if len(G) <= 12:                                      # every subset (2^12 at most); else in order
        subsets = (s for r in range(len(G) + 1) for s in combinations(range(len(G)), r))
    else:
        subsets = (tuple(range(r)) for r in range(len(G) + 1))
    for sub in subsets:
        f = sum(cost[i] + forked_extra[i] for i in sub)
        gap = abs(f - (total - sum(cost[i] for i in sub) + here))
        if best is None or gap < best - 1e-12:
            best, choice = gap, sub
    forked = [n for i in sorted(choice) for n in G[i]]
    return forked, [n for n in names if n not in forked]


def impact_runs(S: ZuptSetup, names: list, own_systems: bool = True) -> tuple[list, float]:
    """:func:`covtool.lincov.impact.impact_runs` of the filters at the report times, and the seconds taken."""
    from covtool.lincov.impact import impact_runs as runs

    t0 = time.perf_counter()
    rep = sorted({int(np.argmin(np.abs(S.t - tr))) for tr in S.report_times})
    out = runs(S, names, rep, own_systems=own_systems) if names else []
    return out, time.perf_counter() - t0


def impact_table(S: ZuptSetup, names: list, metrics: dict, bar=None, *, runs=None, record_steps=None) -> pd.DataFrame:
    """The ``impact`` sheet: every reduced filter × dropped block (D'Appolito state deletion).

    For each filter (:func:`covtool.lincov.impact.impact_runs`: its members
    in one batched pass against the truth, streamed in time) and report
    time: the true CEP, altitude PE and azimuth of the nominal filter,
    without equivalent noise, with eq (11)–(13) noise from each dropped
    block alone, and with each dropped block put back as filter states;
    ratios to the nominal and to filter A when it is in the run.  ``runs``
    (one per name, in the order of ``names``) are computed if omitted.

    Raises
    ------
    ValueError
        A run of ``runs`` is not the filter of its place in ``names``.
    """
    if runs is None:
        runs = impact_runs(S, names)[0]
    if [r.filter for r in runs] != list(names):
        raise ValueError(f"impact_table: runs of {[r.filter for r in runs]} for the filters {list(names)}")
    nodes = S.nodes
    rows = []
    for name, r in zip(names, runs):
        rs = r.record_steps
        ms = [nav_metrics(r.P[b], nodes.lat[rs], nodes.h[rs], nodes.q_nb[rs]) for b in range(len(r.variants))]
        nstates = {b: sum(1 for s in S.truth.states if s.block == b) for _, b in r.variants if b}
        for k, step in enumerate(rs):
            nom = ms[0]
            for (variant, block), m in zip(r.variants, ms):
                row = {"filter": name, "t [min]": S.t[step] / 60.0, "variant": variant,
                       "block": block or "", "block states": nstates.get(block, 0),
                       "CEP [ft]": m["cep"][k] / FT, "alt PE [ft]": m["alt_pe"][k] / FT,
                       "azimuth 1sigma [arcmin]": m["sigma_azimuth"][k] / ARCMIN,
                       "CEP / nominal [-]": m["cep"][k] / nom["cep"][k],
                       "alt PE / nominal [-]": m["alt_pe"][k] / nom["alt_pe"][k],
                       "azimuth / nominal [-]": m["sigma_azimuth"][k] / nom["sigma_azimuth"][k]}
                if "A" in metrics:
                    # metrics on the run's record steps (all steps when not given)
                    ka = step if record_steps is None else int(np.searchsorted(record_steps, step))
                    row["CEP / A [-]"] = m["cep"][k] / metrics["A"]["cep"][ka]
                    row["alt PE / A [-]"] = m["alt_pe"][k] / metrics["A"]["alt_pe"][ka]
                row["filter noise vs its own Q_f (max rel.)"] = r.noise_check
                rows.append(row)
        if bar is not None:
            bar.update(1)
    return pd.DataFrame(rows)
