"""The aided kind streams in time (issue 13): Φ, Q_d made chunk by chunk, the same numbers as whole-grid stacks.

Also the filters' own navigation options there: a filter declared without
the Coriolis terms or with the vertical channel decoupled (seed 002 Table 1,
B2, B3, C, D) must be built from the truth's F under those options, not
under the truth's own (the aided kind built C and D with the truth's).
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from covtool.errors import NumericalError
from covtool.lincov.dynamics import DynamicsStream, error_dynamics, HORIZONTAL, NavOptions, VERTICAL
from covtool.lincov.reduced import build_filter
from covtool.lincov.reference import propagate
from covtool.lincov.streamed import ChunkPool, StreamedSystem

ROOT = Path(__file__).resolve().parents[1]
ODO = ROOT / "studies" / "aided_odometer_nhc.toml"


def _counting_make(n=3, seed=0):
    rng = np.random.default_rng(seed)
    calls = []

    def make(a, b):
        calls.append((a, b))
        k = np.arange(a, b, dtype=float)[:, None, None]
        Phi = np.eye(n) + 1e-3 * k * np.ones((n, n))
        Qd = np.broadcast_to(np.eye(n) * (1.0 + k), (b - a, n, n)).copy()
        return Phi, Qd

    return make, calls, rng


def test_streamed_system_holds_chunks_within_the_pool_and_makes_the_others_again():
    make, calls, _ = _counting_make()
    nb = 2 * 10 * 9 * 8                                     # Φ and Q_d of one 10-step chunk of 3 states
    s = StreamedSystem(make, 45, 3, chunk=10, pool=ChunkPool(2 * nb))   # room for two of the five chunks
    first = [(s.Phi[k].copy(), s.Qd[k].copy()) for k in range(45)]
    assert calls == [(0, 10), (10, 20), (20, 30), (30, 40), (40, 45)]
    again = [(s.Phi[k], s.Qd[k]) for k in range(45)]
    # chunks 0 and 1 are held; 2, 3, 4 are made again, in order, on the second pass
    assert calls[5:] == [(20, 30), (30, 40), (40, 45)] and s.made == 8
    for (p, q), (p2, q2) in zip(first, again):
        assert np.array_equal(p, p2) and np.array_equal(q, q2)
    assert s.Phi[44][0, 1] == pytest.approx(1e-3 * 44) and s.Qd[7][2, 2] == 8.0 and s.Phi[-1][0, 1] == s.Phi[44][0, 1]
    assert s.Phi.shape == (45, 3, 3) and len(s.Qd) == 45
    with pytest.raises(ValueError, match="read-only"):
        s.Phi[3][0, 0] = 1.0


def test_streamed_system_without_a_pool_holds_everything():
    make, calls, _ = _counting_make()
    s = StreamedSystem(make, 25, 3, chunk=10)
    for _ in range(3):
        [s.Phi[k] for k in range(25)]
    assert s.made == 3 and len(calls) == 3


def test_streamed_stack_is_read_one_step_at_a_time():
    make, _, _ = _counting_make()
    s = StreamedSystem(make, 25, 3, chunk=10)
    with pytest.raises(TypeError, match="one step at a time"):
        s.Phi[2:5]
    with pytest.raises(IndexError, match=r"step 25 outside 0 … 24"):
        s.Qd[25]
    bad = StreamedSystem(lambda a, b: (np.zeros((b - a, 3, 3)), np.zeros((b - a, 2, 2))), 25, 3, chunk=10)
    with pytest.raises(ValueError, match=r"make\(0, 10\) gave Φ \(10, 3, 3\) and Q_d \(10, 2, 2\)"):
        bad.Phi[0]


def _system(n=6, N=700, seed=1):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(N, n, n)) * 0.05
    Phi = np.eye(n) + A
    G = rng.normal(size=(N, n, n)) * 0.1
    Qd = G @ np.swapaxes(G, 1, 2)
    return Phi, Qd, np.eye(n)


def test_recorded_pure_propagation_equals_the_whole_history_at_its_steps():
    Phi, Qd, P0 = _system()
    full = propagate(Phi, Qd, P0)
    rec = np.array([0, 3, 511, 512, 513, 700, 3])           # across a guard block; unsorted, repeated
    out = propagate(Phi, Qd, P0, record=rec)
    assert out.shape == (6, 6, 6)
    assert np.array_equal(out, full[np.unique(rec)])
    s = StreamedSystem(lambda a, b: (Phi[a:b], Qd[a:b]), 700, 6, chunk=128)
    assert np.array_equal(propagate(s.Phi, s.Qd, P0, record=rec, system_checked=True), out)
    with pytest.raises(ValueError, match=r"record steps must lie in 0 … 700"):
        propagate(Phi, Qd, P0, record=[701])


def test_recorded_pure_propagation_keeps_the_leading_states():
    Phi, Qd, P0 = _system()
    full = propagate(Phi, Qd, P0)
    out = propagate(Phi, Qd, P0, record=[0, 350, 700], keep=4)
    assert out.shape == (3, 4, 4) and np.array_equal(out, full[[0, 350, 700], :4, :4])
    assert np.array_equal(propagate(Phi, Qd, P0, keep=2), full[:, :2, :2])
    with pytest.raises(ValueError, match="keep must be a positive number of states, got 0"):
        propagate(Phi, Qd, P0, keep=0)


def test_a_streamed_chunk_names_the_grid_step_of_a_bad_input():
    """A discretisation error inside a chunk names the step on the whole grid, as the whole-grid call does."""
    from covtool.studies.grid import discretize_chunked
    F = np.zeros((1300, 3, 3))
    F[1250, 0, 1] = np.nan
    Qc = np.zeros_like(F)
    t = np.arange(1301.0)
    with pytest.raises(NumericalError) as whole:
        discretize_chunked(F, Qc, np.ones(1300), "van_loan", what="x", times=t[:-1])
    s = StreamedSystem(lambda a, b: discretize_chunked(F[a:b], Qc[a:b], np.ones(b - a), "van_loan", what="x",
                                                       times=t[a:b], first=a), 1300, 3, chunk=600)
    s.Phi[0]
    with pytest.raises(NumericalError) as streamed:
        s.Phi[1200]
    assert str(streamed.value) == str(whole.value) == "x: step 1250 (t = 1250 s, Δt = 1 s): F has non-finite entries"


def test_recorded_pure_propagation_guards_the_steps_it_does_not_keep():
    Phi, Qd, P0 = _system()
    Qd = Qd.copy()
    Qd[599, 2, 2] = np.nan                                     # P at step 600 is not finite; not recorded
    t = np.arange(701) * 0.5
    with pytest.raises(NumericalError) as whole:
        propagate(Phi, Qd, P0, times=t, system_checked=True)
    with pytest.raises(NumericalError) as rec:
        propagate(Phi, Qd, P0, times=t, system_checked=True, record=[0, 700])
    assert str(rec.value) == str(whole.value) and "t = 300.0 s (5.0 min)" in str(rec.value)


# ---------------------------------------------------------------- the aided kind


def _grid(duration=360.0):
    from covtool.io.filters import load_filters
    from covtool.studies.aided import filters_file
    from covtool.studies.grid import time_grid
    from covtool.studies.inputs import load_trajectory, load_truth, study_header

    decl = tomllib.loads(ODO.read_text())
    where = str(ODO)
    hdr = study_header(decl, where)
    truth = load_truth(decl, where, ODO.parent)
    specs = load_filters(filters_file(decl["filters"], where, ODO.parent), truth)
    traj = load_trajectory(decl, where, ODO.parent, hdr["dt"], duration)
    t = time_grid(duration, hdr["dt"], where)
    return hdr, truth, specs, traj, t, traj.sample(t)


def test_build_filter_refuses_truth_dynamics_under_other_options():
    hdr, truth, specs, traj, t, nodes = _grid(60.0)
    from covtool.studies.grid import midpoint_context
    ctx = midpoint_context(traj, t)
    for dyn in (error_dynamics(truth, ctx), DynamicsStream(truth, ctx, NavOptions())):
        with pytest.raises(ValueError, match=r"filter 'C': its truth dynamics were built under "
                                             r"NavOptions\(coriolis=True, couple_vertical=True\), but the filter "
                                             r"declares NavOptions\(coriolis=False, couple_vertical=False\)"):
            build_filter(specs["C"], truth, ctx, zupt_interval=60.0, truth_dynamics=dyn, dt_steps=np.diff(t))
    # and a chunk of the streamed filter refuses a chunk of the truth's own dynamics
    fm = build_filter(specs["C"], truth, ctx, zupt_interval=60.0, dt_steps=np.diff(t),
                      truth_dynamics=DynamicsStream(truth, ctx, specs["C"].options))
    with pytest.raises(ValueError, match=r"filter 'C': the chunk's truth dynamics were built under "
                                         r"NavOptions\(coriolis=True"):
        fm.chunk(DynamicsStream(truth, ctx, NavOptions()).chunk(0, 10), 0, 10)
    F_f, _ = fm.chunk(DynamicsStream(truth, ctx, specs["C"].options).chunk(0, 10), 0, 10)
    assert F_f.shape == (10, 16, 16)


@pytest.fixture(scope="module")
def aided_systems():
    """Filters A, B1, B2 (vertical decoupled) and C (also no Coriolis) of the odometer study, streamed and whole.

    Filter A keeps every state but is discretised by eq (6b)–(6d) (the library's default), the truth by Van
    Loan: it has a system of its own, streamed like the others.
    """
    from covtool.studies.aided import filter_system
    from covtool.studies.grid import truth_stream, truth_system

    hdr, truth, specs, traj, t, nodes = _grid(1260.0)            # 3 chunks of 600, 600, 60 steps
    kw = dict(ewn_dt=300.0, mean_speed=5.0, update_steps=np.arange(0, t.size, 5))
    ctx, dyn, Phi, Qd = truth_system(truth, traj, t, hdr["discretization"])
    ctx_s, dyn_s, sys_s = truth_stream(truth, traj, t, hdr["discretization"], pool=ChunkPool(0))
    out = {}
    for c in ("A", "B1", "B2", "C"):
        whole = filter_system(specs[c], truth, ctx, dyn, Phi, Qd, hdr, t, nodes, **kw)
        streamed = filter_system(specs[c], truth, ctx_s, dyn_s, sys_s.Phi, sys_s.Qd, hdr, t, nodes,
                                 pool=ChunkPool(0), **kw)
        out[c] = whole, streamed
    return t, (Phi, Qd), sys_s, out


def test_aided_filters_are_built_under_their_own_navigation_options(aided_systems):
    """Decoupled vertical channel: Φ_f has no vertical-from-horizontal entry (F_f has none, and no path
    through the sensor states, whose rows are zero on the navigation states); coupled, it has."""
    t, _, _, out = aided_systems
    V, H = np.array(VERTICAL), np.array(HORIZONTAL)
    steps = [0, 299, 600, 1259]
    for c in ("B2", "C"):
        for Phi_f in (out[c][0][1], out[c][1][1]):
            assert all(np.array_equal(Phi_f[k][np.ix_(V, H)], np.zeros((2, 8))) for k in steps), c
            assert all(np.array_equal(Phi_f[k][np.ix_(H, V)], np.zeros((8, 2))) for k in steps), c
    # B1 couples them: the down velocity feels the latitude (gravity, transport rate) within one step
    assert min(np.abs(out["B1"][1][1][k][np.ix_(V, H)]).max() for k in steps) > 1e-9


def test_streamed_aided_systems_equal_the_whole_grid_stacks(aided_systems):
    t, (Phi, Qd), sys_s, out = aided_systems
    N = t.size - 1
    for k in range(N):
        assert np.array_equal(sys_s.Phi[k], Phi[k]) and np.array_equal(sys_s.Qd[k], Qd[k])
    for c, ((fm, Pw, Qw), (fms, Ps, Qs)) in out.items():
        for k in range(N):                                      # chunk by chunk as on the whole grid: bit for bit
            assert np.array_equal(Ps[k], Pw[k]) and np.array_equal(Qs[k], Qw[k]), (c, k)


def _odo_decl(duration):
    d = tomllib.loads(ODO.read_text())
    d["study"]["duration"] = duration
    d["filters"]["file"] = str(ROOT / "models" / "filters" / "zupt_filters.toml")
    d["output"]["report_times"] = [duration]
    return d


def test_aided_study_is_the_same_whatever_the_pool_holds(monkeypatch):
    """Every table of a 21-min study (three chunks) with no chunk held equals the run that holds them all."""
    import copy

    from covtool.studies import aided

    d = _odo_decl("21 min")
    held = aided.run(copy.deepcopy(d))
    monkeypatch.setattr(aided, "HELD_CHUNKS", 0)
    remade = aided.run(copy.deepcopy(d))
    assert held.tables.keys() == remade.tables.keys()
    for name, df in held.tables.items():
        other = remade.tables[name]
        assert list(df.columns) == list(other.columns), name
        num = df.select_dtypes("number").columns
        assert np.array_equal(df[num].to_numpy(), other[num].to_numpy(), equal_nan=True), name
    # the filters that drop the Coriolis terms and the vertical coupling (C) differ from B1, which keeps them
    s = held.tables["summary"]
    assert s.loc[s["case"] == "C", "CEP [m]"].iloc[0] != s.loc[s["case"] == "B1", "CEP [m]"].iloc[0]


def test_a_grade_frees_its_chunks_before_the_next_grade_makes_any(monkeypatch):
    """Nothing of one grade's streamed systems outlives it (the last run's Φ_f, filter A's = the truth's)."""
    import gc

    from covtool.lincov import streamed
    from covtool.studies import aided

    live = []

    class Pool(streamed.ChunkPool):
        def __init__(self, budget):
            super().__init__(budget)
            gc.collect()                                    # not the unreachable stores of earlier tests
            live.append(sum(isinstance(o, streamed._Store) for o in gc.get_objects()))

    monkeypatch.setattr(aided, "ChunkPool", Pool)
    d = _odo_decl("6 min")
    d["filters"]["cases"] = ["B1", "A"]                     # A last: its Φ_f is its own streamed system
    d["grade"] = [{"name": "navigation", "scale": 1.0}, {"name": "tactical", "scale": 30.0}]
    d["filters"].pop("variant", None)
    aided.run(d)
    assert len(live) == 2 and live[1] == live[0]               # none of the first grade's is left


def test_a_variant_of_a_filter_that_does_not_run_is_refused():
    from covtool.errors import StudyFileError
    from covtool.studies import aided

    d = _odo_decl("6 min")
    d["filters"]["cases"] = ["A"]
    with pytest.raises(StudyFileError, match=r"<study>: \[\[filters.variant\]\] 'B1 no odo SF' base: 'B1' is not "
                                             r"one of the \[filters\] cases \(A\): a variant is tabulated against "
                                             r"its base, which must run"):
        aided.run(d)


def test_bad_chunk_and_keep_are_refused():
    from covtool.lincov.aided import propagate_aided
    make, _, _ = _counting_make()
    with pytest.raises(ValueError, match="chunk must be a positive number of steps, got 0"):
        StreamedSystem(make, 25, 3, chunk=0)
    Phi, Qd, P0 = _system(n=3, N=5)
    with pytest.raises(ValueError, match="filter x: keep must be a positive number of states, got 0"):
        propagate_aided(Phi, Qd, P0, Phi, Qd, P0, np.eye(3), [], keep=0, label="filter x")
