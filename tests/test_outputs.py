"""Safe outputs (issue 10, cases 2, 3, 6; issue 14 case 5).

* every user string is a text cell in the workbook (never a formula) and is
  neutralised in CSV (a leading apostrophe before ``= + - @ TAB CR``);
* a NaN or infinity is never an empty cell or 0;
* names are validated at load, the study name is one plain file-name
  component, checked before any computation;
* ``--out`` is checked before any computation; nothing is written outside it;
* file-level read errors of TOML files are one line naming the file;
* atomic writes honour the umask; staging directories of killed runs are
  removed by the next run.
"""

from __future__ import annotations

import copy
import csv
import errno
import math
import os
import shutil
import signal
import stat
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import numpy as np
import openpyxl
import pandas as pd
import pytest
import tomli_w

import covtool
from covtool.cli import main
from covtool.errors import InputError, ModelFileError, StudyFileError
from covtool.io import atomic
from covtool.io.atomic import atomic_path, check_output_dir, remove_stale, staging_dir, write_text
from covtool.io.cells import csv_text_value
from covtool.io.config import load_toml
from covtool.io.names import NAME_PATTERN, check_file_stem
from covtool.io.writers import write_outputs
from covtool.results import StudyResult

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = Path(covtool.__file__).resolve().parent
PURE = ROOT / "studies" / "pure_ins_land_vehicle.toml"
ZUPT = ROOT / "studies" / "zupt_filter_order.toml"

#: the strings of issue 10 case 2, and the other OWASP triggers
EVIL = ['=1+2', '=HYPERLINK("http://x","y")', '=1+1', '@SUM(1,2)', "=cmd|' /C calc'!A0", '+1+2', '-1+2',
        '\t=1+2', '\r=1+2', '\uff1d1+2']
HARMLESS = ['plain', 'a,b "quoted"; c', 'x=1']


def _read_xlsx(path):
    wb = openpyxl.load_workbook(path)
    formulas = [(ws.title, c.coordinate, c.value) for ws in wb for row in ws.iter_rows() for c in row
                if c.data_type == "f"]
    return wb, formulas


def _column(ws, header):
    heads = [c.value for c in ws[1]]
    j = heads.index(header) + 1
    return [ws.cell(row=i, column=j) for i in range(2, ws.max_row + 1)]


def _csv_rows(path):
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.reader(fh))


# ---------------------------------------------------------------------------
# writer: text cells, neutralised CSV, NaN as text


def _evil_result():
    n = len(EVIL) + len(HARMLESS)
    x = np.linspace(1.0, 2.0, n) / 3.0           # full-precision floats
    x[1], x[2], x[3] = np.nan, np.inf, -np.inf
    table = pd.DataFrame({
        "case": EVIL + HARMLESS,
        "x [m]": x,
        "count": np.arange(n),
        "=SUM(A1:A3)": -x,                        # a formula-like header; negative numbers stay numbers
        "note": ["a\x01b"] + [None] * (n - 1),    # a control character; missing text
    })
    return StudyResult(
        name="evil_study", kind="test", tables={"summary": table},
        resolved={"study": {"kind": "test", "name": "evil_study", "description": "=4+4"}},
        provenance={"source": "=cmd|' /C calc'!A0", "model": "=4+4"},
        charts=[{"sheet": "summary", "x": "count", "y": ["x [m]"], "title": "=1+2"}])


def test_workbook_has_no_formula_and_keeps_user_text(tmp_path):
    r = _evil_result()
    write_outputs(r, tmp_path, figures=False)
    wb, formulas = _read_xlsx(tmp_path / "evil_study.xlsx")
    assert formulas == []
    ws = wb["summary"]
    cases = _column(ws, "case")
    # XML line-end normalisation reads a carriage return back as a line feed (documented in io.cells)
    assert [c.value for c in cases] == [e.replace("\r", "\n") for e in EVIL] + HARMLESS
    assert all(c.data_type == "s" for c in cases)
    # Excel's quote prefix: edited, the cell stays text (like a typed leading apostrophe)
    assert [bool(c.quotePrefix) for c in cases] == [True] * len(EVIL) + [False] * len(HARMLESS)
    heads = ws[1]
    assert heads[3].value == "=SUM(A1:A3)" and heads[3].data_type == "s" and heads[3].quotePrefix
    assert _column(ws, "note")[0].value == "a\\x01b"          # XML cannot hold \x01: written as its escape
    prov = {k.value: v for k, v in zip(_column(wb["provenance"], "key"), _column(wb["provenance"], "value"))}
    assert prov["source"].value == "=cmd|' /C calc'!A0" and prov["source"].data_type == "s"
    assert prov["model"].value == "=4+4" and prov["model"].quotePrefix


