"""Odometer: along-track speed with scale-factor and boresight error states; NHC."""

from __future__ import annotations

import numpy as np

from covtool.lincov.measurements.base import body_velocity, body_velocity_jacobian, Measurement


class Odometer(Measurement):
    """Along-track speed of the wheel point, with scale factor and boresight errors.

    ``sensor = (1 + s_c + s_m) a(θ, ψ)·v_b`` with ``v_b = C_nᵇ V^n + ω_ib^b × l``
    (:func:`body_velocity`) and the odometer axis
    ``a = [cos θ cos ψ, cos θ sin ψ, −sin θ]`` misaligned from body x by the
    boresight pitch θ and yaw ψ; ``predict = v_b,x`` (the INS assumes an
    ideal odometer along body x).
    """

    DIMENSION = "velocity"
    kind = "odometer"
    COMPONENTS = ("along",)
    LEVER = True
    ERRORS = {"scale_factor": ("dimensionless", "odometer scale-factor error (random constant)"),
              "scale_factor_markov": ("dimensionless", "odometer scale-factor error, correlated part"),
              "boresight_pitch": ("angle", "odometer boresight misalignment, pitch"),
              "boresight_yaw": ("angle", "odometer boresight misalignment, yaw")}
    ref = "issue 15 (odometer; MAPS, seed 002 ref [4])"

    def predict(self, x, w):
        return body_velocity(x, w, self.lever_arm)[..., :1]

    def sensor(self, x, w, e):
        s = 1.0 + self.error_value(e, "scale_factor") + self.error_value(e, "scale_factor_markov")
        th, ps = self.error_value(e, "boresight_pitch"), self.error_value(e, "boresight_yaw")
        a = np.stack(np.broadcast_arrays(np.cos(th) * np.cos(ps), np.cos(th) * np.sin(ps), -np.sin(th)), axis=-1)
        return np.asarray(s * (a @ body_velocity(x, w, self.lever_arm)))[..., None]

    def nav_jacobian(self, x, w):
        return body_velocity_jacobian(x, w, self.lever_arm)[:1]

    def error_jacobian(self, x, w):
        vb = body_velocity(x, w, self.lever_arm)
        col = {"scale_factor": vb[0], "scale_factor_markov": vb[0], "boresight_pitch": -vb[2],
               "boresight_yaw": vb[1]}
        return np.array([[col[s.name[len(self.name) + 1:]] for s in self.states]]).reshape(1, -1)


class NonHolonomic(Measurement):
    """Non-holonomic constraint: zero lateral and vertical velocity of a wheel point.

    ``predict = [v_b,y, v_b,z]`` from the INS, ``sensor`` the true ones
    (zero for a vehicle that neither slides nor jumps; the violation is the
    white noise σ).
    """

    DIMENSION = "velocity"
    kind = "nhc"
    COMPONENTS = ("lateral", "vertical")
    LEVER = True
    ref = "issue 15 (non-holonomic constraint)"

    def predict(self, x, w):
        return body_velocity(x, w, self.lever_arm)[..., 1:]

    def sensor(self, x, w, e):
        return body_velocity(x, w, self.lever_arm)[1:]

    def nav_jacobian(self, x, w):
        return body_velocity_jacobian(x, w, self.lever_arm)[1:]
