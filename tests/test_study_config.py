"""Study files: block overrides, filters across files, the filters' P0 rule, static span (issue 14 item 3)."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

import covtool
from covtool.errors import ModelFileError, StudyFileError
from covtool.io.filters import load_filters
from covtool.io.model_file import load_model
from covtool.studies.inputs import load_trajectory, load_truth
from covtool.studies.zupt_setup import filters_file, setup

ROOT = Path(__file__).resolve().parents[1]
FLAGSHIP = ROOT / "studies" / "zupt_filter_order.toml"
LIBRARY_FILTERS = ROOT / "models" / "filters" / "zupt_filters.toml"
DEG_H = math.pi / 180 / 3600          # 1 deg/h in rad/s
UG = 9.80665e-6                       # 1 ug in m/s^2


def short(cases=("B1",), duration="6 min"):
    d = tomllib.loads(FLAGSHIP.read_text())
    d["study"]["duration"] = duration
    d["filters"]["cases"] = list(cases)
    d["filters"]["file"] = str(LIBRARY_FILTERS)
    d["output"]["report_times"] = [duration]
    return d


@pytest.fixture(scope="module")
def nominal():
    return load_model(ROOT / "models" / "sdins58.toml")


# ---------------------------------------------------------------------------
# block-level overrides
# ---------------------------------------------------------------------------

def test_block_override_applies_to_every_state_and_a_state_override_wins(nominal):
    m = load_truth({"truth": {"override": {"gyro_bias": {"sigma": "2 deg/h"},
                                           "gyro_bias_z": {"sigma": "5 deg/h"}}}}, "s.toml", None)
    sig = {s.name: s.sigma for s in m.states}
    assert sig["gyro_bias_x"] == pytest.approx(2 * DEG_H, rel=1e-12)
    assert sig["gyro_bias_y"] == pytest.approx(2 * DEG_H, rel=1e-12)
    assert sig["gyro_bias_z"] == pytest.approx(5 * DEG_H, rel=1e-12)
    # every other state keeps the model file's value
    for s in nominal.states:
        if s.block != "gyro_bias":
            assert sig[s.name] == s.sigma


def test_block_override_of_a_process_parameter_is_checked_per_state(nominal):
    proc = {s.block: s.process for s in nominal.states}
    assert proc["gyro_bias"] != "markov"
    with pytest.raises(StudyFileError, match=r"s.toml: \[truth.override.gyro_bias\] tau: 'tau' applies only to "
                                             r"process 'markov'; state 'gyro_bias_x' follows process"):
        load_truth({"truth": {"override": {"gyro_bias": {"tau": "1 h"}}}}, "s.toml", None)


def test_block_override_with_a_bad_unit_names_the_block_table():
    with pytest.raises(StudyFileError, match=r"\[truth.override.acc_bias\] sigma: '3 deg' is not an acceleration"):
        load_truth({"truth": {"override": {"acc_bias": {"sigma": "3 deg"}}}}, "s.toml", None)


def test_unknown_state_or_block_override_lists_the_blocks():
    with pytest.raises(StudyFileError, match=r"\[truth.override.gyro_bais\]: unknown state or block 'gyro_bais' "
                                             r"of truth model 'sdins58' \(blocks: nav, acc_bias, gyro_bias"):
        load_truth({"truth": {"override": {"gyro_bais": {"sigma": "1 deg/h"}}}}, "s.toml", None)


# ---------------------------------------------------------------------------
# filters extending filters of another file, add, several files per study
# ---------------------------------------------------------------------------

def _write(path: Path, filters: list[dict]) -> Path:
    path.write_text(tomli_w.dumps({"filter": filters}))
    return path


def test_filter_extends_a_filter_of_another_file_and_adds_states(tmp_path, nominal):
    mine = _write(tmp_path / "mine.toml", [{"name": "B1M", "base": "B1", "add": ["acc_markov"],
                                            "description": "B1 with the accelerometer Markov states"}])
    specs = load_filters([LIBRARY_FILTERS, mine], nominal)
    b1, b1m = specs["B1"], specs["B1M"]
    markov = [s.name for s in nominal.states if s.block == "acc_markov"]
    assert len(markov) == 3
    assert set(b1m.kept) == set(b1.kept) | set(markov)
    assert list(b1m.kept) == [nm for nm in nominal.names if nm in set(b1m.kept)]   # truth order
    assert b1m.n == b1.n + 3 == 25
    assert b1m.options == b1.options and b1m.equivalent_noise == b1.equivalent_noise


def test_filter_base_may_be_declared_in_a_later_file_and_inherits_options(tmp_path, nominal):
    first = _write(tmp_path / "a.toml", [{"name": "C2", "base": "B3x", "drop": ["acc_sf", "gyro_sf"]}])
    second = _write(tmp_path / "b.toml", [{"name": "B3x", "base": "B1", "coriolis": False}])
    specs = load_filters([first, second, LIBRARY_FILTERS], nominal)
    assert list(specs)[:2] == ["C2", "B3x"]
    assert specs["C2"].kept == specs["C"].kept and specs["C2"].n == 16
    assert specs["C2"].options.coriolis is False and specs["C2"].options.couple_vertical is True


@pytest.mark.parametrize("filters,match", [
    ([{"name": "X", "base": "Z9"}], r"mine.toml: filter 'X': base: unknown base filter 'Z9' \(declared in none of "
                                    r"the filter files: .*mine.toml"),
    ([{"name": "X", "base": "Y", "keep": ["nav"]}, {"name": "Y", "base": "X"}],
     r"filter 'Y': base: circular base: X -> Y -> X"),
    ([{"name": "B1", "keep": ["nav"]}], r"mine.toml: filter 'B1': duplicate filter name \(also declared in .*"
                                        r"zupt_filters.toml\)"),
    ([{"name": "X", "base": "B1", "add": ["acc_markov_q"]}], r"filter 'X': add: unknown truth state or block "
                                                             r"'acc_markov_q'"),
    ([{"name": "X", "base": "B1", "add": ["acc_markov"], "drop": ["acc_markov_x"]}],
     r"filter 'X': add: state 'acc_markov_x' is both added and dropped"),
    ([{"name": "X", "base": "B1", "add": 3}], r"filter 'X': add: expected a list of truth state or blocks, got 3"),
])
def test_filter_file_errors_across_files(tmp_path, nominal, filters, match):
    mine = _write(tmp_path / "mine.toml", filters)
    with pytest.raises(ModelFileError, match=match):
        load_filters([LIBRARY_FILTERS, mine], nominal)


@pytest.mark.parametrize("value,match", [
    ([], r"\[filters\] file: expected a filter file or a non-empty list of filter files, got \[\]"),
    (["zupt_filters", "zupt_filters"], r"\[filters\] file\[1\]: '.*zupt_filters.toml' is named twice"),
    (["no_such_filters"], r"\[filters\] file\[0\]: no filter file 'no_such_filters' in the library"),
    (["zupt_filters", 3], r"\[filters\] file\[1\]: 3 is not a file name"),
    (["zupt_filters", "gone.toml"], r"\[filters\] file\[1\]: no such filter file '.*gone.toml'"),
])
def test_filters_file_list_errors(tmp_path, value, match):
    with pytest.raises(StudyFileError, match=match):
        filters_file({"file": value}, "s.toml", tmp_path)


def test_study_with_two_filter_files_runs_and_records_both(tmp_path):
    """Issue 14 item 3: ``file = [a, b]`` was a TypeError traceback."""
    mine = _write(tmp_path / "mine.toml", [{"name": "B1M", "base": "B1", "add": ["acc_markov"]}])
    d = short(cases=("B1", "B1M"))
    d["filters"]["file"] = ["zupt_filters", "mine.toml"]
    study = tmp_path / "s.toml"
    study.write_text(tomli_w.dumps(d))
    r = covtool.run_study(study)
    one = covtool.run_study(short(cases=("B1",)))
    s = r.summary.set_index("case")
    # B1 is the same filter whichever file list declares it
    assert s.loc["B1", "CEP [m]"] == one.summary.set_index("case").loc["B1", "CEP [m]"]
    assert s.loc["B1M", "states"] == 25
    assert r.provenance["filter_file"] == str(LIBRARY_FILTERS.resolve())
    assert r.provenance["filter_2_file"] == str(mine.resolve())
    assert len(r.provenance["filter_2_file_sha256"]) == 64


# ---------------------------------------------------------------------------
# the rule for the filters' P0 under a truth override
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("follow", [None, False, True])
def test_truth_override_reaches_the_filters_only_when_asked(follow, nominal):
    d = short(cases=("B1",), duration="5 min")
    d["truth"]["override"] = {"acc_bias": {"sigma": "200 ug"}}
    if follow is not None:
        d["truth"]["override_filters"] = follow
    S = setup(d)
    i_truth = S.truth.index["acc_bias_x"]
    assert math.sqrt(S.P0[i_truth, i_truth]) == pytest.approx(200 * UG, rel=1e-12)
    fm = S.filter_model("B1")[0]
    j = fm.names.index("acc_bias_x")
    expected = 200 * UG if follow else nominal.states[nominal.index["acc_bias_x"]].sigma
    assert math.sqrt(fm.P0[j, j]) == pytest.approx(expected, rel=1e-12)
    assert expected != pytest.approx(200 * UG) or follow


def test_override_filters_must_be_a_boolean():
    with pytest.raises(StudyFileError, match=r"\[truth\] override_filters: 'yes' is not true or false"):
        load_truth({"truth": {"override_filters": "yes"}}, "s.toml", None)


def test_optimal_filter_claims_the_truth_only_when_it_knows_the_override():
    """Filter A (every truth state, no equivalent noise) is the Kalman filter of the truth: its own
    covariance equals the truth's when it is told the override, and not when it keeps the file's P0."""
    d = short(cases=("A",), duration="5 min")
    d["filters"]["pure_ins"] = False
    d["truth"]["override"] = {"gyro_bias": {"sigma": "0.05 deg/h"}}
    for follow in (True, False):
        d["truth"]["override_filters"] = follow
        r = covtool.run_study(d)
        row = r.summary.iloc[0]
        rel = abs(row["filter-claimed CEP [ft]"] / row["CEP [ft]"] - 1)
        if follow:
            assert rel < 1e-9
        else:
            assert rel > 1e-3


# ---------------------------------------------------------------------------
# the static builtin follows the study's duration
# ---------------------------------------------------------------------------

STATIC = {"builtin": "static", "lat": "37 deg", "lon": "127 deg", "h": "50 m"}


def test_static_builtin_spans_the_study_duration():
    traj = load_trajectory({"trajectory": dict(STATIC)}, "s.toml", None, 1.0, 3600.0)
    assert traj.t[-1] == 3600.0


def test_static_builtin_with_its_own_shorter_duration_is_refused():
    with pytest.raises(StudyFileError, match=r"s.toml: \[study\] duration: 3600 s is longer than the trajectory "
                                             r"\(600 s\)"):
        load_trajectory({"trajectory": {**STATIC, "duration": "10 min"}}, "s.toml", None, 1.0, 3600.0)


def test_one_hour_static_pure_ins_study_runs():
    """Issue 14 item 3: a 1 h study on the static builtin was refused (the builtin kept 30 min)."""
    d = {"study": {"kind": "pure_ins", "duration": "1 h", "dt": "10 s"}, "trajectory": dict(STATIC),
         "truth": {"model": "sdins58", "only": ["acc_bias_x"]}}
    r = covtool.run_study(d)
    assert r.summary["t [min]"].iloc[-1] == pytest.approx(60.0)


# ---------------------------------------------------------------------------
# resolved_study.toml re-runs from where it lies (issue 14 item 4)
# ---------------------------------------------------------------------------

def test_resolved_study_reruns_from_anywhere_and_reproduces_every_csv(tmp_path, monkeypatch):
    import hashlib
    import shutil

    import pandas as pd

    from covtool.cli import main

    work = tmp_path / "work"
    (work / "filters").mkdir(parents=True)
    shutil.copy(LIBRARY_FILTERS, work / "filters" / "mine.toml")
    d = short(cases=("A", "B1", "D"), duration="6 min")
    d["filters"]["file"] = "filters/mine.toml"           # relative to the study file
    study = work / "s.toml"
    study.write_text(tomli_w.dumps(d))
    monkeypatch.chdir(work)
    assert main(["run", "s.toml", "--out", "o", "--quiet", "--no-figures"]) == 0
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(["run", str(work / "o" / "resolved_study.toml"), "--out", "o2", "--quiet", "--no-figures"]) == 0
    csvs = sorted(p.name for p in (work / "o").glob("*.csv"))
    assert {"summary.csv", "history.csv", "filter_states.csv"} <= set(csvs)
    assert csvs == sorted(p.name for p in (elsewhere / "o2").glob("*.csv"))
    for name in csvs:
        assert (work / "o" / name).read_bytes() == (elsewhere / "o2" / name).read_bytes(), name
    resolved = tomllib.loads((work / "o" / "resolved_study.toml").read_text())
    assert resolved["filters"]["file"] == str(work / "filters" / "mine.toml")
    prov = pd.read_excel(work / "o" / f"{d['study']['name']}.xlsx", sheet_name="provenance")
    prov = dict(zip(prov["key"], prov["value"]))
    for label, path in (("study", study), ("filter", work / "filters" / "mine.toml"),
                        ("truth_model", ROOT / "models" / "sdins58.toml")):
        assert prov[f"{label}_file"] == str(path.resolve())
        assert prov[f"{label}_file_sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    from covtool.version import source_revision
    assert prov["tool_commit"] == source_revision()


def test_source_revision_is_the_checkout_head():
    import subprocess

    from covtool.version import source_revision

    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0:
        assert source_revision().split()[0] == head.stdout.strip()
    else:
        assert source_revision().endswith("(not a git checkout)")
