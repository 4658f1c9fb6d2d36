"""Error budget study: the sources of the error (seed 002, Fig 4).

The truth covariance of each case is split exactly into contributions of its
sources (:mod:`covtool.analysis.budget`): initial errors by block (navigation split
into position, velocity, tilt, azimuth), process noises, and the ZUPT noise,
all under the gains of the case's nominal filter run.  A pure INS case
(``"pure_ins"``) has no gains; its budget is the one seed 002 used to choose
the sensor states of its 22-state filter.

Study file::

    [study]
    kind = "error_budget"
    duration = "30 min"
    dt = "1 s"

    [trajectory]
    builtin = "land_vehicle"

    [truth]
    model = "sdins58"            # only = [...] and [truth.override.*] as elsewhere

    [filters]
    cases = ["pure_ins", "A", "B1", "D"]   # "pure_ins" = no aiding; default: pure_ins + every filter
    # file = "../models/filters/zupt_filters.toml"

    [zupt]                       # as in zupt_filter_order
    interval = "5 min"

    [budget]
    resolution = "block"         # or "state": one source per state / per noise source
    top = 8                      # sources drawn in the stacked figures: largest peak share (rest: "other")

    [output]
    history_every = "30 s"
    report_times = ["10 min", "30 min"]

With ``[[measurement]]`` tables (the aided kind's declaration) instead of
``[zupt]``, the budget runs in :mod:`covtool.studies.aided_budget`: each
measurement-error state and each measurement's R are sources too (issue 15).

Reported per navigation error: horizontal (σ_N² + σ_E², the squared RMS
radial error), altitude (σ_D²) and azimuth (σ_ψ²); shares of variance and
the 1σ-equivalent ``√(variance)`` in ft or arcmin.  Every case records how
closely the contributions sum to the total run (provenance and summary).
"""

from __future__ import annotations

import copy
import time
from functools import partial

import numpy as np
import pandas as pd

from covtool.analysis.budget import (budget_sources, ERRORS, MEASUREMENT, nav_variances, relative_residual,
                                     RESOLUTIONS, run_budget)
from covtool.analysis.metrics import cep, nav_metrics, ned_position_covariance, validity_text
from covtool.errors import StudyFileError
from covtool.io.config import check_keys, choice, integer, names, table
from covtool.lincov.batch import events, run_batch, System
from covtool.lincov.noise import compose_noise
from covtool.forked import Forked
from covtool.lincov.reduced import zupt_matrices
from covtool.plotting.budget import budget_figure, top_sources
from covtool.results import ErrorBudgetResult
from covtool.studies.grid import record_steps
from covtool.studies.inputs import length_unit, study_header, study_inputs
from covtool.studies.resources import (composed_memory_estimate, noise_columns, progress_bar, resource_provenance,
                                       STREAM_CHUNK)
from covtool.studies.tables import case_validity
from covtool.studies.zupt_setup import setup
from covtool.units import ARCMIN, FT


PURE = "pure_ins"
#: paper unit of each error: (SI per unit, label)
PAPER_UNITS = {"horizontal": (FT, "ft"), "altitude": (FT, "ft"), "azimuth": (ARCMIN, "arcmin")}
_LABEL = {"horizontal": "horizontal RMS (drms)", "altitude": "altitude 1sigma", "azimuth": "azimuth 1sigma"}
_ERROR_TITLES = {"horizontal": "horizontal position (σ_N² + σ_E²)", "altitude": "altitude (σ_D²)",
                 "azimuth": "azimuth (σ_ψ²)"}


def budget_options(decl: dict, where: str) -> dict:
    """Validate ``[budget]``: ``resolution`` and ``top``.

    Raises
    ------
    StudyFileError
        Unknown key, unknown resolution, or ``top`` not a positive integer.
    """
    w = f"{where}: [budget]"
    cfg = table(decl.get("budget", {}), w, StudyFileError)
    check_keys(cfg, {"resolution", "top"}, w, StudyFileError)
    res = choice(cfg.get("resolution", "block"), tuple(RESOLUTIONS), f"{w} resolution", StudyFileError)
    top = integer(cfg.get("top", 8), f"{w} top", StudyFileError, limit="budget_top")
    return {"resolution": res, "top": top}


