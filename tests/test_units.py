"""Datasheet units: the grammar, its refusals, and every unit string in the repository.

Every datasheet unit used in models/, studies/, docs/ and the package's own
examples round-trips to a hand-computed SI value (issue 2, acc. 7); every
spelling engineers write gives one SI value or a refusal naming what cannot
be read (issue 9 case 7, issue 10 case 5).
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import pytest

from covtool.errors import UnitError
from covtool.units import from_si, is_unit, parse_quantity, to_si

ROOT = Path(__file__).resolve().parents[1]
G = 9.80665
DEG = math.pi / 180

#: hand-computed SI value of one unit, and its dimension
HAND = {
    "rad": (1.0, "angle"),
    "m": (1.0, "length"),
    "ft/s": (0.3048, "velocity"),
    "mm/s": (1e-3, "velocity"),
    "m/s": (1.0, "velocity"),
    "ug": (1e-6 * G, "acceleration"),
    "mGal": (1e-5, "acceleration"),
    "deg/h": (DEG / 3600, "angular_rate"),
    "ppm": (1e-6, "dimensionless"),
    "arcsec": (DEG / 3600, "angle"),
    "deg/sqrt(h)": (DEG / 60, "angle_random_walk"),
    "ug/sqrt(Hz)": (1e-6 * G, "velocity_random_walk"),
    "deg/h/g": (DEG / 3600 / G, "g_sensitivity"),
    "deg/h/g**2": (DEG / 3600 / G**2, "g2_sensitivity"),
    "min": (60.0, "time"),
    "GB": (8e9, "memory"),               # the unit layer's memory is in bits (pint's base)
    "MiB": (8 * 2.0**20, "memory"),
    "h": (3600.0, "time"),
    "s": (1.0, "time"),
    "km": (1000.0, "length"),
    "Hz": (1.0, "frequency"),
    "ft": (0.3048, "length"),
    "mg": (1e-3 * G, "acceleration"),
    "g": (G, "acceleration"),
    "mrad": (1e-3, "angle"),
    "deg/s": (DEG, "angular_rate"),
    "m/s/sqrt(h)": (1.0 / 60.0, "velocity_random_walk"),
    "mm/s": (1e-3, "velocity"),
    "m/s^2": (1.0, "acceleration"),
    "deg": (DEG, "angle"),
    "ms": (1e-3, "time"),
    "mm": (1e-3, "length"),
    "urad": (1e-6, "angle"),
    "ppm/g": (1e-6 / G, "inverse_acceleration"),
    "km/h": (1000.0 / 3600.0, "velocity"),
    "deg/h/sqrt(h)": (DEG / 3600 / 60, "rate_random_walk"),
}
_Q = re.compile(r"^\s*([-+]?\d*\.?\d+(?:[eE][-+]?\d+)?)\s+([A-Za-zµμ][A-Za-zµμ/*()0-9.^]*)\s*$")


def _strings(obj):
    if isinstance(obj, str):
        yield obj
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from _strings(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _strings(v)


_QUOTED = re.compile(r"""["']([-+]?\d*\.?\d+(?:[eE][-+]?\d+)?\s+[A-Za-zµμ][A-Za-zµμ/*()0-9.^]*)["']""")


def _quantities():
    """(file, value, unit) of every 'number unit' string in models/, studies/, docs/ and covtool/."""
    found = []
    for p in sorted(list((ROOT / "models").rglob("*.toml")) + list((ROOT / "studies").rglob("*.toml"))):
        for s in _strings(tomllib.loads(p.read_text(encoding="utf-8"))):
            m = _Q.match(s)
            if m and not m.group(2).startswith(("state", "states", "run ")):
                found.append((p.relative_to(ROOT).as_posix(), float(m.group(1)), m.group(2).strip()))
    # quoted quantities in the documentation and in the package's docstrings and defaults
    texts = list((ROOT / "docs").rglob("*.md")) + [ROOT / "README.md"] + list((ROOT / "covtool").rglob("*.py"))
    for p in sorted(texts):
        if not p.is_file() or p.name == "units.py":
            continue
        for s in _QUOTED.findall(p.read_text(encoding="utf-8")):
            m = _Q.match(s)
            if m:
                found.append((p.relative_to(ROOT).as_posix(), float(m.group(1)), m.group(2).strip()))
    return found


#: units quoted in the documentation as examples of a refusal (an angular acceleration is no dimension here)
REFUSED_EXAMPLES = {"deg/h/s": "angular_rate", "deg/hr/s": "angular_rate"}
QUANTITIES = [q for q in _quantities() if q[2] not in REFUSED_EXAMPLES]


def test_model_files_use_only_hand_checked_units():
    units = {u for _, _, u in QUANTITIES}
    assert len(QUANTITIES) > 300
    assert {f.split("/")[0] for f, _, _ in QUANTITIES} >= {"models", "studies", "docs", "covtool"}
    assert not (units - set(HAND)), f"add hand-computed values for {sorted(units - set(HAND))}"


@pytest.mark.parametrize("unit,dim", sorted(REFUSED_EXAMPLES.items()))
def test_documented_refusal_examples_are_refused(unit, dim):
    with pytest.raises(UnitError, match=rf"'0\.018 {unit}' is not an angular rate"):
        parse_quantity(f"0.018 {unit}", dim)


@pytest.mark.parametrize("unit", sorted(HAND))
def test_unit_round_trip(unit):
    factor, dim = HAND[unit]
    assert parse_quantity(f"2.5 {unit}", dim) == pytest.approx(2.5 * factor, rel=1e-12)


@pytest.mark.parametrize("fname,value,unit", QUANTITIES)
def test_every_quantity_in_files_parses_to_hand_value(fname, value, unit):
    factor, dim = HAND[unit]
    assert parse_quantity(f"{value} {unit}", dim) == pytest.approx(value * factor, rel=1e-12)


def test_g_means_standard_gravity_not_gram():
    assert parse_quantity("1 g", "acceleration") == pytest.approx(G)
    assert parse_quantity("20 µg", "acceleration") == pytest.approx(20e-6 * G)
    assert parse_quantity("0.1 g", "acceleration") == pytest.approx(0.1 * G)


@pytest.mark.parametrize("text,dim,match", [
    ("0.018 deg/h/s", "angular_rate", r"where: '0.018 deg/h/s' is not an angular rate"),
    ("35 ppm", "angle", r"'35 ppm' is not an angle"),
    ("3 furlongz", "length", r"'3 furlongz': unknown unit"),
    ("20 ug", "angular_rate", r"is not an angular rate"),
    (0.5, "acceleration", r"0.5 has no unit"),
    ("0.018 /h", "angular_rate", r"is not an angular rate"),
])
def test_unit_errors(text, dim, match):
    with pytest.raises(UnitError, match=match):
        parse_quantity(text, dim, where="where")


# --------------------------------------------------------------------------
# the grammar: every spelling engineers write (issue 9 case 7)
# --------------------------------------------------------------------------

PI = math.pi
SQRT_H = math.sqrt(3600.0)        # √h in √s
FT = 0.3048                        # exact, by definition of the international foot
NMI = 1852.0                       # exact, by definition of the nautical mile

#: (string, dimension, SI value computed by hand)
SPELLINGS = [
    # degrees and hours, with and without the square root
    ("0.5 °/√h", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 deg/sqrt(h)", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 degree/sqrt(hr)", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 deg/rt-hr", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 deg/rt(h)", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 deg/√hour", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 deg/h^0.5", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 deg/h**0.5", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 deg/h^(1/2)", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 deg/hr^1/2", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 deg/h½", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 °/rthr", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.5 deg·h^-1/2", "angle_random_walk", 0.5 * PI / 180 / SQRT_H),
    ("0.15 °/√h", "angle_random_walk", 0.15 * PI / 180 / 60),
    ("0.5 °/h", "angular_rate", 0.5 * PI / 180 / 3600),
    ("0.5 deg/hr", "angular_rate", 0.5 * PI / 180 / 3600),
    ("0.5 degree/hour", "angular_rate", 0.5 * PI / 180 / 3600),
    ("0.5 dph", "angular_rate", 0.5 * PI / 180 / 3600),
    ("0.5 °/s", "angular_rate", 0.5 * PI / 180),
    ("0.5 deg/h/√Hz", "angle_random_walk", 0.5 * PI / 180 / 3600),
    ("0.5 deg/h/sqrt(Hz)", "angle_random_walk", 0.5 * PI / 180 / 3600),
    ("0.5 deg/s/rt-Hz", "angle_random_walk", 0.5 * PI / 180),
    ("0.01 deg/h/√h", "rate_random_walk", 0.01 * PI / 180 / 3600 / SQRT_H),
    ("0.01 deg/h/rt(h)", "rate_random_walk", 0.01 * PI / 180 / 3600 / SQRT_H),
    ("0.01 deg/h^1.5", "rate_random_walk", 0.01 * PI / 180 / 3600**1.5),
    # micro: the micro sign, the Greek mu and u; g is standard gravity
    ("20 µg", "acceleration", 20e-6 * 9.80665),
    ("20 μg", "acceleration", 20e-6 * 9.80665),
    ("20 ug", "acceleration", 20e-6 * 9.80665),
    ("20ug", "acceleration", 20e-6 * 9.80665),
    ("2 mg", "acceleration", 2e-3 * 9.80665),
    ("50 ng", "acceleration", 50e-9 * 9.80665),
    ("3 g", "acceleration", 3 * 9.80665),
    ("5 µg/√Hz", "velocity_random_walk", 5e-6 * 9.80665),
    ("5 ug/sqrt(Hz)", "velocity_random_walk", 5e-6 * 9.80665),
    ("5 ug/rtHz", "velocity_random_walk", 5e-6 * 9.80665),
    ("0.05 m/s/√h", "velocity_random_walk", 0.05 / SQRT_H),
    ("0.05 m/s/rt-hr", "velocity_random_walk", 0.05 / SQRT_H),
    ("0.05 ft/s/√h", "velocity_random_walk", 0.05 * FT / SQRT_H),
    # accelerations
    ("9.81 m/s²", "acceleration", 9.81),
    ("9.81 m/s^2", "acceleration", 9.81),
    ("9.81 m/s**2", "acceleration", 9.81),
    ("9.81 m/s/s", "acceleration", 9.81),
    ("9.81 m·s⁻²", "acceleration", 9.81),
    ("9.81 m*s^-2", "acceleration", 9.81),
    ("9.81 m/(s*s)", "acceleration", 9.81),
    ("10 mGal", "acceleration", 10 * 1e-5),
    ("0.1 Gal", "acceleration", 0.1 * 1e-2),
    ("1 ft/s²", "acceleration", FT),
    # dimensionless
    ("35 ppm", "dimensionless", 35e-6),
    ("35 ppb", "dimensionless", 35e-9),
    ("4 %", "dimensionless", 0.04),
    ("4 ‰", "dimensionless", 0.004),
    ("0.25", "dimensionless", 0.25),
    # angles
    ("3 arcsec", "angle", 3 * PI / 180 / 3600),
    ('3 "', "angle", 3 * PI / 180 / 3600),
    ("3″", "angle", 3 * PI / 180 / 3600),
    ("3''", "angle", 3 * PI / 180 / 3600),
    ("3 arcmin", "angle", 3 * PI / 180 / 60),
    ("3′", "angle", 3 * PI / 180 / 60),
    ("3'", "angle", 3 * PI / 180 / 60),
    ("45°", "angle", 45 * PI / 180),
    ("45 deg", "angle", 45 * PI / 180),
    ("45 degrees", "angle", 45 * PI / 180),
    ("2 mrad", "angle", 2e-3),
    ("2 µrad", "angle", 2e-6),
    ("2 μrad", "angle", 2e-6),
    ("2 urad", "angle", 2e-6),
    ("−2 mrad", "angle", -2e-3),
    # velocities and lengths
    ("0.01 ft/s", "velocity", 0.01 * FT),
    ("45 km/h", "velocity", 45 * 1000 / 3600),
    ("10 kn", "velocity", 10 * NMI / 3600),
    ("1 ft", "length", FT),
    ("1 nmi", "length", NMI),
    ("1 nmi/h", "velocity", NMI / 3600),
    ("2.5 km", "length", 2500.0),
    # g-sensitivity, per g
    ("1 deg/h/g", "g_sensitivity", PI / 180 / 3600 / 9.80665),
    ("1 °/h/g", "g_sensitivity", PI / 180 / 3600 / 9.80665),
    ("1 deg/h/g^2", "g2_sensitivity", PI / 180 / 3600 / 9.80665**2),
    ("1 deg/h/g²", "g2_sensitivity", PI / 180 / 3600 / 9.80665**2),
    ("1000 ppm/g", "inverse_acceleration", 1000e-6 / 9.80665),
    # times and frequencies
    ("90 min", "time", 5400.0),
    ("1.5 h", "time", 5400.0),
    ("1.5 hr", "time", 5400.0),
    ("20 ms", "time", 0.02),
    ("100 Hz", "frequency", 100.0),
    ("2 /h", "frequency", 2 / 3600),
    ("2 h^-1", "frequency", 2 / 3600),
    ("1e-3 s", "time", 1e-3),
    ("2.5E+2 s", "time", 250.0),
]


def test_spelling_table_is_large():
    assert len(SPELLINGS) >= 40 and len({s for s, _, _ in SPELLINGS}) == len(SPELLINGS)


@pytest.mark.parametrize("text,dim,si", SPELLINGS)
def test_every_spelling_gives_its_si_value(text, dim, si):
    assert parse_quantity(text, dim, where="w") == pytest.approx(si, rel=1e-12, abs=0)


@pytest.mark.parametrize("text,dim,si", SPELLINGS[:40])
def test_spellings_of_a_dimension_are_units_of_it(text, dim, si):
    unit = text.split(" ", 1)[1] if " " in text else None
    if unit:
        assert is_unit(unit, dim)
        assert to_si(2.0, unit) == pytest.approx(2.0 * parse_quantity(f"1 {unit}", dim), rel=1e-14)
        assert from_si(si, unit) == pytest.approx(float(text.split(" ")[0].replace("−", "-")), rel=1e-12)


#: (value, dimension, message the refusal must match)
REFUSALS = [
    # hostile input is refused by the grammar, before any arithmetic
    ("9**9**9 ug", "acceleration", r"'9\*\*9\*\*9 ug': cannot read '\*\*' at character 2: a number takes no exponent"),
    ("1 ug**9**9", "acceleration",
     r"exponent 9 at character 7 is not allowed \(a non-zero multiple of 1/2 within ±4\)"),
    ("1 ug^100", "acceleration", r"exponent 100 at character 6 is not allowed"),
    ("1 s^3/4", "time", r"exponent 3/4 at character 5 is not allowed"),
    ("1 s^0", "time", r"exponent 0 at character 5 is not allowed"),
    ("1 " + "(" * 7 + "m" + ")" * 7, "length", r"parentheses or roots nested deeper than 6 \(at character 9\)"),
    ("1 " + "m*" * 5000 + "m", "length", r"is 10003 characters long; a quantity has at most 100"),
    ("1 m^^2", "length", r"'1 m\^\^2': unexpected '\^' at character 5; expected an exponent"),
    ("1 ug^ug", "acceleration", r"unexpected 'ug' at character 6; expected an exponent"),
    ("__import__('os') m", "length", r"a quantity starts with a number"),
    ("1 m; 2 s", "length", r"cannot read ';' \(U\+003B\) at character 4"),
    # characters and tokens that cannot be read are named
    ("0.5 º/h", "angular_rate", r"cannot read 'º' \(U\+00BA\) at character 5; the ordinal indicator"),
    ("0.5 deg/h$", "angular_rate", r"cannot read '\$' \(U\+0024\) at character 10"),
    ("0,5 deg/h", "angular_rate", r"cannot read ',' \(U\+002C\) at character 2"),
    ("3 furlongz", "length", r"'3 furlongz': unknown unit 'furlongz' at character 3"),
    ("1 m s", "length", r"unexpected 's' at character 5; write '\*' or '/' between two units"),
    ("1 deg/h g", "g_sensitivity", r"unexpected 'g' at character 9; write '\*' or '/'"),
    ("1 √ h", "time", r"'√' at character 3 must touch the unit it applies to"),
    ("1 √h^3", "time", r"after a square root is ambiguous; write √\(h\^3\) or \(√h\)\^3"),
    ("1 deg/rt hr", "angle_random_walk", r"'rt' is ambiguous"),
    ("1 m/", "length", r"'1 m/': ends too early; expected a unit"),
    ("1 (m", "length", r"ends too early; expected '\)'"),
    ("1 m)", "length", r"unexpected '\)' at character 4"),
    ("1 m 2", "length", r"unexpected '2' at character 5"),
    ("1 m/2", "length", r"unexpected number '2' at character 5; only the leading number may be a number"),
    ("deg/h", "angular_rate", r"'deg/h': a quantity starts with a number"),
    ("", "length", r"'' is empty"),
    # names engineers use for two different things
    ("1 nm", "length", r"'nm' is ambiguous \(nanometre or nautical mile; write nmi"),
    ("1 NM", "length", r"'NM' is ambiguous"),
    ("2 mil", "angle", r"'mil' is ambiguous"),
    ("0.5 G", "acceleration", r"'G' is ambiguous \(gauss or standard gravity; write g"),
    ("10 mgal", "acceleration", r"'mgal' is ambiguous \(milligallon; write mGal"),
    ("1 ppt", "dimensionless", r"'ppt' is ambiguous"),
    ("1 degC", "dimensionless", r"'degC' is an offset unit"),
    # never a different number: a square root of the wrong unit, or mass for g
    ("0.5 °/√h", "angular_rate", r"'0\.5 °/√h' is not an angular rate"),
    ("0.15 °/h", "angle_random_walk", r"'0\.15 °/h' is not an angle random walk"),
    ("0.5 deg/√Hz", "angle_random_walk", r"is not an angle random walk"),
    ("20 kg", "acceleration", r"'20 kg' is not an acceleration"),
    ("35 ppm", "angle", r"'35 ppm' is not an angle"),
    ("5 min", "angle", r"'5 min' is not an angle"),
    ("5 sec", "angle", r"'5 sec' is not an angle"),
    # numbers that are not finite, strings and bare numbers
    ("nan", "dimensionless", r"'nan' is not finite"),
    ("inf ppm", "dimensionless", r"'inf ppm' is not finite"),
    ("-inf ppm", "dimensionless", r"'-inf ppm' is not finite"),
    ("1e999 m", "length", r"'1e999 m' is not finite"),
    (float("nan"), "dimensionless", r"nan is not finite"),
    (float("inf"), "quaternion", r"inf is not finite"),
    (float("-inf"), "acceleration", r"-inf is not finite"),
    (0.5, "acceleration", r"0\.5 has no unit; write it with a unit, e\.g\. '0\.5 ug'"),
    ("0.5", "angle", r"'0\.5' has no unit; write it with a unit, e\.g\. '0\.5 arcsec'"),
    (True, "dimensionless", r"True is not a quantity"),
    ([1], "length", r"\[1\] is not a quantity string"),
]


@pytest.mark.parametrize("value,dim,match", REFUSALS)
def test_refusals_name_what_cannot_be_read(value, dim, match):
    with pytest.raises(UnitError, match=r"^w: .*" + match):
        parse_quantity(value, dim, where="w")


def test_hostile_strings_never_reach_arithmetic(monkeypatch):
    """The grammar refuses them: no unit is ever resolved or multiplied (issue 10 case 5)."""
    import covtool.units as units

    def forbidden(*args, **kwargs):
        raise AssertionError("arithmetic reached")

    units._parse.cache_clear()
    monkeypatch.setattr(units._Unit, "power", forbidden)
    monkeypatch.setattr(units._Unit, "__mul__", forbidden)
    for text in ("9**9**9 ug", "1 ug**9**9", "1 " + "(" * 50 + "m" + ")" * 50, "9" * 10000 + " ug",
                 "1 ug^99999999999999999999", "1 " + "sqrt(" * 40 + "h" + ")" * 40):
        with pytest.raises(UnitError):
            parse_quantity(text, "acceleration", where="w")


def test_bare_zero_any_dimension_and_unitless_where_unambiguous():
    assert parse_quantity(0, "angular_rate") == 0.0
    assert parse_quantity("0", "angular_rate") == 0.0
    assert parse_quantity(0.7, "quaternion") == 0.7
    assert parse_quantity("0.1 rad", "quaternion") == 0.1


def test_units_of_dimensions_and_unit_strings():
    assert is_unit("°/√h", "angle_random_walk") and not is_unit("°/√h", "angular_rate")
    assert is_unit("ug", "acceleration") and not is_unit("ug", "length")
    assert not is_unit("9**9", "dimensionless") and not is_unit("deg/h", "no_such_dimension")
    assert to_si(1.0, "") == 1.0 and to_si(3.0, "1/s") == 3.0
    assert from_si(PI / 180 / 60, "°/√h") == pytest.approx(1.0, rel=1e-14)
    with pytest.raises(UnitError, match=r"'deg/h\$': cannot read '\$'"):
        to_si(1.0, "deg/h$")
    with pytest.raises(UnitError, match=r"unknown dimension 'speed'"):
        parse_quantity("1 m/s", "speed")


def test_ppm_per_g_constant_is_the_parsed_unit():
    """PPM_G (one home, covtool.units) is what the unit layer reads for '1 ppm/g' (1e-15)."""
    from covtool.units import PPM_G
    assert PPM_G == pytest.approx(1e-6 / 9.80665, rel=1e-15)
    assert to_si(1.0, "ppm/g") == pytest.approx(PPM_G, rel=1e-15)
