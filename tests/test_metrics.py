"""CEP, probable error and attitude mapping against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from covtool import quaternion as quat
from covtool.metrics import PE_FACTOR, cep, cep_approx


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
