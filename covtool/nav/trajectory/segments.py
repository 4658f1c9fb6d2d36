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
``q = from_euler(0, θ, ψ)``; all are analytic in time.

Position
--------
Position is the only integrated quantity (:func:`covtool.nav.earth.position_rates`)::

    h = h0 + ∫ s sin θ,   L = L0 + ∫ s cos θ cos ψ / (R_M(L) + h),
    l = l0 + ∫ s cos θ sin ψ / ((R_N(L) + h) cos L).

It is integrated piece by piece (pieces end wherever a higher derivative
jumps) by Clenshaw–Curtis (Chebyshev spectral) integration with
Chebyshev–Picard iteration (:class:`_Profile`): each piece is cut into
sub-intervals on which the kinematic integrands are resolved to round-off
by their Chebyshev interpolants, ``h`` is their integral, the weak feedback
of ``L`` on itself through ``R_M`` is iterated to convergence, and ``l``
follows.  The integrals are kept as Chebyshev series, so
:meth:`Trajectory.sample` of a declared profile evaluates the generating
kinematics at any time to ~1e-15 relative, not an interpolation of the
time grid.
"""

from __future__ import annotations

from dataclasses import dataclass
import functools

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

# position integration (:class:`_Profile`)
#: Chebyshev–Lobatto nodes per sub-interval (the integrands are interpolated with degree _NODES − 1)
_NODES = 33
#: trailing Chebyshev coefficients that must be at round-off for a sub-interval to count as resolved
_TAIL = 3
#: round-off of a Chebyshev coefficient relative to the leading ones, per unit of max(1, |ψ|): the
#: rounding of the heading (~eps |ψ|) is the noise floor of cos ψ and sin ψ
_ROUNDOFF = 16.0 * np.finfo(float).eps
#: largest heading change of a first sub-interval [rad] (so that no long turn is aliased)
_MAX_TURN = 8.0
#: Picard iterations at most
_PICARD_MAX = 50
#: halvings of a piece at most, and sub-intervals of a profile at most
_SPLIT_MAX = 40
_SUB_MAX = 2**16
#: largest latitude [rad] (check_position's limit: the NED frame is singular at the poles)
_LAT_MAX = np.radians(89.9)


# --------------------------------------------------------------------------
# profile pieces
# --------------------------------------------------------------------------


def _ramp_value(a, b, T, tau):
    """``x(τ) = a + (b − a) S(τ/T)``, elementwise (exactly ``a`` where ``a == b``)."""
    return a + (b - a) * 0.5 * (1.0 - np.cos(np.pi * tau / T))


def _ramp_rate(a, b, T, tau):
    """``dx/dτ``, elementwise."""
    return (b - a) * 0.5 * np.pi / T * np.sin(np.pi * tau / T)


def _ramp_integral(a, b, T, tau):
    """``∫_0^τ x``, elementwise (exactly ``a τ`` where ``a == b``)."""
    u = tau / T
    return a * tau + (b - a) * T * 0.5 * (u - np.sin(np.pi * u) / np.pi)


def _ramp_integral2(a, b, T, tau):
    """``∫_0^τ ∫_0^σ x``, elementwise (exactly ``a τ²/2`` where ``a == b``)."""
    u = tau / T
    return 0.5 * a * tau * tau + (b - a) * T**2 * 0.5 * (0.5 * u * u + (np.cos(np.pi * u) - 1.0) / np.pi**2)


@dataclass(frozen=True)
class _Ramp:
    """Raised-cosine step ``x(τ) = a + (b − a) S(τ/T)`` on [0, T]."""

    a: float
    b: float
    T: float

    def value(self, tau):
        return _ramp_value(self.a, self.b, self.T, tau)

    def rate(self, tau):
        return _ramp_rate(self.a, self.b, self.T, tau)

    def integral(self, tau):
        """``∫_0^τ x``."""
        return _ramp_integral(self.a, self.b, self.T, tau)

    def integral2(self, tau):
        """``∫_0^τ ∫_0^σ x``."""
        return _ramp_integral2(self.a, self.b, self.T, tau)


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
        profile = _Profile(self.pieces, self.lat0, self.lon0, self.h0, where=where)
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
    """Analytic kinematics of pieces, with integrated position.

    Parameters
    ----------
    pieces : sequence of _Piece
        Consecutive pieces (each C-infinity).
    lat0, lon0 : float
        Start position. [rad]
    h0 : float
        Start height. [m]
    where : str
        Location prefix of error messages.

    Raises
    ------
    TrajectoryError
        The position could not be integrated to round-off (the Picard
        iteration did not converge, or a piece could not be resolved by
        :data:`_SPLIT_MAX` halvings, e.g. at a pole); the message names the
        piece and its time span.

    Notes
    -----
    Position (module docstring) is integrated by Chebyshev–Picard iteration
    with Clenshaw–Curtis quadrature [1]_, [2]_, [3]_:

    1. Each piece ``[0, T]`` is cut into sub-intervals, halved until the
       Chebyshev interpolants of the kinematic integrands ``s cos θ cos ψ``,
       ``s cos θ sin ψ``, ``s sin θ`` (which do not depend on the position)
       at :data:`_NODES` Chebyshev–Lobatto points have their last
       :data:`_TAIL` coefficients at round-off relative to the largest
       [4]_.  A first cut keeps every turn below :data:`_MAX_TURN`.
    2. The interpolant of an integrand is integrated exactly (Chebyshev
       series, ``chebint``); the running integrals are chained across
       sub-intervals and pieces.  ``h`` needs no iteration; ``L`` feeds
       back into itself only through ``R_M(L)`` (contraction ~ 0.02 ×
       distance / R_E per sweep), so global Picard sweeps from ``L = L0``
       converge to round-off in a few iterations; then ``l`` is one
       integral.
    3. The latitude and longitude integrands are checked in the same way
       (``1/cos L`` on a long flight); unresolved sub-intervals are halved
       and the iteration repeated.

    Each sub-interval keeps the Chebyshev series (degree :data:`_NODES`)
    of its offsets from the position at the start of its piece
    (:attr:`pos0`), evaluated at any time by Clenshaw's recurrence.

    References
    ----------
    .. [1] C. W. Clenshaw and A. R. Curtis, "A method for numerical
       integration on an automatic computer", Numer. Math. 2, 197–205 (1960).
    .. [2] C. W. Clenshaw and H. J. Norton, "The solution of nonlinear
       ordinary differential equations in Chebyshev series", Comput. J. 6,
       88–92 (1963).
    .. [3] X. Bai and J. L. Junkins, "Modified Chebyshev–Picard iteration
       methods for orbit propagation", J. Astronaut. Sci. 58, 583–613 (2011).
    .. [4] L. N. Trefethen, *Approximation Theory and Approximation
       Practice*, SIAM (2013), ch. 3 and 19.

    Attributes
    ----------
    pieces : list of _Piece
    starts : ndarray, shape (K,)
        Start time of each piece. [s]
    span : tuple of float
        First and last time. [s]
    pos0 : ndarray, shape (K, 3)
        ``(lat [rad], lon [rad], h [m])`` at the start of each piece.
    """

    def __init__(self, pieces, lat0, lon0, h0, where="trajectory"):
        self.pieces = list(pieces)
        self.starts = np.array([p.t0 for p in self.pieces])
        self.span = (float(self.pieces[0].t0), float(self.pieces[-1].t0 + self.pieces[-1].T))
        # the pieces' parameters as arrays, for evaluating any number of pieces at once
        cols = np.array([(p.T, p.s0, p.d0, p.accel.a, p.accel.b, p.psi0, p.yaw_rate.a, p.yaw_rate.b,
                          p.pitch.a, p.pitch.b) for p in self.pieces], dtype=float)
        self._par = {key: cols[:, j].copy() for j, key in enumerate(
            ("T", "s0", "d0", "acc_a", "acc_b", "psi0", "yaw_a", "yaw_b", "th_a", "th_b"))}
        self._integrate(np.array([lat0, lon0, h0], dtype=float), where)

    # ---- kinematics -----------------------------------------------------------
    def _channels(self, k, tau, rates=True):
        """Speed, heading, pitch (and rates, distance) of pieces ``k`` at piece times ``tau``."""
        P = self._par
        T = P["T"][k]
        acc = (P["acc_a"][k], P["acc_b"][k], T)
        yaw = (P["yaw_a"][k], P["yaw_b"][k], T)
        pitch = (P["th_a"][k], P["th_b"][k], T)
        out = {"s": P["s0"][k] + _ramp_integral(*acc, tau), "psi": P["psi0"][k] + _ramp_integral(*yaw, tau),
               "theta": _ramp_value(*pitch, tau)}
        if rates:
            out.update(ds=_ramp_value(*acc, tau), dpsi=_ramp_value(*yaw, tau), dtheta=_ramp_rate(*pitch, tau),
                       d=P["d0"][k] + P["s0"][k] * tau + _ramp_integral2(*acc, tau))
        return out

    def _piece_of(self, t):
        return np.clip(np.searchsorted(self.starts, t, side="right") - 1, 0, len(self.pieces) - 1)

    def kinematics(self, t):
        """Speed, heading, pitch, their rates, distance and position.

        Parameters
        ----------
        t : array_like
            Times in the span (any, not only the grid). [s]

        Returns
        -------
        dict of ndarray, each of the shape of ``t``
            ``s`` [m/s], ``ds`` [m/s²], ``psi``, ``theta`` [rad], ``dpsi``,
            ``dtheta`` [rad/s], ``d`` [m], ``lat``, ``lon`` [rad], ``h`` [m].
        """
        t = np.asarray(t, dtype=float)
        flat = t.ravel()
        k = self._piece_of(flat)
        tau = flat - self.starts[k]
        out = self._channels(k, tau)
        pos = self.pos0[k] + self._offsets(flat, k, tau)
        out.update(lat=pos[:, 0], lon=pos[:, 1], h=pos[:, 2])
        return {key: v.reshape(t.shape) for key, v in out.items()}

    # ---- position ----------------------------------------------------------------
    def _integrands(self, piece, ta, tb):
        """Kinematic integrands at the nodes of sub-intervals, their scale and round-off.

        Returns
        -------
        F : ndarray, shape (3, M, _NODES)
            ``s cos θ cos ψ``, ``s cos θ sin ψ``, ``s sin θ``. [m/s]
        scale : ndarray, shape (M,)
            Largest Chebyshev coefficient of the three. [m/s]
        roundoff : ndarray, shape (M,)
            Relative round-off of the coefficients.
        resolved : ndarray of bool, shape (M,)
        """
        x, to_coef, _, _ = _chebyshev()
        tau = 0.5 * (ta + tb)[:, None] + 0.5 * (tb - ta)[:, None] * x
        c = self._channels(np.broadcast_to(piece[:, None], tau.shape), tau, rates=False)
        s, psi, th = c["s"], c["psi"], c["theta"]
        ch = s * np.cos(th)
        F = np.stack([ch * np.cos(psi), ch * np.sin(psi), s * np.sin(th)])
        coef = F @ to_coef.T
        scale = np.abs(coef).max(axis=(0, 2))
        roundoff = _ROUNDOFF * np.maximum(1.0, np.abs(psi).max(axis=1))
        resolved = np.all(_tail(coef) <= roundoff * scale, axis=0)
        return F, scale, roundoff, resolved

    def _integrate(self, start, where):
        """Sub-intervals, Picard iteration, and the stored Chebyshev series (class Notes)."""
        P = self._par
        K = len(self.pieces)
        # first cut: no sub-interval turns by more than _MAX_TURN
        n0 = np.maximum(1, np.ceil(np.maximum(np.abs(P["yaw_a"]), np.abs(P["yaw_b"])) * P["T"] / _MAX_TURN))
        n0 = n0.astype(int)
        piece = np.repeat(np.arange(K), n0)
        i = np.arange(piece.size) - np.repeat(np.cumsum(n0) - n0, n0)
        T = P["T"][piece]
        ta, tb = T * (i / n0[piece]), T * ((i + 1) / n0[piece])
        depth = np.zeros(piece.size, dtype=int)
        while True:
            # 1. halve until the kinematic integrands are resolved (they do not depend on the position)
            done = []
            while piece.size:
                F, scale, roundoff, ok = self._integrands(piece, ta, tb)
                done.append((piece[ok], ta[ok], tb[ok], depth[ok], F[:, ok], scale[ok], roundoff[ok]))
                count = sum(d[0].size for d in done) + 2 * int((~ok).sum())
                piece, ta, tb, depth = _halve(self, ~ok, piece, ta, tb, depth, count, where, "kinematics")
            piece, ta, tb, depth, F, scale, roundoff = zip(*done)
            order = np.lexsort((np.concatenate(ta), np.concatenate(piece)))
            piece, ta, tb, depth, scale, roundoff = (np.concatenate(a)[order]
                                                     for a in (piece, ta, tb, depth, scale, roundoff))
            F = np.concatenate(F, axis=1)[:, order]
            # 2. Picard iteration for the latitude; height and longitude are plain integrals
            G, ok = self._picard(F, piece, ta, tb, scale, roundoff, start, where)
            if ok.all():
                break
            # 3. halve where the latitude or longitude integrand is not resolved, and repeat
            keep = (piece[ok], ta[ok], tb[ok], depth[ok])
            new = _halve(self, ~ok, piece, ta, tb, depth, piece.size + int((~ok).sum()), where, "position rates")
            piece, ta, tb, depth = (np.concatenate(ab) for ab in zip(keep, new))

        # the Chebyshev series of the integrals on each sub-interval, chained
        _, _, int_coef, int_nodes = _chebyshev()
        hw = 0.5 * (tb - ta)
        total = hw * (G @ int_nodes[-1])                                  # (3, M): over each sub-interval
        off = np.concatenate([np.zeros((3, 1)), np.cumsum(total, axis=1)[:, :-1]], axis=1)
        first = np.searchsorted(piece, np.arange(K))
        self.pos0 = start + off[:, first].T                               # (K, 3)
        C = hw[:, None] * (G @ int_coef.T)                                # (3, M, _NODES + 1)
        C[..., 0] += off - off[:, first[piece]]
        self._coef = np.ascontiguousarray(C.transpose(2, 1, 0))           # (_NODES + 1, M, 3)
        self._sub_t = self.starts[piece] + ta
        self._sub_mid = 0.5 * (ta + tb)
        self._sub_hw = hw
        self._sub_first = np.append(first, piece.size)

    def _picard(self, F, piece, ta, tb, scale, roundoff, start, where):
        """Integrands of (lat, lon, h) at the nodes, and which sub-intervals resolve them.

        Returns
        -------
        G : ndarray, shape (3, M, _NODES)
            ``dL/dt`` [rad/s], ``dl/dt`` [rad/s], ``dh/dt`` [m/s] at the
            converged position.
        resolved : ndarray of bool, shape (M,)
        """
        _, to_coef, _, Q = _chebyshev()
        hw = 0.5 * (tb - ta)[:, None]

        def running(g):
            """Integral of g from the start of the trajectory, at every node."""
            rel = hw * (g @ Q.T)
            return np.concatenate([[0.0], np.cumsum(rel[:, -1])[:-1]])[:, None] + rel

        h = start[2] + running(F[2])
        lat = np.full(h.shape, start[0])
        for _ in range(_PICARD_MAX):
            rm, _ = earth.radii(lat)
            new = start[0] + running(F[0] / (rm + h))
            change = np.abs(new - lat).max(axis=1)
            lat = new
            tol = 4.0 * np.finfo(float).eps * max(1.0, float(np.abs(lat).max()))
            if change.max() <= tol:
                break
        else:
            _check_latitude(self, lat, piece, where)
            m = int(np.argmax(~(change <= tol)))          # the first sub-interval not converged
            raise TrajectoryError(where, f"{_piece_name(self, piece[m])}: the latitude did not converge in "
                                  f"{_PICARD_MAX} Picard iteration(s) (last change {change[m]:.3g} rad, "
                                  f"round-off {tol:.3g} rad)")
        _check_latitude(self, lat, piece, where)
        rm, rn = earth.radii(lat)
        G = np.stack([F[0] / (rm + h), F[1] / ((rn + h) * np.cos(lat)), F[2]])
        coef = G[:2] @ to_coef.T
        floor = scale[None, :] / np.stack([(rm + h).min(axis=1), ((rn + h) * np.cos(lat)).min(axis=1)])
        gscale = np.maximum(np.abs(coef).max(axis=2), floor)
        resolved = np.all(_tail(coef) <= roundoff * gscale, axis=0)
        return G, resolved

    def _offsets(self, t, k, tau):
        """Position offsets from :attr:`pos0` of pieces ``k``, shape (n, 3) (Clenshaw's recurrence)."""
        j = np.clip(np.searchsorted(self._sub_t, t, side="right") - 1,
                    self._sub_first[k], self._sub_first[k + 1] - 1)
        x = ((tau - self._sub_mid[j]) / self._sub_hw[j])[:, None]
        C = self._coef
        b1 = np.zeros((t.size, 3))
        b2 = np.zeros((t.size, 3))
        for c in C[:0:-1]:
            b1, b2 = c[j] + 2.0 * x * b1 - b2, b1
        return C[0][j] + x * b1 - b2

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


@functools.lru_cache(maxsize=None)
def _chebyshev(n=_NODES):
    """Chebyshev–Lobatto nodes on [−1, 1] and the Clenshaw–Curtis matrices.

    Returns
    -------
    x : ndarray, shape (n,)
        ``−cos(πj/(n−1))``, ascending.
    to_coef : ndarray, shape (n, n)
        Node values → Chebyshev coefficients of the interpolant (discrete
        orthogonality of ``T_k`` on the nodes).
    int_coef : ndarray, shape (n + 1, n)
        Node values → Chebyshev coefficients of ``∫_{−1}^x`` of the
        interpolant.
    int_nodes : ndarray, shape (n, n)
        Node values → that integral at the nodes; the last row holds the
        Clenshaw–Curtis weights.
    """
    from numpy.polynomial import chebyshev as cheb        # 2 ms, when the first profile is built

    m = n - 1
    x = -np.cos(np.pi * np.arange(n) / m)
    if n % 2:
        x[m // 2] = 0.0
    w = np.ones(n)
    w[[0, -1]] = 0.5
    to_coef = (2.0 / m) * w[:, None] * cheb.chebvander(x, m).T * w[None, :]
    int_coef = cheb.chebint(np.eye(n), lbnd=-1.0, axis=0) @ to_coef
    int_nodes = cheb.chebvander(x, n) @ int_coef
    out = (x, to_coef, int_coef, int_nodes)
    for arr in out:
        arr.flags.writeable = False                        # shared by every profile
    return out


def _tail(coef):
    """Largest of the last :data:`_TAIL` Chebyshev coefficients (last axis)."""
    return np.abs(coef[..., -_TAIL:]).max(axis=-1)


def _piece_name(profile, k):
    p = profile.pieces[k]
    return f"piece {k} (t = {p.t0:.6g} to {p.t0 + p.T:.6g} s)"


def _check_latitude(profile, lat, piece, where):
    """Refuse a latitude beyond ±89.9 deg (at the nodes ``lat`` of the sub-intervals of ``piece``)."""
    over = np.abs(lat).max(axis=1) > _LAT_MAX
    if over.any():
        m = int(np.argmax(over))
        raise TrajectoryError(where, f"{_piece_name(profile, piece[m])}: the latitude reaches "
                              f"{np.degrees(lat[m][np.argmax(np.abs(lat[m]))]):.6g} deg, beyond ±89.9 deg "
                              "(the NED frame is singular at the poles)")


def _halve(profile, bad, piece, ta, tb, depth, count, where, what):
    """The halves of the sub-intervals ``bad``.

    ``count`` is the number of sub-intervals of the profile after the
    halving; more than :data:`_SUB_MAX`, or a piece halved more than
    :data:`_SPLIT_MAX` times, is an error.
    """
    if bad.any() and (depth[bad].max() >= _SPLIT_MAX or count > _SUB_MAX):
        k = piece[bad][np.argmax(depth[bad])]
        raise TrajectoryError(where, f"{_piece_name(profile, k)}: the {what} are not resolved to round-off by "
                              f"Chebyshev series of degree {_NODES - 1} after {depth[bad].max()} halvings of the "
                              f"piece ({count} sub-intervals in all; at most {_SPLIT_MAX} halvings and {_SUB_MAX} "
                              "sub-intervals)")
    piece, ta, tb, depth = piece[bad], ta[bad], tb[bad], depth[bad] + 1
    mid = 0.5 * (ta + tb)
    return np.repeat(piece, 2), np.column_stack([ta, mid]).ravel(), np.column_stack([mid, tb]).ravel(), \
        np.repeat(depth, 2)
