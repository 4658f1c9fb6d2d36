"""CUPT: a coordinate update at a surveyed point (PADS, MAPS; seed 002 refs [2]–[4])."""

from __future__ import annotations

from covtool.lincov.measurements.base import (antenna_position, antenna_position_jacobian, Measurement,
                                              ned_metres)


class Cupt(Measurement):
    """Position fix of a body-fixed reference point (lever arm) at a survey mark.

    ``predict`` is the geodetic position of the reference point from the INS,
    ``sensor`` the surveyed coordinates of the mark (the true position of the
    point: the survey error is white, σ per NED axis); the residual is in
    NED metres (``M = diag(R_M + h, (R_N + h) cos L, −1)`` at the mark).
    """

    DIMENSION = "length"
    kind = "cupt"
    COMPONENTS = ("N", "E", "D")
    LEVER = True
    ref = "seed 002 refs [2]-[4] (PADS/MAPS coordinate updates)"

    def predict(self, x, w):
        return antenna_position(x, self.lever_arm)

    def sensor(self, x, w, e):
        return antenna_position(x, self.lever_arm)

    def nav_jacobian(self, x, w):
        return antenna_position_jacobian(x, self.lever_arm)

    def scale(self, x):
        return ned_metres(x)
