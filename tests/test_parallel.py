"""Backends give identical results; a killed sweep resumes with no case lost or computed twice.

A damaged store is verified, reported and recomputed; a second run into the
same OUT is refused; SIGINT/SIGTERM stop the workers promptly and a killed
parent leaves no worker behind (the store-level units are in test_store.py).

Also the engine's rank-m update forms (covtool.lincov.kalman.joseph_update) against the
product forms they replace.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import psutil
import pytest
import tomli_w

from covtool.cli import main
from covtool.lincov.reference import propagate_with_filter
from covtool.lincov.batch import System, events, run_batch
from covtool.lincov.kalman import joseph_update as _joseph
from covtool.io.lock import LOCK_NAME
from covtool.parallel import (ProcessBackend, SerialBackend, WorkerError, call_limited,
                              make_backend, run_chunks)
from covtool.io.store import ResultStore, StoreError, _record_hash, fingerprint

ROOT = Path(__file__).resolve().parents[1]
TRADE = ROOT / "studies" / "trade_grid.toml"


# --------------------------------------------------------------------------
# engine: expanded update forms
# --------------------------------------------------------------------------

def test_expanded_joseph_equals_product_form_for_any_gain():
    rng = np.random.default_rng(3)
    B, n, m = 4, 9, 3
    L = rng.standard_normal((B, n, n))
    P = L @ np.swapaxes(L, 1, 2)
    H = rng.standard_normal((m, n))
    R = np.eye(m) * 0.3
    K = rng.standard_normal((B, n, m))                      # not the optimal gain
    HP = H @ P
    A = np.eye(n) - K @ H
    ref = A @ P @ np.swapaxes(A, 1, 2) + K @ R @ np.swapaxes(K, 1, 2)
    out = _joseph(P.copy(), K, H, R, HP=HP)
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    assert np.array_equal(out, np.swapaxes(out, 1, 2))     # exactly symmetric


@pytest.mark.parametrize("form, kept", [("joseph", [0, 1, 2, 3]), ("standard", [0, 1, 2, 3]),
                                        ("joseph", [2, 3, 4, 5]), ("joseph", [0, 1, 3, 6])])
def test_run_batch_equals_stepwise_reference_on_random_system(form, kept):
    """Truth n = 7 under a 4-state filter with a wrong model: engine = propagate_with_filter (≤ 1e-10).

    The kept states are a leading block, an inner block (both the selection
    fast path) and scattered states (the general path).
    """
    rng = np.random.default_rng(4)
    N, n, nf, m = 60, 7, 4, 2
    Phi = np.eye(n) + 0.05 * rng.standard_normal((N, n, n))
    L = rng.standard_normal((N, n, n))
    Qd = 1e-3 * L @ np.swapaxes(L, 1, 2)
    D = np.eye(n)[:, kept]
    ix = np.ix_(range(N), kept, kept)
    Phi_f = Phi[ix] + 0.01
    Qd_f = 2.0 * Qd[ix]
    H = np.eye(n)[kept[:m]]
    Hf = np.eye(nf)[:m]
    P0 = np.eye(n) + 0.1
    R = 0.1 * np.eye(m)
    upd = [5, 6, 7, 20, 21, 40, 59]
    rec = [0, 10, 30, 60]
    ev = events(N, upd, rec)
    scales = [(1.0, 1.0, 1.0), (10.0, 0.1, 3.0)]
    res = run_batch(System.from_steps(Phi, Qd, ev), P0, H, R, D, upd, rec, filt=System.from_steps(Phi_f, Qd_f, ev),
                    Pf0=np.stack([s[0] * P0[np.ix_(kept, kept)] for s in scales]), Hf=Hf,
                    Rf=np.stack([s[2] * R for s in scales]), q_scale=np.array([s[1] for s in scales]), form=form,
                    keep=slice(0, n))
    for b, (sp, sq, sr) in enumerate(scales):
        ref = propagate_with_filter(Phi, Qd, P0, Phi_f, sq * Qd_f, sp * P0[np.ix_(kept, kept)], H, Hf, D, R, upd,
                                    Rf=sr * R, form=form)
        np.testing.assert_allclose(res.P_truth[b], ref.P_truth[rec], rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(res.P_filter[b], ref.P_filter[rec][:, :nf, :nf], rtol=1e-10, atol=1e-14)


# --------------------------------------------------------------------------
# backends
# --------------------------------------------------------------------------

def small_decl() -> dict:
    """8 min at 1 s; 2 grades x 3 intervals = 6 chunks of 2 filters x 2 Q scales (24 cases)."""
    d = tomllib.loads(TRADE.read_text())
    d["study"].update(duration="8 min", dt="1 s")
    d["output"]["report_times"] = ["8 min"]
    d["filters"]["cases"] = ["B1", "D"]
    d["grid"].update(zupt_interval=["3 min", "4 min", "5 min"], zupt_sigma=["0.01 ft/s"], q_scale=[1.0, 3.0])
    d["grade"] = [d["grade"][0], d["grade"][3]]
    return d


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """The small grid as a study file next to a copy of the filter file (relative path)."""
    base = tmp_path_factory.mktemp("grid")
    (base / "models" / "filters").mkdir(parents=True)
    (base / "models" / "filters" / "zupt_filters.toml").write_text(
        (ROOT / "models" / "filters" / "zupt_filters.toml").read_text())
    (base / "studies").mkdir()
    p = base / "studies" / "grid.toml"
    p.write_text(tomli_w.dumps(small_decl()))
    return p


@pytest.fixture(scope="module")
def reference(study, tmp_path_factory):
    """Uninterrupted in-process CLI run."""
    out = tmp_path_factory.mktemp("ref")
    assert main(["run", str(study), "--out", str(out), "--quiet", "--no-figures"]) == 0
    return out


def sheets(out: Path) -> dict:
    """Every workbook sheet but the provenance (timestamps, timings)."""
    book = pd.read_excel(out / "trade_grid.xlsx", sheet_name=None)
    return {k: v for k, v in book.items() if k != "provenance"}


def assert_same_outputs(a: Path, b: Path):
    sa, sb = sheets(a), sheets(b)
    assert sa.keys() == sb.keys()
    for k in sa:
        pd.testing.assert_frame_equal(sa[k], sb[k], check_exact=True, obj=k)
    assert (a / "summary.csv").read_bytes() == (b / "summary.csv").read_bytes()


def test_process_backend_identical_to_in_process(study, reference, tmp_path):
    out = tmp_path / "proc"
    assert main(["run", str(study), "--out", str(out), "--quiet", "--no-figures", "--workers", "2"]) == 0
    assert_same_outputs(reference, out)
    prov = pd.read_excel(out / "trade_grid.xlsx", sheet_name="provenance").set_index("key")["value"]
    assert prov["backend"] == "2 local processes"


#: the Dask run of the test below, in a Python process of its own: a Dask client leaves its IO loop and
#: offload threads running in the process for good, and a process with other threads never forks
#: (covtool.forked.can_split), so later tests in this worker would not take their forked paths
_DASK_RUN = """
import sys
from dask.distributed import LocalCluster
from covtool.cli import main
with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                  host="127.0.0.1") as cluster:
    code = main(["run", sys.argv[1], "--out", sys.argv[2], "--quiet", "--no-figures",
                 "--scheduler", cluster.scheduler_address])
