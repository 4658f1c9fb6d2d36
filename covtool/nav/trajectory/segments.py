"""Segment profiles: piecewise analytic kinematics with integrated position.

The segments (``stand``, ``accelerate``/``decelerate``, ``cruise``,
``turn``, ``grade``) are declared in SI by :class:`ProfileBuilder` (the
built-in profiles) or with datasheet units in a study file
(:func:`covtool.io.trajectory.from_segments`).

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
integrated quantity: :func:`covtool.nav.earth.position_rates` is integrated piece
by piece (pieces end wherever a higher derivative jumps) with DOP853 at
``rtol = 1e-12`` and kept as dense output, so :meth:`Trajectory.sample` of a
declared profile evaluates the generating kinematics, not an interpolation
of the time grid.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from covtool.errors import TrajectoryError
from covtool.nav import attitude as quat, earth
from covtool.nav.trajectory.core import body_rate_from_euler, grid_times, inverse_mechanization, Trajectory

__all__ = [
    "SEGMENT_KINDS",
]


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
TRANSITION = {"accelerate": 3.0, "decelerate": 3.0, "turn": 3.0, "grade": 5.0}

_ODE_RTOL = 1e-12
# absolute tolerances of the (Δlat [rad], Δlon [rad], Δh [m]) offsets: ~1e-9 m
_ODE_ATOL = (1e-16, 1e-16, 1e-9)


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


class ProfileBuilder:
    """Accumulate pieces from segment commands (SI arguments)."""

    def __init__(self, lat, lon, h, heading, speed=0.0, where="trajectory"):
        check_position(lat, h, where)
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
        check_positive(duration, f"{where}: duration")
        if self.s != 0.0:
            raise TrajectoryError(where, f"the vehicle is moving ({self.s:.6g} m/s) at the start of a "
                                  "stand; decelerate to 0 first")
        self._add(duration, stand=True)

    def cruise(self, duration, where, allow_zero=False):
        if allow_zero and duration == 0:
            return
        check_positive(duration, f"{where}: duration")
        if self.s == 0.0:
            raise TrajectoryError(where, "cruise at zero speed; accelerate first or use kind='stand'")
        self._add(duration)

    def accelerate(self, to_speed, *, duration=None, acceleration=None, transition=3.0,
                   decelerate=False, where="accelerate"):
        if to_speed < 0:
            raise TrajectoryError(f"{where}: to_speed", f"{to_speed:g} m/s must not be negative")
        if (duration is None) == (acceleration is None):
            raise TrajectoryError(where, "give exactly one of 'duration' and 'acceleration'")
        check_positive(transition, f"{where}: transition")
        change = to_speed - self.s
        if decelerate and not change < 0:
            raise TrajectoryError(f"{where}: to_speed", f"{to_speed:g} m/s is not below the current "
                                  f"speed {self.s:.6g} m/s")
        if change == 0:
            raise TrajectoryError(f"{where}: to_speed", f"equals the current speed {self.s:.6g} m/s; "
                                  "use kind='cruise'")
        if duration is not None:
            check_positive(duration, f"{where}: duration")
            T = duration
        else:
            check_positive(acceleration, f"{where}: acceleration")
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
        check_positive(transition, f"{where}: transition")
        if duration is not None:
            check_positive(duration, f"{where}: duration")
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
        check_positive(duration, f"{where}: duration")
        check_positive(transition, f"{where}: transition")
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


def check_positive(x, where):
    if not (np.isfinite(x) and x > 0):
        raise TrajectoryError(where, f"must be positive, got {x:g} (SI)")


def check_position(lat, h, where):
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
        from scipy.integrate import solve_ivp     # when a profile is built, not when a copy is sampled

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
        w_nb_b = body_rate_from_euler(zero, th, zero, k["dtheta"], k["dpsi"])
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
        check_positive(dt, f"{where}: dt")
        t = grid_times(*self.span, dt)
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
