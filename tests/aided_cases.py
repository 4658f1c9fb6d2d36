"""The two aided measurement set-ups the aided Monte Carlo tests share.

An odometer (scale factor and boresight-yaw error states, lever arm) with
the non-holonomic constraint, and GNSS position (first-order Markov error
states, lever arm) and velocity at 1 Hz with a 2-min outage.
"""

from __future__ import annotations

import math

import numpy as np

from covtool.lincov.measurements import GnssPosition, GnssVelocity, NonHolonomic, Odometer, Schedule
from covtool.lincov.measurements.base import error_state


def odometer_nhc():
    odo = Odometer(name="odo", sigma=np.array([0.02]), lever_arm=np.array([-1.2, 0.75, 0.9]),
                   states=(error_state("odo", "odometer", "scale_factor", 2e-3),
                           error_state("odo", "odometer", "boresight_yaw", math.radians(0.5))))
    nhc = NonHolonomic(name="nhc", sigma=np.array([0.05, 0.05]))
    sch = Schedule(period=1.0, start=1.0)
    return [(odo, sch), (nhc, sch)]


def gnss_outage():
    lever = np.array([0.5, 0.0, -1.5])
    pos = GnssPosition(name="gps", sigma=np.array([1.0, 1.0, 2.0]), lever_arm=lever,
                       states=tuple(error_state("gps", "gnss_position", a, s, "markov", tau=600.0)
                                    for a, s in zip("NED", (1.5, 1.5, 3.0))))
    vel = GnssVelocity(name="gpsv", sigma=np.full(3, 0.05), lever_arm=lever)
    sch = Schedule(period=1.0, start=1.0, outages=((150.0, 270.0),))
    return [(pos, sch), (vel, sch)]