sys.exit(code)
"""


def _isolated(code: str, *args: str, timeout: float) -> subprocess.CompletedProcess:
    """``python -c code args…`` in a session of its own; on a timeout the whole group (its Dask workers) is killed."""
    proc = subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def test_dask_local_cluster_identical_to_in_process(study, reference, tmp_path):
    """Two single-threaded Dask workers reached through the CLI's --scheduler ADDRESS."""
    out = tmp_path / "dask"
    done = _isolated(_DASK_RUN, str(study), str(out), timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert_same_outputs(reference, out)
    prov = pd.read_excel(out / "trade_grid.xlsx", sheet_name="provenance").set_index("key")["value"]
    assert prov["backend"].startswith("dask at tcp://127.0.0.1") and "(2 workers)" in prov["backend"]


def _start(study: Path, out: Path, *extra: str) -> tuple[subprocess.Popen, Path]:
    """``covtool run`` in its own session (as a terminal's foreground job); stderr to a file.

    A file, not a pipe: an orphaned worker holding a pipe would block the read.
    """
    err = out.with_name(out.name + ".stderr")
    with open(err, "wb") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "covtool", "run", str(study), "--out", str(out), "--quiet",
                                 "--no-figures", *extra], start_new_session=True, stdout=subprocess.DEVNULL,
                                stderr=fh, env={**os.environ, "PYTHONPATH": str(ROOT)})
    return proc, err


