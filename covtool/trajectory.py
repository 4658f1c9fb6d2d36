"""Reference trajectories and their inverse mechanization.

A :class:`Trajectory` is the true motion of the vehicle about which the error
model is linearised: geodetic position, NED velocity, attitude quaternion and
the ideal IMU outputs (specific force ``f_b`` and inertial body rate
``w_ib_b``) that make the navigation equations reproduce that motion exactly.

Trajectories come from three sources:

* a list of *segments* (``stand``, ``accelerate``/``decelerate``, ``cruise``,
  ``turn``, ``grade``) declared with datasheet units in a study file
  (:func:`from_segments`);
* the built-in profiles :func:`land_vehicle` (the ZUPT route standing in for
  seed 002, Fig 3) and :func:`static`;
* a CSV file (:func:`load_trajectory_csv`).

Segment kinematics
------------------
Every segment changes at most one channel among speed ``s``, heading ``ψ``
(yaw; right turn positive) and pitch ``θ``; roll is zero.  Changes use
raised-cosine transitions ``S(u) = (1 − cos πu)/2``:

* speed: a jerk-limited trapezoid of acceleration whose ramps are ``S``;
* heading: the same trapezoid shape for the yaw rate;
* pitch: ``S`` itself (up to the grade angle, hold, back down),

so ``ṡ``, ``ψ̇``, ``θ̇`` and hence ``f_b`` and ``w_ib_b`` are continuous.  The
velocity is ``v^n = s [cos θ cos ψ, cos θ sin ψ, −sin θ]`` and the attitude is
``q = from_euler(0, θ, ψ)``; all are analytic in time.  Position is the only
integrated quantity: :func:`covtool.earth.position_rates` is integrated piece
by piece (pieces end wherever a higher derivative jumps) with DOP853 at
``rtol = 1e-12`` and kept as dense output, so :meth:`Trajectory.sample` of a
declared profile evaluates the generating kinematics, not an interpolation
of the time grid.

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

import inspect
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

from . import earth
from . import quaternion as quat
from .errors import TrajectoryError
from .io.config import check_keys, integer, quantity, resolve_input
from .io.csv_table import read_numeric_csv

__all__ = [
    "Trajectory", "land_vehicle", "static", "from_segments", "trajectory_from_config",
    "load_trajectory_csv", "save_trajectory_csv", "inverse_mechanization",
    "CSV_COLUMNS", "CSV_OPTIONAL_COLUMNS", "SEGMENT_KINDS", "BUILTINS", "wrap_longitude",
    "GAP_FACTOR", "STATIONARY_FLAG_SPEED", "STATIONARY_FLAG_RATE",
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

#: speed below which a CSV sample counts as stationary [m/s]
STATIONARY_SPEED = 1e-3
#: body rate w.r.t. NED below which a CSV sample counts as stationary [rad/s]
STATIONARY_RATE = 1e-6
#: tolerance on |q| - 1 when loading a CSV file [-]
QUATERNION_NORM_TOL = 1e-6
#: a CSV time step longer than this many times the file's median step is a
#: gap (at least one missing sample) and is refused unless declared
GAP_FACTOR = 1.5
#: speed above which a row flagged ``stationary = 1`` is refused [m/s]
STATIONARY_FLAG_SPEED = 0.01
#: body rate w.r.t. NED above which a row flagged ``stationary = 1`` is refused [rad/s]
STATIONARY_FLAG_RATE = 1e-3
#: largest |longitude| accepted in a CSV file [deg]
MAX_CSV_LONGITUDE = 360.0

#: segment kind -> allowed keys
SEGMENT_KINDS = {
    "stand": ("kind", "duration"),
    "accelerate": ("kind", "to_speed", "duration", "acceleration", "transition"),
    "decelerate": ("kind", "to_speed", "duration", "acceleration", "transition"),
    "cruise": ("kind", "duration"),
    "turn": ("kind", "rate", "angle", "duration", "transition"),
    "grade": ("kind", "grade", "angle", "duration", "transition", "level_off"),
}

#: default transition times [s]
_TRANSITION = {"accelerate": 3.0, "decelerate": 3.0, "turn": 3.0, "grade": 5.0}

_ODE_RTOL = 1e-12
# absolute tolerances of the (Δlat [rad], Δlon [rad], Δh [m]) offsets: ~1e-9 m
_ODE_ATOL = (1e-16, 1e-16, 1e-9)


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
        src = self._source if self._source is not None else _Interpolant(self)
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


def _unwrap_longitude(lon, lat, h, v_e, t):
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


def _body_rate_from_euler(roll, pitch, droll, dpitch, dyaw):
    """ω_nb^b from 3-2-1 Euler angles and their rates [rad/s]."""
    sr, cr = np.sin(roll), np.cos(roll)
    sp, cp = np.sin(pitch), np.cos(pitch)
    return np.stack([
        droll - dyaw * sp,
        dpitch * cr + dyaw * sr * cp,
        -dpitch * sr + dyaw * cr * cp,
    ], axis=-1)


# --------------------------------------------------------------------------
# profile pieces
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class _Ramp:
    """Raised-cosine step ``x(τ) = a + (b − a) S(τ/T)`` on [0, T]."""

    a: float
    b: float
    T: float

    def value(self, tau):
        if self.a == self.b:
            return self.a + 0.0 * tau
        return self.a + (self.b - self.a) * 0.5 * (1.0 - np.cos(np.pi * tau / self.T))

    def rate(self, tau):
        if self.a == self.b:
            return 0.0 * tau
        return (self.b - self.a) * 0.5 * np.pi / self.T * np.sin(np.pi * tau / self.T)

    def integral(self, tau):
        """``∫_0^τ x``."""
        base = self.a * tau
        if self.a == self.b:
            return base
        u = tau / self.T
        return base + (self.b - self.a) * self.T * 0.5 * (u - np.sin(np.pi * u) / np.pi)

    def integral2(self, tau):
        """``∫_0^τ ∫_0^σ x``."""
        base = 0.5 * self.a * tau * tau
        if self.a == self.b:
            return base
        u = tau / self.T
        return base + (self.b - self.a) * self.T**2 * 0.5 * (0.5 * u * u + (np.cos(np.pi * u) - 1.0) / np.pi**2)


@dataclass(frozen=True)
class _Piece:
    """A time span on which all channels are C-infinity."""

    t0: float
    T: float
    s0: float          # speed at t0 [m/s]
    accel: _Ramp       # ds/dt [m/s^2]
    psi0: float        # heading at t0 [rad]
    yaw_rate: _Ramp    # dψ/dt [rad/s]
    pitch: _Ramp       # θ [rad]
    d0: float          # distance at t0 [m]
    stand: bool


class _Builder:
    """Accumulate pieces from segment commands (SI arguments)."""

    def __init__(self, lat, lon, h, heading, speed=0.0, where="trajectory"):
        _check_position(lat, h, where)
        if speed < 0:
            raise TrajectoryError(f"{where}: speed", f"{speed:g} m/s must not be negative")
        self.lat0, self.lon0, self.h0 = float(lat), float(lon), float(h)
        self.t = 0.0
        self.s = float(speed)
        self.psi = float(heading)
        self.theta = 0.0
        self.d = 0.0
        self.pieces: list[_Piece] = []

    def _add(self, T, *, accel=(0.0, 0.0), yaw_rate=(0.0, 0.0), pitch=None, stand=False):
        if T <= 1e-12:
            return
        pitch = (self.theta, self.theta) if pitch is None else pitch
        p = _Piece(self.t, T, self.s, _Ramp(*accel, T), self.psi, _Ramp(*yaw_rate, T),
                   _Ramp(*pitch, T), self.d, stand)
        self.pieces.append(p)
        self.d = p.d0 + p.s0 * T + p.accel.integral2(T)
        self.s = p.s0 + p.accel.integral(T)
        if abs(self.s) < 1e-12:
            self.s = 0.0
        self.psi = p.psi0 + p.yaw_rate.integral(T)
        self.theta = p.pitch.b
        self.t += T

    def _trapezoid(self, change, T, Tr):
        """Split ``change`` over ``T`` into ramp-hold-ramp rate parts."""
        Tr = min(Tr, 0.5 * T)
        peak = change / (T - Tr)
        return peak, [(Tr, (0.0, peak)), (T - 2.0 * Tr, (peak, peak)), (Tr, (peak, 0.0))]

    def stand(self, duration, where):
        _positive(duration, f"{where}: duration")
        if self.s != 0.0:
            raise TrajectoryError(where, f"the vehicle is moving ({self.s:.6g} m/s) at the start of a "
                                  "stand; decelerate to 0 first")
        self._add(duration, stand=True)

    def cruise(self, duration, where, allow_zero=False):
        if allow_zero and duration == 0:
            return
        _positive(duration, f"{where}: duration")
        if self.s == 0.0:
            raise TrajectoryError(where, "cruise at zero speed; accelerate first or use kind='stand'")
        self._add(duration)

    def accelerate(self, to_speed, *, duration=None, acceleration=None, transition=3.0,
                   decelerate=False, where="accelerate"):
        if to_speed < 0:
            raise TrajectoryError(f"{where}: to_speed", f"{to_speed:g} m/s must not be negative")
        if (duration is None) == (acceleration is None):
            raise TrajectoryError(where, "give exactly one of 'duration' and 'acceleration'")
        _positive(transition, f"{where}: transition")
        change = to_speed - self.s
        if decelerate and not change < 0:
            raise TrajectoryError(f"{where}: to_speed", f"{to_speed:g} m/s is not below the current "
                                  f"speed {self.s:.6g} m/s")
        if change == 0:
            raise TrajectoryError(f"{where}: to_speed", f"equals the current speed {self.s:.6g} m/s; "
                                  "use kind='cruise'")
        if duration is not None:
            _positive(duration, f"{where}: duration")
            T = duration
        else:
            _positive(acceleration, f"{where}: acceleration")
            Tr = min(transition, abs(change) / acceleration)
            T = abs(change) / acceleration + Tr
        peak, parts = self._trapezoid(change, T, transition)
        for dt_, acc in parts:
            self._add(dt_, accel=acc)
        self.s = float(to_speed)

    def turn(self, *, rate=None, angle=None, duration=None, transition=3.0, where="turn"):
        given = [k for k, v in (("rate", rate), ("angle", angle), ("duration", duration)) if v is not None]
        if len(given) != 2:
            raise TrajectoryError(where, f"give exactly two of 'rate', 'angle' and 'duration' (got "
                                  f"{', '.join(map(repr, given)) or 'none'})")
        _positive(transition, f"{where}: transition")
        if duration is not None:
            _positive(duration, f"{where}: duration")
        for key, val in (("rate", rate), ("angle", angle)):
            if val is not None and val == 0:
                raise TrajectoryError(f"{where}: {key}", "must not be zero")
        if rate is not None and angle is not None:
            if np.sign(rate) != np.sign(angle):
                raise TrajectoryError(where, "rate and angle have opposite signs (right turn is positive)")
            hold = angle / rate
            T = hold + min(transition, hold)
        elif rate is not None:
            T = duration
            angle = rate * (T - min(transition, 0.5 * T))
        else:
            T = duration
        _, parts = self._trapezoid(angle, T, transition)
        psi_end = self.psi + angle
        for dt_, r in parts:
            self._add(dt_, yaw_rate=r)
        self.psi = psi_end

    def grade(self, angle, duration, *, transition=5.0, level_off=True, where="grade"):
        _positive(duration, f"{where}: duration")
        _positive(transition, f"{where}: transition")
        if not abs(angle) < 0.5 * np.pi:
            raise TrajectoryError(where, f"grade angle {np.degrees(angle):g} deg is not within ±90 deg")
        if self.s == 0.0:
            raise TrajectoryError(where, "grade at zero speed; accelerate first")
        Tr = min(transition, 0.5 * duration if level_off else duration)
        self._add(Tr, pitch=(self.theta, angle))
        self._add(duration - (2.0 if level_off else 1.0) * Tr, pitch=(angle, angle))
        if level_off:
            self._add(Tr, pitch=(angle, 0.0))

    def build(self, *, dt, name, where):
        if not self.pieces:
            raise TrajectoryError(where, "no segments (the trajectory has zero duration)")
        profile = _Profile(self.pieces, self.lat0, self.lon0, self.h0)
        return profile.trajectory(dt=dt, name=name, where=where)


def _positive(x, where):
    if not (np.isfinite(x) and x > 0):
        raise TrajectoryError(where, f"must be positive, got {x:g} (SI)")


def _check_position(lat, h, where):
    if not abs(lat) < np.radians(89.9):
        raise TrajectoryError(f"{where}: lat", f"{np.degrees(lat):g} deg is not within ±89.9 deg "
                              "(the NED frame is singular at the poles)")
    if not -1e4 < h < 1e5:
        raise TrajectoryError(f"{where}: h", f"{h:g} m is outside [-10 km, 100 km]")


class _Profile:
    """Analytic kinematics of pieces, with integrated position."""

    def __init__(self, pieces, lat0, lon0, h0):
        self.pieces = list(pieces)
        self.starts = np.array([p.t0 for p in self.pieces])
        self.span = (float(self.pieces[0].t0), float(self.pieces[-1].t0 + self.pieces[-1].T))
        self.pos0 = []
        self.sols = []
        pos = np.array([lat0, lon0, h0], dtype=float)
        for p in self.pieces:
            self.pos0.append(pos.copy())
            moving = p.s0 != 0.0 or p.accel.a != 0.0 or p.accel.b != 0.0
            if not moving:
                self.sols.append(None)
                continue
            sol = solve_ivp(_position_rhs, (0.0, p.T), np.zeros(3), method="DOP853",
                            rtol=_ODE_RTOL, atol=_ODE_ATOL, dense_output=True, args=(p, pos[0], pos[2]))
            self.sols.append(sol.sol)
            pos = pos + sol.y[:, -1]

    def kinematics(self, t):
        """Speed, heading, pitch, their rates, distance and position."""
        t = np.asarray(t, dtype=float)
        idx = np.clip(np.searchsorted(self.starts, t, side="right") - 1, 0, len(self.pieces) - 1)
        out = {k: np.empty(t.shape) for k in ("s", "ds", "psi", "dpsi", "theta", "dtheta", "d",
                                              "lat", "lon", "h")}
        for k in np.unique(idx):
            m = idx == k
            p = self.pieces[k]
            tau = t[m] - p.t0
            out["s"][m] = p.s0 + p.accel.integral(tau)
            out["ds"][m] = p.accel.value(tau)
            out["psi"][m] = p.psi0 + p.yaw_rate.integral(tau)
            out["dpsi"][m] = p.yaw_rate.value(tau)
            out["theta"][m] = p.pitch.value(tau)
            out["dtheta"][m] = p.pitch.rate(tau)
            out["d"][m] = p.d0 + p.s0 * tau + p.accel.integral2(tau)
            pos = self.pos0[k][:, None] + (0.0 if self.sols[k] is None else self.sols[k](tau))
            out["lat"][m], out["lon"][m], out["h"][m] = pos
        return out

    def evaluate(self, t):
        """Trajectory fields (except ``t``) at times ``t``."""
        k = self.kinematics(t)
        s, psi, th = k["s"], k["psi"], k["theta"]
        cp, sp, ct, st = np.cos(psi), np.sin(psi), np.cos(th), np.sin(th)
        u = np.stack([ct * cp, ct * sp, -st], axis=-1)
        v_n = s[:, None] * u
        du = np.stack([-st * cp * k["dtheta"] - ct * sp * k["dpsi"],
                       -st * sp * k["dtheta"] + ct * cp * k["dpsi"],
                       -ct * k["dtheta"]], axis=-1)
        dv_n = k["ds"][:, None] * u + s[:, None] * du
        zero = np.zeros_like(th)
        q = quat.from_euler(zero, th, psi)
        w_nb_b = _body_rate_from_euler(zero, th, zero, k["dtheta"], k["dpsi"])
        f_b, w_ib_b = inverse_mechanization(k["lat"], k["h"], v_n, dv_n, q, w_nb_b)
        return dict(lat=k["lat"], lon=k["lon"], h=k["h"], v_n=v_n, q_nb=q, f_b=f_b,
                    w_ib_b=w_ib_b, distance=k["d"])

    def stationary(self):
        """Merged closed intervals of the stand pieces. [s]"""
        out = []
        for p in self.pieces:
            if not p.stand:
                continue
            if out and abs(out[-1][1] - p.t0) < 1e-9:
                out[-1] = (out[-1][0], p.t0 + p.T)
            else:
                out.append((p.t0, p.t0 + p.T))
        return tuple(out)

    def trajectory(self, *, dt, name, where):
        _positive(dt, f"{where}: dt")
        t0, t1 = self.span
        n = int(math.floor((t1 - t0) / dt + 1e-9))
        t = t0 + dt * np.arange(n + 1)
        if t1 - t[-1] > 1e-9 * max(1.0, t1):
            t = np.append(t, t1)
        else:
            t[-1] = t1
        return Trajectory(t=t, **self.evaluate(t), stationary=self.stationary(), name=name,
                          _source=self)


def _position_rhs(tau, y, p, lat_p, h_p):
    """d(Δlat, Δlon, Δh)/dt on a piece (earth.position_rates, scalar)."""
    s = p.s0 + p.accel.integral(tau)
    psi = p.psi0 + p.yaw_rate.integral(tau)
    th = p.pitch.value(tau)
    lat = lat_p + y[0]
    h = h_p + y[2]
    sl = math.sin(lat)
    w = 1.0 - earth.E2 * sl * sl
    rn = earth.A / math.sqrt(w)
    rm = rn * (1.0 - earth.E2) / w
    ch = s * math.cos(th)
    return [ch * math.cos(psi) / (rm + h), ch * math.sin(psi) / ((rn + h) * math.cos(lat)),
            s * math.sin(th)]


# --------------------------------------------------------------------------
# built-in profiles
# --------------------------------------------------------------------------

#: turn-angle signs per cycle of :func:`land_vehicle` (right positive); the
#: route visits all four cardinal headings and ends heading north
_LV_TURNS = ((+1, +1), (+1, -1), (-1, -1), (-1, +1), (+1, +1), (+1, +1))


def land_vehicle(*, dt=1.0, cycles=6, period=300.0, stop_duration=90.0, distance=15000.0,
                 accel_duration=20.0, turn_rate=math.radians(5.0), turn_angle=math.radians(90.0),
                 grade=0.04, grade_duration=60.0, lat=math.radians(36.37), lon=math.radians(127.36),
                 h=60.0, heading=0.0, name="land_vehicle") -> Trajectory:
    """Built-in ZUPT land-vehicle route (stands in for seed 002 Fig 3).

    Each of ``cycles`` periods drives for ``period − stop_duration`` and
    then stands still for ``stop_duration``, so every stop contains a
    multiple of ``period`` (the 5-min ZUPT of seed 002).  A drive is:
    accelerate, cruise, turn, cruise, grade (climb on odd cycles, descend on
    even ones), cruise, turn, cruise, decelerate to rest.  The turns
    alternate left and right so that all four headings are visited.

    Parameters
    ----------
    dt : float
        Time step of the returned grid. [s]
    cycles : int
        Number of drive/stop cycles.
    period : float
        Cycle length (ZUPT interval). [s]
    stop_duration : float
        Standstill at the end of each cycle. [s]
    distance : float
        Total distance travelled; sets the cruise speed. [m]
    accel_duration : float
        Duration of each start and stop manoeuvre. [s]
    turn_rate, turn_angle : float
        Peak yaw rate [rad/s] and angle [rad] of every turn.
    grade : float
        Road grade (rise over run) of the hill in each drive. [-]
    grade_duration : float
        Duration of each hill, transitions included. [s]
    lat, lon : float
        Start position. [rad]
    h : float
        Start height. [m]
    heading : float
        Initial heading. [rad]
    name : str
        Label of the trajectory.

    Returns
    -------
    Trajectory
        Sampled every ``dt``; :meth:`Trajectory.sample` is exact.

    Notes
    -----
    With the defaults: 1800 s, 15 km, cruise 47.4 km/h, moving-average speed
    42.9 km/h (seed 002: ~43 km/h), stops on [210, 300], ..., [1710, 1800] s,
    twelve 90-deg turns at 5 deg/s and six 4 % hills.
    """
    return _land_vehicle("land_vehicle", dt=dt, cycles=cycles, period=period,
                         stop_duration=stop_duration, distance=distance,
                         accel_duration=accel_duration, turn_rate=turn_rate, turn_angle=turn_angle,
                         grade=grade, grade_duration=grade_duration, lat=lat, lon=lon, h=h,
                         heading=heading, name=name)


def _land_vehicle(where, *, dt, cycles, period, stop_duration, distance, accel_duration, turn_rate,
                  turn_angle, grade, grade_duration, lat, lon, h, heading, name):
    if isinstance(cycles, bool) or not isinstance(cycles, (int, np.integer)) or cycles < 1:
        raise TrajectoryError(f"{where}: cycles", f"{cycles!r} is not a positive integer")
    for key, val in (("period", period), ("stop_duration", stop_duration), ("distance", distance),
                     ("accel_duration", accel_duration), ("turn_rate", turn_rate),
                     ("turn_angle", turn_angle), ("grade_duration", grade_duration)):
        _positive(val, f"{where}: {key}")
    tr_turn = _TRANSITION["turn"]
    turn_T = turn_angle / turn_rate + min(tr_turn, turn_angle / turn_rate)
    drive = period - stop_duration
    spare = drive - 2.0 * accel_duration - 2.0 * turn_T - grade_duration
    if spare < 0:
        raise TrajectoryError(where, f"the drive of {drive:g} s per cycle is too short for two "
                              f"{accel_duration:g} s speed changes, two {turn_T:g} s turns and a "
                              f"{grade_duration:g} s hill")
    cruise_T = spare / 4.0
    speed = distance / (cycles * (drive - accel_duration))
    angle = math.atan(grade)
    tr_grade = min(8.0, 0.25 * grade_duration)
    b = _Builder(lat, lon, h, heading, where=where)
    for c in range(cycles):
        w = f"{where}: cycle {c + 1}"
        sign1, sign2 = _LV_TURNS[c % len(_LV_TURNS)]
        b.accelerate(speed, duration=accel_duration, where=w)
        b.cruise(cruise_T, w, allow_zero=True)
        b.turn(rate=sign1 * turn_rate, angle=sign1 * turn_angle, transition=tr_turn, where=w)
        b.cruise(cruise_T, w, allow_zero=True)
        if grade != 0:
            b.grade(angle if c % 2 == 0 else -angle, grade_duration, transition=tr_grade, where=w)
        else:
            b.cruise(grade_duration, w)
        b.cruise(cruise_T, w, allow_zero=True)
        b.turn(rate=sign2 * turn_rate, angle=sign2 * turn_angle, transition=tr_turn, where=w)
        b.cruise(cruise_T, w, allow_zero=True)
        b.accelerate(0.0, duration=accel_duration, where=w)
        b.stand(stop_duration, w)
    return b.build(dt=dt, name=name, where=where)


def static(duration=1800.0, *, lat, lon, h, heading=0.0, dt=1.0, name="static") -> Trajectory:
    """A vehicle at rest: one stationary interval over the whole span.

    Parameters
    ----------
    duration : float
        Span. [s]
    lat, lon : float
        Position. [rad]
    h : float
        Height. [m]
    heading : float
        Heading (yaw); roll and pitch are zero. [rad]
    dt : float
        Time step. [s]
    name : str
        Label.

    Returns
    -------
    Trajectory
        ``f_b = C_n^b [0, 0, −g]``, ``w_ib_b = C_n^b ω_ie^n``.
    """
    return _static("static", duration=duration, lat=lat, lon=lon, h=h, heading=heading, dt=dt, name=name)


def _static(where, *, duration, lat, lon, h, heading, dt, name):
    b = _Builder(lat, lon, h, heading, where=where)
    b.stand(duration, where)
    return b.build(dt=dt, name=name, where=where)


# --------------------------------------------------------------------------
# declarations (study files)
# --------------------------------------------------------------------------

_SEGMENT_DIMS = {"duration": "time", "to_speed": "velocity", "acceleration": "acceleration",
                 "transition": "time", "rate": "angular_rate", "angle": "angle", "grade": "dimensionless"}
_INITIAL_KEYS = {"lat": "angle", "lon": "angle", "h": "length", "heading": "angle", "speed": "velocity"}

#: built-in profile -> {parameter: dimension}
BUILTINS = {
    "land_vehicle": {
        "cycles": "int", "period": "time", "stop_duration": "time", "distance": "length",
        "accel_duration": "time", "turn_rate": "angular_rate", "turn_angle": "angle",
        "grade": "dimensionless", "grade_duration": "time",
        "lat": "angle", "lon": "angle", "h": "length", "heading": "angle",
    },
    "static": {"duration": "time", "lat": "angle", "lon": "angle", "h": "length", "heading": "angle"},
}


def _q(value, dimension, where):
    return quantity(value, dimension, where, TrajectoryError)


def _check_keys(d, allowed, where):
    check_keys(d, allowed, where, TrajectoryError)


def from_segments(segments, initial, *, dt=1.0, name="", where="trajectory") -> Trajectory:
    """Trajectory from segment declarations with datasheet units.

    Parameters
    ----------
    segments : list of dict
        E.g. ``{"kind": "turn", "rate": "3 deg/s", "angle": "90 deg"}``;
        kinds and keys in :data:`SEGMENT_KINDS`.
    initial : dict
        ``lat``, ``lon``, ``h`` (required), ``heading`` and ``speed``
        (default 0).
    dt : float
        Time step of the returned grid. [s]
    name : str
        Label.
    where : str
        Location prefix of error messages.

    Returns
    -------
    Trajectory
        Its :meth:`~Trajectory.sample` evaluates the profile exactly.

    Raises
    ------
    TrajectoryError
        Unknown kind or key, missing or inconsistent keys, bad units,
        non-positive durations, or an impossible sequence (e.g. a stand
        while moving).

    Notes
    -----
    * ``accelerate``/``decelerate``: ``to_speed`` and one of ``duration``
      or ``acceleration`` (the plateau acceleration); the acceleration ramps
      take ``transition`` (default 3 s).
    * ``turn``: two of ``rate``, ``angle``, ``duration`` (right positive);
      the yaw rate ramps take ``transition`` (default 3 s).
    * ``grade``: ``grade`` (rise/run, e.g. ``"5 %"``) or ``angle``; the
      pitch moves from its current value to the grade angle over
      ``transition`` (default 5 s), holds, and returns to level within
      ``duration``; with ``level_off = false`` it stays on the grade, so
      later segments (a turn: a helical ramp) run on it.  Vertical velocity
      is ``−s sin θ``.
    """
    _check_keys(initial, _INITIAL_KEYS, f"{where}: initial")
    init = {}
    for key, dim in _INITIAL_KEYS.items():
        if key in initial:
            init[key] = _q(initial[key], dim, f"{where}: initial: {key}")
        elif key in ("lat", "lon", "h"):
            raise TrajectoryError(f"{where}: initial", f"missing required key {key!r}")
    b = _Builder(init["lat"], init["lon"], init["h"], init.get("heading", 0.0),
                 init.get("speed", 0.0), where=f"{where}: initial")
    if not isinstance(segments, (list, tuple)) or not segments:
        raise TrajectoryError(f"{where}: segment", "expected a non-empty list of segments")
    for i, seg in enumerate(segments):
        w = f"{where}: segment[{i}]"
        if not isinstance(seg, dict):
            raise TrajectoryError(w, f"expected a table, got {type(seg).__name__}")
        kind = seg.get("kind")
        if kind not in SEGMENT_KINDS:
            raise TrajectoryError(w, f"unknown segment kind {kind!r} (one of: "
                                  f"{', '.join(sorted(SEGMENT_KINDS))})")
        w = f"{w} ({kind})"
        _check_keys(seg, SEGMENT_KINDS[kind], w)
        v = {k: _q(x, _SEGMENT_DIMS[k], f"{w}: {k}") for k, x in seg.items() if k in _SEGMENT_DIMS}
        if "level_off" in seg:
            if not isinstance(seg["level_off"], bool):
                raise TrajectoryError(f"{w}: level_off", f"{seg['level_off']!r} is not true or false")
            v["level_off"] = seg["level_off"]
        if kind in ("stand", "cruise"):
            if "duration" not in v:
                raise TrajectoryError(w, "missing required key 'duration'")
            getattr(b, kind)(v["duration"], w)
        elif kind in ("accelerate", "decelerate"):
            if "to_speed" not in v:
                raise TrajectoryError(w, "missing required key 'to_speed'")
            b.accelerate(v["to_speed"], duration=v.get("duration"), acceleration=v.get("acceleration"),
                         transition=v.get("transition", _TRANSITION[kind]),
                         decelerate=kind == "decelerate", where=w)
        elif kind == "turn":
            b.turn(rate=v.get("rate"), angle=v.get("angle"), duration=v.get("duration"),
                   transition=v.get("transition", _TRANSITION[kind]), where=w)
        else:  # grade
            if ("grade" in v) == ("angle" in v):
                raise TrajectoryError(w, "give exactly one of 'grade' and 'angle'")
            if "duration" not in v:
                raise TrajectoryError(w, "missing required key 'duration'")
            angle = math.atan(v["grade"]) if "grade" in v else v["angle"]
            b.grade(angle, v["duration"], transition=v.get("transition", _TRANSITION[kind]),
                    level_off=v.get("level_off", True), where=w)
    return b.build(dt=dt, name=name, where=where)


def trajectory_from_config(cfg: dict, *, where: str, base_dir: Path | None, dt: float) -> Trajectory:
    """Trajectory from a study-file table.

    Parameters
    ----------
    cfg : dict
        One of ``{builtin = "land_vehicle", ...parameters}``,
        ``{builtin = "static", duration, lat, lon, h, heading}``,
        ``{segment = [...], initial = {...}}`` or ``{csv = "file.csv"}``
        (with an optional ``max_gap = "5 s"``: the longest time step that
        may be interpolated, see :func:`load_trajectory_csv`); each may
        carry ``name``.  Parameters use datasheet units.
    where : str
        Location prefix of error messages (``"studies/x.toml: [trajectory]"``).
    base_dir : Path or None
        Directory against which a relative ``csv`` path is resolved
        (the current directory if None).
    dt : float
        Time step of generated profiles (a CSV keeps its own grid). [s]

    Returns
    -------
    Trajectory

    Raises
    ------
    TrajectoryError
        Naming ``where``, the key and the problem.
    """
    if not isinstance(cfg, dict):
        raise TrajectoryError(where, f"expected a table, got {type(cfg).__name__}")
    sources = [k for k in ("builtin", "segment", "csv") if k in cfg]
    if len(sources) != 1:
        raise TrajectoryError(where, "give exactly one of 'builtin', 'segment' and 'csv' "
                              f"(got {', '.join(map(repr, sources)) or 'none'})")
    name = cfg.get("name", "")
    if not isinstance(name, str):
        raise TrajectoryError(f"{where}: name", f"{name!r} is not a string")
    source = sources[0]
    if source == "segment":
        _check_keys(cfg, ("segment", "initial", "name"), where)
        if "initial" not in cfg:
            raise TrajectoryError(where, "missing required key 'initial'")
        return from_segments(cfg["segment"], cfg["initial"], dt=dt, name=name or "segments", where=where)
    if source == "csv":
        _check_keys(cfg, ("csv", "name", "max_gap"), where)
        max_gap = None
        if "max_gap" in cfg:
            max_gap = _q(cfg["max_gap"], "time", f"{where}: max_gap")
            _positive(max_gap, f"{where}: max_gap")
        # relative to the study file that names it, never the current directory
        path = resolve_input(cfg["csv"], base_dir, f"{where}: csv", TrajectoryError, must_exist=False)
        try:
            traj = load_trajectory_csv(path, max_gap=max_gap)
        except TrajectoryError as exc:
            raise TrajectoryError(f"{where}: {exc.where}", exc.problem) from None
        return traj if not name else Trajectory(**_fields(traj), stationary=traj.stationary,
                                                name=name, _source=traj._source)
    builtin = cfg["builtin"]
    if builtin not in BUILTINS:
        raise TrajectoryError(f"{where}: builtin", f"unknown builtin {builtin!r} (one of: "
                              f"{', '.join(sorted(BUILTINS))})")
    spec = BUILTINS[builtin]
    w = f"{where}: builtin {builtin!r}"
    _check_keys(cfg, set(spec) | {"builtin", "name"}, w)
    params = {}
    for key, dim in spec.items():
        if key not in cfg:
            continue
        if dim == "int":
            params[key] = integer(cfg[key], f"{w}: {key}", TrajectoryError, limit=key)
        else:
            params[key] = _q(cfg[key], dim, f"{w}: {key}")
    if "lon" in params and not abs(params["lon"]) <= math.pi:
        raise TrajectoryError(f"{w}: lon", f"{cfg['lon']!r} is not within ±180 deg")
    if builtin == "static":
        for key in ("lat", "lon", "h"):
            if key not in params:
                raise TrajectoryError(w, f"missing required key {key!r}")
        return _static(w, duration=params.get("duration", 1800.0), lat=params["lat"], lon=params["lon"],
                       h=params["h"], heading=params.get("heading", 0.0), dt=dt, name=name or "static")
    defaults = {k: p.default for k, p in inspect.signature(land_vehicle).parameters.items()
                if k in spec}
    defaults.update(params)
    _check_position(defaults["lat"], defaults["h"], w)
    return _land_vehicle(w, dt=dt, name=name or "land_vehicle", **defaults)


def _fields(traj):
    return dict(t=traj.t, lat=traj.lat, lon=traj.lon, h=traj.h, v_n=traj.v_n, q_nb=traj.q_nb,
                f_b=traj.f_b, w_ib_b=traj.w_ib_b, distance=traj.distance)


# --------------------------------------------------------------------------
# CSV trajectories
# --------------------------------------------------------------------------


class _Interpolant:
    """Linear (slerp for attitude) interpolation of sampled data."""

    def __init__(self, traj: Trajectory):
        self.data = _fields(traj)
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


def load_trajectory_csv(path, *, max_gap: float | None = None, max_bytes: int | None = None) -> Trajectory:
    """Read a trajectory CSV file.

    Parameters
    ----------
    path : str or Path
        File with the columns :data:`CSV_COLUMNS` and optionally
        :data:`CSV_OPTIONAL_COLUMNS`, in any order (matched by name).
    max_gap : float, optional
        Longest time step that is interpolated. [s]  Default: a step longer
        than :data:`GAP_FACTOR` times the file's median step is a gap and
        is refused; give ``max_gap`` (``[trajectory] max_gap`` in a study
        file) to declare that longer steps may be interpolated.
    max_bytes : int, optional
        Largest file read (:data:`covtool.io.csv_table.MAX_BYTES`). [bytes]

    Returns
    -------
    Trajectory
        :meth:`~Trajectory.sample` interpolates it.  Longitude is unwrapped
        (each step the one nearest the east velocity's, so a file crossing
        the antimeridian interpolates the short way) and is wrapped again
        only when written.  Without a ``stationary`` column, samples with
        speed below :data:`STATIONARY_SPEED` and body rate w.r.t. NED below
        :data:`STATIONARY_RATE` form the stationary intervals (runs of at
        least two samples).  Without ``distance [m]``, the distance is the
        trapezoidal integral of the speed.  Quaternions are normalised and
        their signs made continuous.

    Raises
    ------
    TrajectoryError
        One line naming the file, the column and the row (1-based data row)
        for: everything :func:`covtool.io.csv_table.read_numeric_csv`
        refuses (missing, unknown or duplicated columns, truncated lines,
        empty, non-numeric or non-finite cells, time not strictly
        increasing, a file over the size limit); a gap in time; quaternion
        norm off by more than :data:`QUATERNION_NORM_TOL`; latitude beyond
        ±89.9°; |longitude| over :data:`MAX_CSV_LONGITUDE`; a ``stationary``
        flag that is not 0 or 1, or is 1 while the vehicle moves faster
        than :data:`STATIONARY_FLAG_SPEED` or turns faster than
        :data:`STATIONARY_FLAG_RATE` with respect to the NED frame.
    """
    path = Path(path)
    where = str(path)
    cols = read_numeric_csv(path, CSV_COLUMNS, CSV_OPTIONAL_COLUMNS, error=TrajectoryError, max_bytes=max_bytes)
    t = cols["t [s]"]
    step = np.diff(t)
    median = float(np.median(step))
    bound = GAP_FACTOR * median if max_gap is None else float(max_gap)
    long_steps = step > bound
    if long_steps.any():
        r = int(np.argmax(long_steps)) + 2
        how = (f"more than {GAP_FACTOR:g} × the file's median step {median:.6g} s" if max_gap is None
               else f"more than the declared max_gap {bound:.6g} s")
        raise TrajectoryError(f"{where}: column 't [s]'", f"row {r}: a gap of {step[r - 2]:.6g} s after t = "
                              f"{t[r - 2]:.9g} s, {how}; {int(long_steps.sum())} gap(s) in all (declare "
                              "[trajectory] max_gap to interpolate across them)")
    q = np.column_stack([cols[c] for c in ("q0", "q1", "q2", "q3")])
    norm = np.linalg.norm(q, axis=1)
    off = np.abs(norm - 1.0) > QUATERNION_NORM_TOL
    if off.any():
        r = int(np.argmax(off))
        raise TrajectoryError(f"{where}: columns 'q0'..'q3'", f"row {r + 1}: |q| = {norm[r]:.9g} is not 1 "
                              f"(tolerance {QUATERNION_NORM_TOL:g})")
    q = q / norm[:, None]
    flips = np.cumprod(np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0))
    q[1:] *= flips[:, None]
    lat, h = np.radians(cols["lat [deg]"]), cols["h [m]"]
    bad_lat = np.abs(lat) >= np.radians(89.9)
    if bad_lat.any():
        r = int(np.argmax(bad_lat))
        raise TrajectoryError(f"{where}: column 'lat [deg]'", f"row {r + 1}: {cols['lat [deg]'][r]:g} deg "
                              "is not within ±89.9 deg")
    bad_lon = np.abs(cols["lon [deg]"]) > MAX_CSV_LONGITUDE
    if bad_lon.any():
        r = int(np.argmax(bad_lon))
        raise TrajectoryError(f"{where}: column 'lon [deg]'", f"row {r + 1}: {cols['lon [deg]'][r]:g} deg "
                              f"is not within ±{MAX_CSV_LONGITUDE:g} deg")
    v_n = np.column_stack([cols[c] for c in ("v_N [m/s]", "v_E [m/s]", "v_D [m/s]")])
    lon = _unwrap_longitude(np.radians(cols["lon [deg]"]), lat, h, v_n[:, 1], t)
    f_b = np.column_stack([cols[c] for c in ("f_x [m/s^2]", "f_y [m/s^2]", "f_z [m/s^2]")])
    w_ib_b = np.column_stack([cols[c] for c in ("w_x [rad/s]", "w_y [rad/s]", "w_z [rad/s]")])
    speed = np.linalg.norm(v_n, axis=1)
    if "distance [m]" in cols:
        distance = cols["distance [m]"]
    else:
        distance = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * step)])
    w_in = earth.earth_rate_n(lat) + earth.transport_rate_n(lat, h, v_n)
    turn = np.linalg.norm(w_ib_b - np.einsum("kji,kj->ki", quat.dcm(q), w_in), axis=1)   # |ω_nb^b|
    if "stationary" in cols:
        flag = cols["stationary"]
        bad = (flag != 0) & (flag != 1)
        if bad.any():
            r = int(np.argmax(bad))
            raise TrajectoryError(f"{where}: column 'stationary'", f"row {r + 1}: {flag[r]:g} is not 0 or 1")
        still = flag == 1
        moving = still & ((speed > STATIONARY_FLAG_SPEED) | (turn > STATIONARY_FLAG_RATE))
        if moving.any():
            r = int(np.argmax(moving))
            what = (f"speed {speed[r]:.6g} m/s (tolerance {STATIONARY_FLAG_SPEED:g} m/s)"
                    if speed[r] > STATIONARY_FLAG_SPEED else
                    f"body rate w.r.t. NED {turn[r]:.6g} rad/s (tolerance {STATIONARY_FLAG_RATE:g} rad/s)")
            raise TrajectoryError(f"{where}: column 'stationary'", f"row {r + 1}: flagged stationary (1) while "
                                  f"the vehicle moves: {what}; {int(moving.sum())} such row(s)")
    else:
        still = (speed < STATIONARY_SPEED) & (turn < STATIONARY_RATE)
    intervals = []
    k = 0
    while k < t.size:
        if still[k]:
            j = k
            while j + 1 < t.size and still[j + 1]:
                j += 1
            if j > k or "stationary" in cols:
                intervals.append((float(t[k]), float(t[j])))
            k = j + 1
        else:
            k += 1
    traj = Trajectory(t=t, lat=lat, lon=lon, h=h, v_n=v_n, q_nb=q, f_b=f_b, w_ib_b=w_ib_b,
                      distance=distance, stationary=tuple(intervals), name=path.stem)
    return Trajectory(**_fields(traj), stationary=traj.stationary, name=traj.name,
                      _source=_Interpolant(traj))


def save_trajectory_csv(traj: Trajectory, path) -> None:
    """Write a trajectory as CSV (exact round trip with the loader).

    Parameters
    ----------
    traj : Trajectory
        The samples to write.
    path : str or Path
        Output file; written atomically, numbers with 17 significant digits.
    """
    from .io.atomic import write_text

    write_text(path, traj.to_dataframe().to_csv(index=False, float_format="%.17g"))
