"""Monte Carlo of aided filters on the nonlinear INS (issue 15, acceptance 3).

M nonlinear strapdown runs with sensor errors drawn from the truth, each with
its own measurement-error realisation, aided by the feedback filter whose
gains the linear analysis computed; the measurements are the library's
nonlinear functions applied to the strapdown solution and the true
trajectory (:func:`covtool.validation.aided.run_aided_ensemble`).  The RMS of
the position errors must lie inside the 99 % χ² bounds of the linear σ at 95 %
of the times (the RMS curves are correlated in time; the ZUPT ensemble's test
uses the same criterion).  A noise-free single run equals the linear
prediction ``x ← (I − D K H) x``, ``x ← Φ x``.
"""

from __future__ import annotations


import numpy as np
import pytest

from covtool.analysis import consistency as mc
from covtool.lincov.aided import augment, build_epochs, error_processes, propagate_aided
from covtool.nav.imu.simulator import ImuSimulator
from covtool.nav.trajectory.profiles import land_vehicle
from covtool.studies.grid import initial_covariance, time_grid, truth_system
from covtool.studies.inputs import load_truth
from covtool.validation.aided import run_aided_ensemble
from covtool.validation.sensor_errors import SensorErrors, sample_states

from aided_cases import gnss_outage, odometer_nhc

M = 60
DURATION = 300.0


def linear_and_ensemble(decls, seed, *, noise=True, runs=M, x0=None, e0=None):
    truth = load_truth({"truth": {"model": "sdins58", "only": ["nav", "acc_bias", "gyro_bias", "arw", "vrw"]}},
                       "<test>", None)
    traj = land_vehicle(dt=1.0)
    t = time_grid(DURATION, 1.0)
    _, _, Phi, Qd = truth_system(truth, traj, t, "van_loan")
    nodes = traj.sample(t)
    P0 = initial_covariance(truth, nodes, "<test>")
    plan = [(m, sch.steps(t, nodes)) for m, sch in decls]
    states = [s for m, _ in plan for s in m.states]
    kept = [s.name for s in states]
    P0a, Pf_e, D = augment(P0, np.eye(truth.n), states, kept)
    names = list(truth.names) + kept
    epochs = build_epochs(plan, nodes, names, names)
    err = error_processes(states, np.diff(t))[:2]
    run = propagate_aided(Phi, Qd, P0a, Phi, Qd, P0a, D, epochs, err=err, err_f=err, times=t)
    rng = np.random.default_rng(seed)
    if x0 is None:
        x0 = sample_states(truth, runs, rng, q0=nodes.q_nb[0])
    if e0 is None:
        e0 = rng.standard_normal((runs, len(states))) * np.array([s.sigma for s in states])
    sim = ImuSimulator(traj, 100.0, duration=DURATION, errors=SensorErrors(truth, x0, rng=rng, noise=noise))
    errs = run_aided_ensemble(sim, x0, e0, t, samples_per_step=4, plan=plan, epochs=epochs, gains=run.gains,
                              filter_names=names, states=states, kept=kept, model=truth, err=err, rng=rng,
                              measurement_noise=noise)
    return truth, t, nodes, run, errs, Phi, D, epochs


def ned_sigma(P, nodes):
    from covtool.nav import earth
    rm, rn = earth.radii(nodes.lat)
    s = np.sqrt(np.stack([P[:, 0, 0], P[:, 1, 1], P[:, 2, 2]], -1))
    return s * np.stack([rm + nodes.h, (rn + nodes.h) * np.cos(nodes.lat), np.ones_like(nodes.h)], -1)


