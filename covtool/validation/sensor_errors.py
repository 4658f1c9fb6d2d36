"""Sensor errors drawn from an error-state model, injected into IMU increments.

One realisation per run of the error states of a model, ``x`` of shape
``(M, n_states)`` (e.g. drawn by :func:`sample_states` from the model's
P0), propagated with the model's own processes and injected with the
sensitivities of :mod:`covtool.lincov.model.blocks` — the very functions
that define the linear model's sensor error equations (seed 002, eq (3) and
(5)).  This is how the nonlinear reference (:mod:`covtool.validation.monte_carlo`)
realises the truth model the linear analysis propagates.

Sensor-error increments
-----------------------
With ``ω̄ = Δθ/h`` and ``f̄ = Δv/h`` the sample means and ``x̄`` the mean
error state over the sample::

    δΔθ = h S_g(f̄, ω̄) x̄ + ARW noise,   δΔv = h S_a(f̄, ω̄) x̄ + VRW noise

with ``S`` the block sensitivities (exact for the terms linear in ``f`` and
``ω``: biases, scale factors, misalignments, g-sensitivity).  The
gravity-disturbance block enters as the specific-force error
``C_n^b diag(g, g, −1) x`` the accelerometers would sense, and the AD-reset
block (seed 000) as the velocity increment ``Δe`` of its state.  White
noises: ``N(0, arw² h)`` and ``N(0, vrw² h)`` per sample and axis
(root-PSDs of :attr:`Model.arw`, :attr:`Model.vrw`).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numba
import numpy as np

from covtool.lincov.kalman import covariance_root
from covtool.lincov.model.blocks import BLOCK_KINDS, gravity_sensitivity
from covtool.lincov.model.spec import Model
from covtool.nav import attitude as quat
from covtool.nav.imu.simulator import ImuSimulator

__all__ = [
    "sample_states", "SensorErrors", "grade_simulator",
]


# --------------------------------------------------------------------------
# error states
# --------------------------------------------------------------------------


def sample_states(model: Model, n_runs: int, rng=None, *, q0=None) -> np.ndarray:
    """Draw initial error-state vectors from a model's P0.

    Parameters
    ----------
    model : Model
    n_runs : int
        Number of runs M.
    rng : numpy.random.Generator or int, optional
    q0 : array_like, shape (4,), optional
        Initial attitude (see :meth:`Model.initial_covariance`).

    Returns
    -------
    ndarray, shape (M, n_states)
        Zero-mean Gaussian samples with covariance P0 (P0 may be singular).
    """
    rng = np.random.default_rng(rng)
    P = model.initial_covariance(q0)
    # the principal root: unique and continuous in P (an eigenvector factor is fixed only by round-off
    # where eigenvalues are equal, so a round-off change of P would give other, equivalent draws)
    L = covariance_root(P)
    return rng.standard_normal((int(n_runs), model.n)) @ L.T


@dataclass
class _Group:
    """A block of sensor states and its sensitivity."""

    kind: str
    sensor: str
    cols: np.ndarray          # indices into the model state vector
    sensitivity: object


class SensorErrors:
    """One realisation per run of a model's sensor-error states.

    Parameters
    ----------
    model : Model
        Error-state model (a truth model, or :meth:`covtool.io.imu_grade.ImuGrade.to_model`).
    x0 : ndarray, shape (M, n_states)
        Initial error states (only the sensor and environment states are
        used here; the first ten, the navigation errors, belong to the
        initial :class:`~covtool.nav.strapdown.NavState`).
    rng : numpy.random.Generator or int, optional
        Source of the driving and white noises.
    noise : bool
        False: no driving noise, no ARW/VRW — every state then follows its
        deterministic mean (constants stay, Markov states decay), which is
        what ``ẋ = F x`` of the linear model describes.
    process_dt : float
        Step of the exact discretisation of the state processes; the states
        are interpolated linearly between steps. [s]

    Notes
    -----
    Processes (exactly discretised over ``Δ``): random constant;
    random walk ``x += rw √Δ w``; Markov ``x = e^{−Δ/τ} x +
    σ √(1 − e^{−2Δ/τ}) w``; Markov in distance the same with the horizontal
    distance travelled over ``Δ`` in place of ``Δ/τ·d``.  These are the
    processes behind the model's F and Q_c (:func:`covtool.lincov.dynamics.error_dynamics`).
    """

    def __init__(self, model: Model, x0, rng=None, *, noise: bool = True, process_dt: float = 0.1):
        x0 = np.atleast_2d(np.asarray(x0, dtype=float))
        if x0.ndim != 2 or x0.shape[1] != model.n:
            raise ValueError(f"x0 must have shape (M, {model.n}) for model {model.name!r}, got {x0.shape}")
        if not process_dt > 0:
            raise ValueError(f"process_dt must be positive, got {process_dt!r}")
        self.model = model
        self.x0 = x0
        self.n_runs = x0.shape[0]
        self.rng = np.random.default_rng(rng)
        self.noise = bool(noise)
        self.process_dt = float(process_dt)
        self.arw = model.arw if noise else 0.0
        self.vrw = model.vrw if noise else 0.0
        self.groups: list[_Group] = []
        for block in model.block_names():
            idx = [i for i, s in enumerate(model.states) if s.block == block]
            kind = model.states[idx[0]].kind
            if kind == "navigation":
                continue
            bk = BLOCK_KINDS[kind]
            self.groups.append(_Group(kind, bk.sensor, np.array(idx), bk.sensitivity))
        sensor_cols = [i for g in self.groups for i in g.cols]
        self.dynamic = np.array([i for i in sensor_cols if model.states[i].process != "constant"], dtype=int)
        self.needs_speed = any(model.states[i].process == "markov_distance" for i in self.dynamic)
        self.needs_attitude = any(g.sensor == "gravity" for g in self.groups)
        # process state: values at the last process node
        self._x_dyn = x0[:, self.dynamic].copy()
        self._node_t = None
        self._node_x = None

    @classmethod
    def from_grade(cls, grade, n_runs: int, rng=None, **kw) -> "SensorErrors":
        """Draw M realisations of a grade's errors (:meth:`covtool.io.imu_grade.ImuGrade.to_model`)."""
        rng = np.random.default_rng(rng)
        model = grade.to_model()
        return cls(model, sample_states(model, n_runs, rng), rng, **kw)

    # ---- processes -------------------------------------------------------
    def _coefficients(self, dt, dist):
        """Transition ``a`` and noise scale ``b`` of every dynamic state.

        ``dist`` (horizontal distance of each step, shape (J,)) may be None
        when no state is Markov in distance.  Returns arrays of shape
        (J, n_dyn).
        """
        J = 1 if dist is None else dist.size
        a = np.ones((J, self.dynamic.size))
        b = np.zeros((J, self.dynamic.size))
        for j, i in enumerate(self.dynamic):
            s = self.model.states[i]
            if s.process == "markov":
                a[:, j] = math.exp(-dt / s.tau)
                b[:, j] = s.sigma * math.sqrt(max(0.0, 1.0 - a[0, j] ** 2))
            elif s.process == "markov_distance":
                a[:, j] = np.exp(-dist / s.distance)
                b[:, j] = s.sigma * np.sqrt(np.clip(1.0 - a[:, j] ** 2, 0.0, None))
            else:  # random walk
                b[:, j] = s.rw * math.sqrt(dt)
        if not self.noise:
            b[:] = 0.0
        return a, b

    def _dynamic_path(self, t_edges, speed_fn, *, nodes: bool = False):
        """Dynamic states at the sample edges, shape (M, K+1, n_dyn).

        ``nodes=True`` returns the process nodes and the interpolation instead,
        ``(x_nodes (M, J, n_dyn), j (K+1,), u (K+1,))`` with the edge values
        ``x_nodes[:, j] + u (x_nodes[:, j+1] − x_nodes[:, j])`` (J = 1: j = 0,
        u = 0, the single node everywhere).
        """
        nd = self.dynamic.size
        if nd == 0:
            if nodes:
                return np.zeros((self.n_runs, 1, 0)), np.zeros(t_edges.size, np.int64), np.zeros(t_edges.size)
            return np.zeros((self.n_runs, t_edges.size, 0))
        if self._node_t is None:
            self._node_t = np.array([float(t_edges[0])])
            self._node_x = self._x_dyn[:, None, :]
        # new process nodes up to the end of the chunk, exactly discretised
        last = self._node_t[-1]
        J = max(0, int(math.ceil((t_edges[-1] - last) / self.process_dt - 1e-9)))
        if J:
            tn = last + self.process_dt * np.arange(1, J + 1)
            dist = None
            if self.needs_speed:
                if speed_fn is None:
                    raise ValueError("Markov-in-distance states need the horizontal speed (speed_fn)")
                dist = np.asarray(speed_fn(tn - 0.5 * self.process_dt), float) * self.process_dt
            a, b = self._coefficients(self.process_dt, dist)
            a = np.ascontiguousarray(np.broadcast_to(a, (J, nd)))
            b = np.ascontiguousarray(np.broadcast_to(b, (J, nd)))
            xs = np.empty((self.n_runs, J, nd))
            _process_steps(np.ascontiguousarray(self._node_x[:, -1, :]), a, b, self.rng, self.noise, xs)
            self._node_t = np.concatenate([self._node_t, tn])
            self._node_x = np.concatenate([self._node_x, xs], axis=1)
        # keep the nodes from the one at or before the chunk start
        keep = max(0, int(np.searchsorted(self._node_t, t_edges[0] + 1e-12, side="right")) - 1)
        self._node_t = self._node_t[keep:]
        self._node_x = self._node_x[:, keep:]
        nt, nx = self._node_t, self._node_x
        if nt.size == 1:
            if nodes:
                return nx, np.zeros(t_edges.size, np.int64), np.zeros(t_edges.size)
            return np.repeat(nx, t_edges.size, axis=1)
        j = np.clip(np.searchsorted(nt, t_edges, side="right") - 1, 0, nt.size - 2)
        u = (t_edges - nt[j]) / (nt[j + 1] - nt[j])
        if nodes:
            return nx, j.astype(np.int64), u
        u = u[None, :, None]
        return nx[:, j] + u * (nx[:, j + 1] - nx[:, j])

    def advance(self, t0, h, k: int, *, speed_fn=None, **context) -> None:
        """Advance the processes over ``k`` samples from ``t0`` without injecting errors.

        What :meth:`increment_errors` does first (the same process nodes and
        speed look-ups); the attitude and gravity of ``context`` are not
        needed.
        """
        self._dynamic_path(t0 + h * np.arange(k + 1), speed_fn, nodes=True)

    # ---- injection ---------------------------------------------------------
    def increment_errors(self, t0, h, dtheta, dv, *, speed_fn=None, attitude=None, gravity=None):
        """Errors of one chunk of samples (advances the processes).

        Parameters
        ----------
        t0 : float
            Start of the chunk. [s]
        h : float
            Sample period. [s]
        dtheta, dv : ndarray, shape (Mv, k, 3)
            True increments (``Mv`` = 1 or M).
        speed_fn : callable, optional
            Horizontal speed at an array of times [m/s] (Markov-in-distance
            states).
        attitude : ndarray, shape (k, 4), optional
            True ``q_ns`` at the sample mid-points (gravity block).
        gravity : ndarray, shape (k,), optional
            Normal gravity at the sample mid-points. [m/s²]

        Returns
        -------
        ddtheta, ddv : ndarray, shape (M, k, 3)
            Errors to add to the increments. [rad], [m/s]
        """
        M = self.n_runs
        k = dtheta.shape[-2]
        t_edges = t0 + h * np.arange(k + 1)
        nx, jn, un = self._dynamic_path(t_edges, speed_fn, nodes=True)  # process nodes, interpolation
        dyn_pos = {int(i): j for j, i in enumerate(self.dynamic)}
        Mv = dtheta.shape[0]
        fbar = (dv / h).reshape(Mv * k, 3)
        wbar = (dtheta / h).reshape(Mv * k, 3)
        # collect the sensitivities per sensor, constant and dynamic states apart
        parts = {(t, d): ([], []) for t in ("gyro", "accel") for d in (False, True)}
        for g in self.groups:
            if g.sensor == "ad_reset":
                continue
            if g.sensor == "gravity":
                if attitude is None or gravity is None:
                    raise ValueError("the gravity-disturbance block needs the true attitude and gravity")
                S = np.einsum("kji,kjl->kil", quat.dcm(attitude), gravity_sensitivity(gravity))[None]
                target = "accel"
            else:
                S = g.sensitivity(fbar, wbar).reshape(Mv, k, 3, g.cols.size)
                target = g.sensor
            for j, i in enumerate(g.cols):
                dyn = int(i) in dyn_pos
                Ss, cols = parts[(target, dyn)]
                Ss.append(np.broadcast_to(S[..., j], (Mv, k, 3)))
                cols.append(dyn_pos[int(i)] if dyn else int(i))
        out = {}
        for target in ("gyro", "accel"):
            acc = None
            Ss, cols = parts[(target, False)]
            if cols:
                S = np.stack(Ss, axis=-1)                                  # (Mv, k, 3, nc)
                xc = self.x0[:, cols]                                      # (M, nc)
                if Mv == 1:   # one matrix product for all runs
                    acc = (S[0].reshape(k * 3, -1) @ xc.T).T.reshape(M, k, 3)
                else:
                    acc = np.einsum("mkij,mj->mki", S, xc)
                acc = np.require(acc, requirements=["C", "W"])
            if acc is None:
                acc = np.zeros((M, k, 3))
            Ss, cols = parts[(target, True)]
            if cols:
                # S x̄ with x̄ the mean of the interpolated path over the sample (compiled)
                S = np.ascontiguousarray(np.stack(Ss, axis=-1))            # (Mv, k, 3, nd)
                _mean_path_apply(nx, jn, un, S, np.array(cols, np.int64), acc)
            acc *= h
            out[target] = acc
        ddth, ddv = out["gyro"], out["accel"]
        for g in self.groups:
            if g.sensor == "ad_reset":
                # δf^b = ė: the velocity-increment error is the change of e
                cols = np.array([dyn_pos[int(i)] for i in g.cols], np.int64)
                _path_difference_add(nx, jn, un, cols, ddv)
        if self.arw > 0:
            _add_white(ddth, self.arw * math.sqrt(h), self.rng)
        if self.vrw > 0:
            _add_white(ddv, self.vrw * math.sqrt(h), self.rng)
        return ddth, ddv


