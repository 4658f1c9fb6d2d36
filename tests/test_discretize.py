"""Discretisation: exact Van Loan against seed 002's Taylor series, eq (6b)–(6d).

Oracles:

* scalar Ornstein–Uhlenbeck closed forms (Stone Soup ``test_ou.py`` style):
  ``Φ = e^{−aΔt}``, ``Q_d = q (1 − e^{−2aΔt}) / 2a`` and, for the Taylor
  series truncated at n terms, the partial sums themselves;
* the Van Loan identity ``F Q_d + Q_d Fᵀ + Q_c − Φ Q_c Φᵀ = 0`` (pyins
  ``test_process_matrices``): integrate ``d/ds (e^{Fs} Q_c e^{Fᵀs})`` over
  the step;
* Gauss–Legendre quadrature of ``Q_d = ∫₀^Δt e^{Fs} Q_c e^{Fᵀs} ds`` with
  ``scipy.linalg.expm``, and ``Φ = expm(F Δt)``;
* the truncation order: with n terms, the first omitted terms are
  ``F^n Δt^n / n!`` and ``C_{n−1} Δt^n / n!``, so both errors scale as Δt^n.

All on the full 58-state model (every noise source on) along the
land-vehicle route.  Comparison norms:

* Φ element-wise relative with a tiny floor,
  ``|ΔΦ_ij| / max(|Φ_ij|, 1e-12 max_k |Φ_kj|)``, where both sides come from
  the same arithmetic (Van Loan against Taylor: structural zeros are exact
  zeros in both); column-wise relative, ``max_i |ΔΦ_ij| / max_i |Φ_ij|``,
  against scipy's expm, whose round-off leaves ±1e-15 in structural zeros;
* Q_d in correlation scaling, ``max |ΔQ_ij| / sqrt(Q_ii Q_jj)``, i.e. in
  units of each state's own process-noise σ over the step (dimensionless;
  states without noise have zero rows in both).
"""

from __future__ import annotations

from pathlib import Path

import math

import numpy as np
import pytest
from scipy.linalg import expm

from covtool.lincov.discretize import (THETA, block_triangular, discretize, per_source, taylor, taylor_terms,
                                       van_loan)
from covtool.lincov.discretize import methods as dz_methods
from covtool.lincov.dynamics import Context, error_dynamics
from covtool.errors import InputError, NumericalError
from covtool.io.model_file import load_model
from covtool.nav.trajectory.profiles import land_vehicle

SDINS58 = Path(__file__).resolve().parents[1] / "models" / "sdins58.toml"

AGREE = 1e-10
#: time steps of the error-versus-step table [s]
STEPS = (0.125, 0.25, 0.5, 1.0, 2.0, 4.0)


@pytest.fixture(scope="module")
def dyn():
    """F, Q_c of the 58-state model at 40 points of the route (turns, hills, stops)."""
    model = load_model(SDINS58)
    route = land_vehicle(dt=1.0)
    ctx = Context.from_trajectory(route.sample(np.linspace(5.0, 1795.0, 40)))
    d = error_dynamics(model, ctx)
    F, Qc = d.F, d.Qc
    assert np.count_nonzero(np.einsum("tii->ti", Qc)[0]) >= 10    # ARW, VRW, Markov, AD-reset noise
    return F, Qc


def _phi_error(A, B):
    """max_ij |A − B| / max(|B_ij|, 1e-12 max_k |B_kj|) (see module notes)."""
    floor = 1e-12 * np.max(np.abs(B), axis=-2, keepdims=True)
    den = np.maximum(np.abs(B), floor)
    diff = np.abs(A - B)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.max(np.where(diff > 0, diff / den, 0.0))


def _phi_column_error(A, B):
    """max_j max_i |A − B|_ij / max_i |B_ij| (column-wise relative)."""
    return np.max(np.max(np.abs(A - B), axis=-2) / np.max(np.abs(B), axis=-2))


def _q_error(A, B):
    """max |A − B|_ij / sqrt(B_ii B_jj) (correlation scaling of B)."""
    d = np.sqrt(np.clip(np.einsum("...ii->...i", B), 0.0, None))
    d = np.where(d > 0, d, 1.0)
    return np.max(np.abs(A - B) / d[..., :, None] / d[..., None, :])


# --------------------------------------------------------------------------
# closed forms
# --------------------------------------------------------------------------


@pytest.mark.parametrize("dt", [0.1, 1.0, 30.0])
def test_scalar_ou_closed_form(dt):
    """Van Loan = e^{−aΔt}, q(1 − e^{−2aΔt})/2a; Taylor(n) = the n-term partial sums (1e-14).

    A truncated series with 2aΔt ≥ n is refused (module notes): at Δt = 30 s,
    aΔt = 1.5, so n ≤ 3; n = 3 would give Q_d = qΔt(1 − 2aΔt/2) < 0.
    """
    a, q = 0.05, 3.0
    F = np.full((1, 1, 1), -a)
    Qc = np.full((1, 1, 1), q)
    Phi, Qd = van_loan(F, Qc, dt)
    assert Phi[0, 0, 0] == pytest.approx(math.exp(-a * dt), rel=1e-14)
    assert Qd[0, 0, 0] == pytest.approx(q * (1 - math.exp(-2 * a * dt)) / (2 * a), rel=1e-13)
    for n in (1, 2, 3, 6):
        if 2 * a * dt >= n:
            with pytest.raises(InputError, match=rf"the {n}-term Taylor series of eq \(6b\)-\(6d\) diverges at step 0"):
                taylor(F, Qc, dt, order=n)
            continue
        Phi_t, Qd_t = taylor(F, Qc, dt, order=n)
        phi_sum = sum((-a * dt) ** i / math.factorial(i) for i in range(n))
        # eq (6d) for a scalar: C_i = 2F C_{i−1} = (−2a)^i q
        q_sum = sum(q * (-2 * a) ** (i - 1) * dt**i / math.factorial(i) for i in range(1, n))
        assert Phi_t[0, 0, 0] == pytest.approx(phi_sum, rel=1e-14)
        assert Qd_t[0, 0, 0] == pytest.approx(q_sum, rel=1e-14, abs=0.0)