def budget_cases(decl: dict, where: str) -> tuple[list | None, bool]:
    """Requested cases: ``(filter cases or None, pure INS wanted)``.

    Raises
    ------
    StudyFileError
        ``pure_ins = ...`` in ``[filters]`` (list it in ``cases`` instead),
        ``cases`` not a non-empty list of names, or a case listed twice.
    """
    fcfg = decl.get("filters", {})
    w = f"{where}: [filters]"
    if not isinstance(fcfg, dict):
        raise StudyFileError(w, f"expected a table, got {type(fcfg).__name__}")
    if "pure_ins" in fcfg:
        raise StudyFileError(f"{w} pure_ins", "an error budget lists the pure INS as a case: "
                             "cases = [\"pure_ins\", ...]")
    if "cases" not in fcfg:
        return None, True
    cases = names(fcfg["cases"], f"{w} cases", StudyFileError, what="case (a filter or \"pure_ins\")")
    return [c for c in cases if c != PURE], PURE in cases


def _memory(decl: dict, where: str, resolution: str, pure: bool):
    """What a budget holds: per source its noise composed over the event grid (J, K, n, n), and the systems.

    The truth's and the filters' systems and the per-source noise are made
    chunk by chunk in time and composed on the events, in this process and
    the forked one (:func:`~covtool.studies.resources.composed_memory_estimate`);
    the per-source stacks grow with the records (the history spacing), not
    with the steps.
    """
    from covtool.studies.inputs import output_options
    from covtool.studies.zupt_setup import zupt_options, zupt_update_count

    def memory(steps, truth, filters, dynamics):
        n = truth.n
        hdr = study_header(decl, where)
        every, rtimes = output_options(decl, where, hdr["duration"])
        updates = zupt_update_count(zupt_options(decl.get("zupt", {}), where, hdr["dt"], hdr["duration"]),
                                    hdr["duration"])
        events = min(steps, updates + int(hdr["duration"] / every) + len(rtimes) + 2 + steps // STREAM_CHUNK + 1)
        sources = n + 4 if resolution == "state" else 24          # noise sources + initial errors
        est = composed_memory_estimate(steps, n, filters=filters, dynamics=dynamics, noise=noise_columns(truth),
                                       updates=updates, reports=events - updates, processes=2)
        # the per-source noise of every chunk and their concatenation (compose_noise), then one case's
        # per-source covariances in each process
        parts = {**est["parts"], "per-source composed noise": 2 * sources * events * n * n * 8,
                 "per-source covariances": 2 * 3 * sources * n * n * 8}
        return {**est, "bytes": float(sum(parts.values())), "parts": parts}
    return memory


def report_record_steps(t: np.ndarray, every: float, report_times) -> np.ndarray:
    """Record steps of a budget: every ``every`` s, the report times, the start and the end
    (:func:`covtool.studies.grid.record_steps`)."""
    return record_steps(t, every, [int(np.argmin(np.abs(t - tr))) for tr in report_times])


def run(decl: dict, *, path=None, progress: bool = False) -> ErrorBudgetResult:
    """Run an error-budget study; see the module docstring."""
    if "measurement" in decl:              # declared measurements (issue 15): covtool.studies.aided_budget
        from covtool.studies.aided_budget import run as run_aided
        return run_aided(decl, path=path, progress=progress)
    t_start = time.perf_counter()
    where = str(path) if path else "<study>"
    opts = budget_options(decl, where)
    fcases, want_pure = budget_cases(decl, where)
    decl_z = copy.deepcopy(decl)
    if fcases is not None:
        decl_z.setdefault("filters", {})["cases"] = fcases
    S = setup(decl_z, path=path, progress=progress, extra_sections=("budget",),
              memory=_memory(decl_z, where, opts["resolution"], want_pure))
    cases = ([PURE] if want_pure else []) + list(S.cases)
    truth_model, t, nodes = S.truth, S.t, S.nodes
    N = t.size - 1
    rec = report_record_steps(t, S.every, S.report_times)
    # the events with the stream's chunk boundaries: the truth's Φ, Q_d and each source's noise are made
    # and composed one chunk at a time (ZuptSetup.composed_truth), nothing of size N x n^2 held
    ev = S.stream_grid(events(N, S.update_steps, rec))
    dt = np.diff(t)
    found, Qparts = [], []

    def per_source(a, cev, dyn, Phi):
        sources, factors = budget_sources(truth_model, dyn.noise, nodes.q_nb[0], S.R, resolution=opts["resolution"])
        if not found:
            found.append((sources, factors))
        Qparts.append(compose_noise(Phi, dyn.F, factors, dt[a:a + Phi.shape[0]], cev - a))

    truth = S.composed_truth(ev, on_chunk=per_source)
    sources, factors = found[0]
    Qn = np.concatenate(Qparts, axis=1) if len(Qparts) > 1 else Qparts[0]
    Qparts.clear()
    q_check = _composed_noise_check(Qn, truth.Q)
    lat, h, q = nodes.lat[rec], nodes.h[rec], nodes.q_nb[rec]

    runs, var, nominal, residuals, first = {}, {}, {}, {}, {}
    # the second half of the cases is computed in a forked process meanwhile (covtool.forked)
    later = cases[(len(cases) + 1) // 2:]
    job = Forked(lambda: {c: case_budget(S, c, truth, sources, Qn, rec) for c in later}) if later else None
    with progress_bar(len(cases), "budget cases", progress) as bar:
        for c in cases:
            br, nominal[c] = job.result()[c] if c in later else case_budget(S, c, truth, sources, Qn, rec)
            runs[c] = br
            var[c] = nav_variances(br.P, lat, h, q)
            residuals[c] = _residuals(br, nominal[c], lat, h, q)
            first[c] = case_validity(c, nav_metrics(nominal[c], lat, h, q), t[rec])
            bar.update(1)
    elapsed = time.perf_counter() - t_start

    tables = _tables(cases, runs, var, nominal, residuals, t, rec, S, lat, h, first)
    tables["sources"] = _source_table(sources, factors)
    provenance = {"truth_model": truth_model.name, "truth_model_file": truth_model.path,
                  "truth_model_sha256": truth_model.sha256, "filter_file": ", ".join(map(str, S.filter_files)),
                  "resolution": opts["resolution"], "sources": len(sources), "zupt_updates": int(len(S.update_steps)),
                  "per-source Q_d sum vs study Q_d (composed, max relative)": f"{q_check:.3g}",
                  **resource_provenance(S.resources), "compute_seconds": f"{elapsed:.2f}"}
    provenance.update(study_inputs(path, decl, truth_model, S.filter_files))
    for c in cases:
        provenance[f"{c}: sum-to-total residual (same Q_d)"] = f"{residuals[c]['same']:.3g}"
        provenance[f"{c}: sum vs nominal run residual"] = f"{residuals[c]['nominal']:.3g}"
    result = ErrorBudgetResult(
        name=S.hdr["name"], kind="error_budget", tables=tables,
        charts=budget_charts(cases, runs, var, opts["top"]),
        resolved={**decl, "study": {**decl["study"], "name": S.hdr["name"]},
                  "budget": {**decl.get("budget", {}), **opts}},
        provenance=provenance,
        runs=runs, residuals=residuals, record_steps=np.asarray(rec), setup=S, truth_system=truth, noise=Qn,
        times=t[rec], length_unit=length_unit(decl, where), update_times=t[S.update_steps], stops=S.stops,
        variances=var, sources={c: [s.name for s in runs[c].sources] for c in cases},
        source_order=[s.name for s in sources], top=opts["top"])
    result.figures = {f"budget_{c}": partial(budget_figure, result, c) for c in cases}
    return result


def budget_charts(cases, runs, var, top: int) -> list[dict]:
    """Workbook chart specs: per error and case, the total and the top sources on a log axis.

    One series per source (variance contribution, not stacked), drawn
    from the ``history_<error>`` sheets; the first record (t = 0, where
    the noise sources are zero) is left out of the log axis.
    """
    charts = []
    for k, e in enumerate(ERRORS):
        si, unit = PAPER_UNITS[e]
        for j, c in enumerate(cases):
            idx = top_sources(var[c][e] / si**2, top)
            ys = [f"total [{unit}^2]"] + [f"{runs[c].sources[i].name} [{unit}^2]" for i in idx]
            charts.append({"sheet": f"history_{e}", "where": {"case": c}, "x": "t [min]", "y": ys, "skip": 1,
                           "log_y": True, "title": f"{c}: {_ERROR_TITLES[e]}, variance by source (top {top})",
                           "x_title": "time [min]", "y_title": f"variance [{unit}^2]",
                           "target": "charts", "anchor": (1 + 19 * k, 1 + 12 * j)})
    return charts


def case_budget(S, case: str, truth: System, sources: list, Qn: np.ndarray, rec, *, P0=None):
    """One case's budget and its nominal run.

    Parameters
    ----------
    S : covtool.studies.zupt_setup.ZuptSetup
    case : str
        A filter name, or ``"pure_ins"`` (no updates; the measurement
        source is left out).
    truth : covtool.lincov.batch.System
        Truth Φ, Q_d composed on the event grid of ``rec`` and the updates.
    sources : list of covtool.analysis.budget.Source
    Qn : ndarray, shape (J, K, n, n)
        Composed per-source noise.
    rec : ndarray of int
        Record steps.
    P0 : ndarray, shape (n, n), optional
        Total initial covariance (default ``S.P0``).

    Returns
    -------
    budget : covtool.analysis.budget.BudgetRun
        Contributions under the gains of the nominal filter run.
    P_nominal : ndarray, shape (n_rec, 10, 10)
        The nominal run (running filter, the study's own Q_d).
    """
    P0 = S.P0 if P0 is None else P0
    names, t = S.truth.names, S.t
    if case == PURE:
        src = [s for s in sources if s.kind != MEASUREMENT]
        n = truth.n
        nom = run_batch(truth, P0[None], S.H, S.R, np.eye(n), [], rec, gains=np.zeros((1, 0, n, S.H.shape[0])),
                        label=f"{S.where}: pure INS (nominal run)", names=names, times=t)
        return run_budget(truth, src, Qn, P0, S.H, S.R, None, None, [], rec,
                          label=f"{S.where}: pure INS error budget", names=names, times=t), nom.P_truth[0]
    fm, filt, _ = S.composed_filter(case, truth.ev, truth=truth)       # chunk by chunk in time
    nom = run_batch(truth, P0[None], S.H, S.R, fm.D, S.update_steps, rec, filt=filt, Pf0=fm.P0[None],
                    Hf=zupt_matrices(fm.names), Rf=S.filter_R(case)[None], form=S.specs[case].update,
                    label=f"{S.where}: filter {case} (nominal run)", names=names, filter_names=fm.names, times=t)
    br = run_budget(truth, sources, Qn, P0, S.H, S.R, fm.D, nom.gains, S.update_steps, rec,
                    label=f"{S.where}: filter {case} error budget", names=names, times=t)
    return br, nom.P_truth[0]


def _composed_noise_check(Qn: np.ndarray, Q_ref: np.ndarray) -> float:
    """Largest ``|Σ_j Q_j − Q|_ik / √(Q_ii Q_kk)`` over the intervals."""
    if len(Qn) == 0:
        return float(np.abs(Q_ref).max())
    S = Qn.sum(axis=0)
    d = np.sqrt(np.clip(np.einsum("kii->ki", Q_ref), 0, None))
    den = d[:, :, None] * d[:, None, :]
    m = den > 0
    return float((np.abs(S - Q_ref)[m] / den[m]).max())


def _residuals(br, P_nom, lat, h, q) -> dict:
    """Sum-to-total residuals: same-Q_d total and the nominal run."""
    P_sum = br.P.sum(axis=0)
    out = {"same": relative_residual(P_sum, br.P_total, q), "nominal": relative_residual(P_sum, P_nom, q)}
    vs = nav_variances(P_sum, lat, h, q)
    vt = nav_variances(br.P_total, lat, h, q)
    vn = nav_variances(P_nom, lat, h, q)
    for e in ERRORS:
        pos = vt[e] > 0
        out[f"{e} same"] = float(np.max(np.abs(vs[e] - vt[e])[pos] / vt[e][pos])) if pos.any() else 0.0
        pos = vn[e] > 0
        out[f"{e} nominal"] = float(np.max(np.abs(vs[e] - vn[e])[pos] / vn[e][pos])) if pos.any() else 0.0
    return out


def _states_text(states) -> str:
    if len(states) <= 4:
        return ", ".join(states)
    return f"{states[0]} … {states[-1]} ({len(states)})"


def _sqrt_total(total: float, parts) -> float:
    """√ of a summed variance; NaN (never 0) if it is negative beyond round-off of its parts."""
    if total < -1e-9 * float(np.sum(np.abs(parts))):
        return np.nan
    return float(np.sqrt(max(total, 0.0)))


def _tables(cases, runs, var, nominal, residuals, t, rec, S, lat, h, first) -> dict:
    rep = [int(np.argmin(np.abs(t[rec] - tr))) for tr in S.report_times]
    summary, ranked, shares = [], {e: [] for e in ERRORS}, {}
    for c in cases:
        srcs = runs[c].sources
        vn = nav_variances(nominal[c], lat, h, S.nodes.q_nb[rec])
        Pn = ned_position_covariance(nominal[c][:, :3, :3], lat, h)
        cep_nom = cep(Pn[:, :2, :2])
        for r in rep:
            row = {"case": c, "t [min]": t[rec[r]] / 60.0,
                   "CEP (nominal run) [ft]": cep_nom[r] / FT}
            for e in ERRORS:
                si, unit = PAPER_UNITS[e]
                v = var[c][e][:, r]
                total = v.sum()
                order = np.argsort(-v, kind="stable")
                row[f"{_LABEL[e]} [{unit}]"] = _sqrt_total(total, v) / si
                row[f"{_LABEL[e]}, nominal run [{unit}]"] = _sqrt_total(vn[e][r], [vn[e][r]]) / si
                top = [f"{srcs[i].name} {100 * v[i] / total:.1f} %" for i in order[:3]] if total > 0 else []
                row[f"{e} top sources"] = "; ".join(top)
                cum = 0.0
                for rank, i in enumerate(order, start=1):
                    share = 100.0 * v[i] / total if total > 0 else np.nan
                    cum += share
                    ranked[e].append({
                        "case": c, "t [min]": t[rec[r]] / 60.0, "rank": rank, "source": srcs[i].name,
                        "kind": srcs[i].kind, "states": _states_text(srcs[i].states),
                        f"variance [{unit}^2]": v[i] / si**2, "share [%]": share, "cumulative [%]": cum,
                        f"1sigma-equivalent [{unit}]": np.sign(v[i]) * np.sqrt(abs(v[i])) / si})
                if r == rep[-1]:
                    col = f"{c} {e} [%]"
                    shares[col] = {s.name: 100.0 * v[i] / total if total > 0 else np.nan
                                   for i, s in enumerate(srcs)}
            row["sum-to-total residual (same Q_d)"] = residuals[c]["same"]
            row["sum vs nominal run residual"] = residuals[c]["nominal"]
            row["validity"] = validity_text(first[c], until=t[rec[r]])
            summary.append(row)
    out = {"summary": pd.DataFrame(summary)}
    for e in ERRORS:
        out[f"budget_{e}"] = pd.DataFrame(ranked[e])
    sh = pd.DataFrame(shares)
    sh.index.name = "source"
    out["shares"] = sh.reset_index()
    for e in ERRORS:
        si, unit = PAPER_UNITS[e]
        frames = []
        for c in cases:
            cols = {"case": c, "t [min]": t[rec] / 60.0}
            v = var[c][e]
            cols[f"total [{unit}^2]"] = v.sum(axis=0) / si**2
            for i, s in enumerate(runs[c].sources):
                cols[f"{s.name} [{unit}^2]"] = v[i] / si**2
            frames.append(pd.DataFrame(cols))
        out[f"history_{e}"] = pd.concat(frames, ignore_index=True)
    return out


def _source_table(sources, factors) -> pd.DataFrame:
    rows = []
    for s in sources:
        rows.append({"source": s.name, "kind": s.kind, "states": ", ".join(s.states),
                     "noise columns": factors[s.noise].G.shape[2] if s.noise is not None else 0})
    return pd.DataFrame(rows)
