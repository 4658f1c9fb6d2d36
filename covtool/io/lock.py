"""One run per output directory: a lock file with ``flock`` and its holder's PID, host and command.

:class:`DirLock` keeps a second covtool run out of an output directory
(outputs and the result store are written by one process); a lock left by
a dead process on this host is taken over with a note.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
from pathlib import Path
import socket
import sys
import threading
from typing import Callable

from covtool.errors import InputError

__all__ = [
    "DirLock", "OutputLockedError",
]


class OutputLockedError(InputError):
    """Another covtool run holds the directory's lock."""


def report_stderr(message: str) -> None:
    """Default sink of store and lock notes: one line on stderr."""
    print(f"covtool: {message}", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------
# directory lock
# --------------------------------------------------------------------------

#: lock file of a directory that a run writes to (OUT/ of ``covtool run``)
LOCK_NAME = ".covtool.lock"

_held_locks: dict[str, list] = {}          # resolved directory -> [fd, count, created_dir]; re-entrant per process
_held_guard = threading.Lock()


def pid_alive(pid) -> bool:
    """Whether process ``pid`` may exist on this host.

    False for a PID that is not a positive integer or names no process;
    True for one that exists (even owned by someone else) and, to be safe,
    when the system cannot tell: a lock or a staging directory is taken
    over only when its owner is known to be gone.
    """
    if not isinstance(pid, int) or isinstance(pid, bool) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:                    # exists, owned by someone else
        return True
    except OSError:
        return True
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
        self.report = report or report_stderr
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
                record = {"pid": os.getpid(), "host": socket.gethostname(), "started": utc_now(),
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
                        and pid_alive(holder.get("pid")):
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
        why = "does not hold the lock" if pid_alive(pid) and pid != os.getpid() else "is no longer running"
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


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")