def test_taylor_recursion_is_the_van_loan_integrand_series():
    """C_i of eq (6d) are the derivatives of e^{Fs} Q_c e^{Fᵀs} at s = 0.

    So eq (6c) summed to convergence is the Van Loan integral: on a random
    4×4 system (non-normal F) 30 terms equal 30-point Gauss–Legendre
    quadrature of the integrand to 1e-12.
    """
    rng = np.random.default_rng(3)
    F = rng.normal(size=(1, 4, 4)) * 0.3
    G = rng.normal(size=(4, 2))
    Qc = (G @ G.T)[None]
    dt = 0.7
    _, Qd_t = taylor(F, Qc, dt, order=30)
    x, w = np.polynomial.legendre.leggauss(30)
    s, w = 0.5 * dt * (x + 1), 0.5 * dt * w
    Qq = sum(wk * expm(F[0] * sk) @ Qc[0] @ expm(F[0] * sk).T for sk, wk in zip(s, w))
    np.testing.assert_allclose(Qd_t[0], Qq, rtol=1e-12, atol=1e-14 * np.abs(Qq).max())


# --------------------------------------------------------------------------
# the 58-state model
# --------------------------------------------------------------------------


def test_exact_methods_match_the_long_truncated_series_at_1s(dyn):
    """The exact path = the unscaled 30-term series of eq (6b)–(6d) at Δt = 1 s.

    At 1 s the 58-state model has νΔt ≤ 0.14 (no squaring), so the
    truncated series with 30 terms is converged far below round-off: it
    checks the adaptive stopping rule (11 terms) independently.  Measured:
    Φ 1e-15 (element-wise), Q_d 3e-16 (correlation-scaled).  ``van_loan``,
    ``taylor`` and the dispatcher give the same numbers.
    """
    F, Qc = dyn
    Phi_v, Qd_v = van_loan(F, Qc, 1.0)
    Phi_t, Qd_t, info = taylor(F, Qc, 1.0, info=True)
    Phi_30, Qd_30 = taylor(F, Qc, 1.0, order=30)
    assert np.all(info.squarings == 0) and info.terms.max() < 30
    assert _phi_error(Phi_v, Phi_30) <= AGREE and _q_error(Qd_v, Qd_30) <= AGREE
    assert np.array_equal(Phi_v, Phi_t) and np.array_equal(Qd_v, Qd_t)
    Phi_d, Qd_d = discretize(F, Qc, 1.0, "taylor")
    assert np.array_equal(Phi_d, Phi_t) and np.array_equal(Qd_d, Qd_t)


def test_van_loan_phi_is_the_matrix_exponential(dyn):
    """Φ of Van Loan = expm(F Δt) (scipy, own call): column-wise 1e-12.

    Measured 2.7e-15 (1 s) and 1.4e-13 (60 s).
    """
    F, Qc = dyn[0][::4], dyn[1][::4]
    for dt in (1.0, 60.0):
        Phi, _ = van_loan(F, Qc, dt)
        assert _phi_column_error(Phi, expm(F * dt)) <= 1e-12


@pytest.mark.parametrize("dt", [1.0, 10.0, 60.0])
def test_van_loan_residual(dyn, dt):
    """``F Q_d + Q_d Fᵀ + Q_c − Φ Q_c Φᵀ = 0`` (pyins style), any step.

    Residual times Δt, in the correlation scaling of Q_d (units of Q_d
    itself), ≤ 1e-10; measured 6e-12 (1 s), 2e-12 (10 s), 2e-11 (60 s),
    while the individual terms are of order 1 in that scaling.
    """
    F, Qc = dyn[0][::4], dyn[1][::4]
    Phi, Qd = van_loan(F, Qc, dt)
    FQ = F @ Qd
    R = FQ + np.swapaxes(FQ, 1, 2) + Qc - Phi @ Qc @ np.swapaxes(Phi, 1, 2)
    assert _q_error(Qd + R * dt, Qd) <= AGREE
    # the identity is not trivially met: its terms are O(1) in this scaling
    assert _q_error(Qd + FQ * dt, Qd) > 0.5


@pytest.mark.parametrize("dt", [1.0, 10.0, 60.0])
def test_van_loan_qd_against_quadrature(dyn, dt):
    """Q_d = ∫₀^Δt e^{Fs} Q_c e^{Fᵀs} ds by 24-point Gauss–Legendre: ≤ 1e-10.

    Measured 7e-14 (1 s), 6e-13 (10 s), 3e-13 (60 s), correlation-scaled.
    """
    F, Qc = dyn
    F, Qc = F[::8], Qc[::8]
    _, Qd = van_loan(F, Qc, dt)
    x, w = np.polynomial.legendre.leggauss(24)
    Qq = np.zeros_like(Qd)
    for sk, wk in zip(0.5 * dt * (x + 1), 0.5 * dt * w):
        E = expm(F * sk)
        Qq += wk * E @ Qc @ np.swapaxes(E, 1, 2)
    assert _q_error(Qq, Qd) <= AGREE


