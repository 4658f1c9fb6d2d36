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

    [impact]                 # dropped-state impact table (covtool.impact)
    filters = ["B1", "C", "D"]   # default: every reduced filter of the run; [] for none
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from covtool.lincov.kalman import check_system
from covtool.lincov.reference import propagate, propagate_with_filter
from covtool.lincov.dynamics import dyn_key, error_dynamics
from covtool.errors import StudyFileError
from covtool.lincov.reduced import build_filter, ewn_navigation_effect, zupt_matrices
from covtool.io.filters import default_filter_file, load_filters
from covtool.io.config import boolean, check_keys, names, quantity, resolve_input, table
from covtool.analysis.metrics import nav_metrics
from covtool.results import StudyResult
from covtool.studies.common import (ARCMIN, case_validity, check_memory, discretize_chunked, FT, history_frame,
                     initial_covariance, load_truth, memory_estimate, noise_columns, progress_bar,
                     resource_provenance, steps_of, study_header, study_inputs, summary_row, time_grid,
                     truth_system)
from covtool.studies.nav_covariance import load_trajectory, output_options


ZUPT_KEYS = {"interval", "duration", "rate", "sigma", "first"}


def zupt_options(cfg: dict, where: str, dt: float, duration: float) -> dict:
    """Validate ``[zupt]`` against the grid step ``dt`` and the study ``duration`` [s].

    Raises
    ------
    StudyFileError
        Unknown key, bad unit or sign, a window not shorter than the
        interval, an interval shorter than ``dt``, a rate above ``1/dt``
        (at most one update per propagation step) or a first ZUPT after the
        end of the study.
    """
    w = f"{where}: [zupt]"
    table(cfg, w, StudyFileError)
    check_keys(cfg, ZUPT_KEYS, w, StudyFileError)
    o = {
        "interval": quantity(cfg.get("interval", "5 min"), "time", f"{w} interval", StudyFileError, positive=True),
        "duration": quantity(cfg.get("duration", "30 s"), "time", f"{w} duration", StudyFileError,
                             nonnegative=True),
        "rate": quantity(cfg.get("rate", "1 Hz"), "frequency", f"{w} rate", StudyFileError, positive=True),
        # σ = 0 makes S = H P_f Hᵀ + R of eq (7) singular once P_f's velocity block is (a previous
        # exact ZUPT leaves it zero): the gain is undefined, so the noise must be positive
        "sigma": quantity(cfg.get("sigma", "0.01 ft/s"), "velocity", f"{w} sigma", StudyFileError, positive=True),
    }
    o["first"] = quantity(cfg.get("first", cfg.get("interval", "5 min")), "time", f"{w} first", StudyFileError,
                          positive=True)
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


def zupt_schedule(cfg: dict, where: str, t: np.ndarray, traj) -> tuple[np.ndarray, float, float]:
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


def _filters_file(cfg, where, base_dir) -> Path:
    if "file" not in cfg:
        return default_filter_file()
    # relative to the study file that names it, never the current directory
    return resolve_input(cfg["file"], base_dir, f"{where}: [filters] file", StudyFileError, what="filter file")


def filter_cases(fcfg: dict, specs: dict, ffile, where: str, *, nonempty: bool = False) -> list:
    """``[filters] cases``: declared filter names, each once (default: every filter).

    An empty list is allowed unless ``nonempty`` (a pure-INS-only run).
    """
    if "cases" not in fcfg:
        return list(specs)
    return names(fcfg["cases"], f"{where}: [filters] cases", StudyFileError, known=list(specs), nonempty=nonempty,
                 what="filter")


def filter_dynamics(specs: dict, cases) -> int:
    """Distinct truth dynamics the cases need (the truth's own and one per other NavOptions)."""
    return len({dyn_key(None)} | {dyn_key(specs[c].options) for c in cases})


