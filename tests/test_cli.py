"""The command line as a navigation engineer meets it (issue 14 items 1, 2, 5, 6, 9).

Every subcommand with bad input answers with one line ``covtool: error:``,
exit status 2 and no traceback; a bug answers with one line and exit 70;
a closed output pipe ends quietly; ``covtool models`` / ``covtool show``
find truth models, filters and IMU grades from any directory and print
datasheet units beside SI at full precision.
"""

from __future__ import annotations

import io
import math
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pandas as pd
import pytest
import tomli_w

import covtool
from covtool.cli import EXIT_BUG, main
from covtool.errors import ModelFileError
from covtool.io.console import console_table, format_number
from covtool.io.library import describe, list_models, lookup
from covtool.progress import progress_bar, wanted

ROOT = Path(__file__).resolve().parents[1]
PURE = ROOT / "studies" / "pure_ins_land_vehicle.toml"
DUAL = ROOT / "studies" / "dual_imu_flight.toml"
ZUPT_FILTERS = ROOT / "models" / "filters" / "zupt_filters.toml"
DEG_H = math.pi / 180 / 3600            # 1 deg/h [rad/s]
G0 = 9.80665


def _call(argv, capsys):
    """``main(argv)`` in-process: (exit status, stdout, stderr); argparse's SystemExit counted as its code."""
    try:
        status = main(argv)
    except SystemExit as exc:
        status = exc.code
    out, err = capsys.readouterr()
    return status, out, err


def _one_line_error(status, out, err, pattern=""):
    assert status == 2, (status, err)
    assert "Traceback" not in err and "Traceback" not in out
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("covtool: error: "), lines[0]
    assert re.search(pattern, lines[0]), lines[0]


@pytest.fixture()
def files(tmp_path):
    """Bad inputs of every kind: a directory, a garbage file, a TOML of no known kind, a wrong-kind study."""
    d = tmp_path / "inputs"
    d.mkdir()
    (d / "garbage.toml").write_bytes(b"\x00\x01 not toml \xff")
    (d / "not_toml.toml").write_text("this is = = not TOML\n")
    (d / "other.toml").write_text('[something]\nkey = 1\n')
    (d / "existing_file").write_text("keep")
    unknown_kind = tomllib.loads(PURE.read_text())
    unknown_kind["study"]["kind"] = "no_such_kind"
    (d / "unknown_kind.toml").write_text(tomli_w.dumps(unknown_kind))
    (d / "garbage.csv").write_text("a,b\n1,2\n")
    return d


# ---------------------------------------------------------------------------
# the matrix: every subcommand, several kinds of bad input, one line each
# ---------------------------------------------------------------------------