def _wait_for_chunks(proc: subprocess.Popen, cases: Path, n: int, err: Path) -> None:
    deadline = time.monotonic() + 120
    while len(list(cases.glob("chunk-*.json"))) < n:
        assert proc.poll() is None, err.read_text()
        assert time.monotonic() < deadline, f"fewer than {n} chunks stored within 120 s"
        time.sleep(0.01)


def _running(procs) -> list[int]:
    """PIDs of the processes still running (a zombie has exited)."""
    alive = []
    for p in procs:
        try:
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                alive.append(p.pid)
        except psutil.NoSuchProcess:
            pass
    return alive


def _wait_gone(procs, timeout: float) -> list[int]:
    """Wait up to ``timeout`` s for ``procs`` to end; return the PIDs still running."""
    deadline = time.monotonic() + timeout
    while _running(procs) and time.monotonic() < deadline:
        time.sleep(0.05)
    return _running(procs)


def _kill_all(procs) -> None:
    """Clean up after a failed test: the processes it started, by PID."""
    for p in procs:
        with contextlib.suppress(psutil.NoSuchProcess):
            p.kill()


def _journal(cases: Path) -> list[dict]:
    return [json.loads(line) for line in (cases / "journal.jsonl").read_text().splitlines() if line.strip()]


def _journal_counts(cases: Path) -> dict:
    """How often each case was stored ("stored" and "recovered" journal events)."""
    counts = {}
    for r in _journal(cases):
        if r["event"] in ("stored", "recovered"):
            for c in r["cases"]:
                counts[c] = counts.get(c, 0) + 1
    return counts


def test_kill_and_resume_loses_and_repeats_nothing(study, reference, tmp_path, capsys):
    """kill -9 after two chunks are stored, then --resume: same workbook, every case stored exactly once.

    The killed run's lock is stale (its PID is dead): the resumed run takes it over with a note.
    """
    out = tmp_path / "killed"
    cases = out / "cases"
    proc, err = _start(study, out)
    try:
        _wait_for_chunks(proc, cases, 2, err)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    stored = len(list(cases.glob("chunk-*.json")))
    assert 2 <= stored < 6, stored                          # interrupted part-way
    assert not (out / "trade_grid.xlsx").exists()
    assert json.loads((out / LOCK_NAME).read_text())["pid"] == proc.pid

    assert main(["run", str(study), "--out", str(out), "--quiet", "--no-figures", "--resume"]) == 0
    notes = capsys.readouterr().err
    assert f"{out / LOCK_NAME}: took over a stale lock (PID {proc.pid} on host {socket.gethostname()}" in notes
    assert "that process is no longer running)" in notes and "not used" not in notes
    assert_same_outputs(reference, out)
    store_cases = json.loads((cases / "manifest.json").read_text())["cases"]
    counts = _journal_counts(cases)
    assert sorted(counts) == list(range(store_cases)) == list(range(24))
    assert set(counts.values()) == {1}                     # no case lost, none computed twice
    assert len({r["run"] for r in _journal(cases)}) == 2            # the killed run and the resumed one
    prov = pd.read_excel(out / "trade_grid.xlsx", sheet_name="provenance").set_index("key")["value"]
    assert int(prov["chunks_reused"]) == stored and int(prov["chunks_computed"]) == 6 - stored
    assert not (out / LOCK_NAME).exists()


