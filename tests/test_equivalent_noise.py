"""Equivalent white noise matched over the ZUPT intervals (issue 11, acceptance 1).

Oracles: closed forms of the integrated effect of a dropped random constant
(seed 002 eq (12)), of a random walk (eq (13)), and the schedule's own
update times.
"""

from __future__ import annotations

import numpy as np
import pytest

from covtool.lincov.equivalent_noise import (equivalent_noise_source, equivalent_white_noise,
                                             pointwise_overstatement, tail_integral, zupt_intervals)
from covtool.lincov.model.spec import State


def _state(process="constant", sigma=2.0, tau=None, distance=None, rw=0.0):
    return State("s", "s", "b", "accel_bias", "", "acceleration", "ug", sigma, process,
                 tau=tau, distance=distance, rw=rw)


def _integrated(src, dt, a, b):
    """``∫_a^b G diag(psd) Gᵀ dt``: the white noise's integrated covariance over steps a..b−1."""
    G, q = src.G[a:b], src.psd[a:b]
    return np.einsum("tik,tk,tjk,t->ij", G, q, G, dt[a:b])


T_S = 300.0                                   # ZUPT interval Δt_s
N = 900                                       # three intervals of 1 s steps
DT = np.ones(N)
T = np.r_[0.0, np.cumsum(DT)]
ONE_PER_STOP = [300, 600, 900]                # one update at the end of each stop


def test_constant_coupling_gives_the_printed_eq12():
    """For a constant coupling the interval-matched noise is today's P0·Δt_s·c cᵀ at every step."""
    st = _state(sigma=3.0)
    c = np.tile([0.5, -2.0, 1.0], (N, 1))
    bounds = zupt_intervals(ONE_PER_STOP, T, T_S)
    src, rule = equivalent_noise_source(st, c, DT, bounds, dt_s=T_S)
    pw, _ = equivalent_noise_source(st, c, DT, bounds, dt_s=T_S, mode="pointwise")
    np.testing.assert_allclose(src.qc(), pw.qc(), rtol=1e-13)
    np.testing.assert_allclose(src.qc()[0], 9.0 * T_S * np.outer(c[0], c[0]), rtol=1e-13)
    assert "interval-matched" in rule and "eq (12)" in rule


