"""Backends give identical results; a killed sweep resumes with no case lost or computed twice.

Also the engine's rank-m update forms (covtool.engine._joseph) against the
product forms they replace.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tomli_w

from covtool.cli import main
from covtool.covariance import propagate_with_filter
from covtool.engine import System, _joseph, events, run_batch
from covtool.parallel import (DaskBackend, ProcessBackend, ResultStore, SerialBackend, StoreError, WorkerError,
                              call_limited, make_backend, run_chunks)

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
    out = _joseph(P, K, HP, HP @ H.T + R)
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


def test_dask_local_cluster_identical_to_in_process(study, reference, tmp_path):
    """Two single-threaded Dask workers reached through the CLI's --scheduler ADDRESS."""
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      host="127.0.0.1") as cluster:
        out = tmp_path / "dask"
        assert main(["run", str(study), "--out", str(out), "--quiet", "--no-figures",
                     "--scheduler", cluster.scheduler_address]) == 0
    assert_same_outputs(reference, out)
    prov = pd.read_excel(out / "trade_grid.xlsx", sheet_name="provenance").set_index("key")["value"]
    assert prov["backend"].startswith("dask at tcp://127.0.0.1") and "(2 workers)" in prov["backend"]


def test_kill_and_resume_loses_and_repeats_nothing(study, reference, tmp_path):
    """kill -9 after two chunks are stored, then --resume: same workbook, every case stored exactly once."""
    out = tmp_path / "killed"
    cases = out / "cases"
    proc = subprocess.Popen([sys.executable, "-m", "covtool.cli", "run", str(study), "--out", str(out), "--quiet",
                             "--no-figures"], start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while len(list(cases.glob("chunk-*.json"))) < 2:
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "no chunk stored within 120 s"
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    stored = len(list(cases.glob("chunk-*.json")))
    assert 2 <= stored < 6, stored                          # interrupted part-way
    assert not (out / "trade_grid.xlsx").exists()

    assert main(["run", str(study), "--out", str(out), "--quiet", "--no-figures", "--resume"]) == 0
    assert_same_outputs(reference, out)
    store_cases = json.loads((cases / "manifest.json").read_text())["cases"]
    journal = [json.loads(line) for line in (cases / "journal.jsonl").read_text().splitlines() if line.strip()]
    counts = {}
    for r in journal:
        for c in r["cases"]:
            counts[c] = counts.get(c, 0) + 1
    assert sorted(counts) == list(range(store_cases)) == list(range(24))
    assert set(counts.values()) == {1}                     # no case lost, none computed twice
    assert len({r["run"] for r in journal}) == 2            # the killed run and the resumed one
    prov = pd.read_excel(out / "trade_grid.xlsx", sheet_name="provenance").set_index("key")["value"]
    assert int(prov["chunks_reused"]) == stored and int(prov["chunks_computed"]) == 6 - stored


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


def test_store_reconciles_torn_journal_and_unjournaled_chunks(tmp_path):
    st = ResultStore(tmp_path / "s", {"a": 1})
    st.save("k0", [0, 1], {"y": 1.5})
    st.save("k1", [2], {"y": 2.5})
    j = tmp_path / "s" / "journal.jsonl"
    lines = j.read_text().splitlines()
    j.write_text(lines[0] + "\n" + lines[1][:10])         # k1's line torn by a kill
    st2 = ResultStore(tmp_path / "s", {"a": 1}, resume=True)
    assert st2.keys() == {"k0", "k1"}
    assert st2.case_counts() == {0: 1, 1: 1, 2: 1}
    assert [r["event"] for r in st2.journal()] == ["stored", "recovered"]
    res, stats = run_chunks(_square, [1.0, 2.0, 3.0], ["k0", "k1", "k2"], [[0, 1], [2], [3]], store=st2)
    assert res == [{"y": 1.5}, {"y": 2.5}, {"y": 9.0}] and (stats["computed"], stats["reused"]) == (1, 2)
    ResultStore(tmp_path / "s", {"a": 1})                    # without resume: afresh
    assert not list((tmp_path / "s").glob("chunk-*"))


def test_store_errors(tmp_path):
    ResultStore(tmp_path / "s", {"a": 1})
    with pytest.raises(StoreError, match=r"was written for a different sweep \(differs in: a\)"):
        ResultStore(tmp_path / "s", {"a": 2}, resume=True)
    (tmp_path / "s" / "manifest.json").write_text("{not json")
    with pytest.raises(StoreError, match=r"manifest.json: unreadable manifest"):
        ResultStore(tmp_path / "s", {"a": 1}, resume=True)
    with pytest.raises(ValueError, match="chunk keys are not unique"):
        run_chunks(_square, [1, 2], ["k", "k"], [[0], [1]])


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
    with pytest.raises(ValueError, match=r"scheduler: cannot connect to Dask scheduler 'tcp://127.0.0.1:9'"):
        DaskBackend("tcp://127.0.0.1:9", timeout="1s")


def test_process_backend_maps_and_reraises(tmp_path):
    with ProcessBackend(2) as be:
        got = dict(be.imap_unordered(_square, [1.0, 2.0, 3.0]))
        assert got == {0: {"y": 1.0}, 1: {"y": 4.0}, 2: {"y": 9.0}}
        with pytest.raises(WorkerError, match="holds a lock"):
            dict(be.imap_unordered(_fails, [1]))


def test_cli_rejects_bad_worker_count(study, capsys):
    with pytest.raises(SystemExit):
        main(["run", str(study), "--workers", "0"])
    assert "'0' is not a positive integer" in capsys.readouterr().err
