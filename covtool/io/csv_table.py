"""Strict, bounded-memory reading of numeric CSV tables (trajectories, IMU logs).

Every problem is one error naming the file, the column and the row; nothing
is silently dropped or coerced.  Columns are matched by their header names,
never by position.

Memory: the file is read in blocks of :data:`CHUNK_ROWS` lines straight into
preallocated float64 arrays (one per column), so the reader holds the
numeric data once plus one block of text.  A file larger than
:data:`MAX_BYTES` (or the ``max_bytes`` given) is refused before it is read.
"""

from __future__ import annotations

import csv
import itertools
from pathlib import Path

import numpy as np

from covtool.errors import InputError

__all__ = ["read_numeric_csv", "MAX_BYTES", "CHUNK_ROWS"]

#: largest CSV file read [bytes] (2 GiB: about 6 million trajectory rows at
#: 17 significant digits, whose arrays take under 1 GB)
MAX_BYTES = 2 * 1024**3
#: lines parsed per block
CHUNK_ROWS = 65536
_BLOCK = 1 << 24


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _size(n: int) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.3g} {unit} ({n} bytes)"
    return f"{n} bytes"


def _scan(path: Path, where: str, error) -> tuple[int, bool]:
    """Count line ends and tell whether the file ends with one."""
    lines, last = 0, b""
    with open(path, "rb") as f:
        while True:
            block = f.read(_BLOCK)
            if not block:
                break
            lines += block.count(b"\n")
            last = block[-1:]
    return lines, last in (b"\n", b"")


def _utf8_problem(path: Path) -> str:
    """Where the first byte that is not UTF-8 lies (only called on failure)."""
    import codecs

    dec = codecs.getincrementaldecoder("utf-8")()
    offset, lines = 0, 0
    with open(path, "rb") as f:
        while True:
            block = f.read(_BLOCK)
            if not block:
                break
            try:
                dec.decode(block)
            except UnicodeDecodeError as exc:
                pos = offset + exc.start - len(dec.getstate()[0])
                with open(path, "rb") as g:
                    head = g.read(pos)
                lines = head.count(b"\n")
                g_bad = exc.object[exc.start:exc.start + 1]
                where = "in the header" if lines == 0 else f"in row {lines}"
                return f"not UTF-8 text: byte 0x{g_bad.hex()} at byte {pos} {where}"
            offset += len(block)
    return "not UTF-8 text"


def _cell_problem(text: str) -> str:
    if text.strip() == "":
        return "is empty"
    if _is_float(text):
        return f"{text.strip()!r} is not finite"
    return f"{text.strip()!r} is not a number"


def _diagnose(lines, first_row: int, cols: list, where: str, error):
    """Raise the precise error for the first bad line of a block."""
    n = len(cols)
    for k, row in enumerate(csv.reader(lines, skipinitialspace=True)):
        r = first_row + k
        if not row or all(c.strip() == "" for c in row) and len(row) <= 1:
            raise error(where, f"row {r}: empty line")
        if len(row) < n:
            raise error(f"{where}: column {cols[len(row)]!r}", f"row {r}: missing: the line has {len(row)} of the "
                        f"{n} cells of the header (truncated line?)")
        if len(row) > n:
            raise error(where, f"row {r}: the line has {len(row)} cells, the header has {n}")
        for c, text in zip(cols, row):
            try:
                x = float(text)
            except ValueError:
                x = float("nan")
            if not np.isfinite(x):
                raise error(f"{where}: column {c!r}", f"row {r}: {_cell_problem(text)}")
    raise error(where, f"rows {first_row}-{first_row + len(lines) - 1}: not readable as numbers")