def test_alternating_coupling_matches_the_integrated_variance():
    """c(t) = u (1 + 3 s(t)), s = ±1 switching every 25 s: the rule's P0 (∫c)(∫c)ᵀ holds exactly.

    Closed forms per 300 s interval: ∫c = 300 u, ∫|c|² = 10·300 |u|²; the
    pointwise form integrates to P0 Δt_s ∫ccᵀ, too large by
    Δt_s ∫|c|² / |∫c|² = 10.
    """
    P0 = 4.0
    st = _state(sigma=2.0)
    u = np.array([1.0, -0.5])
    s = np.where((np.arange(N) // 25) % 2 == 0, 1.0, -1.0)
    c = (1.0 + 3.0 * s)[:, None] * u[None, :]
    bounds = zupt_intervals(ONE_PER_STOP, T, T_S)
    src, _ = equivalent_noise_source(st, c, DT, bounds, dt_s=T_S)
    pw, _ = equivalent_noise_source(st, c, DT, bounds, dt_s=T_S, mode="pointwise")
    for a, b in zip(bounds[:-1], bounds[1:]):
        integ = 300.0 * u
        np.testing.assert_allclose(_integrated(src, DT, a, b), P0 * np.outer(integ, integ), rtol=1e-12)
        np.testing.assert_allclose(_integrated(pw, DT, a, b), P0 * T_S * 10 * 300.0 * np.outer(u, u), rtol=1e-12)
    over, worst = pointwise_overstatement(c, DT, bounds, T_S)
    assert over == pytest.approx(10.0, rel=1e-12) and worst == pytest.approx(10.0, rel=1e-12)


def test_a_cancelling_coupling_gets_no_noise():
    """A left and a right turn that cancel within the interval: ∫c = 0, so no equivalent noise."""
    c = np.zeros((N, 1))
    c[100:120] = 1.0
    c[200:220] = -1.0
    bounds = zupt_intervals(ONE_PER_STOP, T, T_S)
    src, _ = equivalent_noise_source(_state(), c, DT, bounds, dt_s=T_S)
    assert np.abs(_integrated(src, DT, 0, 300)).max() < 1e-14
    over, worst = pointwise_overstatement(c, DT, bounds, T_S)
    assert np.isinf(over) and np.isinf(worst)


@pytest.mark.parametrize("upd,expected", [
    (ONE_PER_STOP, [0, 300, 600, 900]),
    ([k for e in (300, 600, 900) for k in range(e - 30, e + 1)], [0, 300, 600, 900]),  # 1 Hz windows
    ([120, 420, 720], [0, 120, 420, 720, 900]),                                       # [zupt] first = 2 min
    ([270, 280, 290, 300], [0, 300, 900]),                                            # one window only
    ([], [0, 900]),
])
def test_intervals_follow_the_schedule(upd, expected):
    """Intervals end at the last update of each stop; a first stop off k·Δt_s and a tail are kept."""
    np.testing.assert_array_equal(zupt_intervals(upd, T, T_S), expected)


def test_partial_first_interval_uses_its_own_length():
    """A first stop at 120 s: over [0, 120) the noise integrates to P0 (120 c)², not P0 Δt_s·120 c²."""
    st = _state(sigma=1.0)
    c = np.ones((N, 1))
    bounds = zupt_intervals([120, 420, 720], T, T_S)
    src, _ = equivalent_noise_source(st, c, DT, bounds, dt_s=T_S)
    assert _integrated(src, DT, 0, 120)[0, 0] == pytest.approx(120.0**2, rel=1e-12)
    assert _integrated(src, DT, 720, 900)[0, 0] == pytest.approx(180.0**2, rel=1e-12)


def test_random_walk_matches_the_walks_integrated_variance():
    """Eq (13): x = x(t_a) + W(t − t_a); ∫c x over an interval has variance
    (σ0² + q t_a)(∫c)² + q ∫∫ c c min(s, s') = for constant c:
    (σ0² + q t_a) c² Δt² + q c² Δt³/3 (the midpoint quadrature's −Δt/12 is below 1e-5)."""
    sig0, q = 0.3, 0.02
    st = _state("random_walk", sigma=sig0, rw=np.sqrt(q))
    c = np.full((N, 1), 2.0)
    bounds = zupt_intervals(ONE_PER_STOP, T, T_S)
    src, rule = equivalent_noise_source(st, c, DT, bounds, dt_s=T_S)
    assert "random walk" in rule
    for a, b in zip(bounds[:-1], bounds[1:]):
        ta = T[a]
        exact = (sig0**2 + q * ta) * 4.0 * T_S**2 + q * 4.0 * T_S**3 / 3.0
        assert _integrated(src, DT, a, b)[0, 0] == pytest.approx(exact, rel=1e-5)
    # the printed form (pointwise) takes q Δt_s² for the increment: 3x the matched value
    pw_q, _ = equivalent_white_noise(st, T_S)
    assert pw_q == pytest.approx(sig0**2 * T_S + q * T_S**2, rel=1e-12)


def test_tail_integral_closed_form():
    c = np.ones((N, 1))
    bounds = np.array([0, 300, 900])
    tail = tail_integral(c, DT, bounds)
    assert tail[0, 0] == pytest.approx(299.5) and tail[299, 0] == pytest.approx(0.5)
    assert tail[300, 0] == pytest.approx(599.5)


def test_markov_source_short_tau_stays_pointwise():
    """Eq (11): τ ≤ Δt_s/2 decorrelates within the interval: 2τP0 through c(t) at every step."""
    st = _state("markov", sigma=2.0, tau=20.0)
    rng = np.random.default_rng(1)
    c = rng.standard_normal((N, 2))
    bounds = zupt_intervals(ONE_PER_STOP, T, T_S)
    src, rule = equivalent_noise_source(st, c, DT, bounds, dt_s=T_S)
    np.testing.assert_allclose(src.qc(), 2 * 20.0 * 4.0 * np.einsum("ti,tj->tij", c, c), rtol=1e-13)
    assert rule.startswith("eq (11)")
    long = _state("markov", sigma=2.0, tau=3600.0)
    src2, rule2 = equivalent_noise_source(long, c, DT, bounds, dt_s=T_S)
    assert "interval-matched" in rule2 and "tau = 3600 s > dt_s/2" in rule2


def test_interval_mean_sums_each_interval_with_or_without_a_strict_schedule():
    """c̄_i = (1/Δt_i) ∫_i c dt by an explicit loop; a bounds list with a repeated entry (an empty interval) too."""
    from covtool.lincov.equivalent_noise import interval_mean

    rng = np.random.default_rng(4)
    c = rng.standard_normal((N, 3))
    dt = 0.5 + rng.random(N)
    for bounds in (zupt_intervals(ONE_PER_STOP, T, T_S), np.array([0, 250, 250, 700, N])):
        cbar, dti = interval_mean(c, dt, bounds)
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b == a:
                continue
            L = dt[a:b].sum()
            np.testing.assert_allclose(cbar[a:b], np.tile((c[a:b] * dt[a:b, None]).sum(0) / L, (b - a, 1)),
                                       rtol=1e-12, atol=1e-15)
            np.testing.assert_allclose(dti[a:b], L, rtol=1e-13)


def test_equivalent_noise_qc_is_the_sum_of_the_sources_own_qc():
    """Formed on each source's rows, the sum equals Σ G diag(psd) Gᵀ of the full products, element by element."""
    from covtool.lincov.dynamics import NoiseSource
    from covtool.lincov.reduced import equivalent_noise_qc

    rng = np.random.default_rng(9)
    n, M = 7, 50
    srcs = []
    for rows_, k in (([3, 4, 5], 1), ([0, 1, 2, 3], 2), ([6], 1)):
        G = np.zeros((M, n, k))
        G[:, rows_, :] = rng.standard_normal((M, len(rows_), k))
        srcs.append(NoiseSource("s", G, rng.random((M, k))))
    base = rng.standard_normal((M, n, n))
    ref = base.copy()
    for s in srcs:
        ref += s.qc()
    got = equivalent_noise_qc(srcs, (M, n, n), out=base.copy())
    np.testing.assert_array_equal(got, ref)
    np.testing.assert_array_equal(equivalent_noise_qc([], (M, n, n)), np.zeros((M, n, n)))
