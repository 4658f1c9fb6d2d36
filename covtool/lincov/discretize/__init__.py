"""Discretisation of ``ẋ = F x + G w``: Van Loan's integral and seed 002's Taylor series.

Every function takes stacks of matrices (leading step axis) and returns
``Φ = e^{FΔt}`` and ``Q_d = ∫₀^Δt e^{Fs} Q_c e^{Fᵀs} ds`` (Van Loan 1978) for
every step.

Exact for any step
------------------
:func:`van_loan`, the adaptive :func:`taylor` (``order=None``),
:func:`block_triangular` and :func:`per_source` are exact to round-off for
any ``Δt``, or raise :class:`~covtool.errors.NumericalError` naming the step
when the result is not representable (an unstable mode that overflows):

1. *Balancing.*  ``F̃ = D⁻¹ F D`` and ``Q̃_c = D⁻¹ Q_c D⁻¹`` with ``D``
   diagonal, made of powers of two (LAPACK ``gebal`` on the envelope
   ``max_k |F_k|`` of the stack): a change of the states' units, exact in
   floating point, after which ``ν = max(‖F̃‖₁, ‖F̃‖_∞) ≥ ‖F̃‖₂`` measures how
   fast the dynamics really are.  For the 58-state INS model ``‖F‖₁`` is
   20–30 s⁻¹ in SI units but ``ν = 0.05–0.14 s⁻¹``, near the rate of its
   fastest Markov state (1/20 s).
2. *Scaling.*  A step with ``νΔt > θ`` (:data:`THETA`) is computed over
   ``h = Δt/2^s``, ``s = ⌈log₂(νΔt/θ)⌉``, so that ``νh ≤ θ``.
3. *Base step*: the series of eq (6b)–(6d) at ``h``, summed until the
   rigorous bound of its tail is below ``2⁻⁵³`` of the sum, column by column
   for Φ and element by element (correlation scaling) for ``Q_d``
   (:func:`_series`).
4. *Squaring*, ``s`` times (an exact identity, the integral over ``[0, 2h]``
   split at ``h``)::

       Φ(2h) = Φ(h)²,    Q_d(2h) = Φ(h) Q_d(h) Φ(h)ᵀ + Q_d(h)

Why: Van Loan's matrix ``[[−F, Q_c], [0, Fᵀ]]Δt`` holds ``e^{−FΔt}``, which
grows as ``e^{Δt/τ}`` for a Markov state of time constant τ; ``Q_d``
recovered as ``Φ · (Φ⁻¹Q_d)`` then has a relative error of about
``2⁻⁵³ e^{2Δt/τ}`` (``Q_vv = 3.55e11`` instead of 22 800 at ``Δt/τ = 30``),
and its normwise accuracy loses the small variances of integrated states at
short steps (3e-10 relative on the altitude variance of an IMU model at
0.04 s).  The series of eq (6b) has terms ``(FΔt)^i/i!`` that grow until
``i ≈ ‖FΔt‖``; summed to a fixed cap (40 terms) it returned ``Q_d = 7.5e15``
for ``F = −1, Δt = 20`` (exact: 1).  Squaring is stable for stable ``F``
(each update adds a PSD term to a contracted PSD matrix) and exact for
unstable ``F`` until ``Φ`` overflows.  So :func:`van_loan` and the adaptive
:func:`taylor` compute the same converged series: the integral of Van Loan
is seed 002's series summed to convergence.

Truncated series (seed 002's filters)
-------------------------------------
``taylor(order=N_t)`` is the paper's deliberate truncation over the whole
``Δt`` (no scaling), which the filters model.  It is refused when it is
meaningless: with ``a = νΔt`` the terms of eq (6b) shrink by at least the
factor ``a/(i+1)`` and those of eq (6c) by ``2a/(i+1)`` per order
(``‖C_i‖ ≤ 2‖F̃‖₂ ‖C_{i−1}‖`` for symmetric ``C``), so for ``2νΔt < N_t``
every omitted term is smaller than the last one kept and the truncation
error is at most the first omitted term over ``1 − 2νΔt/(N_t+1)``.  For
``2νΔt ≥ N_t`` that guarantee is gone, and for a Markov state (``ν = 1/τ``)
the first omitted term of eq (6c) is then really as large as the last one
kept: the series has not begun to converge (for ``N_t = 3``,
``Q_d = q Δt (1 − Δt/τ)`` is negative beyond ``Δt = τ``).  Hence the
refusal criterion ``2νΔt ≥ N_t``, i.e. ``Δt ≥ N_t τ/2`` for the fastest
Markov state.

Layout
------
:mod:`~covtool.lincov.discretize.limits`
    every limit and tolerance (``THETA``, ``MAX_TERMS``, ``MAX_ORDER``, ``PSD_TOL`` …).
:mod:`~covtool.lincov.discretize.steps`
    :class:`StepInfo`, :func:`repeated_steps`, input checks, :func:`check_qd`.
:mod:`~covtool.lincov.discretize.series`
    balancing, scaling, the series of eq (6b)–(6d) and squaring.
:mod:`~covtool.lincov.discretize.structured`
    :func:`block_triangular` and the sensor-state block path.
:mod:`~covtool.lincov.discretize.sources`
    :func:`per_source` (``Q_d`` of each noise source).
:mod:`~covtool.lincov.discretize.methods`
    :func:`van_loan`, :func:`taylor`, :func:`taylor_terms`, :func:`discretize`.
"""

from covtool.lincov.discretize.steps import PSD_TOL, StepInfo, check_qd, repeated_steps
from covtool.lincov.discretize.series import (
    MAX_ORDER, MAX_TERMS, THETA, UNIT_ROUNDOFF, balancing, reach, scaling, sensor_states)
from covtool.lincov.discretize.structured import BLOCK_FRACTION, block_triangular, is_block_triangular
from covtool.lincov.discretize.sources import per_source
from covtool.lincov.discretize.methods import discretize, taylor, taylor_terms, van_loan

__all__ = ["StepInfo", "THETA", "BLOCK_FRACTION", "balancing", "block_triangular", "check_qd", "discretize",
           "is_block_triangular",
           "per_source", "reach", "repeated_steps", "scaling", "sensor_states", "taylor", "taylor_terms", "van_loan"]
