"""One function call in a forked child process, its result collected later.

Used to overlap independent work on a multi-core machine without pickling
the inputs: the child inherits the parent's memory (copy-on-write), runs
the call and sends back only its (small) result through a pipe.  The
figures of a study are drawn while its tables are written
(:mod:`covtool.io.writers`); the flagship's dropped-state impact table is
computed while its cases are propagated
(:mod:`covtool.studies.zupt_filter_order`); :func:`split` runs parts of one
computation at once that write their results into shared memory
(:func:`shared_empty`: the large discretisations of
:func:`covtool.studies.grid.discretize_chunked`); :meth:`Forked.waiting`
starts a server that waits for its job (the command line's figure server,
:mod:`covtool.io.figure_server`).  Without ``os.fork`` the call runs at
once, in this process.
"""

from __future__ import annotations

import os
import pickle
import warnings


#: children running, and the BLAS limiter that holds this process to one thread while any runs
_ACTIVE = {"children": 0, "limiter": None}


def _one_blas_thread() -> None:
    """Hold BLAS to one thread while forked children run (the first child takes the limit).

    A child and its parent each running the default BLAS pool (one thread
    per core) put twice as many busy threads as cores on the machine: the
    pool's threads spin waiting for each other and both processes slow
    down (the flagship's impact child took twice its solo time).  One
    thread each keeps one process per core.
    """
    if _ACTIVE["children"] == 0:
        try:
            from threadpoolctl import threadpool_limits

            _ACTIVE["limiter"] = threadpool_limits(limits=1, user_api="blas")
        except Exception:                                   # noqa: BLE001 - a speed measure only
            _ACTIVE["limiter"] = None
    _ACTIVE["children"] += 1


def _release_blas() -> None:
    """One child fewer; the last one gives the BLAS pool back."""
    _ACTIVE["children"] = max(0, _ACTIVE["children"] - 1)
    if _ACTIVE["children"] == 0 and _ACTIVE["limiter"] is not None:
        try:
            _ACTIVE["limiter"].restore_original_limits()
        finally:
            _ACTIVE["limiter"] = None


#: the signals a forked child takes only inside its guard (:func:`_hold_signals`)
HELD_SIGNALS = ("SIGINT", "SIGTERM")


def _hold_signals():
    """Block :data:`HELD_SIGNALS` in this thread; return the mask to restore (None where it cannot be done).

    Around ``os.fork``: the child inherits the block, so a signal sent to it
    before it reaches its ``try`` (the parent stopping a server it has just
    started, Ctrl-C to the process group) waits until :func:`_release_signals`
    inside the guard, where whatever its handler raises ends the child, never
    the parent's code.  The parent's own signals wait for the few
    microseconds of the fork and are then taken as usual.
    """
    import signal

    if not hasattr(signal, "pthread_sigmask"):
        return None
    sigs = {getattr(signal, name) for name in HELD_SIGNALS if hasattr(signal, name)}
    return signal.pthread_sigmask(signal.SIG_BLOCK, sigs)


def _release_signals(mask) -> None:
    """Restore the signal mask :func:`_hold_signals` returned (a signal held meanwhile is taken now)."""
    if mask is not None:
        import signal

        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def _tracing() -> bool:
    import sys

    return "tracemalloc" in sys.modules and sys.modules["tracemalloc"].is_tracing()


