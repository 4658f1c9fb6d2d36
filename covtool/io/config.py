"""TOML loading and the typed field helpers every parser uses.

Each helper takes ``where`` (``"<file>: <section> <key>"``) and an exception
class so that every message names the file, the field and the problem:
:func:`integer`, :func:`number`, :func:`boolean`, :func:`string`,
:func:`choice`, :func:`names`, :func:`quantity` (finite SI values from
datasheet strings), :func:`quantities`, :func:`quantity_list`, :func:`table`.
:data:`LIMITS` holds the upper limit of every count, rate and order with
its reason.  :func:`resolve_input` resolves a file named in another file
against that file's directory.
"""

from __future__ import annotations

import stat
import hashlib
import math
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path

from covtool.errors import InputError, UnitError
from covtool.units import parse_quantity


#: largest TOML file read [bytes]; a model or study file is a few kB
MAX_TOML_BYTES = 16 * 2**20


def load_toml(path, error=InputError) -> dict:
    """Read a TOML file; every file-level problem is one ``error`` naming it.

    Parameters
    ----------
    path : path-like
    error : type
        :class:`~covtool.errors.InputError` subclass to raise.

    Returns
    -------
    dict

    Raises
    ------
    InputError
        (``error``) The file is missing, a directory or not a regular file,
        unreadable, larger than :data:`MAX_TOML_BYTES`, binary (NUL bytes),
        not UTF-8 (the message gives line and column of the first bad
        byte), or not valid TOML.  A UTF-8 byte-order mark is accepted.
    """
    path = Path(path)
    name = str(path)
    try:
        st = path.stat()
        if stat.S_ISDIR(st.st_mode):
            raise error(name, "is a directory, not a TOML file")
        if not stat.S_ISREG(st.st_mode):
            raise error(name, "is not a regular file (a device, pipe or socket), not a TOML file")
        if st.st_size > MAX_TOML_BYTES:
            raise error(name, f"is {st.st_size / 2**20:.0f} MiB; a TOML file over "
                        f"{MAX_TOML_BYTES // 2**20} MiB is refused (is it the right file?)")
        with open(path, "rb") as fh:
            data = fh.read(MAX_TOML_BYTES + 1)
    except (FileNotFoundError, NotADirectoryError):
        raise error(name, "file not found") from None
    except PermissionError:
        raise error(name, "permission denied (cannot read the file)") from None
    except OSError as exc:
        raise error(name, f"cannot read the file: {exc.strerror or exc}") from None
    if len(data) > MAX_TOML_BYTES:
        raise error(name, f"a TOML file over {MAX_TOML_BYTES // 2**20} MiB is refused (is it the right file?)")
    if b"\x00" in data:
        line = data[:data.index(b"\x00")].count(b"\n") + 1
        raise error(name, f"is a binary file (NUL byte on line {line}), not TOML text")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        pos = exc.start + (3 if data.startswith(b"\xef\xbb\xbf") else 0)
        line = data[:pos].count(b"\n") + 1
        col = pos - (data.rfind(b"\n", 0, pos) + 1) + 1
        raise error(name, f"is not UTF-8 text: byte 0x{data[pos]:02x} at line {line}, column {col} "
                    "(save the file as UTF-8)") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(name, f"TOML syntax error: {exc}") from None


def check_keys(d: dict, allowed, where: str, error=InputError) -> None:
    """Raise ``error`` naming the first key of ``d`` not in ``allowed``."""
    if not isinstance(d, dict):
        raise error(where, f"expected a table, got {type(d).__name__}")
    allowed = set(allowed)
    for k in d:
        if k not in allowed:
            raise error(where, f"unknown key {k!r} (allowed: {', '.join(sorted(allowed))})")


def require(d: dict, key: str, where: str, error=InputError):
    """Return ``d[key]`` or raise ``error`` saying it is missing."""
    if key not in d:
        raise error(where, f"missing required key {key!r}")
    return d[key]