@pytest.fixture(scope="module")
def error_table(dyn):
    """Fixed order-3 Taylor error against Van Loan for each step of STEPS."""
    F, Qc = dyn[0][::4], dyn[1][::4]
    rows = []
    for dt in STEPS:
        Phi_v, Qd_v = van_loan(F, Qc, dt)
        Phi_t, Qd_t = taylor(F, Qc, dt, order=3)
        rows.append((np.max(np.abs(Phi_t - Phi_v)), np.max(np.abs(Qd_t - Qd_v))))
    return np.array(rows)


def test_taylor_error_grows_as_dt_to_the_order(error_table):
    """Order-3 Taylor: errors grow ∝ Δt³ (ratio 8 per doubling).

    With n = 3 terms the first omitted terms are F³Δt³/3! and C₂Δt³/3!.
    Measured max-abs errors (Δt = 0.125, 0.25, 0.5, 1, 2, 4 s): Φ 2.5e-3,
    2.0e-2, 0.16, 1.26, 10.1, 80.9 (log₂ ratios 3.000000–3.000006); Q_d
    3.5e-11, 2.8e-10, 2.2e-9, 1.7e-8, 1.3e-7, 1.0e-6 (log₂ ratios 2.994,
    2.987, 2.975, 2.950, 2.905: the next terms bend it at large steps).
    Required: 3 ± 0.05 for Φ everywhere and for Q_d up to 0.5 s.
    """
    slopes = np.log2(error_table[1:] / error_table[:-1])
    np.testing.assert_allclose(slopes[:, 0], 3.0, atol=0.05)
    asym = np.array(STEPS[1:]) <= 0.5
    np.testing.assert_allclose(slopes[asym, 1], 3.0, atol=0.05)
    # monotone over the whole table
    assert np.all(np.diff(error_table, axis=0) > 0)


@pytest.mark.parametrize("order", [2, 4, 5])
def test_taylor_error_order_follows_the_number_of_terms(dyn, order):
    """With n terms the Φ error ratio per step doubling is 2ⁿ (± 3 %)."""
    F, Qc = dyn[0][::4], dyn[1][::4]
    errs = []
    for dt in (0.25, 0.5):
        Phi_v, _ = van_loan(F, Qc, dt)
        Phi_t, _ = taylor(F, Qc, dt, order=order)
        errs.append(np.max(np.abs(Phi_t - Phi_v)))
    assert errs[1] / errs[0] == pytest.approx(2.0**order, rel=0.03)


# --------------------------------------------------------------------------
# any step: Gauss–Markov closed forms, divergent series, unstable modes
# --------------------------------------------------------------------------

TAU = 20.0
SIGMA = 1.0


def _gm_closed_form(x):
    """v' = b, b' = −b/τ + w (Q_c = 2σ²/τ) over Δt = xτ, in 50-digit arithmetic.

    Φ_bb = e^{−x}, Φ_vb = τ(1 − e^{−x}); Q_bb = σ²(1 − e^{−2x}),
    Q_vb = σ²τ(1 − e^{−x})², Q_vv = σ²τ²(2x − 3 + 4e^{−x} − e^{−2x})
    (the last cancels badly in double precision for small x).
    """
    import mpmath as mp

    with mp.workdps(50):
        x = mp.mpf(x)
        e1, e2 = mp.exp(-x), mp.exp(-2 * x)
        phi = [[1, TAU * (1 - e1)], [0, e1]]
        q = [[SIGMA**2 * TAU**2 * (2 * x - 3 + 4 * e1 - e2), SIGMA**2 * TAU * (1 - e1) ** 2],
             [SIGMA**2 * TAU * (1 - e1) ** 2, SIGMA**2 * (1 - e2)]]
        return (np.array([[float(v) for v in r] for r in phi]), np.array([[float(v) for v in r] for r in q]))


GM_F = np.array([[[0.0, 1.0], [0.0, -1.0 / TAU]]])
GM_QC = np.array([[[0.0, 0.0], [0.0, 2 * SIGMA**2 / TAU]]])


@pytest.mark.parametrize("x", [0.01, 0.1, 1.0, 30.0, 45.0, 1000.0])
def test_gauss_markov_closed_form_any_step(x):
    """Every exact discretiser = the Gauss–Markov closed forms, Δt/τ = 0.01 … 1000.

    Issue 9 case 1: the old Van Loan exponential gave Q_vv = 3.55e11 at
    Δt/τ = 30 and −7.2e25 at 45 (closed form 22 800 and 34 800).  Required
    1e-12 relative on every element (measured ≤ 4e-15).
    """
    Phi_r, Q_r = _gm_closed_form(x)
    dt = x * TAU
    results = {"van_loan": van_loan(GM_F, GM_QC, dt), "taylor": taylor(GM_F, GM_QC, dt),
               "block_triangular": block_triangular(GM_F, GM_QC, dt, 1)}
    Qs = per_source(GM_F, np.array([[[0.0], [1.0]]]), np.array([[2 * SIGMA**2 / TAU]]), dt)
    for name, (Phi, Qd) in results.items():
        np.testing.assert_allclose(Phi[0], Phi_r, rtol=1e-12, atol=0, err_msg=name)
        np.testing.assert_allclose(Qd[0], Q_r, rtol=1e-12, atol=0, err_msg=name)
    np.testing.assert_allclose(Qs[0, 0], Q_r, rtol=1e-12, atol=0, err_msg="per_source")
    if x in (30.0, 45.0):
        assert Q_r[0, 0] == pytest.approx(400.0 * (2 * x - 3), rel=1e-12)    # 22 800, 34 800


