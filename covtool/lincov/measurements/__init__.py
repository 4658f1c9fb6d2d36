"""Measurement library: one declared block per aiding kind (issue 15).

Each kind (:data:`KINDS`) has its nonlinear measurement function (``predict``
from the INS, ``sensor`` from the truth with its own error states), its truth
H including those states, and the filter H by name (:func:`place`).  See
:mod:`covtool.lincov.measurements.base` for the conventions and
``docs/aiding.md`` for the equations.
"""

from covtool.lincov.measurements.base import (Measurement, MEAS_PROCESSES, nav_point, NAV_POINT, place,
                                              transition)
from covtool.lincov.measurements.baro import Baro, Heading
from covtool.lincov.measurements.cupt import Cupt
from covtool.lincov.measurements.gnss import GnssPosition, GnssVelocity
from covtool.lincov.measurements.odometer import NonHolonomic, Odometer
from covtool.lincov.measurements.schedule import Schedule, WHEN
from covtool.lincov.measurements.zupt import Zupt

#: every measurement kind, by the name used in study files
KINDS = {c.kind: c for c in (Zupt, Cupt, Odometer, NonHolonomic, GnssPosition, GnssVelocity, Baro,
                              Heading)}

__all__ = ["KINDS", "Measurement", "MEAS_PROCESSES", "NAV_POINT", "nav_point", "place", "transition", "Schedule", "WHEN",
           "Zupt", "Cupt", "Odometer", "NonHolonomic", "GnssPosition", "GnssVelocity", "Baro", "Heading"]
