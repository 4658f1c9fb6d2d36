"""TOML loading and small validation helpers shared by model and study files.

Each helper takes ``where`` (``"<file>: <section>"``) and an exception class so
that every message names the file, the field and the problem.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from ..errors import InputError, UnitError
from ..units import parse_quantity


def load_toml(path, error=InputError) -> dict:
    """Read a TOML file, turning I/O and syntax errors into ``error``."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise error(str(path), "file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise error(str(path), f"TOML syntax error: {exc}") from None


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


def quantity(value, dimension: str, where: str, error=InputError, *, nonnegative=False, positive=False) -> float:
    """Parse a quantity with :func:`covtool.units.parse_quantity`, re-raising as ``error``."""
    try:
        x = parse_quantity(value, dimension, where=where)
    except UnitError as exc:
        raise error(exc.where, exc.problem) from None
    if positive and not x > 0:
        raise error(where, f"{value!r} must be positive")
    if nonnegative and x < 0:
        raise error(where, f"{value!r} must not be negative")
    return x


def as_list(value, n: int, where: str, error=InputError) -> list:
    """Broadcast a scalar to ``n`` items, or check a list has ``n`` items."""
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise error(where, f"expected {n} values, got {len(value)}")
        return list(value)
    return [value] * n
