"""The common unit names resolve without building pint's registry, to pint's exact values (issue 13).

:data:`covtool.units.tables.PINNED` holds the SI factor and base-unit
exponents of the usual datasheet names as pint resolves them, so that a
study written in them never imports pint (0.5 s of every run).  Each entry
must equal pint's own resolution bit for bit; a name outside the table is
resolved by pint as before.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from covtool.units import parse_quantity
from covtool.units.tables import PINNED, _resolve, _resolve_pint

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", sorted(PINNED))
def test_every_pinned_unit_equals_pints_resolution(name):
    got, ref = _resolve(name), _resolve_pint(name)
    assert got.factor == ref.factor                 # the same double: numbers cannot change
    assert got.dims == ref.dims


def test_a_shipped_study_parses_without_pint_and_other_names_still_use_it():
    code = ("import sys\n"
            "from covtool.studies import load_study\n"
            "from covtool.studies.zupt_setup import setup\n"
            "d, p = load_study('studies/zupt_filter_order.toml')\n"
            "from covtool.units import parse_quantity\n"
            "v = [parse_quantity(x, k) for x, k in (('0.01 ft/s', 'velocity'), ('20 ug', 'acceleration'),\n"
            "     ('0.018 deg/h', 'angular_rate'), ('0.002 deg/sqrt(h)', 'angle_random_walk'), ('30 min', 'time'))]\n"
            "S = setup(d, path=p)\n"
            "print('pint' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    assert parse_quantity("1 furlong", "length") == _resolve_pint("furlong").factor > 201.0     # by pint
    assert parse_quantity("0.01 ft/s", "velocity") == 0.01 * _resolve_pint("ft").factor