def grade_simulator(traj, grade, n_runs: int, rng=None, *, extras: bool = True, rate=None, noise: bool = True,
                    **kw) -> ImuSimulator:
    """Simulator of M runs of an IMU grade (errors drawn from its model).

    Parameters
    ----------
    traj : covtool.nav.trajectory.core.Trajectory
        True motion.
    grade : covtool.io.imu_grade.ImuGrade
        The grade (its model, quantisation, range and rate).
    n_runs : int
        Number of runs M.
    rng : numpy.random.Generator or int, optional
    extras : bool
        Apply the grade's quantisation and range saturation.
    rate : float, optional
        Sample rate (default: the grade's). [Hz]
    noise : bool
        See :class:`SensorErrors`.
    **kw
        Passed to :class:`~covtool.nav.imu.simulator.ImuSimulator` (``t0``,
        ``duration``, ``vibration``, ``mounting`` …).

    Raises
    ------
    ValueError
        The grade has no rate and none is given.
    """
    rng = np.random.default_rng(rng)
    rate = grade.rate if rate is None else rate
    if rate is None:
        raise ValueError(f"IMU grade {grade.name!r} has no rate; pass rate=")
    errors = SensorErrors.from_grade(grade, n_runs, rng, noise=noise)
    if extras:
        kw.setdefault("quantization", grade.quantization)
        kw.setdefault("saturation", grade.range)
    return ImuSimulator(traj, rate, errors=errors, rng=rng, **kw)


