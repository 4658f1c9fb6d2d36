"""Monte Carlo with declared measurements (issue 15): ``monte_carlo`` with ``[[measurement]]``.

A ``monte_carlo`` study that declares ``[[measurement]]`` tables (the
declaration of the ``aided`` kind, :mod:`covtool.studies.aided`) instead of
``[zupt]`` runs here.  For each declared filter:

* the linear aided analysis: the truth ``[x_INS; e]`` under the filter's
  gains, seed 002, eq (15)–(16) (:func:`covtool.studies.aided.filter_run`,
  the ``aided`` kind's computation, every measurement-error state kept);
* M nonlinear strapdown runs with sensor errors drawn from the truth model
  and their own measurement-error realisation, aided by the feedback filter
  with those gains; the measurements are the library's nonlinear functions
  applied to the strapdown solution and the true trajectory
  (:func:`covtool.validation.aided.run_aided_ensemble`);
* per quantity (north, east, down, horizontal position, azimuth): the ensemble
  RMS against the linear σ inside the two-sided χ² bounds at ``confidence``
  (:func:`covtool.analysis.consistency.rms_bounds`; the horizontal error with
  its Satterthwaite dof, :func:`~covtool.analysis.consistency.horizontal_dof`).

The verdict of a (case, quantity) is the criterion of the ZUPT ensemble's and
the aided ensemble's tests (``tests/test_aiding_monte_carlo.py``): the RMS
lies inside the bounds at ``INSIDE_REQUIRED`` (95 %) of the times (the RMS
curves are correlated in time, so the share is not binomial), and the time
mean of RMS/σ lies inside the χ² bounds of one time.  No null distribution
(``null_replicas``) and no conditional σ: those are the ZUPT kind's.  All
measurement kinds have a nonlinear ``sensor``/``predict`` pair, so every kind
the ``aided`` kind accepts is simulated.

Study file::

    [study]
    kind = "monte_carlo"
    duration = "5 min"
    dt = "1 s"

    [trajectory]
    builtin = "land_vehicle"

    [filters]
    cases = ["A"]

    [[measurement]]            # as in the aided kind
    name = "odo"
    kind = "odometer"
    ...

    [monte_carlo]
    runs = 40
    seed = 1
    imu_rate = "100 Hz"
    samples_per_step = 4
    confidence = 0.99
    sensor_noise = true
    measurement_noise = true   # the measurements' white noise R and error-state driving noise

The runs go in one piece in-process (no chunks, no result store).
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from covtool.analysis.consistency import horizontal_dof, inside_fraction, rms_bounds
from covtool.analysis.metrics import nav_metrics, ned_position_covariance
from covtool.errors import StudyFileError
from covtool.io.config import check_keys, table
from covtool.io.filters import load_filters
from covtool.lincov.aided import error_processes
from covtool.nav.imu.simulator import ImuSimulator
from covtool.results import StudyResult
from covtool.studies.aided import (_measurement_table, _memory, check_error_state_names, filter_run,
                                   filter_system, measurement_steps, parse_measurements)
from covtool.studies.grid import initial_covariance, time_grid, truth_system
from covtool.studies.inputs import load_trajectory, load_truth, study_header, study_inputs
from covtool.studies.monte_carlo import mc_options
from covtool.studies.resources import check_memory, resource_provenance
from covtool.studies.zupt_setup import filter_cases, filters_file
from covtool.units import ARCMIN
from covtool.validation.aided import run_aided_ensemble
from covtool.validation.sensor_errors import SensorErrors, sample_states

#: [monte_carlo] keys this study uses (the ZUPT kind's chunking, NEES and null keys are refused)
AIDED_MC_KEYS = {"runs", "seed", "imu_rate", "samples_per_step", "confidence", "sensor_noise", "measurement_noise"}
#: the defaults of :func:`covtool.studies.monte_carlo.mc_options`, as a study file writes them (resolved study)
MC_DEFAULTS = {"seed": 1, "imu_rate": "100 Hz", "samples_per_step": 4, "confidence": 0.95, "sensor_noise": True,
               "measurement_noise": True}
#: share of the times the RMS must lie inside its bounds (tests/test_aiding_monte_carlo.py)
INSIDE_REQUIRED = 0.95
#: compared quantities: (name, σ key of nav_metrics, unit label, display scale)
QUANTITIES = (("north", "sigma_north", "m", 1.0), ("east", "sigma_east", "m", 1.0),
              ("down", "sigma_down", "m", 1.0), ("horizontal", "sigma_horizontal", "m", 1.0),
              ("azimuth", "sigma_azimuth", "arcmin", 1.0 / ARCMIN))


def ensemble_rms(errs: np.ndarray) -> dict:
    """Ensemble RMS of the compared quantities.

    Parameters
    ----------
    errs : ndarray, shape (N+1, M, 9)
        :func:`covtool.validation.aided.run_aided_ensemble` output (NED
        position [m], velocity [m/s], tilts and azimuth [rad]).

    Returns
    -------
    dict of str to ndarray, shape (N+1,)
        RMS per quantity of :data:`QUANTITIES`, SI.
    """
    ms = np.mean(errs ** 2, axis=1)
    return {"north": np.sqrt(ms[:, 0]), "east": np.sqrt(ms[:, 1]), "down": np.sqrt(ms[:, 2]),
            "horizontal": np.sqrt(ms[:, 0] + ms[:, 1]), "azimuth": np.sqrt(ms[:, 8])}


def run(decl: dict, *, path=None, progress: bool = False) -> StudyResult:
    """Run a Monte Carlo with declared measurements; see the module docstring.

    Raises
    ------
    StudyFileError
        ``[zupt]`` next to ``[[measurement]]``, an unknown key (also a
        ``[monte_carlo]`` key of the ZUPT kind this study does not use), a bad
        measurement declaration, a schedule outside the trajectory, no
        update inside the study.
    """
    t_start = time.perf_counter()
    where = str(path) if path else "<study>"
    base_dir = path.parent if path else None
    if "zupt" in decl:
        raise StudyFileError(f"{where}: [zupt]", "a Monte Carlo with [[measurement]] declares its ZUPTs as a "
                             "measurement (kind = \"zupt\"), not in [zupt]")
    check_keys(decl, {"study", "trajectory", "truth", "filters", "measurement", "monte_carlo", "output"}, where,
               StudyFileError)
    mc = decl.get("monte_carlo")
    if isinstance(mc, dict):
        extra = sorted(set(mc) - AIDED_MC_KEYS)
        if extra:
            raise StudyFileError(f"{where}: [monte_carlo] {extra[0]}", "not used with [[measurement]] (runs go in "
                                 f"one piece, no null distribution); keys: {', '.join(sorted(AIDED_MC_KEYS))}")
    opt = mc_options(decl, where)
    hdr = study_header(decl, where)
    plan, states = parse_measurements(decl["measurement"], where)
    kept = [s.name for s in states]
    fcfg = table(decl.get("filters", {}), f"{where}: [filters]", StudyFileError)
    check_keys(fcfg, {"file", "cases"}, f"{where}: [filters]", StudyFileError)
    truth = load_truth(decl, where, base_dir)
    ffile = filters_file(fcfg, where, base_dir)
    specs = load_filters(ffile, truth)
    cases = filter_cases(fcfg, specs, ffile, where, nonempty=True)
    check_error_state_names(plan, states, truth, where)
    est = check_memory(_memory(hdr, truth, specs, cases, {}, states, hdr["dt"], False), where, hdr["max_memory"],
                       "a larger [study] dt, a shorter duration or fewer [filters] cases")
    traj = load_trajectory(decl, where, base_dir, hdr["dt"], hdr["duration"])
    t = time_grid(hdr["duration"], hdr["dt"], where)
    nodes = traj.sample(t)
    steps, all_steps = measurement_steps(plan, t, nodes, where)   # every schedule, before any computation
    ewn_dt = float(t[-1]) / all_steps.size
    moving = t[-1] - sum(max(0.0, min(b, t[-1]) - max(a, 0.0)) for a, b in traj.stationary)
    mean_speed = float(nodes.distance[-1] / moving) if moving > 0 else None
    meas_pairs = list(zip([m for m, _ in plan], steps))
    names_all = list(truth.names) + kept
    err = error_processes(states, np.diff(t))[:2]
    every = np.arange(t.size)
    M = opt["runs"]

    ctx, dyn, Phi, Qd = truth_system(truth, traj, t, hdr["discretization"], progress=progress, where=where)
    P0 = initial_covariance(truth, nodes, where)
    rows, hist, bands = [], [], {}
    t_mc = 0.0
    for i, c in enumerate(cases):
        fm, Phi_f, Qd_f = filter_system(specs[c], truth, ctx, dyn, Phi, Qd, hdr, t, nodes, ewn_dt=ewn_dt,
                                        mean_speed=mean_speed, update_steps=all_steps, where=where)
        r, fnames, _, epochs = filter_run(fm, Phi, Qd, Phi_f, Qd_f, P0, states, kept, meas_pairs, nodes, names_all,
                                          err, every, form=specs[c].update, label=f"{where}: filter {c}",
                                          all_gains=True)
        m = nav_metrics(r.P_truth, nodes.lat, nodes.h, nodes.q_nb)
        dof_h = horizontal_dof(ned_position_covariance(r.P_truth[:, :3, :3], nodes.lat, nodes.h)[:, :2, :2])
        # one random stream per case, from the seed: the cases are independent ensembles
        rng = np.random.default_rng([opt["seed"], i])
        x0 = sample_states(truth, M, rng, q0=nodes.q_nb[0])
        e0 = rng.standard_normal((M, len(states))) * np.array([s.sigma for s in states])
        sim = ImuSimulator(traj, opt["imu_rate"], t0=float(t[0]), duration=float(t[-1] - t[0]),
                           errors=SensorErrors(truth, x0, rng=rng, noise=opt["sensor_noise"]))
        t0 = time.perf_counter()
        errs = run_aided_ensemble(sim, x0, e0, t, samples_per_step=opt["samples_per_step"], plan=meas_pairs,
                                  epochs=epochs, gains=r.gains, filter_names=fnames, states=states, kept=kept,
                                  model=truth, err=err, rng=rng, measurement_noise=opt["measurement_noise"])
        t_mc += time.perf_counter() - t0
        rms = ensemble_rms(errs)
        for q, key, unit, scale in QUANTITIES:
            sig = m[key]
            lo, hi = rms_bounds(sig, M, dof_h if q == "horizontal" else 1.0, confidence=opt["confidence"])
            bands[(c, q)] = (rms[q], sig, lo, hi)
            fr = inside_fraction(rms[q], lo, hi)
            pos = sig > 0
            ratio = float(np.mean(rms[q][pos] / sig[pos]))
            b_lo, b_hi = rms_bounds(1.0, M, float(np.mean(dof_h[pos])) if q == "horizontal" else 1.0,
                                    confidence=opt["confidence"])
            ok = fr["inside"] >= INSIDE_REQUIRED and b_lo < ratio < b_hi
            rows.append({"case": c, "quantity": q, "mean RMS/σ": ratio, "ratio lower bound": float(b_lo),
                         "ratio upper bound": float(b_hi), "inside bounds [%]": 100 * fr["inside"],
                         "above [%]": 100 * fr["above"], "below [%]": 100 * fr["below"],
                         "final RMS": rms[q][-1] * scale, "final linear σ": sig[-1] * scale, "unit": unit,
                         "verdict": "in bounds" if ok else "OUT OF BOUNDS"})
            hist.append(pd.DataFrame({"case": c, "quantity": q, "t [s]": t, "RMS": rms[q] * scale,
                                      "linear σ": sig * scale, "lower bound": lo * scale, "upper bound": hi * scale,
                                      "unit": unit}))
        del r, Phi_f, Qd_f, errs
    elapsed = time.perf_counter() - t_start
    summary = pd.DataFrame(rows)
    tables = {"summary": summary, "history": pd.concat(hist, ignore_index=True),
              "measurements": _measurement_table(plan, steps, t), "truth_states": truth.state_table()}
    provenance = {**study_inputs(path, decl, truth, ffile), "truth_model": truth.name,
                  "truth_model_sha256": truth.sha256, "measurement_states": ", ".join(kept),
                  "runs": M, "seed": opt["seed"], "confidence": opt["confidence"],
                  "imu_rate_hz": f"{opt['imu_rate']:g}", "updates": int(all_steps.size),
                  "equivalent_noise_interval_s": f"{ewn_dt:g}", **resource_provenance(est),
                  "monte_carlo_seconds": f"{t_mc:.2f}", "compute_seconds": f"{elapsed:.2f}"}
    return StudyResult(name=hdr["name"], kind="monte_carlo", tables=tables,
                       figures={"mc_aided_ratio": _figure(hdr["name"], cases, bands, t, M, opt["confidence"])},
                       resolved={**decl, "study": {**decl["study"], "name": hdr["name"]},
                                 "monte_carlo": {**MC_DEFAULTS, **decl["monte_carlo"]}},
                       provenance=provenance)


def _figure(study, cases, bands, t, runs, confidence):
    def make():
        import matplotlib.pyplot as plt
        qs = [q for q, *_ in QUANTITIES]
        fig, axs = plt.subplots(len(qs), 1, figsize=(9, 2.2 * len(qs)), sharex=True)
        for ax, q in zip(axs, qs):
            for c in cases:
                rms, sig, lo, hi = bands[(c, q)]
                pos = sig > 0
                line, = ax.plot(t[pos] / 60, rms[pos] / sig[pos], lw=1.0, label=f"filter {c}")
                ax.fill_between(t[pos] / 60, lo[pos] / sig[pos], hi[pos] / sig[pos], color=line.get_color(),
                                alpha=0.15, lw=0)
            ax.axhline(1.0, color="0.3", lw=0.8)
            ax.set_ylabel(f"{q}\nRMS/σ")
            ax.grid(True, alpha=0.3)
        axs[0].legend(fontsize=8)
        axs[-1].set_xlabel("time [min]")
        fig.suptitle(f"{study}: {runs}-run ensemble RMS / linear σ ({100 * confidence:g} % χ² bounds shaded)")
        return fig
    return make
