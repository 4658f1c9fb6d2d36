"""Unit layer: datasheet strings in, SI floats out.

covtool is SI inside.  Units appear only at the edges: model and study files,
spreadsheet headers and plot axes.  This module is the only place where unit
strings are interpreted.

Grammar
-------
A quantity string is read by a small tokenizer and recursive-descent parser
(never by evaluating an expression)::

    quantity := number [unit]
    number   := [+-−] digits [. digits] [e [+-] digits]       (finite)
    unit     := ["/"] term (("*" | "·" | "/") term)*          (left-associative)
    term     := factor [("^" | "**") exponent | superscript]
    factor   := name | "(" unit ")" | "sqrt(" unit ")" | "√" factor
              | "rt(" unit ")" | "rt-" name | "rt" name         (square roots)
    exponent := a multiple of 1/2 within ±4: 2, -1, 0.5, 1/2, (1/2), ½, ², ⁻¹

Only *single unit names* are resolved by pint (with the SI prefixes), and
pint converts; the arithmetic of the expression is done here on
(SI factor, base-unit exponents) pairs.  Strings are at most
:data:`MAX_LENGTH` characters and parentheses nest at most
:data:`MAX_DEPTH` deep, so a hostile string is refused by the grammar
before any arithmetic.  Every refusal names the character or token it
could not read.

Conventions
-----------
* ``g`` means standard gravity (9.80665 m/s^2); ``ug``/``µg``/``μg``, ``mg``
  and ``ng`` are micro-, milli- and nano-g.  Mass never appears in an INS
  error model.
* ``°``, ``deg``, ``degree``; ``′``, ``'`` (arcmin); ``″``, ``"``, ``''``
  (arcsec); ``h``, ``hr``, ``hour``; ``µ`` (U+00B5), ``μ`` (U+03BC) and
  ``u`` are all micro; ``dph`` is deg/h and ``dps`` deg/s.
* ``√h``, ``sqrt(h)``, ``rt-hr``, ``rt(h)``, ``rtHz``, ``h^0.5``, ``h^½``
  are one square root.
* Names that engineers use for two different things are refused with a
  hint (``nm``: nanometre or nautical mile; ``mil``; ``ppt``; ``G``).
* Angles carry their own pseudo-dimension here (pint treats the radian as
  dimensionless), so ``35 ppm`` is rejected where an angle is expected and
  ``0.018 deg/h`` is an angular rate, not a frequency.

Layout
------
``tables`` (constants, :data:`DIMENSIONS`, ``_Unit`` and the resolution of
one unit name), ``grammar`` (tokenizer and parser); this module holds the
public API (:func:`parse_quantity`, :func:`to_si`, :func:`from_si`,
:func:`si_unit`, :func:`is_unit`).
"""

from __future__ import annotations

import math
from fractions import Fraction
from functools import lru_cache

from covtool.errors import UnitError
from covtool.units.grammar import _parse, _parse_or_raise, _Parser, _tokenize, _Tok  # noqa: F401 - re-exported
from covtool.units.tables import (  # noqa: F401 - re-exported
    ARCMIN, ARCSEC, DIMENSIONS, FT, G0, OUTPUT_LENGTHS, PPM_G, MAX_DEPTH, MAX_EXPONENT, MAX_LENGTH, _ONE, _RADIAN, _Refusal, _resolve, _Unit,
    _unit, registry,
)


def __getattr__(name):
    if name == "ureg":                    # pint's registry, built when first asked for (registry())
        return registry()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

__all__ = ["ureg", "parse_quantity", "to_si", "from_si", "si_unit", "DIMENSIONS", "is_unit", "G0", "FT", "OUTPUT_LENGTHS", "ARCMIN", "ARCSEC", "PPM_G",
           "MAX_LENGTH", "MAX_DEPTH", "MAX_EXPONENT"]


@lru_cache(maxsize=None)
def _target(dimension: str) -> _Unit:
    si_unit = DIMENSIONS[dimension][0]
    return _parse(si_unit, False)[1] if si_unit else _ONE


def _matches(unit: _Unit, dimension: str) -> bool:
    return unit.physical == _target(dimension).physical and unit.angle in DIMENSIONS[dimension][1]


# --------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------


def is_unit(text: str, dimension: str) -> bool:
    """True if ``text`` is a unit (or quantity) of ``dimension``.

    Parameters
    ----------
    text : str
        ``"deg/h"``, ``"°/√h"`` or a whole quantity ``"1 deg/h"``.
    dimension : str
        One of :data:`DIMENSIONS`.
    """
    if not isinstance(text, str) or dimension not in DIMENSIONS:
        return False
    try:
        _, unit = _parse(text, False)
    except _Refusal:
        return False
    return _matches(_ONE if unit is None else unit, dimension)


