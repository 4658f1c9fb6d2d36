"""Telemetry gaps of IMU logs: found, bridged by a declared policy, and what each bridge costs."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from covtool.errors import InputError

__all__ = [
    "GAP_POLICIES", "GapReport", "BridgedLog", "find_gaps", "bridge_gaps", "clock_rate",
]


#: gap bridging policies
GAP_POLICIES = ("hold", "interpolate", "propagate", "refuse")


# --------------------------------------------------------------------------
# telemetry gaps
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class GapReport:
    """One bridged gap.

    Attributes
    ----------
    imu : str
    after : float
        Time of the last sample before the gap. [s]
    before : float
        Time of the first sample after the gap. [s]
    samples : int
        Samples bridged.
    policy : str
    sigma_attitude : ndarray, shape (3,)
        Predicted extra error of the summed angle increments per sensor
        axis (1σ). [rad]
    sigma_velocity : ndarray, shape (3,)
        Predicted extra error of the summed velocity increments (1σ). [m/s]
    trials : int
        Trial bridges the prediction rests on (0: the lost white noise
        only).
    """

    imu: str
    after: float
    before: float
    samples: int
    policy: str
    sigma_attitude: np.ndarray
    sigma_velocity: np.ndarray
    trials: int = 0


@dataclass
class BridgedLog:
    """An IMU log after gap bridging.

    Attributes
    ----------
    t : ndarray, shape (K,)
        Sample end times: the recorded times of the kept samples, exactly;
        bridged samples evenly between their recorded neighbours. [s]
    dtheta, dv : ndarray, shape (K, 3) or (M, K, 3)
    dt : float
        Nominal sample period (the grade's). [s]
    gaps : list of GapReport
    bridged : ndarray of bool, shape (K,)
        True for the samples the policy filled in.
    where : str
        The log (its file) named in every message.
    period : float or None
        Sample period measured from the recorded times
        (:func:`clock_rate`). [s]
    """

    t: np.ndarray
    dtheta: np.ndarray
    dv: np.ndarray
    dt: float
    gaps: list = field(default_factory=list)
    bridged: np.ndarray | None = None
    where: str = ""
    period: float | None = None

    @property
    def clock_ppm(self) -> float:
        """Measured period's offset from the nominal one. [ppm]"""
        period = self.period if self.period is not None else clock_rate(self.t, self.dt)[0]
        return (period / self.dt - 1.0) * 1e6


#: resolution of :func:`clock_rate` on recorded times exact to 17 digits [ppm]
CLOCK_PPM_TOL = 0.1


def clock_rate(t, dt: float) -> tuple[float, float]:
    """Sample period of a log measured from its recorded times.

    Parameters
    ----------
    t : array_like, shape (K,)
        Recorded sample end times, strictly increasing, possibly with
        missing samples. [s]
    dt : float
        Nominal sample period. [s]

    Returns
    -------
    period : float
        Least-squares slope of ``t`` against the sample number (missing
        samples counted from the median step). [s]
    ppm : float
        ``(period / dt − 1) · 10⁶``: how far the log's clock runs from its
        nominal rate. [ppm]
    """
    t = np.asarray(t, float)
    if t.size < 2:
        return float(dt), 0.0
    step = np.diff(t)
    n = np.concatenate([[0.0], np.cumsum(np.maximum(np.rint(step / np.median(step)), 1.0))])
    tc = t - t[0]
    nc = n - n.mean()
    period = float(nc @ (tc - tc.mean()) / (nc @ nc))
    return period, (period / dt - 1.0) * 1e6


def find_gaps(t, dt: float, where: str = "IMU log"):
    """Locate missing samples on a nominal sample grid.

    Parameters
    ----------
    t : array_like, shape (K,)
        Sample end times, strictly increasing. [s]
    dt : float
        Nominal sample period. [s]
    where : str
        Names the log in error messages.

    Returns
    -------
    list of (int, int)
        ``(k, n)``: ``n`` samples are missing between samples ``k`` and
        ``k + 1``.

    Raises
    ------
    InputError
        A step that is not a whole number of periods (within 10 %): the log
        is not on one sample grid, so no gap can be bridged reliably.
    """
    t = np.asarray(t, float)
    steps = np.diff(t) / dt
    whole = np.rint(steps)
    bad = (np.abs(steps - whole) > 0.1) | (whole < 1)
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(f"{where}: column 't [s]'", f"row {k + 2}: step {t[k + 1] - t[k]:.9g} s after "
                         f"t = {t[k]:.9g} s is not a whole number of sample periods ({dt:.9g} s); "
                         "the log is not on one sample grid")
    return [(int(k), int(whole[k]) - 1) for k in np.flatnonzero(whole > 1)]


def _fill(prev, nxt, n: int, policy: str):
    """Increments for ``n`` missing samples from the samples around them.

    ``prev`` (…, w, 3) are the valid samples just before the gap, ``nxt``
    (…, w, 3) those just after (w ≥ 1, oldest first).
    """
    w = prev.shape[-2]
    if policy == "hold":
        return np.repeat(prev[..., -1:, :], n, axis=-2)
    a = prev.mean(axis=-2)
    if policy == "propagate":
        return np.repeat(a[..., None, :], n, axis=-2)
    # interpolate: a straight line through the window means at their mid-times
    b = nxt.mean(axis=-2)
    ta, tb = -(w + 1) / 2.0, n + (w - 1) / 2.0
    u = (np.arange(n) - ta) / (tb - ta)
    return a[..., None, :] + u[:, None] * (b - a)[..., None, :]


def _trial_errors(x, stretches, n, policy, w, max_trials):
    """Errors of the summed increments of trial bridges in valid data."""
    errs = []
    for s0, s1 in stretches:                  # valid samples s0 … s1 (inclusive), no gap inside
        first, last = s0 + w - 1, s1 - n - w  # the trial gap covers a+1 … a+n
        if last < first:
            continue
        for a in np.linspace(first, last, min(max_trials, last - first + 1)).astype(int):
            fill = _fill(x[..., a + 1 - w:a + 1, :], x[..., a + n + 1:a + n + 1 + w, :], n, policy)
            errs.append((fill.sum(axis=-2) - x[..., a + 1:a + n + 1, :].sum(axis=-2)).reshape(-1, 3))
    return np.concatenate(errs) if errs else np.zeros((0, 3))


def bridge_gaps(t, dtheta, dv, dt: float, policy: str, *, arw: float = 0.0, vrw: float = 0.0,
                imu: str = "IMU", window: int = 10, trials: int = 8, where: str = "IMU log") -> BridgedLog:
    """Bridge missing samples of an IMU log by a declared policy.

    Parameters
    ----------
    t : array_like, shape (K,)
        Sample end times. [s]
    dtheta, dv : array_like, shape (K, 3) or (M, K, 3)
        Increments. [rad], [m/s]
    dt : float
        Nominal sample period. [s]
    policy : {"hold", "interpolate", "propagate", "refuse"}
        ``hold``: repeat the last sample; ``propagate``: the mean increment
        of the ``window`` samples before the gap; ``interpolate``: a
        straight line between the means of the ``window`` samples on either
        side; ``refuse``: raise.
    arw, vrw : float
        Root-PSDs of the IMU's white noises: the noise the missing samples
        carried is lost, at least ``σ² = arw² T_gap``. [rad/√s], [m/s/√s]
    imu : str
        Name in the report.
    window : int
        Samples averaged by ``propagate`` and ``interpolate``.
    trials : int
        Trial bridges on each side of a gap for the error prediction.
    where : str
        Names the log in error messages (and in :attr:`BridgedLog.where`).

    Returns
    -------
    BridgedLog
        Kept samples keep their recorded times exactly; the ``n`` samples
        inserted in a gap get times evenly between the recorded
        neighbours.  Gaps are counted in the log's own median step, and the
        measured period (:func:`clock_rate`) is kept.  Every bridged gap is
        reported (:class:`GapReport`) with its predicted extra error: the
        RMS error of the summed increments of the same policy applied to
        trial gaps of the same length in the valid data on each side (up to
        ``trials`` per side, all runs pooled; the larger side), and never
        less than the lost white noise.

    Raises
    ------
    InputError
        Unknown policy, a gap with ``policy = "refuse"``, too few valid
        samples around a gap to bridge it, or a log not on one grid.
    """
    if policy not in GAP_POLICIES:
        raise InputError(f"{where}: gap policy", f"{policy!r} is not one of {', '.join(GAP_POLICIES)}")
    t = np.asarray(t, float)
    dtheta = np.asarray(dtheta, float)
    dv = np.asarray(dv, float)
    # gaps are counted in the log's own sample period: a clock a few hundred ppm off its nominal rate
    # would otherwise turn a long gap into a non-integer number of periods
    own = float(np.median(np.diff(t))) if t.size > 1 else float(dt)
    gaps = find_gaps(t, own, where)
    period, _ = clock_rate(t, dt)
    if gaps and policy == "refuse":
        k, n = gaps[0]
        raise InputError(f"{where}: column 't [s]'", f"{n} samples missing between t = {t[k]:.9g} s and "
                         f"{t[k + 1]:.9g} s (gap policy 'refuse'); {len(gaps)} gap(s) in all")
    if not gaps:
        return BridgedLog(t, dtheta, dv, dt, [], np.zeros(t.size, bool), where, period)
    w = max(1, int(window)) if policy != "hold" else 1
    bounds = [-1] + [k for k, _ in gaps] + [t.size - 1]
    stretches = [(bounds[i] + 1, bounds[i + 1]) for i in range(len(bounds) - 1)]
    pieces_t, pieces_th, pieces_v, flags, reports = [], [], [], [], []
    start = 0
    for g, (k, n) in enumerate(gaps):
        s_before, s_after = stretches[g], stretches[g + 1]
        if k - s_before[0] + 1 < w or s_after[1] - (k + 1) + 1 < w:
            raise InputError(f"{where}: column 't [s]'", f"gap of {n} samples after t = {t[k]:.9g} s: fewer than "
                             f"{w} valid samples on each side to bridge it with policy {policy!r}")
        pieces_t.append(t[start:k + 1])
        pieces_th.append(dtheta[..., start:k + 1, :])
        pieces_v.append(dv[..., start:k + 1, :])
        flags.append(np.zeros(k + 1 - start, bool))
        # kept samples keep their recorded times; only the inserted ones are placed, evenly between the
        # recorded neighbours (the log's own clock, whatever its rate)
        pieces_t.append(t[k] + (t[k + 1] - t[k]) * np.arange(1, n + 1) / (n + 1))
        prev = slice(k + 1 - w, k + 1)
        nxt = slice(k + 1, k + 1 + w)
        pieces_th.append(_fill(dtheta[..., prev, :], dtheta[..., nxt, :], n, policy))
        pieces_v.append(_fill(dv[..., prev, :], dv[..., nxt, :], n, policy))
        flags.append(np.ones(n, bool))
        T = n * dt
        var_att, var_vel, count = np.full(3, arw**2 * T), np.full(3, vrw**2 * T), 0
        for side in (s_before, s_after):
            # the larger side's mean square: the dynamics may change at the gap
            e_th = _trial_errors(dtheta, [side], n, policy, w, trials)
            e_v = _trial_errors(dv, [side], n, policy, w, trials)
            if len(e_th):
                var_att = np.maximum(var_att, np.mean(e_th**2, axis=0))
                var_vel = np.maximum(var_vel, np.mean(e_v**2, axis=0))
                count += len(e_th)
        reports.append(GapReport(imu, float(t[k]), float(t[k + 1]), n, policy, np.sqrt(var_att), np.sqrt(var_vel),
                                 count))
        start = k + 1
    pieces_t.append(t[start:])
    pieces_th.append(dtheta[..., start:, :])
    pieces_v.append(dv[..., start:, :])
    flags.append(np.zeros(t.size - start, bool))
    return BridgedLog(np.concatenate(pieces_t), np.concatenate(pieces_th, axis=-2), np.concatenate(pieces_v, axis=-2),
                      dt, reports, np.concatenate(flags), where, period)
