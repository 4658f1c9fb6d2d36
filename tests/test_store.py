"""The result store verifies before it trusts; the directory lock keeps one run per OUT.

Unit level: a store of a toy sweep (``_square`` over a few chunks), each
file damaged the way a user or a crash would damage it.  The CLI-level
counterparts (a real trade grid, a second run while one is running, a
killed run's stale lock) are in test_parallel.py.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import pytest

from covtool.io.lock import LOCK_NAME, DirLock, OutputLockedError
from covtool.io.store import ResultStore, StoreError
from covtool.parallel import SerialBackend, WorkerError, run_chunks

PLAN = {"kind": "toy", "chunks": ["k0", "k1", "k2"]}
OTHER = {"kind": "toy", "chunks": ["k0", "k1", "k2"], "q": 3.0}
ITEMS, KEYS, CASES = [1.0, 2.0, 3.0], ["k0", "k1", "k2"], [[0, 1], [2], [3, 4]]
EXPECTED = [{"y": 1.0}, {"y": 4.0}, {"y": 9.0}]


def _square(x):
    return {"y": x * x}


def _half(x):
    """A run killed after its first chunk."""
    if x > 1.0:
        raise KeyboardInterrupt
    return {"y": x * x}


def _complete_store(path, manifest=PLAN):
    with ResultStore(path, manifest, report=lambda m: None) as st:
        res, stats = run_chunks(_square, ITEMS, KEYS, CASES, store=st)
    assert res == EXPECTED and stats["computed"] == 3
    return path


def _resume(path, manifest=PLAN):
    """Resume the sweep; return (results, stats, notes, store)."""
    notes = []
    with ResultStore(path, manifest, resume=True, report=notes.append) as st:
        res, stats = run_chunks(_square, ITEMS, KEYS, CASES, store=st)
    return res, stats, notes, st


def _ordered(x):
    """A result whose member order and non-finite floats must survive the store."""
    return {"z": [x, float("nan"), float("inf")], "a": {"2": x / 3.0, "10": -x}, "m": 0.1 + x}


def test_a_stored_result_reads_back_as_the_fresh_one_key_order_and_every_bit():
    """The chunk file holds the caller's own JSON of the result (written once, not serialised again): a resume
    returns what the run returned, member order, NaN, inf and every float bit, and verifies its hash."""
    import tempfile
    from pathlib import Path as P

    with tempfile.TemporaryDirectory() as tmp:
        d = P(tmp) / "st"
        with ResultStore(d, PLAN, report=lambda m: None) as st:
            fresh, _ = run_chunks(_ordered, ITEMS, KEYS, CASES, store=st)
        notes = []
        with ResultStore(d, PLAN, resume=True, report=notes.append) as st:
            again, stats = run_chunks(_ordered, ITEMS, KEYS, CASES, store=st)
        assert stats["computed"] == 0 and stats["reused"] == 3 and stats["rejected"] == 0
        assert json.dumps(again) == json.dumps(fresh)
        assert [list(r) for r in again] == [["z", "a", "m"]] * 3 and list(again[1]["a"]) == ["2", "10"]
        assert again[2]["m"] == 0.1 + 3.0 and again[0]["z"][2] == float("inf")


# --------------------------------------------------------------------------
# damaged chunks: each detected, reported in one line, moved away, recomputed
# --------------------------------------------------------------------------

def _swap(d):
    (d / "chunk-k1.json").write_bytes((d / "chunk-k0.json").read_bytes())


def _edit(d):
    rec = json.loads((d / "chunk-k1.json").read_text())
    rec["result"]["y"] = 1.0                                   # hand-edited number, hash left as it was
    (d / "chunk-k1.json").write_text(json.dumps(rec))


def _truncate(d):
    data = (d / "chunk-k1.json").read_bytes()
    (d / "chunk-k1.json").write_bytes(data[: len(data) // 2])


def _empty(d):
    (d / "chunk-k1.json").write_bytes(b"")


def _binary(d):
    (d / "chunk-k1.json").write_bytes(bytes(range(256)) * 4)


def _foreign(d):
    """k1 of another study (same key, valid hash, other plan key): what two runs into one OUT leave."""
    other = d.parent / "other"
    _complete_store(other, OTHER)
    (d / "chunk-k1.json").write_bytes((other / "chunk-k1.json").read_bytes())


def _cases(d):
    """A record whose case list is not the plan's, with a hash that matches (forged, not edited)."""
    from covtool.io.store import _record_hash

    rec = json.loads((d / "chunk-k1.json").read_text())
    rec["cases"] = [2, 3]
    rec["sha256"] = _record_hash(rec)
    (d / "chunk-k1.json").write_text(json.dumps(rec))


