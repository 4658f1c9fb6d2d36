"""The navigation state of an ensemble and its errors.

:data:`NAV_STATES` (the error-state order of seed 002, eq (14)),
:class:`NavState` (``L, l, h, v^n, q`` of M runs), :func:`truth_state`,
:func:`correct` (feedback of estimated errors) and :func:`nav_errors`
(computed − true, with the additive quaternion error ``δq = q̂ − q`` of
seed 002, eq (1)).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from covtool.nav import attitude as quat


#: error-state order of the navigation block (seed 002, eq (14))
NAV_STATES = ("dL", "dl", "dh", "dvN", "dvE", "dvD", "dq0", "dq1", "dq2", "dq3")

# --------------------------------------------------------------------------
# state
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class NavState:
    """Navigation state of M runs at one time.

    Attributes
    ----------
    t : float
        Time. [s]
    lat, lon : ndarray, shape (M,)
        Geodetic latitude and longitude. [rad]
    h : ndarray, shape (M,)
        Height above the ellipsoid. [m]
    v_n : ndarray, shape (M, 3)
        NED velocity. [m/s]
    q : ndarray, shape (M, 4)
        Attitude quaternion body→NED, scalar first (kept unit-norm, sign
        not forced, so it stays continuous).
    dtheta_prev, dv_prev : ndarray, shape (M, 3)
        Last IMU sample of the previous interval (the "1-previous" of seed
        001 eq (2), (4)). [rad], [m/s]
    """

    t: float
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    q: np.ndarray
    dtheta_prev: np.ndarray
    dv_prev: np.ndarray

    @property
    def n_runs(self) -> int:
        """Number of runs M."""
        return self.lat.shape[0]

    @classmethod
    def from_trajectory(cls, traj, t0=None, *, n_runs: int = 1, errors=None,
                        mounting=None, previous=None) -> "NavState":
        """Initial state from a trajectory, optionally with initial errors.

        Parameters
        ----------
        traj : covtool.nav.trajectory.core.Trajectory
            True motion.
        t0 : float, optional
            Start time (default: the trajectory start). [s]
        n_runs : int
            Number of runs M (ignored if ``errors`` has a run axis).
        errors : ndarray, shape (M, 10) or (10,), optional
            Initial errors in the order of :data:`NAV_STATES` (computed −
            true; e.g. ``x0[:, :10]`` sampled from a model's P0).  The
            quaternion is renormalised after adding ``δq``.
        mounting : array_like, shape (4,), optional
            Quaternion ``q_bs`` of the IMU (sensor) frame relative to the
            vehicle body; the state is then the sensor frame's attitude
            ``q_nb ⊗ q_bs``.
        previous : tuple of ndarray, optional
            ``(Δθ, Δv)`` of the sample before ``t0``, shape (3,) or (M, 3);
            zeros if omitted (exact at rest, negligible otherwise).

        Returns
        -------
        NavState
        """
        t0 = float(traj.t[0]) if t0 is None else float(t0)
        s = truth_state(traj, [t0], mounting=mounting)
        if errors is not None:
            errors = np.atleast_2d(np.asarray(errors, dtype=float))
            if errors.shape[-1] != 10:
                raise ValueError(f"errors must have 10 columns ({', '.join(NAV_STATES)}), "
                                 f"got shape {errors.shape}")
            n_runs = errors.shape[0]
        M = int(n_runs)
        lat = np.repeat(s.lat, M)
        lon = np.repeat(s.lon, M)
        h = np.repeat(s.h, M)
        v = np.repeat(s.v_n, M, axis=0)
        q = np.repeat(s.q, M, axis=0)
        if errors is not None:
            lat = lat + errors[:, 0]
            lon = lon + errors[:, 1]
            h = h + errors[:, 2]
            v = v + errors[:, 3:6]
            q = q + errors[:, 6:10]
            q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        if previous is None:
            dth_p = np.zeros((M, 3))
            dv_p = np.zeros((M, 3))
        else:
            dth_p = np.broadcast_to(np.asarray(previous[0], float), (M, 3)).copy()
            dv_p = np.broadcast_to(np.asarray(previous[1], float), (M, 3)).copy()
        return cls(t0, lat, lon, h, v, q, dth_p, dv_p)

    def replace(self, **changes) -> "NavState":
        """Copy with fields changed."""
        return dataclasses.replace(self, **changes)

    def as_vector(self) -> np.ndarray:
        """``[L, l, h, v_N, v_E, v_D, q0, q1, q2, q3]``, shape (M, 10)."""
        return np.column_stack([self.lat, self.lon, self.h, self.v_n, self.q])


def truth_state(traj, t, *, mounting=None) -> NavState:
    """True navigation state at times ``t`` (one "run" per time).

    Parameters
    ----------
    traj : covtool.nav.trajectory.core.Trajectory
    t : array_like, shape (S,)
        Strictly increasing times. [s]
    mounting : array_like, shape (4,), optional
        ``q_bs`` of the IMU frame (see :meth:`NavState.from_trajectory`).

    Returns
    -------
    NavState
        Arrays of leading length S; ``t`` is the first time.
    """
    s = traj.sample(np.atleast_1d(np.asarray(t, dtype=float)))
    q = np.array(s.q_nb)
    if mounting is not None:
        q = quat.mul(q, np.asarray(mounting, dtype=float))
    S = s.t.size
    return NavState(float(s.t[0]), np.array(s.lat), np.array(s.lon), np.array(s.h), np.array(s.v_n), q,
                    np.zeros((S, 3)), np.zeros((S, 3)))

def _unpack(state: NavState):
    return (state.lat, state.lon, state.h, *state.v_n.T, *state.q.T)


def _pack(t, x, dtheta_prev, dv_prev) -> NavState:
    return NavState(t, x[0], x[1], x[2], np.column_stack(x[3:6]), np.column_stack(x[6:10]),
                    dtheta_prev, dv_prev)

def correct(state: NavState, dx) -> NavState:
    """Feed estimated errors back into the navigation state.

    Parameters
    ----------
    state : NavState
    dx : array_like, shape (M, 10) or (10,)
        Estimated errors (computed − true) in the order of :data:`NAV_STATES`.

    Returns
    -------
    NavState
        ``x ← x − x̂`` for position, velocity and quaternion (seed 002,
        eq (10)); the quaternion is renormalised.
    """
    dx = np.asarray(dx, dtype=float)
    if dx.shape[-1] != 10 or dx.ndim > 2:
        raise ValueError(f"dx must have shape (10,) or (M, 10), got {dx.shape}")
    dx = np.broadcast_to(dx, (state.n_runs, 10))
    q = state.q - dx[:, 6:10]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return state.replace(lat=state.lat - dx[:, 0], lon=state.lon - dx[:, 1], h=state.h - dx[:, 2],
                         v_n=state.v_n - dx[:, 3:6], q=q)


def nav_errors(state: NavState, truth: NavState) -> np.ndarray:
    """Navigation errors (computed − true), shape (M, 10).

    Parameters
    ----------
    state : NavState
        Computed state of M runs.
    truth : NavState
        True state (one run broadcast, or M).

    Returns
    -------
    ndarray, shape (M, 10)
        ``[δL, δl, δh, δv_N, δv_E, δv_D, δq0…δq3]`` in the order of
        :data:`NAV_STATES`.  ``δl`` is wrapped to ±π; ``q̂`` takes the sign
        of the true quaternion before ``δq = q̂ − q`` is formed.
    """
    q = state.q
    qt = np.broadcast_to(truth.q, q.shape)
    sign = np.where(np.sum(q * qt, axis=-1) < 0, -1.0, 1.0)[:, None]
    dl = np.angle(np.exp(1j * (state.lon - truth.lon)))
    return np.column_stack([state.lat - truth.lat, dl, state.h - truth.h,
                            state.v_n - truth.v_n, sign * q - qt])
