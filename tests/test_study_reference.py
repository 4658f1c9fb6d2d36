"""The study-file reference (docs/study_files.md) and `covtool new` against the parsers (issue 14 acc. 1, 3)."""

from __future__ import annotations

import copy
import re
import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest
import tomli_w

from covtool.errors import InputError
from covtool.studies import config as C
from covtool.studies.reference import (FILTER_FILE_KEYS, MODEL_FILE_KEYS, _all_sections, new_study, section_keys,
                                       study_files_markdown)

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "study_files.md"
STUDIES = ROOT / "studies"
UNKNOWN = "zz_not_a_key"


def test_committed_reference_is_the_generated_one():
    """Regenerate with: python -m covtool.studies.reference > docs/study_files.md"""
    assert DOC.read_text(encoding="utf-8") == study_files_markdown()


def _doc_tables() -> dict[str, set[str]]:
    """``### heading`` -> the keys in the first column of the table under it."""
    out, head = {}, None
    for line in DOC.read_text(encoding="utf-8").splitlines():
        if line.startswith("### "):
            head = line[4:].strip()
            out[head] = set()
        elif line.startswith("## "):
            head = None
        elif head and line.startswith("| `"):
            out[head].add(line.split("`")[1])
    return out


def test_every_declared_key_is_in_the_reference():
    tables = _doc_tables()
    sections = _all_sections()
    assert len(sections) >= 40
    for s in sections:
        # a [[array]] section's heading closes its brackets before any qualifier: "[[grade]] (aided)"
        head = f"[{s.name}" if s.name.startswith("[") else f"[{s.name}]"
        assert head.count("[") == head.count("]"), head
        assert set(section_keys(s)) == tables[head], s.__name__
    for tab, keys in MODEL_FILE_KEYS.items():
        assert set(keys) == tables[tab]
    doc = DOC.read_text(encoding="utf-8")
    for k in FILTER_FILE_KEYS:
        assert f"| `{k}` |" in doc
    for kind in C.KINDS:
        assert f"| `{kind}` |" in doc and f"### {kind}\n" in doc


# ---------------------------------------------------------------------------
# the declarations against the keys the parsers accept
# ---------------------------------------------------------------------------

def _allowed(call) -> set[str]:
    """The keys a parser accepts, from its refusal of an unknown key ("allowed: a, b, c")."""
    with pytest.raises(InputError, match=f"unknown key '{UNKNOWN}'") as exc:
        call()
    m = re.search(r"\(allowed: ([^)]*)\)", str(exc.value))
    return set(m.group(1).split(", "))


def _decl(name):
    return tomllib.loads((STUDIES / name).read_text())


def _inject(decl, path, key=UNKNOWN):
    d = copy.deepcopy(decl)
    t = d
    for p in path:
        t = t.setdefault(p, {}) if not isinstance(p, int) else t[p]
    t[key] = 1
    return d


def test_shared_sections_match_their_parsers():
    from covtool.studies.inputs import load_truth, output_options, study_header
    from covtool.studies.zupt_setup import setup, zupt_options

    flag = _decl("zupt_filter_order.toml")
    assert _allowed(lambda: study_header(_inject(flag, ["study"]), "s")) == set(section_keys(C.StudySection))
    assert _allowed(lambda: output_options(_inject(flag, ["output"]), "s", 1800.0)) == \
        set(section_keys(C.OutputSection))
    assert _allowed(lambda: zupt_options(_inject(flag, ["zupt"])["zupt"], "s", 1.0, 1800.0)) == \
        set(section_keys(C.ZuptSection))
    assert _allowed(lambda: load_truth(_inject(flag, ["truth"]), "s", None)) == set(section_keys(C.TruthSection))
    assert _allowed(lambda: load_truth({"truth": {"override": {"acc_bias": {UNKNOWN: 1}}}}, "s", None)) == \
        set(section_keys(C.OverrideEntry))
    assert _allowed(lambda: setup(_inject(flag, ["filters"]))) == set(section_keys(C.FiltersSection))
    # the whole file is parsed into its kind's configuration (zupt_filter_order: the ZUPT sections and [impact])
    assert _allowed(lambda: setup(_inject(flag, []))) == set(C.ZuptFilterOrderConfig.model_fields)


def test_trajectory_declarations_match_their_parsers():
    from covtool.io.flight import _INITIAL_DIMS, SEGMENT_KEYS
    from covtool.io.trajectory import _INITIAL_KEYS, BUILTINS
    from covtool.nav.trajectory.segments import SEGMENT_KINDS

    assert set(section_keys(C.LandVehicle)) == set(BUILTINS["land_vehicle"]) | {"builtin", "name"}
    assert set(section_keys(C.Static)) == set(BUILTINS["static"]) | {"builtin", "name"}
    assert set(section_keys(C.Initial)) == set(_INITIAL_KEYS)
    assert set(section_keys(C.Segment)) == {k for keys in SEGMENT_KINDS.values() for k in keys}
    assert set(section_keys(C.FlightInitial)) == set(_INITIAL_DIMS)
    assert set(section_keys(C.FlightSegment)) == {k for keys in SEGMENT_KEYS.values() for k in keys}
    from covtool.io.trajectory import trajectory_from_config
    seg = {"segment": [{"kind": "stand", "duration": "1 s"}], "initial": {"lat": "1 deg", "lon": "1 deg", "h": "0 m"}}
    assert _allowed(lambda: trajectory_from_config({**seg, UNKNOWN: 1}, where="s", base_dir=None, dt=1.0)) == \
        set(section_keys(C.Segments))
    assert _allowed(lambda: trajectory_from_config({"csv": "x.csv", UNKNOWN: 1}, where="s", base_dir=None,
                                                   dt=1.0)) == set(section_keys(C.CsvTrajectory))


