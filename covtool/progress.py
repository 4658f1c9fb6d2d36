"""The one progress bar of covtool's long runs (tqdm on stderr).

Every study runner, the execution backends' chunk loop and ``covtool
dualnav`` call :func:`progress_bar`, so ``--quiet`` silences them all and
they look alike.  The command line decides whether bars are shown
(:func:`wanted`): on when stderr is a terminal, or when asked
(``--progress``); never with ``--quiet``.
"""

from __future__ import annotations

import sys

__all__ = ["progress_bar", "progress_iter", "wanted", "NoBar", "DELAY"]

#: seconds before a bar appears: work shorter than this shows nothing
DELAY = 1.0


def wanted(*, quiet: bool = False, force: bool = False, stream=None) -> bool:
    """Whether to show progress bars.

    Parameters
    ----------
    quiet : bool
        ``--quiet``: never (wins over ``force``).
    force : bool
        ``--progress``: also when stderr is not a terminal (a log file).
    stream : file, optional
        The stream the bars go to (default ``sys.stderr``).

    Returns
    -------
    bool
    """
    if quiet:
        return False
    if force:
        return True
    s = sys.stderr if stream is None else stream
    try:
        return bool(s.isatty())
    except (AttributeError, ValueError):          # a closed or replaced stream
        return False


def progress_bar(total: int, desc: str, enabled: bool, *, unit: str = "step", initial: int = 0):
    """A tqdm bar on stderr, shown only after :data:`DELAY` seconds.

    Parameters
    ----------
    total : int
        Units of work.
    desc : str
        Label (``"filters"``, ``"flights"``).
    enabled : bool
        False draws nothing (``--quiet``, or stderr not a terminal).
    unit : str
        Name of one unit of work.
    initial : int
        Units already done (a resumed run).

    Returns
    -------
    tqdm.tqdm or NoBar
        A tqdm bar, or (``enabled`` false) a :class:`NoBar` that draws nothing.
        Use as a context manager; ``update(n)`` after each piece.
    """
    if not enabled:
        # nothing to draw: tqdm's import (60-90 ms, its version lookup through importlib.metadata) is not paid
        return NoBar(total, initial)
    from tqdm.auto import tqdm

    # no monitor thread: a process with a thread alive does not fork (covtool.forked.can_split)
    tqdm.monitor_interval = 0
    return tqdm(total=total, initial=initial, desc=desc, disable=False, delay=DELAY, leave=False,
                unit=unit, file=sys.stderr, smoothing=0.1, dynamic_ncols=True)


class NoBar:
    """A progress bar that draws nothing (:func:`progress_bar` when bars are not wanted).

    It counts as a shown tqdm bar does (``n``, ``total``; ``disable`` is
    True) and is a context manager.
    """

    disable = True

    def __init__(self, total: int, initial: int = 0):
        self.total, self.n = total, initial

    def update(self, n: int = 1) -> None:
        """Count ``n`` more units done."""
        self.n += n

    def close(self) -> None:
        """Nothing to close."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def progress_iter(iterable, desc: str, enabled: bool, *, unit: str = "step"):
    """Iterate over ``iterable`` with a :func:`progress_bar` (its length is the total)."""
    items = list(iterable)
    with progress_bar(len(items), desc, enabled, unit=unit) as bar:
        for item in items:
            yield item
            bar.update(1)