@pytest.mark.parametrize("case, seed", [("odometer + NHC", 11), ("GNSS outage", 12)])
def test_ensemble_inside_the_chi2_bounds(case, seed, capsys):
    decls = odometer_nhc() if case == "odometer + NHC" else gnss_outage()
    _, t, nodes, run, errs, *_ = linear_and_ensemble(decls, seed)
    sig = ned_sigma(run.P_truth, nodes)
    lines = []
    for j, axis in enumerate(("north", "east", "down")):
        rms = np.sqrt(np.mean(errs[:, :, j] ** 2, axis=1))
        lo, hi = mc.rms_bounds(sig[:, j], M, 1.0, confidence=0.99)
        fr = mc.inside_fraction(rms[5:], lo[5:], hi[5:])
        ratio = float(np.mean(rms[5:] / sig[5:, j]))
        lines.append(f"{case} {axis}: inside 99 % bounds {100 * fr['inside']:.1f} %, mean RMS/σ {ratio:.3f}")
        assert fr["inside"] >= 0.95, lines[-1]
        b = mc.rms_bounds(1.0, M, 1.0, confidence=0.99)
        assert b[0] < ratio < b[1], lines[-1]
    with capsys.disabled():
        print("\n  " + "\n  ".join(lines))


@pytest.mark.parametrize("case", ["odometer + NHC", "GNSS outage"])
def test_single_run_follows_the_linear_prediction(case):
    """Noise off, a few error sources: the nonlinear run with real feedback equals the linear prediction.

    Linear: ``x ← Φ x`` (INS truth; the error states by their φ) and, at an
    update, ``x ← (I − D K H) x`` with the noise-free ``z = H x``.  The
    nonlinear run applies the same K to the nonlinear residual of its own
    solution.  An accelerometer bias of 300 µg, a gyro bias of 0.1 deg/h, a
    1-mrad azimuth error and the measurements' own errors (odometer scale
    factor 2000 ppm and boresight 5 mrad; GNSS Markov 2, −1, 3 m).
    Tolerance: 1 % of the largest value of each position axis (measured
    0.5 % and 0.3 %: second-order terms).
    """
    from covtool.nav import earth
    from covtool.nav.attitude import attitude_error_matrix
    decls = odometer_nhc() if case == "odometer + NHC" else gnss_outage()
    truth = load_truth({"truth": {"model": "sdins58", "only": ["nav", "acc_bias", "gyro_bias"]}}, "<test>", None)
    traj = land_vehicle(dt=1.0)
    x = np.zeros(truth.n)
    x[truth.index["acc_bias_x"]] = 300e-6 * 9.80665
    x[truth.index["gyro_bias_z"]] = np.radians(0.1) / 3600
    x[6:10] = np.linalg.pinv(attitude_error_matrix(traj.sample([0.0]).q_nb[0])) @ np.array([0.0, 0.0, 1e-3])
    e0 = np.array([[0.002, 0.005]]) if case == "odometer + NHC" else np.array([[2.0, -1.0, 3.0]])
    _, t, nodes, run, errs, Phi, D, epochs = linear_and_ensemble(decls, 0, noise=False, runs=1, x0=x[None, :],
                                                                 e0=e0)
    states = [s for m, _ in decls for s in m.states]
    phi = error_processes(states, np.diff(t))[0]
    n = truth.n
    xl = np.concatenate([x, e0[0]])
    ep = {e.step: e for e in epochs}
    lin = np.empty((t.size, xl.size))
    for k in range(t.size):
        if k in ep:
            xl = xl - D @ (run.gains[k] @ (ep[k].H @ xl))
        lin[k] = xl
        if k < t.size - 1:
            xl = np.concatenate([Phi[k] @ xl[:n], phi[k] * xl[n:]])
    rm, rn = earth.radii(nodes.lat)
    lp = lin[:, :3] * np.stack([rm + nodes.h, (rn + nodes.h) * np.cos(nodes.lat), -np.ones_like(nodes.h)], -1)
    e = errs[:, 0, :3]
    assert np.abs(lp[:, :2]).max() > 3.0                       # metres of error to follow
    rel = np.abs(e - lp).max(axis=0) / np.abs(lp).max(axis=0)
    assert np.all(rel < 0.01), f"{case}: nonlinear against linear, relative to the largest value: {rel}"