def test_damaged_store_is_verified_reported_and_recomputed(study, reference, tmp_path, capsys):
    """Swapped, hand-edited, foreign, truncated and binary chunks and a non-UTF-8 journal line, then --resume.

    Before: the swapped chunk gave 24 rows of 20 distinct cases, the edited CEP went into the summary,
    the others a traceback.  Now each is reported in one line and recomputed; the outputs equal an
    uninterrupted run's and every case appears exactly once.
    """
    out = tmp_path / "damaged"
    shutil.copytree(reference, out)
    cases = out / "cases"
    ch = {k: cases / f"chunk-{k}.json" for k in ("g00-i00", "g00-i01", "g00-i02", "g01-i00", "g01-i01", "g01-i02")}
    ch["g00-i01"].write_bytes(ch["g00-i00"].read_bytes())                      # cp chunk-g00-i00 chunk-g00-i01
    rec = json.loads(ch["g00-i02"].read_text())
    assert rec["result"]["rows"][0]["CEP [ft]"] != 1.0
    rec["result"]["rows"][0]["CEP [ft]"] = 1.0                                 # a hand edit
    ch["g00-i02"].write_text(json.dumps(rec))
    d = small_decl()                                                            # another study's chunk ...
    d["grid"]["q_scale"] = [1.0, 2.0]
    from covtool.studies.trade_grid import TradePlan
    other = TradePlan(d, study)
    rec = json.loads(ch["g01-i00"].read_text())
    rec["plan"] = fingerprint(other.manifest(d))
    for row in rec["result"]["rows"]:
        row["Q scale"] = 2.0 if row["Q scale"] == 3.0 else row["Q scale"]
    rec["sha256"] = _record_hash(rec)                                          # ... internally consistent
    ch["g01-i00"].write_text(json.dumps(rec))
    ch["g01-i01"].write_bytes(ch["g01-i01"].read_bytes()[:700])                # truncated
    ch["g01-i02"].write_bytes(os.urandom(64) + b"\xff\xfe")                    # binary
    with open(cases / "journal.jsonl", "ab") as fh:
        fh.write(b'{"event": "stored", "key": "g00-i00", "cases": [0, 1, 2, 3], "run": "\xe9t\xe9"}\n')

    assert main(["run", str(study), "--out", str(out), "--quiet", "--no-figures", "--resume"]) == 0
    err = capsys.readouterr().err.splitlines()
    rej = f"not used, moved to {cases / 'rejected'}/; recomputing it"
    assert err[0].startswith(f"covtool: {cases / 'journal.jsonl'}: line 7: not UTF-8 text; ignored")
    assert err[1:] == [
        f"covtool: {ch['g00-i01']}: holds chunk 'g00-i00', not 'g00-i01' (a copy of another chunk); {rej}",
        f"covtool: {ch['g00-i02']}: content hash mismatch (edited or corrupted); {rej}",
        f"covtool: {ch['g01-i00']}: written for another study (its plan key differs from this study's); {rej}",
        f"covtool: {ch['g01-i01']}: not valid JSON (truncated or corrupted); {rej}",
        f"covtool: {ch['g01-i02']}: not UTF-8 text (binary or corrupted); {rej}"]
    assert_same_outputs(reference, out)
    summary = pd.read_csv(out / "summary.csv")
    assert sorted(summary["case"]) == list(range(24))                          # every case exactly once
    prov = pd.read_excel(out / "trade_grid.xlsx", sheet_name="provenance").set_index("key")["value"]
    assert (int(prov["chunks_reused"]), int(prov["chunks_computed"])) == (1, 5)
    assert prov["result_store_checks"].startswith("1 chunks verified and reused, 5 rejected, 5 computed; ")
    counts = _journal_counts(cases)                                            # stored by the reference run,
    assert counts == {c: 1 if c < 4 else 2 for c in range(24)}                 # and again if rejected
    assert len(list((cases / "rejected").glob("chunk-*"))) == 5


def _interrupt_mid_run(study: Path, out: Path, sig: int, second_run=None) -> int:
    """Start a --workers 2 run, signal it after its first chunk; check the exit; return the chunks stored.

    SIGINT goes to the whole process group (Ctrl-C in a terminal), SIGTERM to the parent only.
    ``second_run(pid)`` is called while the run is going.
    """
    proc, err = _start(study, out, "--workers", "2")
    kids = []
    try:
        _wait_for_chunks(proc, out / "cases", 1, err)
        kids = psutil.Process(proc.pid).children(recursive=True)
        assert len(kids) >= 3, kids                          # two workers and the resource tracker
        if second_run is not None:
            second_run(proc.pid)
        if sig == signal.SIGINT:
            os.killpg(proc.pid, sig)
        else:
            os.kill(proc.pid, sig)
        assert proc.wait(timeout=10) == 128 + sig
        assert _wait_gone(kids, 10) == []
    finally:
        _kill_all(kids + [psutil.Process(proc.pid)] if proc.poll() is None else kids)
        proc.wait()
    assert err.read_text().splitlines() == [
        f"covtool: interrupted by {signal.Signals(sig).name}; the chunks finished so far are kept in {out / 'cases'} "
        "(continue with --resume); earlier outputs are untouched"]
    stored = len(list((out / "cases").glob("chunk-*.json")))
    assert 1 <= stored < 6, stored                           # stopped mid-run
    assert not list((out / "cases").glob(".*.tmp")) and not list(out.glob(".staging-*"))
    assert not (out / LOCK_NAME).exists()
    return stored