BAD = [
    # (id, argv built from the inputs folder d, pattern the one line must match)
    ("run: missing study file", lambda d: ["run", str(d / "missing.toml"), "--out", str(d / "o")],
     r"missing\.toml.*(no such|not found|does not exist)"),
    ("run: directory instead of study file", lambda d: ["run", str(d), "--out", str(d / "o")],
     r"is a directory"),
    ("run: garbage study file", lambda d: ["run", str(d / "garbage.toml"), "--out", str(d / "o")],
     r"garbage\.toml"),
    ("run: not TOML", lambda d: ["run", str(d / "not_toml.toml"), "--out", str(d / "o")], r"not_toml\.toml"),
    ("run: unknown study kind", lambda d: ["run", str(d / "unknown_kind.toml"), "--out", str(d / "o")],
     r"unknown kind 'no_such_kind'"),
    ("run: --out is an existing file", lambda d: ["run", str(PURE), "--out", str(d / "existing_file")],
     r"is an existing file, not a directory"),
    ("run: --out cannot be created", lambda d: ["run", str(PURE), "--out", "/proc/nope"], r"cannot be created"),
    ("run: bad --workers value", lambda d: ["run", str(PURE), "--workers", "0"],
     r"covtool run: argument -j/--workers/--jobs: '0' is not a positive integer"),
    ("run: --jobs not a number", lambda d: ["run", str(PURE), "--jobs", "many"], r"'many' is not a positive integer"),
    ("run: --workers on a kind that cannot use it",
     lambda d: ["run", str(PURE), "--out", str(d / "o"), "--workers", "2"],
     r"'pure_ins' runs in one process in one piece; it takes no --workers \(kinds that do: monte_carlo, "
     r"trade_grid\)"),
    ("run: --resume on a kind that cannot use it", lambda d: ["run", str(PURE), "--out", str(d / "o"), "--resume"],
     r"takes no --resume"),
    ("run: unknown option", lambda d: ["run", str(PURE), "--bogus"], r"unrecognized arguments: --bogus"),
    ("models: --dir missing", lambda d: ["models", "--dir", str(d / "nope")], r"is not a directory"),
    ("models: --dir is a file", lambda d: ["models", "--dir", str(d / "existing_file")], r"is not a directory"),
    ("models: unexpected argument", lambda d: ["models", "extra"], r"unrecognized arguments: extra"),
    ("show: unknown name", lambda d: ["show", "sdins99"],
     r"sdins99: no such model, filter or IMU grade in the library .*truth models: sdins58.*filters: A, B1.*"
     r"IMU grades: kimu"),
    ("show: directory", lambda d: ["show", str(d)], r"is a directory, not a truth model, filter or IMU-grade file"),
    ("show: missing file", lambda d: ["show", str(d / "missing.toml")], r"no such file"),
    ("show: garbage file", lambda d: ["show", str(d / "garbage.toml")], r"garbage\.toml"),
    ("show: TOML of no known kind", lambda d: ["show", str(d / "other.toml")],
     r"other\.toml: is neither a truth model .* nor an IMU grade \(\[imu\]\); its tables are something"),
    ("show: --markdown of a filter", lambda d: ["show", "B2", "--markdown"],
     r"--markdown 'B2': is a filter; --markdown prints a truth model's state table"),
    ("show: --dir missing", lambda d: ["show", "sdins58", "--dir", str(d / "nope")], r"is not a directory"),
    ("show: no name", lambda d: ["show"], r"the following arguments are required: NAME"),
    ("dualnav: missing logs", lambda d: ["dualnav", str(d / "m.csv"), str(d / "k.csv"), "--study", str(DUAL),
                                         "--out", str(d / "o")], r"m\.csv"),
    ("dualnav: directory instead of log", lambda d: ["dualnav", str(d), str(d), "--study", str(DUAL),
                                                     "--out", str(d / "o")], r"inputs"),
    ("dualnav: garbage log", lambda d: ["dualnav", str(d / "garbage.csv"), str(d / "garbage.csv"),
                                        "--study", str(DUAL), "--out", str(d / "o")], r"garbage\.csv"),
    ("dualnav: study of another kind", lambda d: ["dualnav", str(d / "garbage.csv"), str(d / "garbage.csv"),
                                                  "--study", str(PURE), "--out", str(d / "o")],
     r"\[study\] kind: 'pure_ins': covtool dualnav needs a 'dual_imu' study"),
    ("dualnav: --out is an existing file", lambda d: ["dualnav", str(d / "garbage.csv"), str(d / "garbage.csv"),
                                                      "--out", str(d / "existing_file")],
     r"is an existing file, not a directory"),
    ("dualnav: --workers (it has none)", lambda d: ["dualnav", "a.csv", "b.csv", "--out", "o", "--workers", "2"],
     r"covtool: unrecognized arguments: --workers 2"),
    ("dualnav: missing --out", lambda d: ["dualnav", "a.csv", "b.csv"], r"required: --out"),
    ("dualnav: no study anywhere", lambda d: ["dualnav", "a.csv", "b.csv", "--out", str(d / "o")],
     r"covtool: error: --study: not given, and there is no \$COVTOOL_DUALNAV_STUDY nor "
     r"\./studies/dual_imu_flight\.toml"),
    ("top level: unknown command", lambda d: ["frobnicate"], r"invalid choice: 'frobnicate'"),
    ("top level: no command", lambda d: [], r"the following arguments are required: COMMAND"),
    ("top level: unknown option", lambda d: ["--bogus", "models"], r"unrecognized arguments: --bogus"),
    ("--version with a value", lambda d: ["--version=2"], r"argument --version: ignored explicit argument '2'"),
]