# --------------------------------------------------------------------------
# fault injection
# --------------------------------------------------------------------------


class GSensitiveErrors(SensorErrors):
    """Sensor errors plus a g-sensitive gyro scale-factor error.

    Parameters
    ----------
    model, x0, rng, **kw
        As for :class:`covtool.validation.sensor_errors.SensorErrors`.
    gsens : sequence of (int, int, float)
        ``(i, j, k)``: the scale factor of gyro ``i`` changes by ``k f_j``,
        ``δω_i = k f_j ω_i`` (seed 001, Fig 16 and ref [9]: a parallel-plate
        sense electrode moved by the acceleration along it). ``k`` in
        [1/(m/s²)].

    Notes
    -----
    The term is added per sample from the true sample means
    ``f̄ = Δv/h``, ``ω̄ = Δθ/h``: ``δΔθ_i = k (Δv_j/h) Δθ_i``.
    """

    def __init__(self, model: Model, x0, rng=None, *, gsens=(), **kw):
        super().__init__(model, x0, rng, **kw)
        out = []
        for item in gsens:
            i, j, k = item
            if int(i) not in (0, 1, 2) or int(j) not in (0, 1, 2):
                raise ValueError(f"g-sensitive scale factor axes must be 0, 1 or 2, got {item!r}")
            out.append((int(i), int(j), float(k)))
        self.gsens = tuple(out)

    def increment_errors(self, t0, h, dtheta, dv, **kw):
        """Sensor-error increments plus the g-sensitive term."""
        ddth, ddv = super().increment_errors(t0, h, dtheta, dv, **kw)
        for i, j, k in self.gsens:
            ddth[..., i] += k * (dv[..., j] / h) * dtheta[..., i]
        return ddth, ddv