@pytest.mark.parametrize("dt", [8.0, 10.0, 20.0, 1e4])
def test_adaptive_taylor_converges_for_any_step(dt):
    """taylor(F = −1, Q_c = 2) = 1 − e^{−2Δt} (issue 9 case 2: 2.29, 9035, 7.5e15 before).

    It reports its terms and squarings: νΔt = Δt, so s = ⌈log₂(Δt/θ)⌉
    halvings, and at νh ≤ 0.5 the base series needs at most 20 terms.
    """
    Phi, Qd, info = taylor(np.full((1, 1, 1), -1.0), np.full((1, 1, 1), 2.0), dt, info=True)
    assert Qd[0, 0, 0] == pytest.approx(-math.expm1(-2 * dt), rel=1e-13)
    assert Phi[0, 0, 0] == pytest.approx(math.exp(-dt), rel=1e-11, abs=0.0)
    assert info.squarings[0] == math.ceil(math.log2(dt / THETA))
    assert 5 <= info.terms[0] <= 20
    assert taylor_terms(np.full((1, 1, 1), -1.0), np.full((1, 1, 1), 2.0), dt).terms[0] == info.terms[0]


def test_truncated_series_refused_where_it_diverges():
    """A fixed order N_t is refused when 2νΔt ≥ N_t, naming filter, step and what to change.

    Markov state τ = 10 s at Δt = 5 min (issue 9 case 2): νΔt = 30.
    """
    F = np.full((3, 1, 1), -0.1)
    Qc = np.full((3, 1, 1), 2 * (100e-6 * 9.80665) ** 2 / 10)
    with pytest.raises(InputError, match=r"filters.toml: filter 'B1': taylor_order: the 3-term Taylor series .* "
                                         r"diverges at step 0 \(t = 0 s, Δt = 300 s\): νΔt = 30 ≥ N_t/2 = 1.5 .*"
                                         r"use dt < 15 s, taylor_order ≥ 61, or the exact discretisation"):
        taylor(F, Qc, 300.0, order=3, what="filters.toml: filter 'B1'", times=np.array([0.0, 300, 600]))
    # just inside the criterion: accepted (2 · 0.1 · 14.9 = 2.98 < 3), and the partial sums are returned
    Phi, _ = taylor(F, Qc, 14.9, order=3)
    assert Phi[0, 0, 0] == pytest.approx(1 - 1.49 + 1.49**2 / 2, rel=1e-14)
    for bad in (0, -1, 101, 2.5, "x", True):
        with pytest.raises(InputError, match=r"taylor_order: .* is not an integer from 1 to 100"):
            taylor(F, Qc, 1.0, order=bad)


def test_unstable_vertical_channel_exact_or_refused():
    """δḣ = δv, δv̇ = ω²δh (ω² = 2g/R): cosh/sinh exact while representable, else refused.

    Q_d of a white acceleration (PSD q) on δv:
    Q_hh = q (sinh(2ωΔt)/(2ω) − Δt)/(2ω²).  Required 1e-11 at ωΔt = 50
    and 300 (e^300 = 2e130); at ωΔt = 800, e^800 overflows: NumericalError.
    """
    w = math.sqrt(2 * 9.80665 / 6.371e6)
    F = np.array([[[0.0, 1.0], [w * w, 0.0]]])
    q = 1e-6
    Qc = np.array([[[0.0, 0.0], [0.0, q]]])
    for wt in (50.0, 300.0):
        dt = wt / w
        Phi, Qd = van_loan(F, Qc, dt)
        np.testing.assert_allclose(Phi[0], [[math.cosh(wt), math.sinh(wt) / w], [w * math.sinh(wt), math.cosh(wt)]],
                                   rtol=1e-11)
        assert Qd[0, 0, 0] == pytest.approx(q * (math.sinh(2 * wt) / (2 * w) - dt) / (2 * w * w), rel=1e-11)
    with pytest.raises(NumericalError, match=r"vertical: step 0 \(t = 0 s, Δt = 455951 s\): Φ or Q_d "
                                             r"overflows \(νΔt = "):
        van_loan(F, Qc, 800 / w, what="vertical", times=np.array([0.0]))


def test_schuler_oscillator_long_steps():
    """δẍ = −ω_s² δx: Φ = rotation by ω_sΔt, exact (1e-10) over steps of up to 200 periods."""
    w = math.sqrt(9.80665 / 6.371e6)
    F = np.array([[[0.0, 1.0], [-w * w, 0.0]]])
    for wt in (0.3, 30.0, 1256.0):
        Phi, _ = taylor(F, np.zeros_like(F), wt / w)
        S = np.diag([w, 1.0])                     # ω_s δx, δẋ: Φ is a plane rotation
        np.testing.assert_allclose(S @ Phi[0] @ np.linalg.inv(S),
                                   [[math.cos(wt), math.sin(wt)], [-math.sin(wt), math.cos(wt)]], rtol=0, atol=1e-10)


