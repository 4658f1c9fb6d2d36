"""Execution backends for large sweeps: chunks of cases in-process, in local processes or on Dask.

A sweep is a list of *chunks*: independent tasks, each a pure function of
its (picklable) input that returns JSON-serialisable results.  A backend
maps the function over the chunks and yields each result as it finishes:

* :class:`SerialBackend`: in-process, one chunk after the other (default);
* :class:`ProcessBackend`: local worker processes
  (:class:`concurrent.futures.ProcessPoolExecutor`, ``spawn`` start method);
* :class:`DaskBackend`: a Dask cluster, either an existing scheduler
  (``tcp://host:8786``) or a :class:`dask.distributed.LocalCluster`.  Dask is
  imported only when this backend is made.

Every backend runs a chunk with the BLAS pool limited to one thread
(:func:`call_limited`): the engine's matrices are medium-sized and scale
across processes, not BLAS threads (see :func:`covtool.lincov.batch.run_batch`).
The same limit everywhere also makes results bitwise identical across
backends.

:func:`run_chunks` drives a backend with a result store
(:class:`covtool.io.store.ResultStore`, passed in by the study): every
finished chunk is written atomically (and fsynced) to its own JSON file and
recorded in an append-only journal, so an interrupted sweep resumes where
it stopped.  A stored chunk is used only after it is verified (content
hash, plan key, chunk key, case list); anything else is moved to
``rejected/``, reported and recomputed.  :class:`covtool.io.lock.DirLock` keeps a second run
out of the same directory.

Interrupts: when the consumer of a backend stops with an exception
(``KeyboardInterrupt``, the CLI's SIGTERM), :func:`run_chunks` calls the
backend's ``abort``: pending chunks are cancelled and worker processes
terminated and joined with a timeout.  Worker processes also die with their
parent when it is killed outright (``kill -9``); see :class:`ProcessBackend`.

This module never imports a study; studies import it.
"""

from __future__ import annotations

import contextlib
import json
import os
import pickle
import signal
import sys
import threading
import time
from typing import Any, Callable, Iterator, Sequence
import uuid

from covtool.errors import CovtoolError, InputError

__all__ = [
    "SerialBackend", "ProcessBackend", "DaskBackend", "make_backend", "call_limited", "run_chunks",
    "WorkerError",
]


class WorkerError(CovtoolError, RuntimeError):
    """A chunk failed in a worker (the message names the cause)."""


# --------------------------------------------------------------------------
# chunk execution (runs in the worker)
# --------------------------------------------------------------------------

def call_limited(fn: Callable[[Any], Any], item: Any) -> Any:
    """Run ``fn(item)`` with the BLAS pool limited to one thread.

    Errors that would not survive pickling back to the parent (covtool's
    input errors take two constructor arguments) are re-raised as a
    :class:`WorkerError` with the same message.
    """
    from threadpoolctl import threadpool_limits

    _thread_tqdm_lock()
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(item)
    except Exception as exc:
        try:
            pickle.loads(pickle.dumps(exc))
        except Exception:
            raise WorkerError(f"{type(exc).__name__}: {exc}") from None
        raise


def _thread_tqdm_lock() -> None:
    """Give tqdm a thread lock unless it already has a lock.

    tqdm's default lock is a multiprocessing RLock, a named semaphore that a
    terminated worker never unregisters (the resource tracker then warns of
    a leak at exit); bars in a chunk are off, and one process needs no
    inter-process lock.  Nothing to do while tqdm is not imported: no bar
    has been drawn (:class:`covtool.progress.NoBar` draws none without it),
    and importing it here would cost what NoBar saves (60-90 ms).
    """
    if "tqdm" not in sys.modules:
        return
    from tqdm import tqdm

    if "_lock" not in vars(tqdm):
        tqdm.set_lock(threading.RLock())


#: exit status of a worker whose parent died (seen only by a debugger: nobody waits for it)
ORPHAN_EXIT = 75


def _watch_parent(lifeline) -> None:
    """Worker thread: exit the process when the parent's end of ``lifeline`` closes.

    The parent never writes; ``recv_bytes`` returns only with EOF (or an
    error), which the kernel delivers when the last write end is closed,
    that is when the parent exits or is killed (even by SIGKILL).
    """
    try:
        lifeline.recv_bytes()
    except (EOFError, OSError):
        pass
    os._exit(ORPHAN_EXIT)