# ---------------------------------------------------------------------------
# typed field helpers
#
# One helper per field type; every parser (model, filter and IMU-grade files,
# every study kind) calls these, so a type, finiteness, sign or range rule is
# written once.  Each takes the value, ``where`` ("<file>: <section> <key>")
# and the exception class, and returns the validated value (SI for
# quantities).  They are deliberately declarative so that a later typed
# configuration (pydantic) can take the same bounds.
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Bound:
    """An inclusive range ``[lo, hi]`` of a count, rate or order, with its reason.

    ``reason`` says why the limit is where it is; it is part of the error
    message, so a user knows whether to shrink the value or split the study.
    """

    lo: float | None
    hi: float | None
    reason: str = ""


def _g(x) -> str:
    return f"{x:,}".replace(",", "_") if isinstance(x, int) and abs(x) >= 10_000 else f"{x:g}"


#: Upper (and lower) limits of every count, rate and order read from a file.
#: The reason is printed with the refusal.
LIMITS: dict[str, Bound] = {
    "taylor_order": Bound(2, 40, "eq (6b)-(6d) with 1 term is Phi = I, Q_d = 0 (nothing propagates); "
                                 "past 40 terms every added term is below double precision wherever the "
                                 "series converges (|F|dt < 7)"),
    "cycles": Bound(1, 1_000, "1000 cycles of the default 5-min period span 3.5 days; every cycle's "
                              "pieces are integrated by an ODE solver, about 0.07 s per cycle"),
    "mc_runs": Bound(2, 10_000, "at 10 000 runs the 95 % chi-square band of an RMS is already +-1.4 %; "
                                "more runs cannot sharpen a validation of a linear model"),
    "mc_runs_per_chunk": Bound(1, 10_000, "a chunk holds all its runs' states at once"),
    "dual_runs": Bound(0, 10_000, "10 000 simulated flights resolve a false-alarm rate of 1e-4"),
    "dual_batch": Bound(1, 1_000, "a batch holds every flight's joint covariance and samples at once"),
    "seed": Bound(0, 2**63 - 1, "numpy SeedSequence entropy is a non-negative integer"),
    "repeats": Bound(1, 1_000, "the median of 1000 timings is as good as it gets"),
    "fit_degree": Bound(0, 10, "a log-log polynomial of degree > 10 only fits round-off"),
    "per_decade": Bound(1, 100, "100 scales per decade is finer than any sensitivity curve needs"),
    "sweep_points": Bound(2, 1_000, "each scale is one batched filter case per parameter"),
    "grid_cases": Bound(1, 1_000_000, "each case is one summary row per report time"),
    "grid_axis": Bound(1, 1_000, "an axis longer than 1000 values is a sweep, not a trade grid"),
    "budget_top": Bound(1, 60, "the stacked figure cannot show more sources"),
    "gap_window": Bound(1, 100_000, "samples averaged by a gap bridge"),
    "gap_trials": Bound(0, 1_000, "trial bridges per side for the error prediction"),
    "kimu_ratio": Bound(1, 1_000, "KIMU samples per main-IMU sample"),
    "imu_rate": Bound(1e-3, 1e5, "no strapdown IMU outputs faster than 100 kHz, and the simulator "
                                  "generates every sample"),
    "report_times": Bound(1, 10_000, "each report time is one summary row per case"),
    "filter_scale": Bound(1e-6, 1e6, "six decades either side of the nominal filter; further out the gains "
                                     "have long saturated (K -> 0 or K -> the inverse of H)"),
    "grade_scale": Bound(1e-6, 1e6, "six decades either side of the truth model's sensor errors"),
}


def _range_problem(value, lo, hi, why: str, kind: str) -> str:
    if lo is not None and hi is not None:
        rng = f"in {_g(lo)}..{_g(hi)}"
    elif lo is not None:
        rng = f">= {_g(lo)}"
    else:
        rng = f"<= {_g(hi)}"
    return f"{value!r} is not {kind} {rng}" + (f" ({why})" if why else "")