def test_nan_and_inf_are_text_never_empty_or_zero(tmp_path):
    r = _evil_result()
    x = r.tables["summary"]["x [m]"].to_numpy()
    write_outputs(r, tmp_path, figures=False)
    wb, _ = _read_xlsx(tmp_path / "evil_study.xlsx")
    cells = _column(wb["summary"], "x [m]")
    assert [c.value for c in cells[1:4]] == ["NaN", "inf", "-inf"]
    assert all(c.data_type == "s" for c in cells[1:4])
    finite = [i for i in range(len(x)) if math.isfinite(x[i])]
    assert all(cells[i].data_type == "n" for i in finite)
    # openpyxl writes 16 significant digits (Excel shows 15): equal to 1e-15
    assert [cells[i].value for i in finite] == pytest.approx(x[finite], rel=1e-15, abs=0)
    neg = _column(wb["summary"], "=SUM(A1:A3)")
    assert neg[0].data_type == "n" and neg[0].value == pytest.approx(-x[0], rel=1e-15)   # numbers stay numbers
    assert [c.value for c in _column(wb["summary"], "count")] == list(range(len(x)))
    # pandas keeps a missing text as NaN: shown as NaN too, never as an empty cell
    assert all(c.value == "NaN" for c in _column(wb["summary"], "note")[1:])

    rows = _csv_rows(tmp_path / "summary.csv")
    head, body = rows[0], rows[1:]
    j = head.index("x [m]")
    assert [b[j] for b in body[1:4]] == ["nan", "inf", "-inf"]
    assert all(float(body[i][j]) == x[i] for i in finite)              # exact round trip
    back = pd.read_csv(tmp_path / "summary.csv")
    assert back["x [m]"].isna().sum() == 1 and np.isposinf(back["x [m]"]).sum() == 1


def test_csv_neutralises_formula_text(tmp_path):
    write_outputs(_evil_result(), tmp_path, figures=False)
    rows = _csv_rows(tmp_path / "summary.csv")
    assert rows[0][3] == "'=SUM(A1:A3)"
    cases = [r[0] for r in rows[1:]]
    assert cases[:len(EVIL)] == ["'" + e for e in EVIL]
    assert cases[len(EVIL):] == HARMLESS
    assert [csv_text_value(c) for c in cases] == EVIL + HARMLESS
    assert rows[1][4] == "a\\x01b" and rows[2][4] == "nan"     # pandas holds None as NaN in a text column
    # negative numbers are numbers, not text: no apostrophe
    x = _evil_result().tables["summary"]["x [m]"].to_numpy()
    assert [float(r[3]) for r in rows[1:]] == pytest.approx(list(-x), nan_ok=True, rel=0, abs=0)


def _evil_study_files(tmp_path):
    """A short ZUPT study whose free text (sources, descriptions) looks like formulas."""
    model = tomllib.loads((ROOT / "models" / "sdins58.toml").read_text())
    model["model"]["description"] = "=4+4"
    model["block"][1]["source"] = "=cmd|' /C calc'!A0"
    model["block"][2]["source"] = "@SUM(1,2)"
    (tmp_path / "m.toml").write_text(tomli_w.dumps(model))
    filt = tomllib.loads((ROOT / "models" / "filters" / "zupt_filters.toml").read_text())
    for f in filt["filter"]:
        f["truth"] = model["model"]["name"]
        if f["name"] == "B1":
            f["description"] = '=HYPERLINK("http://x","y")'
    (tmp_path / "f.toml").write_text(tomli_w.dumps(filt))
    study = tomllib.loads(ZUPT.read_text())
    study["study"].update(duration="6 min", description="+1 study", name="evil")
    study["truth"]["model"] = str(tmp_path / "m.toml")
    study["filters"].update(file=str(tmp_path / "f.toml"), cases=["B1"])
    study["output"]["report_times"] = ["6 min"]
    (tmp_path / "s.toml").write_text(tomli_w.dumps(study))
    return tmp_path / "s.toml"