def _init_worker(lifeline=None) -> None:
    """Initialise a :class:`ProcessBackend` worker.

    SIGINT is ignored: a terminal's Ctrl-C reaches the whole process group,
    and only the parent decides what to stop (it terminates the workers).
    The parent spawns workers with SIGINT ignored already
    (:func:`_children_ignore_sigint`); this covers other start methods.
    """
    from threadpoolctl import threadpool_limits

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _thread_tqdm_lock()
    if lifeline is not None:
        threading.Thread(target=_watch_parent, args=(lifeline,), name="covtool-parent-watchdog",
                         daemon=True).start()
    threadpool_limits(limits=1, user_api="blas")


@contextlib.contextmanager
def _children_ignore_sigint():
    """Spawn child processes that ignore SIGINT from their first instruction.

    A terminal's Ctrl-C goes to the whole foreground process group; only
    this process should act on it (it stops the workers).  A SIG_IGN
    disposition survives ``fork`` and ``exec`` and Python keeps it at
    start-up (a blocked signal mask does not survive a spawn), so SIGINT is
    ignored here while children are spawned.  It is also blocked meanwhile:
    Linux never discards a blocked signal, so a Ctrl-C in this window stays
    pending and is raised once the handler is back.
    """
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        if old is not None:
            signal.signal(signal.SIGINT, old)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


# --------------------------------------------------------------------------
# backends
# --------------------------------------------------------------------------

class SerialBackend:
    """Run chunks in this process, in order."""

    name = "serial"
    workers = 1

    def imap_unordered(self, fn, items: Sequence) -> Iterator[tuple[int, Any]]:
        """Yield ``(index, fn(items[index]))`` as each chunk finishes."""
        for i, item in enumerate(items):
            yield i, call_limited(fn, item)

    def close(self) -> None:
        """Release the backend's resources after a finished run."""

    def abort(self) -> None:
        """Stop at once: cancel pending chunks, stop the workers."""
        self.close()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def describe(self) -> str:
        return "in-process"


class ProcessBackend(SerialBackend):
    """Run chunks in local processes (one BLAS thread each).

    Parameters
    ----------
    workers : int
        Number of worker processes (default: the number of CPUs).
    start_method : str
        ``multiprocessing`` start method; ``spawn`` (default) gives every
        worker a fresh interpreter, safe with threaded BLAS in the parent.
    abort_timeout : float
        Seconds :meth:`abort` waits for terminated workers before it kills
        them. [s]

    Notes
    -----
    Workers die with their parent.  Each worker runs a watchdog thread that
    blocks on the read end of a pipe whose only write end the parent holds
    (the *lifeline*); when the parent exits for any reason, SIGKILL
    included, the kernel closes that end, the read returns EOF and the
    worker calls ``os._exit``.  This was chosen over Linux's
    ``prctl(PR_SET_PDEATHSIG)``: the death signal is tied to the *thread*
    that spawned the worker (a worker spawned from a short-lived thread
    would be killed when that thread ends), it is Linux-only, and it needs
    a check for a parent that died before the ``prctl`` call; the pipe has
    none of these problems.  Once the workers are gone, the
    ``multiprocessing`` resource tracker sees EOF on its own pipe (held by
    the parent and the workers) and exits as well.  The watchdog needs the
    ``spawn`` start method: a forked worker would inherit the write end.
    """

    name = "processes"

    def __init__(self, workers: int | None = None, *, start_method: str = "spawn", abort_timeout: float = 5.0):
        if workers is not None and (isinstance(workers, bool) or int(workers) != workers or workers < 1):
            raise InputError("workers", f"{workers!r} is not a positive integer")
        self.workers = int(workers or os.cpu_count() or 1)
        self.start_method = start_method
        self.abort_timeout = float(abort_timeout)
        self._pool = None
        self._lifeline = None

    def _executor(self):
        if self._pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            ctx = multiprocessing.get_context(self.start_method)
            args = ()
            if self.start_method == "spawn":             # a forked worker would inherit the write end too
                self._lifeline = ctx.Pipe(duplex=False)  # (read end for the workers, write end kept here)
                args = (self._lifeline[0],)
            self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx, initializer=_init_worker,
                                             initargs=args)
        return self._pool

    def imap_unordered(self, fn, items):
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        pool = self._executor()
        with _children_ignore_sigint():                      # workers are spawned by submit
            pending = {pool.submit(call_limited, fn, item): i for i, item in enumerate(items)}
        try:
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    i = pending.pop(fut)
                    try:
                        res = fut.result()
                    except BrokenProcessPool:
                        raise WorkerError("a worker process died while running a chunk (killed, or out of "
                                          "memory?); the chunks stored so far are kept: use --resume") from None
                    yield i, res
        finally:
            for fut in pending:
                fut.cancel()

    def _close_lifeline(self) -> None:
        if self._lifeline is not None:
            for conn in self._lifeline:
                conn.close()
            self._lifeline = None

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._close_lifeline()

    def abort(self) -> None:
        """Cancel pending chunks, terminate the workers and join them.

        Running chunks are not waited for: SIGTERM, then SIGKILL for a
        worker still alive after ``abort_timeout`` seconds.  Their results
        are lost (an unfinished chunk is never stored) and recomputed on
        resume.
        """
        pool, self._pool = self._pool, None
        if pool is None:
            self._close_lifeline()
            return
        # ProcessPoolExecutor has no public terminate; _processes (pid -> Process) exists since 3.2
        procs = list((getattr(pool, "_processes", None) or {}).values())
        for p in procs:
            with contextlib.suppress(Exception):
                p.terminate()
        # the manager thread sees the dead workers, fails the pending futures and closes its queues
        pool.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + self.abort_timeout
        for p in procs:
            with contextlib.suppress(Exception):
                p.join(max(0.0, deadline - time.monotonic()))
        for p in procs:
            with contextlib.suppress(Exception):
                if p.is_alive():
                    p.kill()
                    p.join(1.0)
        thread = getattr(pool, "_executor_manager_thread", None)
        if thread is not None:
            thread.join(max(0.5, deadline - time.monotonic()))
        self._close_lifeline()

    def describe(self) -> str:
        return f"{self.workers} local processes"


