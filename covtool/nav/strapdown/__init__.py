"""Strapdown mechanization: the nonlinear reference of the linear model.

Quaternion/NED strapdown navigation driven by IMU increments (``Δθ``,
``Δv``), with the 4-sample + 1-previous coning and sculling compensation of
seed 001 (eq (1)–(4), Figs 9–10).  It is vectorised over an ensemble: every
array carries a leading run axis ``M``, so one :func:`step` advances all
Monte-Carlo runs at once.

Conventions are those of :mod:`covtool` (SI, NED, ``q`` scalar first and
body→NED) and of the linear error model (:mod:`covtool.lincov.dynamics`): error =
computed − true, position errors ``(δL, δl, δh)``, velocity ``δv^n`` and the
additive quaternion error ``δq = q̂ − q`` (seed 002, eq (1)), in the state
order of seed 002, eq (14) (:data:`NAV_STATES`).

Algorithm (one navigation interval ``T = t_m − t_{m−1}``)
--------------------------------------------------------
The interval holds ``n`` IMU samples ``Δθ_1 … Δθ_n``, ``Δv_1 … Δv_n``
(sample ``0`` is the last sample of the previous interval).

*Body increments*: the compensated rotation vector ``φ`` and velocity
increment ``Δv_b`` of the interval, with the n-sample + 1-previous coning
and sculling of seed 001 eq (1)–(4) (:mod:`covtool.nav.coning`).

*Navigation frame* (second order, predictor–corrector at the mid-interval)::

    ζ = (ω_ie^n + ω_en^n)(t_{m−½}) T
    q_m = exp(−ζ/2) ⊗ q_{m−1} ⊗ exp(φ/2)                        (normalised)
    Δv_gc = [g^n − (2ω_ie^n + ω_en^n) × v^n](t_{m−½}) T
    v_m = v_{m−1} + (I − ½[ζ×]) C Δv_b + Δv_gc,        C = C_b^n(t_{m−1})
    ΔR = T [v_{m−1} + C r − ⅙ ζ × C Δv_b + ½ Δv_gc]
    (L, l, h)_m = (L, l, h)_{m−1} + (ΔR_N/(R_M+h), ΔR_E/((R_N+h) cos L), −ΔR_D)   (radii at t_{m−½})

``r = Σ_i (n − i + ½)/n Δv_i + α×υ/6`` (:func:`covtool.nav.coning.body_position_increment`)
weights each sample's specific force at its mid-time, so ``∫v dt`` is
exact for a linearly varying specific force up to ``O(h²)`` rather than
the ``O(T²)`` of the trapezoid (Savage 1998 Part 2, position algorithm).
The mid-interval position and velocity come from a predictor pass with
the start-of-interval rates, so the step is self-starting and a filter may
correct the state between steps (:func:`correct`, seed 002 eq (10)).

Two IMUs at different rates (seed 001 §2.3, Figs 7–10)
------------------------------------------------------
Both navigation solutions run on the *main* interval: the main IMU's
sample period (``n = 1``, the 1-sample + 1-previous algorithm, coefficient
1/12) or a multiple of it.  A second IMU at ``r`` times the main rate
delivers ``r`` samples per interval and runs the ``r``-sample algorithm
(the KIMU of seed 001: ``r = 4``, eq (2) and (4)).  :func:`group_samples`
assigns each sample to the main interval in which its period ends and
refuses a grouping with missing or extra samples rather than dropping data
(the paper's circular queue guarantees none are lost).

References
----------
P. G. Savage, "Strapdown inertial navigation integration algorithm design,
Part 1: Attitude algorithms; Part 2: Velocity and position algorithms",
J. Guid. Control Dyn. 21(1)–(2), 1998 (seed 001 ref [6]).
M. B. Ignagni, "Efficient class of optimized coning compensation
algorithms", J. Guid. Control Dyn. 19(2), 1996.
K. M. Roscoe, "Equivalency between strapdown inertial navigation coning and
sculling integrals/algorithms", J. Guid. Control Dyn. 24(2), 2001.

Layout
------
:mod:`~covtool.nav.strapdown.state`
    :data:`NAV_STATES`, :class:`NavState`, :func:`truth_state`,
    :func:`correct`, :func:`nav_errors`.
:mod:`~covtool.nav.strapdown.mechanization`
    the numpy reference: :func:`step` and ``_nav_core``.
:mod:`~covtool.nav.strapdown.kernels`
    the compiled numba kernels (the same arithmetic for scalars).
:mod:`~covtool.nav.strapdown.records`
    :class:`NavHistory`, :func:`group_samples`, :func:`iter_intervals`, :func:`run`.
"""

from covtool.nav.strapdown.state import NAV_STATES, NavState, _pack, _unpack, correct, nav_errors, truth_state
from covtool.nav.strapdown.mechanization import _check_increments, _nav_core, _rotvec_quat, step
from covtool.nav.strapdown.records import NavHistory, group_samples, iter_intervals, run


def __getattr__(name):
    # the compiled kernels import numba (0.3-0.5 s): only when a record runs, never at CLI start
    if name in ("_nav_loop", "_strapdown_loop"):
        from covtool.nav.strapdown import kernels

        return getattr(kernels, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "NAV_STATES", "NavState", "NavHistory", "step", "run", "iter_intervals", "correct",
    "nav_errors", "truth_state", "group_samples",
]