def test_non_finite_input_is_refused():
    F = np.full((2, 1, 1), -1.0)
    F[1, 0, 0] = np.nan
    with pytest.raises(NumericalError, match=r"truth: step 1 \(Δt = 1 s\): F has non-finite entries"):
        van_loan(F, np.ones((2, 1, 1)), 1.0, what="truth")
    with pytest.raises(ValueError, match=r"step 0 \(Δt = -1 s\): the step must be finite and non-negative"):
        van_loan(F[:1], np.ones((1, 1, 1)), -1.0)
    with pytest.raises(ValueError, match="not block triangular"):
        block_triangular(np.array([[[0.0, 1.0], [1.0, 0.0]]]), np.zeros((1, 2, 2)), 1.0, 1)


def test_zero_length_steps_are_the_identity_without_noise(dyn, monkeypatch):
    """Δt = 0 is a valid step: Φ = I and Q_d = 0 exactly, on every exact path; the other steps as without it.

    Before, a step of Δt = 0 with noise was refused ("did not converge"): its
    Q_d sums stay zero, so the element-wise tail rule, relative to them,
    never held.  Checked on the 58-state model through the folded random
    constants (van_loan), the dense series (taylor on all states), the
    sensor blocks (block_triangular), per-source noise, fixed-order Taylor
    and the terms it reports; zero steps alone, among others, and in a run
    of repeated steps (the de-duplicated path).  The other steps are
    compared with the stack without the zero ones to round-off (1e-14: a
    stack's balancing depends on its steps).
    """
    from covtool.lincov.discretize import sensor_states, structured

    def _dense(F_, Q_, d):
        with monkeypatch.context() as mp:                   # no sensor blocks: the dense series of all states
            mp.setattr(structured, "BLOCK_FRACTION", 2.0)
            return structured._exact(F_, Q_, d, "", None)[:2]

    F, Qc = dyn
    Fs, Qs = F[:6], Qc[:6]
    n = F.shape[1]
    sens = np.r_[np.flatnonzero(~sensor_states(Fs, Qs)), np.flatnonzero(sensor_states(Fs, Qs))]
    k = int(np.count_nonzero(~sensor_states(Fs, Qs)))
    Fb, Qb = Fs[:, sens][:, :, sens], Qs[:, sens][:, :, sens]
    paths = {
        "van_loan": lambda F_, Q_, d: van_loan(F_, Q_, d),
        "taylor": lambda F_, Q_, d: taylor(F_, Q_, d),
        "taylor(order=8)": lambda F_, Q_, d: taylor(F_, Q_, d, 8),
        "dense": lambda F_, Q_, d: _dense(F_, Q_, d),
        "block_triangular": lambda F_, Q_, d: block_triangular(F_, Q_, d, k),
    }
    for dts in ([0.0], [0.0, 0.0], [1.0, 0.0, 2.0, 0.0, 0.5, 0.0], [0.0, 1.0, 1.0, 1.0, 1.0, 1.0]):
        dts = np.array(dts)
        N = dts.size
        zero = dts == 0
        for name, fn in paths.items():
            FF, QQ = (Fb, Qb) if name == "block_triangular" else (Fs, Qs)
            if dts[1:].size and (dts[1:] == 1.0).all():     # a run of equal steps after the zero one
                FF, QQ = np.repeat(FF[1:2], N, axis=0), np.repeat(QQ[1:2], N, axis=0)
            Phi, Qd = fn(FF[:N], QQ[:N], dts)
            np.testing.assert_array_equal(Phi[zero], np.broadcast_to(np.eye(n), (zero.sum(), n, n)), err_msg=name)
            assert not Qd[zero].any(), name
            if (~zero).any():
                P1, Q1 = fn(FF[:N][~zero], QQ[:N][~zero], dts[~zero])
                assert _phi_error(Phi[~zero], P1) <= 1e-14, name
                assert _q_error(Qd[~zero], Q1) <= 1e-14, name
        info = taylor_terms(Fs[:N], Qs[:N], dts)
        assert (info.squarings[zero] == 0).all() and (info.norm_dt[zero] == 0).all()
        G = np.repeat(np.eye(n)[None, :, 10:14], N, axis=0)
        psd = np.ones((N, 4))
        Qp = per_source(Fs[:N], G, psd, dts)
        assert not Qp[zero].any()
        if (~zero).any():
            np.testing.assert_allclose(Qp[~zero], per_source(Fs[:N][~zero], G[~zero], psd[~zero], dts[~zero]),
                                       rtol=1e-14, atol=0)
            assert (Qp[~zero].sum(axis=1) != 0).any()


