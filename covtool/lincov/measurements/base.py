"""Common machinery of the measurement library: error states, the residual, H by name.

Conventions (the same as the error model, seed 002 eq (14)):

* the navigation error ``δx = x̂ − x`` (computed minus true) over
  ``x = [L, l, h, V_N, V_E, V_D, q0, q1, q2, q3]`` (:data:`NAV_POINT`), the
  additive quaternion error entering through the *normalised* quaternion
  (as :func:`covtool.nav.attitude.dcm` does);
* every kind declares ``predict(x, w)``: what the INS predicts the sensor
  reads from its own navigation state (no sensor error), and
  ``sensor(x, w, e)``: what the sensor reads at the true state ``x`` with its
  own error states ``e`` (noise-free; the white noise of covariance R is
  added on top);
* the residual (innovation) is ``z = M (predict(x + δx) − sensor(x, e)) − v``
  with ``M`` a fixed scaling at the true point (metres for a position fix),
  and the truth measurement matrix is its Jacobian::

      H = [M ∂predict/∂x ,  −M ∂sensor/∂e]          (m × (10 + n_e))

  so that ``z ≈ H [δx; e] − v``: seed 002 eq (7), (16) with the truth H
  including the measurement-error states.  ``w`` is the body rate ``ω_ib^b``
  of the trajectory (lever-arm velocity; the gyro errors' effect on it,
  below 1e-5 m/s per metre of lever arm for a 1 deg/h gyro, is neglected).

Error states are :class:`covtool.lincov.model.spec.State` objects (names,
σ, process, datasheet unit), so filters keep or drop them by name like any
other state.
"""

from __future__ import annotations

import abc
import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from covtool.lincov.discretize.scalar import transition  # noqa: F401 - re-exported (measurements.transition)
from covtool.lincov.model.spec import State
from covtool.nav import attitude as quat, earth

#: nonlinear navigation point ``x`` (and error state ``δx``) layout, seed 002 eq (14)
NAV_POINT = ("L", "l", "h", "V_N", "V_E", "V_D", "q0", "q1", "q2", "q3")
I_POS, I_VEL, I_Q = slice(0, 3), slice(3, 6), slice(6, 10)
#: processes a measurement-error state may follow
MEAS_PROCESSES = ("constant", "markov", "random_walk")


