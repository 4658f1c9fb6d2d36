"""The one Kalman kernel (covtool.lincov.kalman): gain, Joseph/eq (16) update.

Checked against independent formulas: the dense product form of the Joseph
update written out here, the information form of the optimal update
(``(P⁺)⁻¹ = P⁻¹ + Hᵀ R⁻¹ H``, ``K = P⁺ Hᵀ R⁻¹``), the scalar closed form,
and the batched form against one case at a time; the selection fast path of
eq (16) against the same ``D`` given as a full matrix.
"""

from __future__ import annotations

import numpy as np
import pytest

from covtool.errors import NumericalError
from covtool.lincov.kalman import (filter_update, joseph_update, kalman_gain, predict, selection,
                                   truth_update)


def _spd(rng, n, shift=1.0):
    L = rng.standard_normal((n, n))
    return L @ L.T + shift * np.eye(n)


def _dense_joseph(P, DK, H, R):
    """``(I − DK H) P (I − DK H)ᵀ + DK R DKᵀ``, written out (seed 002, eq (16))."""
    A = np.eye(P.shape[0]) - DK @ H
    return A @ P @ A.T + DK @ R @ DK.T


def test_scalar_update_is_the_closed_form():
    """n = m = 1: K = P/(P + R), P⁺ = P R/(P + R) (both forms)."""
    P, R, H = np.array([[4.0]]), np.array([[1.0]]), np.array([[1.0]])
    K = kalman_gain(P, H, R)
    assert K[0, 0] == pytest.approx(0.8, rel=1e-15)
    for form in ("joseph", "standard"):
        assert filter_update(P, K, H, R, form)[0, 0] == pytest.approx(0.8, rel=1e-14)


@pytest.mark.parametrize("n,m", [(1, 1), (5, 2), (12, 3)])
def test_optimal_update_equals_the_information_form(n, m):
    """Optimal gain: (P⁺)⁻¹ = P⁻¹ + Hᵀ R⁻¹ H and K = P⁺ Hᵀ R⁻¹ (1e-10)."""
    rng = np.random.default_rng(n + 7 * m)
    P, R = _spd(rng, n), _spd(rng, m, 0.5)
    H = rng.standard_normal((m, n))
    K = kalman_gain(P, H, R)
    Pi = np.linalg.inv(np.linalg.inv(P) + H.T @ np.linalg.solve(R, H))
    np.testing.assert_allclose(K, Pi @ H.T @ np.linalg.inv(R), rtol=1e-10, atol=1e-12)
    for form in ("joseph", "standard"):
        out = filter_update(P, K, H, R, form)
        np.testing.assert_allclose(out, Pi, rtol=1e-10, atol=1e-12 * np.abs(Pi).max())
        assert np.array_equal(out, out.T)


def test_joseph_for_any_gain_equals_the_dense_product_form():
    """A non-optimal gain: the rank-m kernel = the dense Joseph form (1e-12)."""
    rng = np.random.default_rng(1)
    n, m = 8, 3
    P, R = _spd(rng, n), _spd(rng, m)
    H = rng.standard_normal((m, n))
    K = rng.standard_normal((n, m))
    ref = _dense_joseph(P, K, H, R)
    np.testing.assert_allclose(filter_update(P, K, H, R, "joseph"), ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())


def test_batched_update_equals_one_case_at_a_time():
    """joseph_update on B cases = B single updates, bit for bit in shape, 1e-13 in value."""
    rng = np.random.default_rng(2)
    B, n, nf, m = 5, 9, 4, 2
    P = np.stack([_spd(rng, n) for _ in range(B)])
    R = np.stack([_spd(rng, m) for _ in range(B)])
    H = rng.standard_normal((m, n))
    K = rng.standard_normal((B, nf, m))
    sel = (3, 3 + nf)
    D = np.zeros((n, nf))
    D[3:3 + nf] = np.eye(nf)
    HP = H @ P
    out = joseph_update(P.copy(), K, H, R, sel, HP=HP)
    for b in range(B):
        one = truth_update(P[b], D, K[b], H, R[b])
        np.testing.assert_allclose(out[b], one, rtol=1e-13, atol=1e-13 * np.abs(one).max())
        ref = _dense_joseph(P[b], D @ K[b], H, R[b])
        np.testing.assert_allclose(out[b], ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())


def test_selection_D_equals_the_same_D_as_a_full_matrix():
    """eq (16): the selection fast path = the general path with D K formed (1e-13)."""
    rng = np.random.default_rng(3)
    n, nf, m = 10, 4, 3
    P, R = _spd(rng, n), _spd(rng, m)
    H = rng.standard_normal((m, n))
    K = rng.standard_normal((nf, m))
    D = np.zeros((n, nf))
    D[2:6] = np.eye(nf)
    assert selection(D) == (2, 6)
    fast = truth_update(P, D, K, H, R)
    HP = H @ P
    general = joseph_update(P[None].copy(), (D @ K)[None], H, R[None], HP=HP[None])[0]
    np.testing.assert_allclose(fast, general, rtol=1e-13, atol=1e-13 * np.abs(fast).max())
    np.testing.assert_allclose(fast, _dense_joseph(P, D @ K, H, R), rtol=1e-12, atol=1e-12 * np.abs(fast).max())