def test_real_run_writes_free_text_as_text(tmp_path, capsys):
    study = _evil_study_files(tmp_path)
    out = tmp_path / "out"
    assert main(["run", str(study), "--out", str(out), "--quiet", "--no-figures"]) == 0
    wb, formulas = _read_xlsx(out / "evil.xlsx")
    assert formulas == []
    src = _column(wb["truth_states"], "source")
    texts = [c.value for c in src]
    for s in ("=cmd|' /C calc'!A0", "@SUM(1,2)"):
        hits = [c for c in src if c.value == s]
        assert hits and all(c.data_type == "s" and c.quotePrefix for c in hits), (s, texts[:20])
    # the pure-INS row has no filter-claimed CEP: NaN, shown as the text NaN, never an empty cell
    summary = wb["summary"]
    cases = [c.value for c in _column(summary, "case")]
    claimed = _column(summary, "filter-claimed CEP [ft]")
    assert claimed[cases.index("pure_ins")].value == "NaN"
    assert claimed[cases.index("B1")].data_type == "n" and claimed[cases.index("B1")].value > 0
    rows = _csv_rows(out / "truth_states.csv")
    j = rows[0].index("source")
    assert "'=cmd|' /C calc'!A0" in [r[j] for r in rows[1:]]
    srows = _csv_rows(out / "summary.csv")
    k = srows[0].index("filter-claimed CEP [ft]")
    assert [r[k] for r in srows[1:] if r[0] == "pure_ins"] == ["nan"]
    assert not any(p.name.startswith((".staging", ".probe")) for p in out.iterdir())


# ---------------------------------------------------------------------------
# names validated at load


def _model_decl():
    return tomllib.loads((ROOT / "models" / "sdins58.toml").read_text())


def test_every_shipped_name_is_accepted():
    from covtool.io.filters import load_filters
    from covtool.io.imu_grade import load_imu_grade
    from covtool.io.model_file import load_model

    m = load_model(ROOT / "models" / "sdins58.toml")
    names = [m.name, *m.names, *{s.block for s in m.states}]
    for f in sorted((ROOT / "models" / "filters").glob("*.toml")):
        names += list(load_filters(f, m))
    for f in sorted((ROOT / "models" / "imu").glob("*.toml")):
        names.append(load_imu_grade(f).name)
    for f in sorted((ROOT / "studies").glob("*.toml")):
        names.append(tomllib.loads(f.read_text())["study"]["name"])
    assert len(names) > 80
    assert all(NAME_PATTERN.match(n) for n in names), [n for n in names if not NAME_PATTERN.match(n)]


@pytest.mark.parametrize("edit, match", [
    (lambda d: d["model"].update(name="=4+4"), r"\[model\] name: '=4\+4' is not a valid model name"),
    (lambda d: d["model"].update(name=5), r"\[model\] name: 5 is not a string"),
    (lambda d: d["block"][1].update(names=['=HYPERLINK("http://x","y")', "=1+1", "@SUM(1,2)"]),
     r"names: '=HYPERLINK.*is not a valid state name"),
    (lambda d: d["block"][1].update(name="acc bias"), r"block 2 \(acc bias\): name: 'acc bias' is not a valid block"),
    (lambda d: d["block"][0].update(name="=nav"), r"block 1 \(=nav\): name: '=nav' is not a valid block name"),
    (lambda d: d["block"][1].update(name="a" * 64), r"is not a valid state name"),   # 64 + '_x' > 64
])
def test_bad_model_names_refused_at_load(edit, match):
    from covtool.io.model_file import model_from_dict

    d = _model_decl()
    edit(d)
    with pytest.raises(ModelFileError, match=match):
        model_from_dict(d, path="models/x.toml")


