"""Unit tables: constants, dimensions, and units as (SI factor, base units).

The reference SI unit and allowed angle exponent of every dimension covtool
uses (:data:`DIMENSIONS`), the datasheet constants (:data:`G0`, :data:`FT`,
:data:`ARCMIN`, :data:`ARCSEC`), the grammar's limits, the ``_Unit`` value
(SI factor and base-unit exponents, with the radian kept as its own
pseudo-dimension) and the resolution of one unit name by pint
(``_resolve``, with the datasheet shorthands and the ambiguous names).
The grammar that combines names is in :mod:`covtool.units.grammar`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from functools import lru_cache



@lru_cache(maxsize=1)
def registry():
    """pint's unit registry, built on first use (importing pint and building it costs ~0.5 s)."""
    import pint

    return pint.UnitRegistry()


def __getattr__(name):
    if name == "ureg":                    # covtool.units.tables.ureg, as before: built when first asked for
        return registry()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: standard gravity [m/s^2]
G0 = 9.80665
#: international foot [m]
FT = 0.3048
#: SI per unit of the output lengths a study may choose (``[output] units``) [m]
OUTPUT_LENGTHS = {"ft": FT, "m": 1.0}
#: arc minute and arc second [rad]
ARCMIN = math.pi / 180 / 60
ARCSEC = ARCMIN / 60
#: 1 ppm/g (a g-sensitivity coefficient) [1/(m/s^2)]
PPM_G = 1e-6 / G0

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


class _Refusal(Exception):
    """Grammar or resolution failure; the message is the problem text."""


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


#: the common unit names as pint resolves them (SI factor, base-unit exponents), so that a study
#: written in them needs no registry; tests/test_units_pinned.py checks every entry against pint
PINNED: dict[str, tuple[float, tuple]] = {
    "s": (1.0, (("second", "1"),)),
    "ms": (0.001, (("second", "1"),)),
    "us": (1e-06, (("second", "1"),)),
    "min": (60.0, (("second", "1"),)),
    "h": (3600.0, (("second", "1"),)),
    "hr": (3600.0, (("second", "1"),)),
    "hour": (3600.0, (("second", "1"),)),
    "day": (86400.0, (("second", "1"),)),
    "Hz": (1.0, (("second", "-1"),)),
    "kHz": (1000.0, (("second", "-1"),)),
    "m": (1.0, (("meter", "1"),)),
    "km": (1000.0, (("meter", "1"),)),
    "mm": (0.001, (("meter", "1"),)),
    "cm": (0.01, (("meter", "1"),)),
    "ft": (0.30479999999999996, (("meter", "1"),)),
    "nmi": (1852.0, (("meter", "1"),)),
    "mi": (1609.344, (("meter", "1"),)),
    "deg": (0.017453292519943295, (("radian", "1"),)),
    "degree": (0.017453292519943295, (("radian", "1"),)),
    "rad": (1.0, (("radian", "1"),)),
    "radian": (1.0, (("radian", "1"),)),
    "mrad": (0.001, (("radian", "1"),)),
    "urad": (1e-06, (("radian", "1"),)),
    "arcmin": (0.00029088820866572163, (("radian", "1"),)),
    "arcsec": (4.84813681109536e-06, (("radian", "1"),)),
    "ppm": (1e-06, ()),
    "percent": (0.01, ()),
    "mGal": (1e-05, (("meter", "1"), ("second", "-2"))),
    "uGal": (1e-08, (("meter", "1"), ("second", "-2"))),
    "Gal": (0.01, (("meter", "1"), ("second", "-2"))),
    "bit": (1.0, (("bit", "1"),)),
    "byte": (8.0, (("bit", "1"),)),
    "B": (8.0, (("bit", "1"),)),
    "kB": (8000.0, (("bit", "1"),)),
    "MB": (8000000.0, (("bit", "1"),)),
    "GB": (8000000000.0, (("bit", "1"),)),
    "KiB": (8192.0, (("bit", "1"),)),
    "MiB": (8388608.0, (("bit", "1"),)),
    "GiB": (8589934592.0, (("bit", "1"),)),
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
    if name in PINNED:
        factor, dims = PINNED[name]
        return _unit(factor, {k: Fraction(e) for k, e in dims})
    return _resolve_pint(name)


def _resolve_pint(name: str) -> _Unit:
    """One unit name resolved by pint's registry."""
    ureg = registry()
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