def _subcommands() -> set[str]:
    from covtool.cli import build_parser

    return set(next(a for a in build_parser()._actions if a.dest == "command").choices)


if "new" in _subcommands():          # `covtool new STUDY_KIND` (a starting study file), once it exists
    BAD += [
        ("new: unknown study kind", lambda d: ["new", "no_such_kind"], r"no_such_kind"),
        ("new: no study kind", lambda d: ["new"], r"the following arguments are required"),
        ("new: unknown option", lambda d: ["new", "pure_ins", "--bogus"], r"unrecognized arguments: --bogus"),
    ]


@pytest.mark.parametrize("case", BAD, ids=[c[0] for c in BAD])
def test_every_subcommand_refuses_bad_input_in_one_line(case, files, capsys, monkeypatch):
    _, argv, pattern = case
    if case[0] == "dualnav: no study anywhere":       # an installed covtool, run outside a checkout
        import covtool.cli

        monkeypatch.chdir(files)
        monkeypatch.delenv("COVTOOL_DUALNAV_STUDY", raising=False)
        monkeypatch.setattr(covtool.cli, "__file__", str(files / "site-packages" / "covtool" / "cli.py"))
    before = sorted(p.name for p in files.iterdir())
    _one_line_error(*_call(argv(files), capsys), pattern)
    assert sorted(p.name for p in files.iterdir()) == before          # nothing written


def test_the_matrix_covers_every_subcommand_three_ways():
    counts = {name: sum(c[0].startswith(f"{name}:") for c in BAD) for name in _subcommands()}
    assert all(n >= 3 for n in counts.values()), counts
    assert sum(c[0].startswith(("top level", "--version")) for c in BAD) >= 3


def test_covtool_models_env_pointing_nowhere_is_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("COVTOOL_MODELS", str(tmp_path / "nowhere"))
    _one_line_error(*_call(["models"], capsys), r"\$COVTOOL_MODELS '.*nowhere': is not a directory")


# ---------------------------------------------------------------------------
# bugs, pipes, the version
# ---------------------------------------------------------------------------

def test_an_internal_error_is_one_line_exit_70(monkeypatch, capsys):
    import covtool.io.library as library

    def broken(*a, **k):
        raise KeyError("a bug\nover two lines")

    monkeypatch.setattr(library, "list_models", broken)
    monkeypatch.delenv("COVTOOL_DEBUG", raising=False)
    status, out, err = _call(["models"], capsys)
    assert status == EXIT_BUG == 70
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err
    assert lines[0].startswith("covtool: internal error (a bug in covtool, please report it with the command): "
                               "KeyError: 'a bug")
    assert "COVTOOL_DEBUG=1 shows the traceback" in lines[0]
    monkeypatch.setenv("COVTOOL_DEBUG", "1")
    with pytest.raises(KeyError, match="a bug"):
        main(["models"])


def test_an_os_error_is_one_line_naming_the_file(monkeypatch, capsys):
    import covtool.io.library as library

    def refused(*a, **k):
        raise PermissionError(13, "Permission denied", "/some/library/x.toml")

    monkeypatch.setattr(library, "list_models", refused)
    _one_line_error(*_call(["models"], capsys), r"covtool: error: /some/library/x\.toml: Permission denied$")


def _cli(args, cwd, **kw):
    e = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONDONTWRITEBYTECODE": "1", "MPLCONFIGDIR": str(cwd)}
    e.pop("COVTOOL_MODELS", None)
    return subprocess.run([sys.executable, "-m", "covtool", *args], cwd=cwd, env=e, capture_output=True,
                          timeout=300, **kw)


