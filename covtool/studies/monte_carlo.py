"""Monte Carlo validation of the covariance analysis (issue 6).

N nonlinear INS runs (:mod:`covtool.nav.strapdown`) on simulated IMU data with
errors drawn from the truth model (:mod:`covtool.nav.imu`), unaided and under
each declared ZUPT filter running as a real feedback filter
(:mod:`covtool.validation.monte_carlo`), against the linear covariance analysis of the
same setup (:func:`covtool.lincov.reference.propagate`,
:func:`~covtool.lincov.reference.propagate_with_filter`).

Study file (the ``zupt_filter_order`` sections plus ``[monte_carlo]``)::

    [study]
    kind = "monte_carlo"
    duration = "30 min"
    dt = "1 s"                 # grid of the linear analysis, the updates and the statistics

    [trajectory]
    builtin = "land_vehicle"

    [truth]
    model = "sdins58"

    [filters]
    cases = ["B1", "C", "D"]
    pure_ins = true

    [zupt]
    interval = "5 min"
    duration = "30 s"
    rate = "1 Hz"
    sigma = "0.01 ft/s"

    [monte_carlo]
    runs = 200                 # N
    runs_per_chunk = 50        # one chunk = one task of the execution backend
    seed = 1
    imu_rate = "100 Hz"
    samples_per_step = 4       # 25 Hz navigation
    confidence = 0.95
    nees_every = "10 s"        # default: [output] history_every
    sensor_noise = true        # false: only the deterministic part (constants, Markov decay)
    measurement_noise = true
    process_dt = "0.1 s"       # grid of the sensor-error processes
    null_replicas = 100        # linear Monte Carlo replicas of the acceptance test's null (0: bands only)

Besides the linear σ from the model's P0 (unconditional), the study runs the
linear analysis with the sample second moments of the initial states the N runs
drew (:func:`_sample_moment`; driving noise, ZUPT noise and gains unchanged):
the expectation of the ensemble mean square *given* the draws.  The acceptance
test applies to this conditional comparison: per cell (case × quantity) the
time mean T of RMS²/σ² is tested two-sided against its null distribution, sampled
by a linear Monte Carlo of the same setup from the same initial draws
(:func:`covtool.validation.linear_mc.linear_mean_squares`,
:func:`covtool.analysis.consistency.null_test`), Bonferroni over the cells at the
family-wise rate ``1 − confidence``; the in-bounds share of the χ² bands is
reported with its null 5th percentile and p-value (``docs/monte_carlo.md``,
"The acceptance test").  An exact-variance band (:func:`conditional_dof`) is
reported beside it.

Chunks of runs go to a :mod:`covtool.parallel` backend: the one given
(``covtool run --workers N`` or ``--scheduler``), else local processes, one
per CPU.  The conditional and driven-part analyses and the linear Monte Carlo
need only the draws and the gains, so threads of the study's process compute
them while the chunks run (both cores busy; the linear Monte Carlo draws its
random numbers in a thread of its own); their results do not depend on it.
The trajectory as every chunk samples it (:func:`~covtool.validation.monte_carlo.reference_along`)
needs only the update steps and the filters' states: on two cores a forked
process samples it while this one computes the gains, so the chunks start
as soon as the gains exist (the same calls, the same numbers).  With a
result store (``covtool run`` keeps one in ``OUT/cases``) every finished
chunk is stored and ``--resume`` reuses it.

With ``[[measurement]]`` tables (the aided kind's declaration) instead of
``[zupt]``, the study runs in :mod:`covtool.studies.aided_monte_carlo` (issue 15).
"""

from __future__ import annotations

import math
import os
import threading
import time
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd

from covtool.analysis.consistency import (expected_nees, horizontal_dof, inside_fraction, nees_bounds,
                                          nees_whitening, null_test, REDUCED_NAV, rms_bounds)
from covtool.analysis.metrics import nav_metrics, ned_position_covariance, validity_text
from covtool.errors import StudyFileError
from covtool.forked import can_split, Forked
from covtool.parallel import DaskBackend
from covtool.io.config import boolean, check_keys, integer, LIMITS, number, quantity
from covtool.lincov.history import AtSteps
from covtool.lincov.kalman import symmetrize
from covtool.lincov.reduced import zupt_matrices
from covtool.lincov.reference import propagate, propagate_with_filter
from covtool.nav.coning import MAX_SAMPLES
from covtool.nav.strapdown import NAV_STATES
from covtool.plotting.monte_carlo import case_figure, nees_figure, ratio_figure
from covtool.results import MonteCarloResult
from covtool.studies.inputs import length_unit, study_header, study_inputs
from covtool.studies.resources import HELD_CHUNKS, noise_columns, resource_provenance, run_in_chunks
from covtool.studies.tables import case_validity
from covtool.studies.zupt_setup import setup
from covtool.units import ARCMIN
from covtool.validation.feedback import FeedbackFilter, gain_steps
from covtool.validation.linear_mc import GROUPS, linear_mean_squares, output_rows
from covtool.validation.monte_carlo import (EnsembleCase, EnsembleSums, initial_states, reference_along,
                                             reference_inputs, SharedReference, simulate_chunk)
from covtool.version import __version__

__all__ = [
    "run", "mc_options", "conditional_dof",
]


MC_KEYS = ("runs", "runs_per_chunk", "seed", "imu_rate", "samples_per_step", "confidence", "nees_every",
           "sensor_noise", "measurement_noise", "process_dt", "null_replicas")
#: spawn key of the linear Monte Carlo's random stream (the chunks use (0,), (1,), …)
NULL_STREAM = 0x6E756C6C
#: the compared quantities: label, unit of the tables, factor from SI
COMPARED = (("horizontal", "m", 1.0), ("altitude", "m", 1.0), ("azimuth", "arcmin", ARCMIN))
#: column of each compared quantity in the linear Monte Carlo's mean squares
QUANTITY_INDEX = {q: i for i, q in enumerate(GROUPS)}