def test_sigint_with_workers_stops_promptly_and_leaves_a_resumable_store(study, reference, tmp_path, capsys):
    """Ctrl-C with --workers 2 mid-run.

    Before: "interrupted; earlier outputs are untouched", then a hang in 3 of 6 tries
    (ProcessPoolExecutor.shutdown waiting for its workers).  Now: exit 130 within 10 s with one
    line, no child process left, only whole chunks stored, and --resume completes the run.
    """
    out = tmp_path / "int"
    stored = _interrupt_mid_run(study, out, signal.SIGINT)
    assert main(["run", str(study), "--out", str(out), "--quiet", "--no-figures", "--resume"]) == 0
    assert capsys.readouterr().err == ""                     # every stored chunk verified, nothing to report
    assert_same_outputs(reference, out)
    assert _journal_counts(out / "cases") == {c: 1 for c in range(24)}
    prov = pd.read_excel(out / "trade_grid.xlsx", sheet_name="provenance").set_index("key")["value"]
    assert int(prov["chunks_reused"]) == stored


def test_sigterm_with_workers_stops_promptly_and_a_second_run_is_refused(study, tmp_path, capsys):
    """SIGTERM to the parent with --workers 2; meanwhile a second run into the same OUT.

    Before: both workers and the resource tracker stayed alive; two runs into one OUT mixed their
    chunks.  Now: exit 143 within 10 s with one line and no child left; the second run is refused
    with a message naming the first run's PID, and leaves its files alone.
    """
    out = tmp_path / "term"

    def second_run(pid):
        # the finished chunks only: a hidden ".<name>.<pid>-<rand>.tmp" is the first run's atomic write in
        # flight, which that (still running) run renames to its final name meanwhile
        before = sorted(p.name for p in (out / "cases").iterdir() if not p.name.startswith("."))
        assert main(["run", str(study), "--out", str(out), "--quiet", "--no-figures"]) == 2
        assert re.fullmatch(rf"covtool: error: {re.escape(str(out))}: in use by another covtool run \(PID {pid} on "
                            rf"host {re.escape(socket.gethostname())}, started [^,]+, covtool run "
                            rf"{re.escape(str(study))}\); wait for it to finish or choose another --out\n",
                            capsys.readouterr().err)
        assert not (out / "cases.previous").exists()           # the running run's store was not touched
        assert set(before) <= {p.name for p in (out / "cases").iterdir()}

    _interrupt_mid_run(study, out, signal.SIGTERM, second_run)


def test_kill_9_of_the_parent_leaves_no_worker(study, tmp_path):
    """Before: both workers (~300 MB each) and the resource tracker stayed alive.  Now they end with it."""
    out = tmp_path / "orphans"
    proc, err = _start(study, out, "--workers", "2")
    kids = []
    try:
        _wait_for_chunks(proc, out / "cases", 1, err)
        kids = psutil.Process(proc.pid).children(recursive=True)
        assert len(kids) >= 3, kids
        proc.kill()                                          # SIGKILL to the parent alone
        proc.wait(timeout=10)
        assert _wait_gone(kids, 10) == []
    finally:
        _kill_all(kids)
        if proc.poll() is None:
            proc.kill()
        proc.wait()


def test_resume_refuses_a_store_of_another_study(study, reference, tmp_path):
    d = small_decl()
    d["grid"]["q_scale"] = [1.0, 2.0]
    other = study.parent / "other.toml"
    other.write_text(tomli_w.dumps(d))
    assert main(["run", str(other), "--out", str(reference), "--resume", "--quiet"]) == 2


def test_resume_of_a_finished_run_computes_nothing(study, reference, tmp_path):
    import shutil

    out = tmp_path / "again"
    shutil.copytree(reference, out)
    assert main(["run", str(study), "--out", str(out), "--quiet", "--no-figures", "--resume"]) == 0
    assert_same_outputs(reference, out)
    prov = pd.read_excel(out / "trade_grid.xlsx", sheet_name="provenance").set_index("key")["value"]
    assert int(prov["chunks_computed"]) == 0 and int(prov["chunks_reused"]) == 6


# --------------------------------------------------------------------------
# store and backend units
# --------------------------------------------------------------------------

def _square(x):
    return {"y": x * x}


