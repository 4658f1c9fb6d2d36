"""Atomic file writing: a failed or interrupted run never destroys earlier outputs.

* :func:`atomic_path` writes a file beside its destination and renames it
  into place; :func:`staging_dir` does the same for a set of outputs.
* Temporary files and staging directories carry the writer's PID
  (``.staging-<pid>-*``, ``.<name>.<pid>-*.tmp``).  They are removed on every
  exit Python sees (exception, Ctrl-C); one left by a ``kill -9`` is removed
  by the next writer in the same directory once its PID is dead
  (:func:`remove_stale`).
* Files get the mode ``open()`` would give (``0o666`` less the umask), not
  the ``0o600`` of :func:`tempfile.mkstemp`.
* :func:`check_output_dir` checks an output directory before any
  computation.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
import time
from pathlib import Path

from covtool.errors import InputError
from covtool.io.lock import pid_alive

#: ``.staging-<pid>-<random>`` (new) or ``.staging-<random>`` (covtool <= 0.x, no PID)
_STAGING = re.compile(r"^\.staging-(?:(\d+)-)?[A-Za-z0-9_]+$")
#: ``.<name>.<pid>-<random>.tmp`` (:func:`atomic_path`) or ``.probe-<pid>-<random>`` (:func:`check_output_dir`)
_TMP = re.compile(r"^(?:\..+\.(\d+)-[A-Za-z0-9_]+\.tmp|\.probe-(\d+)-[A-Za-z0-9_]+)$")
#: a staging directory without a PID (older covtool) is stale after this long [s]
_PIDLESS_STALE_AFTER = 3600.0
#: a temporary file of a dead PID is removed once it is this old [s]
_TMP_GRACE = 60.0


def current_umask() -> int:
    """The process umask, read without changing it where possible."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def remove_stale(directory: str | os.PathLike) -> list[Path]:
    """Remove staging directories and temporary files of dead writers.

    Parameters
    ----------
    directory : path-like
        A directory covtool writes into.

    Returns
    -------
    list of Path
        What was removed.  Entries of a live PID are left alone; a
        temporary file of a dead PID is removed once it is a minute old, a
        staging directory without a PID (older covtool) once it is an hour
        old.
    """
    directory = Path(directory)
    removed = []
    try:
        entries = list(directory.iterdir())
    except OSError:
        return removed
    now = time.time()
    for p in entries:
        m = _STAGING.match(p.name)
        if m and p.is_dir() and not p.is_symlink():
            if m.group(1) is not None:
                stale = not pid_alive(int(m.group(1)))
            else:
                try:
                    stale = now - p.stat().st_mtime > _PIDLESS_STALE_AFTER
                except OSError:
                    stale = False
            if stale:
                shutil.rmtree(p, ignore_errors=True)
                removed.append(p)
            continue
        m = _TMP.match(p.name)
        if m and p.is_file() and not pid_alive(int(m.group(1) or m.group(2))):
            with contextlib.suppress(OSError):
                # a minute's grace: the PID may belong to a writer on another host of a shared disk
                if now - p.stat().st_mtime > _TMP_GRACE:
                    p.unlink()
                    removed.append(p)
    return removed


def _chmod_default(path: Path) -> None:
    os.chmod(path, 0o666 & ~current_umask())


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path next to ``path``; move it into place on success.

    The temporary file lives in the same directory so that the final
    :func:`os.replace` is atomic on POSIX.  On any exception the temporary
    file is removed and ``path`` is left as it was.  The file gets the
    umask's mode, as ``open()`` would give it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale(path.parent)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}-", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        if tmp.exists():
            _chmod_default(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_text(path, text: str) -> None:
    """Write text atomically (UTF-8, the umask's mode)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


@contextlib.contextmanager
def staging_dir(out_dir: str | os.PathLike):
    """Yield a staging directory; on success move every file into ``out_dir``.

    Before anything moves, every destination is checked (a directory in the
    way of a file is refused), so either all outputs are replaced or none
    is.  Files are moved one by one with :func:`os.replace`, so each output
    is either the old complete file or the new complete file.  On failure
    (any exception, Ctrl-C included) the staging directory is deleted and
    ``out_dir`` is untouched; a staging directory left by a killed process
    is removed by the next call (:func:`remove_stale`).

    Raises
    ------
    InputError
        A destination is a directory.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    remove_stale(out_dir)
    stage = Path(tempfile.mkdtemp(prefix=f".staging-{os.getpid()}-", dir=out_dir))
    try:
        yield stage
        moves = [(src, out_dir / src.relative_to(stage)) for src in sorted(stage.rglob("*")) if src.is_file()]
        for _, dst in moves:
            if dst.is_dir() and not dst.is_symlink():
                raise InputError(str(dst), "is a directory; covtool needs to write a file there "
                                 "(move it away; no output was changed)")
        for src, dst in moves:
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dst)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _package_dirs() -> list[tuple[Path, str]]:
    """Directories no output may go into: the package and the model library."""
    dirs = [(Path(__file__).resolve().parents[1], "the covtool package")]
    with contextlib.suppress(Exception):
        from covtool.io.library import default_model_dir

        dirs.append((Path(default_model_dir()).resolve(), "the model library"))
    return dirs


def check_output_dir(out: str | os.PathLike, where: str = "--out") -> Path:
    """Check that ``out`` can hold a study's outputs; change nothing.

    Run before any computation, so that a run never computes for minutes and
    then fails to write.  Stale staging directories of dead runs in ``out``
    are removed.

    Parameters
    ----------
    out : path-like
        The output directory (existing or to be created).
    where : str
        The option or field that named it, for the message.

    Returns
    -------
    Path
        ``out``.

    Raises
    ------
    InputError
        ``out`` is an existing file, lies under a file, cannot be created,
        is not writable, or lies inside the covtool package or its model
        library.
    """
    out = Path(out)
    label = f"{where} {str(out)!r}" if where else repr(str(out))
    try:
        resolved = out.resolve()
    except (OSError, RuntimeError) as exc:
        raise InputError(label, f"cannot be resolved: {exc}") from None
    for d, what in _package_dirs():
        if resolved == d or d in resolved.parents:
            raise InputError(label, f"is inside {what} ({d}); choose an output directory outside it")
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise InputError(label, "is an existing file, not a directory; choose a directory")
        _probe_write(out, label)
        remove_stale(out)
        return out
    # the nearest existing ancestor must be a directory that lets us create ``out``
    created = []
    parent = out
    while not parent.exists() and parent != parent.parent:
        created.append(parent)
        parent = parent.parent
    if parent.exists() and not parent.is_dir():
        raise InputError(label, f"cannot be created: {str(parent)!r} is a file, not a directory")
    try:
        for d in reversed(created):
            d.mkdir()
    except OSError as exc:
        _remove_created(created)
        raise InputError(label, f"cannot be created: {exc.strerror or exc}") from None
    try:
        _probe_write(out, label)
    finally:
        _remove_created(created)
    return out


def _remove_created(created: list[Path]) -> None:
    for d in created:                       # deepest first
        with contextlib.suppress(OSError):
            d.rmdir()


def _probe_write(directory: Path, label: str) -> None:
    """Create and remove a file in ``directory`` (root ignores permission bits)."""
    try:
        fd, name = tempfile.mkstemp(prefix=f".probe-{os.getpid()}-", dir=directory)
        os.close(fd)
        os.unlink(name)
    except OSError as exc:
        raise InputError(label, f"is not writable: {exc.strerror or exc}") from None


__all__ = ["atomic_path", "write_text", "staging_dir", "check_output_dir", "remove_stale", "current_umask"]
