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
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..covariance import check_system, propagate, propagate_with_filter
from ..dynamics import error_dynamics
from ..errors import StudyFileError
from ..filters import build_filter, default_filter_file, load_filters, zupt_matrices
from ..io.config import check_keys, quantity
from ..metrics import nav_metrics
from ..results import StudyResult
from .common import (ARCMIN, FT, case_validity, discretize_chunked, history_frame, initial_covariance, load_truth,
                     progress_bar, study_header, summary_row, time_grid, truth_system)
from .nav_covariance import load_trajectory, output_options


def zupt_schedule(cfg: dict, where: str, t: np.ndarray, traj) -> tuple[np.ndarray, float, float]:
    """Grid indices of the ZUPT updates, the interval Δt_s and R's σ.

    Raises
    ------
    StudyFileError
        Bad keys or units, update times off the grid, or an update outside the
        trajectory's stationary intervals (the message names the time and the
        nearest stationary interval).
    """
    w = f"{where}: [zupt]"
    check_keys(cfg, {"interval", "duration", "rate", "sigma", "first"}, w, StudyFileError)
    interval = quantity(cfg.get("interval", "5 min"), "time", f"{w} interval", StudyFileError, positive=True)
    dur = quantity(cfg.get("duration", "30 s"), "time", f"{w} duration", StudyFileError, nonnegative=True)
    rate = quantity(cfg.get("rate", "1 Hz"), "frequency", f"{w} rate", StudyFileError, positive=True)
    sigma = quantity(cfg.get("sigma", "0.01 ft/s"), "velocity", f"{w} sigma", StudyFileError, positive=True)
    first = quantity(cfg.get("first", cfg.get("interval", "5 min")), "time", f"{w} first", StudyFileError,
                     positive=True)
    if dur >= interval:
        raise StudyFileError(f"{w} duration", f"the ZUPT window ({dur:g} s) must be shorter than the interval")
    ends = np.arange(first, t[-1] + 1e-9, interval)
    times = []
    for e in ends:
        n = int(np.floor(dur * rate + 1e-9))
        times.extend(e - np.arange(n, -1, -1) / rate)
    times = np.array(times)
    dt = t[1] - t[0]
    idx = np.round(times / dt).astype(int)
    if np.any(np.abs(idx * dt - times) > 1e-6 * dt) or np.any(idx >= t.size):
        bad = times[np.argmax(np.abs(idx * dt - times))]
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
    p = Path(cfg["file"])
    if not p.is_absolute() and base_dir is not None:
        p = Path(base_dir) / p
    if not p.is_file():
        raise StudyFileError(f"{where}: [filters] file", f"no such file {str(p)!r}")
    return p


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
                              mean_speed=self.mean_speed, dt_steps=np.diff(self.t))
            same_method = spec.discretization == self.hdr["discretization"] and (
                spec.discretization == "van_loan" or spec.taylor_order is None)
            if same_method and fm.F.shape == self.dyn.F.shape and np.array_equal(fm.F, self.dyn.F) \
                    and np.array_equal(fm.Qc, self.dyn.Qc):
                self._filters[ckey] = (fm, self.Phi, self.Qd, True)
            else:
                Phi_f, Qd_f = discretize_chunked(fm.F, fm.Qc, np.diff(self.t), spec.discretization,
                                                 spec.taylor_order)
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


def setup(decl: dict, *, path=None, progress: bool = False, extra_sections=()) -> ZuptSetup:
    """Validate a ZUPT study declaration and build the shared truth system."""
    where = str(path) if path else "<study>"
    base_dir = path.parent if path else None
    check_keys(decl, {"study", "trajectory", "truth", "filters", "zupt", "output", *extra_sections}, where,
               StudyFileError)
    hdr = study_header(decl, where)
    every, rtimes = output_options(decl, where, hdr["duration"])
    fcfg = decl.get("filters", {})
    check_keys(fcfg, {"file", "cases", "pure_ins"}, f"{where}: [filters]", StudyFileError)
    traj = load_trajectory(decl, where, base_dir, hdr["dt"], hdr["duration"])
    truth = load_truth(decl, where, base_dir)
    t = time_grid(hdr["duration"], hdr["dt"])
    upd, dt_s, zsig = zupt_schedule(decl.get("zupt", {}), where, t, traj)
    ffile = _filters_file(fcfg, where, base_dir)
    specs = load_filters(ffile, truth)
    cases = fcfg.get("cases", list(specs))
    if not isinstance(cases, list):
        raise StudyFileError(f"{where}: [filters] cases", "expected a list of filter names")
    for c in cases:
        if c not in specs:
            raise StudyFileError(f"{where}: [filters] cases", f"unknown filter {c!r} (declared in {ffile}: "
                                 f"{', '.join(specs)})")
    ctx, dyn, Phi, Qd = truth_system(truth, traj, t, hdr["discretization"], progress=progress, where=where)
    nodes = traj.sample(t)
    P0 = initial_covariance(truth, nodes, where)
    moving = t[-1] - t[0] - sum(max(0.0, min(b, t[-1]) - max(a, t[0])) for a, b in traj.stationary)
    mean_speed = float(nodes.distance[-1] / moving) if moving > 0 else None
    H = zupt_matrices(truth.names)
    R = np.eye(3) * zsig**2
    return ZuptSetup(hdr, where, t, nodes, truth, ctx, dyn, Phi, Qd, P0, H, R, upd, dt_s, zsig, specs, cases,
                     mean_speed, ffile, every, rtimes)


def run(decl: dict, *, path=None, progress: bool = False) -> StudyResult:
    """Run the filter-order trade; see the module docstring."""
    t_start = time.perf_counter()
    S = setup(decl, path=path, progress=progress)
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
    ewn = pd.concat([fm.ewn_table for fm in fmodels.values() if len(fm.ewn_table)], ignore_index=True) \
        if any(len(fm.ewn_table) for fm in fmodels.values()) else pd.DataFrame()
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

    provenance = {"truth_model": truth.name, "truth_model_file": truth.path, "truth_model_sha256": truth.sha256,
                  "filter_file": str(ffile), "zupt_updates": int(len(upd)), "zupt_interval_s": dt_s,
                  "zupt_sigma_m_s": zsig, "mean_moving_speed_m_s": mean_speed, "compute_seconds": f"{elapsed:.2f}"}
    import hashlib
    provenance["filter_file_sha256"] = hashlib.sha256(Path(ffile).read_bytes()).hexdigest()
    return StudyResult(
        name=hdr["name"], kind="zupt_filter_order", tables=tables,
        figures={"fig6_horizontal_cep": fig("horizontal"), "fig7_altitude_pe": fig("altitude")},
        resolved={**decl, "study": {**decl["study"], "name": hdr["name"]}}, provenance=provenance,
        charts=[{"sheet": "history", "x": "t [min]", "y": ["CEP [ft]"], "title": "CEP (all cases, stacked rows)",
                 "y_title": "ft", "anchor": "S2"}],
        data={"t": t, "runs": runs, "filters": fmodels, "metrics": metrics, "claimed": claimed,
              "update_steps": upd, "trajectory": nodes, "truth": truth, "P0": P0, "Phi": Phi, "Qd": Qd,
              "H": H, "R": R},
    )


def dyn_key(options):
    """Cache key of a NavOptions (None: the truth's own)."""
    if options is None:
        return (True, True)
    return (options.coriolis, options.couple_vertical)
