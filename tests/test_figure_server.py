"""The figure server: figures drawn from a light view of the result, the same pixels (issue 13).

``covtool run`` forks :class:`covtool.io.figure_server.FigureServer` first
thing; it prepares matplotlib while the study computes and draws the
figures from :meth:`covtool.results.StudyResult.figure_view`.  The files must
be byte for byte those drawn from the full result; a maker the server
cannot take, or a view it cannot draw from, must fall back to the usual
path; a server that gets no job must go at once, leaving no process.
"""

from __future__ import annotations

import os
import time
import tomllib
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from covtool.io import writers
from covtool.io.figure_server import FigureServer
from covtool.results import StudyResult

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="the server is a forked process")


@dataclass
class _Heavy(StudyResult):
    """A result with a large field no figure reads, and one the figure reads."""

    curve: np.ndarray = field(default_factory=lambda: np.zeros(0))
    system: object = None
    drawn_from = ("curve",)


def _curve_figure(result, k):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(3, 2))
    ax.semilogy(np.arange(result.curve.size), result.curve ** k)
    ax.set_title(f"{result.name}: power {k}")
    return fig


def _system_figure(result):
    """A figure that (wrongly) reads a field declared not drawn: the view cannot draw it."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot(result.system[:10, 0])
    return fig


def _heavy(figures=None) -> _Heavy:
    r = _Heavy(name="heavy", kind="test", tables={"summary": pd.DataFrame({"x [m]": [1.0]})},
               resolved={"study": {"kind": "test", "name": "heavy"}}, provenance={},
               curve=np.linspace(1.0, 1e3, 50), system=np.ones((2000, 1000)))      # 16 MB not drawn
    r.figures = figures(r) if figures else {f"p{k}": partial(_curve_figure, r, k) for k in (1, 2)}
    return r


def _reaped(pid):
    with pytest.raises(ChildProcessError):
        os.waitpid(pid, os.WNOHANG)


def test_the_view_leaves_out_what_no_figure_reads_and_the_makers():
    r = _heavy()
    v = r.figure_view()
    assert type(v) is _Heavy and v.system is None and v.figures == {}
    assert v.tables is None and v.resolved is None and v.name == "heavy" and v.kind == "test"
    assert v.curve is r.curve and r.system is not None and len(r.figures) == 2       # the result is untouched


def test_a_maker_over_a_variant_of_the_result_is_sent_its_view_too(tmp_path):
    """The trade grid's per-aiding figures are partials over ``dataclasses.replace(result, ...)``."""
    import dataclasses
    import pickle

    from covtool.io.figure_server import light_items

    r = _heavy()
    variant = dataclasses.replace(r, curve=r.curve[::-1].copy())
    items = [("own", partial(_curve_figure, r, 1), tmp_path / "own.png"),
             ("variant", partial(_curve_figure, variant, 1), tmp_path / "variant.png")]
    light = light_items(r, items)
    for (_, make, _), src in zip(light, (r, variant)):
        view = make.args[0]
        assert view is not src and view.system is None and view.tables is None
        np.testing.assert_array_equal(view.curve, src.curve)
    assert len(pickle.dumps(light)) < 100_000                        # not the 16-MB systems
    writers.draw_figures(pickle.loads(pickle.dumps(light)))
    ref = tmp_path / "ref.png"
    writers.draw_figures([("v", partial(_curve_figure, variant, 1), ref)])
    assert (tmp_path / "variant.png").read_bytes() == ref.read_bytes()


def test_served_figures_equal_those_drawn_from_the_full_result(tmp_path):
    r = _heavy()
    with FigureServer.start() as server:
        files = writers.write_outputs(r, tmp_path / "out", server=server)
        pid = server._child.pid
        assert server._w is None                           # the job was sent: the server drew them
    _reaped(pid)
    ref = tmp_path / "ref"
    ref.mkdir()
    writers.draw_figures([(n, m, ref / f"{n}.png") for n, m in r.figures.items()])
    assert sorted(p.name for p in files if p.suffix == ".png") == ["p1.png", "p2.png"]
    for n in r.figures:
        assert (tmp_path / "out" / f"{n}.png").read_bytes() == (ref / f"{n}.png").read_bytes()


def test_a_maker_that_does_not_pickle_is_drawn_the_usual_way(tmp_path):
    r = _heavy(lambda r: {"closure": lambda: _curve_figure(r, 1)})
    with FigureServer.start() as server:
        pid = server._child.pid
        assert server.submit(r, [("closure", r.figures["closure"], tmp_path / "x.png")]) is None
        _reaped(pid)                                       # a server that cannot take them is stopped at once
        files = writers.write_outputs(r, tmp_path / "out", server=server)
    assert (tmp_path / "out" / "closure.png") in files


def test_a_view_the_server_cannot_draw_from_falls_back_to_the_full_result(tmp_path):
    r = _heavy(lambda r: {"sys": partial(_system_figure, r)})
    with FigureServer.start() as server:
        files = writers.write_outputs(r, tmp_path / "out", server=server)
        assert server._w is None                           # it was sent, failed there, and was drawn here
    ref = tmp_path / "ref.png"
    writers.draw_figures([("sys", r.figures["sys"], ref)])
    assert (tmp_path / "out" / "sys.png") in files
    assert (tmp_path / "out" / "sys.png").read_bytes() == ref.read_bytes()


