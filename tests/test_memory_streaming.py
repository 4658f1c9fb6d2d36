"""Streaming in time (issue 13, acceptance 2): chunked F, Q_c, Φ, Q_d and a resumable engine.

The streamed propagation (``ZuptSetup.stream`` + ``BatchRun``) must equal the
whole-grid engine and the step-by-step reference, hold nothing of size
N × n², and its memory estimate must follow a measured peak.
"""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import numpy as np
import pytest

from covtool.lincov.batch import BatchRun, events, run_batch, System
from covtool.lincov.dynamics import CompactNoiseSource, error_dynamics, NoiseSource, STREAM_CHUNK
from covtool.lincov.reduced import zupt_matrices
from covtool.lincov.reference import propagate_with_filter
from covtool.nav.attitude import attitude_error_matrix
from memory_peaks import recorded_estimate, traced_peak

ROOT = Path(__file__).resolve().parents[1]
FLAGSHIP = ROOT / "studies" / "zupt_filter_order.toml"


def _decl(duration="11 min", cases=("A", "B1", "D"), impact=()):
    d = tomllib.loads(FLAGSHIP.read_text())
    d["study"]["duration"] = duration
    d["output"]["report_times"] = [duration]
    d["filters"]["cases"] = list(cases)
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["impact"] = {"filters": list(impact)}
    return d


@pytest.fixture(scope="module")
def S():
    """11 min = 660 steps: two chunks of STREAM_CHUNK = 600 steps (the second one short)."""
    from covtool.studies.zupt_setup import setup
    return setup(_decl(), path=FLAGSHIP)


def _physical(P, q):
    T = np.zeros(q.shape[:1] + (9, 10))
    T[:, :6, :6] = np.eye(6)
    T[:, 6:, 6:] = attitude_error_matrix(q)
    return T @ P @ np.swapaxes(T, -1, -2)


def _streamed(S, case, rec):
    fm, _ = S.filter_stream(case)
    ev = S.stream_grid(events(S.t.size - 1, S.update_steps, rec))
    run = BatchRun(ev, S.truth.n, S.P0[None], S.H, S.R, fm.D, S.update_steps, rec, running=True,
                   Pf0=fm.P0[None], Hf=zupt_matrices(fm.names), Rf=S.filter_R(case)[None])
    chunks = 0
    for tsys, fsys in S.stream(ev, [case]):
        run.advance(tsys, fsys[case])
        chunks += 1
    assert chunks == int(np.ceil((S.t.size - 1) / STREAM_CHUNK)) == 2
    return run.finish()


@pytest.mark.parametrize("case", ["B1", "D"])
def test_streamed_run_equals_the_stepwise_reference(S, case):
    """Chunked F, Q_c → Φ, Q_d → composition → BatchRun equals propagate_with_filter to 1e-8 (σ_i σ_j)."""
    N = S.t.size - 1
    rec = np.arange(0, N + 1, 30)
    res = _streamed(S, case, rec)
    fm, Phi_f, Qd_f = S.filter_model(case)                 # whole-grid systems, built only for the reference
    ref = propagate_with_filter(S.Phi, S.Qd, S.P0, Phi_f, Qd_f, fm.P0, S.H, zupt_matrices(fm.names), fm.D, S.R,
                                S.update_steps, Rf=S.filter_R(case))
    q = S.nodes.q_nb[rec]
    a = _physical(res.P_truth[0], q)
    r = _physical(ref.P_truth[rec][:, :10, :10], q)
    d = np.sqrt(np.einsum("kii->ki", r))
    assert (np.abs(a - r) / (d[:, :, None] * d[:, None, :] + 1e-300)).max() < 1e-8
    # and the whole-grid engine on the same event grid: the same numbers to the last bit
    ev = S.stream_grid(events(N, S.update_steps, rec))
    whole = run_batch(System.from_steps(S.Phi, S.Qd, ev), S.P0[None], S.H, S.R, fm.D, S.update_steps, rec,
                      filt=System.from_steps(Phi_f, Qd_f, ev), Pf0=fm.P0[None], Hf=zupt_matrices(fm.names),
                      Rf=S.filter_R(case)[None])
    np.testing.assert_array_equal(res.P_truth, whole.P_truth)
    np.testing.assert_array_equal(res.P_filter, whole.P_filter)