def _old_format(d):
    rec = json.loads((d / "chunk-k1.json").read_text())
    (d / "chunk-k1.json").write_text(json.dumps({"key": "k1", "cases": rec["cases"], "result": rec["result"]}))


@pytest.mark.parametrize("damage, problem", [
    (_swap, "holds chunk 'k0', not 'k1' (a copy of another chunk)"),
    (_edit, "content hash mismatch (edited or corrupted)"),
    (_truncate, "not valid JSON (truncated or corrupted)"),
    (_empty, "empty file"),
    (_binary, "not UTF-8 text (binary or corrupted)"),
    (_foreign, "written for another study (its plan key differs from this study's)"),
    (_cases, "its case list differs from the plan's for this chunk"),
    (_old_format, "not a chunk record of format covtool-chunk/2"),
])
def test_damaged_chunk_is_rejected_reported_and_recomputed(tmp_path, damage, problem):
    d = _complete_store(tmp_path / "s")
    damage(d)
    res, stats, notes, st = _resume(d)
    assert res == EXPECTED                                      # the recomputed value, not the damaged one
    assert (stats["reused"], stats["rejected"], stats["computed"]) == (2, 1, 1)
    assert notes == [f"{d / 'chunk-k1.json'}: {problem}; not used, moved to {d / 'rejected'}/; recomputing it"]
    assert [p.name for p in (d / "rejected").iterdir()] == [f"chunk-k1.json.{st.run_id}"]
    # the journal tells the story: stored by the first run, rejected, stored again
    ev = [(r["event"], r["key"]) for r in st.journal()]
    assert ev == [("stored", "k0"), ("stored", "k1"), ("stored", "k2"), ("rejected", "k1"), ("stored", "k1")]
    assert st.journal()[3]["problem"] == problem
    # and the store now holds every case exactly once, each chunk verified
    for k, c in zip(KEYS, CASES):
        assert st.check(k, c)[1] == ""
    _, stats2, notes2, _ = _resume(d)
    assert (stats2["reused"], stats2["computed"], notes2) == (3, 0, [])


def test_file_that_is_no_chunk_of_the_plan_is_moved_away_not_used(tmp_path):
    d = _complete_store(tmp_path / "s")
    (d / "chunk-k9.json").write_bytes((d / "chunk-k0.json").read_bytes())
    res, stats, notes, _ = _resume(d)
    assert res == EXPECTED and (stats["reused"], stats["computed"]) == (3, 0)
    assert notes == [f"{d / 'chunk-k9.json'}: not a chunk of this study's plan; not used, moved to {d / 'rejected'}/"]
    assert not (d / "chunk-k9.json").exists()


def test_half_written_chunk_is_removed_not_used(tmp_path):
    d = _complete_store(tmp_path / "s")
    (d / "chunk-k2.json").unlink()
    tmp = d / ".chunk-k2.json.abc123.tmp"                     # an atomic write cut short by a kill
    tmp.write_text('{"key": "k2", "res')
    res, stats, _, _ = _resume(d)
    assert res == EXPECTED and (stats["reused"], stats["computed"]) == (2, 1)
    assert not tmp.exists()


def test_plan_with_a_case_in_two_chunks_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"case 2 is in chunks 'k1' and 'k2'"):
        run_chunks(_square, ITEMS, KEYS, [[0, 1], [2], [2, 3]])
    with pytest.raises(ValueError, match="chunk keys are not unique"):
        run_chunks(_square, [1, 2], ["k", "k"], [[0], [1]])


class _Lossy(SerialBackend):
    def imap_unordered(self, fn, items):
        yield 0, fn(items[0])


def test_backend_that_loses_a_chunk_is_an_error():
    with pytest.raises(WorkerError, match=r"no result for chunks k1, k2"):
        run_chunks(_square, ITEMS, KEYS, CASES, backend=_Lossy())


# --------------------------------------------------------------------------
# journal and manifest damage
# --------------------------------------------------------------------------

