"""Execution backends and a verified incremental store for large sweeps.

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

:func:`run_chunks` drives a backend with a :class:`ResultStore`: every
finished chunk is written atomically (and fsynced) to its own JSON file and
recorded in an append-only journal, so an interrupted sweep resumes where
it stopped.  A stored chunk is used only after it is verified (content
hash, plan key, chunk key, case list); anything else is moved to
``rejected/``, reported and recomputed.  :class:`DirLock` keeps a second run
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
import datetime as _dt
import hashlib
import json
import os
import pickle
import shutil
import signal
import socket
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

from covtool.errors import CovtoolError, InputError

__all__ = ["SerialBackend", "ProcessBackend", "DaskBackend", "make_backend", "call_limited", "ResultStore",
           "StoreError", "DirLock", "OutputLockedError", "run_chunks", "WorkerError", "file_sha256"]


class WorkerError(CovtoolError, RuntimeError):
    """A chunk failed in a worker (the message names the cause)."""


class StoreError(InputError):
    """An incremental store cannot be used (e.g. another study's)."""


class OutputLockedError(InputError):
    """Another covtool run holds the directory's lock."""


def _report_stderr(message: str) -> None:
    """Default sink of store and lock notes: one line on stderr."""
    print(f"covtool: {message}", file=sys.stderr, flush=True)


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
    inter-process lock.
    """
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


# --------------------------------------------------------------------------
# directory lock
# --------------------------------------------------------------------------

#: lock file of a directory that a run writes to (OUT/ of ``covtool run``)
LOCK_NAME = ".covtool.lock"

_held_locks: dict[str, list] = {}          # resolved directory -> [fd, count, created_dir]; re-entrant per process
_held_guard = threading.Lock()


def _pid_alive(pid) -> bool:
    """Whether process ``pid`` exists on this host."""
    if not isinstance(pid, int) or isinstance(pid, bool) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:                    # exists, owned by someone else
        return True
    except OSError:
        return False
    return True


def _holder_text(holder: dict) -> str:
    pid, host = holder.get("pid", "?"), holder.get("host", "?")
    started = holder.get("started", "?")
    cmd = f", {holder['command']}" if holder.get("command") else ""
    return f"PID {pid} on host {host}, started {started}{cmd}"


class DirLock:
    """Exclusive lock on a directory for the length of one run.

    The lock file ``<directory>/.covtool.lock`` holds the owner's PID, host,
    start time and command (JSON) for the messages; the lock itself is an
    ``flock(LOCK_EX)`` on that file, which the kernel releases when the
    owner exits in any way, ``kill -9`` included.

    Deciding that a lock is stale:

    * the ``flock`` is refused: a live run holds it, the new run is refused
      (:class:`OutputLockedError`, naming the holder's PID);
    * the ``flock`` is granted but the file names a process of *this* host:
      that process is dead (or never held the lock), and the lock is taken
      over with a note;
    * the file names *another* host: a process there cannot be checked from
      here (and on file systems without shared locks the ``flock`` proves
      nothing), so the run is refused and the message says which file to
      delete once that run has ended.

    The lock is re-entrant within one process (the CLI locks ``OUT/``, the
    store of ``OUT/cases`` locks it again).

    Parameters
    ----------
    directory : path
        Created if missing (and removed on release if this lock created
        it and it is still empty).
    command : str
        What runs (for the other run's message).
    report : callable, optional
        Sink of the one-line notes (default: stderr).

    Raises
    ------
    OutputLockedError
        On :meth:`acquire`, if another run holds the lock.
    """

    def __init__(self, directory, *, command: str = "", report: Callable[[str], None] | None = None):
        self.dir = Path(directory)
        self.path = self.dir / LOCK_NAME
        self.command = command
        self.report = report or _report_stderr
        self._key = None

    def acquire(self) -> "DirLock":
        created = []                            # missing directories, deepest first, removed again if empty
        d = self.dir
        while not d.exists() and d != d.parent:
            created.append(d)
            d = d.parent
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputLockedError(str(self.dir), f"cannot create the directory ({exc.strerror})") from None
        key = str(self.dir.resolve())
        with _held_guard:
            if key in _held_locks:
                _held_locks[key][1] += 1
                self._key = key
                return self
            fd, holder = self._lock_file()
            try:
                self._check_holder(holder)
                record = {"pid": os.getpid(), "host": socket.gethostname(), "started": _now(),
                          "command": self.command}
                os.ftruncate(fd, 0)
                os.pwrite(fd, (json.dumps(record) + "\n").encode("utf-8"), 0)
                with contextlib.suppress(OSError):
                    os.fsync(fd)
            except BaseException:
                os.close(fd)
                raise
            _held_locks[key] = [fd, 1, created]
            self._key = key
        return self

    def _lock_file(self) -> tuple[int, dict]:
        """Open and flock the lock file; return its fd and the previous holder record."""
        try:
            import fcntl
        except ImportError:                    # not POSIX
            fcntl = None
        for _ in range(100):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                if fcntl is None:
                    raise OSError("no flock")
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = self._read(fd)
                os.close(fd)
                raise self._busy(holder) from None
            except OSError:                    # no flock here: the PID decides alone
                holder = self._read(fd)
                if holder.get("host") == socket.gethostname() and holder.get("pid") != os.getpid() \
                        and _pid_alive(holder.get("pid")):
                    os.close(fd)
                    raise self._busy(holder) from None
                return fd, holder
            # the previous owner unlinks the file on release: make sure we locked the file at the path
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                return fd, self._read(fd)
            os.close(fd)
        raise OutputLockedError(str(self.dir), f"cannot lock {self.path} (it keeps being replaced)")

    def _busy(self, holder: dict) -> OutputLockedError:
        return OutputLockedError(str(self.dir), f"in use by another covtool run ({_holder_text(holder)}); "
                                 "wait for it to finish or choose another --out")

    @staticmethod
    def _read(fd: int) -> dict:
        try:
            data = os.pread(fd, 65536, 0)
            rec = json.loads(data.decode("utf-8")) if data.strip() else {}
        except (OSError, ValueError):
            return {"pid": "?", "host": "?"}
        return rec if isinstance(rec, dict) else {"pid": "?", "host": "?"}

    def _check_holder(self, holder: dict) -> None:
        """The flock is ours; a record left in the file is a stale lock (or refused: another host)."""
        if not holder:
            return
        host = holder.get("host")
        if host not in (None, "?") and host != socket.gethostname():
            raise OutputLockedError(str(self.dir), f"locked by a run on another host ({_holder_text(holder)}), "
                                    "which cannot be checked from here; if that run has ended, delete "
                                    f"{self.path}")
        pid = holder.get("pid")
        why = "does not hold the lock" if _pid_alive(pid) and pid != os.getpid() else "is no longer running"
        self.report(f"{self.path}: took over a stale lock ({_holder_text(holder)}; that process {why})")

    def release(self) -> None:
        if self._key is None:
            return
        with _held_guard:
            entry = _held_locks.get(self._key)
            key, self._key = self._key, None
            if entry is None:
                return
            entry[1] -= 1
            if entry[1] > 0:
                return
            del _held_locks[key]
            with contextlib.suppress(OSError):
                self.path.unlink()              # still holding the flock: nobody can take a half-released lock
            os.close(entry[0])
            for d in entry[2]:
                with contextlib.suppress(OSError):
                    d.rmdir()                   # only if still empty (nothing was written)

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()


# --------------------------------------------------------------------------
# incremental result store
# --------------------------------------------------------------------------

#: format tag of a chunk record (records of another format are not used)
CHUNK_FORMAT = "covtool-chunk/2"


def fingerprint(obj) -> str:
    """SHA-256 of the canonical JSON form of ``obj``."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def file_sha256(path) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _record_hash(record: dict) -> str:
    """Content hash of a chunk record: SHA-256 over its canonical JSON, ``sha256`` left out.

    Floats are written with ``repr`` (shortest round-trip form), so parsing
    and re-serialising a record gives the same text and the same hash.
    """
    body = {k: v for k, v in record.items() if k != "sha256"}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=True)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _write_durable(path: Path, text: str) -> None:
    """Write ``text`` to a temporary file, fsync, rename into place."""
    from covtool.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
    _fsync_dir(path.parent)


def _parse_lines(data: bytes) -> tuple[list[dict], list[tuple[int, str]]]:
    """Journal bytes -> (records, [(line number, problem)])."""
    lines = data.split(b"\n")
    torn = bool(lines) and lines[-1] != b""
    if not torn:
        lines = lines[:-1]
    good, bad = [], []
    for n, raw in enumerate(lines, 1):
        if not raw.strip():
            continue
        try:
            rec = json.loads(raw.decode("utf-8"))
            if not isinstance(rec, dict):
                raise ValueError
        except UnicodeDecodeError:
            bad.append((n, "not UTF-8 text"))
        except (ValueError, RecursionError):
            bad.append((n, "torn (a run was killed while writing it)" if torn and n == len(lines)
                        else "not a JSON record"))
        else:
            good.append(rec)
    return good, bad


class ResultStore:
    """Finished chunks on disk, each verified before it is used.

    Layout of ``directory``::

        manifest.json       the sweep's plan: study, model and filter file hashes,
                            covtool version, chunk keys; its ``fingerprint`` is the plan key
        chunk-<key>.json    one finished chunk (atomic, fsynced): plan key, chunk key,
                            case list, result, and a SHA-256 over all of them
        journal.jsonl       append-only: "stored" (computed here), "recovered" (a verified
                            chunk file found without its line) and "rejected" events
        rejected/           chunk files (and damaged journals) that failed verification

    A chunk file is the record of truth: it appears whole or not at all.
    On every open the store

    * locks the directory's parent (:class:`DirLock`, the ``OUT/`` of
      ``covtool run``), so a second run cannot write into it;
    * removes temporary files of an interrupted write (never a
      half-written chunk);
    * ignores (and reports) journal lines that do not parse.

    :meth:`verified` then checks every chunk file against the plan: readable
    UTF-8 JSON of this format, content hash, plan key (this study), chunk
    key (the file's name) and case list.  A chunk that fails is moved to
    ``rejected/``, reported in one line and recomputed; a file that is no
    chunk of the plan is moved away too.  So every case of the plan is
    taken exactly once, from a verified chunk or a fresh computation.

    The hash detects corruption and edits by hand; it is not a signature
    (someone who recomputes it can forge a chunk).

    Parameters
    ----------
    directory : path
    manifest : dict
        Identifies the sweep (JSON-serialisable).  Its fingerprint is the
        plan key written into every chunk.  ``manifest["chunks"]``, the
        list of chunk keys, tells whether a store is complete.
    resume : bool
        Reuse the verified chunks already stored.  Without it an existing
        store is moved aside to ``<directory>.previous`` if it is complete
        (or if there is no earlier one), and that copy is removed once this
        run has stored every chunk (:meth:`finish`); an incomplete store is
        discarded when a complete earlier one exists.
    report : callable, optional
        Sink of the one-line notes (default: stderr with a ``covtool:``
        prefix).  Every note is also kept in :attr:`notes`.
    lock : bool
        Lock the parent directory (default).

    Raises
    ------
    StoreError
        With ``resume``, if the manifest is another sweep's.
    OutputLockedError
        If another run holds the lock.
    """

    def __init__(self, directory, manifest: dict, *, resume: bool = False,
                 report: Callable[[str], None] | None = None, lock: bool = True):
        self.dir = Path(directory)
        self.previous = self.dir.with_name(self.dir.name + ".previous")
        self.run_id = uuid.uuid4().hex[:12]
        self.notes: list[str] = []
        self.rejected: list[str] = []
        self._report = report or _report_stderr
        self.fingerprint = fingerprint(manifest)
        self.manifest = {"fingerprint": self.fingerprint, **manifest}
        self._lock = DirLock(self.dir.parent, command="covtool result store", report=self.note) if lock else None
        if self._lock is not None:
            self._lock.acquire()
        try:
            self._open(resume)
        except BaseException:
            self.close()
            raise

    # ---- opening -----------------------------------------------------------------
    def note(self, message: str) -> None:
        """Report one line and keep it for the provenance."""
        self.notes.append(message)
        self._report(message)

    def _open(self, resume: bool) -> None:
        mpath = self.dir / "manifest.json"
        write_manifest = True
        if resume:
            if not self.dir.is_dir():
                self.note(f"{self.dir}: no stored chunks to resume; computing every chunk")
            else:
                old, problem = self._read_manifest(mpath)
                if old is not None and old.get("fingerprint") != self.fingerprint:
                    diff = sorted(k for k in set(old) | set(self.manifest)
                                  if k != "fingerprint" and old.get(k) != self.manifest.get(k))
                    raise StoreError(str(self.dir), "was written for a different sweep (differs in: "
                                     f"{', '.join(diff) or 'fingerprint'}); run without --resume to start afresh")
                if old is not None:
                    write_manifest = False
                elif self._chunk_files():
                    self.note(f"{mpath}: {problem}; each of the {len(self._chunk_files())} stored chunks is checked "
                              "against this study's plan key instead")
        else:
            self._set_aside()
        self.dir.mkdir(parents=True, exist_ok=True)
        for tmp in self.dir.glob(".*.tmp"):            # an atomic write cut short: never a chunk
            with contextlib.suppress(OSError):
                tmp.unlink()
        if write_manifest:
            _write_durable(mpath, json.dumps(self.manifest, indent=1, sort_keys=True, default=str))
        self._check_journal()

    @staticmethod
    def _read_manifest(path: Path) -> tuple[dict | None, str]:
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            return None, "is missing"
        except OSError as exc:
            return None, f"is unreadable ({exc.strerror})"
        try:
            rec = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError):
            return None, "is not valid JSON (damaged)"
        if not isinstance(rec, dict) or not isinstance(rec.get("fingerprint"), str):
            return None, "has no plan fingerprint"
        return rec, ""

    def _chunk_files(self, directory: Path | None = None) -> list[Path]:
        return sorted((directory or self.dir).glob("chunk-*.json"))

    def _complete(self, directory: Path) -> bool:
        """Whether ``directory`` holds a file for every chunk its manifest lists."""
        man, _ = self._read_manifest(directory / "manifest.json")
        chunks = man.get("chunks") if man else None
        if not isinstance(chunks, list) or not chunks:
            return False
        return all((directory / f"chunk-{k}.json").is_file() for k in chunks)

    def _set_aside(self) -> None:
        """A fresh run: keep the last complete store until this run has stored every chunk."""
        if not self.dir.exists():
            return
        if not self._chunk_files():
            shutil.rmtree(self.dir)
            return
        if self._complete(self.dir) or not self.previous.exists():
            if self.previous.exists():
                shutil.rmtree(self.previous)
            os.replace(self.dir, self.previous)
            _fsync_dir(self.dir.parent)
            self.note(f"{self.dir}: the earlier store is moved to {self.previous} and kept until this run "
                      "has stored every chunk")
        else:
            shutil.rmtree(self.dir)
            self.note(f"{self.dir}: discarded the incomplete store of an interrupted run (continue such a run "
                      f"with --resume); {self.previous} keeps the last complete store")

    def _check_journal(self) -> None:
        """Drop journal lines that do not parse (the damaged file is kept in rejected/)."""
        p = self.dir / "journal.jsonl"
        if not p.is_file():
            return
        good, bad = _parse_lines(p.read_bytes())
        if not bad:
            return
        keep = self.dir / "rejected" / f"journal.jsonl.{self.run_id}"
        keep.parent.mkdir(exist_ok=True)
        shutil.copyfile(p, keep)
        _write_durable(p, "".join(json.dumps(r, sort_keys=True) + "\n" for r in good))
        for n, problem in bad:
            self.note(f"{p}: line {n}: {problem}; ignored (chunk files are verified on their own; "
                      f"the damaged journal is kept in {keep})")

    # ---- paths and listing ---------------------------------------------------
    def path(self, key: str) -> Path:
        return self.dir / f"chunk-{key}.json"

    def keys(self) -> set[str]:
        """Keys of the chunk files present (verified or not)."""
        return {p.name[len("chunk-"):-len(".json")] for p in self._chunk_files()}

    def load(self, key: str) -> dict:
        """The stored record of chunk ``key``, unverified.

        Keys: ``format``, ``plan``, ``key``, ``cases``, ``result``,
        ``computed``, ``sha256``.  :meth:`verified` is what a run uses.
        """
        return json.loads(self.path(key).read_text(encoding="utf-8"))

    def journal(self) -> list[dict]:
        """Journal records; lines that do not parse are skipped."""
        p = self.dir / "journal.jsonl"
        return _parse_lines(p.read_bytes())[0] if p.is_file() else []

    # ---- verification ----------------------------------------------------------
    def check(self, key: str, cases: Sequence) -> tuple[dict | None, str]:
        """Read and verify one chunk file.

        Returns
        -------
        record : dict or None
            The chunk record if every check passes.
        problem : str
            Why it is not used (``""`` if it is).
        """
        try:
            data = self.path(key).read_bytes()
        except OSError as exc:
            return None, f"unreadable ({exc.strerror})"
        if not data.strip():
            return None, "empty file"
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            return None, "not UTF-8 text (binary or corrupted)"
        try:
            rec = json.loads(text)
        except (ValueError, RecursionError):
            return None, "not valid JSON (truncated or corrupted)"
        if not isinstance(rec, dict) or rec.get("format") != CHUNK_FORMAT:
            return None, f"not a chunk record of format {CHUNK_FORMAT}"
        if rec.get("sha256") != _record_hash(rec):
            return None, "content hash mismatch (edited or corrupted)"
        if rec.get("plan") != self.fingerprint:
            return None, "written for another study (its plan key differs from this study's)"
        if rec.get("key") != key:
            return None, f"holds chunk {rec.get('key')!r}, not {key!r} (a copy of another chunk)"
        if rec.get("cases") != list(cases):
            return None, "its case list differs from the plan's for this chunk"
        if "result" not in rec:
            return None, "has no result"
        return rec, ""

    def verified(self, keys: Sequence[str], cases: Sequence[Sequence]) -> dict:
        """Results of the stored chunks that pass every check.

        Every other chunk file is moved to ``rejected/``, journaled and
        reported in one line; chunks of the plan among them are recomputed
        by :func:`run_chunks`.

        Parameters
        ----------
        keys : sequence of str
            The plan's chunk keys.
        cases : sequence of list
            Each chunk's case identifiers, as the plan lists them.

        Returns
        -------
        dict
            ``key -> result`` of the verified chunks.
        """
        plan = {k: list(c) for k, c in zip(keys, cases)}
        journaled = {r.get("sha256") for r in self.journal() if r.get("event") in ("stored", "recovered")}
        good = {}
        for key in sorted(self.keys()):
            if key in plan:
                rec, problem = self.check(key, plan[key])
            else:
                rec, problem = None, "not a chunk of this study's plan"
            if rec is None:
                self._reject(key, problem, recompute=key in plan)
                continue
            good[key] = rec["result"]
            if rec["sha256"] not in journaled:          # stored, then killed before its journal line
                self._append({"event": "recovered", "key": key, "cases": rec["cases"], "sha256": rec["sha256"],
                              "run": self.run_id, "time": _now()})
        return good

    def _reject(self, key: str, problem: str, *, recompute: bool) -> None:
        src = self.path(key)
        dst = self.dir / "rejected" / f"{src.name}.{self.run_id}"
        dst.parent.mkdir(exist_ok=True)
        os.replace(src, dst)
        self.rejected.append(key)
        self._append({"event": "rejected", "key": key, "problem": problem, "run": self.run_id, "time": _now()})
        self.note(f"{src}: {problem}; not used, moved to {dst.parent}/" + ("; recomputing it" if recompute else ""))

    # ---- writing -------------------------------------------------------------
    def _append(self, record: dict) -> None:
        line = json.dumps(record, sort_keys=True) + "\n"
        fd = os.open(self.dir / "journal.jsonl", os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line.encode("utf-8"))
            os.fsync(fd)
        finally:
            os.close(fd)

    def save(self, key: str, cases: list, result, *, seconds: float | None = None) -> None:
        """Store a finished chunk atomically, then journal it."""
        computed = {"run": self.run_id, "host": socket.gethostname(), "time": _now(), "seconds": seconds}
        rec = {"format": CHUNK_FORMAT, "plan": self.fingerprint, "key": key, "cases": list(cases), "result": result,
               "computed": computed}
        rec["sha256"] = _record_hash(rec)
        _write_durable(self.path(key), json.dumps(rec, allow_nan=True))
        self._append({"event": "stored", "key": key, "cases": list(cases), "sha256": rec["sha256"],
                      "run": self.run_id, "time": computed["time"], "seconds": seconds})

    def case_counts(self) -> dict:
        """How many times each case was stored ("stored" and "recovered" events of the journal)."""
        counts: dict = {}
        for r in self.journal():
            if r.get("event") in ("stored", "recovered"):
                for c in r.get("cases", []):
                    counts[c] = counts.get(c, 0) + 1
        return counts

    def finish(self) -> None:
        """Every chunk is stored: the earlier store set aside is no longer needed."""
        if self.previous.exists():
            shutil.rmtree(self.previous, ignore_errors=True)

    def close(self) -> None:
        """Release the directory lock."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _normalise(result):
    """The JSON round trip of ``result`` (floats keep every bit)."""
    return json.loads(json.dumps(result))


class _Timed:
    """Picklable wrapper: ``fn(item)`` and its wall time."""

    def __init__(self, fn):
        self.fn = fn

    def __call__(self, item):
        t0 = time.perf_counter()
        out = self.fn(item)
        return out, time.perf_counter() - t0


def run_chunks(fn: Callable[[Any], Any], items: Sequence, keys: Sequence[str], cases: Sequence[list], *,
               backend=None, store: ResultStore | None = None, progress: bool = False,
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
    store : ResultStore, optional
        Verified chunks already in the store are read back instead of
        computed (:meth:`ResultStore.verified`).
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
    from tqdm.auto import tqdm

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
    with tqdm(total=n_cases, initial=n_done, desc=desc, unit="case", disable=not progress, leave=False,
              smoothing=0.1) as bar:
        if todo:
            try:
                for j, (res, secs) in backend.imap_unordered(_Timed(fn), [items[i] for i in todo]):
                    i = todo[j]
                    res = _normalise(res)
                    if store is not None:
                        store.save(keys[i], list(cases[i]), res, seconds=round(secs, 3))
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