def nav_point(traj, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``(x, w)`` of sample ``k`` of a trajectory: the 10-vector and ``ω_ib^b``.

    Parameters
    ----------
    traj : covtool.nav.trajectory.core.Trajectory
    k : int

    Returns
    -------
    x : ndarray, shape (10,)
        ``[L, l, h, V_N, V_E, V_D, q0..q3]`` [rad, rad, m, m/s, -]
    w : ndarray, shape (3,)
        Body rate. [rad/s]
    """
    x = np.concatenate([[traj.lat[k], traj.lon[k], traj.h[k]], traj.v_n[k], traj.q_nb[k]])
    return x, np.asarray(traj.w_ib_b[k], float)


def body_velocity(x, w, lever):
    """Velocity of a body-fixed point, body axes: ``C_nᵇ v^n + ω × l``, shape (..., 3). [m/s]

    ``x`` of shape (..., 10) (:func:`nav_point`), a stack of points (the runs of a Monte Carlo).
    """
    v = x[..., I_VEL]
    return (v[..., None, :] @ quat.dcm(x[..., I_Q]))[..., 0, :] + np.cross(w, lever)


def body_velocity_jacobian(x, w, lever) -> np.ndarray:
    """``∂ body_velocity / ∂x``, shape (3, 10)."""
    q = np.asarray(x[I_Q], float)
    J = np.zeros((3, 10))
    J[:, I_VEL] = quat.dcm(q).T
    # C(q)ᵀ v = C(q*) v with q* = [q0, −q1, −q2, −q3]
    qc = q * np.array([1.0, -1.0, -1.0, -1.0])
    J[:, I_Q] = quat.dcm_times_vector_jacobian(qc, x[I_VEL]) * np.array([1.0, -1.0, -1.0, -1.0])
    return J


def antenna_position(x, lever):
    """Geodetic position ``[L, l, h]`` of a body-fixed point at lever arm ``l^b``.

    ``r_a = r + C_b^n l``, to first order in ``|l|/R`` (a lever arm of metres
    against the Earth's radius: the neglected term is below 1e-12 m).
    ``x`` of shape (..., 10); returns shape (..., 3).
    """
    lat, h = x[..., 0], x[..., 2]
    rm, rn = earth.radii(lat)
    d = quat.dcm(x[..., I_Q]) @ lever
    return np.stack([lat + d[..., 0] / (rm + h), x[..., 1] + d[..., 1] / ((rn + h) * np.cos(lat)),
                     h - d[..., 2]], axis=-1)


def antenna_position_jacobian(x, lever) -> np.ndarray:
    """``∂ antenna_position / ∂x``, shape (3, 10)."""
    lat, h = float(x[0]), float(x[2])
    rm, rn = earth.radii(lat)
    drm, drn = earth.radii_derivatives(lat)
    q = np.asarray(x[I_Q], float)
    d = quat.dcm(q) @ lever
    Jd = quat.dcm_times_vector_jacobian(q, lever)
    cl, sl = np.cos(lat), np.sin(lat)
    J = np.zeros((3, 10))
    J[0, 0] = 1.0 - d[0] * drm / (rm + h) ** 2
    J[0, 2] = -d[0] / (rm + h) ** 2
    J[0, I_Q] = Jd[0] / (rm + h)
    den = (rn + h) * cl
    J[1, 1] = 1.0
    J[1, 0] = -d[1] * (drn * cl - (rn + h) * sl) / den**2
    J[1, 2] = -d[1] * cl / den**2
    J[1, I_Q] = Jd[1] / den
    J[2, 2] = 1.0
    J[2, I_Q] = -Jd[2]
    return J


def ned_metres(x) -> np.ndarray:
    """``M = diag(R_M + h, (R_N + h) cos L, −1)``: geodetic differences to NED metres."""
    rm, rn = earth.radii(float(np.real(x[0])))
    h = float(np.real(x[2]))
    return np.diag([rm + h, (rn + h) * np.cos(float(np.real(x[0]))), -1.0])


def heading(q):
    """True heading ψ of the 3-2-1 Euler angles of the quaternion ``q`` (shape (..., 4)), shape (...). [rad]"""
    q0, q1, q2, q3 = np.moveaxis(np.asarray(q), -1, 0)
    return np.arctan2(2 * (q1 * q2 + q0 * q3), q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3)


def heading_jacobian(q) -> np.ndarray:
    """``∂ψ/∂q``, shape (4,): ``ψ = atan2(N, D)``, ``dψ = (D dN − N dD)/(N² + D²)``."""
    q0, q1, q2, q3 = (float(v) for v in q)
    N = 2 * (q1 * q2 + q0 * q3)
    D = q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3
    dN = 2 * np.array([q3, q2, q1, q0])
    dD = 2 * np.array([q0, q1, -q2, -q3])
    return (D * dN - N * dD) / (N * N + D * D)


@dataclass(frozen=True, eq=False)
class Measurement(abc.ABC):
    """One declared measurement: kind, noise, lever arm, own error states.

    Subclasses (one per kind, :data:`covtool.lincov.measurements.KINDS`)
    implement :meth:`predict`, :meth:`sensor`, :meth:`nav_jacobian` and
    :meth:`error_jacobian`.

    Attributes
    ----------
    name : str
        Declared name; prefixes the error-state names.
    sigma : ndarray, shape (m,)
        True white-noise 1σ per component. [SI]
    states : tuple of State
        Own error states, in the kind's :attr:`ERRORS` order.
    lever_arm : ndarray, shape (3,)
        Body-frame position of the sensor point from the IMU. [m]
    filter_sigma : ndarray, shape (m,) or None
        1σ the filters assume; default ``sigma``.
    """

    name: str
    sigma: np.ndarray
    states: tuple = ()
    lever_arm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    filter_sigma: np.ndarray | None = None

    kind: ClassVar[str] = ""
    #: component labels of the measurement
    COMPONENTS: ClassVar[tuple] = ()
    #: error states a kind supports: suffix -> (dimension, meaning)
    ERRORS: ClassVar[dict] = {}
    #: physical dimension of the measurement components (covtool.units.DIMENSIONS)
    DIMENSION: ClassVar[str] = ""
    #: whether the kind takes a lever arm
    LEVER: ClassVar[bool] = False
    ref: ClassVar[str] = ""

    @property
    def m(self) -> int:
        return len(self.COMPONENTS)

    @property
    def state_names(self) -> list[str]:
        return [s.name for s in self.states]

    def error_index(self, suffix: str) -> int | None:
        """Position of the error state ``suffix`` among :attr:`states`, or None if not declared."""
        name = f"{self.name}_{suffix}"
        return next((i for i, s in enumerate(self.states) if s.name == name), None)

    def error_value(self, e, suffix: str):
        """The error state ``suffix`` of ``e`` (shape (..., n_e)), shape (...); 0 if not declared."""
        i = self.error_index(suffix)
        return 0.0 if i is None else e[..., i]

    # -- each kind implements these (an abstract base: a kind missing one cannot be built) ----------
    @abc.abstractmethod
    def predict(self, x, w):
        """What the INS expects the sensor to read at its own state ``x`` and sample ``w``.

        ``x`` of shape (10,) or a stack (..., 10) (the runs of a Monte Carlo); returns shape (..., m).
        """

    @abc.abstractmethod
    def sensor(self, x, w, e):
        """What the sensor reads at the true state ``x`` (shape (10,)) with its own errors ``e``.

        ``e`` of shape (n_e,) or a stack (..., n_e); returns shape (..., m), or (m,) for a kind whose
        reading does not depend on ``e``.
        """

    @abc.abstractmethod
    def nav_jacobian(self, x, w) -> np.ndarray:
        """``∂ predict / ∂(navigation error)`` in the truth model's navigation states, shape (m, 10)."""

    def error_jacobian(self, x, w) -> np.ndarray:
        """``∂ sensor / ∂e`` at ``e = 0``, shape (m, n_e)."""
        return np.zeros((self.m, 0))

    def scale(self, x) -> np.ndarray:
        """Residual scaling ``M`` at the true point, shape (m, m) (identity by default)."""
        return np.eye(self.m)

    # -- common -------------------------------------------------------------------------
    def innovation(self, x, w, xh, e):
        """``M (predict(x̂) − sensor(x, e))`` for a stack of estimates, shape (..., m).

        Parameters
        ----------
        x : ndarray, shape (10,)
            True navigation point (:data:`NAV_POINT`).
        w : ndarray, shape (3,)
            Body rate ``ω_ib^b``. [rad/s]
        xh : ndarray, shape (..., 10)
            Navigation points the INS computes (a Monte Carlo's runs).
        e : ndarray, shape (..., n_e)
            Values of the measurement's own error states, per estimate.
        """
        return (self.predict(xh, w) - self.sensor(x, w, e)) @ self.scale(x).T

    def residual(self, x, w, dx, e):
        """Nonlinear residual ``M (predict(x + δx) − sensor(x, e))``, shape (m,).

        Parameters
        ----------
        x : ndarray, shape (10,)
            True navigation point (:data:`NAV_POINT`).
        w : ndarray, shape (3,)
            Body rate ``ω_ib^b``. [rad/s]
        dx : ndarray, shape (10,)
            Navigation error (computed − true).
        e : ndarray, shape (n_e,)
            Values of the measurement's own error states.
        """
        return self.innovation(x, w, x + dx, e)

    def jacobian(self, x, w) -> tuple[np.ndarray, np.ndarray]:
        """``(H_nav, H_err)``: the truth H over ``δx`` and the own error states.

        Returns
        -------
        H_nav : ndarray, shape (m, 10)
        H_err : ndarray, shape (m, n_e)
        """
        M = self.scale(x)
        return M @ self.nav_jacobian(x, w), -M @ self.error_jacobian(x, w)

    def geometry_key(self) -> tuple:
        """What :meth:`jacobian` depends on besides the trajectory: the kind and every field but the noise 1σ.

        Two measurements with equal keys have equal Jacobians at every point
        (``sigma`` and ``filter_sigma`` enter R and R_f only, never H: seed
        002, eq (14)); a σ sweep's scaled copies share them
        (:class:`covtool.lincov.aided.Jacobians`).
        """
        def frozen(v):
            if isinstance(v, np.ndarray):
                return ("array", v.shape, v.dtype.str, v.tobytes())
            if isinstance(v, (tuple, list)):
                return (type(v).__name__,) + tuple(frozen(u) for u in v)
            return repr(v)                   # dataclasses (the error states), numbers, text: exact reprs

        return (type(self),) + tuple((f.name, frozen(getattr(self, f.name))) for f in dataclasses.fields(self)
                                     if f.name not in ("sigma", "filter_sigma"))

    def R(self) -> np.ndarray:
        """True measurement-noise covariance, shape (m, m)."""
        return np.diag(np.asarray(self.sigma, float) ** 2)

    def Rf(self) -> np.ndarray:
        """Measurement-noise covariance the filters assume, shape (m, m)."""
        s = self.sigma if self.filter_sigma is None else self.filter_sigma
        return np.diag(np.asarray(s, float) ** 2)


def error_state(meas: str, kind: str, suffix: str, sigma: float, process: str = "constant", *,
                tau: float | None = None, rw: float = 0.0, unit: str = "", source: str = "") -> State:
    """An own error state of measurement ``meas``, declared like a model block's state.

    Parameters
    ----------
    meas : str
        Measurement name (the state is ``<meas>_<suffix>``).
    kind : str
        Measurement kind (:data:`covtool.lincov.measurements.KINDS`).
    suffix : str
        One of the kind's ``ERRORS``.
    sigma : float
        Initial (and, for a Markov state, steady) 1σ. [SI]
    process : {"constant", "markov", "random_walk"}
    tau : float, optional
        Markov correlation time. [s]
    rw : float
        Random-walk intensity. [SI/√s]

    Raises
    ------
    ValueError
        Unknown suffix or process, or a Markov state without a positive τ
        (the study layer reports these as one-line file errors first).
    """
    from covtool.lincov.measurements import KINDS
    errors = KINDS[kind].ERRORS
    if suffix not in errors:
        raise ValueError(f"{kind} has no error state {suffix!r} (known: {', '.join(errors) or 'none'})")
    if process not in MEAS_PROCESSES:
        raise ValueError(f"process {process!r} is not one of {', '.join(MEAS_PROCESSES)}")
    if process == "markov" and not (tau is not None and tau > 0):
        raise ValueError("a Markov state needs a positive correlation time tau")
    dim, meaning = errors[suffix]
    return State(name=f"{meas}_{suffix}", symbol=f"{meas}.{suffix}", block=meas, kind=f"measurement:{kind}",
                 meaning=meaning, dimension=dim, unit=unit, sigma=float(sigma), process=process,
                 tau=tau, rw=float(rw), source=source)


def place(H_nav: np.ndarray, H_err: np.ndarray, meas: Measurement, names) -> np.ndarray:
    """Truth or filter H over the state ``names`` (by name), shape (m, len(names)).

    The navigation columns are the first ten states (seed 002, eq (14)); an
    own error state the state vector does not hold is dropped from H (a
    filter that does not model it: its H is the truth H restricted to the
    kept states, ``H_f = H D``).
    """
    names = list(names)
    H = np.zeros((H_nav.shape[0], len(names)))
    H[:, :10] = H_nav
    pos = {s: i for i, s in enumerate(names)}
    for j, s in enumerate(meas.state_names):
        if s in pos:
            H[:, pos[s]] = H_err[:, j]
    return H
