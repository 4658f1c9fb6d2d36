"""GNSS position and velocity at an antenna lever arm; Markov position error."""

from __future__ import annotations

import numpy as np

from covtool.lincov.measurements.base import (antenna_position, antenna_position_jacobian, I_Q, I_VEL,
                                              Measurement, ned_metres)
from covtool.nav import attitude as quat


class GnssPosition(Measurement):
    """GNSS antenna position with a first-order Gauss–Markov NED error.

    ``sensor = p_a(x) + M⁻¹ ε`` where ``p_a`` is the antenna's geodetic
    position (:func:`antenna_position`) and ``ε`` the correlated NED position
    error (states ``<name>_N``, ``<name>_E``, ``<name>_D``, each optional);
    the residual is in NED metres, so ``H_err = −I`` on the declared axes.
    """

    DIMENSION = "length"
    kind = "gnss_position"
    COMPONENTS = ("N", "E", "D")
    LEVER = True
    ERRORS = {"N": ("length", "GNSS correlated position error, north"),
              "E": ("length", "GNSS correlated position error, east"),
              "D": ("length", "GNSS correlated position error, down")}
    ref = "issue 15 (GNSS position); residual in NED metres"

    def predict(self, x, w):
        return antenna_position(x, self.lever_arm)

    def sensor(self, x, w, e):
        eps = np.stack(np.broadcast_arrays(*(self.error_value(e, a) for a in "NED")), axis=-1)
        return antenna_position(x, self.lever_arm) + np.linalg.solve(ned_metres(np.real(x)), eps[..., None])[..., 0]

    def nav_jacobian(self, x, w):
        return antenna_position_jacobian(x, self.lever_arm)

    def error_jacobian(self, x, w):
        Minv = np.linalg.inv(ned_metres(x))
        return np.stack([Minv[:, "NED".index(s.name.rsplit("_", 1)[1])] for s in self.states], 1) \
            if self.states else np.zeros((3, 0))

    def scale(self, x):
        return ned_metres(x)


class GnssVelocity(Measurement):
    """GNSS antenna velocity ``V^n + C_b^n (ω_ib^b × l)`` (white error)."""

    DIMENSION = "velocity"
    kind = "gnss_velocity"
    COMPONENTS = ("V_N", "V_E", "V_D")
    LEVER = True
    ref = "issue 15 (GNSS velocity)"

    def _v(self, x, w):
        return x[..., I_VEL] + quat.dcm(x[..., I_Q]) @ np.cross(w, self.lever_arm)

    def predict(self, x, w):
        return self._v(x, w)

    def sensor(self, x, w, e):
        return self._v(x, w)

    def nav_jacobian(self, x, w):
        J = np.zeros((3, 10))
        J[:, I_VEL] = np.eye(3)
        J[:, I_Q] = quat.dcm_times_vector_jacobian(np.asarray(x[I_Q], float), np.cross(w, self.lever_arm))
        return J
