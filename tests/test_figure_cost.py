"""Figures drawn once, with the same pixels (issue 13, acceptance 1 and 3).

Before: ``savefig`` drew every figure of :mod:`covtool.plotting` twice
(a figure laid out by ``fixed_margins`` or ``tight_layout`` keeps a
placeholder layout engine, and matplotlib pre-draws any figure that has a
layout engine); each of two figure processes imported matplotlib; PNGs
were compressed at zlib level 6.
"""

from __future__ import annotations

import os

import numpy as np
import pandas as pd
import pytest

from covtool.io import writers


def _budget_result():
    from covtool.results import ErrorBudgetResult

    t = np.linspace(0, 600, 61)
    v = {e: np.array([(1.0 + t) * 10.0 ** -k for k in range(12)]) for e in ("horizontal", "altitude", "azimuth")}
    names = [f"initial source {k}" for k in range(12)]
    return ErrorBudgetResult(name="b", kind="error_budget", tables={"summary": pd.DataFrame()}, times=t,
                             variances={"B1": v}, sources={"B1": names}, source_order=names, top=8,
                             stops=((200.0, 300.0),), length_unit="ft")


def _counted(make, draws: list):
    """``make`` whose figure counts its draws into ``draws``."""
    def counted():
        fig = make()
        draw = fig.draw

        def counting(renderer):
            draws.append(1)
            return draw(renderer)

        fig.draw = counting
        return fig
    return counted


def _pixels(path):
    from PIL import Image

    return np.asarray(Image.open(path))


@pytest.mark.parametrize("layout", ["fixed_margins", "tight_layout"])
def test_a_laid_out_figure_is_drawn_once_with_the_pixels_of_a_plain_savefig(tmp_path, layout):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from covtool.plotting.budget import budget_figure

    def make():
        fig = budget_figure(_budget_result(), "B1")          # laid out by fixed_margins
        if layout == "tight_layout":
            fig.set_layout_engine(None)
            fig.tight_layout()
        return fig

    draws: list = []
    writers.draw_figures([("b", _counted(make, draws), tmp_path / "b.png")])
    assert len(draws) == 1
    ref = make()
    assert ref.get_layout_engine() is not None               # matplotlib would pre-draw this one
    ref_draws: list = []
    ref = _counted(lambda: ref, ref_draws)()
    ref.savefig(tmp_path / "ref.png", dpi=120)                # matplotlib's defaults: two draws, zlib level 6
    plt.close(ref)
    assert len(ref_draws) == 2
    a, b = _pixels(tmp_path / "b.png"), _pixels(tmp_path / "ref.png")
    assert a.shape == b.shape == (1320, 1920, 4)
    np.testing.assert_array_equal(a, b)