def test_show_into_a_closed_pipe_ends_quietly(tmp_path):
    """``covtool show sdins58 | head -1``: before, a BrokenPipeError traceback; now exit 141, stderr empty."""
    e = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONDONTWRITEBYTECODE": "1", "MPLCONFIGDIR": str(tmp_path)}
    p = subprocess.run(["bash", "-c", f"set -o pipefail; '{sys.executable}' -m covtool show sdins58 | head -1"],
                       cwd=tmp_path, env=e, capture_output=True, text=True, timeout=300)
    assert p.stderr == "", p.stderr
    assert p.stdout == "truth model sdins58: 58 states\n" and p.returncode in (0, 141)   # 0: it fitted the pipe
    # a reader that has gone before the first write: always the broken pipe
    r, w = os.pipe()
    os.close(r)
    p = subprocess.run([sys.executable, "-m", "covtool", "models"], cwd=tmp_path, env=e, stdout=w,
                       stderr=subprocess.PIPE, text=True, timeout=300)
    os.close(w)
    assert p.stderr == "" and p.returncode == 141, (p.returncode, p.stderr)


def test_version_from_any_directory(tmp_path):
    p = _cli(["--version"], tmp_path, text=True)
    assert p.returncode == 0 and p.stderr == ""
    assert re.fullmatch(rf"covtool {re.escape(covtool.__version__)}( \(.*\))? from {re.escape(str(ROOT))}/covtool "
                        r"\(Python \d+\.\d+\.\d+\)\n", p.stdout), p.stdout


_FROM_ELSEWHERE = """
import os, sys
from covtool.cli import main
for argv in (["models"], ["show", "sdins58"], ["show", "B1"], ["show", "kimu"], ["show", sys.argv[1]],
             ["show", sys.argv[2]]):
    print("STATUS", argv, main(argv), flush=True)
os.environ["COVTOOL_MODELS"] = sys.argv[3]
for argv in (["show", "mygrade"], ["show", "sdins58"]):
    print("STATUS", argv, main(argv), flush=True)
"""


def test_models_and_show_work_from_another_directory(tmp_path):
    """Before: ``cd /tmp && covtool models`` printed an empty table and ``show B1`` 'no such model'."""
    lib = tmp_path / "lib"                           # $COVTOOL_MODELS: another library
    (lib / "imu").mkdir(parents=True)
    (lib / "imu" / "mygrade.toml").write_text((ROOT / "models" / "imu" / "kimu.toml").read_text()
                                              .replace('name = "kimu"', 'name = "mygrade"'))
    e = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONDONTWRITEBYTECODE": "1", "MPLCONFIGDIR": str(tmp_path)}
    e.pop("COVTOOL_MODELS", None)
    p = subprocess.run([sys.executable, "-c", _FROM_ELSEWHERE, str(ZUPT_FILTERS),
                        str(ROOT / "models" / "imu" / "kimu.toml"), str(lib)],
                       cwd=tmp_path, env=e, capture_output=True, text=True, timeout=300)
    status = re.findall(r"STATUS (.*) (\d+)\n", p.stdout)
    assert [int(s) for _, s in status] == [0, 0, 0, 0, 0, 0, 0, 2], (status, p.stderr)
    assert re.search(r"\n  B1 +22 ", p.stdout) and "IMU grade kimu" in p.stdout and "IMU grade mygrade" in p.stdout
    assert p.stderr.strip().splitlines() == [p.stderr.strip()] and "truth models: none" in p.stderr


def test_models_help_documents_the_library_variable(capsys):
    with pytest.raises(SystemExit):
        main(["models", "--help"])
    assert "$COVTOOL_MODELS" in capsys.readouterr().out


# ---------------------------------------------------------------------------
# covtool models / covtool show: the values
# ---------------------------------------------------------------------------

