"""Every datasheet unit used in models/ round-trips to hand-computed SI (issue 2, acc. 7)."""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

import pytest

from covtool.errors import UnitError
from covtool.units import parse_quantity

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


def _quantities():
    """(file, value, unit) of every 'number unit' string in models/."""
    found = []
    for p in sorted((ROOT / "models").rglob("*.toml")):
        for s in _strings(tomllib.loads(p.read_text())):
            m = _Q.match(s)
            if m:
                found.append((p.name, float(m.group(1)), m.group(2).strip()))
    return found


QUANTITIES = _quantities()


def test_model_files_use_only_hand_checked_units():
    units = {u for _, _, u in QUANTITIES}
    assert len(QUANTITIES) > 20
    assert not (units - set(HAND)), f"add hand-computed values for {sorted(units - set(HAND))}"


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