def parse_quantity(value, dimension: str, *, where: str = "") -> float:
    """Convert a datasheet quantity to an SI float.

    Parameters
    ----------
    value : str or float
        ``"20 ug"``, ``"0.018 deg/h"``, ``"35 ppm"``, ``"0.15 °/√h"``.  A
        bare number is taken as already in SI and is only accepted where
        that is unambiguous: dimensionless and quaternion quantities, or
        zero.  A string without a unit follows the same rule.
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
        A string the grammar cannot read (naming the character or token),
        an unknown or ambiguous unit, a unit of the wrong dimension, a
        missing unit, or a value that is not finite.
    """
    if dimension not in DIMENSIONS:
        raise UnitError(where, f"unknown dimension {dimension!r}")
    if isinstance(value, bool):
        raise UnitError(where, f"{value!r} is not a quantity")
    if isinstance(value, (int, float)):
        if not math.isfinite(value):
            raise UnitError(where, f"{value!r} is not finite")
        if value == 0 or dimension in ("dimensionless", "quaternion"):
            return float(value)
        raise UnitError(where, f"{value!r} has no unit; write it with a unit, e.g. '{value} {_example(dimension)}'")
    if not isinstance(value, str):
        raise UnitError(where, f"{value!r} is not a quantity string")
    number, unit = _parse_or_raise(value, where)
    if unit is None and not (number == 0 or dimension in ("dimensionless", "quaternion")):
        raise UnitError(where, f"{value!r} has no unit; write it with a unit, e.g. "
                        f"'{value.strip()} {_example(dimension)}'")
    if unit is not None and not _matches(unit, dimension):
        raise UnitError(where, f"{value!r} is not {_article(dimension)} {dimension.replace('_', ' ')}")
    mag = number * (1.0 if unit is None else unit.factor)
    if not math.isfinite(mag):
        raise UnitError(where, f"{value!r} is not finite")
    return float(mag)


def _unit_factor(unit: str) -> float:
    if not isinstance(unit, str):
        raise UnitError("", f"{unit!r} is not a unit string")
    if not unit.strip():
        return 1.0
    number, u = _parse_or_raise(unit, "", need_number=False)
    return (1.0 if number is None else number) * (1.0 if u is None else u.factor)


def to_si(value, unit: str) -> float:
    """Convert a number expressed in ``unit`` to SI.

    Parameters
    ----------
    value : float
        Number in ``unit``.
    unit : str
        Unit expression of the grammar (``"deg/h"``, ``"°/√h"``).

    Returns
    -------
    float
        ``value`` in SI.

    Raises
    ------
    UnitError
        ``unit`` cannot be read.
    """
    return float(value) * _unit_factor(unit)


def from_si(value, unit: str):
    """Express an SI number (or array) in ``unit`` (a unit string).

    Raises
    ------
    UnitError
        ``unit`` cannot be read.
    """
    return value / _unit_factor(unit)


def _article(dimension: str) -> str:
    return "an" if dimension[0] in "aeiou" else "a"


def _example(dimension: str) -> str:
    return {
        "angle": "arcsec", "angular_rate": "deg/h", "acceleration": "ug",
        "velocity": "m/s", "length": "m", "time": "s", "angle_random_walk": "deg/sqrt(h)",
        "velocity_random_walk": "ug/sqrt(Hz)", "g_sensitivity": "deg/h/g",
        "g2_sensitivity": "deg/h/g**2", "frequency": "Hz", "inverse_acceleration": "ppm/g",
    }.get(dimension, "SI")


_SI_SYMBOL = {"meter": "m", "second": "s", "radian": "rad", "kilogram": "kg", "ampere": "A", "kelvin": "K"}


def si_unit(unit: str, power: int = 1, seconds=0) -> str:
    """The SI unit of ``unit`` (to ``power``), as a header writes it.

    Parameters
    ----------
    unit : str
        A unit expression of the grammar (``"ug"``, ``"deg/sqrt(h)"``);
        ``""`` is dimensionless.
    power : int
        Exponent applied (2 for a variance).
    seconds : int or Fraction
        Extra power of the second multiplied in (``Fraction(-1, 2)`` for a
        random-walk intensity, 1 for a PSD of a variance rate).

    Returns
    -------
    str
        ``"m/s^2"``, ``"rad/s^(1/2)"``, ``"-"`` (dimensionless).

    Raises
    ------
    UnitError
        ``unit`` cannot be read.
    """
    u = _ONE if not unit.strip() else (_parse_or_raise(unit, "", need_number=False)[1] or _ONE)
    dims = (u.power(Fraction(power)) * _unit(1.0, {"second": Fraction(seconds)})).dims

    def part(name, e):
        sym = _SI_SYMBOL.get(name, name)
        e = abs(e)
        return sym if e == 1 else (f"{sym}^{e}" if e.denominator == 1 else f"{sym}^({e})")

    num = [part(k, e) for k, e in dims if e > 0]
    den = [part(k, e) for k, e in dims if e < 0]
    text = "*".join(num) or ("1" if den else "-")
    return text + "".join("/" + d for d in den)