def test_a_figure_error_still_reaches_the_caller_as_itself(tmp_path):
    from covtool.errors import InputError

    r = _heavy(lambda r: {"bad": partial(_bad_figure, r)})
    with FigureServer.start() as server:
        with pytest.raises(InputError, match=r"heavy.toml: \[output\] figure: cannot be drawn \(test\)"):
            writers.write_outputs(r, tmp_path / "out", server=server)
    assert not [p for p in (tmp_path / "out").rglob("*") if p.is_file()]


def _bad_figure(result):
    from covtool.errors import InputError

    raise InputError(f"{result.name}.toml: [output] figure", "cannot be drawn (test)")


def test_a_process_forked_after_the_server_does_not_hold_up_its_job(tmp_path):
    """The job is length-prefixed: a later child holding the pipe's write end open changes nothing."""
    from covtool.forked import Forked

    r = _heavy()
    with FigureServer.start() as server:
        sleeper = Forked(time.sleep, 60)                   # inherits the job pipe's write end
        try:
            t0 = time.perf_counter()
            writers.write_outputs(r, tmp_path / "out", server=server)
            assert time.perf_counter() - t0 < 30
            assert server._w is None
        finally:
            sleeper.cancel()
    assert sorted(p.name for p in (tmp_path / "out").glob("*.png")) == ["p1.png", "p2.png"]


def test_a_server_without_a_job_goes_at_once_and_leaves_no_process():
    server = FigureServer.start()
    pid = server._child.pid
    t0 = time.perf_counter()
    server.close()                                         # still importing matplotlib: SIGTERM, not awaited
    assert time.perf_counter() - t0 < 2.0
    _reaped(pid)
    server.close()                                         # idempotent


def _short(name: str, tmp_path: Path) -> Path:
    """``studies/<name>.toml`` over 6 min (if it has a duration), reported at 6 min, the models' paths absolute."""
    decl = tomllib.loads((ROOT / "studies" / f"{name}.toml").read_text())
    if "duration" in decl["study"]:
        decl["study"]["duration"] = "6 min"
    if "report_times" in decl.get("output", {}):
        decl["output"]["report_times"] = ["6 min"]
    if "file" in decl.get("filters", {}):
        decl["filters"]["file"] = str(ROOT / "models" / "filters" / Path(decl["filters"]["file"]).name)
    import tomli_w

    p = tmp_path / f"{name}.toml"
    p.write_text(tomli_w.dumps(decl))
    return p


@pytest.mark.parametrize("name", ["zupt_filter_order", "error_budget", "zupt_sensitivity", "pure_ins_land_vehicle",
                                  "ad_reset_scale_error", "aided_odometer_sweep"])
def test_every_figure_of_the_studies_that_leave_fields_out_is_the_same_from_the_view(name, tmp_path):
    """The fields each result declares drawn are the only ones its figures read; every maker pickles."""
    import pickle

    from covtool.studies import run_study

    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")                    # validity notes of a short study: not the point here
        r = run_study(_short(name, tmp_path))
    from covtool.io.figure_server import light_items

    full, served = tmp_path / "full", tmp_path / "served"
    full.mkdir()
    served.mkdir()
    items = [(n, m, served / f"{n}.png") for n, m in r.figures.items()]
    job = pickle.dumps(light_items(r, items))               # what the server is sent: it must pickle
    over_result = [m for m in r.figures.values() if isinstance(m, partial) and m.args and m.args[0] is r]
    assert not over_result or type(r).drawn_from is not None
    writers.draw_figures([(n, m, full / f"{n}.png") for n, m in r.figures.items()])
    writers.draw_figures(pickle.loads(job))
    for n in r.figures:
        assert (served / f"{n}.png").read_bytes() == (full / f"{n}.png").read_bytes(), n
    # the job unpickles without the modules only the study needed: a trajectory would import
    # covtool.nav.trajectory (and, while its position was a scipy ODE solution, scipy.integrate: 0.3 s in
    # the server, before any figure), the board's parameters python-control
    blob = tmp_path / "job.pickle"
    blob.write_bytes(job)
    import subprocess
    import sys

    code = ("import pickle, sys; import covtool.results; pickle.loads(open(sys.argv[1], 'rb').read()); "
            "print(sorted(m for m in ('scipy.integrate', 'covtool.nav.trajectory', 'control') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code, str(blob)], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_every_field_a_result_class_draws_from_is_one_of_its_fields():
    import dataclasses

    from covtool.results import RESULT_CLASSES

    classes = RESULT_CLASSES.values() if isinstance(RESULT_CLASSES, dict) else RESULT_CLASSES
    for cls in classes:
        fields = {f.name for f in dataclasses.fields(cls)}
        if cls.drawn_from is not None:
            assert set(cls.drawn_from) <= fields - {"name", "kind", "figures"}, cls.__name__
