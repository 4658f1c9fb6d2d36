"""Per-source noise composition over event intervals (issue 13): reach sets and pairwise reduction.

:func:`covtool.lincov.noise.compose_scan` reduces each interval pairwise
instead of step by step, and :func:`covtool.lincov.noise.compose_noise`
composes each source on the states it reaches only.  Both are exact
rearrangements: checked against the step-by-step composition
(:func:`covtool.lincov.batch.compose`) and against the same composition on
the whole state space, at round-off tolerances.
"""

from __future__ import annotations

import numpy as np
import pytest

from covtool.lincov.batch import compose
from covtool.lincov.discretize import van_loan
from covtool.lincov.dynamics import NoiseSource
from covtool.lincov.noise import _compose_block, compose_noise, compose_scan, compose_transition, reached_states


def _psd(rng, N, n):
    A = rng.standard_normal((N, n, n))
    return A @ np.swapaxes(A, 1, 2)


@pytest.mark.parametrize("ev", [[0, 37], [0, 3, 4, 9, 37], [0, 1, 2, 36, 37]])
@pytest.mark.parametrize("chunk", [None, 1, 5, 8])
def test_pairwise_reduction_equals_the_step_by_step_composition(ev, chunk):
    rng = np.random.default_rng(11)
    N, n = 37, 5
    Phi = np.eye(n) + 0.1 * rng.standard_normal((N, n, n))
    Q = _psd(rng, N, n)
    ev = np.array(ev)
    P1, Q1 = compose(Phi, Q, ev)
    P2, Q2 = compose_scan(Phi, Q, ev, chunk=chunk)
    np.testing.assert_allclose(P2, P1, rtol=1e-13, atol=1e-13 * np.abs(P1).max())
    np.testing.assert_allclose(Q2, Q1, rtol=1e-13, atol=1e-13 * np.abs(Q1).max())
    np.testing.assert_array_equal(Q2, np.swapaxes(Q2, 1, 2))                  # symmetric
    np.testing.assert_allclose(compose_transition(Phi, ev), P1, rtol=1e-13, atol=1e-13 * np.abs(P1).max())
    Q3 = compose_scan(Phi, np.stack([Q, 2.0 * Q], axis=1), ev, chunk=chunk)[1]  # several sources at once
    np.testing.assert_allclose(Q3[:, 1], 2.0 * Q3[:, 0], rtol=1e-15, atol=0)


def test_reached_states_follow_the_couplings():
    P = np.zeros((5, 5), bool)
    P[0, 3] = P[1, 0] = P[2, 4] = True                  # 3 drives 0, 0 drives 1, 4 drives 2
    assert reached_states(P, np.eye(5, dtype=bool)[3]).tolist() == [True, True, False, True, False]
    assert reached_states(P, np.zeros(5, bool)).tolist() == [False] * 5


def test_sources_composed_on_their_reach_sets_equal_the_whole_space_composition():
    """A 3-state navigation-like block driven by two sensor states (a random constant and a Markov state)."""
    rng = np.random.default_rng(5)
    N, n = 40, 6
    F = np.zeros((N, n, n))
    F[:, :3, :3] = 0.02 * rng.standard_normal((N, 3, 3))
    F[:, :3, 3] = rng.standard_normal((N, 3))             # sensor 3 (random constant) drives the nav block
    F[:, :3, 4] = rng.standard_normal((N, 3))             # sensor 4 (Markov) too
    F[:, 4, 4] = -1 / 50.0
    F[:, 5, 5] = -1 / 20.0                                # state 5 drives nothing and is driven by nothing
    dt = 1.0
    Phi = van_loan(F, np.zeros_like(F), dt)[0]
    e = np.eye(n)
    factors = [NoiseSource("vrw", np.broadcast_to(e[:, :3], (N, n, 3)), np.full((N, 3), 1e-4)),
               NoiseSource("markov 4", np.broadcast_to(e[:, 4:5], (N, n, 1)), np.full((N, 1), 2e-6)),
               NoiseSource("markov 5", np.broadcast_to(e[:, 5:6], (N, n, 1)), np.full((N, 1), 3e-6)),
               NoiseSource("zero", np.zeros((N, n, 1)), np.ones((N, 1)))]
    ev = np.array([0, 10, 25, 40])
    got = compose_noise(Phi, F, factors, dt, ev)
    ref = _compose_block(Phi, F, factors, dt, ev, 1000)   # every source on the whole space
    for j in range(len(factors)):
        scale = max(np.abs(ref[j]).max(), 1e-300)
        np.testing.assert_allclose(got[j], ref[j], rtol=1e-12, atol=1e-13 * scale, err_msg=factors[j].name)
    assert not got[1][:, 5].any() and not got[2][:, :5].any() and not got[3].any()   # zero outside the reach
    assert got[2][-1, 5, 5] > 0