def test_models_lists_every_kind_with_state_counts_and_bases(capsys):
    df = list_models()
    flag = df[(df["kind"] == "filter") & (df["file"] == str(ZUPT_FILTERS.resolve()))].set_index("name")
    # seed 002 Table 1: A is the truth (58), B1..B3 keep the 22 states of eq (14), C drops the 6 scale
    # factors (16), D also the 6 biases (10)
    assert flag["states"].to_dict() == {"A": 58, "B1": 22, "B2": 22, "B3": 22, "C": 16, "D": 10}
    assert flag["base"].to_dict() == {"A": "", "B1": "", "B2": "B1", "B3": "B2", "C": "B3", "D": "C"}
    truths = df[df["kind"] == "truth model"].set_index("name")
    assert truths.loc["sdins58", "states"] == 58 and truths.loc["sdins58_uncalibrated", "base"] == "sdins58"
    grades = df[df["kind"] == "IMU grade"].set_index("name")
    assert set(grades.index) >= {"kimu", "main_imu", "nav_grade_sdins"}
    status, out, err = _call(["models"], capsys)
    assert status == 0 and err == ""
    assert max(len(line) for line in out.splitlines()) <= 120
    assert "filters in filters/zupt_filters.toml (projections of sdins58):" in out
    assert re.search(r"\n  B2 +22 +B1 +22 states: B1 with the vertical", out)


def test_show_truth_model_gives_datasheet_and_exact_si(capsys):
    status, out, err = _call(["show", "sdins58"], capsys)
    assert status == 0 and err == ""
    assert max(len(line) for line in out.splitlines()) <= 120
    # seed 002 Table 2: W_dz = 0.025 deg/h, B_z = 30 ug; the SI column reads back to the very float the
    # model holds (full precision) and equals the closed-form conversion to the last bits
    m = lookup("sdins58")[0].obj
    for i, name, shown, unit, si, si_unit in ((16, "gyro_bias_z", "0.025", "deg/h", 0.025 * DEG_H, "rad/s"),
                                              (13, "acc_bias_z", "30", "ug", 30e-6 * G0, "m/s^2")):
        row = next(line for line in out.splitlines() if re.match(rf"\s*{i}\s+{name}\b", line)).split()
        assert row[3:5] == [shown, unit] and row[6] == si_unit
        assert float(row[5]) == m.states[m.index[name]].sigma
        assert float(row[5]) == pytest.approx(si, rel=1e-15)
    # the navigation block's white noise: ARW 0.002 deg/sqrt(h), VRW 5 ug/sqrt(Hz) (models/sdins58.toml)
    arw = 0.002 * math.pi / 180 / 60                   # deg/√h → rad/√s
    vrw = 5e-6 * G0                                    # µg/√Hz → m/s/√s
    for key, shown, closed, held in (("ARW", ["0.002", "deg/√h"], arw, m.arw),
                                     ("VRW", ["5", "µg/√Hz"], vrw, m.vrw)):
        cells = next(x for x in out.splitlines() if x.startswith(key)).split()
        assert cells[-6:-4] == shown
        assert float(cells[-4]) == held and float(cells[-2]) == held * held       # full precision
        assert held == pytest.approx(closed, rel=1e-15)
    # a first-order Gauss–Markov state's driving PSD 2σ²/τ: 0.005 deg/h, τ = 1 h
    q = 2 * (0.005 * DEG_H) ** 2 / 3600.0
    line = next(x for x in out.splitlines() if x.startswith("gyro_markov_x ") and "2σ²/τ" in x)
    assert float(line.split()[2]) == pytest.approx(q, rel=1e-15)
    assert re.search(r"acc_markov_x .* Markov, τ 30 min\n", out)
    assert re.search(r"gyro_markov_x .* Markov, τ 1 h\n", out)
    assert re.search(r"grav_dg .* Markov, d 20 km\n", out) and re.search(r"acc_ad_x .* Markov, τ 20 s\n", out)


