"""Recorded IMU logs in CSV: sample time, angle and velocity increments.

File format (one row per IMU sample, comma separated, header first)::

    t [s],dtheta_x [rad],dtheta_y [rad],dtheta_z [rad],dv_x [m/s],dv_y [m/s],dv_z [m/s]
    0.01,1.2e-7,-3.4e-8,5.6e-7,1.1e-4,-2.0e-4,-0.0980665
    ...

* ``t [s]`` is the end of each sample's integration period (the instant the
  IMU latches the increments), on the clock both logs share.
* ``dtheta_*`` and ``dv_*`` are the integrated gyro and accelerometer
  outputs over the period, sensor axes, SI units.
* Columns may come in any order and are matched by their header names,
  never by position; no other column is allowed.  Time must be strictly
  increasing.  Missing samples (telemetry gaps) are allowed: they are found
  and bridged by :func:`covtool.dualnav.gaps.bridge_gaps`, never dropped
  silently.
* Against the grade that produced it (:func:`check_imu_log`): no increment
  beyond the grade's range over one period, and the alignment window at
  rest (mean specific force near gravity, mean rate small), so a log whose
  header labels the wrong columns is refused, not read.

Every problem raises :class:`~covtool.errors.InputError` naming the file,
the column and the (1-based data) row.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from covtool.errors import InputError
from covtool.units import from_si
from covtool.io.csv_table import read_numeric_csv

__all__ = ["LOG_COLUMNS", "ImuLog", "load_imu_log", "save_imu_log", "nominal_period", "check_imu_log",
           "RANGE_MARGIN", "REST_FORCE_TOL", "REST_RATE_MAX"]

#: required columns, in the order written
LOG_COLUMNS = ("t [s]", "dtheta_x [rad]", "dtheta_y [rad]", "dtheta_z [rad]",
               "dv_x [m/s]", "dv_y [m/s]", "dv_z [m/s]")
#: an increment beyond ``RANGE_MARGIN × range × period`` is not a physical
#: output (the sensor saturates at its range; the margin covers the scale
#: factor, the quantisation carry and the clock rate)
RANGE_MARGIN = 1.1
#: at rest the mean specific force is gravity within this fraction
REST_FORCE_TOL = 0.1
#: at rest the mean body rate is below this (Earth rate plus any gyro bias) [rad/s]
REST_RATE_MAX = 0.01


@dataclass(frozen=True)
class ImuLog:
    """A recorded IMU log.

    Attributes
    ----------
    path : str
        File it was read from.
    t : ndarray, shape (K,)
        Sample end times, strictly increasing. [s]
    dtheta, dv : ndarray, shape (K, 3)
        Angle and velocity increments. [rad], [m/s]
    """

    path: str
    t: np.ndarray
    dtheta: np.ndarray
    dv: np.ndarray

    @property
    def period(self) -> float:
        """Nominal sample period (the median step). [s]"""
        return nominal_period(self.t)


def nominal_period(t) -> float:
    """Median step of a time column (robust to gaps). [s]"""
    return float(np.median(np.diff(np.asarray(t, float))))


def load_imu_log(path, *, max_bytes: int | None = None) -> ImuLog:
    """Read and validate an IMU log.

    Parameters
    ----------
    path : str or Path
    max_bytes : int, optional
        Largest file read (:data:`covtool.io.csv_table.MAX_BYTES`). [bytes]

    Returns
    -------
    ImuLog

    Raises
    ------
    InputError
        Naming the file, the column and the row: file not found or not CSV,
        larger than the limit, missing or unknown or duplicated columns,
        fewer than 2 rows, a truncated line, an empty, non-numeric or
        non-finite value, time not strictly increasing.
    """
    where = str(path)
    data = read_numeric_csv(path, LOG_COLUMNS, error=InputError, max_bytes=max_bytes)
    t = data["t [s]"]
    dth = np.column_stack([data[c] for c in LOG_COLUMNS[1:4]])
    dv = np.column_stack([data[c] for c in LOG_COLUMNS[4:7]])
    return ImuLog(where, t, dth, dv)


def check_imu_log(log: ImuLog, *, period: float, gyro_range=None, accel_range=None, align_time: float = 0.0,
                  gravity: float | None = None, label: str = "IMU") -> None:
    """Refuse a log whose values no IMU of its grade can output.

    Parameters
    ----------
    log : ImuLog
    period : float
        Nominal sample period of the grade. [s]
    gyro_range, accel_range : float or None
        The grade's rate range [rad/s] and specific-force range [m/s²]
        (:attr:`covtool.io.imu_grade.ImuGrade.range`); None skips the check.
    align_time : float
        Span at the start of the log during which the vehicle is at rest
        (the alignment); 0 skips the rest check. [s]
    gravity : float, optional
        Magnitude of gravity at the alignment site (needed with
        ``align_time``). [m/s²]
    label : str
        The grade's role in messages (``"main"``, ``"kimu"``).

    Raises
    ------
    InputError
        Naming the log's file, the column and the row: an increment beyond
        :data:`RANGE_MARGIN` × range × period; or, over the alignment
        window, a mean specific force that is not gravity within
        :data:`REST_FORCE_TOL`, or a mean rate above :data:`REST_RATE_MAX`
        (the vehicle moved, or the header labels the wrong columns).
    """
    where = log.path
    for names, data, rng, unit, what in ((LOG_COLUMNS[1:4], log.dtheta, gyro_range, "rad", "rate"),
                                         (LOG_COLUMNS[4:7], log.dv, accel_range, "m/s", "specific-force")):
        if rng is None:
            continue
        bound = RANGE_MARGIN * float(rng) * float(period)
        bad = np.abs(data) > bound
        if bad.any():
            k, j = (int(i) for i in np.argwhere(bad)[0])
            shown = (f"{from_si(float(rng), 'deg/s'):.6g} deg/s" if unit == "rad"
                     else f"{from_si(float(rng), 'g'):.6g} g")
            raise InputError(f"{where}: column {names[j]!r}", f"row {k + 1}: {data[k, j]:.6g} {unit} is beyond what "
                             f"the {label} grade can output ({RANGE_MARGIN:g} × its {what} range {shown} × "
                             f"{period:.6g} s = {bound:.6g} {unit}): a corrupted value, or a header that labels "
                             "the wrong columns")
    if align_time > 0:
        n = int(np.searchsorted(log.t, log.t[0] + align_time - 0.5 * period, side="right"))
        T = n * float(period)
        f = np.linalg.norm(log.dv[:n].sum(axis=0)) / T
        w = np.linalg.norm(log.dtheta[:n].sum(axis=0)) / T
        if gravity is not None and abs(f - gravity) > REST_FORCE_TOL * gravity:
            raise InputError(f"{where}: columns 'dv_x [m/s]'..'dv_z [m/s]'",
                             f"rows 1-{n}: the mean specific force over the {align_time:g} s alignment is "
                             f"{f:.6g} m/s², not gravity {gravity:.6g} m/s² within {100 * REST_FORCE_TOL:g} %: the vehicle was not "
                             "at rest, or the header labels the wrong columns")
        if w > REST_RATE_MAX:
            raise InputError(f"{where}: columns 'dtheta_x [rad]'..'dtheta_z [rad]'",
                             f"rows 1-{n}: the mean rate over the {align_time:g} s alignment is {w:.6g} rad/s, more "
                             f"than {REST_RATE_MAX:g} rad/s at rest: the vehicle turned, or the header labels the "
                             "wrong columns")


def save_imu_log(path, t, dtheta, dv) -> None:
    """Write an IMU log (exact round trip with :func:`load_imu_log`).

    Parameters
    ----------
    path : str or Path
        Output file, written atomically, numbers with 17 significant digits.
    t : array_like, shape (K,)
        Sample end times. [s]
    dtheta, dv : array_like, shape (K, 3)
        Increments. [rad], [m/s]

    Raises
    ------
    ValueError
        Shapes that do not match.
    """
    from covtool.io.atomic import write_text

    t = np.asarray(t, float)
    dtheta = np.asarray(dtheta, float)
    dv = np.asarray(dv, float)
    if t.ndim != 1 or dtheta.shape != (t.size, 3) or dv.shape != (t.size, 3):
        raise ValueError(f"expected t (K,), dtheta and dv (K, 3); got {t.shape}, {dtheta.shape}, {dv.shape}")
    import io

    buf = io.StringIO()
    np.savetxt(buf, np.column_stack([t, dtheta, dv]), fmt="%.17g", delimiter=",", header=",".join(LOG_COLUMNS),
               comments="")
    write_text(path, buf.getvalue())