def test_kind_sections_match_their_parsers():
    from covtool.studies.error_budget import budget_options
    from covtool.studies.monte_carlo import MC_KEYS
    from covtool.studies.zupt_filter_order import impact_filters
    from covtool.studies.zupt_sensitivity import COST_KEYS, SWEEP_KEYS, sweep_options
    from covtool.studies.magnitude_sweep import sweep_options as mag_sweep

    assert set(section_keys(C.MonteCarloSection)) == set(MC_KEYS)
    assert set(section_keys(C.SensitivitySweep)) == SWEEP_KEYS
    assert set(section_keys(C.CostSection)) == COST_KEYS
    # the trade grid's [grid] and [[grade]] are parsed by their declarations (no parser of their own)
    assert _allowed(lambda: budget_options({"budget": {UNKNOWN: 1}}, "s")) == set(section_keys(C.BudgetSection))
    assert _allowed(lambda: impact_filters({"impact": {UNKNOWN: 1}}, SimpleNamespace(where="s"))) == \
        set(section_keys(C.ImpactSection))
    assert _allowed(lambda: sweep_options({"scales": {"from": 1, "to": 2, "per_decade": 1, UNKNOWN: 1}}, "s")) == \
        set(section_keys(C.Scales))
    mis = _decl("misalignment_sweep.toml")
    assert _allowed(lambda: mag_sweep(_inject(mis, ["sweep"]), "s", None)) == set(section_keys(C.MagnitudeSweep))
    assert _allowed(lambda: mag_sweep(_inject(mis, ["sweep", "group", 0]), "s", None)) == \
        set(section_keys(C.SweepGroup))


def test_dual_imu_and_board_sections_match_their_parsers():
    from covtool.studies.ad_reset_config import parse
    from covtool.studies.dual_imu_config import parse_study

    dual = _decl("dual_imu_flight.toml")
    cases = [([], C.DualImuConfig), (["study"], C.StudySectionShort), (["imu"], C.ImuSection),
             (["alignment"], C.DualAlignment), (["comparison"], C.Comparison), (["monitor"], C.Monitor),
             (["gaps"], C.Gaps), (["simulation"], C.Simulation), (["simulation", "fault"], C.Fault),
             (["simulation", "gap", 0], C.GapEntry)]
    for path, cls in cases:
        keys = set(cls.model_fields) if cls is C.DualImuConfig else set(section_keys(cls))
        assert _allowed(lambda: parse_study(_inject(dual, path), "s", STUDIES)) == keys, path
    kimu = _allowed(lambda: parse_study(_inject(dual, ["imu", "kimu"]), "s", STUDIES))
    main = _allowed(lambda: parse_study(_inject(dual, ["imu", "main"]), "s", STUDIES))
    assert kimu == set(section_keys(C.ImuUnit)) and main == kimu - {"ratio"}
    board = _decl("ad_reset_scale_error.toml")
    cases = [([], C.AdResetConfig), (["study"], C.AdResetStudySection), (["board"], C.Board),
             (["output_filter"], C.OutputFilter), (["navigation"], C.BoardNavigation),
             (["alignment"], C.BoardAlignment), (["alignment", "coarse"], C.Gains),
             (["alignment", "prefilter"], C.Prefilter), (["sweeps"], C.Sweeps), (["reference"], C.Reference),
             (["reference", "table1"], C.ReferenceTable)]
    for path, cls in cases:
        keys = set(cls.model_fields) if cls is C.AdResetConfig else set(section_keys(cls))
        assert _allowed(lambda: parse(_inject(board, path), None)) == keys, path


def test_filter_and_model_file_keys_match_their_parsers():
    from covtool.io.filters import _FILTER_KEYS
    from covtool.io import model_file as mf

    assert set(FILTER_FILE_KEYS) == _FILTER_KEYS
    assert set(MODEL_FILE_KEYS["[model]"]) == mf._MODEL_KEYS
    assert set(MODEL_FILE_KEYS["(top level)"]) == mf._TOP_KEYS
    assert set(MODEL_FILE_KEYS["[[block]] (kind = \"navigation\")"]) == mf._NAV_KEYS
    assert set(MODEL_FILE_KEYS["[[block]] (sensor and environment blocks)"]) == mf._BLOCK_KEYS
    assert set(MODEL_FILE_KEYS["[block.board]"]) == mf._BOARD_KEYS