def mc_options(decl: dict, where: str) -> dict:
    """Validate ``[monte_carlo]`` (before any expensive work).

    Raises
    ------
    StudyFileError
        Missing table or ``runs``, unknown key, bad number or unit, a
        duration that is not a whole number of grid steps ``dt``, an IMU rate
        that does not put a whole number of navigation steps into one grid
        step.
    """
    cfg = decl.get("monte_carlo")
    if not isinstance(cfg, dict):
        raise StudyFileError(where, "missing [monte_carlo] table (runs = ..., imu_rate = ..., ...)")
    w = f"{where}: [monte_carlo]"
    check_keys(cfg, set(MC_KEYS), w, StudyFileError)
    if "runs" not in cfg:
        raise StudyFileError(w, "missing required key 'runs' (the number of Monte Carlo runs)")
    hdr = study_header(decl, where)
    o = {
        "runs": integer(cfg["runs"], f"{w} runs", StudyFileError, limit="mc_runs"),
        "runs_per_chunk": integer(cfg.get("runs_per_chunk", 50), f"{w} runs_per_chunk", StudyFileError,
                                  limit="mc_runs_per_chunk"),
        "seed": integer(cfg.get("seed", 1), f"{w} seed", StudyFileError, limit="seed"),
        "imu_rate": quantity(cfg.get("imu_rate", "100 Hz"), "frequency", f"{w} imu_rate", StudyFileError,
                             positive=True, hi=LIMITS["imu_rate"].hi, why=LIMITS["imu_rate"].reason),
        "samples_per_step": integer(cfg.get("samples_per_step", 4), f"{w} samples_per_step", StudyFileError,
                                    lo=1, hi=MAX_SAMPLES),
        "sensor_noise": boolean(cfg.get("sensor_noise", True), f"{w} sensor_noise", StudyFileError),
        "measurement_noise": boolean(cfg.get("measurement_noise", True), f"{w} measurement_noise", StudyFileError),
        "process_dt": quantity(cfg.get("process_dt", "0.1 s"), "time", f"{w} process_dt", StudyFileError,
                               positive=True),
        "null_replicas": integer(cfg.get("null_replicas", 100), f"{w} null_replicas", StudyFileError, lo=0,
                                 hi=100000),
    }
    if 0 < o["null_replicas"] < 10:
        raise StudyFileError(f"{w} null_replicas", f"{o['null_replicas']} replicas cannot give a null distribution; "
                             "use at least 10 (or 0: no acceptance test, the per-point bands only)")
    o["confidence"] = number(cfg.get("confidence", 0.95), f"{w} confidence", StudyFileError, lo=0.0, hi=1.0,
                             lo_open=True, hi_open=True)
    every = (decl.get("output") or {}).get("history_every", "10 s")
    o["nees_every"] = quantity(cfg.get("nees_every", every), "time", f"{w} nees_every", StudyFileError,
                               positive=True)
    if o["process_dt"] * o["imu_rate"] < 1 - 1e-9:
        raise StudyFileError(f"{w} process_dt", f"{o['process_dt']:g} s is shorter than one IMU sample "
                             f"({1 / o['imu_rate']:g} s); the sensor errors are injected per sample")
    steps = hdr["duration"] / hdr["dt"]
    if abs(steps - round(steps)) > 1e-9 * max(1.0, steps):
        raise StudyFileError(f"{where}: [study] duration", f"{hdr['duration']:g} s is not a whole number of grid "
                             f"steps dt = {hdr['dt']:g} s (the Monte Carlo grid must be uniform)")
    spr = hdr["dt"] * o["imu_rate"]
    if abs(spr - round(spr)) > 1e-6 * max(1.0, spr) or round(spr) % o["samples_per_step"]:
        raise StudyFileError(f"{w} imu_rate", f"{o['imu_rate']:g} Hz puts {spr:g} samples into one grid step "
                             f"dt = {hdr['dt']:g} s; it must be a whole multiple of samples_per_step = "
                             f"{o['samples_per_step']}")
    o["samples_per_grid_step"] = int(round(spr))
    o["navigation_rate"] = o["imu_rate"] / o["samples_per_step"]
    return o


def _memory(opt: dict, dt: float, shared: bool = False):
    """``memory(steps, truth, filters, dynamics)`` of a Monte Carlo study with options ``opt`` (an upper estimate).

    The linear analyses read the truth's and the filters' systems a chunk at
    a time (:meth:`~covtool.studies.zupt_setup.ZuptSetup.streamed_system`:
    every chunk held where the total fits the memory limit, else as many as
    four fifths of what the rest leaves, at least
    :data:`~covtool.studies.resources.HELD_CHUNKS` bytes; the dict's
    ``layout`` and ``held`` say which) and keep the navigation block of every
    step and the whole covariance at the NEES steps only; the null (:func:`covtool.validation.linear_mc.linear_mean_squares`)
    holds the dense rows of Φ and the noise roots of every step in single
    precision and the mean squares of every replica.  Nothing grows with
    duration × n².
    """
    from covtool.studies.resources import memory_limit, stream_memory_estimate

    def memory(steps, truth, filters, dynamics, *, max_memory=None, distinct=None, **_):
        N, n = int(steps), truth.n
        cases = len(filters) + 1                                       # and the pure INS
        est = stream_memory_estimate(N, n, filters=list(filters), dropped=[n - m for m in filters],
                                     dynamics=dynamics, noise=noise_columns(truth))
        parts = dict(est["parts"])
        # the truth's and each distinct filter system's Φ, Q_d (a filter that is the truth reads the truth's)
        systems = 2 * N * (n * n + sum(m * m for m in (filters if distinct is None else distinct))) * 8
        parts["held chunks of the systems"] = systems
        J = int(N * dt / opt["nees_every"]) + 2                       # NEES steps (and the last)
        worst = max([n] + list(filters))
        # three runs alive at once (a filter's design and its truth run here, a conditional run beside),
        # each with its every-step navigation blocks and its NEES-step covariances (truth and filter)
        parts["recorded covariances"] = 3 * (2 * (N + 1) * 100 + J * (n * n + worst * worst)) * 8
        # per case the NEES whitening of the truth's and the filter's navigation errors (9 states) and of
        # the filter's navigation and constant states (at most 9 + n_f)
        parts["NEES whitening"] = sum(J * (2 * 81 + (9 + m) ** 2 + 3 * (9 + m)) * 8 for m in [9] + list(filters))
        parts["linear sigma histories"] = 3 * cases * 12 * (N + 1) * 8
        # each of those runs guards a block of 512 steps at a time; each system read keeps the chunks it
        # reads last (two: the threads), and the null stacks a chunk of 600 steps of Φ and Q_d
        parts["guard blocks and chunks in use"] = (3 * 512 * (n * n + worst * worst)
                                                   + 2 * 2 * 600 * (n * n + worst * worst) + 2 * 600 * n * n) * 8
        cols = min(20000, opt["runs"] * max(opt["null_replicas"], 1))
        if opt["null_replicas"]:
            # Φ's dense rows (the navigation block's) and diagonal, the noise roots (n × noise columns, their
            # array headers) in float32, every case's state of the replicas and the draws ahead
            parts["null: systems"] = N * (10 * n * 4 + n * 4 + n * noise_columns(truth) * 4 + 112)
            parts["null: mean squares"] = cases * opt["null_replicas"] * (N + 1) * 3 * 8
            parts["null: states"] = (cases + 8) * n * cols * 4
        # the ensemble's reference (the trajectory at the IMU rate, reference_along: about 180 bytes a sample,
        # measured) in this process and, shared, once in the file every worker maps; else pickled into the
        # chunks in flight and unpickled by every worker
        samples = N * dt * opt["imu_rate"]
        chunks = math.ceil(opt["runs"] / opt["runs_per_chunk"])
        parts["ensemble reference"] = 180 * samples * (2 if shared else 3 + min(chunks, os.cpu_count() or 1))
        # every chunk held (each made once, as the whole-grid stacks were) where that fits the limit, else as
        # many as fit four fifths of what the rest leaves (at least HELD_CHUNKS), the others made again by
        # every analysis that reads them
        layout = "every chunk of the systems held"
        limit = memory_limit(max_memory)[0]
        if sum(parts.values()) > limit and systems > HELD_CHUNKS:
            rest = sum(parts.values()) - systems
            parts["held chunks of the systems"] = min(systems, max(HELD_CHUNKS, 0.8 * (limit - rest)))
            layout = "streamed (some chunks of the systems held, the others made again on each read)"
        total = sum(parts.values())
        return {"bytes": float(total), "steps": N, "parts": parts, "parallel": 1, "layout": layout,
                "held": parts["held chunks of the systems"]}

    memory.records = memory.limit = True          # setup passes [study] max_memory (the layout must fit it)
    return memory


