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
* the linear analysis again with the truth's P0 replaced by the second
  moments of the initial states the M runs drew, INS and measurement-error
  states (the *conditional* prediction σ_cond: the expectation of the
  ensemble mean square given the draws; driving and measurement noise and
  the gains unchanged);
* the acceptance test of the ZUPT Monte Carlo (:mod:`covtool.studies.monte_carlo`,
  ``docs/monte_carlo.md``, "The acceptance test"): per cell (case × quantity:
  north, east, down, horizontal position, azimuth) the time mean T of
  RMS²/σ_cond² is tested two-sided against its null distribution, sampled by
  a linear Monte Carlo of the same setup from the same initial draws
  (:func:`covtool.validation.linear_mc.linear_mean_squares` with the truth
  H and R of every epoch, the error states appended to the truth Φ and
  Q_d), Bonferroni over the cells at the family-wise rate ``1 − confidence``
  (:func:`covtool.analysis.consistency.null_test`).  The share of times the
  RMS lies inside the χ² bounds of σ_cond is reported with its null 5th
  percentile; the bounds of the model's σ and the time mean of RMS/σ are
  reported beside it.

All measurement kinds have a nonlinear ``sensor``/``predict`` pair, so every
kind the ``aided`` kind accepts is simulated.

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
    confidence = 0.99          # family-wise: 1 % false alarms over all cells
    sensor_noise = true
    measurement_noise = true   # the measurements' white noise R and error-state driving noise
    null_replicas = 100        # linear Monte Carlo replicas of the null (0: no test, the bands only)

The runs go in one piece in-process (no chunks, no result store).
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np
import pandas as pd

from covtool.analysis.consistency import horizontal_dof, inside_fraction, null_test, rms_bounds
from covtool.analysis.metrics import nav_metrics, ned_position_covariance
from covtool.errors import StudyFileError
from covtool.io.config import check_keys, table
from covtool.io.filters import load_filters
from covtool.lincov.aided import error_processes, Jacobians
from covtool.lincov.kalman import symmetrize
from covtool.nav.imu.simulator import ImuSimulator
from covtool.plotting.aided import aided_ensemble_figure
from covtool.results import StudyResult
from covtool.studies.aided import (_measurement_table, _memory, check_error_state_names, filter_run,
                                   filter_system, measurement_steps, parse_measurements)
from covtool.studies.grid import initial_covariance, time_grid, truth_system
from covtool.studies.inputs import load_trajectory, load_truth, study_header, study_inputs
from covtool.studies.monte_carlo import mc_options, NULL_STREAM
from covtool.studies.resources import check_memory, resource_provenance
from covtool.studies.zupt_setup import filter_cases, filters_file
from covtool.units import ARCMIN
from covtool.validation.aided import run_aided_ensemble
from covtool.validation.linear_mc import linear_mean_squares, noise_factors, output_rows
from covtool.validation.sensor_errors import SensorErrors, sample_states

#: [monte_carlo] keys this study uses (the ZUPT kind's chunking and NEES keys are refused)
AIDED_MC_KEYS = {"runs", "seed", "imu_rate", "samples_per_step", "confidence", "sensor_noise", "measurement_noise",
                 "null_replicas"}
#: the defaults of :func:`covtool.studies.monte_carlo.mc_options`, as a study file writes them (resolved study)
MC_DEFAULTS = {"seed": 1, "imu_rate": "100 Hz", "samples_per_step": 4, "confidence": 0.95, "sensor_noise": True,
               "measurement_noise": True, "null_replicas": 100}
#: compared quantities: (name, σ key of nav_metrics, unit label, display scale)
QUANTITIES = (("north", "sigma_north", "m", 1.0), ("east", "sigma_east", "m", 1.0),
              ("down", "sigma_down", "m", 1.0), ("horizontal", "sigma_horizontal", "m", 1.0),
              ("azimuth", "sigma_azimuth", "arcmin", 1.0 / ARCMIN))