# --------------------------------------------------------------------------
# compiled path kernels (issue 13): the same arithmetic as the numpy
# interpolation of _dynamic_path, without (M, K, n_dyn) temporaries
# --------------------------------------------------------------------------


@numba.njit(cache=True, nogil=True)
def _edge(nx, jn, un, m, e, d):
    j = jn[e]
    if nx.shape[1] == 1:
        return nx[m, 0, d]
    return nx[m, j, d] + un[e] * (nx[m, j + 1, d] - nx[m, j, d])


@numba.njit(cache=True, nogil=True)
def _mean_path_apply(nx, jn, un, S, cols, acc):
    """``acc[m, k] += S[k] x̄[m, k, cols]``, x̄ the mean of the edge values.

    ``S`` (Mv, K, 3, len(cols)) with Mv = 1 (shared) or M.  The states are
    added in ``cols`` order at every sample.
    """
    M, K = acc.shape[0], acc.shape[1]
    shared = S.shape[0] == 1
    for m in range(M):
        mv = 0 if shared else m
        for c in range(cols.size):
            d = cols[c]
            lo = _edge(nx, jn, un, m, 0, d)
            for k in range(K):
                hi = _edge(nx, jn, un, m, k + 1, d)
                xb = 0.5 * (hi + lo)
                for i in range(3):
                    acc[m, k, i] += S[mv, k, i, c] * xb
                lo = hi


