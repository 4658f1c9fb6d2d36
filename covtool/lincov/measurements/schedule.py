"""When a measurement is processed: periodic, at stops, while moving or stationary, with outages."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: conditions a schedule may put on the vehicle's motion
WHEN = ("always", "moving", "stationary")


@dataclass(frozen=True)
class Schedule:
    """Update times of one measurement on a study grid.

    Attributes
    ----------
    period : float
        Time between updates. [s]
    start : float
        First candidate update. [s]
    end : float or None
        Last candidate update (None: the end of the study). [s]
    when : {"always", "moving", "stationary"}
        Keep the candidates where the vehicle moves / stands
        (``"stationary"`` is also a check: ZUPT and CUPT at a stop).
    outages : tuple of (float, float)
        Closed windows without updates (a GNSS outage). [s]
    at : tuple of float
        Explicit update times (survey points) instead of the periodic ones. [s]
    """

    period: float = 1.0
    start: float = 0.0
    end: float | None = None
    when: str = "always"
    outages: tuple = ()
    at: tuple = ()

    def times(self, duration: float) -> np.ndarray:
        """Candidate update times before the motion filter and outages. [s]"""
        if self.at:
            return np.asarray(self.at, float)
        end = duration if self.end is None else self.end
        n = int(np.floor((end - self.start) / self.period + 1e-9))
        return self.start + self.period * np.arange(n + 1)

    def problem(self, t: np.ndarray, traj) -> str | None:
        """Why this schedule cannot run on grid ``t`` and trajectory ``traj`` (None if it can).

        The checks run before any computation: every window inside the
        study, candidate times on the grid, and a ``"stationary"`` schedule
        only at stops (the message names the time).
        """
        dur = float(t[-1])
        for key, val in (("start", self.start), ("end", self.end)):
            if val is not None and not (-1e-9 <= val <= dur + 1e-9):
                return f"{key} {val:g} s is outside the study [0, {dur:g}] s"
        if self.end is not None and self.end < self.start:
            return f"end {self.end:g} s is before start {self.start:g} s"
        for a, b in self.outages:
            if not (-1e-9 <= a < b <= dur + 1e-9):
                return f"outage [{a:g}, {b:g}] s is not a window inside the study [0, {dur:g}] s"
        times = self.times(dur)
        if times.size == 0:
            return "no update time"
        out = times[(times < -1e-9) | (times > dur + 1e-9)]
        if out.size:
            return f"update time {out[0]:g} s is outside the study [0, {dur:g}] s"
        dt = t[1] - t[0]
        idx = np.round(times / dt).astype(int)
        off = np.abs(idx * dt - times) > 1e-6 * dt
        if np.any(off):
            return f"update time {times[off][0]:g} s is not on the {dt:g} s grid"
        if self.when == "stationary":
            stat = traj.stationary_mask(times)
            if not np.all(stat):
                return f"update at t = {times[~stat][0]:g} s is not at a stop of the trajectory"
        return None

    def steps(self, t: np.ndarray, traj) -> np.ndarray:
        """Grid indices of the updates, shape (k,).

        Raises
        ------
        ValueError
            :meth:`problem` is not None.
        """
        p = self.problem(t, traj)
        if p is not None:
            raise ValueError(p)
        times = self.times(float(t[-1]))
        keep = np.ones(times.size, bool)
        if self.when == "moving":
            keep &= ~traj.stationary_mask(times)
        for a, b in self.outages:
            keep &= ~((times >= a - 1e-9) & (times <= b + 1e-9))
        return np.round(times[keep] / (t[1] - t[0])).astype(int)