#: the rows of :func:`covtool.validation.linear_mc.output_rows` (north, east, down, azimuth) each quantity sums
GROUPS = {"north": (0,), "east": (1,), "down": (2,), "horizontal": (0, 1), "azimuth": (3,)}


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
        update inside the study, ``null_replicas`` between 1 and 9.
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
                                 f"one piece, no NEES); keys: {', '.join(sorted(AIDED_MC_KEYS))}")
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
    est = _memory(hdr, truth, specs, cases, {}, states, hdr["dt"], False)
    if opt["null_replicas"]:
        # the linear Monte Carlo: Φ, Q_d over [x_INS; e], its noise factors and float32 copies (≈ 3 N n²
        # doubles), two blocks of 20000 float32 columns
        na, steps_ = truth.n + len(states), hdr["duration"] / hdr["dt"]
        extra = 3.0 * steps_ * na * na * 8.0 + 2 * 20000 * na * 4.0
        est = {**est, "bytes": est["bytes"] + extra, "parts": {**est["parts"], "linear Monte Carlo (null)": extra}}
    est = check_memory(est, where, hdr["max_memory"], "a larger [study] dt, a shorter duration or fewer [filters] "
                       "cases")
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
    conf, R_null = opt["confidence"], opt["null_replicas"]
    cells = len(cases) * len(QUANTITIES)
    alpha_cell = (1.0 - conf) / cells          # Bonferroni: family-wise false-alarm rate 1 - confidence
    if R_null:
        # the truth [x_INS; e] of the linear Monte Carlo: the error states' exact scalar
        # transitions on the diagonal (seed 002, eq (15); covtool.lincov.aided)
        Phi_a, Qd_a = augmented_system(Phi, Qd, err)
        factors = noise_factors(Qd_a)
        C_out = output_rows(nodes.lat, nodes.h, nodes.q_nb)
    rows, hist, bands, tests = [], [], {}, {}
    jac = Jacobians(nodes)                 # the measurement Jacobians, shared by every case and run
    t_mc = t_null = 0.0
    for i, c in enumerate(cases):
        fm, Phi_f, Qd_f = filter_system(specs[c], truth, ctx, dyn, Phi, Qd, hdr, t, nodes, ewn_dt=ewn_dt,
                                        mean_speed=mean_speed, update_steps=all_steps, where=where)
        r, fnames, D, epochs = filter_run(fm, Phi, Qd, Phi_f, Qd_f, P0, states, kept, meas_pairs, nodes, names_all,
                                          err, every, form=specs[c].update, label=f"{where}: filter {c}",
                                          all_gains=True, jacobians=jac)
        m = nav_metrics(r.P_truth, nodes.lat, nodes.h, nodes.q_nb)
        dof_h = horizontal_dof(ned_position_covariance(r.P_truth[:, :3, :3], nodes.lat, nodes.h)[:, :2, :2])
        # one random stream per case, from the seed: the cases are independent ensembles
        rng = np.random.default_rng([opt["seed"], i])
        x0 = sample_states(truth, M, rng, q0=nodes.q_nb[0])
        e0 = rng.standard_normal((M, len(states))) * np.array([s.sigma for s in states])
        # the conditional prediction: the second moments of the drawn [x0, e0] in place of P0
        X0 = np.hstack([x0, e0])
        rc = filter_run(fm, Phi, Qd, Phi_f, Qd_f, P0, states, kept, meas_pairs, nodes, names_all, err, every,
                        form=specs[c].update, label=f"{where}: filter {c} (conditional)",
                        P0_truth=symmetrize(X0.T @ X0 / M), jacobians=jac)[0]
        mc_ = nav_metrics(rc.P_truth, nodes.lat, nodes.h, nodes.q_nb)
        dof_c = horizontal_dof(ned_position_covariance(rc.P_truth[:, :3, :3], nodes.lat, nodes.h)[:, :2, :2])
        sim = ImuSimulator(traj, opt["imu_rate"], t0=float(t[0]), duration=float(t[-1] - t[0]),
                           errors=SensorErrors(truth, x0, rng=rng, noise=opt["sensor_noise"]))
        t0 = time.perf_counter()
        errs = run_aided_ensemble(sim, x0, e0, t, samples_per_step=opt["samples_per_step"], plan=meas_pairs,
                                  epochs=epochs, gains=r.gains, filter_names=fnames, states=states, kept=kept,
                                  model=truth, err=err, rng=rng, measurement_noise=opt["measurement_noise"])
        t_mc += time.perf_counter() - t0
        t0 = time.perf_counter()
        null = None
        if R_null:
            # replicas of the M runs of the linear error-state system from the same draws (eq (15)-(16)):
            # the truth H and R of each epoch, the filter's correction D K; fresh driving and measurement noise
            null = linear_mean_squares(
                Phi_a, Qd_a, {c: {k: D @ K for k, K in r.gains.items()}}, C_out, runs=M, replicas=R_null, x0=X0,
                H={ep.step: ep.H for ep in epochs}, R={ep.step: ep.R for ep in epochs}, factors=factors,
                groups=GROUPS, rng=np.random.default_rng(np.random.SeedSequence(opt["seed"],
                                                                                 spawn_key=(NULL_STREAM, i))))[c]
        t_null += time.perf_counter() - t0
        rms = ensemble_rms(errs)
        for j, (q, key, unit, scale) in enumerate(QUANTITIES):
            sig, sig_c = m[key], mc_[key]
            lo, hi = rms_bounds(sig, M, dof_h if q == "horizontal" else 1.0, confidence=conf)
            lo_c, hi_c = rms_bounds(sig_c, M, dof_c if q == "horizontal" else 1.0, confidence=conf)
            bands[(c, q)] = (rms[q], sig, lo, hi)
            pts = (np.arange(t.size) >= 1) & (sig_c > 0)      # t = 0: no error to compare
            fr = inside_fraction(rms[q][pts], lo[pts], hi[pts])
            pos = pts & (sig > 0)
            ratio = float(np.mean(rms[q][pos] / sig[pos]))
            b_lo, b_hi = rms_bounds(1.0, M, float(np.mean(dof_h[pos])) if q == "horizontal" else 1.0,
                                    confidence=conf)
            row = {"case": c, "quantity": q, "mean RMS/σ": ratio, "ratio lower bound": float(b_lo),
                   "ratio upper bound": float(b_hi), "inside bounds [%]": 100 * fr["inside"],
                   "above [%]": 100 * fr["above"], "below [%]": 100 * fr["below"]}
            if null is not None:
                tests[(c, q)] = nt = null_test(rms[q] ** 2, null[:, :, j], sig_c, lo_c, hi_c, pts, alpha_cell)
                row.update({"conditional: inside [%]": 100 * nt["inside"],
                            "null: inside 5th percentile [%]": 100 * nt["inside_null_p5"],
                            "inside p-value (one-sided)": nt["inside_p"],
                            "T = time-mean RMS^2/sigma_cond^2": nt["T"], "T null mean": nt["T_null_mean"],
                            "T null std": nt["T_null_std"], "z = (T-1)/std": nt["z"], "p-value": nt["p"],
                            "p-value (rank among replicas)": nt["T_p_empirical"],
                            "cell false-alarm rate": alpha_cell})
            row.update({"final RMS": rms[q][-1] * scale, "final linear σ": sig[-1] * scale,
                        "final conditional σ": sig_c[-1] * scale, "unit": unit,
                        "verdict": ("reject" if tests[(c, q)]["reject"] else "accept") if null is not None
                        else "no test (null_replicas = 0)"})
            rows.append(row)
            hist.append(pd.DataFrame({"case": c, "quantity": q, "t [s]": t, "RMS": rms[q] * scale,
                                      "linear σ": sig * scale, "lower bound": lo * scale, "upper bound": hi * scale,
                                      "conditional σ": sig_c * scale, "conditional lower bound": lo_c * scale,
                                      "conditional upper bound": hi_c * scale, "unit": unit}))
        del r, rc, Phi_f, Qd_f, errs, null
    elapsed = time.perf_counter() - t_start
    summary = pd.DataFrame(rows)
    verdict = ("pass" if not any(v["reject"] for v in tests.values()) else "FAIL: " + ", ".join(
        f"{c} {q}" for (c, q), v in tests.items() if v["reject"])) if R_null else "none (null_replicas = 0)"
    tables = {"summary": summary, "history": pd.concat(hist, ignore_index=True),
              "measurements": _measurement_table(plan, steps, t), "truth_states": truth.state_table()}
    provenance = {**study_inputs(path, decl, truth, ffile), "truth_model": truth.name,
                  "truth_model_sha256": truth.sha256, "measurement_states": ", ".join(kept),
                  "runs": M, "seed": opt["seed"], "confidence": conf,
                  "imu_rate_hz": f"{opt['imu_rate']:g}", "updates": int(all_steps.size),
                  "equivalent_noise_interval_s": f"{ewn_dt:g}", **resource_provenance(est),
                  "acceptance_test": (f"per cell (case x quantity) T = time mean of RMS^2/sigma_cond^2 over t >= dt, "
                                      f"two-sided against its null from {R_null} replicas of a linear Monte Carlo "
                                      f"of the {M} runs from the same initial draws; Bonferroni over {cells} cells "
                                      f"(cell level {alpha_cell:.3g}, family-wise {1 - conf:.3g})" if R_null
                                      else "none (null_replicas = 0): the per-point bands only"),
                  "verdict": verdict,
                  "monte_carlo_seconds": f"{t_mc:.2f}", "null_seconds": f"{t_null:.2f}",
                  "compute_seconds": f"{elapsed:.2f}"}
    return StudyResult(name=hdr["name"], kind="monte_carlo", tables=tables,
                       figures={"mc_aided_ratio": partial(aided_ensemble_figure, hdr["name"],
                                                          [q for q, *_ in QUANTITIES], cases, bands, t, M, conf)},
                       resolved={**decl, "study": {**decl["study"], "name": hdr["name"]},
                                 "monte_carlo": {**MC_DEFAULTS, **decl["monte_carlo"]}},
                       provenance=provenance)


