"""Monte Carlo of an aided feedback filter on the nonlinear INS (issue 15).

The ensemble of :mod:`covtool.validation.monte_carlo` with the library's
measurements instead of the ZUPT: M nonlinear strapdown runs
(:mod:`covtool.nav.strapdown`) driven by an IMU simulator with sensor errors
drawn from the truth model, each with its own realisation ``e`` of the
measurements' error states (drawn from their σ, propagated exactly), aided by
a feedback filter that uses the gains of the linear analysis
(:func:`covtool.lincov.aided.propagate_aided`; the filter's covariance is
evaluated along the reference trajectory, as the ZUPT ensemble's is).

At an update, for each run, the **nonlinear** measurement functions give the
residual ``z = M (predict(x̂) − sensor(x, e)) − v`` with the run's own
navigation solution ``x̂`` and the true state ``x`` (:mod:`covtool.lincov.measurements`);
the filter subtracts what its estimate ``ê`` of the measurement-error states
it keeps predicts, ``ν = z − H_f,e ê``, and applies ``x̂ = K ν``: navigation
and sensor parts are fed back (eq (10)) exactly as in the ZUPT ensemble,
``ê ← ê + x̂_e``.  Between updates ``ê`` follows the mean dynamics of its
state, so ``e − ê`` obeys the truth model's process and is the truth state of
the linear analysis after eq (16).

Pure numeric core: arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np

from covtool.lincov.measurements import nav_point
from covtool.nav import attitude as quat, earth, strapdown as sd
from covtool.validation.feedback import RecordContext, SensorFeedback

__all__ = ["run_aided_ensemble"]


def _due(plan):
    due: dict[int, list] = {}
    for meas, steps in plan:
        for k in np.asarray(steps, int):
            due.setdefault(int(k), []).append(meas)
    return due


def run_aided_ensemble(sim, x0, e0, t, *, samples_per_step: int, plan, epochs, gains, filter_names, states,
                       kept, model, err, rng=None, measurement_noise: bool = True) -> np.ndarray:
    """Run M nonlinear INS with an aided feedback filter; return their errors.

    Parameters
    ----------
    sim : covtool.nav.imu.simulator.ImuSimulator
        Raw IMU increments of the M runs (sensor errors included).
    x0 : ndarray, shape (M, n_truth)
        Initial INS truth states of the runs (navigation errors first).
    e0 : ndarray, shape (M, n_e)
        Initial values of the measurement-error states (``states`` order).
    t : ndarray, shape (N+1,)
        Uniform grid of the linear analysis. [s]
    samples_per_step : int
        IMU samples per strapdown step.
    plan : sequence of (Measurement, ndarray of int)
        The measurements and their update steps, as given to
        :func:`covtool.lincov.aided.build_epochs`.
    epochs : list of covtool.lincov.aided.Epoch
        The updates (their ``Hf`` and true ``R``).
    gains : dict of int to ndarray, shape (n_f, m)
        The filter's gain at every update step (``AidedRun.gains``).
    filter_names : sequence of str
        The filter's states: its INS states, then the kept error states.
    states : sequence of State
        The measurement-error states of the truth.
    kept : sequence of str
        The measurement-error states the filter keeps.
    model : covtool.lincov.model.spec.Model
        The INS truth model (sensor feedback).
    err : tuple of ndarray (phi, qd), each shape (N, n_e)
        Exact transitions of the error states
        (:func:`covtool.lincov.aided.error_processes`).
    rng : numpy.random.Generator or int, optional
        Measurement noise and the error states' driving noise.
    measurement_noise : bool
        False: noise-free measurements (deterministic checks).

    Returns
    -------
    ndarray, shape (N+1, M, 9)
        North, east, down position [m], NED velocity [m/s] and north tilt,
        east tilt, azimuth [rad] errors of every run at every grid time
        (posterior at update times).
    """
    rng = np.random.default_rng(rng)
    t = np.asarray(t, float)
    dt = float(t[1] - t[0])
    h = sim.dt
    spr = int(round(dt / h))
    if abs(dt / h - spr) > 1e-6 or spr % int(samples_per_step):
        raise ValueError(f"a grid step of {dt:g} s is not a whole number of {samples_per_step}-sample strapdown steps")
    M, N = sim.n_runs, t.size - 1
    nodes = sim.traj.sample(t)
    truth = sd.truth_state(sim.traj, t, mounting=sim.mounting)
    rm, rn = earth.radii(truth.lat)
    scale = np.stack([rm + truth.h, (rn + truth.h) * np.cos(truth.lat), -np.ones_like(truth.h)], -1)
    A = quat.attitude_error_matrix(truth.q)
    fnames = list(filter_names)
    nav_cols = [fnames.index(nm) if nm in fnames else -1 for nm in sd.NAV_STATES]
    snames = [s.name for s in states]
    e_cols = [fnames.index(nm) for nm in kept]
    e_idx = [snames.index(nm) for nm in kept]
    fb = SensorFeedback(model, [nm for nm in fnames if nm not in kept], M)
    s_cols = [fnames.index(nm) for nm in fb.names]
    phi, qd = err
    e = np.array(e0, float).reshape(M, len(states))
    e_hat = np.zeros((M, len(kept)))
    due = _due(plan)
    by_step = {ep.step: ep for ep in epochs}
    state = sim.initial_state(np.asarray(x0, float)[:, :10])
    out = np.empty((N + 1, M, 9))

    def update(k):
        nonlocal e_hat
        ep = by_step[k]
        x, w = nav_point(nodes, k)
        z = np.empty((M, ep.H.shape[0]))
        for m in range(M):
            xh = np.concatenate([[state.lat[m], state.lon[m], state.h[m]], state.v_n[m], state.q[m]])
            parts = []
            for meas in due[k]:
                em = e[m, [snames.index(nm) for nm in meas.state_names]]
                parts.append(meas.scale(x) @ (meas.predict(xh, w) - meas.sensor(x, w, em)))
            z[m] = np.concatenate(parts)
        if measurement_noise:
            z = z - rng.standard_normal(z.shape) @ np.linalg.cholesky(ep.R).T
        if e_cols:
            z = z - e_hat @ ep.Hf[:, e_cols].T
        xh_all = z @ gains[k].T                                   # x̂ = K ν, (M, n_f)
        dx = np.zeros((M, 10))
        for i, c in enumerate(nav_cols):
            if c >= 0:
                dx[:, i] = xh_all[:, c]
        if fb.n:
            fb.add(xh_all[:, s_cols])
        if e_cols:
            e_hat = e_hat + xh_all[:, e_cols]
        return sd.correct(state, dx)

    records = sim.records(chunk=spr * max(1, int(round(60.0 / dt))))
    buf, pos = None, 0
    for k in range(N + 1):
        if k in by_step:
            state = update(k)
        E = sd.nav_errors(state, sd.NavState(float(t[k]), truth.lat[k:k + 1], truth.lon[k:k + 1], truth.h[k:k + 1],
                                             truth.v_n[k:k + 1], truth.q[k:k + 1], np.zeros((1, 3)),
                                             np.zeros((1, 3))))
        out[k, :, :3] = E[:, :3] * scale[k]
        out[k, :, 3:6] = E[:, 3:6]
        out[k, :, 6:9] = E[:, 6:10] @ A[k].T
        if k == N:
            break
        if buf is None or pos >= buf.dtheta.shape[-2]:
            buf, pos = next(records), 0
        rec = buf.slice(pos, pos + spr)
        pos += spr
        ctx = RecordContext.along(sim.traj, rec.t0, h, spr, sim.mounting) if fb.needs_context else None
        raw_th = np.broadcast_to(rec.dtheta, (M, spr, 3))
        raw_dv = np.broadcast_to(rec.dv, (M, spr, 3))
        dth, dvv = fb.compensate(raw_th, raw_dv, h, ctx) if fb.n else (raw_th, raw_dv)
        hist = sd.run(state, type(rec)(rec.t0, h, dth, dvv), int(samples_per_step), every=10**9)
        state = hist.state(-1).replace(t=float(t[k + 1]), dtheta_prev=np.array(dth[:, -1, :]),
                                       dv_prev=np.array(dvv[:, -1, :]))
        # the error states' own processes; the filter's estimate follows their mean dynamics
        noise = rng.standard_normal(e.shape) if measurement_noise else np.zeros(e.shape)
        e = e * phi[k] + noise * np.sqrt(qd[k])
        e_hat = e_hat * phi[k, e_idx]
    return out