def read_numeric_csv(path, required, optional=(), *, error=InputError, time_column: str | None = "t [s]",
                     min_rows: int = 2, max_bytes: int | None = None) -> dict[str, np.ndarray]:
    """Read a CSV whose every cell is a finite number.

    Parameters
    ----------
    path : str or Path
    required : sequence of str
        Column headers that must be present (units in brackets), in any
        order; columns are matched by name.
    optional : sequence of str
        Headers that may be present.
    error : type
        Exception class raised (a :class:`covtool.errors.InputError` subclass).
    time_column : str or None
        A column that must be strictly increasing.
    min_rows : int
        Minimum number of data rows.
    max_bytes : int, optional
        Largest file accepted [bytes]; default :data:`MAX_BYTES`.

    Returns
    -------
    dict of str to ndarray, shape (K,)
        One float array per column present.

    Raises
    ------
    error
        File missing, a directory, unreadable or not UTF-8 text; larger than
        ``max_bytes`` (with its size and the limit, before reading);
        duplicate, missing or unknown column; too few rows; an empty line; a
        line with fewer cells than the header (truncated) or more; a last
        line without a line end (the file was cut off); an empty,
        non-numeric or non-finite cell; time not strictly increasing.  Rows
        count data rows from 1 and every message names the file.
    """
    path = Path(path)
    where = str(path)
    limit = MAX_BYTES if max_bytes is None else int(max_bytes)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise error(where, "file not found") from None
    except OSError as exc:
        raise error(where, f"cannot read the file ({exc.strerror})") from None
    if path.is_dir():
        raise error(where, "is a directory, not a CSV file")
    if size > limit:
        raise error(where, f"the file is {_size(size)}, larger than the {_size(limit)} covtool reads; split or "
                    "decimate it")
    try:
        n_lines, ends_with_newline = _scan(path, where, error)
        f = open(path, encoding="utf-8-sig", newline="")
    except OSError as exc:
        raise error(where, f"cannot read the file ({exc.strerror})") from None
    with f:
        try:
            header_line = f.readline()
        except UnicodeDecodeError:
            raise error(where, f"not a readable CSV file ({_utf8_problem(path)})") from None
        if not header_line.strip():
            raise error(where, "not a readable CSV file (no header line)")
        header = next(csv.reader([header_line], skipinitialspace=True))
        cols = [c.strip() for c in header]
        seen = set()
        for c in cols:
            if c in seen:
                raise error(where, f"column {c!r} appears more than once")
            seen.add(c)
        expected = f"expected {', '.join(required)}" + (f"; optional {', '.join(optional)}" if optional else "")
        for c in required:
            if c not in cols:
                raise error(where, f"missing column {c!r} ({expected})")
        allowed = set(required) | set(optional)
        for c in cols:
            if c not in allowed:
                raise error(where, f"unknown column {c!r} ({expected})")
        n_rows = n_lines - 1 + (0 if ends_with_newline else 1)
        if not ends_with_newline and n_rows >= 1:
            raise error(where, f"row {n_rows}: the last line has no line end: the file looks truncated "
                        "(every line must end with a newline)")
        if n_rows < min_rows:
            raise error(where, f"needs at least {min_rows} data rows, found {max(n_rows, 0)}")
        out = np.empty((len(cols), n_rows))
        row = 0
        while True:
            try:
                lines = list(itertools.islice(f, CHUNK_ROWS))
            except UnicodeDecodeError:
                raise error(where, f"not a readable CSV file ({_utf8_problem(path)})") from None
            if not lines:
                break
            first = row + 1
            if row + len(lines) > n_rows:        # a lone '\r' line end splits differently from '\n'
                raise error(where, f"row {n_rows + 1}: more lines than line ends (mixed line ends?)")
            try:
                block = np.loadtxt(lines, delimiter=",", ndmin=2, quotechar='"', dtype=float, comments=None)
            except ValueError:
                _diagnose(lines, first, cols, where, error)
            if block.shape != (len(lines), len(cols)) or not np.isfinite(block).all():
                _diagnose(lines, first, cols, where, error)
            out[:, row:row + len(lines)] = block.T
            row += len(lines)
        if row != n_rows:
            raise error(where, f"read {row} data rows, expected {n_rows} (mixed line ends?)")
    data = {c: out[k] for k, c in enumerate(cols)}
    if time_column is not None:
        t = data[time_column]
        step = np.diff(t)
        if np.any(step <= 0):
            r = int(np.argmax(step <= 0)) + 2
            raise error(f"{where}: column {time_column!r}", f"row {r}: time {t[r - 1]:.17g} s is not after the "
                        f"previous row's {t[r - 2]:.17g} s (time must be strictly increasing)")
    return data
