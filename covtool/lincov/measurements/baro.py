"""Barometric altitude with a Markov bias and a scale factor; heading."""

from __future__ import annotations

import numpy as np

from covtool.lincov.measurements.base import heading, heading_jacobian, I_Q, Measurement


class Baro(Measurement):
    """Barometric altitude ``sensor = (1 + k) h + b``; ``predict = ĥ``.

    The bias ``b`` (usually Markov: weather) and scale factor ``k`` are the
    optional states ``<name>_bias`` and ``<name>_scale_factor``.  Aiding the
    height damps the unstable vertical channel (``cosh √2 ω_s t`` unaided).
    """

    DIMENSION = "length"
    kind = "baro"
    COMPONENTS = ("h",)
    ERRORS = {"bias": ("length", "barometric altitude bias"),
              "scale_factor": ("dimensionless", "barometric altitude scale-factor error")}
    ref = "issue 15 (barometric altitude)"

    def predict(self, x, w):
        return x[..., 2:3]

    def sensor(self, x, w, e):
        return np.asarray((1.0 + self.error_value(e, "scale_factor")) * x[2] + self.error_value(e, "bias"))[..., None]

    def nav_jacobian(self, x, w):
        J = np.zeros((1, 10))
        J[0, 2] = 1.0
        return J

    def error_jacobian(self, x, w):
        col = {"bias": 1.0, "scale_factor": float(x[2])}
        return np.array([[col[s.name[len(self.name) + 1:]] for s in self.states]]).reshape(1, -1)


class Heading(Measurement):
    """Heading ``sensor = ψ + b`` (magnetometer-like with bias, or an azimuth mark without)."""

    DIMENSION = "angle"
    kind = "heading"
    COMPONENTS = ("psi",)
    ERRORS = {"bias": ("angle", "heading sensor bias")}
    ref = "issue 15 (heading / azimuth mark)"

    def predict(self, x, w):
        return np.asarray(heading(x[..., I_Q]))[..., None]

    def sensor(self, x, w, e):
        return np.asarray(heading(x[I_Q]) + self.error_value(e, "bias"))[..., None]

    def innovation(self, x, w, xh, e):
        r = super().innovation(x, w, xh, e)
        return (r + np.pi) % (2 * np.pi) - np.pi        # a heading difference, not an angle

    def nav_jacobian(self, x, w):
        J = np.zeros((1, 10))
        J[0, I_Q] = heading_jacobian(x[I_Q])
        return J

    def error_jacobian(self, x, w):
        return np.ones((1, len(self.states)))
