"""Strict reading of numeric CSV tables (trajectories, IMU logs).

Every problem is an error naming the file, the column and the row; nothing
is silently dropped or coerced.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_numeric_csv(path, required, optional=(), *, error=InputError, time_column: str | None = "t [s]",
                     min_rows: int = 2) -> dict[str, np.ndarray]:
    """Read a CSV whose every cell is a finite number.

    Parameters
    ----------
    path : str or Path
    required : sequence of str
        Column headers that must be present (units in brackets).
    optional : sequence of str
        Headers that may be present.
    error : type
        Exception class raised (a :class:`covtool.errors.InputError` subclass).
    time_column : str or None
        A column that must be strictly increasing.
    min_rows : int
        Minimum number of data rows.

    Returns
    -------
    dict of str to ndarray, shape (K,)
        One float array per column present.

    Raises
    ------
    error
        File missing or unreadable, duplicate, missing or unknown column, too
        few rows, an empty, non-numeric or non-finite cell (with its row,
        counting data rows from 1), or time not strictly increasing.
    """
    import pandas as pd

    path = Path(path)
    where = str(path)
    try:
        df = pd.read_csv(path, dtype=str, keep_default_na=False, skipinitialspace=True)
    except FileNotFoundError:
        raise error(where, "file not found") from None
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise error(where, f"not a readable CSV file ({exc})") from None
    cols = [str(c).strip() for c in df.columns]
    seen = set()
    for c in cols:
        if c in seen or c.split(".")[0] in seen and c.rsplit(".", 1)[-1].isdigit():
            raise error(where, f"column {c.split('.')[0]!r} appears more than once")
        seen.add(c)
    df.columns = cols
    expected = f"expected {', '.join(required)}" + (f"; optional {', '.join(optional)}" if optional else "")
    for c in required:
        if c not in cols:
            raise error(where, f"missing column {c!r} ({expected})")
    allowed = set(required) | set(optional)
    for c in cols:
        if c not in allowed:
            raise error(where, f"unknown column {c!r} ({expected})")
    if len(df) < min_rows:
        raise error(where, f"needs at least {min_rows} data rows, found {len(df)}")
    data = {}
    for c in cols:
        raw = df[c].str.strip()
        num = pd.to_numeric(raw, errors="coerce").to_numpy(dtype=float)
        bad = ~np.isfinite(num)
        if bad.any():
            r = int(np.argmax(bad))
            text = raw.iloc[r]
            what = "is empty" if text == "" else (f"{text!r} is not finite" if _is_float(text)
                                                 else f"{text!r} is not a number")
            raise error(f"{where}: column {c!r}", f"row {r + 1}: {what}")
        data[c] = num
    if time_column is not None:
        t = data[time_column]
        step = np.diff(t)
        if np.any(step <= 0):
            r = int(np.argmax(step <= 0)) + 2
            raise error(f"{where}: column {time_column!r}", f"row {r}: time {t[r - 1]:.17g} s is not after the "
                        f"previous row's {t[r - 2]:.17g} s (time must be strictly increasing)")
    return data