def test_shared_compositions_are_reused_only_for_the_same_source_system_and_states():
    """A subspace that holds a source's reach set takes its composition from the cache (issue 13).

    The oracle is the same composition computed afresh on the subspace; a
    changed PSD or another system must be computed, not reused.
    """
    from covtool.lincov.noise import ComposedCache

    rng = np.random.default_rng(8)
    N, n = 30, 6
    F = np.zeros((N, n, n))
    F[:, :3, :3] = 0.02 * rng.standard_normal((N, 3, 3))
    F[:, :3, 3] = rng.standard_normal((N, 3))
    F[:, :3, 4] = rng.standard_normal((N, 3))
    F[:, 4, 4] = -1 / 50.0
    F[:, 5, 5] = -1 / 20.0
    dt = 1.0
    Phi = van_loan(F, np.zeros_like(F), dt)[0]
    e = np.eye(n)
    factors = [NoiseSource("vrw", np.broadcast_to(e[:, :3], (N, n, 3)), np.full((N, 3), 1e-4)),
               NoiseSource("markov 4", np.broadcast_to(e[:, 4:5], (N, n, 1)), np.full((N, 1), 2e-6)),
               NoiseSource("markov 5", np.broadcast_to(e[:, 5:6], (N, n, 1)), np.full((N, 1), 3e-6))]
    ev = np.array([0, 7, 30])
    cache = ComposedCache()
    full = compose_noise(Phi, F, factors, dt, ev, cache=cache, system="truth")
    assert cache.hits == 0 and len(cache.store) == 3
    rows = np.array([0, 1, 2, 4])                                  # a "filter" without states 3 and 5
    sub = [NoiseSource(f.name, f.G[:, rows], f.psd) for f in factors[:2]]
    P_s, F_s = Phi[:, rows][:, :, rows], F[:, rows][:, :, rows]
    got = compose_noise(P_s, F_s, sub, dt, ev, cache=cache, system="truth", rows=rows)
    assert cache.hits == 2                                         # both reach sets lie in the subspace
    ref = compose_noise(P_s, F_s, sub, dt, ev)                     # computed afresh
    for j in range(2):
        np.testing.assert_allclose(got[j], ref[j], rtol=1e-14, atol=1e-14 * np.abs(ref[j]).max())
        np.testing.assert_array_equal(got[j], full[j][:, rows[:, None], rows[None, :]])
    # another PSD, or another system: computed, not taken
    other = [NoiseSource("vrw", sub[0].G, 2.0 * sub[0].psd)]
    q2 = compose_noise(P_s, F_s, other, dt, ev, cache=cache, system="truth", rows=rows)
    np.testing.assert_allclose(q2[0], 2.0 * ref[0], rtol=1e-13, atol=1e-14 * np.abs(ref[0]).max())
    compose_noise(P_s, F_s, sub[:1], dt, ev, cache=cache, system="filter options", rows=rows)
    assert cache.hits == 2


def _with_constants(rng, N, nd, nc):
    """Per-step Φ with ``nc`` random-constant states (identity rows) driving ``nd`` dynamic ones, permuted."""
    n = nd + nc
    F = np.zeros((N, n, n))
    F[:, :nd, :] = 0.05 * rng.standard_normal((N, nd, n))
    Phi = van_loan(F, np.zeros_like(F), 1.0)[0]
    perm = rng.permutation(n)                               # the constants anywhere, not trailing
    Phi = Phi[:, perm[:, None], perm[None, :]]
    d = np.sort(np.flatnonzero(perm < nd))
    return Phi, d