def test_every_guard_names_the_step(monkeypatch):
    """Non-PSD Q_d, a series that stops short, bad shapes and non-finite noise: each refused by name."""
    from covtool.lincov import discretize as dz

    Q = np.zeros((3, 2, 2))
    Q[:] = np.eye(2)
    Q[2] = [[1.0, 2.0], [2.0, 1.0]]                      # correlation 2: eigenvalue −1
    with pytest.raises(NumericalError, match=r"sys: step 2 \(t = 20 s, Δt = 10 s\): Q_d is not positive "
                                             r"semi-definite \(smallest eigenvalue of its correlation matrix -1\)"):
        dz.check_qd(Q, "sys", dt=np.full(3, 10.0), times=np.array([0.0, 10.0, 20.0]))
    Q[2] = [[-1.0, 0.0], [0.0, 1.0]]
    with pytest.raises(NumericalError, match=r"step 2 \(Δt = nan s\): Q_d is not positive semi-definite"):
        dz.check_qd(Q)
    monkeypatch.setattr(dz.series, "MAX_TERMS", 3)
    with pytest.raises(NumericalError, match=r"step 0 \(Δt = 0.5 s\): the series of eq \(6b\)-\(6d\) did not "
                                             r"converge in 3 terms at νh = 0.5"):
        dz.taylor(np.full((1, 1, 1), -1.0), np.ones((1, 1, 1)), 0.5)
    monkeypatch.undo()
    with pytest.raises(ValueError, match=r"F must have shape \(N, n, n\), got \(2, 2\)"):
        van_loan(np.eye(2), np.eye(2), 1.0)
    with pytest.raises(NumericalError, match=r"budget: step 0 \(Δt = 1 s\): G has non-finite entries"):
        per_source(np.full((1, 1, 1), -1.0), np.full((1, 1, 1), np.inf), np.ones((1, 1)), 1.0, what="budget")
    with pytest.raises(NumericalError, match=r"budget: step 0 \(Δt = 800 s\): Q_d overflows \(νΔt = 800\)"):
        per_source(np.full((1, 1, 1), 1.0), np.ones((1, 1, 1)), np.ones((1, 1)), 800.0, what="budget")
    # representable: Q_d = (e^{2Δt} − 1)/2 for ẋ = x + w
    Qs = per_source(np.full((1, 1, 1), 1.0), np.ones((1, 1, 1)), np.ones((1, 1)), 300.0)
    assert Qs[0, 0, 0, 0] == pytest.approx(math.expm1(600.0) / 2, rel=1e-12)


def test_repeated_steps_are_computed_once_and_exactly(dyn):
    """A stack with runs of equal steps (a stop) equals each step computed alone.

    The discretisers compute each run of equal (F, Q_c, Δt) once
    (:func:`covtool.lincov.discretize.repeated_steps`); every step of the
    expanded result must be the lone computation of that step, and a bad
    step inside a repeated run is still named by its own index.
    """
    from covtool.lincov.discretize import repeated_steps

    F, Qc = dyn
    idx = np.r_[0, 0, 0, 1, 2, 2, 2, 2, 3, 0]             # stops: equal consecutive steps
    Fs, Qs = F[idx], Qc[idx]
    first, inv = repeated_steps(Fs, Qs, np.ones(idx.size))
    np.testing.assert_array_equal(first, [0, 3, 4, 8, 9])
    np.testing.assert_array_equal(first[inv], [0, 0, 0, 3, 4, 4, 4, 4, 8, 9])
    for fn in (lambda F_, Q_: van_loan(F_, Q_, 1.0), lambda F_, Q_: taylor(F_, Q_, 1.0, 6)):
        Phi, Qd = fn(Fs, Qs)
        for k in range(idx.size):
            P1, Q1 = fn(Fs[k:k + 1], Qs[k:k + 1])
            assert _phi_error(Phi[k], P1[0]) <= 1e-14
            assert _q_error(Qd[k], Q1[0]) <= 1e-14
    G = np.repeat(np.eye(58)[None, :, 10:14], idx.size, axis=0)
    psd = np.ones((idx.size, 4))
    Qp = per_source(Fs, G, psd, 1.0)
    for k in (2, 6, 9):
        np.testing.assert_allclose(Qp[k], per_source(Fs[k:k + 1], G[:1], psd[:1], 1.0)[0], rtol=1e-14, atol=0)
    bad = Fs.copy()
    bad[6:8] = np.inf                                     # a repeated run of bad steps: step 6 is named
    with pytest.raises(NumericalError, match=r"step 6 \(Δt = 1 s\): F has non-finite entries"):
        van_loan(bad, Qs, 1.0)


def test_sensor_states_by_blocks_equal_the_dense_series(dyn, monkeypatch):
    """The exact discretisation by blocks equals the dense series (58-state model, 1 s and 30 s).

    The 58-state model has 45 sensor states (36 random constants and the
    Markov/random-walk states, each driven by nothing but itself and its own
    noise): moved after the 13 navigation and reset states, F is block
    triangular and the series is summed by blocks.  Forcing the dense path
    (``BLOCK_FRACTION`` above 1) must give the same Φ and Q_d to round-off.
    """
    from covtool.lincov import discretize as dz

    F, Qc = dyn
    sens = dz.sensor_states(F, Qc)
    assert sens.sum() == 45 and not sens[:10].any()
    for dt in (1.0, 30.0):
        Pb, Qb = van_loan(F, Qc, dt)
        with monkeypatch.context() as mp:
            mp.setattr(dz.structured, "BLOCK_FRACTION", 2.0)
            Pd, Qd = van_loan(F, Qc, dt)
        assert _phi_column_error(Pb, Pd) <= 1e-14
        assert _q_error(Qb, Qd) <= 1e-14


def test_transition_alone_by_blocks_is_the_exponential(dyn):
    """Without noise the block series sums Φ alone: Q_d = 0 exactly, Φ that of the noisy system.

    (Without noise the random walks are random constants too, folded out
    (:func:`covtool.lincov.discretize.methods._exact_constants`): a smaller
    system, balanced and scaled on its own, so Φ agrees to round-off, not
    bit for bit.)  Φ is checked against ``scipy.linalg.expm`` (independent)
    at 1 s and 30 s.
    """
    F, Qc = dyn
    for dt in (1.0, 30.0):
        Pn, _ = van_loan(F[:40], Qc[:40], dt)
        P0, Q0 = van_loan(F[:40], np.zeros_like(Qc[:40]), dt)
        assert _phi_column_error(P0, Pn) <= 1e-13
        assert not Q0.any()
        ref = np.array([expm(F[k] * dt) for k in (0, 17, 39)])
        assert _phi_column_error(P0[[0, 17, 39]], ref) <= 1e-13


