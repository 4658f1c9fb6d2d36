"""Figures drawn in forked processes while the tables are written (issue 13).

:func:`covtool.io.writers.write_outputs` draws a study's figures in up to
``FIGURE_PROCESSES`` children: the files must be the same as drawn in
process, an error raised while drawing must reach the caller as itself
(type and message), and a failed run must leave no output.
"""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pandas as pd
import pytest

from covtool.errors import InputError
from covtool.io import writers
from covtool.results import StudyResult


def _figure(k: int):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot(np.arange(5), np.arange(5) ** k)
    ax.set_title(f"power {k} (pid-independent)")
    return fig


def _result(figures: dict) -> StudyResult:
    table = pd.DataFrame({"x [m]": [1.0, 2.0]})
    res = StudyResult(name="figs", kind="test", tables={"summary": table},
                      resolved={"study": {"kind": "test", "name": "figs"}}, provenance={})
    res.figures = figures
    return res


def _png_size(path):
    head = open(path, "rb").read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def test_figures_from_child_processes_equal_those_drawn_in_process(tmp_path):
    figs = {f"p{k}": (lambda k=k: _figure(k)) for k in range(3)}
    files = writers.write_outputs(_result(figs), tmp_path / "out")
    assert sorted(p.name for p in files if p.suffix == ".png") == ["p0.png", "p1.png", "p2.png"]
    ref = tmp_path / "ref"
    ref.mkdir()
    writers.draw_figures([(n, m, ref / f"{n}.png") for n, m in figs.items()])
    for n in figs:
        assert _png_size(tmp_path / "out" / f"{n}.png") == _png_size(ref / f"{n}.png") == (360, 240)
        assert (tmp_path / "out" / f"{n}.png").read_bytes() == (ref / f"{n}.png").read_bytes()


@pytest.mark.parametrize("processes", [1, 2, None])
def test_more_figures_than_processes_are_each_drawn_once_from_the_queue(tmp_path, monkeypatch, processes):
    """The drawing children take the figures from a queue (one per core by default): all of them, once."""
    monkeypatch.setattr(writers, "FIGURE_PROCESSES", processes)
    figs = {f"q{k}": (lambda k=k: _figure(k % 4)) for k in range(7)}
    files = writers.write_outputs(_result(figs), tmp_path / "out")
    assert sorted(p.name for p in files if p.suffix == ".png") == sorted(f"{n}.png" for n in figs)
    ref = tmp_path / "ref"
    ref.mkdir()
    writers.draw_figures([(n, m, ref / f"{n}.png") for n, m in figs.items()])
    for n in figs:
        assert (tmp_path / "out" / f"{n}.png").read_bytes() == (ref / f"{n}.png").read_bytes(), n


def test_drawing_processes_follow_the_cores_up_to_a_cap(monkeypatch):
    """One per core this process may run on, at most MAX_FIGURE_PROCESSES (a container may show its host's)."""
    monkeypatch.setattr(writers, "FIGURE_PROCESSES", None)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(64)), raising=False)
    assert writers._figure_processes() == writers.MAX_FIGURE_PROCESSES == 4
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert writers._figure_processes() == 2
    monkeypatch.setattr(writers, "FIGURE_PROCESSES", 3)
    assert writers._figure_processes() == 3


def test_an_error_while_drawing_reaches_the_caller_and_nothing_is_written(tmp_path):
    def bad():
        raise InputError("figs.toml: [output] figure", "cannot be drawn (test)")

    out = tmp_path / "out"
    with pytest.raises(InputError, match=r"figs.toml: \[output\] figure: cannot be drawn \(test\)"):
        writers.write_outputs(_result({"good": lambda: _figure(1), "bad": bad}), out)
    assert not [p for p in out.rglob("*") if p.is_file()]


def test_a_figure_process_that_dies_is_reported(tmp_path):
    def dies():
        os._exit(3)

    with pytest.raises(RuntimeError, match="a worker process ended with status 3 and no result"):
        writers.write_outputs(_result({"dies": dies}), tmp_path / "out")


# ---------------------------------------------------------------------------
# covtool.forked.Forked, the one helper behind the figure processes and the flagship's impact table


def _child_work(n):
    import warnings

    from covtool.errors import CovtoolWarning

    warnings.warn(f"from the child: {n}", CovtoolWarning)
    return os.getpid(), np.arange(n) ** 2


def test_forked_call_returns_its_value_from_another_process_and_reissues_its_warnings():
    from covtool.errors import CovtoolWarning
    from covtool.forked import Forked

    job = Forked(_child_work, 5)
    with pytest.warns(CovtoolWarning, match="from the child: 5"):
        pid, sq = job.result()
    assert pid != os.getpid()
    np.testing.assert_array_equal(sq, [0, 1, 4, 9, 16])
    np.testing.assert_array_equal(job.result()[1], sq)          # collected once, kept


def test_a_child_that_dies_leaves_no_result_memory_open():
    """A drawing child may die (the figure queue's other children go on): its result memory is closed too."""
    from covtool.forked import Forked

    job = Forked(os._exit, 3)
    with pytest.raises(RuntimeError, match="a worker process ended with status 3 and no result"):
        job.result()
    assert job._mfd is None                                 # closed (Forked._close_memory) and forgotten