@pytest.mark.parametrize("chunk", [None, 1, 7])
def test_random_constants_are_composed_on_the_dynamic_rows_exactly(chunk):
    """Identity rows of Φ (random constants) keep that form: the structured reduction equals the steps.

    Oracle: :func:`covtool.lincov.batch.compose`, step by step.  A ``Q`` that
    reaches a constant's row must take the dense reduction, and still agree.
    """
    from covtool.lincov.batch import dynamic_states
    from covtool.lincov.noise import _constant_rows

    rng = np.random.default_rng(21)
    N, nd, nc = 40, 4, 7
    Phi, d = _with_constants(rng, N, nd, nc)
    n = nd + nc
    ev = np.array([0, 1, 6, 17, 40])
    assert np.array_equal(dynamic_states(Phi)[0], d)
    Qdd = _psd(rng, N, nd)
    Q = np.zeros((N, n, n))
    Q[:, d[:, None], d[None, :]] = Qdd
    assert _constant_rows(Phi, Q, ev) is not None
    P1, Q1 = compose(Phi, Q, ev)
    P2, Q2 = compose_scan(Phi, Q, ev, chunk=chunk)
    np.testing.assert_allclose(P2, P1, rtol=1e-13, atol=1e-13 * np.abs(P1).max())
    np.testing.assert_allclose(Q2, Q1, rtol=1e-13, atol=1e-13 * np.abs(Q1).max())
    c = np.setdiff1d(np.arange(n), d)
    np.testing.assert_array_equal(P2[:, c], np.broadcast_to(np.eye(n)[c], (len(ev) - 1, c.size, n)))
    assert not Q2[:, c].any() and not Q2[:, :, c].any()
    np.testing.assert_allclose(compose_transition(Phi, ev), P1, rtol=1e-13, atol=1e-13 * np.abs(P1).max())
    # two sources at once, the second twice the first
    Q3 = compose_scan(Phi, np.stack([Q, 2.0 * Q], axis=1), ev, chunk=chunk)[1]
    np.testing.assert_allclose(Q3[:, 0], Q1, rtol=1e-13, atol=1e-13 * np.abs(Q1).max())
    np.testing.assert_allclose(Q3[:, 1], 2.0 * Q3[:, 0], rtol=1e-15, atol=0)
    # noise on a constant's row: not of that form, composed densely, the same answer
    Qx = Q.copy()
    Qx[:, c[0], c[0]] = 1e-3
    assert _constant_rows(Phi, Qx, ev) is None
    P4, Q4 = compose_scan(Phi, Qx, ev, chunk=chunk)
    P5, Q5 = compose(Phi, Qx, ev)
    np.testing.assert_allclose(Q4, Q5, rtol=1e-13, atol=1e-13 * np.abs(Q5).max())
    np.testing.assert_allclose(P4, P5, rtol=1e-13, atol=1e-13 * np.abs(P5).max())


def test_no_steps_compose_to_the_identity_as_step_by_step():
    """N = 0: every interval is empty; the pairwise reduction agrees with the step-by-step composition."""
    Phi, Q = np.zeros((0, 3, 3)), np.zeros((0, 3, 3))
    P1, Q1 = compose(Phi, Q, np.array([0, 0]))
    P2, Q2 = compose_scan(Phi, Q, np.array([0, 0]))
    np.testing.assert_array_equal(P2, P1)
    np.testing.assert_array_equal(P2, np.eye(3)[None])
    np.testing.assert_array_equal(Q2, Q1)
    np.testing.assert_array_equal(Q2, np.zeros((1, 3, 3)))


def test_nonzero_rows_and_cache_keys_tell_every_bit_pattern_apart():
    """``_nonzero_rows``: rows with an entry ``!= 0`` (NaN, inf, a denormal) and rows not +0.0 bit for bit.

    The composition cache names the all-+0.0 rows of a source's ``G`` in its
    key instead of digesting them, so its key must still change with any
    bit of ``G``: a −0.0 row (``!= 0`` false, yet not +0.0), a denormal, a NaN.
    """
    from covtool.lincov.noise import ComposedCache, _nonzero_rows

    G = np.zeros((3, 6, 2))
    G[1, 1, 0] = np.nan
    G[2, 2, 1] = 5e-324
    G[0, 3, 1] = -0.0
    G[2, 4, 0] = -np.inf
    seed, live = _nonzero_rows(G)
    assert seed.tolist() == [False, True, True, False, True, False]
    assert live.tolist() == [False, True, True, True, True, False]
    psd, ev, dt = np.ones((3, 2)), np.array([0, 3]), np.ones(3)
    states = np.arange(6)
    keys = {ComposedCache.key("s", states, X, psd, ev, dt)
            for X in (G, np.where(np.arange(6)[None, :, None] == 3, 0.0, G), np.zeros((3, 6, 2)),
                      np.zeros((3, 6, 1)))}
    assert len(keys) == 4                                  # −0.0 against +0.0, and the shape, change the key
    assert ComposedCache.key("s", states, G.copy(), psd, ev, dt) == ComposedCache.key("s", states, G, psd, ev, dt)