# ---------------------------------------------------------------------------
# covtool new KIND > s.toml && covtool run s.toml
# ---------------------------------------------------------------------------

#: shortened through the file's own keys, so the test runs in seconds
SHORTEN = {
    "zupt_filter_order": {"study": {"duration": "6 min"}, "filters": {"cases": ["B1", "D"]}},
    "error_budget": {"study": {"duration": "6 min"}},
    "zupt_sensitivity": {"study": {"duration": "6 min"}},
    "monte_carlo": {"study": {"duration": "6 min"}, "monte_carlo": {"runs": 2, "runs_per_chunk": 2}},
    "magnitude_sweep": {"study": {"duration": "6 min"}},
    "trade_grid": {"study": {"duration": "6 min"}},
    "dual_imu": {"trajectory": {"segment": [{"kind": "stand", "duration": "12 s"},
                                            {"kind": "fly", "duration": "8 s", "to_speed": "100 m/s",
                                             "transition": "1 s"}],
                                "initial": {"lat": "36 deg", "lon": "127 deg", "h": "60 m"}, "vibration": []}},
}


@pytest.mark.parametrize("kind", list(C.KINDS))
def test_new_study_runs(kind, tmp_path, monkeypatch, capsys):
    # In-process through the CLI's entry point, as a shell runs `covtool new KIND > s.toml` and
    # `covtool run s.toml` in tmp_path: what is tested is the generated file, and a fresh interpreter
    # per command spent ~4 s per kind on imports.  `python -m covtool` itself is run by test_cli.
    from covtool.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["new", kind]) == 0
    new = capsys.readouterr()
    assert new.err == ""
    decl = tomllib.loads(new.out)
    assert decl["study"]["kind"] == kind
    cfg = C.load_config(decl, "new")           # valid as generated
    assert type(cfg) is C.KINDS[kind]
    for section, values in SHORTEN.get(kind, {}).items():
        if section == "trajectory":
            decl[section] = values
        else:
            decl.setdefault(section, {}).update(values)
    (tmp_path / "s.toml").write_text(tomli_w.dumps(decl))
    status = main(["run", "s.toml", "--out", "o", "--quiet", "--no-figures"])
    run = capsys.readouterr()
    assert status == 0, run.err
    assert "Traceback" not in run.err
    assert (tmp_path / "o" / "resolved_study.toml").is_file()


def test_new_refuses_an_unknown_kind(capsys):
    from covtool.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["new", "zupt_fliter_order"])
    assert exc.value.code == 2
    assert "invalid choice: 'zupt_fliter_order'" in capsys.readouterr().err
    with pytest.raises(InputError, match=r"covtool new: unknown study kind 'x' \(one of: pure_ins, "):
        new_study("x")


def test_aided_sections_match_their_parser():
    """Every [[measurement]], schedule, errors, [filters], variant and grade key the aided parser accepts."""
    from covtool.studies.aided import parse_grades, parse_measurement, parse_schedule, parse_variants, run

    gnss = _decl("aided_gnss_outage.toml")
    odo = _decl("aided_odometer_nhc.toml")
    assert _allowed(lambda: run(_inject(gnss, []), path=None)) == set(C.AidedConfig.model_fields)
    assert _allowed(lambda: run(_inject(gnss, ["study"]), path=None)) == set(section_keys(C.StudySection))
    assert _allowed(lambda: run(_inject(gnss, ["filters"]), path=None)) == set(section_keys(C.AidedFiltersSection))
    m0 = gnss["measurement"][0]
    assert _allowed(lambda: parse_measurement({**m0, UNKNOWN: 1}, 0, "s")) == set(section_keys(C.MeasurementEntry))
    assert _allowed(lambda: parse_measurement(_inject(m0, ["errors", "N"]), 0, "s")) == \
        set(section_keys(C.MeasurementError))
    assert _allowed(lambda: parse_schedule({**m0["schedule"], UNKNOWN: 1}, "s")) == \
        set(section_keys(C.MeasurementSchedule))
    variant = odo["filters"]["variant"][0]
    assert _allowed(lambda: parse_variants({"variant": [{**variant, UNKNOWN: 1}]}, {"B1": None}, [], "s")) == \
        set(section_keys(C.FilterVariant))
    assert _allowed(lambda: parse_grades(_inject(gnss, ["grade", 0]), "s")) == set(section_keys(C.AidedGrade))
    # the measurement kinds and schedule conditions offered are the library's, no more
    from covtool.lincov.measurements import KINDS as MK, WHEN
    for k in MK:
        assert C.MeasurementEntry.model_validate({"name": "m", "kind": k, "sigma": "1 m"}).kind == k
    for w in WHEN:
        assert C.MeasurementSchedule.model_validate({"when": w}).when == w
    with pytest.raises(ValueError, match=re.escape("'gps' is not one of: " + ", ".join(map(repr, MK)))):
        C.MeasurementEntry.model_validate({"name": "m", "kind": "gps", "sigma": "1 m"})