class DaskBackend(SerialBackend):
    """Run chunks on a Dask cluster.

    Parameters
    ----------
    address : str, optional
        Scheduler address (``tcp://host:8786``).  ``None`` or ``"local"``
        starts a :class:`dask.distributed.LocalCluster` of ``workers``
        single-threaded processes on this machine.
    client : dask.distributed.Client, optional
        An existing client (its cluster is not closed by :meth:`close`).
    workers : int, optional
        Workers of the local cluster (default: the number of CPUs).
    timeout : str
        How long to try to reach the scheduler.
    **cluster_kwargs
        Passed to :class:`~dask.distributed.LocalCluster`.

    Notes
    -----
    Workers must be able to import covtool and read the model and study
    files the chunks name (the same paths as on the client).
    """

    name = "dask"

    def __init__(self, address: str | None = None, *, client=None, workers: int | None = None,
                 timeout: str = "20s", **cluster_kwargs):
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError:  # pragma: no cover - exercised only without the extra
            raise InputError("scheduler", "Dask is not installed; install covtool[dask]") from None
        self._own = client is None
        self._cluster = None
        if client is not None:
            self.client = client
        elif address in (None, "local"):
            kw = {"n_workers": workers or os.cpu_count() or 1, "threads_per_worker": 1, "processes": True,
                  "dashboard_address": None}
            kw.update(cluster_kwargs)
            with _children_ignore_sigint():                  # the cluster starts its worker processes here
                self._cluster = LocalCluster(**kw)
                try:
                    self.client = Client(self._cluster)
                except BaseException:
                    self._cluster.close()
                    raise
        else:
            try:
                self.client = Client(address, timeout=timeout)
            except (OSError, TimeoutError) as exc:
                raise InputError("scheduler", f"cannot connect to Dask scheduler {address!r}: {exc}") from None
        self.address = self.client.scheduler.address
        self.workers = len(self.client.scheduler_info().get("workers", {})) or (workers or 1)

    def imap_unordered(self, fn, items):
        from dask.distributed import as_completed

        token = uuid.uuid4().hex[:8]
        futures = {}
        for i, item in enumerate(items):
            fut = self.client.submit(call_limited, fn, item, pure=False, key=f"covtool-chunk-{token}-{i}")
            futures[fut] = i
        try:
            for fut in as_completed(list(futures)):
                i = futures[fut]
                res = fut.result()
                fut.release()
                yield i, res
        finally:
            for fut in futures:
                if not fut.done():
                    fut.cancel()

    def close(self) -> None:
        if self._own and self.client is not None:
            self.client.close()
            if self._cluster is not None:
                self._cluster.close()
            self.client = self._cluster = None

    def describe(self) -> str:
        return f"dask at {self.address} ({self.workers} workers)"