def test_show_filter_gives_base_options_and_p0(tmp_path, capsys):
    status, out, err = _call(["show", str(ZUPT_FILTERS)], capsys)
    assert status == 0
    b2 = out[out.index("filter B2:"):out.index("filter B3:")]
    assert re.search(r"base filter +B1\n", b2) and re.search(r"vertical channel +decoupled", b2)
    assert re.search(r"kept states +22 of 58", b2)
    assert "dropped states (36), by block: acc_mis (6)" in b2
    # a user filter file: base across a P0 override, shown in datasheet units and SI
    f = tmp_path / "mine.toml"
    f.write_text('[[filter]]\nname = "mine"\nkeep = ["nav", "gyro_bias"]\n[filter.P0]\ngyro_bias_z = "0.1 deg/h"\n'
                 '[[filter]]\nname = "mine_vl"\nbase = "mine"\ndiscretization = "van_loan"\nzupt_sigma = "0.01 ft/s"\n')
    status, out, err = _call(["show", str(f)], capsys)
    assert status == 0, err
    mine = out[:out.index("filter mine_vl:")]
    row = next(x for x in mine.splitlines() if re.match(r"\s*13\s+gyro_bias_z\b", x))
    assert row.split()[3:5] == ["0.1", "deg/h"] and row.endswith("[filter.P0]")
    assert float(row.split()[5]) == pytest.approx(0.1 * DEG_H, rel=1e-15)
    row = next(x for x in mine.splitlines() if re.match(r"\s*11\s+gyro_bias_x\b", x))
    assert row.split()[3] == "0.018" and row.endswith("truth")
    vl = out[out.index("filter mine_vl:"):]
    assert re.search(r"base filter +mine\n", vl) and "Van Loan" in vl
    zs = re.search(r"ZUPT 1σ assumed +0\.01 ft/s = (\S+) m/s", vl)
    assert zs and float(zs.group(1)) == lookup(str(f))[1].obj.zupt_sigma == pytest.approx(0.003048, rel=1e-15)


def test_show_name_declared_in_two_filter_files_shows_both(capsys):
    entries = lookup("B1")
    assert [e.kind for e in entries] == ["filter", "filter"]
    assert entries[0].path.name == "zupt_filters.toml"          # the flagship's first
    status, out, err = _call(["show", "B1"], capsys)
    assert status == 0 and out.startswith("B1: 2 entries of that name")
    assert out.count("filter B1: 22 states, a projection of sdins58") == 2


def test_show_imu_grade_gives_every_value_and_noise_density(capsys):
    status, out, err = _call(["show", "kimu"], capsys)
    assert status == 0 and err == ""
    assert max(len(line) for line in out.splitlines()) <= 120
    # seed 001 Table 2: gyro bias repeatability 30 deg/h, accelerometer bias 2 mg
    g = lookup("kimu")[0].obj
    for sensor, text, si, closed, unit in (("gyro", "30 deg/h", g.gyro["bias"][0], 30 * DEG_H, "rad/s"),
                                           ("accel", "2 mg", g.accel["bias"][0], 2e-3 * G0, "m/s\\^2")):
        assert re.search(rf"{sensor} +bias +{text} +{re.escape(repr(si))} \(all 3\) +{unit}", out)
        assert si == pytest.approx(closed, rel=1e-15)
    # VRW 0.1 m/s/√h = 0.1/60 m/s/√s = 169.953 µg/√Hz
    vrw = 0.1 / 60
    line = next(x for x in out.splitlines() if x.startswith("VRW"))
    assert f"{vrw / (1e-6 * G0):.6g} µg/√Hz" in line and repr(vrw) in line and repr(vrw * vrw) in line
    assert "as an error-state model: 46 states" in out


def test_lookup_of_a_file_of_each_kind():
    assert [e.kind for e in lookup(str(ROOT / "models" / "sdins58.toml"))] == ["truth model"]
    assert [e.kind for e in lookup(str(ROOT / "models" / "imu" / "kimu.toml"))] == ["IMU grade"]
    assert [e.name for e in lookup(str(ZUPT_FILTERS))] == ["A", "B1", "B2", "B3", "C", "D"]
    with pytest.raises(ModelFileError, match=r"no such model, filter or IMU grade"):
        lookup("nothing_here")
    assert "truth model sdins58: 58 states" in describe(lookup("sdins58")[0])


# ---------------------------------------------------------------------------
# console tables and progress
# ---------------------------------------------------------------------------

