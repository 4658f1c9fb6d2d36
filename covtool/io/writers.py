"""Write a :class:`~covtool.results.StudyResult` to an output directory.

Outputs: ``summary.csv``, one CSV per table, ``<name>.xlsx`` workbook with a
provenance sheet, one PNG per figure, and ``resolved_study.toml``.  Everything
is staged and moved into place atomically (:mod:`covtool.io.atomic`).  Text
is written so that no spreadsheet evaluates it, and a NaN is never an empty
cell (:mod:`covtool.io.cells`).  Every file lands inside ``out_dir``: the
workbook's name is checked to be one plain file-name component first.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
from pathlib import Path

import tomli_w

from covtool.version import __version__, source_revision
from covtool.results import StudyResult
from covtool.errors import InputError
from covtool.io.atomic import staging_dir
from covtool.io.cells import write_csv
from covtool.io.names import check_file_stem


def build_workbook(*args, **kwargs):
    """:func:`covtool.io.workbook.build_workbook`, imported on first use (pandas-free start)."""
    from covtool.io.workbook import build_workbook as build

    return build(*args, **kwargs)


def _toml_safe(obj):
    if isinstance(obj, dict):
        return {str(k): _toml_safe(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, (list, tuple)):
        return [_toml_safe(v) for v in obj]
    if hasattr(obj, "item"):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def provenance_rows(result: StudyResult) -> dict:
    """Provenance key/value rows: tool version, time, platform, resolved study."""
    rows = {
        "tool": "covtool",
        "tool_version": __version__,
        "tool_commit": source_revision(),
        "study": result.name,
        "kind": result.kind,
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    rows.update(result.provenance)
    rows["resolved_study"] = tomli_w.dumps(_toml_safe(result.resolved))
    return rows


def _inside(stage: Path, filename: str) -> Path:
    """``stage / filename``, refused unless it is a direct child of ``stage``."""
    p = stage / filename
    if p.parent != stage or p.name != filename:
        raise InputError(repr(filename), "is not a plain file name; no output was written")
    return p


def write_outputs(result: StudyResult, out_dir, *, figures: bool = True, server=None) -> list[Path]:
    """Write all outputs of ``result`` into ``out_dir``; return the file paths.

    Parameters
    ----------
    result : StudyResult
    out_dir : path-like
    figures : bool
        Draw the figures (PNG files).
    server : covtool.io.figure_server.FigureServer, optional
        A running figure server (the command line's; one job each): the
        figures are sent to it, else (or if it cannot take them, or fails)
        drawn in forked processes from ``result`` as usual.

    Raises
    ------
    InputError
        The study or a table name is not one plain file-name component
        (checked before anything is written), or an output's place in
        ``out_dir`` is taken by a directory.
    """
    out_dir = Path(out_dir)
    check_file_stem(result.name, "study name", strict=False)
    for name in result.tables:
        check_file_stem(name, f"table {name!r}", strict=False)
    written = []
    with staging_dir(out_dir) as stage:
        tables = [(df, _inside(stage, f"{name}.csv")) for name, df in result.tables.items()]
        book = _inside(stage, f"{result.name}.xlsx")
        items = [(name, make, _inside(stage, f"{name}.png")) for name, make in result.figures.items()] \
            if figures and result.figures else []
        # the figures are drawn in other processes (started first: matplotlib's import is the longest
        # wait, which a figure server has done already) while this one writes the tables and the workbook
        served = server.submit(result, items) if server is not None and items else None
        children = [served] if served is not None else _start_figures(items)
        try:
            for df, path in tables:
                write_csv(df, path)
            build_workbook(result.tables, provenance_rows(result), result.charts, path=book)
            (stage / "resolved_study.toml").write_text(
                f"# resolved by covtool {__version__}, source {source_revision()}\n" + tomli_w.dumps(_toml_safe(result.resolved)), encoding="utf-8")
        except BaseException:
            _finish_figures(children, report=False)
            raise
        try:
            _finish_figures(children)
        except Exception:
            if served is None:
                raise
            # the server could not draw them (a view it could not use): drawn from the full result; a
            # figure's own error is raised again from there
            _finish_figures(_start_figures(items))
        except BaseException:                           # interrupted while waiting: no drawing goes on
            _finish_figures(children, report=False)
            raise
        written = [out_dir / p.relative_to(stage) for p in sorted(stage.rglob("*")) if p.is_file()]
    return written


#: processes that draw a study's figures at once (besides the one writing the tables); None: one per core,
#: at most :data:`MAX_FIGURE_PROCESSES` (a container may report its host's cores)
FIGURE_PROCESSES = None
MAX_FIGURE_PROCESSES = 4
#: zlib level of the PNG files (PIL's default is 6)
PNG_COMPRESSION = 3


#: axes titles at the top of their axes (matplotlib's default moves each one above any decoration on
#: top, measuring the x axis's tight box at every draw: 14 % of drawing the budget's figures, which,
#: like every figure of the shipped studies, have nothing on top, so the pixels are the same)
FIXED_TITLES = {"axes.titley": 1.0}


def draw_figures(items) -> None:
    """Draw and save ``(name, make, path)`` figures with the Agg backend.

    Titles sit at the top of their axes (:data:`FIXED_TITLES`).

    A figure without a layout gets the constrained layout (never
    ``bbox_inches="tight"``, which draws every figure twice).  A figure
    whose layout is done (:func:`covtool.plotting.style.fixed_margins`,
    ``tight_layout``) holds a placeholder layout engine; it is removed
    before saving, because ``savefig`` draws a figure that has any layout
    engine twice (once without rendering, for the layout) -- the same
    pixels at twice the cost.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.layout_engine import PlaceHolderLayoutEngine

    for _name, make, path in items:
        with matplotlib.rc_context(FIXED_TITLES):
            fig = make()
            engine = fig.get_layout_engine()
            if engine is None:
                fig.set_layout_engine("constrained")
            elif isinstance(engine, PlaceHolderLayoutEngine):
                fig.set_layout_engine(None)
            # zlib level 3 instead of 6: the same pixels, encoded in ~30 % less time, files 5-12 % larger
            fig.savefig(path, dpi=120, pil_kwargs={"compress_level": PNG_COMPRESSION})
        plt.close(fig)


def draw_in_processes(items) -> None:
    """Import matplotlib once, then draw the figures in forked children.

    Runs in a child of the writer (:func:`_start_figures`) or in a figure
    server (:mod:`covtool.io.figure_server`): matplotlib's
    import (0.3-0.8 s) is paid once, by this process, never by the one
    writing the tables, and each child inherits it.  Up to
    :data:`FIGURE_PROCESSES` children (one per core by default) take the
    figures from a queue in the study's order, the next one as soon as
    they are done with the last, so that a long figure does not wait
    behind another and a child's second figure finds its fonts and text
    caches warm.  The first error is re-raised.
    """
    from covtool.forked import Forked

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401 - imported once here, inherited by every child

    n = min(len(items), _figure_processes())
    if n <= 1 or len(items) > 255:
        _finish_figures([Forked(draw_figures, items[w::max(n, 1)]) for w in range(max(n, 1))])
        return
    r, w = os.pipe()                                     # the queue: one byte per figure, read one at a time
    try:
        os.write(w, bytes(range(len(items))))            # ≤ 255 bytes: one atomic write into the pipe's buffer
        os.close(w)
        w = None
        children = [Forked(_draw_queued, items, r) for _ in range(n)]   # each dies with this process
    finally:
        if w is not None:
            os.close(w)
        os.close(r)
    _finish_figures(children)


def _figure_processes() -> int:
    """:data:`FIGURE_PROCESSES`, or the cores this process may run on (at most :data:`MAX_FIGURE_PROCESSES`)."""
    if FIGURE_PROCESSES is not None:
        return max(1, int(FIGURE_PROCESSES))
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_FIGURE_PROCESSES))


def _draw_queued(items, fd: int) -> None:
    """In a figure child: draw the figures whose indices it reads from ``fd`` until the queue is empty."""
    while True:
        b = os.read(fd, 1)
        if not b:
            return
        draw_figures([items[b[0]]])


def _start_figures(items) -> list:
    """Draw ``items`` in a forked child (:func:`draw_in_processes`), while this process writes the tables."""
    from covtool.forked import Forked

    return [Forked(draw_in_processes, items)] if items else []


def _finish_figures(children, report: bool = True) -> None:
    """Wait for the figure processes; re-raise the first error (if ``report``; else stop them)."""
    error = None
    for c in children:
        if not report:
            c.cancel()
            continue
        try:
            c.result()
        except BaseException as e:                     # noqa: BLE001 - the first one is re-raised
            error = error or e
    if error is not None:
        raise error