def test_bad_filter_and_grade_names_refused_at_load():
    from covtool.io.filters import filters_from_dict
    from covtool.io.imu_grade import imu_grade_from_dict
    from covtool.io.model_file import model_from_dict

    truth = model_from_dict(_model_decl(), path="m.toml")
    with pytest.raises(ModelFileError, match=r"f.toml: filter 1: name: '=1\+2' is not a valid filter name"):
        filters_from_dict({"filter": [{"name": "=1+2", "keep": "all"}]}, truth, path="f.toml")
    grade = tomllib.loads((ROOT / "models" / "imu" / "kimu.toml").read_text())
    grade["imu"]["name"] = "@SUM(1,2)"
    with pytest.raises(ModelFileError, match=r"g.toml: \[imu\] name: '@SUM\(1,2\)' is not a valid IMU grade name"):
        imu_grade_from_dict(grade, path="g.toml")


UNSAFE_STUDY_NAMES = [
    ("/abs/path/victim", "is not a valid study name"),
    ("../../x", "is not a valid study name"),
    ("a/b", "is not a valid study name"),
    ("a\x00b", "is not a valid study name"),
    ("a\nb", "is not a valid study name"),
    ("", "is not a valid study name"),
    (".hidden", "is not a valid study name"),
    ("x" * 65, "is not a valid study name"),
    ("CON", "reserved device name"),
    ("nul.x", "reserved device name"),
    (7, "is not a string"),
]


@pytest.mark.parametrize("name, match", UNSAFE_STUDY_NAMES)
def test_unsafe_study_name_refused_before_any_computation(name, match):
    d = tomllib.loads(PURE.read_text())
    d["study"]["name"] = name
    d["truth"]["model"] = "no_such_model"          # loading the truth would fail: the name is checked first
    with pytest.raises(StudyFileError, match=r"<study>: \[study\] name: .*" + match):
        covtool.run_study(d)


@pytest.mark.parametrize("kind", ["ad_reset", "dual_imu"])
def test_unsafe_study_name_refused_by_every_study_kind(kind):
    with pytest.raises(StudyFileError, match=r"\[study\] name: '\.\./x' is not a valid study name"):
        covtool.run_study({"study": {"kind": kind, "name": "../x"}})


def test_study_name_from_an_unsafe_file_name(tmp_path):
    d = tomllib.loads(PURE.read_text())
    del d["study"]["name"]
    p = tmp_path / "my study.toml"
    p.write_text(tomli_w.dumps(d))
    with pytest.raises(StudyFileError, match=r"my study.toml: \[study\] name: 'my study' is not a valid study "
                       r"name.*\(taken from the file name; set \[study\] name\)"):
        covtool.run_study(p)


def test_writer_refuses_a_name_that_is_not_one_file_component(tmp_path):
    r = _evil_result()
    (tmp_path / "keep.txt").write_text("x")
    for bad, match in (("../x", "contains '/'"), ("..", "starts with '.'"), ("a/b", "contains '/'"),
                       ("/abs", "contains '/'"), ("-rf", "starts with '.' or '-'"),
                       ("a\x00b", r"contains '\\x00'")):
        r.name = bad
        with pytest.raises(InputError, match="study name: .*cannot be a file name: (it )?" + match):
            write_outputs(r, tmp_path / "out", figures=False)
    r.name = "ok"
    r.tables = {"../t": r.tables["summary"]}
    with pytest.raises(InputError, match=r"table '\.\./t'"):
        write_outputs(r, tmp_path / "out", figures=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]
    # a stem taken from an input file may have blanks (dualnav_<log stem>), unlike a study name
    assert check_file_stem("dualnav_flight 1", "x", strict=False) == "dualnav_flight 1"
    with pytest.raises(InputError, match="not a valid study name"):
        check_file_stem("dualnav_flight 1", "x")
    with pytest.raises(InputError, match="leading or trailing blanks"):
        check_file_stem("flight ", "x", strict=False)
    with pytest.raises(InputError, match="longer than 200 bytes"):
        check_file_stem("é" * 101, "x", strict=False)
    with pytest.raises(InputError, match="not a file name"):
        check_file_stem(None, "x", strict=False)


# ---------------------------------------------------------------------------
# --out checked before any computation


