"""FLOP counts of one on-board filter cycle (seed 002 Table 4).

The closed forms of :mod:`covtool.analysis.cost` are checked against an explicit
count: the same cycle written as naive Python loops in which every scalar
add, subtract, multiply and divide increments a counter.  The naive cycle is
also checked to compute the same numbers as the timed cycle (covtool's own
Taylor discretisation, gain and update: the kernel of covtool.lincov.kalman).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from covtool.analysis import cost
from covtool.lincov.discretize import taylor


class Counter:
    """Naive dense linear algebra on lists, counting scalar FLOPs."""

    def __init__(self):
        self.n = 0

    def matmul(self, A, B):
        a, b, c = len(A), len(B), len(B[0])
        out = [[0.0] * c for _ in range(a)]
        for i in range(a):
            for j in range(c):
                acc = 0.0
                for k in range(b):
                    acc += A[i][k] * B[k][j]
                    self.n += 2
                out[i][j] = acc
        return out

    def add(self, A, B, sign=1.0):
        self.n += len(A) * len(A[0])
        return [[x + sign * y for x, y in zip(ra, rb)] for ra, rb in zip(A, B)]

    def scale(self, c, A):
        self.n += len(A) * len(A[0])
        return [[c * x for x in r] for r in A]

    def div(self, A, c):
        self.n += len(A) * len(A[0])
        return [[x / c for x in r] for r in A]

    def scalar(self, k=1):
        self.n += k

    @staticmethod
    def T(A):
        return [list(r) for r in zip(*A)]

    @staticmethod
    def eye(n):
        return [[1.0 if i == j else 0.0 for j in range(n)] for i in range(n)]

    def lu_solve_rows(self, S, U):
        """X with X S = U (S symmetric), by unpivoted LU.

        LU of S without pivoting, then S Xᵀ = Uᵀ row by row.
        """
        m = len(S)
        L = [[1.0 if i == j else 0.0 for j in range(m)] for i in range(m)]
        W = [list(r) for r in S]
        for k in range(m):
            for i in range(k + 1, m):
                L[i][k] = W[i][k] / W[k][k]
                self.n += 1
                for j in range(k + 1, m):
                    W[i][j] -= L[i][k] * W[k][j]
                    self.n += 2
        X = []
        for b in U:                                   # one right-hand side per row of U
            y = [0.0] * m
            for i in range(m):
                acc = b[i]
                for j in range(i):
                    acc -= L[i][j] * y[j]
                    self.n += 2
                y[i] = acc
            x = [0.0] * m
            for i in reversed(range(m)):
                acc = y[i]
                for j in range(i + 1, m):
                    acc -= W[i][j] * x[j]
                    self.n += 2
                x[i] = acc / W[i][i]
                self.n += 1
            X.append(x)
        return X


def naive_cycle(F, Qc, dt, P, H, R, order, form):
    """The cycle of :func:`covtool.analysis.cost.onboard_cycle`, counted."""
    c = Counter()
    F, Qc, P, H, R = (np.asarray(x, float).tolist() for x in (F, Qc, P, H, R))
    n = len(F)
    counts = {}
    start = c.n
    A = c.scale(dt, F)
    Phi = [list(r) for r in A]
    for i in range(n):
        Phi[i][i] += 1.0
    c.scalar(n)
    T = A
    for i in range(2, order):
        T = c.div(c.matmul(T, A), i)
        Phi = c.add(Phi, T)
    counts["phi"] = c.n - start
    start = c.n
    C = Qc
    Q = c.scale(dt, C)
    coef = dt
    for i in range(2, order):
        G = c.matmul(F, C)
        C = c.add(G, c.T(G))
        coef = coef * dt / i
        c.scalar(2)
        Q = c.add(Q, c.scale(coef, C))
    counts["qd"] = c.n - start
    start = c.n
    P = c.add(c.matmul(c.matmul(Phi, P), c.T(Phi)), Q)
    counts["propagation"] = c.n - start
    start = c.n
    U = c.matmul(P, c.T(H))
    S = c.add(c.matmul(H, U), R)
    K = c.lu_solve_rows(S, U)
    counts["gain"] = c.n - start
    start = c.n
    if form == "joseph":
        Aj = c.add(c.eye(n), c.matmul(K, H), sign=-1.0)
        P = c.add(c.matmul(c.matmul(Aj, P), c.T(Aj)), c.matmul(c.matmul(K, R), c.T(K)))
    else:
        P = c.add(P, c.matmul(K, c.matmul(H, P)), sign=-1.0)
    counts["update"] = c.n - start
    counts["total"] = c.n
    return np.array(P), np.array(K), counts


def _problem(n, m, seed=0):
    rng = np.random.default_rng(seed)
    F = 0.1 * rng.standard_normal((n, n))
    L = rng.standard_normal((n, n))
    Qc = 1e-3 * L @ L.T
    L = rng.standard_normal((n, n))
    P = L @ L.T + n * np.eye(n)
    H = rng.standard_normal((m, n))
    R = np.diag(rng.uniform(0.5, 2.0, m))
    return F, Qc, 0.7, P, H, R


@pytest.mark.parametrize("n,m,order,form", [(1, 1, 2, "joseph"), (3, 1, 3, "standard"), (4, 3, 4, "joseph"),
                                            (5, 2, 5, "standard"), (6, 3, 2, "standard"), (2, 3, 6, "joseph")])
def test_closed_forms_equal_an_explicit_count(n, m, order, form):
    """Every closed form equals the naive loops' count, exactly."""
    args = _problem(n, m, seed=n + 10 * m + 100 * order)
    _, _, counts = naive_cycle(*args, order, form)
    assert cost.cycle_flops(n, m, order, form) == counts


