"""CEP, probable error and attitude mapping against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from covtool.nav import attitude as quat
from covtool.analysis.metrics import PE_FACTOR, cep, cep_approx


def test_cep_circular_closed_form():
    """Circular normal: CEP = σ √(2 ln 2) = 1.17741 σ (Rayleigh median)."""
    for s in (1e-3, 1.0, 3e4):
        assert cep(np.eye(2) * s**2) == pytest.approx(s * np.sqrt(2 * np.log(2)), rel=1e-9)


def test_cep_degenerate_limit_is_probable_error():
    """σ₂ → 0: CEP → 0.67449 σ₁ (the 1-D probable error)."""
    assert cep(np.diag([4.0, 0.0])) == pytest.approx(2 * PE_FACTOR, rel=1e-6)


def test_cep_against_monte_carlo_and_rule_of_thumb():
    """Elliptical and correlated: exact CEP vs the median of 10⁶ samples (≤ 0.3 %)."""
    rng = np.random.default_rng(1)
    S = np.array([[9.0, 2.5], [2.5, 1.5]])
    x = rng.multivariate_normal([0, 0], S, 1_000_000)
    assert cep(S) == pytest.approx(np.median(np.hypot(*x.T)), rel=3e-3)
    # the 0.589(σ1+σ2) rule is within 3 % for σ2/σ1 > 0.3 but not beyond
    assert cep_approx(np.diag([1.0, 0.36])) == pytest.approx(cep(np.diag([1.0, 0.36])), rel=0.03)
    assert abs(cep_approx(np.diag([1.0, 0.0])) / cep(np.diag([1.0, 0.0])) - 1) > 0.1


def test_cep_vectorised_and_zero():
    P = np.stack([np.zeros((2, 2)), np.eye(2)])
    out = cep(P)
    assert out[0] == 0.0 and out[1] == pytest.approx(1.1774100225154747)


def test_quaternion_error_to_attitude_error_round_trip():
    """δq = −½ R(q) φ and φ = −2 R(q)ᵀ δq: exact inverse, norm direction ignored."""
    rng = np.random.default_rng(2)
    q = quat.normalize(rng.standard_normal(4))
    phi = 1e-5 * rng.standard_normal(3)
    qhat = quat.mul(quat.from_rotvec(-phi), q)           # Ĉ = (I − [φ×]) C
    M = quat.attitude_error_matrix(q)
    np.testing.assert_allclose(M @ (qhat - q), phi, rtol=1e-4)
    np.testing.assert_allclose(M @ q, 0.0, atol=1e-15)


@pytest.mark.parametrize("ratio", [1.0, 0.3, 0.05, 0.01, 0.0033, 0.001, 1e-5])
def test_cep_against_independent_quadrature_for_elongated_ellipses(ratio):
    """Exact CEP against scipy's adaptive quad + brentq for any eccentricity (rel ≤ 1e-9).

    Reference: P(r) = ∫ φ(x₂/σ₂)/σ₂ erf(√(r²−x₂²)/(√2σ₁)) dx₂ by adaptive
    quadrature; for σ₂/σ₁ ≥ 0.05 also the major-axis form, which must agree.
    Regression: a Newton test on the step size alone returned a CEP 10 % low
    at σ₂/σ₁ = 0.0033.  Physics: CEP → 0.67449 σ₁ (1 + O((σ₂/σ₁)²)).
    """
    from scipy.integrate import quad
    from scipy.optimize import brentq
    from scipy.special import erf as _erf
    s1, s2 = 3.0, 3.0 * ratio

    def p_minor(r):
        lim = min(r, 14 * s2)
        g = lambda x: np.exp(-0.5 * (x / s2) ** 2) / (np.sqrt(2 * np.pi) * s2) * _erf(  # noqa: E731
            np.sqrt(max(r * r - x * x, 0.0)) / (np.sqrt(2) * s1))
        return 2 * quad(g, 0, lim, epsabs=1e-15, epsrel=1e-13, limit=400)[0]

    def p_major(r):
        g = lambda x: np.exp(-0.5 * (x / s1) ** 2) / (np.sqrt(2 * np.pi) * s1) * _erf(  # noqa: E731
            np.sqrt(max(r * r - x * x, 0.0)) / (np.sqrt(2) * s2))
        return 2 * quad(g, 0, r, epsabs=1e-15, epsrel=1e-13, limit=400)[0]

    ref = brentq(lambda r: p_minor(r) - 0.5, 0.5 * s1, 1.3 * np.hypot(s1, s2), xtol=1e-15)
    if ratio >= 0.05:
        ref2 = brentq(lambda r: p_major(r) - 0.5, 0.5 * s1, 1.3 * np.hypot(s1, s2), xtol=1e-15)
        assert ref2 == pytest.approx(ref, rel=1e-10)
    got = cep(np.diag([s1**2, s2**2]))
    assert got == pytest.approx(ref, rel=1e-9)
    assert got >= PE_FACTOR * s1 * (1 - 1e-12)


def test_cep_batch_point_stays_on_its_root():
    """A converged point is frozen while the others iterate (issue 13).

    One circular point (closed form σ √(2 ln 2)) batched with elongated
    ellipses that need many safeguarded steps: the circular CEP must stay at
    the closed form to 1e-13, and each point must equal its CEP computed alone
    (the solver now iterates only the points not yet converged).
    """
    ratios = np.array([1.0, 1e-5, 0.0033, 0.001, 0.3, 1e-4])
    P = np.stack([np.diag([9.0, 9.0 * q * q]) for q in ratios])
    got = cep(P)
    assert got[0] == pytest.approx(3.0 * np.sqrt(2 * np.log(2)), rel=1e-13)
    alone = np.array([cep(p) for p in P])
    np.testing.assert_allclose(got, alone, rtol=1e-13)


def test_nav_metrics_at_points_of_a_history_with_its_running_scale():
    """Points taken from a history are judged as in the history when given its running scale.

    State δv_N has σ = 1 m/s at t₀ and 1e-10 m/s at t₁, with a covariance to
    δv_E of 2e-10: by its own σ the correlation is 2 (not PSD), by the
    largest σ it has had it is round-off (the history's rule,
    :func:`covtool.lincov.kalman.running_scale`).  The metrics of point t₁
    alone are NaN; with the history's scale they are the history's values.
    """
    from covtool.analysis.metrics import nav_metrics
    from covtool.lincov.kalman import running_scale

    P = np.stack([np.eye(10) * 1e-12, np.eye(10) * 1e-12])
    P[:, 3, 3] = [1.0, 1e-20]
    P[1, 3, 4] = P[1, 4, 3] = 2e-10
    P[1, 4, 4] = 1.0
    lat, h = np.full(2, 0.6), np.zeros(2)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))
    full = nav_metrics(P, lat, h, q)
    assert full["sigma_vn"][1] == pytest.approx(1e-10, rel=1e-12)
    alone = nav_metrics(P[1:], lat[1:], h[1:], q[1:])
    assert np.isnan(alone["sigma_vn"][0])
    scaled = nav_metrics(P[1:], lat[1:], h[1:], q[1:], scale=running_scale(P)[1:])
    for key, v in full.items():
        np.testing.assert_array_equal(scaled[key], v[1:])