def test_numbers_for_the_console():
    assert format_number(14.999999999999996) == "15"
    assert format_number(4281.289115) == "4281"
    assert format_number(123456.7) == "123457"
    assert format_number(1.029629e-14) == "1.03e-14"
    assert format_number(0.0123456) == "0.01235"
    assert format_number(float("nan")) == "NaN"


def test_console_table_fits_and_names_what_it_leaves_out():
    wide = pd.DataFrame({"case": ["pure_ins", "B1"], "t [min]": [30.0, 30.0],
                         **{f"horizontal CEP variant {k} [ft]": [6763.123456, 11.81] for k in range(12)},
                         "horizontal top sources": ["initial tilt 93.6 %", "initial azimuth 2.6 %"],
                         "validity": ["ok", "beyond the linear domain after 20 min"]})
    text = console_table(wide, width=100, file_hint="summary.csv")
    lines = text.splitlines()
    assert max(len(x) for x in lines) <= 100
    assert "6763" in text and "11.81" in text and "6763.12" not in text
    assert "beyond the linear domain" in text                     # validity is never left out
    assert "every row: t [min] = 30" in text                      # a constant column is said once
    note = " ".join(lines[lines.index(next(x for x in lines if x.startswith("("))):])
    # the explanation goes first, then the rightmost numbers; the note lists them in the table's order
    m = re.match(r"\((\d+) more columns in summary\.csv: horizontal CEP variant (\d+) \[ft\]", note)
    first = int(m.group(2))
    assert int(m.group(1)) == 12 - first + 1 and 0 < first < 12
    assert note.endswith("variant 11 [ft]; horizontal top sources)")


def test_progress_is_shown_on_a_terminal_or_when_asked_never_with_quiet():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    assert wanted(stream=Tty()) is True
    assert wanted(stream=io.StringIO()) is False                   # a log file: no bar
    assert wanted(force=True, stream=io.StringIO()) is True        # --progress
    assert wanted(quiet=True, force=True, stream=Tty()) is False   # --quiet wins
    with progress_bar(3, "x", False) as bar:
        assert bar.disable
    with progress_bar(3, "x", True) as bar:
        assert not bar.disable and bar.total == 3