def test_chunked_dynamics_and_filter_systems_equal_the_whole_grid(S):
    """DynamicsStream chunks, FilterModel.chunk and the streamed Φ_f are the whole-grid values exactly."""
    S.release()                                   # nothing whole-grid left from the other tests
    assert S._Phi is None and not S._filters
    dyn = error_dynamics(S.truth, S.ctx)
    ds = S.dynamics_stream(None)
    for a, b in ds.bounds():
        ch = ds.chunk(a, b)
        np.testing.assert_array_equal(ch.F, dyn.F[a:b])
        np.testing.assert_array_equal(ch.Qc, dyn.Qc[a:b])
    np.testing.assert_array_equal(ds.columns([3, 4, 5], [10, 11, 40]).transpose(2, 1, 0),
                                  dyn.F[:, [3, 4, 5]][:, :, [10, 11, 40]])
    fs, reused = S.filter_stream("B1")
    assert not reused and fs.F is None and fs.Qc is None
    assert all(isinstance(s, CompactNoiseSource) for s in fs.ewn_noise) and len(fs.ewn_noise) == 36
    fm, Phi_f, _ = S.filter_model("B1")
    F, Qc = fs.chunk(S.dynamics_stream(fs.spec.options).chunk(600, 660), 600, 660)
    np.testing.assert_array_equal(F, fm.F[600:660])
    np.testing.assert_array_equal(Qc, fm.Qc[600:660])
    np.testing.assert_array_equal(fs.P0, fm.P0)
    from covtool.studies.zupt_setup import StreamedTransitions
    st = StreamedTransitions(S, "B1")
    assert st.shape == Phi_f.shape
    for k in (659, 0, 599, 600, -1):
        np.testing.assert_array_equal(st[k], Phi_f[k])
    assert S.filter_stream("A") == (S.filter_stream("A")[0], True)      # the truth's own Φ, Q_d


def test_compact_noise_source_is_the_full_one():
    rng = np.random.default_rng(3)
    G = np.zeros((7, 6, 2))
    G[:, [1, 4], :] = rng.standard_normal((7, 2, 2))
    psd = rng.random((7, 2))
    full, comp = NoiseSource("x", G, psd), NoiseSource("x", G, psd).compact()
    assert comp.G_rows.shape == (7, 2, 2) and list(comp.rows) == [1, 4]
    np.testing.assert_array_equal(comp.G, G)
    np.testing.assert_array_equal(comp.qc(), full.qc())
    Q = np.zeros((3, 6, 6))
    comp.add_qc(Q, 2, 5)
    np.testing.assert_array_equal(Q, full.qc()[2:5])


def test_batch_run_refuses_a_chunk_that_does_not_continue(S):
    N = S.t.size - 1
    rec = [0, N]
    ev = S.stream_grid(events(N, S.update_steps, rec))
    args = (ev, S.truth.n, S.P0[None], S.H, S.R, np.zeros((S.truth.n, 0)), [], rec)
    kw = dict(running=False, gains=np.zeros((1, 0, 0, 3)))
    gen = S.stream(ev, [])
    first, _ = next(gen)
    second, _ = next(gen)
    run = BatchRun(*args, **kw)
    with pytest.raises(ValueError, match=r"chunk from step 600 does not continue the event grid at step 0"):
        run.advance(second)
    run = BatchRun(*args, **kw)
    run.advance(first)
    with pytest.raises(ValueError, match=r"finished at step 600, before the end of its event grid \(step 660\)"):
        run.finish()
    run = BatchRun(*args, **kw)
    run.advance(first)
    run.advance(second)
    res = run.finish()
    assert res.P_truth.shape == (1, 2, 10, 10) and run.finish() is res
    with pytest.raises(ValueError, match="the batch is finished"):
        run.advance(second)
    with pytest.raises(TypeError, match=r"unknown keywords \['Pf'\]"):
        BatchRun(*args, Pf=None, **kw)
    with pytest.raises(ValueError, match=r"the event grid lacks the chunk boundaries 0, 600 \(use stream_grid\)"):
        next(S.stream(np.array([0, 330, 660]), []))


def test_streamed_study_equals_the_whole_grid_study():
    """The flagship without the impact table streams; with it the systems are whole: same summary and histories."""
    import covtool
    streamed = covtool.run_study(_decl("11 min", ("A", "B1", "C")))
    whole = covtool.run_study(_decl("11 min", ("A", "B1", "C"), impact=("C",)))
    for name in ("summary", "history", "equivalent_noise"):
        a, b = streamed.tables[name], whole.tables[name]
        num = a.select_dtypes("number").columns
        np.testing.assert_array_equal(a[num].to_numpy(), b[num].to_numpy())