def test_journal_lines_that_do_not_parse_are_reported_and_dropped(tmp_path):
    d = _complete_store(tmp_path / "s")
    j = d / "journal.jsonl"
    lines = j.read_bytes().splitlines(keepends=True)
    j.write_bytes(lines[0] + b'{"event": "stored", "key": "k1", \xff\xfe}\n' + lines[1] + b"not json\n"
                  + lines[2][:20])                              # non-UTF-8, not JSON, torn by a kill
    res, stats, notes, st = _resume(d)
    assert res == EXPECTED and stats["computed"] == 0
    keep = d / "rejected" / f"journal.jsonl.{st.run_id}"
    tail = f"; ignored (chunk files are verified on their own; the damaged journal is kept in {keep})"
    assert notes == [f"{j}: line 2: not UTF-8 text{tail}", f"{j}: line 4: not a JSON record{tail}",
                     f"{j}: line 5: torn (a run was killed while writing it){tail}"]
    assert keep.read_bytes().startswith(lines[0])
    # k2's line was torn: its verified chunk is journaled as recovered; every case counted once
    assert [(r["event"], r["key"]) for r in st.journal()] == [("stored", "k0"), ("stored", "k1"), ("recovered", "k2")]
    assert st.case_counts() == {0: 1, 1: 1, 2: 1, 3: 1, 4: 1}
    _, _, notes2, _ = _resume(d)
    assert notes2 == []                                        # reported once, then clean


@pytest.mark.parametrize("damage, problem", [
    (lambda p: p.unlink(), "is missing"),
    (lambda p: p.write_text("{not json"), "is not valid JSON (damaged)"),
    (lambda p: p.write_bytes(b"\x89PNG\r\n"), "is not valid JSON (damaged)"),
    (lambda p: p.write_text('{"chunks": []}'), "has no plan fingerprint"),
])
def test_lost_manifest_is_reported_and_chunks_checked_by_their_plan_key(tmp_path, damage, problem):
    d = _complete_store(tmp_path / "s")
    damage(d / "manifest.json")
    res, stats, notes, _ = _resume(d)
    assert res == EXPECTED and (stats["reused"], stats["computed"]) == (3, 0)
    assert notes == [f"{d / 'manifest.json'}: {problem}; each of the 3 stored chunks is checked against this "
                     "study's plan key instead"]
    assert json.loads((d / "manifest.json").read_text())["kind"] == "toy"


def test_lost_manifest_does_not_let_another_studys_chunks_in(tmp_path):
    d = _complete_store(tmp_path / "s", OTHER)
    (d / "manifest.json").unlink()
    res, stats, notes, _ = _resume(d)
    assert res == EXPECTED and (stats["rejected"], stats["computed"]) == (3, 3)
    assert len(notes) == 4 and all("written for another study" in n for n in notes[1:])


def test_resume_refuses_another_studys_manifest(tmp_path):
    d = _complete_store(tmp_path / "s")
    with pytest.raises(StoreError, match=r"s: was written for a different sweep \(differs in: q\); run without "
                                         r"--resume to start afresh"):
        ResultStore(d, OTHER, resume=True)


def test_resume_without_a_store_says_so(tmp_path):
    res, stats, notes, _ = _resume(tmp_path / "nothing")
    assert res == EXPECTED and stats["computed"] == 3
    assert notes == [f"{tmp_path / 'nothing'}: no stored chunks to resume; computing every chunk"]


# --------------------------------------------------------------------------
# a fresh run keeps the earlier complete store until it has stored every chunk
# --------------------------------------------------------------------------

def test_fresh_run_sets_the_complete_store_aside_until_it_finishes(tmp_path):
    d = _complete_store(tmp_path / "s")
    prev = tmp_path / "s.previous"
    before = {p.name: p.read_bytes() for p in d.glob("chunk-*.json")}
    notes = []
    with ResultStore(d, PLAN, report=notes.append) as st, pytest.raises(KeyboardInterrupt):
        run_chunks(_half, ITEMS, KEYS, CASES, store=st)         # killed after its first chunk
    assert notes == [f"{d}: the earlier store is moved to {prev} and kept until this run has stored every chunk"]
    assert {p.name: p.read_bytes() for p in prev.glob("chunk-*.json")} == before   # intact
    assert [p.name for p in d.glob("chunk-*.json")] == ["chunk-k0.json"]
    # a second fresh run: the partial store goes, the complete one stays ...
    notes.clear()
    with ResultStore(d, PLAN, report=notes.append) as st:
        assert notes == [f"{d}: discarded the incomplete store of an interrupted run (continue such a run with "
                         f"--resume); {prev} keeps the last complete store"]
        assert prev.is_dir() and not list(d.glob("chunk-*.json"))
        res, _ = run_chunks(_square, ITEMS, KEYS, CASES, store=st)
    # ... until this run has stored every chunk
    assert res == EXPECTED and not prev.exists()
    assert sorted(p.name for p in d.glob("chunk-*.json")) == sorted(before)


def test_fresh_run_over_an_incomplete_store_without_an_earlier_one_keeps_it(tmp_path):
    d = tmp_path / "s"
    with ResultStore(d, PLAN, report=lambda m: None) as st, pytest.raises(KeyboardInterrupt):
        run_chunks(_half, ITEMS, KEYS, CASES, store=st)
    with ResultStore(d, PLAN, report=lambda m: None):
        assert [p.name for p in (tmp_path / "s.previous").glob("chunk-*")] == ["chunk-k0.json"]