@numba.njit(cache=True, nogil=True)
def _process_steps(x, a, b, rng, noise, out):
    """``out[:, j] = x_j = a_j x_{j−1} + b_j w_j`` from ``x_{−1} = x`` (M, n_dyn).

    ``a``, ``b`` (J, n_dyn); ``w ~ N(0, 1)`` drawn from ``rng`` in (j, run,
    state) order (the stream of ``rng.standard_normal((J, M, n_dyn))``), or
    zero without ``noise``.
    """
    M, J, nd = out.shape
    cur = x.copy()
    for j in range(J):
        for m in range(M):
            for d in range(nd):
                w = rng.standard_normal() if noise else 0.0
                cur[m, d] = a[j, d] * cur[m, d] + b[j, d] * w
                out[m, j, d] = cur[m, d]


@numba.njit(cache=True, nogil=True)
def _add_white(out, scale, rng):
    """``out += scale · w``, ``w ~ N(0, 1)`` from ``rng`` in C order (the stream of
    ``rng.standard_normal(out.shape)``); ``out`` C-contiguous."""
    flat = out.reshape(-1)
    for i in range(flat.size):
        flat[i] += scale * rng.standard_normal()


@numba.njit(cache=True, nogil=True)
def _path_difference_add(nx, jn, un, cols, out):
    """``out[m, k, i] += x[m, k+1, cols[i]] − x[m, k, cols[i]]`` (edge values)."""
    M, K = out.shape[0], out.shape[1]
    for m in range(M):
        for k in range(K):
            for i in range(cols.size):
                d = cols[i]
                out[m, k, i] += _edge(nx, jn, un, m, k + 1, d) - _edge(nx, jn, un, m, k, d)