@pytest.mark.parametrize("budget", [None, 1])
def test_stream_keeps_the_filters_transitions_for_the_equivalent_noise_table(budget, monkeypatch):
    """The reduced filters' Φ_f chunks of the propagation's stream serve the equivalent-noise table
    (ZuptSetup._keep, StreamedTransitions) within KEPT_TRANSITIONS bytes: the same table as the whole-grid
    study's, element for element, with the chunks kept (11 min: all of them) or with none fitting the budget
    (every chunk computed again)."""
    import covtool
    import covtool.studies.zupt_setup as zs

    if budget is not None:
        monkeypatch.setattr(zs, "KEPT_TRANSITIONS", budget)
    made = []
    discretise = zs.ZuptSetup._discretise_filter
    monkeypatch.setattr(zs.ZuptSetup, "_discretise_filter",
                        lambda self, name, dyn, a, b, **kw: made.append((name, a)) or discretise(self, name, dyn, a, b, **kw))
    streamed = covtool.run_study(_decl("11 min", ("A", "B1", "C")))
    whole = covtool.run_study(_decl("11 min", ("A", "B1", "C"), impact=("C",)))
    a, b = streamed.tables["equivalent_noise"], whole.tables["equivalent_noise"]
    num = a.select_dtypes("number").columns
    np.testing.assert_array_equal(a[num].to_numpy(), b[num].to_numpy())
    # each reduced filter's two chunks: discretised once by the stream and taken by the table as they were,
    # or, with nothing kept, discretised again by the table
    per_chunk = [(c, a0) for c in ("B1", "C") for a0 in (0, 600)]
    assert sorted(made) == sorted(per_chunk * (1 if budget is None else 2))


def test_chunk_constants_agree():
    from covtool.lincov.guard import _CHUNK
    from covtool.studies.resources import DISCRETIZE_CHUNK, GUARD_CHUNK, STREAM_CHUNK as RES_CHUNK
    assert RES_CHUNK == STREAM_CHUNK and STREAM_CHUNK % DISCRETIZE_CHUNK == 0
    assert GUARD_CHUNK == _CHUNK


def _order_estimate(path, impact=True):
    from covtool.io.filters import load_filters
    from covtool.studies.inputs import load_truth, output_options, study_config, study_header
    from covtool.studies.resources import steps_of
    from covtool.studies.zupt_setup import (filter_cases, filter_dynamics, filters_file, history_records,
                                            order_memory, system_key, truth_copy, zupt_options,
                                            zupt_update_count)
    decl = tomllib.loads(path.read_text())
    where = str(path)
    cfg = study_config(decl, where)
    hdr = study_header(cfg, where)
    every, rtimes = output_options(cfg, where, hdr["duration"])
    truth, ftruth = load_truth(cfg, where, path.parent, for_filters=True)
    specs = load_filters(filters_file(cfg.filters, where, path.parent), truth)
    cases = filter_cases(cfg.filters, specs, None, where)
    N = steps_of(hdr["duration"], hdr["dt"])
    zo = zupt_options(cfg.zupt, where, hdr["dt"], hdr["duration"])
    rec, K = history_records(N, hdr["dt"], every, rtimes, zupt_update_count(zo, hdr["duration"]))
    shared = sum(1 for c in cases if truth_copy(specs[c], truth, ftruth))
    keys = []
    for c in cases:
        if not truth_copy(specs[c], truth, ftruth) and system_key(specs[c]) not in keys:
            keys.append(system_key(specs[c]))
    args = (N, truth, [specs[c].n for c in cases], filter_dynamics(specs, cases))
    kw = dict(records=rec, intervals=K, shared=shared, distinct=[k.n for k in keys],
              updates=zupt_update_count(zo, hdr["duration"]), reports=len(rtimes))
    return order_memory(True, False)(*args, **kw), order_memory(True, impact)(*args, **kw)


def test_long_studies_fit_the_memory_check(monkeypatch):
    """Streamed, with the dropped-state impact table in both of its processes: 6 h × 6 cases ~1.7 GB, 24 h × 20
    cases ~5.5 GB (~1.1 and ~4 GB without it); over the whole grid they needed ~7 GB and more than 24 GB (refused)."""
    import covtool.studies.zupt_setup as zs

    six, six_imp = _order_estimate(ROOT / "benchmarks" / "long" / "zupt_filter_order_6h.toml")
    day, day_imp = _order_estimate(ROOT / "benchmarks" / "long" / "zupt_filter_order_24h.toml")
    assert six["steps"] == 21600 and day["steps"] == 86400
    assert six["layout"] == six_imp["layout"] == day_imp["layout"] == "streamed"
    assert six["bytes"] < 1.1e9 and six_imp["bytes"] < 2e9
    assert day["bytes"] < 4e9 and day_imp["bytes"] < 6e9
    monkeypatch.setattr(zs, "WHOLE_GRID_BYTES", float("inf"))             # the impact's systems over the grid
    monkeypatch.setattr(zs, "memory_limit", lambda max_memory=None: (float("inf"), "test"))
    six_whole, day_whole = (_order_estimate(ROOT / "benchmarks" / "long" / f)[1]
                            for f in ("zupt_filter_order_6h.toml", "zupt_filter_order_24h.toml"))
    assert six_whole["layout"] == day_whole["layout"] == "whole grid"
    assert six_whole["bytes"] > 5e9 and day_whole["bytes"] > 24 * 2**30