def test_forked_call_reraises_the_error_and_cancel_reaps_the_child():
    import time

    from covtool.errors import NumericalError
    from covtool.forked import Forked

    def fails():
        raise NumericalError("impact: filter B1: step 3 is not PSD")

    with pytest.raises(NumericalError, match="impact: filter B1: step 3 is not PSD"):
        Forked(fails).result()
    job = Forked(time.sleep, 60)
    job.cancel()
    with pytest.raises(ChildProcessError):
        os.waitpid(job.pid, os.WNOHANG)                     # reaped: no such child any more
    with pytest.raises(RuntimeError, match="a worker process ended with status -9 and no result"):
        job.result()


def test_fixed_margins_place_the_axes_in_inches_and_no_writer_overrides_them(tmp_path):
    import matplotlib.pyplot as plt

    from covtool.plotting.style import fixed_margins

    fig = _figure(2)
    fig.set_size_inches(10, 5)
    fixed_margins(fig, left=1.0, right=2.0, bottom=0.5, top=1.0)
    writers.draw_figures([("m", lambda: fig, tmp_path / "m.png")])      # the writer's path: no other layout
    x0, y0, x1, y1 = fig.axes[0].get_position().extents
    assert (x0, x1) == pytest.approx((0.1, 0.8), abs=1e-12)
    assert (y0, y1) == pytest.approx((0.1, 0.8), abs=1e-12)
    assert _png_size(tmp_path / "m.png") == (1200, 600)
    plt.close(fig)


def test_budget_figure_legend_lies_beside_the_axes_and_inside_the_figure():
    import matplotlib.pyplot as plt

    from covtool.plotting.budget import budget_figure
    from covtool.results import ErrorBudgetResult

    t = np.linspace(0, 600, 61)
    v = {e: np.array([(1.0 + t) * 10.0 ** -k for k in range(12)]) for e in ("horizontal", "altitude", "azimuth")}
    names = [f"initial source {k}" for k in range(12)]
    r = ErrorBudgetResult(name="b", kind="error_budget", tables={"summary": pd.DataFrame()}, times=t,
                          variances={"B1": v}, sources={"B1": names}, source_order=names, top=8,
                          stops=((200.0, 300.0),), length_unit="ft")
    fig = budget_figure(r, "B1")
    fig.canvas.draw()
    leg = fig.legends[0].get_window_extent()
    right = max(ax.get_window_extent().x1 for ax in fig.axes)
    assert leg.x0 >= right and leg.x1 <= fig.bbox.x1
    plt.close(fig)


def test_forked_call_runs_in_process_while_tracemalloc_traces():
    import tracemalloc

    from covtool.forked import Forked

    tracemalloc.start()
    try:
        assert Forked(os.getpid).result() == os.getpid()
    finally:
        tracemalloc.stop()
    assert Forked(os.getpid).result() != os.getpid()


def _blas_threads():
    from threadpoolctl import threadpool_info

    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_forked_children_and_their_parent_use_one_blas_thread_until_the_last_is_collected():
    """Two processes × the default BLAS pool on a 2-core machine doubled the impact child's time (issue 13)."""
    from threadpoolctl import threadpool_limits

    from covtool.forked import Forked

    assert _blas_threads()                                    # numpy's OpenBLAS, seen by threadpoolctl
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        a = Forked(_blas_threads)
        b = Forked(_blas_threads)
        assert set(_blas_threads()) == {1}                   # the parent, while children run
        assert set(a.result()) == {1}                         # the child
        assert set(_blas_threads()) == {1}                    # b still runs
        assert set(b.result()) == {1}
        assert _blas_threads() == before                      # the pool given back
        c = Forked(_blas_threads)
        c.cancel()
        assert _blas_threads() == before


class _Unwound(BaseException):
    """Raised by the test's signal handler (as the command line's handler raises Interrupted)."""


@pytest.mark.skipif(not hasattr(os, "fork") or not hasattr(signal, "pthread_sigmask"), reason="POSIX fork")
@pytest.mark.parametrize("waiting", [False, True])
def test_a_signal_before_the_child_reaches_its_guard_never_unwinds_the_parent_code(tmp_path, monkeypatch, waiting):
    """SIGTERM at the child's first instruction after the fork (a figure server stopped at once, under load).

    With a raising handler (the command line's ``_on_signal``) the child used to unwind through the parent's
    callers: under xdist it returned 143 from ``main()`` and went on running tests (INTERNALERROR).  Now the
    signal waits until the child's guard: the child ends there, the caller's code runs in the parent only.
    """
    import covtool.forked as fk

    parent = os.getpid()
    marker = tmp_path / "escaped"
    real_fork = os.fork

    def fork_then_signal():
        pid = real_fork()
        if pid == 0:
            os.kill(os.getpid(), signal.SIGTERM)          # delivered now unless held across the fork
        return pid

    def on_term(signum, frame):
        raise _Unwound()

    old = signal.signal(signal.SIGTERM, on_term)
    monkeypatch.setattr(fk.os, "fork", fork_then_signal)
    try:
        try:
            job = (fk.Forked.waiting if waiting else fk.Forked)(time.sleep, 0.01)
        except _Unwound:
            if os.getpid() != parent:                     # the child unwound into this test: record it, leave
                marker.write_text("the child ran the caller's code")
                os._exit(99)
            raise
        with pytest.raises((RuntimeError, _Unwound)):     # the child ended in its guard: no value
            job.result()
    finally:
        monkeypatch.undo()
        signal.signal(signal.SIGTERM, old)
    assert os.getpid() == parent and not marker.exists()