def test_output_dir_checks(tmp_path):
    f = tmp_path / "README.md"
    f.write_text("keep")
    with pytest.raises(InputError, match=r"--out '.*README.md': is an existing file, not a directory"):
        check_output_dir(f)
    with pytest.raises(InputError, match=r"--out '.*README.md/sub': cannot be created: '.*README.md' is a file"):
        check_output_dir(f / "sub")
    with pytest.raises(InputError, match=r"--out '/proc/nope': cannot be created: No such file or directory"):
        check_output_dir("/proc/nope")
    with pytest.raises(InputError, match=r"--out '/proc': is not writable"):
        check_output_dir("/proc")
    with pytest.raises(InputError, match=r"is inside the covtool package"):
        check_output_dir(PACKAGE / "results")
    with pytest.raises(InputError, match=r"is inside the covtool package"):
        check_output_dir(PACKAGE)
    from covtool.io.library import default_model_dir
    with pytest.raises(InputError, match=r"is inside the model library"):
        check_output_dir(Path(default_model_dir()) / "out")
    # a new nested directory is accepted and nothing is created by the check
    assert check_output_dir(tmp_path / "a" / "b" / "c") == tmp_path / "a" / "b" / "c"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["README.md"]
    assert check_output_dir(tmp_path) == tmp_path
    assert f.read_text() == "keep"