@pytest.mark.parametrize("form", ["joseph", "standard"])
def test_counted_cycle_is_the_numpy_cycle(form):
    """The counted loops compute what onboard_cycle does (1e-12)."""
    args = _problem(5, 3, seed=3)
    Pn, Kn, _ = naive_cycle(*args, 4, form)
    P, K = cost.onboard_cycle(*args, 4, form)
    np.testing.assert_allclose(P, Pn, rtol=1e-12, atol=1e-12 * np.abs(P).max())
    np.testing.assert_allclose(K, Kn, rtol=1e-12, atol=1e-12 * np.abs(K).max())


def test_leading_term_is_cubic():
    """FLOPs/n³ → 2(2N_t − 4) + 4 (+ 4 with Joseph) for large n."""
    n, m, order = 20000, 3, 5
    assert cost.cycle_flops(n, m, order, "standard")["total"] / n**3 == pytest.approx(2 * (2 * order - 4) + 4,
                                                                                      rel=1e-3)
    assert cost.cycle_flops(n, m, order, "joseph")["total"] / n**3 == pytest.approx(2 * (2 * order - 4) + 8,
                                                                                    rel=1e-3)


def test_taylor_terms_is_the_adaptive_series_length():
    """taylor_terms is the length of the adaptive eq (6b)-(6d) series.

    On steps the series reaches without squaring (νΔt ≤ θ), taylor(order=N_t)
    with that step's N_t reproduces the adaptive result to round-off (the
    adaptive sum is formed as Φ − I, then I added); a step
    that needs squaring is refused (one on-board cycle has no squarings).
    """
    from covtool.lincov.discretize import THETA, taylor_terms
    from covtool.errors import InputError

    rng = np.random.default_rng(2)
    F = 0.03 * rng.standard_normal((4, 6, 6))
    L = rng.standard_normal((4, 6, 6))
    Qc = L @ np.swapaxes(L, 1, 2)
    info = taylor_terms(F, Qc, 1.0)
    assert not info.squarings.any()
    assert cost.taylor_terms(F, Qc, 1.0) == info.terms.max()
    for j in range(4):
        Pa, Qa = taylor(F[j:j + 1], Qc[j:j + 1], 1.0)
        Pk, Qk = taylor(F[j:j + 1], Qc[j:j + 1], 1.0, order=int(info.terms[j]))
        np.testing.assert_allclose(Pa, Pk, rtol=0, atol=4 * 2.0**-53)
        np.testing.assert_allclose(Qa, Qk, rtol=4 * 2.0**-53, atol=0)
    # scalar closed form of the stopping rule: the first i with a^i/i! · r/(1 − r) ≤ 2^-53 (2 − e^a), r = a/(i+1)
    a = 0.4
    i = next(i for i in range(1, 40)
             if a**i / math.factorial(i) * (a / (i + 1)) / (1 - a / (i + 1)) <= 2.0**-53 * (2 - math.exp(a)))
    assert cost.taylor_terms(np.full((1, 1, 1), a), np.zeros((1, 1, 1)), 1.0) == i + 1
    assert a <= THETA
    with pytest.raises(InputError, match=r'taylor_order = "auto": at step 0 \(νΔt = 4 > 0.5\) the adaptive series '
                                         r"is summed over Δt/8 and squared"):
        cost.taylor_terms(np.full((1, 1, 1), -4.0), np.ones((1, 1, 1)), 1.0)


def test_power_law_recovers_exponent():
    n = np.array([10, 16, 22, 58])
    p, a = cost.power_law(n, 3.5 * n**3.2)
    assert p == pytest.approx(3.2, rel=1e-12)
    assert a == pytest.approx(3.5, rel=1e-12)


@pytest.mark.parametrize("call,match", [
    (lambda: cost.phi_flops(4, 1), "at least 2 terms"),
    (lambda: cost.qd_flops(4, 2.5), "at least 2 terms"),
    (lambda: cost.gain_flops(0, 3), "positive integers"),
    (lambda: cost.propagation_flops(2.5), "positive integers"),
    (lambda: cost.update_flops(4, 3, "kalman"), "unknown update form"),
])
def test_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()
