"""Built-in trajectories: the ZUPT land-vehicle route and a static vehicle (SI arguments)."""

from __future__ import annotations

import math

import numpy as np

from covtool.errors import TrajectoryError
from covtool.nav.trajectory.core import Trajectory
from covtool.nav.trajectory.segments import check_positive, ProfileBuilder, TRANSITION

__all__ = [
    "land_vehicle", "static",
]


# --------------------------------------------------------------------------
# built-in profiles
# --------------------------------------------------------------------------

#: turn-angle signs per cycle of :func:`land_vehicle` (right positive); the
#: route visits all four cardinal headings and ends heading north
_LV_TURNS = ((+1, +1), (+1, -1), (-1, -1), (-1, +1), (+1, +1), (+1, +1))


def land_vehicle(*, dt=1.0, cycles=6, period=300.0, stop_duration=90.0, distance=15000.0,
                 accel_duration=20.0, turn_rate=math.radians(5.0), turn_angle=math.radians(90.0),
                 grade=0.04, grade_duration=60.0, lat=math.radians(36.37), lon=math.radians(127.36),
                 h=60.0, heading=0.0, name="land_vehicle", where="land_vehicle") -> Trajectory:
    """Built-in ZUPT land-vehicle route (stands in for seed 002 Fig 3).

    Each of ``cycles`` periods drives for ``period − stop_duration`` and
    then stands still for ``stop_duration``, so every stop contains a
    multiple of ``period`` (the 5-min ZUPT of seed 002).  A drive is:
    accelerate, cruise, turn, cruise, grade (climb on odd cycles, descend on
    even ones), cruise, turn, cruise, decelerate to rest.  The turns
    alternate left and right so that all four headings are visited.

    Parameters
    ----------
    dt : float
        Time step of the returned grid. [s]
    cycles : int
        Number of drive/stop cycles.
    period : float
        Cycle length (ZUPT interval). [s]
    stop_duration : float
        Standstill at the end of each cycle. [s]
    distance : float
        Total distance travelled; sets the cruise speed. [m]
    accel_duration : float
        Duration of each start and stop manoeuvre. [s]
    turn_rate, turn_angle : float
        Peak yaw rate [rad/s] and angle [rad] of every turn.
    grade : float
        Road grade (rise over run) of the hill in each drive. [-]
    grade_duration : float
        Duration of each hill, transitions included. [s]
    lat, lon : float
        Start position. [rad]
    h : float
        Start height. [m]
    heading : float
        Initial heading. [rad]
    name : str
        Label of the trajectory.
    where : str
        Location prefix of error messages (a study file's ``[trajectory]``).

    Returns
    -------
    Trajectory
        Sampled every ``dt``; :meth:`Trajectory.sample` is exact.

    Notes
    -----
    With the defaults: 1800 s, 15 km, cruise 47.4 km/h, moving-average speed
    42.9 km/h (seed 002: ~43 km/h), stops on [210, 300], ..., [1710, 1800] s,
    twelve 90-deg turns at 5 deg/s and six 4 % hills.
    """
    return land_vehicle_profile(where, dt=dt, cycles=cycles, period=period,
                         stop_duration=stop_duration, distance=distance,
                         accel_duration=accel_duration, turn_rate=turn_rate, turn_angle=turn_angle,
                         grade=grade, grade_duration=grade_duration, lat=lat, lon=lon, h=h,
                         heading=heading, name=name)


def land_vehicle_profile(where, *, dt, cycles, period, stop_duration, distance, accel_duration, turn_rate,
                  turn_angle, grade, grade_duration, lat, lon, h, heading, name):
    if isinstance(cycles, bool) or not isinstance(cycles, (int, np.integer)) or cycles < 1:
        raise TrajectoryError(f"{where}: cycles", f"{cycles!r} is not a positive integer")
    for key, val in (("period", period), ("stop_duration", stop_duration), ("distance", distance),
                     ("accel_duration", accel_duration), ("turn_rate", turn_rate),
                     ("turn_angle", turn_angle), ("grade_duration", grade_duration)):
        check_positive(val, f"{where}: {key}")
    tr_turn = TRANSITION["turn"]
    turn_T = turn_angle / turn_rate + min(tr_turn, turn_angle / turn_rate)
    drive = period - stop_duration
    spare = drive - 2.0 * accel_duration - 2.0 * turn_T - grade_duration
    if spare < 0:
        raise TrajectoryError(where, f"the drive of {drive:g} s per cycle is too short for two "
                              f"{accel_duration:g} s speed changes, two {turn_T:g} s turns and a "
                              f"{grade_duration:g} s hill")
    cruise_T = spare / 4.0
    speed = distance / (cycles * (drive - accel_duration))
    angle = math.atan(grade)
    tr_grade = min(8.0, 0.25 * grade_duration)
    b = ProfileBuilder(lat, lon, h, heading, where=where)
    for c in range(cycles):
        w = f"{where}: cycle {c + 1}"
        sign1, sign2 = _LV_TURNS[c % len(_LV_TURNS)]
        b.accelerate(speed, duration=accel_duration, where=w)
        b.cruise(cruise_T, w, allow_zero=True)
        b.turn(rate=sign1 * turn_rate, angle=sign1 * turn_angle, transition=tr_turn, where=w)
        b.cruise(cruise_T, w, allow_zero=True)
        if grade != 0:
            b.grade(angle if c % 2 == 0 else -angle, grade_duration, transition=tr_grade, where=w)
        else:
            b.cruise(grade_duration, w)
        b.cruise(cruise_T, w, allow_zero=True)
        b.turn(rate=sign2 * turn_rate, angle=sign2 * turn_angle, transition=tr_turn, where=w)
        b.cruise(cruise_T, w, allow_zero=True)
        b.accelerate(0.0, duration=accel_duration, where=w)
        b.stand(stop_duration, w)
    return b.build(dt=dt, name=name, where=where)


def static(duration=1800.0, *, lat, lon, h, heading=0.0, dt=1.0, name="static") -> Trajectory:
    """A vehicle at rest: one stationary interval over the whole span.

    Parameters
    ----------
    duration : float
        Span. [s]
    lat, lon : float
        Position. [rad]
    h : float
        Height. [m]
    heading : float
        Heading (yaw); roll and pitch are zero. [rad]
    dt : float
        Time step. [s]
    name : str
        Label.

    Returns
    -------
    Trajectory
        ``f_b = C_n^b [0, 0, −g]``, ``w_ib_b = C_n^b ω_ie^n``.
    """
    return static_profile("static", duration=duration, lat=lat, lon=lon, h=h, heading=heading, dt=dt, name=name)


def static_profile(where, *, duration, lat, lon, h, heading, dt, name):
    b = ProfileBuilder(lat, lon, h, heading, where=where)
    b.stand(duration, where)
    return b.build(dt=dt, name=name, where=where)
