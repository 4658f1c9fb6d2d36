"""High-dynamics flight profiles with the Trajectory interface.

A flight profile is the true motion of a high-dynamics vehicle (seed 001:
a guided vehicle with boost, manoeuvres and flight vibration) returned as a
:class:`covtool.nav.trajectory.core.Trajectory` whose :meth:`~covtool.nav.trajectory.core.Trajectory.sample`
evaluates the generating kinematics, so IMU increments and the linear
error model see the same exact motion as for the land-vehicle profiles.

Kinematics
----------
Four channels: speed ``s``, heading ``ψ``, flight-path pitch ``θ`` and roll
``φ``.  A ``fly`` segment changes any of them; each change is a
trapezoid of its *rate* (raised-cosine ramps ``S(u) = (1 − cos πu)/2`` of
length ``transition``, a hold, and a ramp back), so every rate and its
derivative are continuous.  The body x axis lies along the flight path
(no angle of attack) and roll turns the body about it::

    v^n = s [cos θ cos ψ, cos θ sin ψ, −sin θ] + C_b^n v_vib^b
    q_nb = from_euler(φ + δφ, θ + δθ, ψ + δψ)

A *vibration interval* adds small angular oscillations ``δφ, δθ, δψ`` (about
body x, y, z) and a body-frame velocity oscillation ``v_vib^b`` whose
acceleration amplitude is the declared one, both multiplied by a smooth
on/off envelope.  ``v̇^n``, ``ω_nb^b`` (3-2-1 Euler rates, with roll) and
hence ``f^b`` and ``ω_ib^b`` follow analytically
(:func:`covtool.nav.trajectory.core.inverse_mechanization`).

Position is the only integrated quantity: ``h = h0 − ∫v_D``,
``L = L0 + ∫v_N/(R_M + h)`` (Picard iteration) and
``l = l0 + ∫v_E/((R_N + h) cos L)``, by spectral (Gauss–Legendre)
integration on a knot grid that contains every breakpoint of the channels
and is fine enough for the highest vibration frequency; positions between
knots use the integrated interpolating polynomial through the nodes.  The
result is exact to ~1e-14 relative.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from covtool.errors import TrajectoryError
from covtool.nav import attitude as quat, earth
from covtool.nav.trajectory.core import grid_times, inverse_mechanization, Trajectory

__all__ = [
    "FlightProfile", "Segment", "VibrationTone", "VibrationInterval", "flight", "quadrature_nodes",
]


#: kinds of vibration tone: rotation about an axis, acceleration along it
TONE_KINDS = ("angular", "linear")
#: default transition of a channel change [s]
DEFAULT_TRANSITION = 1.0

# spectral integration: nodes per knot interval and the largest interval
_NODES = 10
#: Picard iterations of the latitude at most (:meth:`FlightProfile._integrate`)
_PICARD_MAX = 50
_MAX_KNOT = 0.1


def _S(u):
    return 0.5 * (1.0 - np.cos(np.pi * u))


@dataclass(frozen=True)
class _Change:
    """A trapezoid-of-rate change of one channel over ``[t0, t0 + T]``."""

    t0: float
    T: float
    delta: float
    Tr: float

    @property
    def peak(self) -> float:
        """Rate held between the ramps."""
        return self.delta / (self.T - self.Tr)

    def rate(self, tau):
        """Rate at time ``tau`` into the change."""
        p, Tr, T = self.peak, self.Tr, self.T
        up = p * _S(np.clip(tau, 0.0, Tr) / Tr)
        down = p * _S(np.clip(T - tau, 0.0, Tr) / Tr)
        return np.where(tau < Tr, up, np.where(tau > T - Tr, down, p))

    def integral(self, tau):
        """Change accumulated by ``tau``."""
        p, Tr, T = self.peak, self.Tr, self.T
        u = np.clip(tau, 0.0, Tr) / Tr
        first = p * Tr * 0.5 * (u - np.sin(np.pi * u) / np.pi)
        hold = p * Tr * 0.5 + p * (tau - Tr)
        w = np.clip(T - tau, 0.0, Tr) / Tr
        last = self.delta - p * Tr * 0.5 * (w - np.sin(np.pi * w) / np.pi)
        return np.where(tau < Tr, first, np.where(tau > T - Tr, last, hold))


class _Channel:
    """A channel: its start value and its sequence of changes."""

    def __init__(self, x0: float):
        self.x0 = float(x0)
        self.changes: list[_Change] = []
        self.end = float(x0)

    def add(self, t0, T, delta, Tr):
        """Append a change of ``delta`` over ``[t0, t0 + T]``."""
        if delta != 0.0:
            self.changes.append(_Change(float(t0), float(T), float(delta), float(min(Tr, 0.5 * T))))
            self.end += float(delta)

    def breakpoints(self):
        """Times where a rate derivative changes form."""
        out = []
        for c in self.changes:
            out += [c.t0, c.t0 + c.Tr, c.t0 + c.T - c.Tr, c.t0 + c.T]
        return out

    def evaluate(self, t):
        """Value and rate at times ``t``."""
        x = np.full(t.shape, self.x0)
        r = np.zeros(t.shape)
        for c in self.changes:
            tau = t - c.t0
            inside = (tau > 0.0) & (tau < c.T)
            after = tau >= c.T
            if inside.any():
                x[inside] += c.integral(tau[inside])
                r[inside] += c.rate(tau[inside])
            x[after] += c.delta
        return x, r


@dataclass(frozen=True)
class Segment:
    """One flight segment, SI values.

    Attributes
    ----------
    kind : str
        ``"stand"`` (at rest) or ``"fly"``.
    duration : float
        [s]
    to_speed, to_pitch, to_roll : float or None
        Target speed [m/s], flight-path pitch [rad] and roll [rad] at the end
        of the segment (None: unchanged).  Roll is a continuous angle, so
        ``to_roll = 2π`` is a full roll.
    turn : float
        Heading change (right positive). [rad]
    transition : float
        Ramp time of every rate change (at most half the duration). [s]
    """

    kind: str
    duration: float
    to_speed: float | None = None
    to_pitch: float | None = None
    to_roll: float | None = None
    turn: float = 0.0
    transition: float = DEFAULT_TRANSITION


@dataclass(frozen=True)
class VibrationTone:
    """A sinusoidal vibration component.

    Attributes
    ----------
    kind : str
        ``"angular"``: oscillation of the roll, pitch or yaw angle (axis x,
        y, z) with amplitude [rad]; ``"linear"``: body-frame acceleration
        along the axis with amplitude [m/s²].
    axis : str
        ``"x"``, ``"y"`` or ``"z"``.
    amplitude, frequency, phase : float
        [rad or m/s²], [Hz], [rad].
    """

    kind: str
    axis: str
    amplitude: float
    frequency: float
    phase: float = 0.0


@dataclass(frozen=True)
class VibrationInterval:
    """Vibration over ``[start, start + duration]`` with on/off ramps.

    Attributes
    ----------
    start, duration, ramp : float
        [s]; the envelope rises over ``ramp`` with ``S`` and falls likewise.
    tones : tuple of VibrationTone
    """

    start: float
    duration: float
    ramp: float
    tones: tuple

    def envelope(self, t):
        """Envelope ``w(t)`` and ``ẇ(t)``."""
        tau = t - self.start
        R, T = self.ramp, self.duration
        u = np.clip(tau, 0.0, R) / R
        d = np.clip(T - tau, 0.0, R) / R
        w = np.where(tau < R, _S(u), np.where(tau > T - R, _S(d), 1.0))
        k = 0.5 * np.pi / R
        dw = np.where(tau < R, k * np.sin(np.pi * u), np.where(tau > T - R, -k * np.sin(np.pi * d), 0.0))
        outside = (tau <= 0.0) | (tau >= T)
        return np.where(outside, 0.0, w), np.where(outside, 0.0, dw)

    @property
    def max_frequency(self) -> float:
        """Highest tone frequency. [Hz]"""
        return max((tn.frequency for tn in self.tones), default=0.0)

    def breakpoints(self):
        """Ends of the ramps and of the interval."""
        s, T, R = self.start, self.duration, self.ramp
        return [s, s + R, s + T - R, s + T]


_AXIS = {"x": 0, "y": 1, "z": 2}


class FlightProfile:
    """Analytic flight kinematics (the ``_source`` of a Trajectory).

    Parameters
    ----------
    segments : sequence of Segment
    lat, lon, h : float
        Start position. [rad], [rad], [m]
    heading, pitch : float
        Start heading and pitch (e.g. the launcher elevation). [rad]
    vibration : sequence of VibrationInterval
    where : str
        Location prefix of error messages.

    Raises
    ------
    TrajectoryError
        A stand while moving, flying at zero speed, a non-positive duration
        or transition, overlapping vibration intervals, a vibration before the
        vehicle moves, a pitch beyond ±80 deg.
    """

    def __init__(self, segments, *, lat, lon, h, heading=0.0, pitch=0.0, vibration=(), where="flight"):
        self.where = where
        if not abs(lat) < math.radians(89.9):
            raise TrajectoryError(f"{where}: initial: lat", f"{math.degrees(lat):g} deg is not within ±89.9 deg")
        if not -1e4 < h < 1e5:
            raise TrajectoryError(f"{where}: initial: h", f"{h:g} m is outside [-10 km, 100 km]")
        if not abs(pitch) <= math.radians(80.0):
            raise TrajectoryError(f"{where}: initial: pitch", f"{math.degrees(pitch):g} deg is not within ±80 deg")
        if not segments:
            raise TrajectoryError(f"{where}: segment", "expected a non-empty list of segments")
        self.lat0, self.lon0, self.h0 = float(lat), float(lon), float(h)
        self.speed = _Channel(0.0)
        self.heading = _Channel(heading)
        self.pitch = _Channel(pitch)
        self.roll = _Channel(0.0)
        t = 0.0
        stands = []
        moving_from = None
        for i, seg in enumerate(segments):
            w = f"{where}: segment[{i}] ({seg.kind})"
            if not (math.isfinite(seg.duration) and seg.duration > 0):
                raise TrajectoryError(f"{w}: duration", f"must be positive, got {seg.duration:g} s")
            T = float(seg.duration)
            if seg.kind == "stand":
                if self.speed.end != 0.0:
                    raise TrajectoryError(w, f"the vehicle is moving ({self.speed.end:.6g} m/s); "
                                          "a stand needs zero speed")
                stands.append((t, t + T))
            elif seg.kind == "fly":
                if not (math.isfinite(seg.transition) and seg.transition > 0):
                    raise TrajectoryError(f"{w}: transition", f"must be positive, got {seg.transition:g} s")
                Tr = seg.transition
                if self.speed.end == 0.0 and not (seg.to_speed or 0.0) > 0:
                    raise TrajectoryError(w, "flying at zero speed; give a positive 'to_speed' or use "
                                          "kind = 'stand'")
                if seg.to_speed is not None:
                    if seg.to_speed < 0:
                        raise TrajectoryError(f"{w}: to_speed", f"{seg.to_speed:g} m/s must not be negative")
                    self.speed.add(t, T, seg.to_speed - self.speed.end, Tr)
                if seg.to_pitch is not None:
                    if not abs(seg.to_pitch) <= math.radians(80.0):
                        raise TrajectoryError(f"{w}: to_pitch",
                                              f"{math.degrees(seg.to_pitch):g} deg is not within ±80 deg")
                    self.pitch.add(t, T, seg.to_pitch - self.pitch.end, Tr)
                if seg.to_roll is not None:
                    self.roll.add(t, T, seg.to_roll - self.roll.end, Tr)
                self.heading.add(t, T, seg.turn, Tr)
                if moving_from is None:
                    moving_from = t
            else:
                raise TrajectoryError(w, f"unknown segment kind {seg.kind!r} (one of: fly, stand)")
            t += T
        self.span = (0.0, t)
        self.stands = tuple(stands)
        vib = sorted(vibration, key=lambda v: v.start)
        for k, v in enumerate(vib):
            w = f"{where}: vibration[{k}]"
            if not (v.duration > 0 and v.ramp > 0 and 2.0 * v.ramp <= v.duration):
                raise TrajectoryError(w, f"needs duration > 0 and 0 < ramp <= duration/2 "
                                      f"(got duration {v.duration:g} s, ramp {v.ramp:g} s)")
            if v.start < 0 or v.start + v.duration > t + 1e-9:
                raise TrajectoryError(w, f"[{v.start:g}, {v.start + v.duration:g}] s is outside the "
                                      f"flight [0, {t:g}] s")
            if any(a < v.start + v.duration and v.start < b for a, b in stands):
                raise TrajectoryError(w, "overlaps a stand segment (vibration is a flight environment)")
            if k and v.start < vib[k - 1].start + vib[k - 1].duration:
                raise TrajectoryError(w, "overlaps the previous vibration interval")
            for j, tn in enumerate(v.tones):
                if tn.kind not in TONE_KINDS:
                    raise TrajectoryError(f"{w}: tone[{j}]", f"kind {tn.kind!r} is not 'angular' or 'linear'")
                if tn.axis not in _AXIS:
                    raise TrajectoryError(f"{w}: tone[{j}]", f"axis {tn.axis!r} is not 'x', 'y' or 'z'")
                if not tn.frequency > 0:
                    raise TrajectoryError(f"{w}: tone[{j}]", f"frequency {tn.frequency:g} Hz must be positive")
        self.vibration = tuple(vib)
        br = [0.0, t]
        for ch in (self.speed, self.heading, self.pitch, self.roll):
            br += ch.breakpoints()
        for v in self.vibration:
            br += v.breakpoints()
        br = np.unique(np.clip(np.array(br), 0.0, t))
        self.breakpoints = br
        knots = [br[:1]]
        for a, b in zip(br[:-1], br[1:]):
            # inside a vibration interval a knot interval spans at most 1/6 of the fastest period
            step = _MAX_KNOT
            for v in self.vibration:
                if a < v.start + v.duration and v.start < b:
                    step = min(step, 1.0 / (6.0 * v.max_frequency))
            n = max(1, int(math.ceil((b - a) / step - 1e-9)))
            knots.append(a + (b - a) * np.arange(1, n + 1) / n)
        knots = np.concatenate(knots)
        self._knots = knots[np.concatenate([[True], np.diff(knots) > 1e-12])]
        self._integrate()

    # ---- kinematics ------------------------------------------------------
    @property
    def max_frequency(self) -> float:
        """Highest vibration frequency. [Hz]"""
        return max((v.max_frequency for v in self.vibration), default=0.0)

    def stationary(self):
        """Closed intervals of the stand segments. [s]"""
        out = []
        for a, b in self.stands:
            if out and abs(out[-1][1] - a) < 1e-9:
                out[-1] = (out[-1][0], b)
            else:
                out.append((a, b))
        return tuple(out)

    def _vibration(self, t):
        """Angle offsets, their rates, body velocity and acceleration."""
        ang = np.zeros(t.shape + (3,))
        dang = np.zeros(t.shape + (3,))
        vb = np.zeros(t.shape + (3,))
        ab = np.zeros(t.shape + (3,))
        for v in self.vibration:
            m = (t > v.start) & (t < v.start + v.duration)
            if not m.any():
                continue
            tt = t[m]
            w, dw = v.envelope(tt)
            for tn in v.tones:
                k = _AXIS[tn.axis]
                om = 2.0 * math.pi * tn.frequency
                arg = om * tt + tn.phase
                if tn.kind == "angular":
                    ang[m, k] += w * tn.amplitude * np.sin(arg)
                    dang[m, k] += tn.amplitude * (dw * np.sin(arg) + w * om * np.cos(arg))
                else:
                    vb[m, k] += -w * tn.amplitude / om * np.cos(arg)
                    ab[m, k] += tn.amplitude * (-dw / om * np.cos(arg) + w * np.sin(arg))
        return ang, dang, vb, ab

    def _motion(self, t):
        """Velocity, its rate, attitude and body rate (no position)."""
        s, ds = self.speed.evaluate(t)
        psi, dpsi = self.heading.evaluate(t)
        th, dth = self.pitch.evaluate(t)
        ph, dph = self.roll.evaluate(t)
        cp, sp, ct, st = np.cos(psi), np.sin(psi), np.cos(th), np.sin(th)
        u = np.stack([ct * cp, ct * sp, -st], axis=-1)
        du = np.stack([-st * cp * dth - ct * sp * dpsi, -st * sp * dth + ct * cp * dpsi, -ct * dth], axis=-1)
        v_n = s[:, None] * u
        dv_n = ds[:, None] * u + s[:, None] * du
        ang, dang, vb, ab = self._vibration(t)
        roll, pitch, yaw = ph + ang[:, 0], th + ang[:, 1], psi + ang[:, 2]
        droll, dpitch, dyaw = dph + dang[:, 0], dth + dang[:, 1], dpsi + dang[:, 2]
        q = quat.from_euler(roll, pitch, yaw)
        sr, cr = np.sin(roll), np.cos(roll)
        spp, cpp = np.sin(pitch), np.cos(pitch)
        w_nb = np.stack([droll - dyaw * spp, dpitch * cr + dyaw * sr * cpp, -dpitch * sr + dyaw * cr * cpp], -1)
        if self.vibration:
            C = quat.dcm(q)
            v_n = v_n + np.einsum("kij,kj->ki", C, vb)
            dv_n = dv_n + np.einsum("kij,kj->ki", C, ab + np.cross(w_nb, vb))
        return v_n, dv_n, q, w_nb

    # ---- position ----------------------------------------------------------
    def _integrate(self):
        x, w = np.polynomial.legendre.leggauss(_NODES)
        u = 0.5 * (1.0 + x)
        self._u, self._w = u, 0.5 * w
        # integrated Lagrange basis through the nodes: B_j(s) = ∫_0^s ℓ_j, as polynomial coefficients
        V = np.vander(u, _NODES, increasing=True)                       # ℓ_j = Σ_p c_pj s^p
        coef = np.linalg.solve(V, np.eye(_NODES))                        # (p, j)
        icoef = np.zeros((_NODES + 1, _NODES))
        icoef[1:] = coef / np.arange(1, _NODES + 1)[:, None]
        self._icoef = icoef
        S = np.vander(u, _NODES + 1, increasing=True) @ icoef            # (i, j): ∫_0^{u_i} ℓ_j
        a = self._knots[:-1]
        d = np.diff(self._knots)
        self._dk = d
        tn = (a[:, None] + d[:, None] * u[None, :]).ravel()
        v_n = self._motion(tn)[0].reshape(a.size, _NODES, 3)
        K = a.size

        def integrate(g, x0):
            knot = x0 + np.concatenate([[0.0], np.cumsum(d * (g @ self._w))])
            nodes = knot[:-1, None] + d[:, None] * (g @ S.T)
            return knot, nodes

        gh = -v_n[..., 2]
        h_k, h_nodes = integrate(gh, self.h0)
        lat_nodes = np.full((K, _NODES), self.lat0)
        # Picard sweeps until the change is at round-off (the latitude feeds back only through R_M: a
        # contraction of ~0.02 × distance / R_E per sweep); never left unconverged
        for _ in range(_PICARD_MAX):
            rm, _rn = earth.radii(lat_nodes)
            gL = v_n[..., 0] / (rm + h_nodes)
            L_k, new = integrate(gL, self.lat0)
            change = float(np.max(np.abs(new - lat_nodes)))
            lat_nodes = new
            tol = 4.0 * np.finfo(float).eps * max(1.0, float(np.max(np.abs(lat_nodes))))
            if change <= tol:
                break
        else:
            raise TrajectoryError(self.where, f"the latitude did not converge in {_PICARD_MAX} Picard iterations "
                                  f"(last change {change:.3g} rad, round-off {tol:.3g} rad)")
        beyond = ~(np.abs(lat_nodes).max(axis=1) < np.radians(89.9))
        if beyond.any():
            k = int(np.argmax(beyond))                                  # the first knot interval beyond
            lat_k = lat_nodes[k][np.argmax(np.abs(lat_nodes[k]))]
            raise TrajectoryError(self.where, f"the flight reaches latitude {np.degrees(lat_k):.6g} deg near "
                                  f"t = {self._knots[k]:.6g} s, beyond ±89.9 deg (the NED frame is singular at the "
                                  "poles)")
        rm, rn = earth.radii(lat_nodes)
        gL = v_n[..., 0] / (rm + h_nodes)
        gl = v_n[..., 1] / ((rn + h_nodes) * np.cos(lat_nodes))
        gd = np.linalg.norm(v_n, axis=-1)
        l_k, _ = integrate(gl, self.lon0)
        d_k, _ = integrate(gd, 0.0)
        self._pos = {"h": (h_k, gh), "lat": (L_k, gL), "lon": (l_k, gl), "distance": (d_k, gd)}

    def position(self, t):
        """Latitude, longitude, height and distance at times ``t``."""
        k = np.clip(np.searchsorted(self._knots, t, side="right") - 1, 0, self._dk.size - 1)
        s = (t - self._knots[k]) / self._dk[k]
        B = np.vander(s, _NODES + 1, increasing=True) @ self._icoef      # (N, j)
        out = {}
        for key, (knot, g) in self._pos.items():
            out[key] = knot[k] + self._dk[k] * np.einsum("nj,nj->n", B, g[k])
        return out

    def evaluate(self, t):
        """Trajectory fields (except ``t``) at times ``t``."""
        t = np.asarray(t, dtype=float)
        v_n, dv_n, q, w_nb = self._motion(t)
        p = self.position(t)
        f_b, w_ib_b = inverse_mechanization(p["lat"], p["h"], v_n, dv_n, q, w_nb)
        return dict(lat=p["lat"], lon=p["lon"], h=p["h"], v_n=v_n, q_nb=q, f_b=f_b, w_ib_b=w_ib_b,
                    distance=p["distance"])


def flight(segments, *, lat, lon, h, heading=0.0, pitch=0.0, vibration=(), dt=0.1, name="flight",
           where="flight") -> Trajectory:
    """A flight profile as a Trajectory.

    Parameters
    ----------
    segments : sequence of Segment
    lat, lon, h, heading, pitch : float
        Start position and attitude (roll 0). [rad], [m]
    vibration : sequence of VibrationInterval
    dt : float
        Step of the returned grid (sampling is exact at any time). [s]
    name, where : str
        Label and error-message prefix.

    Returns
    -------
    Trajectory
        With ``_source`` the :class:`FlightProfile`; its ``max_frequency``
        tells an IMU simulator how many quadrature nodes it needs.
    """
    if not (math.isfinite(dt) and dt > 0):
        raise TrajectoryError(f"{where}: dt", f"must be positive, got {dt!r}")
    prof = FlightProfile(segments, lat=lat, lon=lon, h=h, heading=heading, pitch=pitch, vibration=vibration,
                         where=where)
    t = grid_times(*prof.span, dt)
    return Trajectory(t=t, **prof.evaluate(t), stationary=prof.stationary(), name=name, _source=prof)


def quadrature_nodes(traj, rate: float, minimum: int = 3, tol: float = 1e-13) -> int:
    """Gauss–Legendre nodes per IMU sample for a flight's vibration.

    Parameters
    ----------
    traj : Trajectory
        A flight (its profile's ``max_frequency``) or any other trajectory
        (no vibration: ``minimum``).
    rate : float
        IMU sample rate. [Hz]
    minimum : int
    tol : float
        Bound on ``(λ/2)^{2n}/(2n)!`` with ``λ = 2π f_max / rate``, the
        relative quadrature error of the fastest tone.

    Returns
    -------
    int
        For :class:`covtool.nav.imu.simulator.ImuSimulator`'s ``nodes`` (its own automatic
        choice knows only its own vibration).
    """
    fmax = float(getattr(traj._source, "max_frequency", 0.0) or 0.0)
    lam = 2.0 * math.pi * fmax / float(rate)
    n = int(minimum)
    while n < 24 and (0.5 * lam) ** (2 * n) / math.factorial(2 * n) > tol:
        n += 1
    return n
