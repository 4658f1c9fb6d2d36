"""Recorded truth-under-filter runs and the Monte Carlo study's memory (issue 13).

A run that keeps the navigation block of every step and the whole
covariance at some steps only (``record``, ``all_steps``) must give exactly
the numbers of the whole history at those steps, guard every covariance it
does not keep with the same message, and accept systems streamed a chunk at a
time; the Monte Carlo study uses these and must not hold anything of size
duration × n².
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from covtool.errors import NumericalError
from covtool.lincov.history import AtSteps
from covtool.lincov.reference import GUARD_STEPS, propagate_with_filter
from covtool.lincov.streamed import StreamedSystem
from covtool.validation.feedback import FeedbackFilter

ROOT = Path(__file__).resolve().parents[1]


def _filter_system(N=700, n=8, nf=5, seed=3):
    """A truth of n states with a filter on its first nf (velocity-like rows 0..2 measured)."""
    rng = np.random.default_rng(seed)
    Phi = np.eye(n) + rng.normal(size=(N, n, n)) * 0.03
    G = rng.normal(size=(N, n, n)) * 0.05
    Qd = G @ np.swapaxes(G, 1, 2)
    Phi_f = Phi[:, :nf, :nf].copy()
    Qd_f = Qd[:, :nf, :nf] * 1.3
    H = np.zeros((3, n))
    H[:, :3] = np.eye(3)
    Hf = H[:, :nf].copy()
    D = np.zeros((n, nf))
    D[:nf, :nf] = np.eye(nf)
    R = np.eye(3) * 0.01
    upd = list(range(50, N, 37))
    return dict(Phi=Phi, Qd=Qd, P0=np.eye(n), Phi_f=Phi_f, Qd_f=Qd_f, Pf0=np.eye(nf) * 1.2, H=H, Hf=Hf, D=D, R=R,
                update_steps=upd)


def _run(s, **kw):
    return propagate_with_filter(s["Phi"], s["Qd"], s["P0"], s["Phi_f"], s["Qd_f"], s["Pf0"], s["H"], s["Hf"],
                                 s["D"], s["R"], s["update_steps"], **kw)


def test_recorded_filter_run_equals_the_whole_history_bit_for_bit():
    s = _filter_system()
    whole = _run(s)
    rec = np.array([0, 50, 511, 512, 513, 700, 50])         # across a guard block; unsorted, repeated
    out = _run(s, record=rec, all_steps=4)
    steps = np.unique(rec)
    assert np.array_equal(out.record_steps, steps)
    assert np.array_equal(out.P_truth, whole.P_truth[steps])
    assert np.array_equal(out.P_filter, whole.P_filter[steps])
    assert np.array_equal(out.every_truth, whole.P_truth[:, :4, :4])
    assert np.array_equal(out.every_filter, whole.P_filter[:, :4, :4])
    assert out.gains.keys() == whole.gains.keys()
    assert all(np.array_equal(out.gains[k], whole.gains[k]) for k in whole.gains)
    assert out.prior_truth == {} and out.prior_filter == {}
    # streamed systems (read one step at a time, chunk by chunk): the same numbers
    T = StreamedSystem(lambda a, b: (s["Phi"][a:b], s["Qd"][a:b]), 700, 8, chunk=128)
    F = StreamedSystem(lambda a, b: (s["Phi_f"][a:b], s["Qd_f"][a:b]), 700, 5, chunk=128)
    st = propagate_with_filter(T.Phi, T.Qd, s["P0"], F.Phi, F.Qd, s["Pf0"], s["H"], s["Hf"], s["D"], s["R"],
                               s["update_steps"], system_checked=True, record=rec, all_steps=4)
    assert np.array_equal(st.P_truth, out.P_truth) and np.array_equal(st.every_filter, out.every_filter)
    with pytest.raises(ValueError, match=r"record steps must lie in 0 … 700"):
        _run(s, record=[701])
    with pytest.raises(ValueError, match="all_steps must be a positive number of states, got 0"):
        _run(s, all_steps=0)


@pytest.mark.parametrize("where", ["truth", "filter"])
def test_recorded_filter_run_guards_the_steps_it_does_not_keep(where):
    # a non-finite Q_d at a step in the second guard block (not recorded): the same message as the whole run
    s = _filter_system()
    key = "Qd" if where == "truth" else "Qd_f"
    s[key] = s[key].copy()
    s[key][GUARD_STEPS + 40, 1, 1] = np.nan
    t = np.arange(701) * 0.5
    with pytest.raises(NumericalError) as whole:
        _run(s, times=t, system_checked=True)
    with pytest.raises(NumericalError) as rec:
        _run(s, times=t, system_checked=True, record=[0, 700], all_steps=3)
    assert str(rec.value) == str(whole.value)
    assert f"t = {(GUARD_STEPS + 41) * 0.5:.1f} s" in str(rec.value)


def _zupt_design(record=None, all_steps=None):
    from covtool.nav.strapdown import NAV_STATES

    s = _filter_system(n=10, nf=10)
    t = np.arange(701) * 0.5
    return FeedbackFilter.design("F", NAV_STATES, s["Phi_f"], s["Qd_f"], s["Pf0"], s["R"], s["update_steps"],
                                 times=t, record=record, all_steps=all_steps)


def test_recorded_feedback_design_keeps_the_whole_designs_numbers():
    whole = _zupt_design()
    rec = [0, 87, 512, 700]
    out = _zupt_design(record=rec, all_steps=6)
    assert np.array_equal(out.record_steps, rec)
    assert np.array_equal(out.P, whole.P[rec])
    assert np.array_equal(out.every, whole.P[:, :6, :6])
    assert all(np.array_equal(out.gains[k], whole.gains[k]) for k in whole.gains) and out.gains.keys() == whole.gains.keys()
    # the checks of every recorded run (covtool.lincov.reference.record_plan)
    with pytest.raises(ValueError, match=r"^Monte Carlo filter F: record steps must lie in 0 … 700, got 0 … 701$"):
        _zupt_design(record=[0, 701])
    with pytest.raises(ValueError, match=r"^Monte Carlo filter F: all_steps must be a positive number of states, "
                                         r"got 0$"):
        _zupt_design(all_steps=0)


def test_at_steps_reads_by_grid_step_and_names_a_step_it_lacks():
    P = np.arange(3 * 4).reshape(3, 2, 2).astype(float)
    a = AtSteps([5, 9, 40], P)
    assert np.array_equal(a[9], P[1]) and np.array_equal(a[np.int64(40)], P[2])
    with pytest.raises(KeyError, match="grid step 6 was not kept"):
        a[6]
    with pytest.raises(ValueError, match="2 steps for 3 covariances"):
        AtSteps([1, 2], P)
    with pytest.raises(ValueError, match="the steps of the kept covariances must increase"):
        AtSteps([5, 5, 40], P)


def test_the_chunk_pool_is_set_before_the_first_streamed_system():
    from covtool.studies.zupt_setup import setup

    path = ROOT / "studies" / "monte_carlo_validation.toml"
    S = setup(tomllib.loads(path.read_text()), path=path, extra_sections=("monte_carlo",))
    S.hold_chunks(2**20)
    T = S.streamed_system()
    T.Phi[0]
    assert S._dyn_cache[("streamed pool",)].budget == 2**20
    with pytest.raises(RuntimeError, match="^hold_chunks: the streamed systems' pool is already in use$"):
        S.hold_chunks(2**30)


def test_monte_carlo_memory_does_not_grow_with_duration_times_n_squared():
    """The memory check's estimate of the Monte Carlo, per added grid step (streamed layout): no part grows by
    one 58 × 58 covariance (27 kB) a step, where the whole-grid analysis held F, Q_c, Φ, Q_d and three
    truth histories (seven a step); the whole covariances are kept at the NEES steps only."""
    from covtool.studies.inputs import load_truth
    from covtool.studies.monte_carlo import _memory, mc_options

    decl = tomllib.loads((ROOT / "studies" / "monte_carlo_validation.toml").read_text())
    truth = load_truth({"truth": {"model": "sdins58"}}, "<test>", None)

    def growth(nees_every):
        decl["monte_carlo"]["nees_every"] = nees_every
        mem = _memory(mc_options(decl, "mc"), 1.0)
        a = mem(20000, truth, [58, 22, 16, 10], 2, max_memory=1000.0)
        b = mem(40000, truth, [58, 22, 16, 10], 2, max_memory=1000.0)
        assert a["layout"].startswith("streamed") and b["layout"].startswith("streamed")
        assert b["parts"]["held chunks of the systems"] == a["parts"]["held chunks of the systems"]
        return {k: (b["parts"][k] - a["parts"][k]) / 20000 for k in a["parts"]}

    every10, every100 = growth("10 s"), growth("100 s")
    # (the ensemble's reference is the trajectory at the IMU rate: 100 samples a step, whatever n)
    assert max(v for k, v in every10.items() if k != "ensemble reference") < 58 * 58 * 8, every10
    # the whole covariances are kept at the NEES steps: a tenth of those steps, a tenth of that share (the
    # navigation blocks of every step stay)
    share = 3 * 2 * 58 * 58 * 8
    assert every10["recorded covariances"] - every100["recorded covariances"] == pytest.approx((0.1 - 0.01) * share,
                                                                                              rel=0.01)


@pytest.mark.parametrize("step", [511, 512, 1023])
@pytest.mark.parametrize("where", ["truth", "filter"])
def test_a_bad_covariance_at_a_guard_block_boundary_keeps_the_whole_runs_message(step, where):
    # the last step of a block (511), the first of the next (512) and the run's last (N + 1 = 1024 steps):
    # the block's guard runs inside the loop there, and must not be taken for a gain that cannot be formed
    s = _filter_system(N=1023)
    key = "Qd" if where == "truth" else "Qd_f"
    s[key] = s[key].copy()
    s[key][step - 1, 1, 1] = np.nan
    with pytest.raises(NumericalError) as whole:
        _run(s, system_checked=True)
    with pytest.raises(NumericalError) as rec:
        _run(s, system_checked=True, record=[0, 1023], all_steps=3)
    assert str(rec.value) == str(whole.value) and "gain" not in str(rec.value)
    assert f"at step {step}:" in str(rec.value)


@pytest.mark.parametrize("step", [511, 512, 601])
@pytest.mark.parametrize("times", [True, False])
def test_recorded_feedback_design_keeps_the_whole_designs_message(step, times):
    from covtool.nav.strapdown import NAV_STATES

    s = _filter_system(N=1023, n=10, nf=10)
    s["Qd_f"] = s["Qd_f"].copy()
    s["Qd_f"][step - 1, 4, 4] = np.nan
    t = np.arange(1024) * 0.5 if times else None

    def design(**kw):
        return FeedbackFilter.design("F", NAV_STATES, s["Phi_f"], s["Qd_f"], s["Pf0"], s["R"], s["update_steps"],
                                     times=t, system_checked=True, **kw)

    with pytest.raises(NumericalError) as whole:
        design()
    with pytest.raises(NumericalError) as rec:
        design(record=[0, 1023], all_steps=3)
    assert str(rec.value) == str(whole.value) and "gain" not in str(rec.value)
    assert (f"t = {step * 0.5:.1f} s" if times else f"(matrix ({step},))") in str(rec.value)


def test_a_streamed_systems_own_guard_passes_through_the_feedback_design():
    from covtool.errors import SystemCheckError
    from covtool.nav.strapdown import NAV_STATES

    s = _filter_system(N=700, n=10, nf=10)

    def make(a, b):
        if a <= 600 < b:
            raise NumericalError("filter F: Q_f not finite at step 600")
        return s["Phi_f"][a:b], s["Qd_f"][a:b]

    F = StreamedSystem(make, 700, 10, chunk=100)
    with pytest.raises(SystemCheckError, match=r"^filter F: Q_f not finite at step 600$"):
        FeedbackFilter.design("F", NAV_STATES, F.Phi, F.Qd, s["Pf0"], s["R"], s["update_steps"],
                              times=np.arange(701.0), system_checked=True, record=[0, 700])
    with pytest.raises(ValueError, match="a streamed system is guarded as it is made; pass system_checked=True"):
        FeedbackFilter.design("F", NAV_STATES, F.Phi, F.Qd, s["Pf0"], s["R"], s["update_steps"], record=[0])


def test_a_recorded_run_refuses_to_be_read_as_a_history():
    s = _filter_system()
    out = _run(s, record=[0, 700], all_steps=4)
    with pytest.raises(ValueError, match="a recorded run keeps the covariances of record_steps only"):
        out.truth_history()
    with pytest.raises(ValueError, match="a recorded run"):
        out.filter_history()
    g = out.gain_table()                               # the gains of every update, at the grid's times
    assert np.array_equal(g["times"], np.asarray(s["update_steps"], float))
    assert g["K"].shape == (len(s["update_steps"]), 5, 3)


def test_two_readers_of_a_streamed_system_make_each_chunk_once_each():
    # the Monte Carlo's analyses and its null read the truth in two threads; with no chunk held by the
    # pool, each reader makes each chunk once (the last two read are kept), not once per alternation
    from covtool.lincov.streamed import ChunkPool

    s = _filter_system(N=700)
    sysm = StreamedSystem(lambda a, b: (s["Phi"][a:b], s["Qd"][a:b]), 700, 8, chunk=100, pool=ChunkPool(0))
    for k in range(700):
        sysm.Phi[k]                                    # one reader, in order
        sysm.Qd[(k + 350) % 700]                       # the other, three and a half chunks apart
    assert sysm.made == 7 + 8                          # every chunk for each (the second starts mid-chunk)
