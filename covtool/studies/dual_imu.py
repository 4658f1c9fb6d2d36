"""Dual-IMU verification in flight (seed 001, method II).

A development IMU (the KIMU) flies beside the main IMU on a high-dynamics
flight; both navigate at once, each after its own alignment, and the two
solutions are compared after the mounting misalignment is compensated.
covtool predicts the covariance of the difference from the two grades'
error models, flags the intervals where the difference leaves that
envelope (a χ² test of the normalised innovations over sliding windows,
designed for a given false-alarm probability per flight), and detects and
estimates a g-sensitive gyro scale-factor error of the KIMU (seed 001,
Fig 16).  The same comparison runs on two recorded logs
(:func:`compare_logs`, ``covtool dualnav``).

Study file (datasheet units)::

    [study]
    kind = "dual_imu"
    name = "dual_imu_flight"

    [trajectory]
    builtin = "high_dynamics_flight"     # or segment/initial/vibration (covtool.nav.trajectory.flight)

    [imu.main]
    grade = "main_imu"                   # models/imu/*.toml
    mounting = ["0 deg", "0 deg", "0 deg"]     # roll, pitch, yaw of the sensor in the body
    [imu.kimu]
    grade = "kimu"
    mounting = ["2 deg", "-1.5 deg", "3 deg"]
    ratio = 4                            # KIMU samples per main sample

    [alignment]
    duration = "10 s"                    # at rest, at the start of the logs
    heading_sigma = "0.1 deg"            # the input heading both IMUs share
    # lat, lon, h, heading: the input position/heading (logs; a simulation takes the trajectory's)

    [comparison]
    interval = "1 s"                     # comparison epochs
    model_step = "0.04 s"                # step of the linear model
    components = ["velocity", "attitude"]
    noise = { position = "1 mm", velocity = "0.1 mm/s", attitude = "2 urad" }

    [monitor]
    window = "10 s"
    false_alarm = 0.01                   # per flight, for each test
    candidates = "all"                   # or ["z/x", ...]: gyro axis / accel axis

    [gaps]
    policy = "interpolate"               # hold | interpolate | propagate | refuse
    window = 10                          # samples averaged by interpolate/propagate
    trials = 8                           # trial bridges per side for the error prediction

    [simulation]
    runs = 200                           # fault-free flights (false-alarm rate)
    fault_runs = 50
    batch = 50
    seed = 1
    [simulation.fault]
    gyro = "z"
    accel = "x"
    coefficient = "1000 ppm/g"
    [[simulation.gap]]
    imu = "kimu"
    start = "14 s"
    duration = "40 ms"
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
import time

import numpy as np
import pandas as pd

from covtool.dualnav.difference import DIFF_NAMES
from covtool.dualnav.gaps import bridge_gaps, GapReport
from covtool.dualnav.monitor import candidate_label
from covtool.dualnav.run import as_runs, DualRun, DualSetup, ppm_text, run_dual
from covtool.errors import InputError, StudyFileError
from covtool.io.imu_log import check_imu_log
from covtool.nav import attitude as quat, earth
from covtool.plotting.dual_imu import DIFF_UNITS, dual_imu_figures
from covtool.progress import progress_bar
from covtool.results import DualImuResult
from covtool.studies.dual_imu_config import DualConfig, parse_study
from covtool.units import PPM_G
from covtool.studies.inputs import input_file
from covtool.validation.sensor_errors import GSensitiveErrors


def make_setup(cfg: DualConfig, initial: dict, where: str) -> DualSetup:
    """The numeric setup of :func:`covtool.dualnav.run.run_dual`."""
    for key in ("lat", "lon", "h", "heading"):
        if key not in initial:
            raise StudyFileError(f"{where}: [alignment]", f"missing {key!r}: the logs need the input position and "
                                 "heading (lat, lon, h, heading)")
    hm = 1.0 / cfg.grades["main"].rate
    return DualSetup(
        cfg.grades["main"].to_model(), cfg.grades["kimu"].to_model(), cfg.mounting["main"], cfg.mounting["kimu"],
        cfg.ratio, cfg.align_time, initial["lat"], initial["lon"], initial["h"], initial["heading"],
        cfg.heading_sigma, int(round(cfg.model_step / hm)), int(round(cfg.interval / hm)), cfg.components,
        cfg.noise, int(round(cfg.window / cfg.interval)), cfg.false_alarm, cfg.candidates)


# --------------------------------------------------------------------------
# simulation
# --------------------------------------------------------------------------


def _trajectory(decl, where):
    from covtool.io.flight import flight_from_config

    cfg = decl.get("trajectory", {"builtin": "high_dynamics_flight"})
    return flight_from_config(cfg, where=f"{where}: [trajectory]", dt=0.1)


def _initial_from_trajectory(traj) -> dict:
    s = traj.sample([float(traj.t[0])])
    return {"lat": float(s.lat[0]), "lon": float(s.lon[0]), "h": float(s.h[0]),
            "heading": float(quat.to_euler(s.q_nb)[0, 2])}


def simulate_logs(traj, cfg: DualConfig, n_runs: int, rng, *, fault=None, truth_cache=None):
    """Simulated logs of both IMUs (M runs) with the declared gaps.

    ``truth_cache`` (a dict shared by the batches of a study) holds the exact
    increments of the flight, which are the same for every batch
    (:class:`~covtool.nav.imu.simulator.ImuSimulator`).

    Returns
    -------
    logs : dict of str to (t, dtheta, dv, dt)
        Per IMU: sample end times (gap samples removed) and increments
        (M, K, 3).
    removed : dict of str to list of (ndarray, ndarray, ndarray)
        Per IMU and gap: the removed sample indices and their true increments.
    """
    from covtool.nav.trajectory.flight import quadrature_nodes
    from covtool.nav.imu.simulator import ImuSimulator
    from covtool.validation.sensor_errors import sample_states

    logs, removed = {}, {}
    for key in ("main", "kimu"):
        g = cfg.grades[key]
        model = g.to_model()
        x0 = sample_states(model, n_runs, rng)
        gs = ()
        if key == "kimu" and fault is not None:
            gs = (fault,)
        err = GSensitiveErrors(model, x0, rng, gsens=gs)
        sim = ImuSimulator(traj, g.rate, errors=err, quantization=g.quantization, saturation=g.range,
                           mounting=cfg.mounting[key], nodes=quadrature_nodes(traj, g.rate), truth_cache=truth_cache)
        rec = sim.record()
        t = rec.t
        keep = np.ones(t.size, bool)
        removed[key] = []
        for imu, start, dur in cfg.gaps:
            if imu != key:
                continue
            idx = np.flatnonzero((t > start + 1e-9) & (t <= start + dur + 1e-9))
            keep[idx] = False
            removed[key].append((idx, rec.dtheta[:, idx].copy(), rec.dv[:, idx].copy()))
        logs[key] = (t[keep], rec.dtheta[:, keep], rec.dv[:, keep], rec.dt)
    return logs, removed


def bridge(logs, cfg: DualConfig, where="logs"):
    """Bridge both logs' gaps by the study's policy."""
    out = {}
    for key in ("main", "kimu"):
        t, th, dv, dt = logs[key]
        m = cfg.grades[key].to_model()
        out[key] = bridge_gaps(t, th, dv, dt, cfg.gap_policy, arw=m.arw, vrw=m.vrw, imu=key,
                                  window=cfg.gap_window, trials=cfg.gap_trials, where=f"{where} ({key})")
    return out


def _actual_gap_errors(bridged, removed):
    """RMS over runs of the summed-increment error of every simulated gap."""
    rows = []
    for key, lst in removed.items():
        b = bridged[key]
        filled = np.flatnonzero(b.bridged)
        for (idx, th, dv), rep in zip(lst, b.gaps):
            # the bridged samples of this gap are the n filled ones after rep.after
            sel = filled[(b.t[filled] > rep.after + 1e-9) & (b.t[filled] < rep.before - 1e-9)]
            e_th = as_runs(b.dtheta)[:, sel].sum(axis=1) - th.sum(axis=1)
            e_v = as_runs(b.dv)[:, sel].sum(axis=1) - dv.sum(axis=1)
            rows.append((np.sqrt(np.mean(e_th**2, axis=0)), np.sqrt(np.mean(e_v**2, axis=0))))
    return rows


def run(decl: dict, *, path=None, progress: bool = False) -> DualImuResult:
    """Run a dual-IMU verification study; see the module docstring."""
    where = str(path) if path else "<study>"
    base_dir = path.parent if path else None
    t0 = time.perf_counter()
    cfg = parse_study(decl, where, base_dir)
    traj = _trajectory(decl, where)
    if not any(a <= 1e-9 and b >= cfg.align_time - 1e-9 for a, b in traj.stationary):
        raise StudyFileError(f"{where}: [alignment] duration", f"{cfg.align_time:g} s: the flight must start "
                             "with a stand at least as long as the alignment")
    initial = {**_initial_from_trajectory(traj)}
    setup = make_setup(cfg, initial, where)
    root = np.random.SeedSequence(cfg.seed)
    ss_free, ss_fault = root.spawn(2)
    # every batch: (label, flights, its own seed sequence, fault); a batch's numbers depend only on
    # its seed and the shared difference model, not on where or in which order it runs
    jobs = []
    for label, n_runs, ss, fault in (("fault_free", cfg.runs, ss_free, None),
                                     ("fault", cfg.fault_runs, ss_fault, cfg.fault)):
        batches = [min(cfg.batch, n_runs - a) for a in range(0, n_runs, cfg.batch)]
        jobs += [(label, b, seq, fault) for b, seq in zip(batches, ss.spawn(len(batches)))]
    bar = progress_bar(cfg.runs + cfg.fault_runs, "flights", progress, unit="flight")   # closed below or by GC
    truth_cache = {}   # the flight's exact increments, sampled once for all batches
    # the first batch linearises the one difference model of the study (along its run 0) and reports the gaps
    first, gap_rows = _batch(traj, cfg, setup, initial, jobs[0], None, truth_cache, where, report_gaps=True)
    model = first.model
    bar.update(jobs[0][1])
    done = [first]
    rest = jobs[1:]
    # the other batches in two processes when the machine has two cores: a forked child takes the
    # second half (it inherits the model, its Whitener record and the exact increments)
    child = None
    if len(rest) >= 2 and (os.cpu_count() or 1) >= 2:
        from covtool.forked import Forked

        mine, theirs = rest[:(len(rest) + 1) // 2], rest[(len(rest) + 1) // 2:]
        child = Forked(_batches_detached, traj, cfg, setup, initial, theirs, model, truth_cache, where)
    else:
        mine, theirs = rest, []
    try:
        for job in mine:
            done.append(_batch(traj, cfg, setup, initial, job, model, truth_cache, where)[0])
            bar.update(job[1])
        if child is not None:
            done += [dataclasses.replace(r, model=model) for r in child.result()]
            bar.update(sum(job[1] for job in theirs))
    finally:
        if child is not None:
            child.cancel()
    bar.close()
    outcome = {"fault_free": [], "fault": []}
    for job, r in zip(jobs, done):
        outcome[job[0]].append(r)
    elapsed = time.perf_counter() - t0
    return _result(cfg, decl, traj, setup, outcome, gap_rows, elapsed)


def _batch(traj, cfg: DualConfig, setup: DualSetup, initial: dict, job, model, truth_cache, where,
           report_gaps: bool = False):
    """One batch of simulated flights: simulate, bridge, navigate, compare.

    Returns the :class:`~covtool.dualnav.run.DualRun` and, with
    ``report_gaps``, the rows of the gap report (actual errors pooled over
    the batch's flights).
    """
    _label, b, seq, fault = job
    rng = np.random.default_rng(seq)
    logs, removed = simulate_logs(traj, cfg, b, rng, fault=fault, truth_cache=truth_cache)
    bridged = bridge(logs, cfg, where=f"{where}: simulated logs")
    psi = initial["heading"] + cfg.heading_sigma * rng.standard_normal(b)
    r = run_dual(bridged["main"], bridged["kimu"], setup, heading=psi, model=model)
    rows = []
    if report_gaps:
        actual = _actual_gap_errors(bridged, removed)
        for rep, (a_th, a_v) in zip(bridged["main"].gaps + bridged["kimu"].gaps, actual):
            rows.append(_gap_row(rep, a_th, a_v))
    return r, rows


def _batches_detached(traj, cfg, setup, initial, jobs, model, truth_cache, where):
    """:func:`_batch` over ``jobs`` (in a forked child); the shared model is left out of the results."""
    return [dataclasses.replace(_batch(traj, cfg, setup, initial, job, model, truth_cache, where)[0], model=None)
            for job in jobs]


def _gap_row(rep: GapReport, actual_att=None, actual_vel=None) -> dict:
    row = {"imu": rep.imu, "after [s]": rep.after, "before [s]": rep.before, "samples bridged": rep.samples,
           "duration [ms]": 1e3 * (rep.before - rep.after), "policy": rep.policy, "trials": rep.trials}
    for k, a in enumerate("xyz"):
        row[f"predicted att {a} [urad]"] = 1e6 * rep.sigma_attitude[k]
    for k, a in enumerate("xyz"):
        row[f"predicted vel {a} [mm/s]"] = 1e3 * rep.sigma_velocity[k]
    if actual_att is not None:
        for k, a in enumerate("xyz"):
            row[f"actual RMS att {a} [urad]"] = 1e6 * actual_att[k]
        for k, a in enumerate("xyz"):
            row[f"actual RMS vel {a} [mm/s]"] = 1e3 * actual_vel[k]
    return row


def _history(run: DualRun, i: int, label: str) -> pd.DataFrame:
    comps = run.model.components
    df = pd.DataFrame({"case": label, "run": i, "t [s]": run.t})
    for c_i, c in enumerate(comps):
        name = DIFF_NAMES[c]
        unit, scale = DIFF_UNITS[name[:3]]
        df[f"{name} [{unit}]"] = scale * run.z[i, :, c]
        df[f"{name} 1sigma [{unit}]"] = scale * run.envelope[:, c_i]
    df["NIS"] = run.inn.nis[i]
    w = run.window_stat.shape[1]
    stat = np.full(run.t.size, np.nan)
    stat[run.t.size - w:] = run.window_stat[i]
    df["window chi2 (ending here)"] = stat
    df["window threshold"] = run.window_threshold
    return df


def _run_rows(runs, label, cfg, truth=None):
    rows = []
    k = 0
    for r in runs:
        gs = r.gsens
        for i in range(r.z.shape[0]):
            best = int(gs.identified[i])
            row = {"case": label, "run": k, "max window chi2": float(r.window_stat[i].max()),
                   "window threshold": r.window_threshold, "window alarm": bool(r.flagged[i].any()),
                   "flagged intervals [s]": "; ".join(f"{a:.0f}-{b:.0f}" for a, b in r.intervals[i]),
                   "max GLR": float(gs.glr[i, best]), "GLR threshold": gs.threshold,
                   "g-sensitivity detected": bool(gs.detected[i]),
                   "identified": candidate_label(gs.candidates[best])}
            if truth is not None:
                c = gs.candidates.index((truth[0], truth[1]))
                est = gs.estimate[i, c]
                row.update({"estimate [ppm/g]": est / PPM_G, "1sigma [ppm/g]": gs.sigma[c] / PPM_G,
                            "error [%]": 100.0 * (est - truth[2]) / truth[2],
                            "correctly identified": bool(gs.detected[i] and best == c)})
            rows.append(row)
            k += 1
    return pd.DataFrame(rows)


def _result(cfg, decl, traj, setup, outcome, gap_rows, elapsed) -> DualImuResult:
    free, fault = outcome["fault_free"], outcome["fault"]
    t_free = _run_rows(free, "fault-free", cfg)
    t_fault = _run_rows(fault, "g-sensitivity injected", cfg, cfg.fault)
    n0, n1 = len(t_free), len(t_fault)
    summary = [
        ("flight duration", traj.duration, "s", traj.name),
        ("IMUs", f"{cfg.grades['main'].name} @ {cfg.grades['main'].rate:g} Hz, "
                 f"{cfg.grades['kimu'].name} @ {cfg.grades['kimu'].rate:g} Hz", "", "seed 001 Table 2 grades"),
        ("compared components", ", ".join(DIFF_NAMES[c] for c in cfg.components), "",
         f"every {cfg.interval:g} s after a {cfg.align_time:g} s alignment"),
        ("false-alarm design per flight", 100.0 * cfg.false_alarm, "%",
         f"each test; window test Bonferroni over sliding {cfg.window:g} s windows, GLR over "
         f"{len(cfg.candidates)} candidates"),
    ]
    if n0:
        fa_w = int(t_free["window alarm"].sum())
        fa_g = int(t_free["g-sensitivity detected"].sum())
        fa_any = int((t_free["window alarm"] | t_free["g-sensitivity detected"]).sum())
        summary += [
            ("fault-free flights", n0, "", f"seed {cfg.seed}, independent errors per flight"),
            ("false alarms, window test", 100.0 * fa_w / n0, "%", f"{fa_w} of {n0} flights"),
            ("false detections, g-sensitivity GLR", 100.0 * fa_g / n0, "%", f"{fa_g} of {n0} flights"),
            ("false alarms, either test", 100.0 * fa_any / n0, "%", f"{fa_any} of {n0} flights"),
            ("mean NIS per epoch", float(np.mean(np.concatenate([r.inn.nis for r in free]))), "",
             f"expected {len(cfg.components)} (the compared components)"),
        ]
    if n1:
        det = int(t_fault["g-sensitivity detected"].sum())
        ok = int(t_fault["correctly identified"].sum())
        alarm = int(t_fault["window alarm"].sum())
        err = t_fault["error [%]"].to_numpy()
        est = t_fault["estimate [ppm/g]"].to_numpy()
        summary += [
            ("g-sensitivity injected", f"KIMU gyro {candidate_label(cfg.fault)}: {cfg.fault[2] / PPM_G:g}",
             "ppm/g", "δω_i = k f_j ω_i (seed 001 Fig 16)"),
            ("flights with the fault", n1, "", ""),
            ("detected (GLR)", 100.0 * det / n1, "%", f"{det} of {n1}"),
            ("correctly identified", 100.0 * ok / n1, "%", f"{ok} of {n1}"),
            ("flagged by the window test", 100.0 * alarm / n1, "%", f"{alarm} of {n1}"),
            ("coefficient estimate, mean", float(est.mean()), "ppm/g", f"true {cfg.fault[2] / PPM_G:g}"),
            ("coefficient estimate, std", float(est.std(ddof=1)) if n1 > 1 else float("nan"), "ppm/g",
             f"predicted 1σ {float(t_fault['1sigma [ppm/g]'].mean()):.1f}"),
            ("largest |error|", float(np.max(np.abs(err))), "%", "acceptance: < 20 %"),
            ("estimates within 20 %", 100.0 * float(np.mean(np.abs(err) < 20.0)), "%", ""),
        ]
    summary += [("bridged gaps", len(gap_rows), "", f"policy {cfg.gap_policy!r}"),
                ("wall time", elapsed, "s", "")]
    summary = pd.DataFrame(summary, columns=["item", "value", "unit", "note"])
    summary["value"] = summary["value"].astype(object)
    tables = {"summary": summary, "fault_free_runs": t_free, "fault_runs": t_fault}
    ref = (free or fault)[0]
    cand = {"candidate": [candidate_label(c) for c in cfg.candidates],
            "1sigma [ppm/g]": ref.gsens.sigma / PPM_G}
    if fault:
        g = np.concatenate([r.gsens.glr for r in fault])
        e = np.concatenate([r.gsens.estimate for r in fault])
        cand["fault runs: mean estimate [ppm/g]"] = e.mean(axis=0) / PPM_G
        cand["fault runs: mean GLR"] = g.mean(axis=0)
    if free:
        g = np.concatenate([r.gsens.glr for r in free])
        cand["fault-free runs: mean GLR (expected 1)"] = g.mean(axis=0)
    tables["candidates"] = pd.DataFrame(cand)
    hist = [_history(free[0], 0, "fault-free")] if free else []
    if fault:
        hist.append(_history(fault[0], 0, "g-sensitivity injected"))
    tables["history"] = pd.concat(hist, ignore_index=True)
    tables["gaps"] = pd.DataFrame(gap_rows)
    tables["main_states"] = setup.main_model.state_table()
    tables["kimu_states"] = setup.kimu_model.state_table()
    result = DualImuResult(
        name=cfg.name, kind="dual_imu", tables=tables,
        resolved={**decl, "study": {**decl.get("study", {}), "name": cfg.name}},
        provenance={**input_file("main_grade", cfg.grades["main"].path),
                    **input_file("kimu_grade", cfg.grades["kimu"].path),
                    "main_model_sha256": setup.main_model.sha256, "kimu_model_sha256": setup.kimu_model.sha256,
                    "joint_states": ref.model.n, "epochs": ref.t.size, "compute_seconds": f"{elapsed:.2f}"},
        config=cfg, fault_free=list(free), fault=list(fault))
    result.figures = dual_imu_figures(result)
    return result


# --------------------------------------------------------------------------
# recorded logs
# --------------------------------------------------------------------------


def compare_logs(main_log, kimu_log, decl: dict, *, path=None, progress: bool = False) -> DualImuResult:
    """The dual-IMU comparison of two recorded logs.

    Parameters
    ----------
    main_log, kimu_log : covtool.io.imu_log.ImuLog
        Logs from the start of the alignment (vehicle at rest).
    decl : dict
        A ``dual_imu`` study declaration; ``[alignment]`` must give the
        input ``lat``, ``lon``, ``h`` and ``heading``; ``[trajectory]`` and
        ``[simulation]`` are ignored.
    path : Path, optional
        The study file (messages, relative grade paths).
    progress : bool
        Show a bar of the three phases (two logs bridged, then navigated).

    Returns
    -------
    DualImuResult
        Tables ``summary``, ``history``, ``gaps`` (every bridged interval),
        ``intervals`` (flagged spans), ``candidates``; figures.

    Raises
    ------
    InputError
        Bad logs (columns, time), rates that do not match the grades, gaps
        with policy ``refuse``, logs too short for the alignment and a
        window.
    """
    where = str(path) if path else "<study>"
    base_dir = path.parent if path else None
    t0 = time.perf_counter()
    cfg = parse_study(decl, where, base_dir)
    setup = make_setup(cfg, cfg.initial, where)
    bridged = {}
    bar = progress_bar(3, "logs", progress, unit="phase")   # bridge main, bridge KIMU, navigate and compare
    for key, log in (("main", main_log), ("kimu", kimu_log)):
        bar.update(0 if key == "main" else 1)
        rate = cfg.grades[key].rate
        dt = 1.0 / rate
        measured = log.period
        if abs(measured - dt) > 0.01 * dt:
            raise InputError(f"{log.path}: column 't [s]'", f"median sample period {measured:.9g} s does not match "
                             f"the {key} grade's rate {rate:g} Hz ({dt:.9g} s)")
        gyro_range, accel_range = cfg.grades[key].range
        check_imu_log(log, period=dt, gyro_range=gyro_range, accel_range=accel_range, align_time=cfg.align_time,
                      gravity=float(np.linalg.norm(earth.gravity_n(setup.lat, setup.h))), label=key)
        m = cfg.grades[key].to_model()
        bridged[key] = bridge_gaps(log.t, log.dtheta, log.dv, dt, cfg.gap_policy, arw=m.arw, vrw=m.vrw, imu=key,
                                      window=cfg.gap_window, trials=cfg.gap_trials, where=log.path)
    bar.update(1)
    r = run_dual(bridged["main"], bridged["kimu"], setup)
    bar.update(1)
    bar.close()
    elapsed = time.perf_counter() - t0
    gs = r.gsens
    best = int(gs.identified[0])
    summary = [
        ("main log", main_log.path, "", f"{main_log.t.size} samples"),
        ("KIMU log", kimu_log.path, "", f"{kimu_log.t.size} samples"),
        ("compared span", f"{r.t[0]:.3f} to {r.t[-1]:.3f}", "s", f"{r.t.size} epochs"),
        ("samples not compared (before, after)",
         f"main {r.unused['main'][0]}, {r.unused['main'][1]}; KIMU {r.unused['kimu'][0]}, {r.unused['kimu'][1]}", "",
         "outside the common span or after the last whole comparison interval"),
        ("clock rates", f"main {ppm_text(r.clock['main'])}, KIMU {ppm_text(r.clock['kimu'])}; mismatch "
         f"{ppm_text(r.clock['mismatch'])}",
         "ppm", "measured from the recorded times, against the grades' nominal rates"),
        ("bridged gaps", len(bridged["main"].gaps) + len(bridged["kimu"].gaps), "",
         f"{int(bridged['main'].bridged.sum()) + int(bridged['kimu'].bridged.sum())} samples, policy "
         f"{cfg.gap_policy!r}"),
        ("window alarms", len(r.intervals[0]), "intervals",
         "; ".join(f"{a:.1f}-{b:.1f} s" for a, b in r.intervals[0]) or "none"),
        ("window threshold", r.window_threshold, "", f"α = {cfg.false_alarm:g} per flight"),
        ("max window chi2", float(r.window_stat[0].max()), "", ""),
        ("g-sensitivity detected", bool(gs.detected[0]), "", f"GLR {gs.glr[0, best]:.1f} vs {gs.threshold:.1f}"),
        ("most likely candidate", candidate_label(gs.candidates[best]), "", "gyro axis / accel axis"),
        ("its coefficient", gs.estimate[0, best] / PPM_G, "ppm/g", f"1σ {gs.sigma[best] / PPM_G:.1f} ppm/g"),
        ("wall time", elapsed, "s", ""),
    ]
    summary = pd.DataFrame(summary, columns=["item", "value", "unit", "note"])
    summary["value"] = summary["value"].astype(object)
    gaps = pd.DataFrame([_gap_row(g) for g in bridged["main"].gaps + bridged["kimu"].gaps])
    intervals = pd.DataFrame([{"start [s]": a, "end [s]": b} for a, b in r.intervals[0]],
                             columns=["start [s]", "end [s]"])
    cand = pd.DataFrame({"candidate": [candidate_label(c) for c in gs.candidates],
                         "estimate [ppm/g]": gs.estimate[0] / PPM_G, "1sigma [ppm/g]": gs.sigma / PPM_G,
                         "GLR": gs.glr[0]})
    tables = {"summary": summary, "history": _history(r, 0, "logs"), "gaps": gaps, "intervals": intervals,
              "candidates": cand}
    result = DualImuResult(
        name=f"dualnav_{Path(main_log.path).stem}", kind="dualnav", tables=tables,
        config=cfg, fault_free=[r], fault=[], labels=("logs", ""), estimates=False,
        resolved={**decl, "logs": {"main": main_log.path, "kimu": kimu_log.path}},
        provenance={**input_file("main_grade", cfg.grades["main"].path),
                    **input_file("kimu_grade", cfg.grades["kimu"].path), "compute_seconds": f"{elapsed:.2f}"},
        bridged=bridged,
    )
    result.figures = dual_imu_figures(result)
    return result
