"""A verified incremental result store for large sweeps (chunks of cases, resumable).

Every finished chunk is written atomically (and fsynced) to its own JSON
file and recorded in an append-only journal, so an interrupted sweep
resumes where it stopped (:func:`covtool.parallel.run_chunks`).  A stored
chunk is used only after it is verified (content hash, plan key, chunk key,
case list); anything else is moved to ``rejected/``, reported and
recomputed.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from pathlib import Path
import shutil
import socket
from typing import Callable, Sequence
import uuid

from covtool.errors import InputError
from covtool.io.lock import DirLock, report_stderr, utc_now

__all__ = [
    "ResultStore", "StoreError",
]


class StoreError(InputError):
    """An incremental store cannot be used (e.g. another study's)."""


# --------------------------------------------------------------------------
# incremental result store
# --------------------------------------------------------------------------

#: format tag of a chunk record (records of another format are not used)
CHUNK_FORMAT = "covtool-chunk/2"


def fingerprint(obj) -> str:
    """SHA-256 of the canonical JSON form of ``obj``."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


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
        self._report = report or report_stderr
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
                              "run": self.run_id, "time": utc_now()})
        return good

    def _reject(self, key: str, problem: str, *, recompute: bool) -> None:
        src = self.path(key)
        dst = self.dir / "rejected" / f"{src.name}.{self.run_id}"
        dst.parent.mkdir(exist_ok=True)
        os.replace(src, dst)
        self.rejected.append(key)
        self._append({"event": "rejected", "key": key, "problem": problem, "run": self.run_id, "time": utc_now()})
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

    def save(self, key: str, cases: list, result, *, seconds: float | None = None,
             result_json: str | None = None) -> None:
        """Store a finished chunk atomically, then journal it.

        ``result_json``, if given, is ``json.dumps(result)`` already made (the
        caller's JSON round trip): it is written as it is, not serialised again.
        """
        computed = {"run": self.run_id, "host": socket.gethostname(), "time": utc_now(), "seconds": seconds}
        rec = {"format": CHUNK_FORMAT, "plan": self.fingerprint, "key": key, "cases": list(cases), "result": result,
               "computed": computed}
        rec["sha256"] = _record_hash(rec)
        if result_json is None:
            text = json.dumps(rec, allow_nan=True)
        else:
            # the record without its result, then the result's own text as its last member (the same record read back)
            head = json.dumps({k: v for k, v in rec.items() if k != "result"}, allow_nan=True)
            text = f'{head[:-1]}, "result": {result_json}}}'
        _write_durable(self.path(key), text)
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