def test_a_bar_not_shown_counts_and_does_not_import_tqdm():
    # a run without bars (--quiet, or stderr not a terminal) pays no tqdm import (60-90 ms)
    code = ("import sys\nfrom covtool.progress import progress_bar\n"
            "with progress_bar(5, 'x', False, initial=1) as bar:\n    bar.update(3)\n"
            "print(bar.n, bar.total, bar.disable, 'tqdm' in sys.modules)\n"
            "from covtool.parallel import SerialBackend, run_chunks\n"
            "res, _ = run_chunks(lambda x: {'v': x}, [1, 2], ['a', 'b'], [['a'], ['b']], backend=SerialBackend())\n"
            "print(res == [{'v': 1}, {'v': 2}], 'tqdm' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["4", "5", "True", "False", "True", "False"]


def test_run_prints_a_summary_that_fits(tmp_path, capsys):
    d = tomllib.loads(PURE.read_text())
    d["study"]["duration"] = "6 min"
    d["output"]["report_times"] = ["6 min"]
    study = tmp_path / "s.toml"
    study.write_text(tomli_w.dumps(d))
    status, out, err = _call(["run", str(study), "--out", str(tmp_path / "o"), "--no-figures"], capsys)
    assert status == 0, err
    assert max(len(x) for x in out.splitlines()) <= 120
    assert "wrote" in out
    status, out, err = _call(["run", str(study), "--out", str(tmp_path / "o2"), "--no-figures", "--quiet"], capsys)
    assert status == 0 and out == "" and err == ""


def test_run_writes_with_the_heap_frozen_out_of_the_collector_and_unfreezes_it(tmp_path, capsys, monkeypatch):
    """The writers run with the heap frozen (gc.freeze); after the command nothing stays frozen.

    An in-process caller (these tests) must collect as before: a frozen heap
    would keep every cycle of the run alive.  Also after a writer fails.
    """
    import gc

    from covtool.io import writers

    d = tomllib.loads(PURE.read_text())
    d["study"]["duration"] = "3 min"
    d["output"]["report_times"] = ["3 min"]
    study = tmp_path / "s.toml"
    study.write_text(tomli_w.dumps(d))
    seen = []
    real = writers.write_outputs

    def counting(*args, **kwargs):
        seen.append(gc.get_freeze_count())
        return real(*args, **kwargs)

    monkeypatch.setattr(writers, "write_outputs", counting)
    assert gc.get_freeze_count() == 0
    status, _, err = _call(["run", str(study), "--out", str(tmp_path / "o"), "--no-figures", "--quiet"], capsys)
    assert status == 0, err
    assert len(seen) == 1 and seen[0] > 1000 and gc.get_freeze_count() == 0

    def failing(*args, **kwargs):
        raise OSError(28, "No space left on device", str(tmp_path / "o2" / "summary.csv"))

    monkeypatch.setattr(writers, "write_outputs", failing)
    status, _, err = _call(["run", str(study), "--out", str(tmp_path / "o2"), "--no-figures", "--quiet"], capsys)
    assert status != 0 and "No space left" in err and gc.get_freeze_count() == 0
    # a caller that froze its own objects keeps them frozen
    monkeypatch.setattr(writers, "write_outputs", counting)
    gc.freeze()
    try:
        mine = gc.get_freeze_count()
        status, _, err = _call(["run", str(study), "--out", str(tmp_path / "o3"), "--no-figures", "--quiet"], capsys)
        assert status == 0, err
        # nothing added to it (the run's objects) nor taken out (a frozen object freed by its count may leave)
        assert mine - 100 <= seen[-1] <= mine and mine - 100 <= gc.get_freeze_count() <= mine
    finally:
        gc.unfreeze()


def test_readme_is_self_contained_and_ci_runs_its_test_command():
    """Before: the README pointed at ../shared/BRIEF.md and named the papers only as seed 000/001/002."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert not re.search(r"\.\./|/work/|shared/", text)                  # no path outside the repository
    for target in re.findall(r"\]\(([^)#:]+)\)", text):                  # every relative link exists
        assert (ROOT / target).exists(), target
    # the papers cited with title and authors (seed 001 with its journal, volume, pages and DOI)
    flat = " ".join(text.split())
    assert "Effects of Accelerometer Signal Processing Errors on Inertial Navigation Systems" in flat
    assert "Journal of The Korean Society for Aeronautical and Space Sciences **45**(1), 36–45 (2017)" in flat
    assert "doi:10.5139/JKSAS.2017.45.1.36" in flat
    assert "Design and Performance Analysis of a Zero-velocity Update Kalman Filter for SDINS" in flat
    # CI runs the README's second quick-start command
    quick = re.search(r"# 2\. .*\n(.*)\n", text).group(1)
    test_cmd = quick.split("&& ")[-1].strip()
    assert test_cmd == "python -m pytest -q -n 2"
    assert f"pip install '.[test]' && {test_cmd}" in (ROOT / ".ci" / "run").read_text()


def test_console_shows_a_study_kinds_key_columns_first():
    from covtool.io.console import KEY_COLUMNS

    df = pd.DataFrame({"filter": ["A", "B1"], "states [-]": [58, 22], "horizontal RMS [ft]": [13.4, 14.2],
                       "max sensitivity horizontal [-]": [0.811, 2.365], "FLOPs/cycle [FLOP]": [9614006, 502608],
                       "validity": ["ok", "ok"]})
    header = console_table(df, prefer=KEY_COLUMNS["zupt_sensitivity"]).splitlines()
    text = "\n".join(header)
    # max sensitivity (seed 002 Fig 8) and FLOPs/cycle (Table 4) before the RMS; the cost in whole FLOPs
    assert text.index("9614006") < text.index("13.4") and text.index("2.365") < text.index("14.2")
    one = console_table(df.head(1))                  # one row: nothing is folded into "every row"
    assert "every row" not in one and "9614006" in one and "58" in one
