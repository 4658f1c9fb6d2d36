"""The trajectory object and its inverse mechanization.

A :class:`Trajectory` is the true motion of the vehicle about which the error
model is linearised: geodetic position, NED velocity, attitude quaternion and
the ideal IMU outputs (specific force ``f_b`` and inertial body rate
``w_ib_b``) that make the navigation equations reproduce that motion exactly.
It is built by the segment profiles (:mod:`covtool.nav.trajectory.segments`),
the built-in profiles (:mod:`covtool.nav.trajectory.profiles`), the flight
profiles (:mod:`covtool.nav.trajectory.flight`) or read from a CSV file
(:mod:`covtool.io.trajectory_csv`, interpolated by :class:`Interpolant`).

Inverse mechanization: the unperturbed velocity equation (seed 002, eq (4);
Titterton & Weston §3.7) and the attitude-rate relation behind seed 002,
eq (1), solved for the sensor outputs::

    f^n     = v̇^n + (2 ω_ie^n + ω_en^n) × v^n − g^n
    f^b     = C_n^b f^n
    ω_ib^b  = ω_nb^b + C_n^b (ω_ie^n + ω_en^n)

with ``ω_nb^b = [φ̇ − ψ̇ sin θ, θ̇ cos φ + ψ̇ sin φ cos θ, −θ̇ sin φ + ψ̇ cos φ cos θ]``
from the 3-2-1 Euler-angle rates.

The quaternion is kept *continuous* in time (the heading is not wrapped), so
its sign may be negative; ``q`` and ``−q`` are the same attitude but the
additive quaternion error of seed 002, eq (1) needs a continuous reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from covtool.errors import TrajectoryError
from covtool.nav import attitude as quat, earth

__all__ = [
    "Trajectory", "inverse_mechanization", "CSV_COLUMNS", "CSV_OPTIONAL_COLUMNS", "wrap_longitude",
]


#: required CSV columns, in file order (units in brackets)
CSV_COLUMNS = (
    "t [s]", "lat [deg]", "lon [deg]", "h [m]",
    "v_N [m/s]", "v_E [m/s]", "v_D [m/s]",
    "q0", "q1", "q2", "q3",
    "f_x [m/s^2]", "f_y [m/s^2]", "f_z [m/s^2]",
    "w_x [rad/s]", "w_y [rad/s]", "w_z [rad/s]",
)
#: optional CSV columns: odometer distance, and 0/1 stationary flag
CSV_OPTIONAL_COLUMNS = ("distance [m]", "stationary")


# --------------------------------------------------------------------------
# data object
# --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Trajectory:
    """True vehicle motion and ideal IMU outputs on a time grid.

    Parameters
    ----------
    t : ndarray, shape (n,)
        Time, strictly increasing. [s]
    lat, lon : ndarray, shape (n,)
        Geodetic latitude and longitude. [rad]
    h : ndarray, shape (n,)
        Height above the WGS-84 ellipsoid. [m]
    v_n : ndarray, shape (n, 3)
        NED velocity. [m/s]
    q_nb : ndarray, shape (n, 4)
        Unit quaternion body→NED, scalar first (``C_b^n = dcm(q_nb)``),
        continuous in time.
    f_b : ndarray, shape (n, 3)
        Specific force in body axes. [m/s^2]
    w_ib_b : ndarray, shape (n, 3)
        Body rate with respect to inertial space, body axes. [rad/s]
    distance : ndarray, shape (n,)
        Cumulative distance travelled along the path (odometer). [m]
    stationary : tuple of (float, float)
        Closed intervals ``[t0, t1]`` in which the vehicle is at rest. [s]
    name : str
        Label used in reports.
    """

    t: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    q_nb: np.ndarray
    f_b: np.ndarray
    w_ib_b: np.ndarray
    distance: np.ndarray
    stationary: tuple = ()
    name: str = ""
    _source: object = field(default=None, repr=False)

    def __post_init__(self):
        t = np.atleast_1d(np.array(self.t, dtype=float))
        n = t.size
        if t.ndim != 1 or n == 0:
            raise TrajectoryError("Trajectory", "t must be a non-empty 1-D array")
        if n > 1 and not np.all(np.diff(t) > 0):
            raise TrajectoryError("Trajectory", "t must be strictly increasing")
        shapes = {"lat": (n,), "lon": (n,), "h": (n,), "v_n": (n, 3), "q_nb": (n, 4),
                  "f_b": (n, 3), "w_ib_b": (n, 3), "distance": (n,)}
        object.__setattr__(self, "t", _frozen(t))
        for key, shape in shapes.items():
            a = np.array(getattr(self, key), dtype=float)
            if a.shape != shape:
                raise TrajectoryError("Trajectory", f"{key} has shape {a.shape}, expected {shape}")
            object.__setattr__(self, key, _frozen(a))
        intervals = []
        for iv in self.stationary:
            a, b = (float(x) for x in iv)
            if not a <= b:
                raise TrajectoryError("Trajectory", f"stationary interval {iv!r} has t0 > t1")
            intervals.append((a, b))
        object.__setattr__(self, "stationary", tuple(intervals))

    @property
    def n(self) -> int:
        """Number of samples."""
        return self.t.size

    @property
    def duration(self) -> float:
        """Time span ``t[-1] − t[0]``. [s]"""
        return float(self.t[-1] - self.t[0])

    def euler(self) -> np.ndarray:
        """Roll, pitch and yaw, shape (n, 3). [rad]"""
        return quat.to_euler(self.q_nb)

    def stationary_mask(self, t) -> np.ndarray:
        """True where ``t`` lies in a stationary interval.

        Parameters
        ----------
        t : array_like
            Times. [s]

        Returns
        -------
        ndarray of bool, same shape as ``t``
            Interval ends count as stationary (within 1e-9 s).
        """
        t = np.asarray(t, dtype=float)
        mask = np.zeros(t.shape, dtype=bool)
        for a, b in self.stationary:
            mask |= (t >= a - 1e-9) & (t <= b + 1e-9)
        return mask

    def sample(self, t) -> "Trajectory":
        """State at arbitrary (strictly increasing) times.

        Parameters
        ----------
        t : float or array_like, shape (m,)
            Times within the span of the generating profile or file. [s]

        Returns
        -------
        Trajectory
            The state at ``t``.  A declared profile is evaluated exactly
            from its kinematics; a CSV trajectory is interpolated (linear,
            slerp for the quaternion).  Stationary intervals are clipped to
            the new span.

        Raises
        ------
        TrajectoryError
            ``t`` is outside the span or not strictly increasing.
        """
        src = self._source if self._source is not None else Interpolant(self)
        t = np.atleast_1d(np.asarray(t, dtype=float))
        where = f"trajectory {self.name!r}" if self.name else "trajectory"
        if t.ndim != 1 or not np.all(np.isfinite(t)):
            raise TrajectoryError(where, "sample times must be a finite 1-D array")
        if t.size > 1 and not np.all(np.diff(t) > 0):
            raise TrajectoryError(where, "sample times must be strictly increasing")
        t0, t1 = src.span
        eps = 1e-9 * max(1.0, abs(t0), abs(t1))
        if t[0] < t0 - eps or t[-1] > t1 + eps:
            raise TrajectoryError(where, f"sample times [{t[0]:g}, {t[-1]:g}] s outside the span "
                                  f"[{t0:g}, {t1:g}] s")
        t = np.clip(t, t0, t1)
        state = src.evaluate(t)
        stat = tuple((max(a, t[0]), min(b, t[-1])) for a, b in self.stationary
                     if max(a, t[0]) <= min(b, t[-1]))
        return Trajectory(t=t, **state, stationary=stat, name=self.name, _source=src)

    def to_dataframe(self):
        """Table of the samples with units in the column names.

        Returns
        -------
        pandas.DataFrame
            Columns :data:`CSV_COLUMNS` followed by ``distance [m]`` and
            ``stationary`` (0/1); longitude wrapped to [−180°, 180°).
        """
        import pandas as pd

        data = np.column_stack([
            self.t, np.degrees(self.lat), np.degrees(wrap_longitude(self.lon)), self.h,
            self.v_n, self.q_nb, self.f_b, self.w_ib_b,
        ])
        df = pd.DataFrame(data, columns=list(CSV_COLUMNS))
        df["distance [m]"] = self.distance
        df["stationary"] = self.stationary_mask(self.t).astype(int)
        return df


def grid_times(t0: float, t1: float, dt: float) -> np.ndarray:
    """Time grid of a generated profile: ``t0, t0 + dt, …``, ending exactly at ``t1``.

    Parameters
    ----------
    t0, t1 : float
        Span of the profile. [s]
    dt : float
        Step. [s]

    Returns
    -------
    ndarray, shape (n,)
        The last step is shorter when ``dt`` does not divide the span (to
        within 1e-9 of it); the last time is ``t1`` exactly.
    """
    n = int(math.floor((t1 - t0) / dt + 1e-9))
    t = t0 + dt * np.arange(n + 1)
    if t1 - t[-1] > 1e-9 * max(1.0, t1):
        t = np.append(t, t1)
    else:
        t[-1] = t1
    return t


def wrap_longitude(lon):
    """Longitude wrapped to [−π, π) for reports and files.

    Parameters
    ----------
    lon : float or array_like
        Longitude, possibly continuous across the antimeridian. [rad]

    Returns
    -------
    ndarray
        The same angle in [−π, π); values already in range are returned
        bit for bit.
    """
    lon = np.asarray(lon, dtype=float)
    inside = (lon >= -np.pi) & (lon < np.pi)
    return np.where(inside, lon, np.mod(lon + np.pi, 2.0 * np.pi) - np.pi)


def unwrap_longitude(lon, lat, h, v_e, t):
    """Longitude made continuous, each step chosen nearest the velocity's.

    A file reports longitude wrapped (179.9999° then −179.9999°); the step
    ``Δl`` between rows is taken as the one of ``Δl + 2πk`` closest to the
    trapezoidal integral of ``l̇ = v_E / ((R_N + h) cos L)``, so interpolation
    never runs the long way round the Earth.  Rows with no wrap are
    returned bit for bit.
    """
    _, rn = earth.radii(lat)
    rate = v_e / ((rn + h) * np.cos(lat))
    predicted = 0.5 * (rate[1:] + rate[:-1]) * np.diff(t)
    turns = np.rint((predicted - np.diff(lon)) / (2.0 * np.pi))
    if not turns.any():
        return lon
    return lon + 2.0 * np.pi * np.concatenate([[0.0], np.cumsum(turns)])


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


# --------------------------------------------------------------------------
# inverse mechanization
# --------------------------------------------------------------------------


def inverse_mechanization(lat, h, v_n, dv_n, q_nb, w_nb_b):
    """Ideal IMU outputs that reproduce a given motion.

    Parameters
    ----------
    lat : array_like, shape (...)
        Geodetic latitude. [rad]
    h : array_like, shape (...)
        Height. [m]
    v_n : array_like, shape (..., 3)
        NED velocity. [m/s]
    dv_n : array_like, shape (..., 3)
        Time derivative of ``v_n`` (in NED components). [m/s^2]
    q_nb : array_like, shape (..., 4)
        Attitude quaternion body→NED.
    w_nb_b : array_like, shape (..., 3)
        Body rate with respect to the NED frame, body axes. [rad/s]

    Returns
    -------
    f_b : ndarray, shape (..., 3)
        Specific force. [m/s^2]
    w_ib_b : ndarray, shape (..., 3)
        Body rate with respect to inertial space. [rad/s]

    Notes
    -----
    The unperturbed velocity equation (seed 002, eq (4); Titterton &
    Weston §3.7) and ``ω_ib^b = ω_nb^b + ω_in^b`` (the rates of seed 002,
    eq (1)) solved for the sensor outputs::

        f^n = v̇^n + (2 ω_ie^n + ω_en^n) × v^n − g^n,   f^b = C_n^b f^n
        ω_ib^b = ω_nb^b + C_n^b (ω_ie^n + ω_en^n)
    """
    v_n = np.asarray(v_n, dtype=float)
    w_ie = earth.earth_rate_n(lat)
    w_en = earth.transport_rate_n(lat, h, v_n)
    f_n = np.asarray(dv_n, float) + np.cross(2.0 * w_ie + w_en, v_n) - earth.gravity_n(lat, h)
    c_bn = quat.dcm(q_nb)
    f_b = np.einsum("...ji,...j->...i", c_bn, f_n)
    w_ib_b = np.asarray(w_nb_b, float) + np.einsum("...ji,...j->...i", c_bn, w_ie + w_en)
    return f_b, w_ib_b


def body_rate_from_euler(roll, pitch, droll, dpitch, dyaw):
    """ω_nb^b from 3-2-1 Euler angles and their rates [rad/s]."""
    sr, cr = np.sin(roll), np.cos(roll)
    sp, cp = np.sin(pitch), np.cos(pitch)
    return np.stack([
        droll - dyaw * sp,
        dpitch * cr + dyaw * sr * cp,
        -dpitch * sr + dyaw * cr * cp,
    ], axis=-1)


def trajectory_fields(traj):
    return dict(t=traj.t, lat=traj.lat, lon=traj.lon, h=traj.h, v_n=traj.v_n, q_nb=traj.q_nb,
                f_b=traj.f_b, w_ib_b=traj.w_ib_b, distance=traj.distance)


# --------------------------------------------------------------------------
# CSV trajectories
# --------------------------------------------------------------------------


class Interpolant:
    """Linear (slerp for attitude) interpolation of sampled data."""

    def __init__(self, traj: Trajectory):
        self.data = trajectory_fields(traj)
        self.span = (float(traj.t[0]), float(traj.t[-1]))

    def evaluate(self, t):
        d = self.data
        tk = d["t"]
        if tk.size == 1:
            return {k: np.repeat(v[:1], t.size, axis=0) for k, v in d.items() if k != "t"}
        i = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, tk.size - 2)
        u = (t - tk[i]) / (tk[i + 1] - tk[i])
        out = {}
        for key in ("lat", "lon", "h", "distance", "v_n", "f_b", "w_ib_b"):
            a, b = d[key][i], d[key][i + 1]
            uu = u if a.ndim == 1 else u[:, None]
            out[key] = a + uu * (b - a)
        q0, q1 = d["q_nb"][i], d["q_nb"][i + 1]
        dq = quat.to_rotvec(quat.mul(quat.conj(q0), q1))
        out["q_nb"] = quat.mul(q0, quat.from_rotvec(u[:, None] * dq))
        return out