def test_scattered_D_is_not_a_selection_and_still_eq16():
    rng = np.random.default_rng(4)
    n, m = 7, 2
    kept = [0, 2, 5]
    D = np.eye(n)[:, kept]
    assert selection(D) is None
    P, R = _spd(rng, n), _spd(rng, m)
    H = rng.standard_normal((m, n))
    K = rng.standard_normal((3, m))
    ref = _dense_joseph(P, D @ K, H, R)
    np.testing.assert_allclose(truth_update(P, D, K, H, R), ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())


def test_predict_is_eq_6a_and_symmetric():
    rng = np.random.default_rng(5)
    Phi = rng.standard_normal((4, 4))
    P, Q = _spd(rng, 4), _spd(rng, 4)
    out = predict(Phi, P, Q)
    np.testing.assert_allclose(out, Phi @ P @ Phi.T + Q, rtol=1e-13)
    assert np.array_equal(out, out.T)


def test_kernel_entry_checks_name_the_step():
    P, H, R = np.eye(3), np.ones((1, 3)), np.eye(1)
    with pytest.raises(ValueError, match=r"filter B1 at t = 5 s: H has 2 columns for 3 states"):
        kalman_gain(P, np.ones((1, 2)), R, what="filter B1 at t = 5 s")
    with pytest.raises(ValueError, match=r"R has shape \(2, 2\) for 1 measurements"):
        kalman_gain(P, H, np.eye(2))
    with pytest.raises(ValueError, match=r"truth update: D has shape \(3, 2\), not \(3, 3\)"):
        truth_update(P, np.eye(3)[:, :2], np.ones((3, 1)), H, R)
    with pytest.raises(ValueError, match=r"filter update: K has 2 rows for 3 states"):
        filter_update(P, np.ones((2, 1)), H, R)
    with pytest.raises(ValueError, match=r"K has 2 columns for 1 measurements"):
        filter_update(P, np.ones((3, 2)), H, R)
    with pytest.raises(ValueError, match=r"P has shape \(3, 2\), not \(\.\.\., n, n\)"):
        filter_update(np.ones((3, 2)), np.ones((3, 1)), H, R)
    with pytest.raises(ValueError, match="unknown update form 'info'"):
        filter_update(P, np.ones((3, 1)), H, R, "info")
    with pytest.raises(NumericalError, match="filter D: innovation covariance H P Hᵀ \\+ R is singular"):
        kalman_gain(np.zeros((3, 3)), H, np.zeros((1, 1)), what="filter D")
    with pytest.raises(NumericalError, match="innovation covariance H P Hᵀ \\+ R is not finite"):
        kalman_gain(np.full((3, 3), np.nan), H, R)
    with pytest.raises(NumericalError, match="filter C: the updated covariance is not finite"):
        filter_update(P, np.full((3, 1), np.inf), H, R, what="filter C")
    with pytest.raises(NumericalError, match="truth update: the updated covariance is not finite"):
        truth_update(P, np.eye(3), np.full((3, 1), np.inf), H, R)
    with pytest.raises(NumericalError, match="the updated covariance is not finite"):
        filter_update(P, np.full((3, 1), np.inf), H, R, "standard")


@pytest.mark.parametrize("seed", range(5))
def test_joseph_keeps_its_accuracy_for_a_strong_fix_in_mixed_units(seed):
    """A fix that shrinks σ up to 10⁵-fold, states in rad, m, m/s: information form to 1e-9.

    Errors relative to the posterior's σ_i σ_j.  Measured 2e-13 … 4e-12
    (the information form's own round-off); the expanded rank-m
    ``P + X + Xᵀ`` and eq (8) are off by 3e-8 … 1e-6 on these cases, so
    the test fails for a Joseph update evaluated that way.
    """
    rng = np.random.default_rng(seed)
    n, m = 9, 3
    s = np.array([1e-5, 1e-5, 1e3, 1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])     # lat, lon [rad], h [m], v [m/s], tilt [rad]
    C = _spd(rng, n, float(n))
    d = np.sqrt(np.diag(C))
    P = C / np.outer(d, d) * np.outer(s, s)
    H = np.zeros((m, n))
    H[0, 0], H[1, 1], H[2, 2] = 6.4e6, 4.5e6, 1.0                        # rad → m
    H[:, 6:9] = rng.standard_normal((m, 3))                               # a lever arm couples the attitude
    R = np.diag([0.005, 0.008, 0.012]) ** 2
    Pi = np.linalg.inv(np.linalg.inv(P) + H.T @ np.linalg.solve(R, H))
    out = filter_update(P, kalman_gain(P, H, R), H, R, "joseph")
    sd = np.sqrt(np.diag(Pi))
    assert np.max(np.abs(out - Pi) / np.outer(sd, sd)) < 1e-9
