"""Typed study configurations: every shipped study loads, dumps and loads back equal; messages name the key."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest

from covtool.errors import StudyFileError
from covtool.studies import KINDS as RUNNER_KINDS
from covtool.studies.config import KINDS, dump_config, load_config, parse_section, ZuptSection, StudySection

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = sorted((ROOT / "studies").glob("*.toml"))


def test_every_runner_kind_has_a_configuration():
    assert set(KINDS) == set(RUNNER_KINDS)


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_shipped_study_round_trips(path):
    decl = tomllib.loads(path.read_text())
    cfg = load_config(decl, str(path))
    assert type(cfg) is KINDS[decl["study"]["kind"]]
    again = load_config(dump_config(cfg), str(path))
    assert again == cfg
    # frozen: a configuration is varied by model_copy(update=...), never in place
    with pytest.raises(Exception, match="frozen"):
        cfg.study.duration = 1.0


def test_quantities_are_si_and_defaults_come_from_the_declarations():
    cfg = load_config({"study": {"kind": "zupt_filter_order", "duration": "6 min"}})
    assert cfg.study.duration == 360.0 and cfg.study.dt == 1.0
    assert cfg.zupt.interval == 300.0 and cfg.zupt.duration == 30.0 and cfg.zupt.rate == 1.0
    assert cfg.zupt.sigma == pytest.approx(0.01 * 0.3048, rel=1e-15)
    assert cfg.trajectory.cycles == 6 and cfg.trajectory.turn_rate == pytest.approx(math.radians(5), rel=1e-15)
    assert cfg.truth.override_filters is False and cfg.filters.pure_ins is True
    varied = cfg.model_copy(update={"zupt": cfg.zupt.model_copy(update={"interval": 180.0})})
    assert varied.zupt.interval == 180.0 and cfg.zupt.interval == 300.0


@pytest.mark.parametrize("decl,match", [
    ({"study": {"kind": "pure_ins", "duration": "5 kg"}}, r"^s.toml: \[study\] duration: '5 kg' is not a time"),
    ({"study": {"kind": "pure_ins", "durtion": "5 min"}}, r"^s.toml: \[study\]: unknown key 'durtion' \(allowed: "),
    ({"study": {"kind": "pure_ins"}, "zupt": {}}, r"^s.toml: unknown key 'zupt' \(allowed: output, study, "),
    ({"study": {"kind": "puer_ins"}}, r"^s.toml: \[study\]: unknown kind 'puer_ins'"),
    ({"study": {"kind": "zupt_filter_order"}, "zupt": {"sigma": "0 ft/s"}},
     r"^s.toml: \[zupt\] sigma: '0 ft/s' must be positive"),
    ({"study": {"kind": "monte_carlo"}, "monte_carlo": {}}, r"^s.toml: \[monte_carlo\]: missing required key 'runs'"),
    ({"study": {"kind": "monte_carlo"}, "monte_carlo": {"runs": 1}},
     r"^s.toml: \[monte_carlo\] runs: 1 is not an integer in 2..10_000"),
    ({"study": {"kind": "pure_ins"}, "trajectory": {"builtin": "land_vehicle", "period": "5 kg"}},
     r"^s.toml: \[trajectory\] period: '5 kg' is not a time"),
    ({"study": {"kind": "pure_ins"}, "trajectory": {"builtin": "land_vehicle", "perod": "5 min"}},
     r"^s.toml: \[trajectory\]: unknown key 'perod'"),
    ({"study": {"kind": "pure_ins"}, "output": {"report_times": ["1 min", "2 kg"]}},
     r"^s.toml: \[output\] report_times\[1\]: '2 kg' is not a time"),
])
def test_refusals_are_one_line_naming_file_section_key(decl, match):
    with pytest.raises(StudyFileError, match=match):
        load_config(decl, "s.toml")


_GNSS = {"name": "gnss", "kind": "gnss_position", "sigma": "1 m"}


@pytest.mark.parametrize("decl,match", [
    ({"study": {"kind": "aided"}}, r"^s.toml: missing required key 'measurement'"),
    ({"study": {"kind": "aided"}, "measurement": []}, r"^s.toml: \[measurement\]: .*at least 1 item"),
    ({"study": {"kind": "aided"}, "measurement": [{**_GNSS, "kind": "gps"}]},
     r"^s.toml: \[\[measurement\]\] #1 kind: 'gps' is not one of: 'zupt', 'cupt', "),
    ({"study": {"kind": "aided"}, "measurement": [{**_GNSS, "name": "2gnss"}]},
     r"^s.toml: \[\[measurement\]\] #1 name: '2gnss' must start with a letter and hold only letters, digits "),
    ({"study": {"kind": "aided"}, "measurement": [_GNSS, {**_GNSS, "sigma": "2 m"}]},
     r"^s.toml: \[\[measurement\]\] #2 name: 'gnss' is used twice"),
    ({"study": {"kind": "aided"}, "measurement": [{**_GNSS, "lever_arm": ["1 m", "2 m"]}]},
     r"^s.toml: \[\[measurement\]\] #1 lever_arm: expected three lengths \(body x, y, z\)"),
    ({"study": {"kind": "aided"}, "measurement": [{**_GNSS, "lever_arm": ["1 m", "2 s", "0 m"]}]},
     r"^s.toml: \[\[measurement\]\] #1 lever_arm\[1\]: '2 s' is not a length"),
    ({"study": {"kind": "aided"}, "measurement": [{**_GNSS, "errors": {"N": {"sigma": "1 m", "process": "markov"}}}]},
     r"^s.toml: \[\[measurement\]\] #1 errors.N: a markov error needs 'tau'"),
    ({"study": {"kind": "aided"}, "measurement": [{**_GNSS, "errors": {"N": {"sigma": "1 m", "tau": "1 min"}}}]},
     r"^s.toml: \[\[measurement\]\] #1 errors.N: only a markov state has a correlation time"),
    ({"study": {"kind": "aided"}, "measurement": [{**_GNSS, "errors": {"N": {"sigma": "1 m", "taux": 1}}}]},
     r"^s.toml: \[\[measurement\]\] #1 errors.N: unknown key 'taux'"),
    ({"study": {"kind": "aided"}, "measurement": [{**_GNSS, "schedule": {"period": "1 s", "rate": "1 Hz"}}]},
     r"^s.toml: \[\[measurement\]\] #1 schedule: give period or rate, not both"),
    ({"study": {"kind": "aided"}, "measurement": [{**_GNSS, "schedule": {"when": "parked"}}]},
     r"^s.toml: \[\[measurement\]\] #1 schedule.when: 'parked' is not one of: 'always', 'moving', "),
    ({"study": {"kind": "aided"}, "measurement": [_GNSS], "filters": {"variant": [{"name": "v", "base": "B1"}]}},
     r"^s.toml: \[filters\] variant #1: missing required key 'drop'"),
    ({"study": {"kind": "aided"}, "measurement": [_GNSS], "grade": [{"name": "g", "scale": 1e4}]},
     r"^s.toml: \[\[grade\]\] #1 scale: 10000.0 is not a number >= 0.001 and <= 1000 \(a grade scales every "),
    ({"study": {"kind": "aided"}, "measurement": [_GNSS], "grade": [{"name": "g", "scale": 1}, {"name": "g",
                                                                                                "scale": 2}]},
     r"^s.toml: \[\[grade\]\] #2 name: 'g' is used twice"),
])
def test_aided_refusals_name_the_entry_and_key(decl, match):
    with pytest.raises(StudyFileError, match=match):
        load_config(decl, "s.toml")


def test_aided_configuration_holds_si_and_the_library_defaults():
    cfg = load_config({"study": {"kind": "aided"}, "measurement": [
        {**_GNSS, "lever_arm": ["1 ft", "0 m", "-2 m"], "schedule": {"rate": "2 Hz", "outages": [["1 min", "2 min"]]},
         "errors": {"N": {"sigma": "1 m", "process": "markov", "tau": "10 min"}}}]}, "s.toml")
    m = cfg.measurement[0]
    assert m.lever_arm == pytest.approx((0.3048, 0.0, -2.0), rel=1e-15)
    assert m.schedule.rate == 2.0 and m.schedule.period is None and m.schedule.when == "always"
    assert m.errors["N"].tau == 600.0 and m.errors["N"].process == "markov"
    assert cfg.grade is None and cfg.filters.variant == () and cfg.filters.ewn_interval is None
    assert load_config(dump_config(cfg), "s.toml") == cfg


def test_parse_section_refuses_unknown_keys_first():
    with pytest.raises(StudyFileError, match=r"^s.toml: \[zupt\]: unknown key 'intreval' \(allowed: duration, "
                                             r"first, interval, rate, sigma\)"):
        parse_section(ZuptSection, {"intreval": "3 min", "sigma": -1}, "s.toml", "zupt")
    with pytest.raises(StudyFileError, match=r"^s.toml: \[study\]: expected a table, got list"):
        parse_section(StudySection, [1], "s.toml", "study")


def test_land_vehicle_declared_defaults_are_the_profiles():
    """The reference and `covtool new` show the declared defaults; the route must use the same ones."""
    import inspect

    from covtool.nav.trajectory.profiles import land_vehicle
    from covtool.studies.config import LandVehicle

    declared = LandVehicle()
    params = inspect.signature(land_vehicle).parameters
    for key in LandVehicle.model_fields:
        if key in params:
            assert getattr(declared, key) == pytest.approx(params[key].default, rel=1e-15), key
