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

The ensemble loop is :func:`covtool.validation.monte_carlo.run_ensemble`
(the ZUPT ensemble's): :class:`DeclaredMeasurements` is its measurement hook.

Pure numeric core: arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np

from covtool.lincov.measurements import nav_point
from covtool.validation.feedback import FeedbackFilter
from covtool.validation.monte_carlo import EnsembleCase, run_ensemble

__all__ = ["DeclaredMeasurements", "run_aided_ensemble"]


def _due(plan):
    due: dict[int, list] = {}
    for meas, steps in plan:
        for k in np.asarray(steps, int):
            due.setdefault(int(k), []).append(meas)
    return due


class DeclaredMeasurements:
    """Declared measurements as the hook of the ensemble loop (issue 15).

    The measurement hook of :func:`covtool.validation.monte_carlo.run_ensemble`
    (:class:`covtool.validation.monte_carlo.Zupt` lists its methods).  Every
    run carries its own realisation ``e`` of the measurements' error states,
    shared by the cases (common random numbers); each case keeps its
    estimate ``ê`` of the error states its filter keeps.

    Parameters
    ----------
    plan : sequence of (Measurement, ndarray of int)
        The measurements and their update steps
        (:func:`covtool.lincov.aided.build_epochs`).
    epochs : list of covtool.lincov.aided.Epoch
        The stacked updates (their ``Hf`` and true ``R``).
    states : sequence of State
        The measurement-error states of the truth.
    nodes : Trajectory
        The reference trajectory sampled on the grid (the true state).
    e0 : ndarray, shape (M, n_e)
        Initial values of the error states (``states`` order).
    err : tuple of ndarray (phi, qd), each shape (N, n_e)
        Their exact transitions (:func:`covtool.lincov.aided.error_processes`).
    noise : bool
        False: no measurement noise and no error-state driving noise.
    """

    def __init__(self, plan, epochs, states, nodes, e0, err, noise: bool = True):
        self.due = _due(plan)
        self.by_step = {ep.step: ep for ep in epochs}
        self.snames = [s.name for s in states]
        self.filter_states = tuple(self.snames)
        self.nodes = nodes
        self.e = np.array(e0, float).reshape(-1, len(states))
        self.phi, self.qd = err
        self.noise = bool(noise)

    def start(self, cases, n_runs: int, steps, rng) -> None:
        missing = [k for k in steps if k not in self.by_step]
        if missing:
            raise ValueError(f"a filter has a gain at grid step {missing[0]}, where no measurement is due")
        self.rng = rng
        self.e_cols, self.e_idx, self.e_hat = [], [], []
        for c in cases:
            fn = list(c.filter.names) if c.filter is not None else []
            kept = [nm for nm in fn if nm in self.snames]
            self.e_cols.append([fn.index(nm) for nm in kept])
            self.e_idx.append([self.snames.index(nm) for nm in kept])
            self.e_hat.append(np.zeros((n_runs, len(kept))))
        self._v = {}

    def residual(self, k: int, i: int, state, rows) -> np.ndarray:
        """``ν = M (predict(x̂) − sensor(x, e)) − v − H_f,e ê`` of case ``i`` (M, m)."""
        ep = self.by_step[k]
        x, w = nav_point(self.nodes, k)
        lat, lon, h, v_n, q = (a[rows] for a in (state.lat, state.lon, state.h, state.v_n, state.q))
        # every run at once: its computed navigation point and its own error-state values
        xh = np.concatenate([lat[:, None], lon[:, None], h[:, None], v_n, q], axis=1)          # (M, 10)
        z = np.concatenate([meas.innovation(x, w, xh, self.e[:, [self.snames.index(nm) for nm in meas.state_names]])
                            for meas in self.due[k]], axis=1)
        if self.noise:
            if k not in self._v:              # one draw per update, shared by the cases
                self._v = {k: self.rng.standard_normal(z.shape) @ np.linalg.cholesky(ep.R).T}
            z = z - self._v[k]
        if self.e_cols[i]:
            z = z - self.e_hat[i] @ ep.Hf[:, self.e_cols[i]].T
        return z

    def estimated(self, k: int, i: int, xh) -> None:
        if self.e_cols[i]:
            self.e_hat[i] = self.e_hat[i] + xh[:, self.e_cols[i]]

    def advance(self, k0: int, k1: int) -> None:
        # the error states' own processes, step by step; the filters' estimates follow their mean dynamics
        for j in range(k0, k1):
            noise = self.rng.standard_normal(self.e.shape) if self.noise else np.zeros(self.e.shape)
            self.e = self.e * self.phi[j] + noise * np.sqrt(self.qd[j])
            for i, idx in enumerate(self.e_idx):
                self.e_hat[i] = self.e_hat[i] * self.phi[j, idx]


def run_aided_ensemble(sim, x0, e0, t, *, samples_per_step: int, plan, epochs, gains, filter_names, states,
                       kept, model, err, rng=None, measurement_noise: bool = True) -> np.ndarray:
    """Run M nonlinear INS with an aided feedback filter; return their errors.

    One case of :func:`covtool.validation.monte_carlo.run_ensemble` with
    :class:`DeclaredMeasurements` as its measurement.

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

    Raises
    ------
    ValueError
        ``kept`` differs from the error states among ``filter_names``; a
        grid the strapdown steps do not divide.
    """
    fnames = list(filter_names)
    snames = [s.name for s in states]
    if [nm for nm in fnames if nm in snames] != list(kept):
        raise ValueError(f"kept error states {list(kept)} differ from those of the filter's states "
                         f"{[nm for nm in fnames if nm in snames]}")
    t = np.asarray(t, float)
    hook = DeclaredMeasurements(plan, epochs, states, sim.traj.sample(t), e0, err, noise=measurement_noise)
    case = EnsembleCase("aided", FeedbackFilter("aided", tuple(fnames), dict(gains), np.empty((0, 0, 0))))
    _, errs = run_ensemble(sim, x0, [case], t, samples_per_step=samples_per_step, rng=rng, model=model,
                           record_errors="quantities", measurement=hook)
    return errs["aided"]
