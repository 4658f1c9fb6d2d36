"""TOML loading and small validation helpers shared by model and study files.

Each helper takes ``where`` (``"<file>: <section>"``) and an exception class so
that every message names the file, the field and the problem.
"""

from __future__ import annotations

import stat
import tomllib
from pathlib import Path

from ..errors import InputError, UnitError
from ..units import parse_quantity


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