def augmented_system(Phi, Qd, err):
    """Truth Φ and Q_d over ``[x_INS; e]``: the error states' scalar processes appended.

    Parameters
    ----------
    Phi, Qd : ndarray, shape (N, n₀, n₀)
        INS truth transition and noise (seed 002, eq (15)).
    err : tuple of ndarray (phi, qd), each shape (N, n_e)
        Exact scalar transitions of the measurement-error states
        (:func:`covtool.lincov.aided.error_processes`).

    Returns
    -------
    Phi_a, Qd_a : ndarray, shape (N, n₀ + n_e, n₀ + n_e)
        ``blockdiag(Φ, diag φ)`` and ``blockdiag(Q_d, diag q_d)``, the
        one-step maps of :func:`covtool.lincov.aided.propagate_aided`.
    """
    phi, qd = (np.asarray(a, float) for a in err)
    N, n0, _ = Phi.shape
    n = n0 + phi.shape[1]
    Phi_a, Qd_a = np.zeros((N, n, n)), np.zeros((N, n, n))
    Phi_a[:, :n0, :n0], Qd_a[:, :n0, :n0] = Phi, Qd
    j = np.arange(n0, n)
    Phi_a[:, j, j], Qd_a[:, j, j] = phi, qd
    return Phi_a, Qd_a
