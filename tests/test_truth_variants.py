"""Truth-model variants declared as overrides of a base model (issue 11, item 5)."""

from __future__ import annotations

from pathlib import Path

import pytest

from covtool.errors import ModelFileError
from covtool.io.model_file import dump_model, load_model, model_from_dict, resolve_base
from covtool.units import parse_quantity

ROOT = Path(__file__).resolve().parents[1]


def test_uncalibrated_variant_differs_only_in_the_misalignments():
    base = load_model(ROOT / "models" / "sdins58.toml")
    var = load_model(ROOT / "models" / "sdins58_uncalibrated.toml")
    assert var.name == "sdins58_uncalibrated" and var.names == base.names
    ten, two = parse_quantity("10 arcsec", "angle"), parse_quantity("2 arcsec", "angle")
    for a, b in zip(var.states, base.states):
        if a.block in ("acc_mis", "gyro_mis"):
            assert a.sigma == pytest.approx(ten) and b.sigma == pytest.approx(two), a.name
            assert "uncalibrated" in a.source
        else:
            assert a == b, a.name
    assert (var.arw, var.vrw) == (base.arw, base.vrw)
    # the merged declaration round-trips without its base
    again = model_from_dict(__import__("tomllib").loads(dump_model(var)), path="x.toml")
    assert [s.sigma for s in again.states] == [s.sigma for s in var.states]


@pytest.mark.parametrize("decl,match", [
    ({"model": {"name": "v", "base": "sdins58"}, "override": {"acc_miss": {"sigma": "1 arcsec"}}},
     r"v.toml: \[override.acc_miss\]: base model 'sdins58' has no block 'acc_miss'"),
    ({"model": {"name": "v", "base": "sdins58"}, "override": {"acc_mis": {"kind": "gyro_bias"}}},
     r"\[override.acc_mis\] kind: the kind and name of a base block cannot be overridden"),
    ({"model": {"name": "v"}, "override": {"acc_mis": {"sigma": "1 arcsec"}}},
     r"v.toml: override: overrides need \[model\] base"),
    ({"model": {"name": "v", "base": "nosuchmodel"}}, r"nosuchmodel: no such model"),
    ({"model": {"name": "v", "base": "sdins58"}, "override": {"acc_mis": "1 arcsec"}},
     r"\[override.acc_mis\]: expected a table of block keys"),
])
def test_variant_errors(decl, match):
    with pytest.raises(ModelFileError, match=match):
        resolve_base(decl, str(ROOT / "models" / "v.toml"))


def test_base_with_a_base_is_refused(tmp_path):
    (tmp_path / "a.toml").write_text('[model]\nname = "a"\nbase = "b"\n')
    (tmp_path / "c.toml").write_text('[model]\nname = "c"\nbase = "a"\n')
    with pytest.raises(ModelFileError, match=r"c.toml: \[model\] base: 'a' has a base itself"):
        load_model(tmp_path / "c.toml")


def test_variant_from_a_dict_resolves_its_base():
    """A declaration passed as a dict is resolved like a file (no silently ignored overrides)."""
    m = model_from_dict({"model": {"name": "v", "base": "sdins58"},
                         "override": {"gyro_mis": {"sigma": "7 arcsec"}}}, path="<dict>")
    s = m.states[m.index["gyro_mis_xz"]]
    assert s.sigma == pytest.approx(parse_quantity("7 arcsec", "angle"))
    assert m.states[m.index["acc_mis_xz"]].sigma == pytest.approx(parse_quantity("2 arcsec", "angle"))
