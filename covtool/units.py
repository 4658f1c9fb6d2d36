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
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from fractions import Fraction
from functools import lru_cache

import pint

from covtool.errors import UnitError

__all__ = ["ureg", "parse_quantity", "to_si", "from_si", "si_unit", "DIMENSIONS", "is_unit", "G0", "FT", "ARCMIN", "ARCSEC",
           "MAX_LENGTH", "MAX_DEPTH", "MAX_EXPONENT"]

ureg = pint.UnitRegistry()

#: standard gravity [m/s^2]
G0 = 9.80665
#: international foot [m]
FT = 0.3048
#: arc minute and arc second [rad]
ARCMIN = math.pi / 180 / 60
ARCSEC = ARCMIN / 60

#: longest quantity string read [characters]
MAX_LENGTH = 100
#: deepest nesting of parentheses (and square roots)
MAX_DEPTH = 6
#: largest |exponent| written after ^ or ** (a multiple of 1/2)
MAX_EXPONENT = 4

#: reference SI units and angle exponent of every dimension covtool uses
DIMENSIONS: dict[str, tuple[str, tuple[int, ...]]] = {
    # name: (SI unit, allowed angle exponents)
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
    "inverse_acceleration": ("s**2/m", (0,)),   # a scale factor per g: '1000 ppm/g'
    "memory": ("bit", (0,)),                    # a memory limit ('6 GB', '512 MiB'); pint's base is the bit
}

_RADIAN = "radian"

# --------------------------------------------------------------------------
# tokens
# --------------------------------------------------------------------------

_NUMBER = re.compile(r"[+\-\u2212]?(?:\d+\.?\d*|\.\d+)(?:[eE][+\-]?\d+)?")
_NAME = re.compile(r"[A-Za-z_\u00b5\u03bc]+")
_SUPER = re.compile(r"[\u207b\u207a]?[\u2070\u00b9\u00b2\u00b3\u2074-\u2079]+|\u00bd")
_SUPER_DIGITS = {"\u2070": "0", "\u00b9": "1", "\u00b2": "2", "\u00b3": "3", "\u2074": "4", "\u2075": "5",
                 "\u2076": "6", "\u2077": "7", "\u2078": "8", "\u2079": "9", "\u207b": "-", "\u207a": "+"}
_EXPONENT = re.compile(r"[+\-\u2212]?(?:\d+(?:\.\d+)?|\.\d+)(?:/\d+)?")
_DIGITS = "0123456789"
_MUL = {"*", "\u00b7", "\u22c5", "\u2219"}          # * · ⋅ ∙
_SYMBOLS = {"\u00b0": "degree", "\u2032": "arcminute", "'": "arcminute", "\u2033": "arcsecond",
            '"': "arcsecond", "''": "arcsecond", "%": "percent", "\u2030": "permille"}
_LOOKALIKE = {"\u00ba": "the ordinal indicator 'º' (U+00BA) is not the degree sign '°' (U+00B0)",
              "\u02da": "the ring above '˚' (U+02DA) is not the degree sign '°' (U+00B0)",
              "\u00d7": "write '*' or '·' for a product"}


@dataclass(frozen=True)
class _Tok:
    kind: str      # num, name, sym, op, lpar, rpar, pow, sup, sqrt, ws, end
    text: str
    pos: int       # 0-based character index


class _Refusal(Exception):
    """Grammar or resolution failure; the message is the problem text."""


def _char(text: str, i: int) -> str:
    ch = text[i]
    return f"{ch!r} (U+{ord(ch):04X}) at character {i + 1}"