# --------------------------------------------------------------------------
# directory lock
# --------------------------------------------------------------------------

HOLD = """
import sys, time
from covtool.io.lock import DirLock
DirLock(sys.argv[1], command="holder").acquire()
print("locked", flush=True)
time.sleep(60)
"""


def test_lock_held_by_another_process_refuses_with_its_pid(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    try:
        assert proc.stdout.readline() == "locked\n"
        with pytest.raises(OutputLockedError, match=rf"^{tmp_path}: in use by another covtool run \(PID {proc.pid} "
                                                    rf"on host {socket.gethostname()}, started .*, holder\); wait "
                                                    "for it to finish or choose another --out$"):
            DirLock(tmp_path).acquire()
        with pytest.raises(OutputLockedError, match=rf"in use by another covtool run \(PID {proc.pid} "):
            ResultStore(tmp_path / "cases", PLAN)
    finally:
        proc.kill()
        proc.wait()
    # the holder is dead: its lock is stale and taken over
    notes = []
    with DirLock(tmp_path, report=notes.append):
        assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()
    assert notes == [f"{tmp_path / LOCK_NAME}: took over a stale lock (PID {proc.pid} on host "
                     f"{socket.gethostname()}, started {notes[0].split('started ')[1].split(',')[0]}, holder; that "
                     "process is no longer running)"]
    assert not (tmp_path / LOCK_NAME).exists()                 # released: removed


def test_stale_lock_of_a_dead_pid_is_taken_over(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": pid, "host": socket.gethostname(), "started": "then",
                                                  "command": "covtool run x.toml"}))
    notes = []
    with DirLock(tmp_path, report=notes.append):
        pass
    assert notes == [f"{tmp_path / LOCK_NAME}: took over a stale lock (PID {pid} on host {socket.gethostname()}, "
                     "started then, covtool run x.toml; that process is no longer running)"]


def test_lock_of_another_host_is_not_taken_over(tmp_path):
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": 4242, "host": "elsewhere", "started": "then"}))
    with pytest.raises(OutputLockedError, match=rf"^{tmp_path}: locked by a run on another host \(PID 4242 on host "
                                                rf"elsewhere, started then\), which cannot be checked from here; if "
                                                rf"that run has ended, delete {tmp_path / LOCK_NAME}$"):
        DirLock(tmp_path).acquire()
    assert (tmp_path / LOCK_NAME).exists()


def test_lock_is_reentrant_in_one_process_and_cleans_up(tmp_path):
    out = tmp_path / "new"
    with DirLock(out):
        with ResultStore(out / "cases", PLAN):
            pass
        assert (out / LOCK_NAME).exists()                      # still held by the outer lock
    assert (out / "cases").is_dir() and not (out / LOCK_NAME).exists()
    empty = tmp_path / "unused"
    with DirLock(empty):
        pass
    assert not empty.exists()                                  # created by the lock, nothing written: removed


def test_lock_errors(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("")
    with pytest.raises(OutputLockedError, match=r"file/out: cannot create the directory \(Not a directory\)"):
        DirLock(tmp_path / "file" / "out").acquire()
    real_stat = os.stat

    def moved(path, *a, **k):                                  # the lock file is replaced after every open
        st = real_stat(path, *a, **k)
        return os.stat_result((st.st_mode, st.st_ino + 1) + tuple(st)[2:]) if str(path).endswith(LOCK_NAME) else st

    monkeypatch.setattr(os, "stat", moved)
    with pytest.raises(OutputLockedError, match=r"cannot lock .*\.covtool\.lock \(it keeps being replaced\)"):
        DirLock(tmp_path / "d").acquire()


def test_without_flock_the_pid_decides(tmp_path, monkeypatch):
    """A file system without flock (ENOLCK): a live PID of this host holds the lock, a dead one does not."""
    import errno
    import fcntl

    def no_flock(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", no_flock)
    live = os.getppid()
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": live, "host": socket.gethostname(), "started": "now"}))
    with pytest.raises(OutputLockedError, match=rf"in use by another covtool run \(PID {live} on host "):
        DirLock(tmp_path).acquire()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": int(dead.stdout), "host": socket.gethostname()}))
    notes = []
    with DirLock(tmp_path, report=notes.append):
        assert json.loads((tmp_path / LOCK_NAME).read_text())["pid"] == os.getpid()
    assert len(notes) == 1 and "that process is no longer running" in notes[0]