class _Unpicklable(Exception):
    def __init__(self, msg):
        super().__init__(msg)
        self.lock = threading.Lock()


def _fails(x):
    raise _Unpicklable("holds a lock")


def _dies(x):
    os._exit(3)


def test_store_reconciles_torn_journal_and_unjournaled_chunks(tmp_path):
    with ResultStore(tmp_path / "s", {"a": 1}) as st:
        st.save("k0", [0, 1], {"y": 1.5})
        st.save("k1", [2], {"y": 2.5})
    j = tmp_path / "s" / "journal.jsonl"
    lines = j.read_text().splitlines()
    j.write_text(lines[0] + "\n" + lines[1][:10])         # k1's line torn by a kill
    notes = []
    with ResultStore(tmp_path / "s", {"a": 1}, resume=True, report=notes.append) as st2:
        assert st2.keys() == {"k0", "k1"}
        assert notes == [f"{j}: line 2: torn (a run was killed while writing it); ignored (chunk files are verified "
                         f"on their own; the damaged journal is kept in {j.parent / 'rejected'}/"
                         f"journal.jsonl.{st2.run_id})"]
        res, stats = run_chunks(_square, [1.0, 2.0, 3.0], ["k0", "k1", "k2"], [[0, 1], [2], [3]], store=st2)
        assert res == [{"y": 1.5}, {"y": 2.5}, {"y": 9.0}] and (stats["computed"], stats["reused"]) == (1, 2)
        assert st2.case_counts() == {0: 1, 1: 1, 2: 1, 3: 1}
        assert [r["event"] for r in st2.journal()] == ["stored", "recovered", "stored"]
    with ResultStore(tmp_path / "s", {"a": 1}, report=notes.append):   # without resume: afresh ...
        assert not list((tmp_path / "s").glob("chunk-*"))
    assert sorted(p.name for p in (tmp_path / "s.previous").glob("chunk-*")) == [   # ... the old one set aside
        "chunk-k0.json", "chunk-k1.json", "chunk-k2.json"]


def test_store_errors(tmp_path):
    with ResultStore(tmp_path / "s", {"a": 1}):
        pass
    with pytest.raises(StoreError, match=r"was written for a different sweep \(differs in: a\)"):
        ResultStore(tmp_path / "s", {"a": 2}, resume=True)


def test_backend_errors():
    with pytest.raises(WorkerError, match=r"_Unpicklable: holds a lock"):
        call_limited(_fails, 1)
    with pytest.raises(ZeroDivisionError):                   # picklable errors pass through unchanged
        call_limited(lambda x: 1 / x, 0)
    with pytest.raises(ValueError, match=r"workers: 0 is not a positive integer"):
        ProcessBackend(0)
    with pytest.raises(ValueError, match=r"backend: unknown backend 'gpu'"):
        make_backend("gpu")
    assert isinstance(make_backend(), SerialBackend) and isinstance(make_backend(workers=1), SerialBackend)
    # in a process of its own: a Dask client leaves threads behind (see _DASK_RUN)
    done = _isolated(_DASK_REFUSED, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert re.search(r"scheduler: cannot connect to Dask scheduler 'tcp://127.0.0.1:9'", done.stdout), done.stdout


_DASK_REFUSED = """
from covtool.parallel import DaskBackend
try:
    DaskBackend("tcp://127.0.0.1:9", timeout="1s")
except ValueError as exc:
    print(exc)
else:
    raise SystemExit("no error")
"""


def test_process_backend_maps_and_reraises(tmp_path):
    with ProcessBackend(2) as be:
        got = dict(be.imap_unordered(_square, [1.0, 2.0, 3.0]))
        assert got == {0: {"y": 1.0}, 1: {"y": 4.0}, 2: {"y": 9.0}}
        with pytest.raises(WorkerError, match="holds a lock"):
            dict(be.imap_unordered(_fails, [1]))
    with ProcessBackend(1) as be:
        with pytest.raises(WorkerError, match=r"a worker process died while running a chunk \(killed, or out of "
                                              r"memory\?\); the chunks stored so far are kept: use --resume"):
            dict(be.imap_unordered(_dies, [1]))


def test_cli_rejects_bad_worker_count(study, capsys):
    with pytest.raises(SystemExit):
        main(["run", str(study), "--workers", "0"])
    assert "'0' is not a positive integer" in capsys.readouterr().err
