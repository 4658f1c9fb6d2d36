"""Recorded IMU logs in CSV: sample time, angle and velocity increments.

File format (one row per IMU sample, comma separated, header first)::

    t [s],dtheta_x [rad],dtheta_y [rad],dtheta_z [rad],dv_x [m/s],dv_y [m/s],dv_z [m/s]
    0.01,1.2e-7,-3.4e-8,5.6e-7,1.1e-4,-2.0e-4,-0.0980665
    ...

* ``t [s]`` is the end of each sample's integration period (the instant the
  IMU latches the increments), on the clock both logs share.
* ``dtheta_*`` and ``dv_*`` are the integrated gyro and accelerometer
  outputs over the period, sensor axes, SI units.
* Columns may come in any order; no other column is allowed.  Time must be
  strictly increasing.  Missing samples (telemetry gaps) are allowed: they
  are found and bridged by :func:`covtool.dualnav.bridge_gaps`, never
  dropped silently.

Every problem raises :class:`~covtool.errors.InputError` naming the file,
the column and the (1-based data) row.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .csv_table import read_numeric_csv

__all__ = ["LOG_COLUMNS", "ImuLog", "load_imu_log", "save_imu_log", "nominal_period"]

#: required columns, in the order written
LOG_COLUMNS = ("t [s]", "dtheta_x [rad]", "dtheta_y [rad]", "dtheta_z [rad]",
               "dv_x [m/s]", "dv_y [m/s]", "dv_z [m/s]")


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


def load_imu_log(path) -> ImuLog:
    """Read and validate an IMU log.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    ImuLog

    Raises
    ------
    InputError
        Naming the file, the column and the row: file not found or not CSV,
        missing or unknown or duplicated columns, fewer than 2 rows, an
        empty, non-numeric or non-finite value, time not strictly
        increasing.
    """
    where = str(path)
    data = read_numeric_csv(path, LOG_COLUMNS, error=InputError)
    t = data["t [s]"]
    dth = np.column_stack([data[c] for c in LOG_COLUMNS[1:4]])
    dv = np.column_stack([data[c] for c in LOG_COLUMNS[4:7]])
    return ImuLog(where, t, dth, dv)


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
    from .atomic import write_text

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
