"""ZUPT: zero velocity at a stop (seed 002, §2.3), generalised to the library's form."""

from __future__ import annotations

import numpy as np

from covtool.lincov.measurements.base import I_VEL, Measurement


class Zupt(Measurement):
    """Zero-velocity update: the INS velocity against the true (zero) velocity.

    ``predict = V̂^n``, ``sensor = V^n`` (zero at a stop), so ``H`` is the
    velocity-error rows of seed 002's ZUPT (:func:`covtool.lincov.reduced.zupt_matrices`).
    """

    DIMENSION = "velocity"
    kind = "zupt"
    COMPONENTS = ("V_N", "V_E", "V_D")
    ref = "seed 002, §2.3 (ZUPT), eq (7), (16)"

    def predict(self, x, w):
        return x[..., I_VEL]

    def sensor(self, x, w, e):
        return x[I_VEL]

    def nav_jacobian(self, x, w):
        J = np.zeros((3, 10))
        J[:, I_VEL] = np.eye(3)
        return J