def integer(value, where: str, error=InputError, *, lo: int | None = None, hi: int | None = None,
            limit: str | None = None) -> int:
    """An integer (not a bool, not a float) in ``[lo, hi]`` or in :data:`LIMITS` ``[limit]``."""
    why = ""
    if limit is not None:
        b = LIMITS[limit]
        lo = b.lo if lo is None else lo
        hi = b.hi if hi is None else hi
        why = b.reason
    if isinstance(value, bool) or not isinstance(value, int):
        raise error(where, _range_problem(value, lo, hi, why, "an integer"))
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise error(where, _range_problem(value, lo, hi, why, "an integer"))
    return int(value)


def number(value, where: str, error=InputError, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False, hi_open: bool = False, why: str = "") -> float:
    """A finite bare number (int or float, not a bool) in a range.

    ``lo_open``/``hi_open`` make the bounds exclusive.  ``nan`` and ``inf``
    are always refused.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise error(where, f"{value!r} is not a number")
    x = float(value)
    if not math.isfinite(x):
        raise error(where, f"{value!r} is not finite")
    bad = (lo is not None and (x < lo or (lo_open and x == lo))) or \
          (hi is not None and (x > hi or (hi_open and x == hi)))
    if bad:
        left = "" if lo is None else ("> " if lo_open else ">= ") + _g(lo)
        right = "" if hi is None else ("< " if hi_open else "<= ") + _g(hi)
        rng = " and ".join(p for p in (left, right) if p)
        raise error(where, f"{value!r} is not a number {rng}" + (f" ({why})" if why else ""))
    return x


def positive_number(value, where: str, error=InputError) -> float:
    """A finite number > 0 (a scale factor, a ratio)."""
    return number(value, where, error, lo=0.0, lo_open=True)


def boolean(value, where: str, error=InputError) -> bool:
    """``true`` or ``false``; a string ``"no"`` or an integer ``1`` is refused."""
    if not isinstance(value, bool):
        raise error(where, f"{value!r} is not true or false")
    return value


def string(value, where: str, error=InputError, *, nonempty: bool = False) -> str:
    """A string (``nonempty``: at least one non-blank character)."""
    if not isinstance(value, str) or (nonempty and not value.strip()):
        raise error(where, f"{value!r} is not a {'non-empty ' if nonempty else ''}string")
    return value


def choice(value, options, where: str, error=InputError):
    """One of ``options`` (strings or booleans, compared by type and value)."""
    for o in options:
        if type(value) is type(o) and value == o:
            return value
    shown = ", ".join(repr(o) if isinstance(o, str) else str(o).lower() for o in options)
    raise error(where, f"{value!r} is not one of: {shown}")


def names(value, where: str, error=InputError, *, known=None, nonempty: bool = True, unique: bool = True,
          what: str = "name") -> list[str]:
    """A list of strings, optionally each in ``known``, without repeats."""
    if not isinstance(value, list) or (nonempty and not value):
        raise error(where, f"expected a {'non-empty ' if nonempty else ''}list of {what}s, got {value!r}")
    for v in value:
        if not isinstance(v, str):
            raise error(where, f"{v!r} is not a {what} (a string)")
        if known is not None and v not in known:
            raise error(where, f"unknown {what} {v!r} (one of: {', '.join(known)})")
    if unique:
        seen = set()
        for v in value:
            if v in seen:
                raise error(where, f"{what} {v!r} is listed twice")
            seen.add(v)
    return list(value)


def quantity(value, dimension: str, where: str, error=InputError, *, nonnegative=False, positive=False,
             hi: float | None = None, why: str = "") -> float:
    """A finite quantity in SI, from a datasheet string (``"20 ug"``) or a bare number.

    Bare numbers are accepted where :func:`covtool.units.parse_quantity`
    accepts them (dimensionless, quaternion, or zero) and must be finite too.
    ``positive``: > 0; ``nonnegative``: >= 0 (a negative value is refused,
    never folded); ``hi``: an upper limit in SI, with ``why`` in the message.
    """
    try:
        x = parse_quantity(value, dimension, where=where)
    except UnitError as exc:
        raise error(exc.where, exc.problem) from None
    if not math.isfinite(x):
        raise error(where, f"{value!r} is not finite")
    if positive and not x > 0:
        raise error(where, f"{value!r} must be positive")
    if nonnegative and x < 0:
        raise error(where, f"{value!r} is negative; it must be >= 0")
    if hi is not None and x > hi:
        raise error(where, f"{value!r} is above the limit of {hi:g} (SI)" + (f": {why}" if why else ""))
    return x


def quantities(value, dimension: str, n: int, where: str, error=InputError, **kw) -> list[float]:
    """One quantity for all ``n`` items, or a list of ``n`` quantities (``[i]`` in messages)."""
    vals = as_list(value, n, where, error)
    if isinstance(value, list):
        return [quantity(v, dimension, f"{where}[{i}]", error, **kw) for i, v in enumerate(vals)]
    return [quantity(value, dimension, where, error, **kw)] * n


def quantity_list(value, dimension: str, where: str, error=InputError, *, nonempty=True, limit: str | None = None,
                  **kw) -> list[float]:
    """A list of quantities (``[output] report_times``, a grid axis)."""
    if not isinstance(value, list) or (nonempty and not value):
        raise error(where, f"expected a {'non-empty ' if nonempty else ''}list of quantities, got {value!r}")
    if limit is not None and len(value) > LIMITS[limit].hi:
        raise error(where, f"{len(value)} values; at most {_g(LIMITS[limit].hi)} ({LIMITS[limit].reason})")
    return [quantity(v, dimension, f"{where}[{i}]", error, **kw) for i, v in enumerate(value)]


def table(value, where: str, error=InputError) -> dict:
    """A TOML table (dict)."""
    if not isinstance(value, dict):
        raise error(where, f"expected a table, got {type(value).__name__} {value!r}")
    return value


def as_list(value, n: int, where: str, error=InputError) -> list:
    """Broadcast a scalar to ``n`` items, or check a list has ``n`` items."""
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise error(where, f"expected {n} values, got {len(value)}")
        return list(value)
    return [value] * n


# ---------------------------------------------------------------------------
# input files named by other files
# ---------------------------------------------------------------------------


def is_library_name(value: str) -> bool:
    """True for a bare library name (``"sdins58"``): no suffix, no path separator."""
    p = Path(value)
    return p.suffix == "" and "/" not in value and "\\" not in value and p.name == value


def resolve_input(value, base_dir, where: str, error=InputError, *, what: str = "file",
                  must_exist: bool = True) -> Path:
    """Absolute path of a file named in another file.

    A relative path resolves against ``base_dir``, the directory of the file
    that names it, never against the current directory (``base_dir`` None:
    a declaration given as a dict, resolved against the current directory).
    ``must_exist=False`` leaves the missing-file message to the reader.

    Raises
    ------
    error
        Not a string, or no such file (the message gives the resolved path).
    """
    if not isinstance(value, str) or not value.strip():
        raise error(where, f"{value!r} is not a file name")
    p = Path(value).expanduser()
    if not p.is_absolute():
        p = (Path(base_dir) if base_dir is not None else Path.cwd()) / p
    p = Path(os.path.abspath(p))
    if must_exist and not p.is_file():
        why = ""
        if not Path(value).expanduser().is_absolute() and base_dir is not None:
            why = f" ({value!r} is resolved against {os.path.abspath(base_dir)!r}, the directory of the file that names it)"
        raise error(where, f"no such {what} {str(p)!r}{why}")
    return p


def file_sha256(path) -> str:
    """SHA-256 of a file's bytes (provenance)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