def _shares_reference(store, backend) -> bool:
    """Whether the chunks read the ensemble's reference from one file beside the result ``store``
    (:class:`~covtool.validation.monte_carlo.SharedReference`): with a store, and workers on this machine."""
    return store is not None and not (backend == "dask" or isinstance(backend, DaskBackend))


def _chunks(runs: int, per: int) -> list[int]:
    n = math.ceil(runs / per)
    return [min(per, runs - i * per) for i in range(n)]


def _linear(P, nodes, case=None) -> dict:
    """σ of the compared quantities, the horizontal dof per run and the validity.

    ``first``: :func:`covtool.analysis.metrics.first_invalid` of the linear
    prediction (a :class:`covtool.errors.ValidityWarning` names ``case``).
    """
    m = nav_metrics(P, nodes.lat, nodes.h, nodes.q_nb)
    Pn = ned_position_covariance(P[:, :3, :3], nodes.lat, nodes.h)
    return {"horizontal": m["sigma_horizontal"], "altitude": m["sigma_down"], "azimuth": m["sigma_azimuth"],
            "north": m["sigma_north"], "east": m["sigma_east"], "dof_h": horizontal_dof(Pn[:, :2, :2]),
            "P_ne": Pn[:, :2, :2],
            "first": case_validity(case, m, nodes.t, warn=case is not None)}


def _initial_draws(truth, sizes, seed, q0) -> np.ndarray:
    """The initial states of all N runs, chunk after chunk, shape (N, n).

    Exactly the chunks' draws (:func:`covtool.validation.monte_carlo.initial_states`).
    """
    return np.concatenate([initial_states(truth, m, seed, i, q0) for i, m in enumerate(sizes)])


def _sample_moment(x0) -> np.ndarray:
    """Second moment about zero of the initial states the N runs draw.

    ``(1/N) Σ x0 x0ᵀ`` over the draws (:func:`_initial_draws`): the P0 of the
    conditional linear prediction.
    """
    P = x0.T @ x0 / float(x0.shape[0])
    return symmetrize(P)


def conditional_dof(Lc: dict, Ld: dict, quantity: str) -> np.ndarray:
    """Per-run χ² dof of an ensemble mean square given the drawn constants.

    Parameters
    ----------
    Lc, Ld : dict
        :func:`_linear` of the conditional prediction (sample P0) and of the
        driven part alone (P0 = 0).
    quantity : {"horizontal", "altitude", "azimuth"}

    Returns
    -------
    ndarray, shape (N+1,)
        ``ν/N`` with ``ν = 2 E[m]² / Var[m]`` (Satterthwaite) for the mean
        square ``m = (1/N) Σ (a_i + d_i)²``: ``a_i`` the part the run's drawn
        constants fix, ``d_i ~ N(0, Σ_d)`` the driven part.  Given the draws
        ``E[m] = tr(A + Σ_d)`` and ``N Var[m] = 4 tr(Σ_d A) + 2 tr(Σ_d²)``,
        ``A = P_cond − Σ_d`` (docs/monte_carlo.md, "Statistics").  Without
        constants this is :func:`covtool.analysis.consistency.horizontal_dof`
        (1 for a scalar); without driven noise the spread vanishes (capped at
        1e6 per run).
    """
    if quantity == "horizontal":
        Pc, Pd = Lc["P_ne"], Ld["P_ne"]
        A = Pc - Pd
        mean = np.trace(Pc, axis1=1, axis2=2)
        var = 4.0 * np.clip(np.einsum("nij,nji->n", Pd, A), 0.0, None) + 2.0 * np.einsum("nij,nji->n", Pd, Pd)
    else:
        c2, d2 = Lc[quantity] ** 2, Ld[quantity] ** 2
        mean = c2
        var = 4.0 * np.clip(c2 - d2, 0.0, None) * d2 + 2.0 * d2 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        dof = np.where(var > 0, 2.0 * mean**2 / np.where(var > 0, var, 1.0), 1e6)
    return np.clip(dof, 1e-3, 1e6)


def _rms(s: EnsembleSums, quantity: str) -> np.ndarray:
    return s.rms({"altitude": "down"}.get(quantity, quantity))