@dataclass
class ZuptSetup:
    """Everything a ZUPT study shares between its cases (truth system, schedule, filters).

    Built by :func:`setup`; used by the filter-order, sensitivity, budget and
    trade-grid studies.  Filter models and their discretisation are built on
    demand and cached (:meth:`filter_model`).
    """

    hdr: dict
    where: str
    t: np.ndarray
    nodes: object
    truth: object
    ctx: object
    dyn: object
    Phi: np.ndarray
    Qd: np.ndarray
    P0: np.ndarray
    H: np.ndarray
    R: np.ndarray
    update_steps: np.ndarray
    zupt_interval: float
    zupt_sigma: float
    specs: dict
    cases: list
    mean_speed: float | None
    filter_file: Path
    every: float
    report_times: list
    resources: dict = field(default_factory=dict)
    _dyn_cache: dict = field(default_factory=dict)
    _filters: dict = field(default_factory=dict)

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
        A filter with exactly the truth's F and Q_c, discretised by the
        truth's method (filter A with the same method), has the truth's Φ and
        Q_d: they are returned as they are (``reused = True``), not computed again.
        """
        ckey = (name, None if discretization == "declared" else discretization)
        if ckey not in self._filters:
            spec = self.specs[name]
            if ckey[1] is not None:
                spec = dataclasses.replace(spec, discretization=ckey[1])
            key = dyn_key(spec.options)
            if key not in self._dyn_cache:
                self._dyn_cache[key] = self.dyn if key == dyn_key(None) else error_dynamics(
                    self.truth, self.ctx, spec.options)
            fm = build_filter(spec, self.truth, self.ctx, zupt_interval=self.zupt_interval,
                              q0=self.nodes.q_nb[0], truth_dynamics=self._dyn_cache[key],
                              mean_speed=self.mean_speed, dt_steps=np.diff(self.t),
                              update_steps=self.update_steps)
            same_method = spec.discretization == self.hdr["discretization"] and (
                spec.discretization == "van_loan" or spec.taylor_order is None)
            if same_method and fm.F.shape == self.dyn.F.shape and np.array_equal(fm.F, self.dyn.F) \
                    and np.array_equal(fm.Qc, self.dyn.Qc):
                self._filters[ckey] = (fm, self.Phi, self.Qd, True)
            else:
                Phi_f, Qd_f = discretize_chunked(fm.F, fm.Qc, np.diff(self.t), spec.discretization,
                                                 spec.taylor_order, what=f"{spec.path}: filter {name!r}",
                                                 times=self.t[:-1])
                # guarded once here; the runs that use them are told so (system_checked)
                check_system(f"{self.where}: filter {name}", Phi_f, Qd_f, names=fm.names, times=self.t)
                self._filters[ckey] = (fm, Phi_f, Qd_f, False)
        return self._filters[ckey]

    def filter_model(self, name: str):
        """``(FilterModel, Φ_f, Q_f)`` of a declared filter, cached (see :meth:`filter_system`)."""
        return self.filter_system(name)[:3]

    def filter_R(self, name: str) -> np.ndarray:
        """The measurement noise the filter assumes (its ``zupt_sigma`` or the study's)."""
        zs = self.specs[name].zupt_sigma
        return np.eye(3) * (zs if zs is not None else self.zupt_sigma) ** 2


def setup(decl: dict, *, path=None, progress: bool = False, extra_sections=(), memory=None,
          shrink: str = "a larger [study] dt, a shorter duration or fewer [filters] cases") -> ZuptSetup:
    """Validate a ZUPT study declaration and build the shared truth system.

    Parameters
    ----------
    memory : callable, optional
        ``memory(steps, truth, filter_sizes, dynamics) -> dict`` from
        :func:`covtool.studies.common.memory_estimate`: what the calling
        study holds at its peak.  Checked against the memory limit before
        anything is built; ``None`` skips the check (a worker of a plan
        that was checked as a whole).
    shrink : str
        The options that shrink the study, for the refusal message.
    """
    where = str(path) if path else "<study>"
    base_dir = path.parent if path else None
    check_keys(decl, {"study", "trajectory", "truth", "filters", "zupt", "output", *extra_sections}, where,
               StudyFileError)
    hdr = study_header(decl, where)
    every, rtimes = output_options(decl, where, hdr["duration"])
    fcfg = table(decl.get("filters", {}), f"{where}: [filters]", StudyFileError)
    check_keys(fcfg, {"file", "cases", "pure_ins"}, f"{where}: [filters]", StudyFileError)
    if "pure_ins" in fcfg:
        boolean(fcfg["pure_ins"], f"{where}: [filters] pure_ins", StudyFileError)
    zupt_options(table(decl.get("zupt", {}), f"{where}: [zupt]", StudyFileError), where, hdr["dt"],
                 hdr["duration"])
    truth = load_truth(decl, where, base_dir)
    ffile = _filters_file(fcfg, where, base_dir)
    specs = load_filters(ffile, truth)
    cases = filter_cases(fcfg, specs, ffile, where)
    est = {}
    if memory is not None:
        est = check_memory(memory(steps_of(hdr["duration"], hdr["dt"]), truth, [specs[c].n for c in cases],
                                  filter_dynamics(specs, cases)), where, hdr["max_memory"], shrink)
    traj = load_trajectory(decl, where, base_dir, hdr["dt"], hdr["duration"])
    t = time_grid(hdr["duration"], hdr["dt"], where)
    upd, dt_s, zsig = zupt_schedule(decl.get("zupt", {}), where, t, traj)
    ctx, dyn, Phi, Qd = truth_system(truth, traj, t, hdr["discretization"], progress=progress, where=where)
    nodes = traj.sample(t)
    P0 = initial_covariance(truth, nodes, where)
    moving = t[-1] - t[0] - sum(max(0.0, min(b, t[-1]) - max(a, t[0])) for a, b in traj.stationary)
    mean_speed = float(nodes.distance[-1] / moving) if moving > 0 else None
    H = zupt_matrices(truth.names)
    R = np.eye(3) * zsig**2
    return ZuptSetup(hdr, where, t, nodes, truth, ctx, dyn, Phi, Qd, P0, H, R, upd, dt_s, zsig, specs, cases,
                     mean_speed, ffile, every, rtimes, est)


def order_memory(pure: bool, impact: bool = True):
    """What a filter-order study holds: the system, every filter and every history (pure INS, truth, filter).

    With the dropped-state impact table (``impact``) it also holds, per
    filter in turn, the truth transition under the filter's options and
    the per-source noise series (:data:`covtool.lincov.noise.COMPOSE_WORKSPACE`).
    """
    from covtool.lincov.noise import COMPOSE_WORKSPACE

    def memory(steps, truth, filters, dynamics):
        n = truth.n
        hist = ([n] if pure else []) + [m for nf in filters for m in (n, nf)]
        extra = COMPOSE_WORKSPACE + 2 * int(steps) * n * n * 8 if impact and any(nf < n for nf in filters) else 0.0
        return memory_estimate(steps, n, filters=filters, dynamics=dynamics, histories=hist,
                               noise=noise_columns(truth), extra=extra)
    return memory


def run(decl: dict, *, path=None, progress: bool = False) -> StudyResult:
    """Run the filter-order trade; see the module docstring."""
    t_start = time.perf_counter()
    pure = (decl.get("filters") or {}).get("pure_ins", True) if isinstance(decl.get("filters", {}), dict) else True
    imp = decl.get("impact")
    S = setup(decl, path=path, progress=progress, extra_sections=("impact",),
              memory=order_memory(pure is not False, not (isinstance(imp, dict) and imp.get("filters") == [])))
    imp_filters = impact_filters(decl, S)
    hdr, t, nodes, truth = S.hdr, S.t, S.nodes, S.truth
    Phi, Qd, P0, H, R, upd = S.Phi, S.Qd, S.P0, S.H, S.R, S.update_steps
    cases, every, rtimes, ffile = S.cases, S.every, S.report_times, S.filter_file
    dt_s, zsig, mean_speed = S.zupt_interval, S.zupt_sigma, S.mean_speed
    fcfg = decl.get("filters", {})
    metrics, runs, fmodels, claimed = {}, {}, {}, {}
    where = S.where
    if fcfg.get("pure_ins", True):
        metrics["pure_ins"] = nav_metrics(propagate(Phi, Qd, P0, label=f"{where}: pure INS", names=truth.names,
                                                    times=t, system_checked=True),
                                          nodes.lat, nodes.h, nodes.q_nb, nodes.distance)
    with progress_bar(len(cases), "filters", progress) as bar:
        for c in cases:
            spec = S.specs[c]
            fm, Phi_f, Qd_f = S.filter_model(c)
            Hf = zupt_matrices(fm.names)
            run_ = propagate_with_filter(Phi, Qd, P0, Phi_f, Qd_f, fm.P0, H, Hf, fm.D, R, upd, Rf=S.filter_R(c),
                                         form=spec.update, label=f"{where}: filter {c}", times=t,
                                         names=truth.names, filter_names=fm.names, system_checked=True)
            runs[c], fmodels[c] = run_, fm
            metrics[c] = nav_metrics(run_.P_truth, nodes.lat, nodes.h, nodes.q_nb, nodes.distance)
            claimed[c] = nav_metrics(run_.P_filter[:, :10, :10], nodes.lat, nodes.h, nodes.q_nb, nodes.distance)
            bar.update(1)
    elapsed = time.perf_counter() - t_start

    rows = []
    for case, m in metrics.items():
        first = case_validity(case, m, t)
        for tr in rtimes:
            k = int(np.argmin(np.abs(t - tr)))
            row = summary_row(case, m, k, t[k], float(nodes.distance[k]), first=first)
            row["states"] = truth.n if case == "pure_ins" else fmodels[case].spec.n
            if case in claimed:
                row["filter-claimed CEP [ft]"] = claimed[case]["cep"][k] / FT
                row["filter-claimed alt PE [ft]"] = claimed[case]["alt_pe"][k] / FT
                row["filter-claimed azimuth [arcmin]"] = claimed[case]["sigma_azimuth"][k] / ARCMIN
            if "pure_ins" in metrics and case != "pure_ins":
                row["position improvement over pure INS [x]"] = metrics["pure_ins"]["cep"][k] / m["cep"][k]
                row["altitude improvement over pure INS [x]"] = metrics["pure_ins"]["alt_pe"][k] / m["alt_pe"][k]
            rows.append(row)
    summary = pd.DataFrame(rows)
    order = ["case", "states"] + [c for c in summary.columns if c not in ("case", "states")]
    summary = summary[order]

    hist = pd.concat([history_frame(c, t, m, every) for c, m in metrics.items()], ignore_index=True)
    ewn = equivalent_noise_table(S, fmodels)
    fstates = []
    for c, fm in fmodels.items():
        sig0 = np.sqrt(np.clip(np.diag(fm.P0), 0, None))
        for nm, s0 in zip(fm.names, sig0):
            st = truth.states[truth.index[nm]]
            fstates.append({"filter": c, "state": nm, "symbol": st.symbol, "unit": st.unit,
                            "P0 1sigma [SI]": s0, "process": st.process,
                            "options": f"coriolis={fm.spec.options.coriolis}, "
                                       f"vertical_coupled={fm.spec.options.couple_vertical}"})
    tables = {"summary": summary, "history": hist, "truth_states": truth.state_table(),
              "filter_states": pd.DataFrame(fstates)}
    if len(ewn):
        tables["equivalent_noise"] = ewn
    figures = {}
    t_imp = time.perf_counter()
    if imp_filters:
        with progress_bar(len(imp_filters), "dropped-state impact", progress) as bar:
            tables["impact"] = impact_table(S, imp_filters, metrics, bar)
        figures["impact_dropped_states"] = impact_figure(tables["impact"], S.report_times[-1])
    t_imp = time.perf_counter() - t_imp
    upd_t = t[upd]
    zupt_marks = np.unique(np.round(upd_t[np.r_[True, np.diff(upd_t) > 2 * hdr["dt"]]]))

    def fig(kind):
        def make():
            import matplotlib.pyplot as plt
            fig, ax = plt.subplots(figsize=(9, 5))
            for c, m in metrics.items():
                y = m["cep"] / FT if kind == "horizontal" else m["alt_pe"] / FT
                ax.plot(t / 60, y, label=c, lw=1.2)
            for z in zupt_marks:
                ax.axvline(z / 60, color="0.7", lw=0.6, ls=":")
            ax.set_yscale("log")
            ax.set_ylim(bottom=1.0)
            ax.set_xlabel("time [min]")
            ax.set_ylabel("horizontal CEP [ft]" if kind == "horizontal" else "altitude PE [ft]")
            ax.set_title(("Fig 6: horizontal position error" if kind == "horizontal" else
                          "Fig 7: altitude error") + " by filter model (dotted: ZUPT stops)")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(ncol=4)
            return fig
        return make

    provenance = {**study_inputs(path, decl, truth, ffile), "truth_model": truth.name,
                  "truth_model_sha256": truth.sha256, "zupt_updates": int(len(upd)), "zupt_interval_s": dt_s,
                  "zupt_sigma_m_s": zsig, "mean_moving_speed_m_s": mean_speed, **resource_provenance(S.resources),
                  "compute_seconds": f"{elapsed:.2f}", "impact_compute_seconds": f"{t_imp:.2f}"}
    return StudyResult(
        name=hdr["name"], kind="zupt_filter_order", tables=tables,
        figures={"fig6_horizontal_cep": fig("horizontal"), "fig7_altitude_pe": fig("altitude"), **figures},
        resolved={**decl, "study": {**decl["study"], "name": hdr["name"]}}, provenance=provenance,
        charts=[{"sheet": "history", "x": "t [min]", "y": ["CEP [ft]"], "title": "CEP (all cases, stacked rows)",
                 "y_title": "ft", "anchor": "S2"}],
        data={"t": t, "runs": runs, "filters": fmodels, "metrics": metrics, "claimed": claimed,
              "update_steps": upd, "trajectory": nodes, "truth": truth, "P0": P0, "Phi": Phi, "Qd": Qd,
              "H": H, "R": R},
    )


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
        _, Phi_f, _ = S.filter_model(c)
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


def impact_table(S: ZuptSetup, names: list, metrics: dict, bar=None) -> pd.DataFrame:
    """The ``impact`` sheet: every reduced filter × dropped block (D'Appolito state deletion).

    For each filter (:func:`covtool.lincov.impact.impact_run`, one batched pass
    per filter against one shared truth) and report time: the true CEP,
    altitude PE and azimuth of the nominal filter, without equivalent
    noise, with eq (11)–(13) noise from each dropped block alone, and with
    each dropped block put back as filter states; ratios to the nominal
    and to filter A when it is in the run.
    """
    from covtool.lincov.batch import System, events
    from covtool.lincov.impact import impact_run

    N = S.t.size - 1
    rep = sorted({int(np.argmin(np.abs(S.t - tr))) for tr in S.report_times})
    ev = events(N, S.update_steps, rep)
    truth_sys = System.from_steps(S.Phi, S.Qd, ev)
    nodes = S.nodes
    rows = []
    for name in names:
        r = impact_run(S, name, rep, truth_system=truth_sys)
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
                    row["CEP / A [-]"] = m["cep"][k] / metrics["A"]["cep"][step]
                    row["alt PE / A [-]"] = m["alt_pe"][k] / metrics["A"]["alt_pe"][step]
                row["filter noise vs its own Q_f (max rel.)"] = r.noise_check
                rows.append(row)
        if bar is not None:
            bar.update(1)
    return pd.DataFrame(rows)


def impact_figure(table: pd.DataFrame, t_report: float):
    """Figure maker: per filter, CEP and altitude PE with each dropped block's noise alone / put back."""
    def make():
        import matplotlib.pyplot as plt
        tab = table[np.isclose(table["t [min]"], t_report / 60.0)]
        names = list(dict.fromkeys(tab["filter"]))
        fig, axes = plt.subplots(len(names), 2, figsize=(12, 2.2 + 2.6 * len(names)), squeeze=False)
        for r, name in enumerate(names):
            g = tab[tab["filter"] == name]
            nom = g[g["variant"] == "nominal"].iloc[0]
            none = g[g["variant"] == "no equivalent noise"].iloc[0]
            blocks = list(dict.fromkeys(g.loc[g["block"] != "", "block"]))
            y = np.arange(len(blocks))
            for c, col in enumerate(("CEP [ft]", "alt PE [ft]")):
                ax = axes[r, c]
                only = [g[(g["block"] == b) & (g["variant"] == "noise from block only")][col].iloc[0] for b in blocks]
                back = [g[(g["block"] == b) & (g["variant"] == "block put back")][col].iloc[0] for b in blocks]
                ax.barh(y - 0.2, only, 0.4, label="(a) eq (11)-(13) noise of this block only")
                ax.barh(y + 0.2, back, 0.4, label="(b) this block put back into the filter")
                ax.axvline(nom[col], color="k", lw=1.2, label="nominal (all dropped blocks as noise)")
                ax.axvline(none[col], color="0.5", lw=1.0, ls="--", label="no equivalent noise")
                ax.set_yticks(y)
                ax.set_yticklabels(blocks, fontsize=8)
                ax.invert_yaxis()
                ax.set_xlabel(f"true {col} at {t_report / 60:g} min")
                ax.set_title(f"filter {name}: {col.split(' [')[0]}")
                ax.grid(True, axis="x", alpha=0.3)
        h, lab = axes[0, 0].get_legend_handles_labels()
        fig.legend(h, lab, loc="lower center", ncol=4, fontsize=8)
        fig.suptitle("Dropped-state impact (D'Appolito state deletion, seed 002 ref [13])")
        fig.tight_layout(rect=(0, 0.03, 1, 0.98))
        return fig
    return make