def test_stream_memory_estimate_follows_the_measured_peak():
    """A 40-min, 6-case streamed study: the estimate bounds the measured peak, within a factor 3.

    Measured with ``tracemalloc`` (every numpy and Python allocation of the
    run, deterministic, unlike the RSS of a process that shares its
    allocator pools with a test session; the RSS of the 6-h run is in the
    benchmark, ``benchmarks/run.py --long``).  The estimate counts every
    chunk array as live at once, so it must be an upper bound, and not by
    more than a factor 3.
    """
    import covtool
    d = _decl("40 min", ("A", "B1", "B2", "B3", "C", "D"))
    d["output"]["history_every"] = "10 s"
    d["trajectory"] = {"builtin": "land_vehicle", "cycles": 8, "distance": "20 km"}     # the flagship's speed
    r, peak = traced_peak(lambda: covtool.run_study(d))
    est = recorded_estimate(r)
    assert 0 < peak <= est <= 3.0 * peak, (peak, est)


def test_streamed_impact_estimate_bounds_the_traced_peak(monkeypatch):
    """The flagship with its dropped-state impact table in the streamed layout (21 min, three chunks): the
    estimate bounds the traced peak (under tracemalloc the forked share runs in this process, one after the
    other; the estimate counts both processes' chunks at once), and not by more than a factor 5."""
    import covtool
    import covtool.studies.zupt_setup as zs
    from memory_peaks import recorded_estimate, traced_peak

    monkeypatch.setattr(zs, "WHOLE_GRID_BYTES", 0.0)
    d = _decl("21 min", ("A", "B1", "D"), impact=("B1", "D"))
    r, peak = traced_peak(lambda: covtool.run_study(copy.deepcopy(d)), warm=True)
    est = recorded_estimate(r)
    assert set(r.tables["impact"]["filter"]) == {"B1", "D"}
    assert 0 < peak <= est <= 5.0 * peak, (peak, est)


def test_the_estimate_counts_the_listed_impact_filters():
    """[impact] filters = ["B1", "C", "D"] of the 24-h study's 19 reduced cases: the estimate lies between no
    impact table and one for every reduced case, and grows with the count."""
    path = ROOT / "benchmarks" / "long" / "zupt_filter_order_24h.toml"
    none, one, three, every = (_order_estimate(path, k)[1]["bytes"] for k in (0, 1, 3, True))
    assert none < one < three < every


def test_the_layout_fits_the_memory_limit():
    """A 47-min flagship holds its whole grid (about 0.98 GB estimated) under a roomy limit, but streams (about
    0.8 GB) when [study] max_memory leaves room for the streamed layout only, instead of being refused (found in
    review); the layout is recorded in the provenance."""
    import covtool.studies.zupt_setup as zs
    from covtool.studies.resources import resource_provenance
    from covtool.studies.zupt_setup import setup, order_memory

    d = _decl("47 min", ("A", "B1", "B2", "B3", "C", "D"), impact=("B1", "C", "D"))
    d["trajectory"] = {"builtin": "land_vehicle", "cycles": 10, "distance": "25 km"}
    d["study"]["max_memory"] = "4 GB"
    roomy = setup(copy.deepcopy(d), path=FLAGSHIP, memory=order_memory(True, 3)).resources
    assert roomy["layout"] == "whole grid" and roomy["bytes"] < zs.WHOLE_GRID_BYTES
    d["study"]["max_memory"] = f"{(roomy['bytes'] - 1e6) / 1e9:.3f} GB"
    tight = setup(copy.deepcopy(d), path=FLAGSHIP, memory=order_memory(True, 3)).resources
    assert tight["layout"] == "streamed" and tight["bytes"] < roomy["bytes"] - 1e6
    assert resource_provenance(tight)["memory_layout"] == "streamed"
    assert resource_provenance(roomy)["memory_layout"] == "whole grid"