def test_per_source_groups_equal_the_summed_columns(dyn):
    """``per_source(groups=…)`` equals the per-column Q_d summed by group, and sums to Van Loan's Q_d.

    Checked on the 58-state model at 1 s and 30 s (squared steps): each
    group is the sum of its columns' ``Q_d`` (correlation scaling of the
    total, ≤ 1e-13) and all groups together equal the Van Loan ``Q_d`` of
    ``Q_c = G diag(psd) Gᵀ`` (≤ 1e-12).
    """
    F, Qc = dyn
    F = F[:8]
    # a low-rank Q_c: the noise columns of the model's diagonal Q_c
    dg = np.einsum("kii->ki", Qc[:8])
    cols = np.flatnonzero(dg.max(axis=0) > 0)
    G = np.repeat(np.eye(58)[None][:, :, cols], 8, axis=0)
    psd = dg[:, cols]
    starts = np.array([0, 3, 5])
    for dt in (1.0, 30.0):
        Qp = per_source(F, G, psd, dt)
        Qg = per_source(F, G, psd, dt, groups=starts)
        assert Qg.shape == (8, 3, 58, 58)
        tot = Qp.sum(axis=1)
        for j, (a, b) in enumerate(zip(starts, np.r_[starts[1:], cols.size])):
            d = np.sqrt(np.einsum("kii->ki", tot))
            d = np.where(d > 0, d, 1.0)
            assert np.max(np.abs(Qg[:, j] - Qp[:, a:b].sum(axis=1)) / d[:, :, None] / d[:, None, :]) <= 1e-13
        _, Qv = van_loan(F, G * psd[:, None, :] @ np.swapaxes(G, 1, 2), dt)
        assert _q_error(Qg.sum(axis=1), Qv) <= 1e-12


def test_random_constants_folded_out_closed_form():
    """A Markov state driven by a random constant: Φ_dc = b (1 − e^{−aΔt})/a, the constant's Φ = 1, no Q_d.

    x' = −a x + b c + w (PSD q), c' = 0: the folded path (:func:`_exact_constants`) against the closed form,
    for steps short and long against 1/a.
    """
    a, b, q = 0.05, 3.0, 2e-4
    for dt in (0.5, 1.0, 60.0):
        N = 3
        F = np.zeros((N, 4, 4))
        F[:, 0, 0] = -a
        F[:, 0, 1] = b                            # state 1 and 3: random constants; 1 drives 0
        F[:, 0, 3] = -2.0 * b
        F[:, 2, 2] = -2.0 * a                     # state 2: an undriven Markov state (no constant)
        Qc = np.zeros_like(F)
        Qc[:, 0, 0] = q
        Qc[:, 2, 2] = q
        assert dz_methods.random_constants(F, Qc).tolist() == [False, True, False, True]
        Phi, Qd = van_loan(F, Qc, dt)
        e = np.exp(-a * dt)
        np.testing.assert_allclose(Phi[:, 0, 0], e, rtol=1e-15)
        np.testing.assert_allclose(Phi[:, 0, 1], b * (1 - e) / a, rtol=1e-14)
        np.testing.assert_allclose(Phi[:, 0, 3], -2.0 * b * (1 - e) / a, rtol=1e-14)
        np.testing.assert_array_equal(Phi[:, [1, 3]][:, :, [1, 3]], np.broadcast_to(np.eye(2), (N, 2, 2)))
        np.testing.assert_allclose(Qd[:, 0, 0], q * (1 - e**2) / (2 * a), rtol=1e-14)
        np.testing.assert_allclose(Qd[:, 2, 2], q * (1 - np.exp(-4 * a * dt)) / (4 * a), rtol=1e-14)
        assert not Qd[:, [1, 3]].any() and not Qd[:, :, [1, 3]].any()


def test_random_constants_folded_out_equal_the_whole_system(dyn):
    """The 58-state model's 36 random constants folded out: the same Φ and Q_d as the whole system (1 s, 30 s)."""
    from covtool.lincov.discretize.structured import _exact

    F, Qc = dyn
    assert dz_methods.random_constants(F, Qc).sum() == 36
    for dt in (1.0, 30.0):
        Pf, Qf = van_loan(F, Qc, dt)
        Pw, Qw, _ = _exact(F, Qc, np.full(F.shape[0], dt), "", None)
        assert _phi_column_error(Pf, Pw) <= 1e-14
        assert _q_error(Qf, Qw) <= 1e-14
        Pt, Qt = taylor(F, Qc, dt)                               # the adaptive eq (6b)-(6d): the same series
        np.testing.assert_array_equal(Pt, Pf)
        np.testing.assert_array_equal(Qt, Qf)


