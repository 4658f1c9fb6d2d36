"""Execution backends and an incremental store for large sweeps.

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
across processes, not BLAS threads (see :func:`covtool.engine.run_batch`).
The same limit everywhere also makes results bitwise identical across
backends.

:func:`run_chunks` drives a backend with a :class:`ResultStore`: every
finished chunk is written atomically (and fsynced) to its own JSON file and
recorded in an append-only journal, so an interrupted sweep resumes where
it stopped: stored chunks are read back, never recomputed.

This module never imports a study; studies import it.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import pickle
import socket
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

from .errors import CovtoolError, InputError

__all__ = ["SerialBackend", "ProcessBackend", "DaskBackend", "make_backend", "call_limited", "ResultStore",
           "StoreError", "run_chunks", "WorkerError"]


class WorkerError(CovtoolError, RuntimeError):
    """A chunk failed in a worker (the message names the cause)."""


class StoreError(InputError):
    """An incremental store cannot be used (e.g. another study's)."""


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

    try:
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(item)
    except Exception as exc:
        try:
            pickle.loads(pickle.dumps(exc))
        except Exception:
            raise WorkerError(f"{type(exc).__name__}: {exc}") from None
        raise


def _init_worker() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")


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
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

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
    """

    name = "processes"

    def __init__(self, workers: int | None = None, *, start_method: str = "spawn"):
        if workers is not None and (isinstance(workers, bool) or int(workers) != workers or workers < 1):
            raise InputError("workers", f"{workers!r} is not a positive integer")
        self.workers = int(workers or os.cpu_count() or 1)
        self.start_method = start_method
        self._pool = None

    def _executor(self):
        if self._pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            self._pool = ProcessPoolExecutor(max_workers=self.workers,
                                             mp_context=multiprocessing.get_context(self.start_method),
                                             initializer=_init_worker)
        return self._pool

    def imap_unordered(self, fn, items):
        from concurrent.futures import FIRST_COMPLETED, wait

        pool = self._executor()
        pending = {pool.submit(call_limited, fn, item): i for i, item in enumerate(items)}
        try:
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    i = pending.pop(fut)
                    yield i, fut.result()
        finally:
            for fut in pending:
                fut.cancel()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

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
            self._cluster = LocalCluster(**kw)
            self.client = Client(self._cluster)
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
        if self._own:
            self.client.close()
            if self._cluster is not None:
                self._cluster.close()

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
# incremental result store
# --------------------------------------------------------------------------

def fingerprint(obj) -> str:
    """SHA-256 of the canonical JSON form of ``obj``."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _write_durable(path: Path, text: str) -> None:
    """Write ``text`` to a temporary file, fsync, rename into place."""
    from .io.atomic import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
    _fsync_dir(path.parent)


class ResultStore:
    """Finished chunks on disk: one JSON file each, plus a journal.

    Layout of ``directory``::

        manifest.json       fingerprint of the sweep (study, tool version, chunk plan)
        chunk-<key>.json    one finished chunk: its cases and results (atomic, fsynced)
        journal.jsonl       append-only: one "stored" line per chunk computed and stored,
                            "recovered" for a chunk file found without its line

    A chunk file is the record of truth: it appears whole or not at all.
    Every case therefore is stored exactly once; work in flight when a run
    is killed is lost and redone on resume.

    Parameters
    ----------
    directory : path
    manifest : dict
        Identifies the sweep; a store written for another manifest is not
        resumed (:class:`StoreError`).
    resume : bool
        Keep and reuse the chunks already stored.  Without it an existing
        store is cleared first.
    """

    def __init__(self, directory, manifest: dict, *, resume: bool = False):
        self.dir = Path(directory)
        self.run_id = uuid.uuid4().hex[:12]
        self.manifest = {"fingerprint": fingerprint(manifest), **manifest}
        mpath = self.dir / "manifest.json"
        if resume and mpath.is_file():
            try:
                old = json.loads(mpath.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                raise StoreError(str(mpath), f"unreadable manifest ({exc}); run without --resume") from None
            if old.get("fingerprint") != self.manifest["fingerprint"]:
                diff = sorted(k for k in set(old) | set(self.manifest)
                              if k != "fingerprint" and old.get(k) != self.manifest.get(k))
                raise StoreError(str(self.dir), "was written for a different sweep (differs in: "
                                 f"{', '.join(diff) or 'fingerprint'}); run without --resume to start afresh")
        elif self.dir.exists():
            self.clear()
        self.dir.mkdir(parents=True, exist_ok=True)
        if not mpath.is_file():
            _write_durable(mpath, json.dumps(self.manifest, indent=1, sort_keys=True, default=str))
        self._reconcile()

    # ---- paths and listing ---------------------------------------------------
    def path(self, key: str) -> Path:
        return self.dir / f"chunk-{key}.json"

    def keys(self) -> set[str]:
        """Keys of the chunks stored."""
        return {p.name[len("chunk-"):-len(".json")] for p in self.dir.glob("chunk-*.json")}

    def load(self, key: str) -> dict:
        """The stored record of chunk ``key``.

        Keys: ``cases``, ``result``, ``computed``.
        """
        return json.loads(self.path(key).read_text(encoding="utf-8"))

    def journal(self) -> list[dict]:
        """Journal records; a torn last line (killed mid-write) is skipped."""
        p = self.dir / "journal.jsonl"
        if not p.is_file():
            return []
        out = []
        for line in p.read_text(encoding="utf-8").splitlines():
            with contextlib.suppress(ValueError):
                out.append(json.loads(line))
        return out

    def clear(self) -> None:
        """Remove the stored chunks, journal and manifest."""
        for p in list(self.dir.glob("chunk-*.json")) + [self.dir / "journal.jsonl", self.dir / "manifest.json"]:
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
        for p in self.dir.glob(".chunk-*.tmp"):
            with contextlib.suppress(FileNotFoundError):
                p.unlink()

    # ---- writing -------------------------------------------------------------
    def _append(self, record: dict) -> None:
        line = json.dumps(record, sort_keys=True) + "\n"
        fd = os.open(self.dir / "journal.jsonl", os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line.encode("utf-8"))
            os.fsync(fd)
        finally:
            os.close(fd)

    def _reconcile(self) -> None:
        p = self.dir / "journal.jsonl"
        if p.is_file() and p.stat().st_size:
            with open(p, "rb") as fh:
                fh.seek(-1, os.SEEK_END)
                torn = fh.read(1) != b"\n"
            if torn:                          # a kill in mid-line: end it, so the next record parses
                fd = os.open(p, os.O_WRONLY | os.O_APPEND)
                try:
                    os.write(fd, b"\n")
                    os.fsync(fd)
                finally:
                    os.close(fd)
        journaled = {r["key"] for r in self.journal() if r.get("event") in ("stored", "recovered")}
        for key in sorted(self.keys() - journaled):
            rec = self.load(key)
            self._append({"event": "recovered", "key": key, "cases": rec["cases"], "run": self.run_id,
                          "time": _now()})

    def save(self, key: str, cases: list, result, *, seconds: float | None = None) -> None:
        """Store a finished chunk atomically, then journal it."""
        computed = {"run": self.run_id, "host": socket.gethostname(), "time": _now(), "seconds": seconds}
        _write_durable(self.path(key), json.dumps({"key": key, "cases": cases, "result": result,
                                                   "computed": computed}))
        self._append({"event": "stored", "key": key, "cases": cases, "run": self.run_id, "time": computed["time"],
                      "seconds": seconds})

    def case_counts(self) -> dict:
        """How many times each case was stored, over the whole journal."""
        counts: dict = {}
        for r in self.journal():
            if r.get("event") in ("stored", "recovered"):
                for c in r["cases"]:
                    counts[c] = counts.get(c, 0) + 1
        return counts


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
        Case identifiers of each chunk (the progress bar counts cases).
    backend : backend, optional
        Default :class:`SerialBackend`.
    store : ResultStore, optional
        Chunks already in the store are read back instead of computed.
    progress : bool
        Show a tqdm bar of cases done and the time left.

    Returns
    -------
    results : list
        The chunk results in the order of ``items`` (JSON round-tripped, so
        stored and freshly computed results are identical).
    stats : dict
        ``chunks``, ``computed``, ``reused``, ``cases``, ``backend``, ``seconds``.
    """
    from tqdm.auto import tqdm

    if len(set(keys)) != len(keys):
        raise ValueError("chunk keys are not unique")
    backend = backend or SerialBackend()
    results: list = [None] * len(items)
    done = store.keys() if store is not None else set()
    todo = [i for i, k in enumerate(keys) if k not in done]
    for i, k in enumerate(keys):
        if k in done:
            results[i] = store.load(k)["result"]
    n_cases = sum(len(c) for c in cases)
    n_done = sum(len(cases[i]) for i in range(len(items)) if i not in set(todo))
    t0 = time.perf_counter()
    with tqdm(total=n_cases, initial=n_done, desc=desc, unit="case", disable=not progress, leave=False,
              smoothing=0.1) as bar:
        if todo:
            for j, (res, secs) in backend.imap_unordered(_Timed(fn), [items[i] for i in todo]):
                i = todo[j]
                res = _normalise(res)
                if store is not None:
                    store.save(keys[i], list(cases[i]), res, seconds=round(secs, 3))
                results[i] = res
                bar.update(len(cases[i]))
    stats = {"chunks": len(items), "computed": len(todo), "reused": len(items) - len(todo), "cases": n_cases,
             "backend": backend.describe(), "seconds": time.perf_counter() - t0}
    return results, stats