def make_backend(backend=None, *, workers: int | None = None, scheduler: str | None = None):
    """A backend from command-line style options.

    Parameters
    ----------
    backend : backend object or {"serial", "processes", "dask"}, optional
        Returned as is if it is already a backend.
    workers : int, optional
        Local worker processes (``ProcessBackend``), or workers of a local
        Dask cluster when ``scheduler == "local"``.
    scheduler : str, optional
        Dask scheduler address, or ``"local"`` for a LocalCluster.

    Returns
    -------
    SerialBackend, ProcessBackend or DaskBackend
    """
    if backend is not None and not isinstance(backend, str):
        return backend
    if scheduler is not None or backend == "dask":
        return DaskBackend(scheduler, workers=workers)
    if backend == "processes" or (backend is None and workers is not None and workers != 1):
        return ProcessBackend(workers)
    if backend in (None, "serial"):
        return SerialBackend()
    raise InputError("backend", f"unknown backend {backend!r} (one of: serial, processes, dask)")


class _Timed:
    """Picklable wrapper: ``fn(item)`` and its wall time."""

    def __init__(self, fn):
        self.fn = fn

    def __call__(self, item):
        t0 = time.perf_counter()
        out = self.fn(item)
        return out, time.perf_counter() - t0


def run_chunks(fn: Callable[[Any], Any], items: Sequence, keys: Sequence[str], cases: Sequence[list], *,
               backend=None, store=None, progress: bool = False,
               desc: str = "cases") -> tuple[list, dict]:
    """Map ``fn`` over chunks, storing each result as it finishes.

    Parameters
    ----------
    fn : callable
        A pure, module-level (picklable) function of one chunk's input
        returning JSON-serialisable data.
    items : sequence
        Chunk inputs (picklable).
    keys : sequence of str
        A unique file-name-safe key per chunk.
    cases : sequence of list
        Case identifiers of each chunk, each case in one chunk only (the
        progress bar counts cases; the store checks them).
    backend : backend, optional
        Default :class:`SerialBackend`.
    store : covtool.io.store.ResultStore, optional
        Verified chunks already in the store are read back instead of
        computed (:meth:`covtool.io.store.ResultStore.verified`).
    progress : bool
        Show a tqdm bar of cases done and the time left.

    Returns
    -------
    results : list
        The chunk results in the order of ``items`` (JSON round-tripped, so
        stored and freshly computed results are identical).
    stats : dict
        ``chunks``, ``computed``, ``reused``, ``rejected``, ``cases``,
        ``backend``, ``seconds``.

    Raises
    ------
    ValueError
        If two chunks share a key or a case.

    Notes
    -----
    If the loop stops with any exception (an interrupt included), the
    backend's ``abort`` cancels the pending chunks and stops the workers
    before the exception propagates; the chunks stored so far stay.
    """
    from covtool.progress import progress_bar

    if len(set(keys)) != len(keys):
        raise ValueError("chunk keys are not unique")
    owner: dict = {}
    for k, cs in zip(keys, cases):
        for c in cs:
            if c in owner:
                raise ValueError(f"case {c!r} is in chunks {owner[c]!r} and {k!r}")
            owner[c] = k
    backend = backend or SerialBackend()
    missing = object()
    results: list = [missing] * len(items)
    stored = store.verified(keys, cases) if store is not None else {}
    for i, k in enumerate(keys):
        if k in stored:
            results[i] = stored[k]
    todo = [i for i in range(len(items)) if results[i] is missing]
    n_cases = sum(len(c) for c in cases)
    n_done = n_cases - sum(len(cases[i]) for i in todo)
    t0 = time.perf_counter()
    with progress_bar(n_cases, desc, progress, unit="case", initial=n_done) as bar:
        if todo:
            try:
                for j, (res, secs) in backend.imap_unordered(_Timed(fn), [items[i] for i in todo]):
                    i = todo[j]
                    text = json.dumps(res)                   # the JSON round trip (floats keep every bit)
                    res = json.loads(text)
                    if store is not None:
                        store.save(keys[i], list(cases[i]), res, seconds=round(secs, 3), result_json=text)
                    results[i] = res
                    bar.update(len(cases[i]))
            except BaseException:
                abort = getattr(backend, "abort", None)
                if abort is not None:
                    abort()
                raise
    lost = [keys[i] for i in range(len(items)) if results[i] is missing]
    if lost:                                   # a backend that yields fewer results than chunks
        raise WorkerError(f"no result for chunks {', '.join(lost)}")
    if store is not None:
        store.finish()
    stats = {"chunks": len(items), "computed": len(todo), "reused": len(items) - len(todo),
             "rejected": len(store.rejected) if store is not None else 0, "cases": n_cases,
             "backend": backend.describe(), "seconds": time.perf_counter() - t0}
    return results, stats