def _tokenize(text: str) -> list[_Tok]:
    toks, i, n = [], 0, len(text)
    while i < n:
        ch = text[i]
        if ch.isspace():
            j = i
            while j < n and text[j].isspace():
                j += 1
            toks.append(_Tok("ws", text[i:j], i))
            i = j
            continue
        leading = ch in "+-\u2212" and all(t.kind == "ws" for t in toks)
        if ch in _DIGITS or leading or ch == "." and text[i + 1:i + 2] in _DIGITS and text[i + 1:i + 2]:
            m = _NUMBER.match(text, i)
            if not m:
                if text[i + 1:i + 4].lower() in ("inf", "nan"):
                    raise _Refusal("is not finite")
                raise _Refusal(f"cannot read {_char(text, i)}")
            toks.append(_Tok("num", m.group(), i))
            i = m.end()
            continue
        if ch in "+-\u2212":
            toks.append(_Tok("sign", ch, i))     # in an exponent (s^-1) or after rt (rt-hr)
            i += 1
            continue
        if text.startswith("''", i):
            toks.append(_Tok("sym", "''", i))
            i += 2
            continue
        if ch in _SYMBOLS:
            toks.append(_Tok("sym", ch, i))
            i += 1
            continue
        if ch == "\u221a":                          # √
            toks.append(_Tok("sqrt", ch, i))
            i += 1
            continue
        if text.startswith("**", i):
            toks.append(_Tok("pow", "**", i))
            i += 2
            continue
        if ch == "^":
            toks.append(_Tok("pow", ch, i))
            i += 1
            continue
        if ch in _MUL or ch == "/":
            toks.append(_Tok("op", "*" if ch in _MUL else "/", i))
            i += 1
            continue
        if ch in "()":
            toks.append(_Tok("lpar" if ch == "(" else "rpar", ch, i))
            i += 1
            continue
        m = _SUPER.match(text, i)
        if m:
            toks.append(_Tok("sup", m.group(), i))
            i = m.end()
            continue
        m = _NAME.match(text, i)
        if m:
            toks.append(_Tok("name", m.group(), i))
            i = m.end()
            continue
        hint = _LOOKALIKE.get(ch)
        raise _Refusal(f"cannot read {_char(text, i)}" + (f"; {hint}" if hint else ""))
    toks.append(_Tok("end", "", n))
    return toks


# --------------------------------------------------------------------------
# units as (SI factor, base-unit exponents)
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class _Unit:
    factor: float
    dims: tuple        # sorted ((base unit, Fraction exponent), ...), no zero exponents

    def __mul__(self, other: "_Unit") -> "_Unit":
        d = dict(self.dims)
        for k, e in other.dims:
            d[k] = d.get(k, Fraction(0)) + e
        return _unit(self.factor * other.factor, d)

    def __truediv__(self, other: "_Unit") -> "_Unit":
        return self * other.power(Fraction(-1))

    def power(self, e: Fraction) -> "_Unit":
        return _unit(self.factor ** float(e), {k: v * e for k, v in self.dims})

    @property
    def angle(self) -> Fraction:
        return dict(self.dims).get(_RADIAN, Fraction(0))

    @property
    def physical(self) -> tuple:
        return tuple((k, e) for k, e in self.dims if k != _RADIAN)


def _unit(factor: float, dims: dict) -> _Unit:
    if not (math.isfinite(factor) and factor > 0):
        raise _Refusal("the unit's size is out of range")
    return _Unit(float(factor), tuple(sorted((k, Fraction(e)) for k, e in dims.items() if e != 0)))


_ONE = _Unit(1.0, ())
_ROOT_WORDS = {"rt", "sqrt", "root"}
_G_PREFIX = {"g": 1.0, "ug": 1e-6, "\u00b5g": 1e-6, "\u03bcg": 1e-6, "mg": 1e-3, "ng": 1e-9}
_DOMAIN = {"dph": ("degree", "hour"), "dps": ("degree", "second")}     # datasheet shorthands
_AMBIGUOUS = {
    "nm": "nanometre or nautical mile; write nmi for the nautical mile",
    "NM": "nautical mile or newton metre; write nmi for the nautical mile",
    "mil": "angular mil (1/6400, 1/6000 or 1/6300 of a turn) or thousandth of an inch; write mrad",
    "grade": "road grade or gradian; write % for a grade, gon for the angle",
    "ppt": "parts per thousand or per trillion; write ppm, ppb or %",
    "G": "gauss or standard gravity; write g for standard gravity",
    "mG": "milligauss or milli-g; write mg for milli-g",
    "gal": "gallon; write Gal or mGal for the gal (acceleration)",
    "mgal": "milligallon; write mGal for the milligal (acceleration)",
    "ugal": "microgallon; write uGal for the microgal (acceleration)",
    "rt": "a square root of what? write rt-hr, rt(Hz) or sqrt(h)",
    "sqrt": "a square root of what? write sqrt(h)",
}


