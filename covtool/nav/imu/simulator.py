"""IMU simulator: exact increments of a trajectory, with errors and vibration.

:class:`ImuSimulator` streams :class:`ImuRecord` chunks of shape
``(M, k, 3)`` that :func:`covtool.nav.strapdown.run` consumes: exact
increments of a trajectory (:func:`ideal_increments`), optionally with
mounting rotation and vibration (:mod:`covtool.nav.imu.vibration`, a real
motion, so coning and sculling are physical), plus sensor errors (any
object with ``increment_errors``, e.g.
:class:`covtool.validation.sensor_errors.SensorErrors`) and the extras that
lie outside the linear model (quantisation, range saturation).

Increments
----------
An integrating gyro outputs ``Δθ_k = ∫_{t_k}^{t_{k+1}} ω_ib^b dt`` and an
integrating accelerometer ``Δv_k = ∫ f^b dt``, both in the *instantaneous*
body frame; turning them into a rotation vector and a velocity increment in
the start-of-interval frame is the strapdown algorithm's job (coning and
sculling, seed 001 eq (1)–(4)).  The increments are therefore the
integrals of the trajectory's exact ω_ib^b(t) and f^b(t)
(:meth:`covtool.nav.trajectory.core.Trajectory.sample`), by Gauss–Legendre
quadrature with enough nodes per sample for the highest frequency present.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numba
import numpy as np

from covtool.nav import attitude as quat
from covtool.nav.imu.vibration import right_jacobian_apply, Vibration

__all__ = [
    "ImuRecord", "ideal_increments", "ImuSimulator",
]


# --------------------------------------------------------------------------
# records
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class ImuRecord:
    """IMU increments on a uniform sample grid.

    Attributes
    ----------
    t0 : float
        Start of the first sample period. [s]
    dt : float
        Sample period h. [s]
    dtheta : ndarray, shape (K, 3) or (M, K, 3)
        Angle increments of the sample periods ``[t0 + k h, t0 + (k+1) h]``.
        [rad]
    dv : ndarray, same shape
        Velocity increments. [m/s]
    """

    t0: float
    dt: float
    dtheta: np.ndarray
    dv: np.ndarray

    @property
    def n_samples(self) -> int:
        """Number of samples K."""
        return self.dtheta.shape[-2]

    @property
    def t(self) -> np.ndarray:
        """End time of every sample period, shape (K,). [s]"""
        return self.t0 + self.dt * np.arange(1, self.n_samples + 1)

    @property
    def rate(self) -> float:
        """Sample rate. [Hz]"""
        return 1.0 / self.dt

    def slice(self, a: int, b: int) -> "ImuRecord":
        """Samples ``a … b−1`` as a record."""
        return ImuRecord(self.t0 + a * self.dt, self.dt, self.dtheta[..., a:b, :], self.dv[..., a:b, :])


def _gl_nodes(nodes: int):
    x, w = np.polynomial.legendre.leggauss(nodes)
    return 0.5 * (1.0 + x), 0.5 * w


def _auto_nodes(max_freq: float, h: float, minimum: int = 3) -> int:
    """Gauss–Legendre nodes integrating ``max_freq`` to ~1e-13."""
    lam = 2.0 * math.pi * max_freq * h
    n = minimum
    while n < 24 and (0.5 * lam) ** (2 * n) / math.factorial(2 * n) > 1e-13:
        n += 1
    return n


def _span(traj, rate, t0, duration):
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"IMU rate must be positive, got {rate!r} Hz")
    h = 1.0 / float(rate)
    t0 = float(traj.t[0]) if t0 is None else float(t0)
    end = float(traj.t[-1]) if duration is None else t0 + float(duration)
    K = int(math.floor((end - t0) / h + 1e-9))
    if K < 1:
        raise ValueError(f"the span [{t0:g}, {end:g}] s holds no whole sample at {rate:g} Hz")
    if end > float(traj.t[-1]) + 1e-9 * max(1.0, end) or t0 < float(traj.t[0]) - 1e-9:
        raise ValueError(f"the span [{t0:g}, {end:g}] s exceeds the trajectory "
                         f"[{traj.t[0]:g}, {traj.t[-1]:g}] s")
    return t0, h, K


def ideal_increments(traj, rate: float, *, t0: float | None = None, duration: float | None = None,
                     nodes: int = 3, mounting=None, chunk: int = 20000) -> ImuRecord:
    """Error-free increments of a trajectory.

    Parameters
    ----------
    traj : covtool.nav.trajectory.core.Trajectory
        True motion; :meth:`~covtool.nav.trajectory.core.Trajectory.sample` is exact
        for declared profiles.
    rate : float
        Sample rate. [Hz]
    t0 : float, optional
        Start (default: trajectory start). [s]
    duration : float, optional
        Length (default: to the trajectory end, whole samples). [s]
    nodes : int
        Gauss–Legendre nodes per sample.
    mounting : array_like, shape (4,), optional
        Quaternion ``q_bs`` of the IMU frame in the body frame: the output
        is ``C_b^s Δθ^b``, ``C_b^s Δv^b``.
    chunk : int
        Samples evaluated at once (bounds memory).

    Returns
    -------
    ImuRecord
        ``dtheta``, ``dv`` of shape (K, 3).
    """
    t0, h, K = _span(traj, rate, t0, duration)
    u, w = _gl_nodes(nodes)
    dth = np.empty((K, 3))
    dv = np.empty((K, 3))
    R = None if mounting is None else quat.dcm(np.asarray(mounting, float))
    for a in range(0, K, chunk):
        b = min(K, a + chunk)
        ts = t0 + (np.arange(a, b)[:, None] + u[None, :]) * h
        s = traj.sample(ts.ravel())
        wb = s.w_ib_b.reshape(b - a, nodes, 3)
        fb = s.f_b.reshape(b - a, nodes, 3)
        dth[a:b] = h * np.einsum("j,kjc->kc", w, wb)
        dv[a:b] = h * np.einsum("j,kjc->kc", w, fb)
    if R is not None:
        dth = dth @ R
        dv = dv @ R
    return ImuRecord(t0, h, dth, dv)


# --------------------------------------------------------------------------
# simulator
# --------------------------------------------------------------------------


class ImuSimulator:
    """Stream of IMU increments of M runs along a trajectory.

    Parameters
    ----------
    traj : covtool.nav.trajectory.core.Trajectory
        True motion of the vehicle body.
    rate : float
        Sample rate. [Hz]
    t0, duration : float, optional
        Span (default: the whole trajectory, whole samples). [s]
    errors : covtool.validation.sensor_errors.SensorErrors, optional
        Sensor errors (sets the number of runs M); None: error-free.  Any
        object with ``n_runs`` and ``increment_errors`` will do.
    n_runs : int
        Number of runs when neither ``errors`` nor ``vibration`` sets it.
    quantization : tuple of (float or None), optional
        ``(angle LSB [rad], velocity LSB [m/s])``: the outputs are whole
        multiples of the LSB with the remainder carried to the next sample
        (pulse counting), so the quantisation error never accumulates.
    saturation : tuple of (float or None), optional
        ``(rate range [rad/s], specific-force range [m/s²])``: the sample
        means are clipped per axis.
    vibration : Vibration or VibrationRealization, optional
        Vibration of the IMU as a real motion (see Notes).
    mounting : array_like, shape (4,), optional
        ``q_bs``, the IMU (sensor) frame in the body frame.
    nodes : int, optional
        Gauss–Legendre nodes per sample (default: 3, more when vibration
        frequencies require it).
    chunk : int
        Samples per streamed record (1200 is a multiple of 1 … 6).
    rng : numpy.random.Generator or int, optional
        For the vibration phases (the errors carry their own generator).
    truth_cache : dict, optional
        Memo of the exact increments of each chunk, shared by simulators of
        one motion that differ only in their errors (e.g. the batches of a
        Monte Carlo study): the trajectory is then sampled once for all of
        them.  Keyed by trajectory, rate, nodes, mounting and chunk; the
        cached arrays are read-only.  The reference attitude, gravity and
        speed the errors need (:meth:`_context`) are memoised there too.

    Raises
    ------
    ValueError
        A non-positive rate or chunk, a span outside the trajectory,
        inconsistent numbers of runs, or ``truth_cache`` with a vibration
        realisation (random per simulator, so not shareable).

    Notes
    -----
    Vibration: the IMU frame is the nominal frame rotated by ``exp(θ(t))``
    and accelerated by ``a(t)`` (nominal frame) relative to it, so::

        ω^s = Cᵀ ω_nom^s + J_r(θ) θ̇,   f^s = Cᵀ (f_nom^s + a),   C = C(exp θ)

    and the truth (:meth:`truth`) is ``q_nb ⊗ q_bs ⊗ exp(θ)``, velocity
    ``v + C_s^n ∫a`` and position offset ``C_s^n ∫∫a``.  The increments are
    the quadrature of these exact rates, so coning and sculling are those of
    the real motion.  (The Coriolis and frame-rotation effects of the
    vibration velocity, µm/s for typical levels, are neglected.)
    """

    def __init__(self, traj, rate: float, *, t0=None, duration=None, errors=None,
                 n_runs: int = 1, quantization=None, saturation=None, vibration=None, mounting=None,
                 nodes: int | None = None, chunk: int = 1200, rng=None, truth_cache: dict | None = None):
        self.traj = traj
        self.t0, self.dt, self.n_samples = _span(traj, rate, t0, duration)
        self.rate = 1.0 / self.dt
        self.errors = errors
        if isinstance(vibration, Vibration):
            M = errors.n_runs if errors is not None else int(n_runs)
            vibration = vibration.realize(M, rng)
        self.vibration = vibration
        runs = {int(n_runs)} if errors is None and vibration is None else set()
        if errors is not None:
            runs.add(errors.n_runs)
        if vibration is not None and vibration.n_runs > 1:
            runs.add(vibration.n_runs)
        if len(runs) > 1:
            raise ValueError(f"inconsistent numbers of runs: {sorted(runs)}")
        self.n_runs = runs.pop() if runs else 1
        self.quantization = (None, None) if quantization is None else tuple(quantization)
        self.saturation = (None, None) if saturation is None else tuple(saturation)
        self.mounting = None if mounting is None else np.asarray(mounting, dtype=float)
        self._R = None if mounting is None else quat.dcm(self.mounting)   # C_s^b
        fmax = vibration.max_frequency if vibration is not None else 0.0
        self.nodes = int(nodes) if nodes is not None else _auto_nodes(fmax, self.dt)
        if chunk < 1:
            raise ValueError(f"chunk must be a positive number of samples, got {chunk!r}")
        self.chunk = int(chunk)
        if truth_cache is not None and vibration is not None:
            raise ValueError("truth_cache cannot be shared with a vibration realisation (random per simulator)")
        self.truth_cache = truth_cache

    # ---- truth -----------------------------------------------------------
    def truth(self, t):
        """True state of the IMU frame at times ``t``.

        Returns
        -------
        covtool.nav.strapdown.NavState
            Arrays of leading length S, or (S, M) with per-run vibration.
        """
        from covtool.nav.strapdown import NavState, truth_state

        t = np.atleast_1d(np.asarray(t, dtype=float))
        tr = truth_state(self.traj, t, mounting=self.mounting)
        vib = self.vibration
        if vib is None:
            return tr
        rel = quat.from_rotvec(vib.angle(t))                       # (Mv, S, 4)
        q = quat.mul(tr.q[None], rel)
        C = quat.dcm(tr.q)                                         # (S, 3, 3) nominal C_s^n
        v = tr.v_n[None] + np.einsum("sij,msj->msi", C, vib.velocity(t))
        d = np.einsum("sij,msj->msi", C, vib.displacement(t))
        from covtool.nav import earth
        rm, rn = earth.radii(tr.lat)
        lat = tr.lat[None] + d[..., 0] / (rm + tr.h)
        lon = tr.lon[None] + d[..., 1] / ((rn + tr.h) * np.cos(tr.lat))
        h = tr.h[None] - d[..., 2]
        tp = lambda a: np.swapaxes(a, 0, 1)   # (Mv, S, …) -> (S, Mv, …)
        if vib.n_runs == 1:
            return NavState(tr.t, lat[0], lon[0], h[0], v[0], q[0], tr.dtheta_prev, tr.dv_prev)
        S = t.size
        return NavState(tr.t, tp(lat), tp(lon), tp(h), tp(v), tp(q), np.zeros((S, 3)), np.zeros((S, 3)))

    def initial_state(self, errors=None, *, previous: bool = True):
        """Initial navigation state of the IMU frame for the M runs.

        Parameters
        ----------
        errors : ndarray, shape (M, 10), optional
            Initial navigation errors (e.g. ``x0[:, :10]``).
        previous : bool
            Seed the "previous sample" with the exact increment of the
            sample period before ``t0`` when the trajectory allows it.
        """
        from covtool.nav.strapdown import NavState

        tr = self.truth([self.t0])
        M = self.n_runs
        x = np.zeros((M, 10)) if errors is None else np.broadcast_to(np.asarray(errors, float), (M, 10))
        if tr.lat.ndim == 2:
            lat, lon, h, v, q = tr.lat[0], tr.lon[0], tr.h[0], tr.v_n[0], tr.q[0]
        else:
            lat, lon, h = (np.repeat(a, M) for a in (tr.lat, tr.lon, tr.h))
            v, q = np.repeat(tr.v_n, M, axis=0), np.repeat(tr.q, M, axis=0)
        q = q + x[:, 6:10]
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        dth_p = np.zeros((M, 3))
        dv_p = np.zeros((M, 3))
        if previous and self.t0 - self.dt >= float(self.traj.t[0]) - 1e-12:
            a, b = self._true_increments(self.t0 - self.dt, 1)
            dth_p[:] = a[:, 0]
            dv_p[:] = b[:, 0]
        return NavState(self.t0, lat + x[:, 0], lon + x[:, 1], h + x[:, 2], v + x[:, 3:6], q, dth_p, dv_p)

    # ---- increments --------------------------------------------------------
    def _cache_key(self, *what):
        mounting = None if self.mounting is None else tuple(self.mounting.tolist())
        return (id(self.traj), self.dt, self.nodes, mounting) + what

    @staticmethod
    def adopt_cache(cache: dict, traj) -> dict:
        """A ``truth_cache`` filled along a copy of ``traj``, keyed for ``traj``.

        The cache keys start with the identity of the trajectory object; a
        cache filled in another process (e.g. the parent of Monte Carlo
        workers, along the same motion) is re-keyed for the worker's copy.
        """
        return {(id(traj),) + key[1:]: v for key, v in cache.items()}

    def _true_increments(self, t_start, k):
        """Exact increments of k samples, shape (Mv, k, 3)."""
        if self.truth_cache is not None:
            key = self._cache_key(float(t_start), int(k))
            if key not in self.truth_cache:
                dth, dv = self._sample_increments(t_start, k)
                dth.flags.writeable = dv.flags.writeable = False
                self.truth_cache[key] = (dth, dv)
            return self.truth_cache[key]
        return self._sample_increments(t_start, k)

    def _sample_increments(self, t_start, k):
        h = self.dt
        u, w = _gl_nodes(self.nodes)
        ts = (t_start + (np.arange(k)[:, None] + u[None, :]) * h).ravel()
        s = self.traj.sample(ts)
        wb, fb = s.w_ib_b, s.f_b
        if self._R is not None:
            wb = wb @ self._R
            fb = fb @ self._R
        vib = self.vibration
        if vib is None:
            wb, fb = wb[None], fb[None]
        else:
            th = vib.angle(ts)
            Ct = np.swapaxes(quat.dcm(quat.from_rotvec(th)), -1, -2)   # C(exp θ)ᵀ
            wb = np.einsum("mnij,nj->mni", Ct, wb) + right_jacobian_apply(th, vib.angle_rate(ts))
            fb = np.einsum("mnij,mnj->mni", Ct, fb[None] + vib.accel(ts))
        Mv = wb.shape[0]
        dth = h * np.einsum("j,mkjc->mkc", w, wb.reshape(Mv, k, self.nodes, 3))
        dv = h * np.einsum("j,mkjc->mkc", w, fb.reshape(Mv, k, self.nodes, 3))
        return dth, dv

    def _context(self, t_start, k):
        """Speed, mid-sample attitude and gravity for the errors."""
        from covtool.nav import earth

        kw = {}
        if self.errors is None:
            return kw
        cache = self.truth_cache
        if self.errors.needs_speed:
            traj = self.traj

            def speed(t):
                t = np.atleast_1d(np.asarray(t, float))
                key = None if cache is None else self._cache_key("speed", t.tobytes())
                if key is not None and key in cache:
                    return cache[key]
                v = np.linalg.norm(traj.sample(np.clip(t, traj.t[0], traj.t[-1])).v_n[:, :2], axis=-1)
                if key is not None:
                    cache[key] = v
                return v
            kw["speed_fn"] = speed
        if self.errors.needs_attitude:
            key = None if cache is None else self._cache_key("attitude", float(t_start), int(k))
            if key is None or key not in cache:
                tm = t_start + (np.arange(k) + 0.5) * self.dt
                s = self.traj.sample(tm)
                q = s.q_nb if self.mounting is None else quat.mul(s.q_nb, self.mounting)
                value = (q, earth.gravity(s.lat, s.h))
                if key is None:
                    kw["attitude"], kw["gravity"] = value
                    return kw
                cache[key] = value
            kw["attitude"], kw["gravity"] = cache[key]
        return kw

    def records(self, chunk: int | None = None):
        """Yield consecutive :class:`ImuRecord` chunks of shape (M, k, 3).

        The process states, quantisation remainders and random draws carry
        over from chunk to chunk, so one pass gives one realisation; a
        second pass continues the same processes (make a new simulator, or
        new :class:`~covtool.validation.sensor_errors.SensorErrors`, to start again).
        """
        chunk = self.chunk if chunk is None else int(chunk)
        M = self.n_runs
        qa, qv = self.quantization
        ra, rv = self.saturation
        res_a = np.zeros((M, 3))
        res_v = np.zeros((M, 3))
        for a in range(0, self.n_samples, chunk):
            k = min(chunk, self.n_samples - a)
            ts = self.t0 + a * self.dt
            dth, dv = self._true_increments(ts, k)
            if self.errors is not None:
                e_th, e_v = self.errors.increment_errors(ts, self.dt, dth, dv, **self._context(ts, k))
                dth = dth + e_th
                dv = dv + e_v
            dth = np.broadcast_to(dth, (M, k, 3))
            dv = np.broadcast_to(dv, (M, k, 3))
            if ra is not None:
                dth = np.clip(dth, -ra * self.dt, ra * self.dt)
            if rv is not None:
                dv = np.clip(dv, -rv * self.dt, rv * self.dt)
            if qa is not None:
                dth, res_a = _quantize(dth, qa, res_a)
            if qv is not None:
                dv, res_v = _quantize(dv, qv, res_v)
            yield ImuRecord(ts, self.dt, np.ascontiguousarray(dth), np.ascontiguousarray(dv))

    def fill_cache(self, chunk: int | None = None) -> None:
        """Sample into ``truth_cache`` what a pass of :meth:`records` samples from the trajectory.

        The exact increments and the errors' context (reference attitude,
        gravity, speed) of every record, made by the very calls of
        :meth:`records`, without injecting errors: errors with an
        ``advance(t0, h, k, **context)`` method advance their processes
        instead (the speed they look up; noise-free errors draw nothing).
        A study fills the cache once and hands it to the simulators of its
        chunks of runs.
        """
        if self.truth_cache is None:
            raise ValueError("fill_cache needs a truth_cache")
        chunk = self.chunk if chunk is None else int(chunk)
        advance = getattr(self.errors, "advance", None)
        for a in range(0, self.n_samples, chunk):
            k = min(chunk, self.n_samples - a)
            ts = self.t0 + a * self.dt
            self._true_increments(ts, k)
            kw = self._context(ts, k)
            if advance is not None:
                advance(ts, self.dt, k, **kw)

    def record(self) -> ImuRecord:
        """The whole span as one record (M, K, 3) (memory permitting)."""
        recs = list(self.records())
        return ImuRecord(self.t0, self.dt, np.concatenate([r.dtheta for r in recs], axis=-2),
                         np.concatenate([r.dv for r in recs], axis=-2))


def _quantize(x, lsb, residual):
    """Pulse-count quantisation with the remainder carried, (M, k, 3).

    With ``c_k = r + Σ_{i≤k} x_i`` (r the carried remainder) the output is
    ``q_k − q_{k−1}``, ``q_k = round(c_k / lsb) lsb`` (half to even,
    ``q_{−1} = 0``), and the new remainder ``c_K − q_K``.  Compiled
    (:func:`_quantize_loop`; issue 13): the numpy form made four
    (M, k, 3) temporaries per chunk.
    """
    x = np.require(x, dtype=float, requirements=["C", "W"])
    out = np.empty_like(x)
    new = np.empty((x.shape[0], x.shape[2]))
    _quantize_loop(x, float(lsb), np.require(residual, dtype=float, requirements=["C", "W"]), out, new)
    return out, new


@numba.njit(cache=True, nogil=True)
def _quantize_loop(x, lsb, residual, out, new):
    M, K, C = x.shape
    for m in range(M):
        for i in range(C):
            cs = 0.0
            prev = 0.0
            c = residual[m, i]
            q = 0.0
            for k in range(K):
                cs = x[m, 0, i] if k == 0 else cs + x[m, k, i]      # the running sum, as np.cumsum adds
                c = residual[m, i] + cs
                q = np.rint(c / lsb) * lsb
                out[m, k, i] = q - prev
                prev = q
            new[m, i] = c - q