class Forked:
    """``fn(*args, **kwargs)`` running in a forked child.

    Parameters
    ----------
    fn : callable
        Its result must be picklable.
    *args, **kwargs
        Passed to ``fn`` as they are (inherited, never pickled).

    Notes
    -----
    Warnings the call issues are recorded in the child and issued again
    in the parent by :meth:`result`; an exception is re-raised there as
    itself (or as a ``RuntimeError`` naming it if it cannot be pickled).
    A child whose result is never collected is stopped when the object
    is deleted (the caller failed first).  While a child runs, this
    process and the child use one BLAS thread each (:func:`_one_blas_thread`);
    the last child collected gives the pool back.  A child dies with this
    process, even when it is killed (:func:`_watch_parent`).  While :mod:`tracemalloc`
    traces, the call runs in this process, so that a traced peak is that
    of the whole computation.
    """

    def __init__(self, fn, *args, **kwargs):
        self._start(fn, args, kwargs, busy=True)

    @classmethod
    def waiting(cls, fn, *args, **kwargs) -> "Forked":
        """A child that mostly waits (a server fed through a pipe): not counted as running.

        Unlike a :class:`Forked` child it leaves this process's BLAS pool
        as it is and does not stop :func:`split` from forking; without
        ``os.fork``, or while :mod:`tracemalloc` traces, it raises
        ``OSError`` instead of running the call here (the call would wait
        for this process).
        """
        self = cls.__new__(cls)
        if not hasattr(os, "fork") or _tracing():
            raise OSError("no forked server here")
        self._start(fn, args, kwargs, busy=False)
        return self

    def _start(self, fn, args, kwargs, busy):
        self.pid = None
        self._done = False
        self._busy = busy
        if not hasattr(os, "fork") or _tracing():
            self._run_here(fn, args, kwargs)
            return
        r, w = os.pipe()
        life_r, life_w = os.pipe()                          # the lifeline: only this process writes (never)
        self._mfd = _result_memory() if busy else None      # where the child puts the result's large arrays
        if busy:
            _one_blas_thread()                              # this process and the child: one BLAS thread each
        # SIGINT and SIGTERM are held back across the fork: the child takes them only inside its guard (a
        # handler that raises, as the command line's does, would otherwise unwind the child through this
        # process's callers: found as a figure server stopped at once that returned 143 from main())
        held = _hold_signals()
        try:
            pid = os.fork()
        except OSError:
            _release_signals(held)
            if busy:
                _release_blas()
            for fd in (r, w, life_r, life_w):
                os.close(fd)
            self._close_memory()
            raise
        if pid == 0:                                        # the child: run, report, leave without cleanup
            code = 0
            try:
                _release_signals(held)                      # a signal held since the fork is taken here
                os.close(r)
                os.close(life_w)
                _watch_parent(life_r)
                payload = _outcome(fn, args, kwargs, self._mfd)
            except BaseException:                           # noqa: BLE001 - nothing may escape the child
                code, payload = 1, b""
            try:
                view = memoryview(payload)
                while view:
                    view = view[os.write(w, view):]
            finally:
                os._exit(code)
        _release_signals(held)
        os.close(w)
        os.close(life_r)
        self.pid, self._fd, self._life = pid, r, life_w

    def _close_memory(self) -> None:
        if getattr(self, "_mfd", None) is not None:
            os.close(self._mfd)
            self._mfd = None

    def _run_here(self, fn, args, kwargs):
        self._payload = _outcome(fn, args, kwargs)
        self._status = 0
        self._done = True

    def result(self):
        """Wait for the call; return its value or raise its exception.

        Raises
        ------
        Exception
            What the call raised.
        RuntimeError
            The child ended without a result (killed, out of memory).
        """
        if not self._done:
            chunks = []
            while True:
                b = os.read(self._fd, 1 << 20)
                if not b:
                    break
                chunks.append(b)
            os.close(self._fd)
            os.close(self._life)
            _, status = os.waitpid(self.pid, 0)
            self._payload, self._status = b"".join(chunks), os.waitstatus_to_exitcode(status)
            self._done = True
            if self._busy:
                _release_blas()
        if not self._payload:
            self._close_memory()                            # a child that died leaves its result memory here
            raise RuntimeError(f"a worker process ended with status {self._status} and no result")
        if not hasattr(self, "_outcome"):
            try:
                ok, value, caught = _loads(self._payload, getattr(self, "_mfd", None))
            finally:
                self._close_memory()
            if not ok:
                value = _rebuild(*value)
            self._outcome = ok, value
            for w in caught:                                # issued once, at the first collection
                warnings.warn_explicit(w[0], w[1], w[2], w[3])
        ok, value = self._outcome
        if not ok:
            raise value
        return value

    def cancel(self) -> None:
        """Stop the child (if still running) and reap it; its result is dropped."""
        if self._done or self.pid is None:
            return
        import signal

        try:
            os.kill(self.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        os.waitpid(self.pid, 0)
        self._dropped(-9)

    def terminate(self, grace: float = 5.0) -> None:
        """Stop the child with SIGTERM, SIGKILL after ``grace`` seconds; reap it; its result is dropped.

        For a child that may be writing files outside this module's control
        (matplotlib's font cache): SIGTERM lets it unwind, its ``finally``
        blocks run (a lock file removed).
        """
        if self._done or self.pid is None:
            return
        import signal
        import time

        try:
            os.kill(self.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        end = time.monotonic() + grace
        while time.monotonic() < end:
            if os.waitpid(self.pid, os.WNOHANG)[0]:
                self._dropped(-15)
                return
            time.sleep(0.01)
        self.cancel()

    def _dropped(self, status: int) -> None:
        """The child is reaped without its result: close the pipes, give the BLAS pool back."""
        os.close(self._fd)
        os.close(self._life)
        self._close_memory()
        self._payload, self._status, self._done = b"", status, True
        if self._busy:
            _release_blas()

    def __del__(self):
        # a result never collected (the parent failed first): the child is stopped and reaped
        try:
            self.cancel()
        except Exception:                                   # noqa: BLE001 - interpreter shutdown
            pass


def can_split() -> bool:
    """Whether :func:`split` runs its parts at once: a fork is possible and useful here.

    Only the main thread of a top-level process forks, with two cores or
    more, while no other thread runs (a lock another thread holds at the
    fork would stay held in the child), while no other :class:`Forked`
    child runs (a child of this module or a worker of
    :mod:`covtool.parallel` already keeps the other core busy), and never
    while :mod:`tracemalloc` traces.
    """
    import multiprocessing
    import threading

    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    others = [t for t in threading.enumerate()
              if t is not threading.current_thread() and t.name != WATCHDOG_THREAD]
    return (hasattr(os, "fork") and cores >= 2 and _ACTIVE["children"] == 0 and not _tracing()
            and threading.current_thread() is threading.main_thread() and not others
            and multiprocessing.parent_process() is None)


def shared_empty(shape, dtype=float, *, shared: bool = True):
    """An uninitialised array that a forked child can fill (anonymous shared memory).

    Parameters
    ----------
    shape : tuple of int
    dtype : numpy dtype
    shared : bool
        False: an ordinary ``np.empty`` (nothing will be forked).

    Returns
    -------
    ndarray
        Writable; backed by a ``MAP_SHARED`` anonymous mapping when
        ``shared``, so that what a forked child writes is seen by this
        process (no pickling, no copy).

    Raises
    ------
    OSError
        The system refused the mapping (the caller falls back to
        ``shared=False`` and one process).
    """
    import mmap

    import numpy as np

    size = int(np.prod(shape, dtype=np.int64))
    nbytes = size * np.dtype(dtype).itemsize
    if not shared or nbytes == 0:
        return np.empty(shape, dtype)
    return np.frombuffer(mmap.mmap(-1, nbytes), dtype=dtype, count=size).reshape(shape)   # OSError: no mapping


def split(fn, parts) -> list:
    """``[fn(p) for p in parts]``, the first part here and the others in forked children at once.

    For work that writes its results into :func:`shared_empty` arrays
    (each part its own slice) and returns little.  Runs the parts one
    after the other here unless :func:`can_split`.  The error of the
    earliest failing part is raised (this process's part first), after
    every child has been stopped and reaped.
    """
    parts = list(parts)
    if len(parts) < 2 or not can_split():
        return [fn(p) for p in parts]
    children = []
    try:
        for p in parts[1:]:
            try:
                children.append(Forked(fn, p))
            except OSError:                                 # no fork now (EAGAIN, ENOMEM): the rest here
                break
        first = fn(parts[0])
        return [first] + [c.result() for c in children] + [fn(p) for p in parts[1 + len(children):]]
    finally:
        for c in children:
            c.cancel()


#: name of a forked child's thread that waits for its parent's death (:func:`_watch_parent`)
WATCHDOG_THREAD = "covtool-parent-watchdog"

#: exit status of a forked child whose parent died (nobody waits for it)
ORPHAN_EXIT = 75


def _watch_parent(fd: int) -> None:
    """In a forked child: exit at once when the parent dies (even by SIGKILL).

    ``fd`` is the read end of a pipe whose write end only the parent keeps
    open (the *lifeline*, the same design as
    :class:`covtool.parallel.ProcessBackend`'s workers); the kernel closes
    it when the parent exits, the read returns EOF and the child leaves, so
    it never writes on into a staging directory being removed.  A sibling
    forked later inherits the write end too; it dies first on its own
    lifeline, so the children go in turn, newest first.
    """
    import threading

    def watch():
        try:
            os.read(fd, 1)
        except OSError:
            pass
        os._exit(ORPHAN_EXIT)

    threading.Thread(target=watch, name=WATCHDOG_THREAD, daemon=True).start()


#: arrays of at least this many bytes in a child's result travel through shared memory, not the pipe
OUT_OF_BAND_BYTES = 1 << 20
#: alignment of each array in that memory (bytes)
_ALIGN = 64


def _result_memory() -> int | None:
    """A memory file (``memfd``) a forked child can size and fill with its result's arrays, or None."""
    try:
        return os.memfd_create("covtool-forked-result", os.MFD_CLOEXEC)
    except (AttributeError, OSError):
        return None


def _outcome(fn, args, kwargs, mfd: int | None = None) -> bytes:
    """Pickled ``(ok, value or (exception class, args, attributes), warnings)`` of one call.

    An exception travels as its class, ``args`` and attributes, not pickled
    itself: an exception whose ``__init__`` takes other arguments than its
    ``args`` (``InputError(where, problem)``) does not unpickle.

    With ``mfd`` (a forked child's :func:`_result_memory`), the buffers of
    :data:`OUT_OF_BAND_BYTES` or more (numpy arrays, by pickle protocol 5)
    are written into that memory file instead of the pickle stream
    (:func:`_dumps`): the parent maps them where they are (:func:`_loads`)
    instead of reading tens of MB through the pipe and copying them twice.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            out = (True, fn(*args, **kwargs))
        except BaseException as e:                          # noqa: BLE001 - re-raised by Forked.result
            out = (False, (type(e), e.args, dict(getattr(e, "__dict__", {}))))
    ws = [(w.message, w.category, w.filename, w.lineno) for w in caught]
    try:
        return _dumps((*out, ws), mfd)
    except Exception as e:                                  # noqa: BLE001 - an unpicklable result or error
        what = f"{out[1][0].__name__}: {out[1][1]}" if not out[0] else f"{type(e).__name__}: {e}"
        return _dumps((False, (RuntimeError, (what,), {}), []), None)


def _dumps(obj, mfd: int | None) -> bytes:
    """``pickle.dumps(obj)`` framed as ``(layout, stream)``; large buffers into ``mfd`` (layout: their offsets, sizes)."""
    if mfd is None:
        return pickle.dumps(((), pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)))
    import mmap

    bufs = []

    def keep_in_band(buf):
        if buf.raw().nbytes >= OUT_OF_BAND_BYTES:
            bufs.append(buf)
            return False                                    # out of band: written below
        return True

    stream = pickle.dumps(obj, protocol=5, buffer_callback=keep_in_band)
    layout, end = [], 0
    for b in bufs:
        n = b.raw().nbytes
        layout.append((end, n))
        end += -(-n // _ALIGN) * _ALIGN
    if bufs:
        try:
            os.ftruncate(mfd, end)
            with mmap.mmap(mfd, end) as mm:
                for (off, n), b in zip(layout, bufs):
                    mm[off:off + n] = b.raw()
        except OSError:                                     # no room for the memory file: through the pipe
            return _dumps(obj, None)
    return pickle.dumps((tuple(layout), stream))


def _loads(payload: bytes, mfd: int | None):
    """The object :func:`_dumps` framed; its out-of-band buffers are views of the mapped ``mfd`` (no copy)."""
    layout, stream = pickle.loads(payload)
    if not layout:
        return pickle.loads(stream)
    import mmap

    end = layout[-1][0] + layout[-1][1]
    mm = mmap.mmap(mfd, end, flags=mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0))
    view = memoryview(mm)
    return pickle.loads(stream, buffers=[view[off:off + n] for off, n in layout])


def _rebuild(cls, args, attrs) -> BaseException:
    """The exception ``cls`` with ``args`` and attributes, without calling its ``__init__``."""
    e = cls.__new__(cls)
    BaseException.__init__(e, *args)
    e.__dict__.update(attrs)
    return e