def _run_cli(args, cwd, **kw):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONDONTWRITEBYTECODE": "1", "MPLCONFIGDIR": str(cwd),
           "HOME": str(cwd)}
    return subprocess.run([sys.executable, "-m", "covtool", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300, **kw)


def _one_line_error(p, pattern):
    assert p.returncode == 2, (p.returncode, p.stderr)
    assert "Traceback" not in p.stderr and "Traceback" not in p.stdout
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1, p.stderr
    import re
    assert re.match(r"covtool: error: " + pattern, lines[0]), lines[0]


def _tree(d):
    """Every path under ``d`` (byte-code caches aside)."""
    return sorted(str(p.relative_to(d)) for p in Path(d).rglob("*") if "__pycache__" not in p.parts)


def test_cli_bad_out_is_one_line_before_the_study_runs(tmp_path):
    """``python -m covtool run`` with each bad ``--out``: exit 2, one line, nothing written."""
    d = tmp_path
    try:
        shutil.copy(PURE, d / "pure.toml")
        (d / "README.md").write_text("keep")
        ro = d / "readonly"
        ro.mkdir()
        ro.chmod(0o555)
        before, pkg_before = _tree(d), _tree(PACKAGE)
        cases = [
            ("README.md", r"--out 'README.md': is an existing file, not a directory"),
            ("/proc/nope", r"--out '/proc/nope': cannot be created: No such file or directory"),
            ("README.md/x", r"--out 'README.md/x': cannot be created: 'README.md' is a file"),
            (str(PACKAGE / "out"), r"--out '.*/covtool/out': is inside the covtool package"),
        ]
        for out, pattern in cases:
            _one_line_error(_run_cli(["run", "pure.toml", "--out", out], d), pattern)
        # a read-only directory, and a new directory under it (root ignores permission bits: /sys)
        ro = "/sys" if os.geteuid() == 0 else "readonly"
        for out, pattern in ((ro, rf"--out '{ro}': is not writable: Permission denied"),
                             (f"{ro}/new", rf"--out '{ro}/new': cannot be created: "
                                           "(Permission denied|Operation not permitted)")):
            _one_line_error(_run_cli(["run", "pure.toml", "--out", out], d), pattern)
        assert _tree(d) == before and _tree(PACKAGE) == pkg_before
        assert (d / "README.md").read_text() == "keep"
    finally:
        (d / "readonly").chmod(0o755)


def test_cli_unsafe_study_names_write_nothing(tmp_path, capsys):
    victim = tmp_path / "victim.xlsx"
    victim.write_text("precious")
    (tmp_path / "run").mkdir()
    d = tomllib.loads(PURE.read_text())
    d["study"]["duration"] = "6 min"
    d["output"]["report_times"] = ["6 min"]
    for name in (str(tmp_path / "victim"), "../../x", "a/b", "tab\tname"):
        d["study"]["name"] = name
        study = tmp_path / "run" / "s.toml"
        study.write_text(tomli_w.dumps(d))
        before = _tree(tmp_path)
        out = tmp_path / "run" / "o" / "p"
        assert main(["run", str(study), "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"covtool: error: {study}: [study] name: "), err
        assert "is not a valid study name" in err[0]
        assert _tree(tmp_path) == before
    assert victim.read_text() == "precious"


def test_cli_dualnav_checks_out_before_reading_logs(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("")
    assert main(["dualnav", "missing_main.csv", "missing_kimu.csv", "--out", str(f), "--quiet"]) == 2
    assert "is an existing file, not a directory" in capsys.readouterr().err


# ---------------------------------------------------------------------------
# file-level read errors: one line naming the file


def test_toml_file_errors_name_the_file(tmp_path, monkeypatch):
    good = tmp_path / "good.toml"
    good.write_bytes(b"\xef\xbb\xbf[model]\nname = \"x\"\n")          # a UTF-8 BOM is accepted
    assert load_toml(good) == {"model": {"name": "x"}}
    latin = tmp_path / "latin.toml"
    latin.write_bytes(b"[model]\nname = \"x\"\ndescription = \"caf\xe9\"\n")
    with pytest.raises(ModelFileError, match=r"latin.toml: is not UTF-8 text: byte 0xe9 at line 3, column 19"):
        load_toml(latin, ModelFileError)
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"[a]\n\x00\x01\x02\xff")
    with pytest.raises(StudyFileError, match=r"bin.toml: is a binary file \(NUL byte on line 2\)"):
        load_toml(binary, StudyFileError)
    with pytest.raises(StudyFileError, match=r"is a directory, not a TOML file"):
        load_toml(tmp_path, StudyFileError)
    with pytest.raises(StudyFileError, match=r"nope.toml: file not found"):
        load_toml(tmp_path / "nope.toml", StudyFileError)
    with pytest.raises(StudyFileError, match=r"good.toml/x.toml: file not found"):
        load_toml(good / "x.toml", StudyFileError)
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    with pytest.raises(StudyFileError, match=r"fifo.toml: is not a regular file"):
        load_toml(fifo, StudyFileError)
    big = tmp_path / "big.toml"
    with open(big, "wb") as fh:
        fh.truncate(17 * 2**20)
    with pytest.raises(StudyFileError, match=r"big.toml: is 17 MiB; a TOML file over 16 MiB is refused"):
        load_toml(big, StudyFileError)
    bad = tmp_path / "bad.toml"
    bad.write_text("[study\n")
    with pytest.raises(StudyFileError, match=r"bad.toml: TOML syntax error: .*line 1"):
        load_toml(bad, StudyFileError)

    from covtool.io import config

    def denied(*a, **k):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(config, "open", denied, raising=False)
    with pytest.raises(StudyFileError, match=r"good.toml: permission denied"):
        load_toml(good, StudyFileError)

    def eio(*a, **k):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(config, "open", eio, raising=False)
    with pytest.raises(StudyFileError, match=r"good.toml: cannot read the file: Input/output error"):
        load_toml(good, StudyFileError)


def test_cli_unreadable_study_and_model_files_are_one_line(tmp_path, capsys):
    d = tomllib.loads(PURE.read_text())
    model = tmp_path / "latin_model.toml"
    model.write_bytes((ROOT / "models" / "sdins58.toml").read_bytes().replace(b"navigation-grade", b"caf\xe9", 1))
    d["truth"]["model"] = str(model)
    study = tmp_path / "s.toml"
    study.write_text(tomli_w.dumps(d))
    for target, pattern in ((tmp_path, "is a directory, not a TOML file"),
                            (study, r"latin_model.toml: is not UTF-8 text: byte 0xe9"),
                            (ROOT / "covtool" / "__init__.py", "TOML syntax error")):
        assert main(["run", str(target), "--out", str(tmp_path / "o"), "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "Traceback" not in err[0]
        import re
        assert re.search(pattern, err[0]), err[0]
    assert not (tmp_path / "o").exists()


# ---------------------------------------------------------------------------
# umask, staging, atomicity


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o002])
def test_atomic_files_honour_the_umask(tmp_path, mask):
    old = os.umask(mask)
    try:
        write_text(tmp_path / "a.txt", "x")
        with atomic_path(tmp_path / "b.bin") as tmp:
            tmp.write_bytes(b"y")
        write_outputs(_evil_result(), tmp_path / "out", figures=False)
    finally:
        os.umask(old)
    want = 0o666 & ~mask
    for p in (tmp_path / "a.txt", tmp_path / "b.bin", tmp_path / "out" / "summary.csv",
              tmp_path / "out" / "evil_study.xlsx", tmp_path / "out" / "resolved_study.toml"):
        assert stat.S_IMODE(p.stat().st_mode) == want, (p, oct(p.stat().st_mode))
    assert stat.S_IMODE((tmp_path / "out").stat().st_mode) == 0o777 & ~mask


def _killed_writer(out_dir):
    """Start a process that opens a staging directory and is killed by SIGKILL inside it."""
    code = textwrap.dedent(f"""
        import os, signal
        from covtool.io.atomic import staging_dir, atomic_path
        with atomic_path({str(out_dir / "chunk.json")!r}) as tmp:
            tmp.write_text("half")
            with staging_dir({str(out_dir)!r}) as st:
                (st / "summary.csv").write_text("half-written")
                os.kill(os.getpid(), signal.SIGKILL)
    """)
    p = subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert p.returncode == -signal.SIGKILL


def test_staging_left_by_kill_9_is_removed_by_the_next_run(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    _killed_writer(out)
    left = sorted(p.name for p in out.iterdir())
    assert any(n.startswith(".staging-") for n in left) and any(n.endswith(".tmp") for n in left)
    # a live writer's staging directory is left alone
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        live = out / f".staging-{sleeper.pid}-abc"
        live.mkdir()
        old_style_new = out / ".staging-q1w2e3"              # no PID (older covtool), recent
        old_style_new.mkdir()
        old_style_old = out / ".staging-z9x8c7"
        old_style_old.mkdir()
        os.utime(old_style_old, (1e9, 1e9))
        tmp = next(p for p in out.iterdir() if p.name.endswith(".tmp"))
        os.utime(tmp, (1e9, 1e9))                            # older than the minute of grace
        probe = out / f".probe-{_dead_pid()}-x1"             # of a check_output_dir killed mid-probe
        probe.write_text("")
        os.utime(probe, (1e9, 1e9))
        young = out / f".chunk.json.{_dead_pid()}-y2.tmp"     # within the grace: maybe another host's writer
        young.write_text("")
        write_outputs(_evil_result(), out, figures=False)
        names = sorted(p.name for p in out.iterdir())
        assert live.name in names and old_style_new.name in names
        assert old_style_old.name not in names and tmp.name not in names and probe.name not in names
        assert young.name in names
        assert not [n for n in names if n.startswith(".staging-") and n not in (live.name, old_style_new.name)]
        assert check_output_dir(out) == out                  # the early check cleans up as well
        assert live.exists()
    finally:
        sleeper.kill()
        sleeper.wait()
    assert remove_stale(out) == [live]


def _dead_pid():
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_failure_leaves_earlier_outputs_and_no_staging(tmp_path):
    r = _evil_result()
    write_outputs(r, tmp_path, figures=False)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def interrupted():
        raise KeyboardInterrupt

    r2 = copy.deepcopy(r)
    r2.tables["summary"]["x [m]"] = 0.0
    r2.figures = {"fig": interrupted}
    with pytest.raises(KeyboardInterrupt):
        write_outputs(r2, tmp_path, figures=True)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    # a directory where an output file goes: refused before any file moves
    r2.figures = {}
    (tmp_path / "resolved_study.toml").unlink()
    (tmp_path / "resolved_study.toml").mkdir()
    with pytest.raises(InputError, match=r"resolved_study.toml: is a directory; .*no output was changed"):
        write_outputs(r2, tmp_path, figures=False)
    assert (tmp_path / "summary.csv").read_bytes() == before["summary.csv"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_staging_dir_removed_on_error(tmp_path):
    with pytest.raises(RuntimeError):
        with staging_dir(tmp_path) as st:
            (st / "a").write_text("x")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_current_umask_reads_without_changing():
    old = os.umask(0o037)
    try:
        assert atomic.current_umask() == 0o037
        assert os.umask(0o037) == 0o037
    finally:
        os.umask(old)


def test_trade_grade_name_refused_at_load():
    d = tomllib.loads((ROOT / "studies" / "trade_grid.toml").read_text())
    d["grade"][1]["name"] = "=2*3"
    with pytest.raises(StudyFileError, match=r"\[\[grade\]\] #2 name: '=2\*3' is not a valid grade name"):
        covtool.run_study(d)