def test_a_figure_without_layout_gets_the_constrained_layout(tmp_path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seen = []

    def make():
        fig, ax = plt.subplots(figsize=(4, 3))
        ax.plot([0, 1], [0, 1])
        ax.set_ylabel("a long label [m]")
        fig.set_layout_engine(None)
        seen.append(fig)
        return fig

    writers.draw_figures([("c", make, tmp_path / "c.png")])
    assert type(seen[0].get_layout_engine()).__name__ == "ConstrainedLayoutEngine"
    assert _pixels(tmp_path / "c.png").shape == (360, 480, 4)


def _gone(pid: int) -> bool:
    """The process has exited: no such process, or (Linux) a zombie not yet reaped."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    try:
        with open(f"/proc/{pid}/status") as fh:
            return next(line.split()[1] for line in fh if line.startswith("State:")) == "Z"
    except (FileNotFoundError, ProcessLookupError, StopIteration):
        return True


def test_a_failed_write_stops_the_drawing_children(tmp_path, monkeypatch):
    """The writer fails while a figure is being drawn: its process ends and writes nothing."""
    import time

    pidfile = tmp_path / "pid"

    def slow():
        pidfile.write_text(str(os.getpid()))
        time.sleep(60)
        raise AssertionError("not stopped")

    def boom(*args, **kwargs):
        for _ in range(600):                                   # the figure process has started drawing
            if pidfile.exists() and pidfile.read_text():
                break
            time.sleep(0.05)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(writers, "build_workbook", boom)
    from covtool.results import StudyResult

    res = StudyResult(name="s", kind="test", tables={"summary": pd.DataFrame({"x [m]": [1.0]})},
                      resolved={"study": {"kind": "test", "name": "s"}}, provenance={})
    res.figures = {"slow": slow}
    out = tmp_path / "out"
    with pytest.raises(OSError, match="No space left"):
        writers.write_outputs(res, out)
    pid = int(pidfile.read_text())
    for _ in range(200):                                       # its lifeline closed with its parent
        if _gone(pid):
            break
        time.sleep(0.05)
    assert _gone(pid)
    assert not out.exists() or not [p for p in out.rglob("*") if p.is_file()]


def test_log_axis_puts_minor_ticks_at_2_and_5_of_each_decade():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from covtool.plotting.style import log_axis

    fig, ax = plt.subplots()
    ax.plot([1, 2], [1e-3, 1e2])
    log_axis(ax, "y")
    log_axis(ax, "x")
    assert ax.get_yscale() == "log" and ax.get_xscale() == "log"
    ax.set_ylim(1e-3, 1e2)
    minor = ax.yaxis.get_minorticklocs()
    inside = minor[(minor > 1e-3) & (minor < 1e2)]
    mant = np.round(inside / 10.0 ** np.floor(np.log10(inside)), 6)
    assert set(mant) == {2.0, 5.0} and inside.size == 10           # five decades, two each
    with pytest.raises(ValueError, match="which must be 'x' or 'y', got 'z'"):
        log_axis(ax, "z")
    plt.close(fig)


def test_plain_log_labels_are_the_decades_in_unicode():
    from covtool.plotting.ticks import plain_label, PlainLogFormatter

    # the forms LogFormatterSciNotation writes, each as the text it should read
    assert plain_label(r"$\mathdefault{10^{-2}}$") == "10\u207b\u00b2"
    assert plain_label(r"$\mathdefault{10^{15}}$") == "10\u00b9\u2075"
    assert plain_label(r"$\mathdefault{2\times10^{3}}$") == "2\u00d710\u00b3"
    assert plain_label(r"$\mathdefault{0}$") == "0"
    assert plain_label("") == ""
    assert plain_label(r"$\mathdefault{10^{0.30}}$") == r"$\mathdefault{10^{0.30}}$"   # not a known form: kept
    fmt = PlainLogFormatter(base=10.0)
    assert [fmt(x) for x in (1e-3, 1.0, 1e4)] == ["10\u207b\u00b3", "10\u2070", "10\u2074"]
    assert fmt(3e2) == "3\u00d710\u00b2"                                # a non-decade, as matplotlib writes it


def test_log_axes_draw_without_a_mathtext_parse(monkeypatch):
    """A log axis (major and minor labels) is drawn without mathtext; the labels read 10ⁿ and c×10ⁿ."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.mathtext
    import matplotlib.pyplot as plt

    from covtool.plotting.style import log_axis, plain_log_labels

    parsed = []
    real = matplotlib.mathtext.MathTextParser.parse
    monkeypatch.setattr(matplotlib.mathtext.MathTextParser, "parse",
                        lambda self, s, *a, **k: parsed.append(s) or real(self, s, *a, **k))
    fig, (a1, a2) = plt.subplots(1, 2)
    a1.plot([1, 2], [1e-3, 1e4])
    log_axis(a1, "y")
    a2.plot([1, 2], [20.0, 300.0])
    a2.set_yscale("log")                 # under two decades: matplotlib labels the minor ticks too
    plain_log_labels(a2, "y")
    a1.set_ylim(1e-3, 1e4)
    a2.set_ylim(20.0, 300.0)
    fig.canvas.draw()
    major = [t.get_text() for t in a1.yaxis.get_ticklabels() if t.get_text()]
    minor = [t.get_text() for t in a2.yaxis.get_ticklabels(minor=True) if t.get_text()]
    plt.close(fig)
    assert parsed == []
    assert "10\u207b\u00b3" in major and "10\u2074" in major and "10\u2070" in major
    assert "2\u00d710\u00b9" in minor and "3\u00d710\u00b2" in minor
    with pytest.raises(ValueError, match="which must be 'x' or 'y', got 'z'"):
        plain_log_labels(a1, "z")