@lru_cache(maxsize=1024)
def _resolve(name: str) -> _Unit:
    """One unit name (with an SI prefix) as an SI factor and base units."""
    if name in _G_PREFIX:
        return _unit(_G_PREFIX[name] * G0, {"meter": 1, "second": -2})
    if name in _AMBIGUOUS:
        raise _Refusal(f"{name!r} is ambiguous ({_AMBIGUOUS[name]})")
    if name == "ppb":
        return _unit(1e-9, {})
    if name in _DOMAIN:
        a, b = _DOMAIN[name]
        return _resolve(a) / _resolve(b)
    if name.startswith("rt") and len(name) > 2:
        rest = name[2:].lstrip("_")
        try:
            return _resolve(rest).power(Fraction(1, 2))
        except _Refusal:
            pass
    try:
        unit = ureg.Unit(name)
        q1 = ureg.Quantity(1.0, unit).to_base_units()
        q2 = ureg.Quantity(2.0, unit).to_base_units()
    except Exception:       # pint's resolution errors are assorted
        raise _Refusal(f"unknown unit {name!r}") from None
    if not math.isclose(float(q2.magnitude), 2.0 * float(q1.magnitude), rel_tol=1e-12):
        raise _Refusal(f"{name!r} is an offset unit (a temperature scale)")
    base = q1._units.items()  # noqa: SLF001 - pint has no public API for the base-unit exponents
    return _unit(float(q1.magnitude), {str(k): Fraction(v).limit_denominator(12) for k, v in base})


# --------------------------------------------------------------------------
# parser
# --------------------------------------------------------------------------


