"""Whole records: grouping IMU samples and running the strapdown.

:class:`NavHistory` (M runs at S output times), :func:`group_samples` and
:func:`iter_intervals` (samples of each main interval, seed 001 §2.3,
Figs 7–10) and :func:`run`, the compiled strapdown over a whole record.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from covtool.nav.coning import _weights, body_increments, body_position_increment, MAX_SAMPLES
from covtool.nav.strapdown.mechanization import _rotvec_quat
from covtool.nav.strapdown.state import NavState, _pack, _unpack, nav_errors, truth_state


# --------------------------------------------------------------------------
# whole records
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class NavHistory:
    """Navigation solution of M runs at S output times.

    Attributes
    ----------
    t : ndarray, shape (S,)
        Output times. [s]
    lat, lon, h : ndarray, shape (S, M)
        [rad], [rad], [m]
    v_n : ndarray, shape (S, M, 3)
        [m/s]
    q : ndarray, shape (S, M, 4)
        Attitude quaternion body→NED.
    """

    t: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    q: np.ndarray

    def state(self, i: int) -> NavState:
        """The state at output index ``i`` (previous samples zero)."""
        M = self.lat.shape[1]
        return NavState(float(self.t[i]), self.lat[i], self.lon[i], self.h[i], self.v_n[i], self.q[i],
                        np.zeros((M, 3)), np.zeros((M, 3)))

    def errors(self, truth) -> np.ndarray:
        """Errors (computed − true) at every output time, shape (S, M, 10).

        Parameters
        ----------
        truth : Trajectory or object with ``truth(t) -> NavState``
            A :class:`covtool.nav.trajectory.core.Trajectory` (body frame) or an
            IMU simulator (its own frame: mounting and vibration included).
        """
        if hasattr(truth, "truth"):
            tr = truth.truth(self.t)
        else:
            tr = truth_state(truth, self.t)
        out = np.empty(self.lat.shape + (10,))
        M = self.lat.shape[1]
        for i in range(self.t.size):
            if tr.lat.ndim == 2:  # per-run truth
                ti = NavState(float(self.t[i]), tr.lat[i], tr.lon[i], tr.h[i], tr.v_n[i], tr.q[i],
                              np.zeros((M, 3)), np.zeros((M, 3)))
            else:
                ti = NavState(float(self.t[i]), tr.lat[i:i + 1], tr.lon[i:i + 1], tr.h[i:i + 1],
                              tr.v_n[i:i + 1], tr.q[i:i + 1], np.zeros((1, 3)), np.zeros((1, 3)))
            out[i] = nav_errors(self.state(i), ti)
        return out


def group_samples(t_samples, t_main, where: str = "IMU") -> np.ndarray:
    """Assign IMU samples to main navigation intervals.

    Parameters
    ----------
    t_samples : array_like, shape (K,)
        End time of each IMU sample period, increasing. [s]
    t_main : array_like, shape (S+1,)
        Main interval boundaries ``t_0 < t_1 < … < t_S``. [s]
    where : str
        Name used in error messages.

    Returns
    -------
    ndarray of int, shape (S, n)
        Sample indices of each interval, oldest first.

    Raises
    ------
    ValueError
        If the intervals do not all hold the same number of samples (a gap,
        a duplicate or a rate that is not an integer multiple), naming the
        first offending interval; samples outside ``(t_0, t_S]`` are refused
        too.  Nothing is dropped silently.

    Notes
    -----
    A sample belongs to interval m if its period ends in ``(t_{m−1}, t_m]``
    (with a tolerance of 1e-6 of the sample period), which is how seed 001
    synchronises the KIMU to the main IMU (Fig 7).
    """
    ts = np.asarray(t_samples, dtype=float)
    tm = np.asarray(t_main, dtype=float)
    if ts.ndim != 1 or tm.ndim != 1 or tm.size < 2:
        raise ValueError(f"{where}: sample times and interval boundaries must be 1-D (at least 2 boundaries)")
    tol = 1e-6 * (np.min(np.diff(ts)) if ts.size > 1 else np.min(np.diff(tm)))
    idx = np.searchsorted(tm, ts - tol, side="left")
    out_of = (idx < 1) | (idx > tm.size - 1)
    if out_of.any():
        k = int(np.argmax(out_of))
        raise ValueError(f"{where}: sample {k} (t = {ts[k]:.9g} s) lies outside the main intervals "
                         f"({tm[0]:.9g}, {tm[-1]:.9g}] s")
    counts = np.bincount(idx - 1, minlength=tm.size - 1)
    n = counts[0]
    bad = counts != n
    if bad.any() or n == 0:
        m = int(np.argmax(bad)) if bad.any() else 0
        raise ValueError(f"{where}: main interval {m} ({tm[m]:.9g}, {tm[m + 1]:.9g}] s holds {counts[m]} "
                         f"samples, expected {n or 'at least 1'} (gap, duplicate or non-integer rate ratio)")
    order = np.argsort(idx, kind="stable")
    return order.reshape(tm.size - 1, n)


def iter_intervals(imu, samples_per_step: int):
    """Navigation intervals of an IMU record, for :func:`step`.

    Parameters
    ----------
    imu : ImuRecord, ImuSimulator or iterable of ImuRecord
        As for :func:`run`.
    samples_per_step : int
        Samples per interval n.

    Yields
    ------
    dtheta, dv : ndarray, shape (n, 3) or (M, n, 3)
        The interval's samples.
    dt : float
        Interval length. [s]

    Examples
    --------
    A filter with feedback (seed 002, eq (10))::

        for dth, dv, T in iter_intervals(sim, 4):
            state = step(state, dth, dv, T)
            if zupt_now(state.t):
                state = correct(state, dx_hat)
    """
    n = int(samples_per_step)
    records = [imu] if hasattr(imu, "dtheta") else (imu.records() if hasattr(imu, "records") else imu)
    for rec in records:
        K = rec.dtheta.shape[-2]
        if K % n:
            raise ValueError(f"an IMU record of {K} samples is not a multiple of {n} samples per step")
        for j in range(K // n):
            yield rec.dtheta[..., j * n:(j + 1) * n, :], rec.dv[..., j * n:(j + 1) * n, :], n * rec.dt


def run(state: NavState, imu, samples_per_step: int, *, every: int = 1,
        callback: Callable | None = None, rows=None) -> NavHistory:
    """Run the strapdown algorithm over a whole IMU record.

    Parameters
    ----------
    state : NavState
        Initial state (M runs) at the start of the record.
    imu : ImuRecord, ImuSimulator or iterable of ImuRecord
        Increments (:class:`covtool.nav.imu.simulator.ImuRecord`: ``t0``, sample period
        ``dt``, ``dtheta`` and ``dv`` of shape (K, 3) or (M, K, 3)); a
        simulator or an iterable yields consecutive records (chunks).
    samples_per_step : int
        IMU samples per navigation interval n (each record's K must be a
        multiple of n).
    every : int
        Keep every ``every``-th navigation step in the history (the initial
        and the final state are always kept).
    callback : callable, optional
        ``callback(state) -> NavState or None`` after every step, e.g. to
        apply filter feedback with :func:`correct`; a returned state
        replaces the current one.
    rows : array_like of int, shape (M,), optional
        The record row that drives each run, when runs share rows (e.g. the
        cases of an ensemble that see the same increments): run ``i`` is
        driven by ``dtheta[rows[i]]``, ``dv[rows[i]]``.  Default: run ``i``
        by row ``i`` (every run by the one row of a one-row record).  Not
        with ``callback``.

    Returns
    -------
    NavHistory
    """
    n = int(samples_per_step)
    if not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"samples_per_step must be in 1..{MAX_SAMPLES}, got {samples_per_step!r}")
    if every < 1:
        raise ValueError(f"every must be a positive integer, got {every!r}")
    records: Iterable = [imu] if hasattr(imu, "dtheta") else (imu.records() if hasattr(imu, "records") else imu)
    from covtool.nav.strapdown.kernels import _nav_loop, _strapdown_loop   # numba, imported when a record runs

    M = state.n_runs
    if rows is not None:
        if callback is not None:
            raise ValueError("rows cannot be combined with a callback")
        rows = np.asarray(rows, dtype=np.int64)
        if rows.shape != (M,):
            raise ValueError(f"rows must have shape ({M},), got {rows.shape}")
    # kept states as blocks (t (S_i,), lat, lon, h (S_i, M), v_n (S_i, M, 3), q (S_i, M, 4)), joined at the end
    keep = [_block(state)]
    k = 0
    last_kept = 0
    for rec in records:
        K = rec.dtheta.shape[-2]
        if K % n:
            raise ValueError(f"an IMU record of {K} samples is not a multiple of {n} samples per step")
        T = n * rec.dt
        if abs(rec.t0 - state.t) > 1e-6 * rec.dt:
            raise ValueError(f"IMU record starts at {rec.t0:.9g} s but the state is at {state.t:.9g} s")
        if rows is not None:
            Rb = 1 if rec.dtheta.ndim == 2 else rec.dtheta.shape[0]
            if rows.size and (rows.min() < 0 or rows.max() >= Rb):
                raise ValueError(f"rows index record rows 0..{rows.max()}, the record has {Rb}")
        elif rec.dtheta.ndim == 3 and rec.dtheta.shape[0] not in (1, M):
            raise ValueError(f"IMU record has {rec.dtheta.shape[0]} runs, the state has {M}")
        S = K // n
        xa = np.array(_unpack(state), dtype=float)                              # (10, M)
        t0 = state.t
        if callback is None:
            # the record's rows as they are, each run reading its own row
            src_th = rec.dtheta if rec.dtheta.ndim == 3 else rec.dtheta[None]
            src_dv = rec.dv if rec.dv.ndim == 3 else rec.dv[None]
            run_rows = rows if rows is not None else (np.zeros(M, np.int64) if src_th.shape[0] == 1
                                                      else np.arange(M, dtype=np.int64))
            # all steps of the record in the compiled kernel; the kept ones written out
            js = np.flatnonzero((k + np.arange(1, S + 1)) % every == 0)
            out = np.empty((10, M, js.size))
            pth = np.array(np.broadcast_to(state.dtheta_prev, (M, 3)), dtype=float)
            pdv = np.array(np.broadcast_to(state.dv_prev, (M, 3)), dtype=float)
            # views of the record as they are (the kernel takes any strides): no copy of the increments
            _strapdown_loop(xa, np.asarray(src_th, dtype=float), np.asarray(src_dv, dtype=float), run_rows,
                            pth, pdv, n, _weights(n), T, every, k, out)
            if js.size:
                # the kept states in one block (S_kept, M, ·), not one NavState each
                keep.append((t0 + (js + 1) * T, out[0].T, out[1].T, out[2].T,
                             np.transpose(out[3:6], (2, 1, 0)), np.transpose(out[6:10], (2, 1, 0))))
            if js.size:
                last_kept = k + int(js[-1]) + 1
            k += S
            state = _pack(t0 + S * T, tuple(xa), pth, pdv)
            continue
        # with a callback the state may change between steps: one step per kernel call;
        # shared increments (no run axis) are compensated once for all runs
        shared = ((rec.dtheta.ndim == 2 or rec.dtheta.shape[0] == 1)
                  and np.all(state.dtheta_prev == state.dtheta_prev[:1])
                  and np.all(state.dv_prev == state.dv_prev[:1]))
        Mr = 1 if shared else M
        dth = np.broadcast_to(rec.dtheta, (Mr, K, 3)).reshape(Mr, S, n, 3)
        dvv = np.broadcast_to(rec.dv, (Mr, K, 3)).reshape(Mr, S, n, 3)
        prev_th = np.concatenate([state.dtheta_prev[:Mr, None], dth[:, :-1, -1]], axis=1)
        prev_dv = np.concatenate([state.dv_prev[:Mr, None], dvv[:, :-1, -1]], axis=1)
        phi, dv_b = body_increments(dth, dvv, prev_th, prev_dv)
        qb = np.ascontiguousarray(np.moveaxis(_rotvec_quat(phi), -1, 0))      # (4, Mr, S)
        ub = np.ascontiguousarray(np.moveaxis(dv_b, -1, 0))                   # (3, Mr, S)
        rb = np.ascontiguousarray(np.moveaxis(body_position_increment(dth, dvv), -1, 0))

        def prev(j):
            return (np.broadcast_to(dth[:, j, -1], (M, 3)).copy(), np.broadcast_to(dvv[:, j, -1], (M, 3)).copy())

        one = np.empty((10, M, 1))
        for j in range(S):
            _nav_loop(xa, qb[:, :, j:j + 1], ub[:, :, j:j + 1], rb[:, :, j:j + 1], T, 1, 0, one)
            k += 1
            state = _pack(t0 + (j + 1) * T, tuple(xa.copy()), *prev(j))
            new = callback(state)
            if new is not None:
                state = new
                xa = np.array(_unpack(state), dtype=float)
            if k % every == 0:
                keep.append(_block(state))
                last_kept = k
    if last_kept != k:
        keep.append(_block(state))
    t, lat, lon, h, v_n, q = (np.concatenate(part) for part in zip(*keep))
    return NavHistory(t=t, lat=lat, lon=lon, h=h, v_n=v_n, q=q)


def _block(state: NavState):
    """One state as a block of kept states of :func:`run` (leading length 1)."""
    return (np.array([state.t], dtype=float), np.asarray(state.lat)[None], np.asarray(state.lon)[None],
            np.asarray(state.h)[None], np.asarray(state.v_n)[None], np.asarray(state.q)[None])
