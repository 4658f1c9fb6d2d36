"""Trajectory CSV files: read (validated row by row) and write (exact round trip)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from covtool.errors import TrajectoryError
from covtool.io.csv_table import read_numeric_csv
from covtool.nav import attitude as quat, earth
from covtool.nav.trajectory.core import (CSV_COLUMNS, CSV_OPTIONAL_COLUMNS, Interpolant, Trajectory,
                                         trajectory_fields, unwrap_longitude)

__all__ = [
    "load_trajectory_csv", "save_trajectory_csv", "GAP_FACTOR", "STATIONARY_FLAG_SPEED",
    "STATIONARY_FLAG_RATE",
]


#: speed below which a CSV sample counts as stationary [m/s]
STATIONARY_SPEED = 1e-3
#: body rate w.r.t. NED below which a CSV sample counts as stationary [rad/s]
STATIONARY_RATE = 1e-6
#: tolerance on |q| - 1 when loading a CSV file [-]
QUATERNION_NORM_TOL = 1e-6
#: a CSV time step longer than this many times the file's median step is a
#: gap (at least one missing sample) and is refused unless declared
GAP_FACTOR = 1.5
#: speed above which a row flagged ``stationary = 1`` is refused [m/s]
STATIONARY_FLAG_SPEED = 0.01
#: body rate w.r.t. NED above which a row flagged ``stationary = 1`` is refused [rad/s]
STATIONARY_FLAG_RATE = 1e-3
#: largest |longitude| accepted in a CSV file [deg]
MAX_CSV_LONGITUDE = 360.0


def load_trajectory_csv(path, *, max_gap: float | None = None, max_bytes: int | None = None) -> Trajectory:
    """Read a trajectory CSV file.

    Parameters
    ----------
    path : str or Path
        File with the columns :data:`CSV_COLUMNS` and optionally
        :data:`CSV_OPTIONAL_COLUMNS`, in any order (matched by name).
    max_gap : float, optional
        Longest time step that is interpolated. [s]  Default: a step longer
        than :data:`GAP_FACTOR` times the file's median step is a gap and
        is refused; give ``max_gap`` (``[trajectory] max_gap`` in a study
        file) to declare that longer steps may be interpolated.
    max_bytes : int, optional
        Largest file read (:data:`covtool.io.csv_table.MAX_BYTES`). [bytes]

    Returns
    -------
    Trajectory
        :meth:`~Trajectory.sample` interpolates it.  Longitude is unwrapped
        (each step the one nearest the east velocity's, so a file crossing
        the antimeridian interpolates the short way) and is wrapped again
        only when written.  Without a ``stationary`` column, samples with
        speed below :data:`STATIONARY_SPEED` and body rate w.r.t. NED below
        :data:`STATIONARY_RATE` form the stationary intervals (runs of at
        least two samples).  Without ``distance [m]``, the distance is the
        trapezoidal integral of the speed.  Quaternions are normalised and
        their signs made continuous.

    Raises
    ------
    TrajectoryError
        One line naming the file, the column and the row (1-based data row)
        for: everything :func:`covtool.io.csv_table.read_numeric_csv`
        refuses (missing, unknown or duplicated columns, truncated lines,
        empty, non-numeric or non-finite cells, time not strictly
        increasing, a file over the size limit); a gap in time; quaternion
        norm off by more than :data:`QUATERNION_NORM_TOL`; latitude beyond
        ±89.9°; |longitude| over :data:`MAX_CSV_LONGITUDE`; a ``stationary``
        flag that is not 0 or 1, or is 1 while the vehicle moves faster
        than :data:`STATIONARY_FLAG_SPEED` or turns faster than
        :data:`STATIONARY_FLAG_RATE` with respect to the NED frame.
    """
    path = Path(path)
    where = str(path)
    cols = read_numeric_csv(path, CSV_COLUMNS, CSV_OPTIONAL_COLUMNS, error=TrajectoryError, max_bytes=max_bytes)
    t = cols["t [s]"]
    step = np.diff(t)
    median = float(np.median(step))
    bound = GAP_FACTOR * median if max_gap is None else float(max_gap)
    long_steps = step > bound
    if long_steps.any():
        r = int(np.argmax(long_steps)) + 2
        how = (f"more than {GAP_FACTOR:g} × the file's median step {median:.6g} s" if max_gap is None
               else f"more than the declared max_gap {bound:.6g} s")
        raise TrajectoryError(f"{where}: column 't [s]'", f"row {r}: a gap of {step[r - 2]:.6g} s after t = "
                              f"{t[r - 2]:.9g} s, {how}; {int(long_steps.sum())} gap(s) in all (declare "
                              "[trajectory] max_gap to interpolate across them)")
    q = np.column_stack([cols[c] for c in ("q0", "q1", "q2", "q3")])
    norm = np.linalg.norm(q, axis=1)
    off = np.abs(norm - 1.0) > QUATERNION_NORM_TOL
    if off.any():
        r = int(np.argmax(off))
        raise TrajectoryError(f"{where}: columns 'q0'..'q3'", f"row {r + 1}: |q| = {norm[r]:.9g} is not 1 "
                              f"(tolerance {QUATERNION_NORM_TOL:g})")
    q = q / norm[:, None]
    flips = np.cumprod(np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0))
    q[1:] *= flips[:, None]
    lat, h = np.radians(cols["lat [deg]"]), cols["h [m]"]
    bad_lat = np.abs(lat) >= np.radians(89.9)
    if bad_lat.any():
        r = int(np.argmax(bad_lat))
        raise TrajectoryError(f"{where}: column 'lat [deg]'", f"row {r + 1}: {cols['lat [deg]'][r]:g} deg "
                              "is not within ±89.9 deg")
    bad_lon = np.abs(cols["lon [deg]"]) > MAX_CSV_LONGITUDE
    if bad_lon.any():
        r = int(np.argmax(bad_lon))
        raise TrajectoryError(f"{where}: column 'lon [deg]'", f"row {r + 1}: {cols['lon [deg]'][r]:g} deg "
                              f"is not within ±{MAX_CSV_LONGITUDE:g} deg")
    v_n = np.column_stack([cols[c] for c in ("v_N [m/s]", "v_E [m/s]", "v_D [m/s]")])
    lon = unwrap_longitude(np.radians(cols["lon [deg]"]), lat, h, v_n[:, 1], t)
    f_b = np.column_stack([cols[c] for c in ("f_x [m/s^2]", "f_y [m/s^2]", "f_z [m/s^2]")])
    w_ib_b = np.column_stack([cols[c] for c in ("w_x [rad/s]", "w_y [rad/s]", "w_z [rad/s]")])
    speed = np.linalg.norm(v_n, axis=1)
    if "distance [m]" in cols:
        distance = cols["distance [m]"]
    else:
        distance = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * step)])
    w_in = earth.earth_rate_n(lat) + earth.transport_rate_n(lat, h, v_n)
    turn = np.linalg.norm(w_ib_b - np.einsum("kji,kj->ki", quat.dcm(q), w_in), axis=1)   # |ω_nb^b|
    if "stationary" in cols:
        flag = cols["stationary"]
        bad = (flag != 0) & (flag != 1)
        if bad.any():
            r = int(np.argmax(bad))
            raise TrajectoryError(f"{where}: column 'stationary'", f"row {r + 1}: {flag[r]:g} is not 0 or 1")
        still = flag == 1
        moving = still & ((speed > STATIONARY_FLAG_SPEED) | (turn > STATIONARY_FLAG_RATE))
        if moving.any():
            r = int(np.argmax(moving))
            what = (f"speed {speed[r]:.6g} m/s (tolerance {STATIONARY_FLAG_SPEED:g} m/s)"
                    if speed[r] > STATIONARY_FLAG_SPEED else
                    f"body rate w.r.t. NED {turn[r]:.6g} rad/s (tolerance {STATIONARY_FLAG_RATE:g} rad/s)")
            raise TrajectoryError(f"{where}: column 'stationary'", f"row {r + 1}: flagged stationary (1) while "
                                  f"the vehicle moves: {what}; {int(moving.sum())} such row(s)")
    else:
        still = (speed < STATIONARY_SPEED) & (turn < STATIONARY_RATE)
    intervals = []
    k = 0
    while k < t.size:
        if still[k]:
            j = k
            while j + 1 < t.size and still[j + 1]:
                j += 1
            if j > k or "stationary" in cols:
                intervals.append((float(t[k]), float(t[j])))
            k = j + 1
        else:
            k += 1
    traj = Trajectory(t=t, lat=lat, lon=lon, h=h, v_n=v_n, q_nb=q, f_b=f_b, w_ib_b=w_ib_b,
                      distance=distance, stationary=tuple(intervals), name=path.stem)
    return Trajectory(**trajectory_fields(traj), stationary=traj.stationary, name=traj.name,
                      _source=Interpolant(traj))


def save_trajectory_csv(traj: Trajectory, path) -> None:
    """Write a trajectory as CSV (exact round trip with the loader).

    Parameters
    ----------
    traj : Trajectory
        The samples to write.
    path : str or Path
        Output file; written atomically, numbers with 17 significant digits.
    """
    from covtool.io.atomic import write_text

    write_text(path, traj.to_dataframe().to_csv(index=False, float_format="%.17g"))
