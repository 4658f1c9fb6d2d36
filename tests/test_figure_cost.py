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