def _mean(s: EnsembleSums, quantity: str) -> np.ndarray:
    if quantity == "horizontal":
        return np.hypot(s.mean("north"), s.mean("east"))
    return s.mean({"altitude": "down"}.get(quantity, quantity))


def run(decl: dict, *, path=None, progress: bool = False, backend=None, store=None,
        resume: bool = False) -> MonteCarloResult:
    """Run a Monte Carlo validation study; see the module docstring.

    Parameters
    ----------
    decl : dict
    path : Path, optional
        The study file (relative paths and messages).
    progress : bool
        Progress bars (truth system, then runs done with the time left).
    backend : backend or str, optional
        :mod:`covtool.parallel` backend; default local processes (one per
        CPU) when there is more than one chunk.
    store : path, optional
        Incremental result store (one JSON file per chunk of runs).  With a
        store and local workers, the ensemble's reference is written to
        ``.monte_carlo_reference.bin`` beside it (in its parent directory:
        ``--out``) for the run and removed at its end
        (:class:`~covtool.validation.monte_carlo.SharedReference`).
    resume : bool
        Reuse the chunks already in ``store``.
    """
    from covtool.io.config import file_sha256
    from covtool.studies.inputs import trajectory_csv_sha256
    from covtool.studies.resources import store_checks

    if "measurement" in decl:              # declared measurements (issue 15): covtool.studies.aided_monte_carlo
        from covtool.studies.aided_monte_carlo import run as run_aided
        if backend is not None or resume:              # in one piece: a worker pool or a resume would be ignored
            raise StudyFileError(f"{path if path else '<study>'}: [[measurement]]", "a Monte Carlo with declared "
                                 "measurements runs in-process in one piece; it takes no --workers, --scheduler "
                                 "or --resume")
        return run_aided(decl, path=path, progress=progress)
    t_start = time.perf_counter()
    where = str(path) if path else "<study>"
    opt = mc_options(decl, where)
    S = setup(decl, path=path, progress=progress, extra_sections=("monte_carlo",),
              memory=_memory(opt, study_header(decl, where)["dt"], _shares_reference(store, backend)),
              shrink="a larger [study] dt, a shorter duration or fewer [filters] cases")
    t, nodes, truth = S.t, S.nodes, S.truth
    dt = float(t[1] - t[0])
    fcfg = decl.get("filters", {})
    pure = fcfg.get("pure_ins", True)
    if not pure and not S.cases:
        raise StudyFileError(f"{where}: [filters]", "nothing to run: no filter cases and pure_ins = false")

    # ---- linear covariance analysis and the filters' gain schedules -------------
    t_lin = time.perf_counter()
    every = opt["nees_every"]
    kk = np.arange(1, t.size)
    nees_steps = kk[np.isclose(t[kk] / every, np.round(t[kk] / every), rtol=0, atol=1e-9) | (kk == t.size - 1)]
    lin, claimed, cases, states, pf_check, predicted = {}, {}, [], {}, {}, {}
    # the conditional prediction (docs/monte_carlo.md): the truth's P0 replaced by the second moments
    # of the initial states the ensemble actually drew (random constants and initial errors);
    # driving noises, measurement noise and the filters' gains stay those of the model
    sizes = _chunks(opt["runs"], opt["runs_per_chunk"])
    traj = _trajectory(decl, where, path)
    x0_all = _initial_draws(truth, sizes, opt["seed"], traj.sample([t[0]]).q_nb[0])
    P0_cond = _sample_moment(x0_all)
    later = []                               # the conditional and driven-part analyses, run beside the ensemble
    null_cases = {}                          # correction gains D K of each case, for the linear Monte Carlo
    lin_c, predicted_c, lin_d = {}, {}, {}
    Z0 = np.zeros_like(P0_cond)              # the driven part alone: its sampling is all that remains
    # the trajectory as every chunk samples it (increments, attitude, gravity, span contexts) needs only
    # the update steps and the filters' states: a forked process samples it while this one runs the
    # linear analyses below (the same calls, the same numbers)
    ref_inputs = (gain_steps(S.update_steps, t.size - 1) if S.cases else [],
                  [list(S.filter_stream(c)[0].names) for c in S.cases])
    ref_args = dict(imu_rate=opt["imu_rate"], samples_per_step=opt["samples_per_step"], model=truth,
                    process_dt=opt["process_dt"])
    # the truth's and the filters' Φ, Q_d are made a chunk at a time on first read and held while the
    # setup's pool has room (ZuptSetup.streamed_system): every run below reads them step by step, and
    # keeps the navigation block of every step and the whole covariance at the NEES steps only, so the
    # memory does not grow with duration × n² (the same numbers as whole-grid stacks and histories)
    S.hold_chunks(S.resources.get("held", HELD_CHUNKS) * 1.01)   # (a chunk's array headers beside its data)
    T = S.streamed_system()
    try:
        ref_job = Forked(reference_along, traj, t, *ref_inputs, **ref_args) if can_split() else None
    except OSError:                          # no fork here: sampled in this process, after the gains
        ref_job = None
    rec = dict(record=nees_steps, all_steps=10)
    try:
        if pure:
            P, P_nav = propagate(T.Phi, T.Qd, S.P0, label=f"{where}: pure INS", names=truth.names, times=t,
                                 system_checked=True, **rec)
            lin["pure_ins"] = _linear(P_nav, nodes, "pure_ins")
            spec = nees_whitening(AtSteps(nees_steps, P), truth.names, REDUCED_NAV, nees_steps, nodes.q_nb)
            cases.append(EnsembleCase("pure_ins", None, {"truth": spec}))
            null_cases["pure_ins"] = None
            states["pure_ins"] = truth.n
            del P, P_nav

            def conditional_pure(spec=spec):
                P, P_nav = propagate(T.Phi, T.Qd, P0_cond, label=f"{where}: pure INS (conditional)",
                                     names=truth.names, times=t, system_checked=True, **rec)
                lin_c["pure_ins"] = _linear(P_nav, nodes)
                predicted_c[("pure_ins", "truth")] = expected_nees(spec, AtSteps(nees_steps, P), truth.names,
                                                                   nodes.q_nb)
                P = propagate(T.Phi, T.Qd, Z0, label=f"{where}: pure INS (driven part)", names=truth.names, times=t,
                              system_checked=True, keep=10)
                lin_d["pure_ins"] = _linear(P, nodes)
            later.append(conditional_pure)
        for c in S.cases:
            spec = S.specs[c]
            fm = S.filter_stream(c)[0]
            fsys = S.streamed_system(c)
            Phi_f, Qd_f = fsys.Phi, fsys.Qd
            Rf = S.filter_R(c)
            ff = FeedbackFilter.design(c, fm.names, Phi_f, Qd_f, fm.P0, Rf, S.update_steps, form=spec.update, times=t,
                                       system_checked=True, **rec)
            res = propagate_with_filter(T.Phi, T.Qd, S.P0, Phi_f, Qd_f, fm.P0, S.H, zupt_matrices(fm.names), fm.D, S.R,
                                        S.update_steps, Rf=Rf, form=spec.update, label=f"{where}: filter {c}", times=t,
                                        names=truth.names, filter_names=fm.names, system_checked=True, **rec)
            pf_check[c] = float(max(np.max(np.abs(ff.P - res.P_filter)), np.max(np.abs(ff.every - res.every_filter))))
            lin[c] = _linear(res.every_truth, nodes, c)
            claimed[c] = _linear(ff.every, nodes) if tuple(fm.names[:10]) == NAV_STATES else None
            const = [nm for nm in fm.names[10:] if truth.states[truth.index[nm]].process == "constant"]
            Pt, Pf = AtSteps(nees_steps, res.P_truth), AtSteps(nees_steps, ff.P)
            nees = {"truth": nees_whitening(Pt, truth.names, REDUCED_NAV, nees_steps, nodes.q_nb),
                    "filter": nees_whitening(Pf, ff.names, REDUCED_NAV + tuple(const), nees_steps, nodes.q_nb),
                    "filter_nav": nees_whitening(Pf, ff.names, REDUCED_NAV, nees_steps, nodes.q_nb)}
            # what the linear analysis predicts for the NEES of the filter's claim: the actual errors of the
            # filter states have the truth covariance under its gains (labels are truth state names)
            for key in ("filter", "filter_nav"):
                predicted[(c, key)] = expected_nees(nees[key], Pt, truth.names, nodes.q_nb)
            del res, Pt, Pf

            def conditional_case(c=c, fm=fm, Phi_f=Phi_f, Qd_f=Qd_f, Rf=Rf, spec=spec, nees=nees):
                res = propagate_with_filter(T.Phi, T.Qd, P0_cond, Phi_f, Qd_f, fm.P0, S.H, zupt_matrices(fm.names),
                                            fm.D, S.R, S.update_steps, Rf=Rf, form=spec.update,
                                            label=f"{where}: filter {c} (conditional)", times=t, names=truth.names,
                                            filter_names=fm.names, system_checked=True, **rec)
                lin_c[c] = _linear(res.every_truth, nodes)
                for key in nees:
                    predicted_c[(c, key)] = expected_nees(nees[key], AtSteps(nees_steps, res.P_truth), truth.names,
                                                          nodes.q_nb)
                del res
                res = propagate_with_filter(T.Phi, T.Qd, Z0, Phi_f, Qd_f, fm.P0, S.H, zupt_matrices(fm.names), fm.D,
                                            S.R, S.update_steps, Rf=Rf, form=spec.update,
                                            label=f"{where}: filter {c} (driven part)", times=t, names=truth.names,
                                            filter_names=fm.names, system_checked=True, all_steps=10)
                lin_d[c] = _linear(res.every_truth, nodes)
            later.append(conditional_case)
            cases.append(EnsembleCase(c, FeedbackFilter(c, ff.names, ff.gains, np.empty((0,) + ff.P.shape[1:])), nees))
            states[c] = len(fm.names)
            null_cases[c] = {int(k): fm.D @ K for k, K in ff.gains.items()}
        t_lin = time.perf_counter() - t_lin          # (not the wait for the reference below)
        # the inputs the gains give (always these: the gains are at the update steps, the filters' states
        # are their models'); sampled again after them if they were not
        if ref_job is not None and reference_inputs(cases) != ref_inputs:
            ref_job.cancel()
            ref_job = None
        reference = ref_job.result() if ref_job is not None else None
        ref_job = None                       # (it keeps its pickled result and the value: both go with it)
    except BaseException:                    # the child does not outlive a failed analysis
        if ref_job is not None:
            ref_job.cancel()
        raise
    N = opt["runs"]

    # ---- beside the ensemble: the conditional and driven-part analyses, and the null -------------
    # They need only the draws and the gains, not the runs, so threads of this process compute them
    # while the chunks run in the backend's workers (both cores busy); the results do not depend on it.
    # The null: replicas of N runs of the linear error-state system (eq (15)-(16)) from the same initial
    # draws: what the ensemble statistics would look like if the linear model were exact (docs/monte_carlo.md).
    # The null is the longest of these; in a thread of its own it is not held up by the analyses.
    side = {"null": None, "seconds": 0.0, "null_seconds": 0.0, "errors": []}

    def analyses():
        try:
            t0 = time.perf_counter()
            for fn in later:
                fn()
            side["seconds"] = time.perf_counter() - t0
        except BaseException as exc:          # re-raised in the main thread
            side["errors"].append(exc)

    def null():
        try:
            t0 = time.perf_counter()
            if opt["null_replicas"]:
                side["null"] = linear_mean_squares(
                    T.Phi, T.Qd, null_cases, output_rows(nodes.lat, nodes.h, nodes.q_nb), runs=N,
                    replicas=opt["null_replicas"], x0=x0_all, H=S.H, R=S.R,
                    rng=np.random.default_rng(np.random.SeedSequence(opt["seed"], spawn_key=(NULL_STREAM,))))
            side["null_seconds"] = time.perf_counter() - t0
        except BaseException as exc:
            side["errors"].append(exc)

    workers = [threading.Thread(target=null, name="monte_carlo_null", daemon=True),
               threading.Thread(target=analyses, name="monte_carlo_conditional", daemon=True)]
    for w in workers:
        w.start()

    # ---- the ensemble, in chunks of runs ------------------------------------------
    base = {"traj": traj, "model": truth, "t": t, "imu_rate": opt["imu_rate"],
            "samples_per_step": opt["samples_per_step"], "R": S.R, "cases": cases, "seed": opt["seed"],
            "sensor_noise": opt["sensor_noise"], "measurement_noise": opt["measurement_noise"],
            "process_dt": opt["process_dt"]}
    # the trajectory as every chunk samples it (increments, attitude, gravity, span contexts), sampled once;
    # with a result store and workers on this machine, written once to a file beside the store that every
    # worker maps (SharedReference), not pickled into every chunk
    reference = reference if reference is not None else \
        reference_along(traj, t, *reference_inputs(cases), **ref_args)
    shared = None
    if _shares_reference(store, backend):
        shared = SharedReference(reference, Path(store).parent / ".monte_carlo_reference.bin")
        reference = shared
    base["reference"] = reference
    del reference
    tasks = [{**base, "chunk": i, "runs": m} for i, m in enumerate(sizes)]
    keys = [f"runs-{i:04d}" for i in range(len(sizes))]
    first = np.cumsum([0] + sizes)
    run_ids = [list(range(int(first[i]), int(first[i + 1]))) for i in range(len(sizes))]
    def manifest():
        return {"kind": "monte_carlo", "covtool_version": __version__, "study": decl,
                "truth_model_sha256": truth.sha256,
                "filter_file_sha256": [file_sha256(p) for p in S.filter_files],
                "trajectory_csv_sha256": trajectory_csv_sha256(decl, path.parent if path else None),
                "chunks": keys, "runs": sizes}

    try:
        results, stats, rs = run_in_chunks(
            simulate_chunk, tasks, keys, run_ids, store=store, manifest=manifest, resume=resume, progress=progress,
            backend=backend if backend is not None else ("processes" if len(sizes) > 1 else "serial"),
            desc="Monte Carlo runs")
    finally:
        if shared is not None:
            shared.remove()
    base = tasks = None
    names = [c.name for c in cases]
    sums = {}
    for res in results:
        for nm in names:
            s = EnsembleSums.from_json(res["sums"][nm])
            sums[nm] = s if nm not in sums else sums[nm] + s
    t_wait = time.perf_counter()
    for w in workers:
        w.join()
    t_wait = time.perf_counter() - t_wait
    if side["errors"]:
        raise side["errors"][0]
    # the held chunks of the systems: every analysis has read them (the last case's system, held by the
    # loop's names, too)
    S.release()
    T = fsys = Phi_f = Qd_f = ff = None
    later.clear()
    null_ms, t_null = side["null"], side["null_seconds"]
    t_lin += side["seconds"]
    elapsed = time.perf_counter() - t_start

    # ---- statistics -------------------------------------------------------------------
    conf = opt["confidence"]
    k1 = slice(1, None)                   # t = 0 (zero position σ) is not a test point
    comp_rows, hist_frames, summary_rows, nees_stats = [], [], [], {}
    band = {}
    hsel = np.isclose(t / S.every, np.round(t / S.every), rtol=0, atol=1e-9) | (np.arange(t.size) == t.size - 1)
    band_c, nees_cond, band_x = {}, {}, {}
    cells = len(names) * len(COMPARED)
    alpha_cell = (1.0 - conf) / cells         # Bonferroni: family-wise false-alarm rate 1 - confidence
    tests = {}
    for c in names:
        s, L, Lc = sums[c], lin[c], lin_c[c]
        row = {"case": c, "states": states[c], "runs": N}
        band[c], band_c[c] = {}, {}
        for q, unit, f in COMPARED:
            dof = L["dof_h"] if q == "horizontal" else 1.0
            lo, hi = rms_bounds(L[q], N, dof, conf)
            x = _rms(s, q)
            band[c][q] = (x, L[q], lo, hi)
            fr = inside_fraction(x[k1], lo[k1], hi[k1])
            # conditional: the same χ² bounds about the prediction from the drawn initial states
            lo_c, hi_c = rms_bounds(Lc[q], N, Lc["dof_h"] if q == "horizontal" else 1.0, conf)
            band_c[c][q] = (x, Lc[q], lo_c, hi_c)
            frc = inside_fraction(x[k1], lo_c[k1], hi_c[k1])
            # conditional, exact variance: only the driven part (and its cross term) is sampled
            lo_x, hi_x = rms_bounds(Lc[q], N, conditional_dof(Lc, lin_d[c], q), conf)
            band_x.setdefault(c, {})[q] = (x, Lc[q], lo_x, hi_x)
            frx = inside_fraction(x[k1], lo_x[k1], hi_x[k1])
            if null_ms is not None:
                pts = (np.arange(t.size) >= 1) & (Lc[q] > 0)
                tests[(c, q)] = nt = null_test(x**2, null_ms[c][:, :, QUANTITY_INDEX[q]], Lc[q], lo_c, hi_c, pts,
                                              alpha_cell)
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio_c = x[k1] / np.where(Lc[q][k1] > 0, Lc[q][k1], np.nan)
            end = t.size - 1
            comp_rows.append({
                "case": c, "quantity": q, "time points": fr["points"], "inside [%]": 100 * fr["inside"],
                "above [%]": 100 * fr["above"], "below [%]": 100 * fr["below"],
                "pass (>= 95 % inside)": bool(fr["inside"] >= 0.95),
                "mean RMS/sigma": float(np.mean(x[k1] / np.where(L[q][k1] > 0, L[q][k1], np.nan))),
                "min RMS/sigma": float(np.nanmin(x[k1] / np.where(L[q][k1] > 0, L[q][k1], np.nan))),
                "max RMS/sigma": float(np.nanmax(x[k1] / np.where(L[q][k1] > 0, L[q][k1], np.nan))),
                "unit": unit, "linear sigma at end [unit]": L[q][end] / f, "MC RMS at end [unit]": x[end] / f,
                "lower bound at end [unit]": lo[end] / f, "upper bound at end [unit]": hi[end] / f,
                "|MC mean| at end [unit]": _mean(s, q)[end] / f,
                "dof per run at end": float(np.broadcast_to(dof, t.shape)[end]),
                "conditional: inside [%]": 100 * frc["inside"], "conditional: above [%]": 100 * frc["above"],
                "conditional: below [%]": 100 * frc["below"],
                "conditional: pass (>= 95 % inside)": bool(frc["inside"] >= 0.95),
                "conditional: mean RMS/sigma": float(np.nanmean(ratio_c)),
                "conditional: min RMS/sigma": float(np.nanmin(ratio_c)),
                "conditional: max RMS/sigma": float(np.nanmax(ratio_c)),
                "conditional sigma at end [unit]": Lc[q][end] / f,
                "conditional, exact variance: inside [%]": 100 * frx["inside"],
                "conditional, exact variance: above [%]": 100 * frx["above"],
                "conditional, exact variance: below [%]": 100 * frx["below"]})
            if null_ms is not None:
                comp_rows[-1].update({
                    "null: inside 5th percentile [%]": 100 * nt["inside_null_p5"],
                    "null: inside median [%]": 100 * nt["inside_null_median"],
                    "inside p-value (one-sided)": nt["inside_p"],
                    "T = time-mean RMS^2/sigma^2": nt["T"], "T null std": nt["T_null_std"],
                    "T null mean": nt["T_null_mean"], "z = (T-1)/std": nt["z"], "p-value": nt["p"],
                    "p-value (rank among replicas)": nt["T_p_empirical"], "cell false-alarm rate": alpha_cell,
                    "verdict": "reject" if nt["reject"] else "accept"})
                row[f"{q} p-value"] = nt["p"]
                row[f"{q} verdict"] = "reject" if nt["reject"] else "accept"
            row[f"{q} inside [%]"] = 100 * fr["inside"]
            row[f"{q} conditional inside [%]"] = 100 * frc["inside"]
            row[f"{q} conditional, exact variance, inside [%]"] = 100 * frx["inside"]
            row[f"{q} RMS/sigma at end"] = x[end] / L[q][end] if L[q][end] > 0 else np.nan
        for key, spec in cases[names.index(c)].nees.items():
            mean = s.nees[key] / N
            lo, hi = nees_bounds(spec.dof, N, conf)
            fr = inside_fraction(mean, lo, hi)
            pred = predicted.get((c, key))
            if pred is not None:
                plo, phi = nees_bounds(pred[1], N, conf, mean=pred[0])
                pfr = inside_fraction(mean, plo, phi)
                pred = (pred[0], plo, phi, pfr)
            pc = predicted_c.get((c, key))
            if pc is not None:
                clo, chi = nees_bounds(pc[1], N, conf, mean=pc[0])
                pc = (pc[0], clo, chi, inside_fraction(mean, clo, chi))
                nees_cond[(c, key)] = pc
                row[f"NEES {key}: conditional-predicted mean/dof"] = float(np.mean(pc[0] / spec.dof))
                row[f"NEES {key}: inside bounds of conditional prediction [%]"] = 100 * pc[3]["inside"]
            nees_stats[(c, key)] = (spec, mean, lo, hi, fr, pred)
            row[f"NEES {key}: dof"] = int(np.median(spec.dof))
            row[f"NEES {key}: mean/dof"] = float(np.mean(mean / spec.dof))
            row[f"NEES {key}: inside [%]"] = 100 * fr["inside"]
            if pred is not None:
                row[f"NEES {key}: linear-predicted mean/dof"] = float(np.mean(pred[0] / spec.dof))
                row[f"NEES {key}: inside bounds of prediction [%]"] = 100 * pred[3]["inside"]
        row["validity"] = validity_text(L["first"])
        summary_rows.append(row)
        h = {"case": c, "t [s]": t[hsel], "t [min]": t[hsel] / 60.0}
        for q, unit, f in COMPARED:
            x, sig, lo, hi = band[c][q]
            h[f"{q} sigma linear [{unit}]"] = sig[hsel] / f
            h[f"{q} RMS MC [{unit}]"] = x[hsel] / f
            h[f"{q} lower bound [{unit}]"] = lo[hsel] / f
            h[f"{q} upper bound [{unit}]"] = hi[hsel] / f
            h[f"{q} MC mean [{unit}]"] = _mean(s, q)[hsel] / f
        for q, unit, f in COMPARED:
            _, sig_c, lo_c, hi_c = band_c[c][q]
            h[f"{q} sigma conditional [{unit}]"] = sig_c[hsel] / f
            h[f"{q} conditional lower bound [{unit}]"] = lo_c[hsel] / f
            h[f"{q} conditional upper bound [{unit}]"] = hi_c[hsel] / f
        for ax in ("north", "east"):
            h[f"{ax} sigma linear [m]"] = L[ax][hsel]
            h[f"{ax} RMS MC [m]"] = s.rms(ax)[hsel]
        h["horizontal dof per run"] = np.broadcast_to(L["dof_h"], t.shape)[hsel]
        if claimed.get(c) is not None:
            h["horizontal sigma filter-claimed [m]"] = claimed[c]["horizontal"][hsel]
            h["altitude sigma filter-claimed [m]"] = claimed[c]["altitude"][hsel]
            h["azimuth sigma filter-claimed [arcmin]"] = claimed[c]["azimuth"][hsel] / ARCMIN
        hf = pd.DataFrame(h)
        for key in cases[names.index(c)].nees:
            spec, mean, lo, hi, _, pred = nees_stats[(c, key)]
            cols = {"mean": mean, "lower bound": lo, "upper bound": hi}
            if pred is not None:
                cols.update({"linear-predicted mean": pred[0], "lower bound of prediction": pred[1],
                             "upper bound of prediction": pred[2]})
            pc = nees_cond.get((c, key))
            if pc is not None:
                cols.update({"conditional-predicted mean": pc[0], "lower bound of conditional prediction": pc[1],
                             "upper bound of conditional prediction": pc[2]})
            for nm, arr in cols.items():
                col = pd.Series(np.nan, index=range(t.size))
                col[spec.steps] = arr
                hf[f"NEES {key} {nm}"] = col[hsel].to_numpy()
        hist_frames.append(hf)
    summary = pd.DataFrame(summary_rows)
    comparison = pd.DataFrame(comp_rows)
    history = pd.concat(hist_frames, ignore_index=True)
    nees_rows = []
    for (c, key), (spec, mean, lo, hi, fr, pred) in nees_stats.items():
        row = {"case": c, "NEES": key, "covariance": "filter-claimed P_f" if key.startswith("filter")
               else "linear truth P (eq (15)-(16))", "states": " ".join(spec.labels),
               "dof": int(np.median(spec.dof)), "time points": fr["points"],
               "time-mean NEES": float(np.mean(mean)), "time-mean NEES/dof": float(np.mean(mean / spec.dof)),
               "NEES at end": float(mean[-1]), "lower bound at end": float(lo[-1]),
               "upper bound at end": float(hi[-1]), "inside [%]": 100 * fr["inside"],
               "above [%]": 100 * fr["above"], "below [%]": 100 * fr["below"]}
        if pred is not None:
            row.update({"linear-predicted time-mean NEES/dof": float(np.mean(pred[0] / spec.dof)),
                        "linear-predicted NEES at end": float(pred[0][-1]),
                        "inside bounds of prediction [%]": 100 * pred[3]["inside"]})
        pc = nees_cond.get((c, key))
        if pc is not None:
            row.update({"conditional-predicted time-mean NEES/dof": float(np.mean(pc[0] / spec.dof)),
                        "inside bounds of conditional prediction [%]": 100 * pc[3]["inside"]})
        nees_rows.append(row)
    nees_table = pd.DataFrame(nees_rows)
    chunk_seconds = [r["seconds"] for r in results]
    settings = pd.DataFrame([
        {"setting": "runs N", "value": N},
        {"setting": "chunks (runs each)", "value": ", ".join(map(str, sizes))},
        {"setting": "seed", "value": opt["seed"]},
        {"setting": "IMU rate [Hz]", "value": opt["imu_rate"]},
        {"setting": "samples per navigation step", "value": opt["samples_per_step"]},
        {"setting": "navigation rate [Hz]", "value": opt["navigation_rate"]},
        {"setting": "grid dt (updates, statistics) [s]", "value": dt},
        {"setting": "confidence", "value": conf},
        {"setting": "horizontal bound", "value": "chi-square with Satterthwaite dof N(l1+l2)^2/(l1^2+l2^2) "
                                                 "(l: eigenvalues of the 2x2 horizontal covariance)"},
        {"setting": "conditional prediction", "value": "linear analysis with the truth P0 replaced by the second "
                                                       "moments of the N drawn initial states (initial errors and "
                                                       "random constants); driving and measurement noise and the "
                                                       "filters' gains from the model; the acceptance test "
                                                       "applies to it (docs/monte_carlo.md)"},
        {"setting": "acceptance test", "value": (
            f"per cell (case x quantity) T = time mean of RMS^2/sigma_cond^2 over t >= dt, two-sided, against its "
            f"null from {opt['null_replicas']} replicas of a linear Monte Carlo of N runs from the same initial "
            f"draws; Bonferroni over {cells} cells: a cell is rejected when p < {alpha_cell:.3g} (family-wise "
            f"false-alarm rate {1 - conf:.3g}); verdict: "
            + ("pass" if not any(v["reject"] for v in tests.values()) else "FAIL: " + ", ".join(
                f"{c} {q}" for (c, q), v in tests.items() if v["reject"])))
         if null_ms is not None else "none (null_replicas = 0): the per-point bands only"},
        {"setting": "linear Monte Carlo (null) [s]", "value": round(t_null, 2)},
        {"setting": "wait for the null after the ensemble [s]", "value": round(t_wait, 2)},
        {"setting": "NEES steps every [s]", "value": every},
        {"setting": "sensor noise", "value": opt["sensor_noise"]},
        {"setting": "measurement noise", "value": opt["measurement_noise"]},
        {"setting": "filter covariance vs propagate_with_filter (max |diff|)",
         "value": ", ".join(f"{c}: {v:.3g}" for c, v in pf_check.items()) or "-"},
        {"setting": "backend", "value": stats["backend"]},
        {"setting": "linear analysis [s]", "value": round(t_lin, 2)},
        {"setting": "Monte Carlo wall time [s]", "value": round(stats["seconds"], 2)},
        {"setting": "chunk CPU time, total [s]", "value": round(float(np.sum(chunk_seconds)), 2)},
        {"setting": "study wall time [s]", "value": round(elapsed, 2)},
    ])
    settings["value"] = settings["value"].astype(str)
    tables = {"summary": summary, "comparison": comparison, "nees": nees_table, "history": history,
              "settings": settings}
    provenance = {**study_inputs(path, decl, truth, S.filter_files), **resource_provenance(S.resources),
                  "truth_model": truth.name, "truth_model_sha256": truth.sha256,
                  "runs": N, "chunks": len(sizes), "seed": opt["seed"], "imu_rate_hz": opt["imu_rate"],
                  "samples_per_step": opt["samples_per_step"], "backend": stats["backend"],
                  "chunks_computed": stats["computed"], "chunks_reused": stats["reused"],
                  "compute_seconds": f"{elapsed:.2f}", "monte_carlo_seconds": f"{stats['seconds']:.2f}",
                  "result_store": str(store) if store is not None else "",
                  "result_store_checks": store_checks(rs, stats)}
    result = MonteCarloResult(
        name=S.hdr["name"], kind="monte_carlo", tables=tables,
        resolved={**decl, "study": {**decl["study"], "name": S.hdr["name"]}}, provenance=provenance,
        charts=[{"sheet": "history", "x": "t [min]", "y": ["horizontal RMS MC [m]", "horizontal sigma linear [m]"],
                 "group": "case", "log_y": True, "x_title": "time [min]",
                 "title": "Horizontal RMS (Monte Carlo) and linear sigma, per case", "y_title": "horizontal [m]",
                 "anchor": "B2", "target": "summary"}],
        sums=sums, linear=lin, linear_conditional=lin_c, linear_driven=lin_d, bands_conditional=band_c,
        filter_check=pf_check, stats=stats, acceptance_tests=tests, null_mean_squares=null_ms,
        times=t, cases=list(names), bands=band, nees=nees_stats, runs=N, confidence=conf,
        update_times=t[S.update_steps], stops=S.stops, length_unit=length_unit(decl, S.where))
    result.figures = {f"mc_{c}": partial(case_figure, result, c) for c in names}
    result.figures["mc_ratio"] = partial(ratio_figure, result)
    result.figures["mc_nees"] = partial(nees_figure, result)
    return result


def _trajectory(decl, where, path):
    from covtool.studies.inputs import load_trajectory

    hdr = study_header(decl, where)
    return load_trajectory(decl, where, path.parent if path else None, hdr["dt"], hdr["duration"])