def _block_systems():
    """F, Q_c of block form, sensor states last: the 58-state model at 40 route points, and 60 synthetic steps.

    The synthetic steps ``F = [[A, M], [0, diag(d)]]``, ``Q_c = blockdiag(Q_A, diag(q))``
    (k = 4, m = 5) scale ``A``, ``M``, ``Q_A`` and ``q`` over four to ten decades
    each (``Q_A`` or some ``q`` zero at some steps), so that the blocks of
    ``T_i`` and ``C_i`` set the stopping term in turn.
    """
    rng = np.random.default_rng(7)
    k, m, N = 4, 5, 60
    n = k + m
    F = np.zeros((N, n, n))
    Qc = np.zeros((N, n, n))
    F[:, :k, :k] = rng.normal(size=(N, k, k)) * 10.0 ** rng.uniform(-4, 0, (N, 1, 1))
    F[:, :k, k:] = rng.normal(size=(N, k, m)) * 10.0 ** rng.uniform(-4, 2, (N, 1, 1))
    F[:, np.arange(k, n), np.arange(k, n)] = -10.0 ** rng.uniform(-3, 0, (N, m))
    L = rng.normal(size=(N, k, k))
    Qc[:, :k, :k] = L @ np.swapaxes(L, 1, 2) * 10.0 ** rng.uniform(-6, 2, (N, 1, 1)) * (rng.random((N, 1, 1)) < 0.7)
    Qc[:, np.arange(k, n), np.arange(k, n)] = 10.0 ** rng.uniform(-6, 4, (N, m)) * (rng.random((N, m)) < 0.8)
    return F, Qc


@pytest.mark.parametrize("dt", [0.25, 1.0, 4.0])
def test_block_series_stops_where_the_dense_series_stops(dyn, dt):
    """The block-triangular series takes the dense series' terms at every step, and the same sums.

    ``_block_series`` evaluates the stopping rule of ``_series`` by blocks and
    in stages (a partial maximum first, the rest only while some step can
    pass): its decisions must be those of the dense rule on the whole
    ``T_i`` and ``C_i``.  On the 58-state model at 40 points of the route
    (sensor states moved after the others) and on synthetic steps in which
    each block in turn sets the stopping term (:func:`_block_systems`), steps
    0.25–4 s: the terms equal step by step, Φ − I to 1e-13 of each column's
    scale and Q_d to 1e-13 of √(Q_ii Q_jj) (measured: ≤ 3e-16).  Leaving the
    ``[TM; diag(TD)]`` columns, the ``Q_A`` block or the sensor diagonal out of
    the rule changes the terms of some synthetic step (checked by editing the
    rule; the cross block ``Q_X`` set no step's term on these systems).
    """
    from covtool.lincov.discretize.series import _balanced, _series, balancing, reach, scaling, sensor_states
    from covtool.lincov.discretize.structured import _block_series

    F_syn, Q_syn = _block_systems()
    for F, Qc in (dyn, (F_syn, Q_syn)):
        sens = sensor_states(F, Qc)
        k = int(np.count_nonzero(~sens))
        assert 4 <= k < F.shape[1]
        p = np.r_[np.flatnonzero(~sens), np.flatnonzero(sens)]     # the sensor states last, as _exact orders them
        F, Qc = F[:, p[:, None], p[None, :]], Qc[:, p[:, None], p[None, :]]
        d = balancing(F)
        B, Qb, nu = _balanced(F, Qc, d)
        _, h = scaling(nu, np.full(F.shape[0], dt))
        E_d, Q_d, terms_d, done_d = _series(B, Qb, h, nu, minus_identity=True)
        rch = reach(B, np.einsum("kii->ki", Qb) > 0)
        E_b, Q_b, terms_b, done_b = _block_series(B[:, :k, :k], B[:, :k, k:], np.einsum("kii->ki", B[:, k:, k:]),
                                                  Qb[:, :k, :k], np.einsum("kii->ki", Qb[:, k:, k:]), h, nu, rch)
        assert done_d.all() and done_b.all()
        np.testing.assert_array_equal(terms_b, terms_d)
        assert _phi_error(E_b, E_d) <= 1e-13
        s = np.sqrt(np.clip(np.einsum("kii->ki", Q_d), 0.0, None))
        den = np.maximum(s[:, :, None] * s[:, None, :], 1e-300)
        assert float(np.max(np.abs(Q_b - Q_d) / den)) <= 1e-13


@pytest.mark.parametrize("k", [2, 9])
def test_reach_follows_paths_of_any_length_per_step(k):
    """``reach``: the states a path of couplings leads to from each seed, step by step.

    A chain 0 → 1 → … → 5 at step 0 (``B[i+1, i] ≠ 0``: state i drives i+1)
    and no couplings at step 1; state 6 drives itself only.  With more seed
    columns than states (k = 9) ``reach`` takes the closure by squaring, with
    fewer (k = 2) the path-by-path fixed point: the same sets, written out.
    """
    from covtool.lincov.discretize.series import reach

    n = 7
    B = np.zeros((2, n, n))
    B[0, np.arange(1, 6), np.arange(0, 5)] = 0.5
    B[:, 6, 6] = -1.0
    seed = np.zeros((2, n, k), bool)
    seed[:, 2, 0] = True                         # column 0 seeds state 2
    seed[:, 6, 1] = True                         # column 1 seeds state 6
    R = reach(B, seed)
    want0 = np.zeros((n, k), bool)
    want0[2:6, 0] = True
    want0[6, 1] = True
    want1 = np.zeros((n, k), bool)
    want1[2, 0] = want1[6, 1] = True
    np.testing.assert_array_equal(R[0], want0)
    np.testing.assert_array_equal(R[1], want1)
    np.testing.assert_array_equal(reach(B, seed[:, :, 0]), R[:, :, 0])   # a vector seed: the same set
    assert reach(np.zeros((2, 0, 0)), np.zeros((2, 0), bool)).shape == (2, 0)   # no states: the seed's shape
