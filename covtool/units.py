"""Unit layer: datasheet strings in, SI floats out.

covtool is SI inside.  Units appear only at the edges: model and study files,
spreadsheet headers and plot axes.  This module is the only place where unit
strings are interpreted.

Conventions
-----------
* ``g`` means standard gravity (9.80665 m/s^2); ``ug``/``µg``, ``mg`` and ``ng``
  are micro-, milli- and nano-g.  Mass never appears in an INS error model.
* ``sqrt(X)`` is accepted and means ``(X)**0.5``: ``0.002 deg/sqrt(h)``.
* Angles carry their own pseudo-dimension here (pint treats the radian as
  dimensionless), so ``35 ppm`` is rejected where an angle is expected and
  ``0.018 deg/h`` is an angular rate, not a frequency.
"""

from __future__ import annotations

import math
import re
from functools import lru_cache

import pint

from .errors import UnitError

__all__ = ["ureg", "parse_quantity", "to_si", "from_si", "DIMENSIONS", "is_unit"]

ureg = pint.UnitRegistry()

#: standard gravity [m/s^2]
G0 = 9.80665

# Angle units whose exponent defines the angle pseudo-dimension.
_ANGLE_UNITS = {
    "radian", "degree", "arcminute", "arcsecond", "revolution", "turn",
    "milliradian", "microradian", "grade", "gon", "mil",
}

#: reference SI units and angle exponent of every dimension covtool uses
DIMENSIONS: dict[str, tuple[str, tuple[int, ...]]] = {
    # name: (SI unit for pint, allowed angle exponents)
    "dimensionless": ("", (0,)),
    "angle": ("rad", (1,)),
    "quaternion": ("", (0, 1)),          # quaternion components, 'rad' tolerated (seed 002 Table 2)
    "angular_rate": ("rad/s", (1,)),
    "angle_random_walk": ("rad/s**0.5", (1,)),
    "rate_random_walk": ("rad/s**1.5", (1,)),
    "acceleration": ("m/s**2", (0,)),
    "velocity_random_walk": ("m/s**1.5", (0,)),
    "acceleration_random_walk": ("m/s**2.5", (0,)),
    "velocity": ("m/s", (0,)),
    "length": ("m", (0,)),
    "time": ("s", (0,)),
    "frequency": ("1/s", (0,)),
    "g_sensitivity": ("rad/s/(m/s**2)", (1,)),
    "g2_sensitivity": ("rad/s/(m/s**2)**2", (1,)),
}

_G_TOKEN = re.compile(r"(?<![A-Za-z_0-9.])([uµμmn]?)g(?![A-Za-z_0-9])")
_G_PREFIX = {"": "1", "u": "1e-6", "µ": "1e-6", "μ": "1e-6", "m": "1e-3", "n": "1e-9"}
_SQRT = re.compile(r"sqrt\(([^()]*)\)")


def _normalise(text: str) -> str:
    s = text.strip()
    prev = None
    while prev != s:
        prev = s
        s = _SQRT.sub(r"((\1)**0.5)", s)
    s = _G_TOKEN.sub(lambda m: f"({_G_PREFIX[m.group(1)]}*g_0)", s)
    s = s.replace("°", " deg ")
    return s


def _angle_exponent(q: pint.Quantity) -> float:
    exp = 0.0
    for name, power in q._units.items():  # noqa: SLF001 - pint has no public API for this
        if name in _ANGLE_UNITS:
            exp += power
    return exp


@lru_cache(maxsize=4096)
def _parse(text: str) -> pint.Quantity:
    q = ureg.parse_expression(_normalise(text))
    if not isinstance(q, pint.Quantity):
        q = ureg.Quantity(float(q), "")
    return q


def is_unit(text: str, dimension: str) -> bool:
    """Return True if ``text`` is a unit (or quantity) of ``dimension``."""
    try:
        parse_quantity("1 " + text if text and text[0].isalpha() else text, dimension, where="")
    except UnitError:
        return False
    return True


def parse_quantity(value, dimension: str, *, where: str = "") -> float:
    """Convert a datasheet quantity to an SI float.

    Parameters
    ----------
    value : str or float
        ``"20 ug"``, ``"0.018 deg/h"``, ``"35 ppm"``.  A bare number is taken
        as already in SI (and is only accepted where that is unambiguous:
        dimensionless and quaternion quantities, or zero).
    dimension : str
        One of :data:`DIMENSIONS`.
    where : str
        Location used in error messages (``"models/x.toml: state 'b_x': sigma"``).

    Returns
    -------
    float
        The value in SI units (rad, m, s, m/s^2, rad/s, ...).

    Raises
    ------
    UnitError
        Unknown unit, or a unit of the wrong dimension.
    """
    if dimension not in DIMENSIONS:
        raise UnitError(where, f"unknown dimension {dimension!r}")
    si_unit, angle_exps = DIMENSIONS[dimension]
    if isinstance(value, bool):
        raise UnitError(where, f"{value!r} is not a quantity")
    if isinstance(value, (int, float)):
        if value == 0 or dimension in ("dimensionless", "quaternion"):
            return float(value)
        raise UnitError(where, f"{value!r} has no unit; write it with a unit, e.g. '{value} {_example(dimension)}'")
    if not isinstance(value, str):
        raise UnitError(where, f"{value!r} is not a quantity string")
    try:
        q = _parse(value)
    except (pint.errors.UndefinedUnitError, pint.errors.DefinitionSyntaxError) as exc:
        raise UnitError(where, f"{value!r}: unknown unit ({exc})") from None
    except Exception as exc:  # pint's tokenizer raises assorted errors on garbage
        raise UnitError(where, f"{value!r} is not a quantity ({type(exc).__name__}: {exc})") from None
    if _angle_exponent(q) not in angle_exps or not q.is_compatible_with(si_unit or "dimensionless"):
        raise UnitError(where, f"{value!r} is not {_article(dimension)} {dimension.replace('_', ' ')}")
    mag = q.to(si_unit or "dimensionless").magnitude
    mag = float(mag)
    if not math.isfinite(mag):
        raise UnitError(where, f"{value!r} is not finite")
    return mag


def to_si(value, unit: str) -> float:
    """Convert a number expressed in ``unit`` to SI (``unit`` is a unit string)."""
    q = _parse(unit)
    si = q.to_base_units()
    # angles: pint's base for degree is radian already; g_0 expands to m/s^2
    return float(value) * float(si.magnitude)


def from_si(value, unit: str):
    """Express an SI number (or array) in ``unit`` (a unit string)."""
    return value / to_si(1.0, unit)


def _article(dimension: str) -> str:
    return "an" if dimension[0] in "aeiou" else "a"


def _example(dimension: str) -> str:
    return {
        "angle": "arcsec", "angular_rate": "deg/h", "acceleration": "ug",
        "velocity": "m/s", "length": "m", "time": "s", "angle_random_walk": "deg/sqrt(h)",
        "velocity_random_walk": "ug/sqrt(Hz)", "g_sensitivity": "deg/h/g",
        "g2_sensitivity": "deg/h/g**2", "frequency": "Hz",
    }.get(dimension, "SI")
