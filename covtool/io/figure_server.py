"""A process that prepares matplotlib while a study computes, then draws the study's figures.

Drawing a study's figures first costs about half a second of imports
(matplotlib, pandas, the plotting code) and a first figure's set-up (fonts,
the mathtext parser of log-axis labels), which the figures would otherwise
wait for after the computation.  ``covtool run`` starts this server first
thing (:meth:`FigureServer.start`): a forked child that does that work on
the otherwise idle core, then waits.  When the result is ready,
:func:`covtool.io.writers.write_outputs` sends it the figure makers,
rebound to a light copy of the result
(:meth:`covtool.results.StudyResult.figure_view`), through a pipe; the
server draws them as :func:`covtool.io.writers.draw_in_processes` does.

The server only saves time: when it cannot take the figures (no
``os.fork``, a maker that does not pickle, a view larger than
:data:`MAX_VIEW_BYTES`) or fails to draw them, the writer draws them as
before, from the full result.  It dies with this process
(:class:`covtool.forked.Forked`) and is reaped by :meth:`FigureServer.close`
(SIGTERM first).  The command line starts it once the study file has
been read and the output directory locked, so that a mistake in the
command or the file's TOML starts nothing.
"""

from __future__ import annotations

import os
import pickle
from functools import partial

from covtool.forked import Forked

#: a larger pickled view is not sent (the writer draws from the full result instead)
MAX_VIEW_BYTES = 64 * 2**20


def _prepare() -> None:
    """Import what drawing needs and draw one small figure (fonts, mathtext parser, Agg caches).

    Its log axis keeps matplotlib's mathtext labels, which build the parser
    once for the figures whose labels hold mathtext (seed 000's); the
    studies' own log axes are labelled in plain text
    (:func:`covtool.plotting.style.log_axis`).

    matplotlib's log messages of this step (a cache directory it could not
    create, a font cache it rebuilds) are held back: they would precede the
    study's own output, or an input error's one line.
    """
    import gc
    import logging

    quiet = logging.getLogger("matplotlib")
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)
    # no cyclic collection while matplotlib is imported (its modules are garbage to none of it: one full
    # collection of the growing heap cost 0.1 s), then the imported objects frozen out of every later one:
    # the drawing children's collections scan their figures, not matplotlib
    collecting = gc.isenabled()
    gc.disable()
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        import covtool.results  # noqa: F401 - pandas and the result classes, for unpickling the view

        fig, ax = plt.subplots(figsize=(2.0, 2.0))
        ax.plot([1.0, 2.0, 3.0], [1.0, 30.0, 1e4], label="x")
        ax.set_yscale("log")
        ax.set_title("t [min]")
        ax.legend()
        fig.canvas.draw()
        plt.close(fig)
    finally:
        quiet.setLevel(level)
        gc.freeze()
        if collecting:
            gc.enable()


#: bytes of the job's length, sent before the job (big-endian)
_HEADER = 8


def _read_exactly(fd: int, n: int) -> bytes | None:
    """``n`` bytes from ``fd``, or None at end of file before them."""
    chunks, left = [], n
    while left:
        b = os.read(fd, min(left, 1 << 20))
        if not b:
            return None
        chunks.append(b)
        left -= len(b)
    return b"".join(chunks)


def _serve(job_fd: int, other_fd: int):
    """In the server: prepare, read one length-prefixed job, draw it; None if the pipe closes first.

    The job's length comes first, so the server never waits for the end
    of the pipe (a process forked later may hold its write end open).
    SIGTERM (:meth:`FigureServer.close`) raises ``SystemExit`` here, so
    that matplotlib's ``finally`` blocks run (its font-cache lock file).
    """
    import signal
    import sys

    from covtool.io.writers import draw_in_processes

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    os.close(other_fd)                                  # the write end belongs to the parent
    _prepare()
    head = _read_exactly(job_fd, _HEADER)
    job = None if head is None else _read_exactly(job_fd, int.from_bytes(head, "big"))
    os.close(job_fd)
    if job is None:
        return None
    draw_in_processes(pickle.loads(job))
    return "drawn"


def light_items(result, items) -> list:
    """``items`` with each maker that is a ``functools.partial`` over a result rebound to its figure view.

    Parameters
    ----------
    result : covtool.results.StudyResult
    items : list of (str, callable, pathlib.Path)

    Returns
    -------
    list of (str, callable, pathlib.Path)
        What :meth:`FigureServer.submit` pickles: a maker over the data it
        draws (a partial of a plotting function over arrays and tables) is
        sent as it is; one over ``result``, or over another result object
        (a variant of it, as the trade grid's per-aiding figures), draws from
        that object's :meth:`~covtool.results.StudyResult.figure_view` instead.
    """
    from covtool.results import StudyResult

    views = {}
    light = []
    for name, make, path in items:
        if isinstance(make, partial) and make.args and isinstance(make.args[0], StudyResult):
            own = make.args[0]
            if id(own) not in views:
                views[id(own)] = (own, own.figure_view())      # the object kept: its id stays its own
            make = partial(make.func, views[id(own)][1], *make.args[1:], **(make.keywords or {}))
        light.append((name, make, path))
    return light


class FigureServer:
    """A forked process that draws one study's figures (module notes).

    Use :meth:`start`, then at most one :meth:`submit`, then :meth:`close`
    (or the object as a context manager).
    """

    def __init__(self):
        r, w = os.pipe()
        try:
            self._child = Forked.waiting(_serve, r, w)
        except OSError:
            os.close(r)
            os.close(w)
            raise
        os.close(r)
        self._w = w

    @classmethod
    def start(cls) -> "FigureServer | None":
        """A running server, or None where none can be forked."""
        try:
            return cls()
        except OSError:
            return None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def submit(self, result, items):
        """Send the figures ``items`` of ``result``; return a handle, or None if it cannot take them.

        One job per server: after a call (sent or not) the server takes no
        other; one that cannot take the figures is stopped at once.

        Parameters
        ----------
        result : covtool.results.StudyResult
        items : list of (str, callable, pathlib.Path)
            ``(name, maker, png path)``; a maker that is a
            ``functools.partial`` over ``result`` is rebound to its
            :meth:`~covtool.results.StudyResult.figure_view`.

        Returns
        -------
        object with ``result()`` and ``cancel()``, or None
            ``result()`` waits for the figures and raises the first error.
        """
        if self._w is None:
            return None
        try:
            payload = pickle.dumps(light_items(result, items), protocol=pickle.HIGHEST_PROTOCOL)
        except Exception:                                   # noqa: BLE001 - a closure, a lock: drawn here instead
            payload = None
        if payload is None or len(payload) > MAX_VIEW_BYTES:
            self.close()
            return None
        try:
            data = memoryview(len(payload).to_bytes(_HEADER, "big") + payload)
            while data:
                data = data[os.write(self._w, data):]
        except OSError:                                     # the server is gone
            self.close()
            return None
        os.close(self._w)
        self._w = None
        return self._child

    def close(self) -> None:
        """Stop the server (it has drawn, or will get nothing) and reap it; idempotent.

        A server still preparing or waiting is stopped with SIGTERM (SIGKILL
        after a grace period): killed outright it could leave matplotlib's
        font cache half written and its lock file behind.
        """
        if self._w is not None:
            os.close(self._w)
            self._w = None
        self._child.terminate()                             # nothing once its result was collected