class _Parser:
    """Recursive descent over the tokens of one string (see the module grammar)."""

    def __init__(self, text: str):
        self.text = text
        self.toks = [t for t in _tokenize(text)]
        self.i = 0
        self.depth = 0

    # token helpers (whitespace is insignificant except between two factors)
    def _skip(self):
        while self.toks[self.i].kind == "ws":
            self.i += 1

    def peek(self) -> _Tok:
        self._skip()
        return self.toks[self.i]

    def take(self) -> _Tok:
        tok = self.peek()
        self.i += 1
        return tok

    def unexpected(self, tok: _Tok, what: str = "") -> _Refusal:
        if tok.kind == "end":
            return _Refusal("ends too early" + (f"; expected {what}" if what else ""))
        return _Refusal(f"unexpected {tok.text!r} at character {tok.pos + 1}" + (f"; expected {what}" if what else ""))

    def enter(self, tok: _Tok):
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise _Refusal(f"parentheses or roots nested deeper than {MAX_DEPTH} (at character {tok.pos + 1})")

    # grammar
    def quantity(self, *, need_number: bool) -> tuple[float | None, _Unit]:
        tok = self.peek()
        number = None
        if tok.kind == "num":
            self.take()
            number = _to_float(tok.text)
        elif tok.kind == "name" and tok.text.lower() in ("nan", "inf", "infinity"):
            raise _Refusal("is not finite")
        elif need_number:
            raise _Refusal("a quantity starts with a number, e.g. '0.5 deg/h'" if tok.kind != "end"
                           else "is empty")
        if self.peek().kind == "end":
            return number, None
        nxt = self.peek()
        if number is not None and nxt.kind == "pow":
            raise _Refusal(f"cannot read {nxt.text!r} at character {nxt.pos + 1}: a number takes no exponent "
                           "(write 1e-6, not 10**-6)")
        unit = self.expression(top=True)
        tok = self.peek()
        if tok.kind != "end":
            raise self.unexpected(tok)
        return number, unit

    def expression(self, top=False) -> _Unit:
        tok = self.peek()
        if tok.kind == "op" and tok.text == "/":
            self.take()
            result = _ONE / self.term()
        else:
            result = self.term()
        while True:
            # two factors side by side ("m s") are ambiguous next to a '/': refused
            self._check_juxtaposition()
            tok = self.peek()
            if tok.kind != "op":
                return result
            self.take()
            rhs = self.term()
            result = result * rhs if tok.text == "*" else result / rhs

    def _check_juxtaposition(self):
        j = self.i
        if self.toks[j].kind != "ws":
            return
        while self.toks[j].kind == "ws":
            j += 1
        nxt = self.toks[j]
        if nxt.kind in ("name", "sym", "sqrt", "lpar", "num"):
            raise _Refusal(f"unexpected {nxt.text!r} at character {nxt.pos + 1}; write '*' or '/' between "
                           "two units")

    def term(self) -> _Unit:
        base, rooted = self.factor()
        j = self.i                          # look past whitespace without consuming it
        while self.toks[j].kind == "ws":
            j += 1
        tok = self.toks[j]
        if tok.kind in ("pow", "sup"):
            if rooted:
                raise _Refusal(f"exponent {tok.text!r} at character {tok.pos + 1} after a square root is "
                               "ambiguous; write √(h^3) or (√h)^3")
            self.take()
            e = self.exponent(tok)
            return base.power(e)
        return base

    def exponent(self, tok: _Tok) -> Fraction:
        if tok.kind == "sup":
            text = "".join(_SUPER_DIGITS.get(c, c) for c in tok.text)
            e = Fraction(1, 2) if text == "\u00bd" else Fraction(int(text))
            return _check_exponent(e, tok.text, tok.pos)
        nxt = self.peek()
        if nxt.kind == "lpar":
            self.take()
            inner = self.peek()
            e = self._exponent_literal()
            close = self.take()
            if close.kind != "rpar":
                raise self.unexpected(close, "')'")
            return _check_exponent(e, self.text[inner.pos:close.pos], inner.pos)
        if nxt.kind == "sup" and nxt.text == "\u00bd":
            self.take()
            return Fraction(1, 2)
        return _check_exponent(self._exponent_literal(), None, nxt.pos)

    def _exponent_literal(self) -> Fraction:
        self._skip()
        tok = self.toks[self.i]
        m = _EXPONENT.match(self.text, tok.pos)
        if not m:
            raise self.unexpected(tok, "an exponent such as 2, -1 or 1/2")
        # re-tokenize from the end of the literal: the exponent's characters were tokenised differently
        end = m.end()
        while self.toks[self.i].pos < end and self.toks[self.i].kind != "end":
            self.i += 1
        if self.toks[self.i].pos != end and self.toks[self.i].kind != "end":
            raise self.unexpected(self.toks[self.i])
        lit = m.group().replace("\u2212", "-")
        try:
            return Fraction(lit)
        except (ValueError, ZeroDivisionError):
            raise _Refusal(f"exponent {m.group()!r} at character {tok.pos + 1} is not a number") from None

    def factor(self) -> tuple[_Unit, bool]:
        tok = self.take()
        if tok.kind == "lpar":
            self.enter(tok)
            u = self.expression()
            close = self.take()
            if close.kind != "rpar":
                raise self.unexpected(close, "')'")
            self.depth -= 1
            return u, False
        if tok.kind == "sqrt":                       # √h, √(h), √Hz
            self.enter(tok)
            if self.toks[self.i].kind == "ws":
                raise _Refusal(f"'√' at character {tok.pos + 1} must touch the unit it applies to")
            inner, _ = self.factor()
            self.depth -= 1
            return inner.power(Fraction(1, 2)), True
        if tok.kind == "sym":
            return _resolve(_SYMBOLS[tok.text]), False
        if tok.kind == "name":
            if tok.text in _ROOT_WORDS:
                nxt = self.toks[self.i]
                if nxt.kind == "lpar" or nxt.kind == "sign" and nxt.text != "+":
                    self.enter(tok)
                    if nxt.kind == "sign":
                        self.i += 1
                        if self.toks[self.i].kind != "name":
                            raise self.unexpected(self.toks[self.i], "a unit after 'rt-'")
                        inner, _ = self.factor()
                    else:
                        inner, _ = self.factor()
                    self.depth -= 1
                    return inner.power(Fraction(1, 2)), True
            try:
                return _resolve(tok.text), False
            except _Refusal as exc:
                msg = str(exc)
                if msg.startswith("unknown unit"):
                    msg += f" at character {tok.pos + 1}"
                raise _Refusal(msg) from None
        if tok.kind == "num":
            raise _Refusal(f"unexpected number {tok.text!r} at character {tok.pos + 1}; only the leading "
                           "number may be a number")
        raise self.unexpected(tok, "a unit")


def _check_exponent(e: Fraction, text, pos) -> Fraction:
    if e.denominator not in (1, 2) or abs(e) > MAX_EXPONENT or e == 0:
        shown = text if text is not None else str(e)
        raise _Refusal(f"exponent {shown} at character {pos + 1} is not allowed (a non-zero multiple of 1/2 "
                       f"within ±{MAX_EXPONENT})")
    return e


def _to_float(text: str) -> float:
    x = float(text.replace("\u2212", "-"))
    if not math.isfinite(x):
        raise _Refusal("is not finite")
    return x


@lru_cache(maxsize=4096)
def _parse(text: str, need_number: bool = True) -> tuple[float | None, _Unit]:
    if len(text) > MAX_LENGTH:
        raise _Refusal(f"is {len(text)} characters long; a quantity has at most {MAX_LENGTH}")
    return _Parser(text).quantity(need_number=need_number)


def _parse_or_raise(text: str, where: str, need_number: bool = True):
    try:
        return _parse(text, need_number)
    except _Refusal as exc:
        shown = text if len(text) <= 40 else text[:40] + "…"
        msg = str(exc)
        sep = " " if msg.startswith("is ") else ": "
        raise UnitError(where, f"{shown!r}{sep}{msg}") from None


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
