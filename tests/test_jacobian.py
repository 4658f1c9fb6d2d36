"""Analytic F(t) against the Jacobian of the nonlinear navigation equations.

Issue 2, acceptance item 2.  The oracle is :mod:`nonlinear_reference`, an
independent implementation of the navigation equations (Titterton & Weston
2004, §3.7) with the sensor errors of seed 002 eq (3), (5) injected; its
Jacobian at x = 0 is taken numerically and compared with
:func:`covtool.lincov.dynamics.error_dynamics` along the land-vehicle route.

Numerical differentiation
-------------------------
* **Complex step** (main check): ``J[:, j] = Im δẋ(i h e_j) / h`` with
  ``h = 1e-30``.  It is the exact-derivative refinement of central
  differences: the same O(h²) truncation with no subtractive cancellation,
  so J is exact to round-off (Squire & Trapp 1998).
* **Real central differences** (cross-check at a few points):
  ``(δẋ(s e_j) − δẋ(−s e_j)) / 2s`` with the steps of :data:`CD_NAV_STEPS`
  (1σ for the sensor states, which enter linearly).

Tolerance
---------
Element-wise relative, with a tiny floor::

    |J_ij − F_ij| ≤ tol · max(|F_ij|, floor · max|F[:, group(j)]|)

where ``group(j)`` is the set of columns of j's block with the same physical
dimension (δL and δl; δh; δv; δq; each sensor block), so the floor is scaled
in consistent units.  ``tol = 1e-5`` with ``floor = 1e-9`` for the complex
step: the absolute allowance ``1e-14 · max|F[:, group]|`` is ~50 ulp of the
sums that build F (entries that are zero in exact arithmetic, such as
``∂δv̇_D/∂δq3`` at level attitude, come out as ±1e-15 in both J and F).  The
smallest physical entries (∂δq̇/∂δh ≈ 1e-13 s⁻¹·m⁻¹ against a δh-column
scale of 3e-6) stay well above the floor.  Central differences:
``tol = 1e-4``, same floor (their round-off is ε|ẋ|/s).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import nonlinear_reference as nr
from covtool.lincov.dynamics import Context, NavOptions, error_dynamics
from covtool.io.model_file import load_model
from covtool.nav.trajectory.profiles import land_vehicle

SDINS58 = Path(__file__).resolve().parents[1] / "models" / "sdins58.toml"

TOL_COMPLEX = 1e-5
TOL_CENTRAL = 1e-4
FLOOR = 1e-9
#: central-difference steps of the 10 navigation states: δL, δl [rad] (64 m),
#: δh [m], δv [m/s], δq [-]; truncation O(s²) stays below 1e-8 relative
CD_NAV_STEPS = [1e-5, 1e-5, 10.0, 1e-2, 1e-2, 1e-2, 1e-5, 1e-5, 1e-5, 1e-5]


@pytest.fixture(scope="module")
def model():
    return load_model(SDINS58)


@pytest.fixture(scope="module")
def route():
    return land_vehicle(dt=1.0)


def _check_times(route):
    """80 evenly spread times plus the extremes of every manoeuvre."""
    t = route.t[1:-1]
    special = [
        t[np.argmax(np.abs(route.w_ib_b[1:-1, 2]))],            # peak yaw rate (turn)
        t[np.argmax(np.abs(route.euler()[1:-1, 1]))],           # steepest grade
        t[np.argmax(np.abs(route.w_ib_b[1:-1, 1]))],            # grade transition (pitch rate)
        t[np.argmax(np.abs(route.f_b[1:-1, 0]))],               # peak longitudinal accel
        t[np.argmax(np.linalg.norm(route.v_n[1:-1], axis=1))],  # top speed
        t[np.argmax(np.abs(route.v_n[1:-1, 2]))],               # largest climb rate
    ]
    return np.unique(np.r_[np.linspace(2.0, route.t[-1] - 2.0, 80), special])


def _groups(model):
    """Column groups: same block and same physical dimension."""
    key = [(s.block, s.dimension) for s in model.states]
    return {k: [i for i, kk in enumerate(key) if kk == k] for k in dict.fromkeys(key)}


def _relative_error(J, F, groups, floor=FLOOR):
    """``|J − F| / max(|F|, floor · max|F[:, group]|)`` element-wise."""
    scale = np.zeros(F.shape[1])
    for cols in groups.values():
        scale[cols] = floor * np.max(np.abs(F[:, cols]))
    den = np.maximum(np.abs(F), scale[None, :])
    diff = np.abs(J - F)
    return np.where(diff == 0, 0.0, diff / np.where(den > 0, den, np.inf)), np.abs(F) > scale[None, :]


def _at(route, t):
    s = route.sample(np.atleast_1d(t))
    return s, Context.from_trajectory(s)


@pytest.fixture(scope="module")
def complex_step(model, route):
    """Complex-step J and analytic F at every check time (shared by all tests)."""
    t = _check_times(route)
    s, ctx = _at(route, t)
    F = error_dynamics(model, ctx).F
    J = np.stack([nr.numerical_jacobian(model, s.lat[k], s.lon[k], s.h[k], s.v_n[k], s.q_nb[k],
                                        s.f_b[k], s.w_ib_b[k]) for k in range(t.size)])
    groups = _groups(model)
    err, strict = zip(*(_relative_error(J[k], F[k], groups) for k in range(t.size)))
    return {"t": t, "s": s, "F": F, "J": J, "err": np.stack(err), "strict": np.stack(strict)}


def test_check_points_cover_the_route(complex_step, route):
    """The points include standstill, cruise, turns, hills and speed changes."""
    s = complex_step["s"]
    speed = np.linalg.norm(s.v_n, axis=1)
    assert complex_step["t"].size >= 80
    assert np.any(speed < 1e-9) and np.any(speed > 13.0)
    assert np.max(np.abs(s.w_ib_b[:, 2])) > np.radians(4.9)          # 5 deg/s turns
    assert np.max(np.abs(s.euler()[:, 1])) > 0.9 * np.arctan(0.04)   # 4 % grades
    assert np.max(np.abs(s.f_b[:, 0])) > 0.5                           # 0.66 m/s² speed changes
    assert len(set(np.round(np.degrees(s.euler()[:, 2]) / 90.0) % 4)) == 4  # all four headings


@pytest.mark.parametrize("block", [b for b in load_model(SDINS58).block_names()])
def test_complex_step_jacobian_per_block(complex_step, model, block):
    """Columns of each block: analytic F = complex-step J to 1e-5 (relative, floor 1e-9).

    Measured at the 85 points: every sensor/environment block ≤ 5e-16 on
    entries above the floor (≤ 1.8e-9 counting floored round-off entries);
    navigation block ≤ 1.0e-7 above the floor (∂δv̇_D/∂δq0, itself a
    near-cancellation) and ≤ 4.9e-7 overall.
    """
    cols = [i for i, s in enumerate(model.states) if s.block == block]
    err = complex_step["err"][:, :, cols]
    k, i, j = np.unravel_index(np.argmax(err), err.shape)
    assert err.max() <= TOL_COMPLEX, (
        f"block {block}: max relative error {err.max():.3g} at t = {complex_step['t'][k]:.1f} s, "
        f"∂{model.names[i]}/∂{model.names[cols[j]]}: F = {complex_step['F'][k, i, cols[j]]:.6g}, "
        f"J = {complex_step['J'][k, i, cols[j]]:.6g}")
    # the block couples into the navigation errors, and the check is not vacuous
    assert np.any(np.abs(complex_step["F"][:, :10, cols]) > 0)
    assert np.any(complex_step["strict"][:, :10, cols])


def test_floor_only_absorbs_round_off(complex_step, model):
    """Entries under the floor are negligible in the reference too.

    The floor (1e-9 of the column group's largest entry) only admits entries
    that are zero in exact arithmetic (level-attitude DCM elements of 1e-17,
    cancellations in the δq projection); where F is under it, |J| is under
    twice it.  Thousands of entries are held to the full relative tolerance.
    """
    groups = _groups(model)
    F, J = complex_step["F"], complex_step["J"]
    scale = np.zeros(F.shape[:1] + F.shape[2:])
    for cols in groups.values():
        scale[:, cols] = FLOOR * np.max(np.abs(F[:, :, cols]), axis=(1, 2))[:, None]
    floored = ~complex_step["strict"]
    assert np.all(np.abs(J)[floored] <= 2.0 * np.broadcast_to(scale[:, None, :], J.shape)[floored])
    assert complex_step["strict"].sum() > 8000          # measured 9719


@pytest.mark.parametrize("perturb", ["spherical dg/dh", "no dR_M/dL", "no dω_en/dh in δq̇"])
def test_tolerance_resolves_small_terms(complex_step, model, perturb):
    """The check can fail: dropping a small but physical term breaks it.

    Each perturbation is a common simplification of the error equations; its
    relative effect is far above the 1e-5 tolerance (measured: spherical
    −2g/R for ∂g/∂h 3.4e-3; the dropped terms ≫ 1 against the floor).
    """
    from covtool.nav import earth
    s, F = complex_step["s"], complex_step["F"].copy()
    moving = np.linalg.norm(s.v_n, axis=1) > 10.0
    if perturb == "spherical dg/dh":
        rm, rn = earth.radii(s.lat)
        F[:, 5, 2] = -2.0 * earth.gravity(s.lat, s.h) / np.sqrt((rm + s.h) * (rn + s.h))
    elif perturb == "no dR_M/dL":
        F[:, 0, 0] = 0.0
    else:
        F[:, 6:10, 2] = 0.0
    groups = _groups(model)
    worst = max(_relative_error(complex_step["J"][k], F[k], groups)[0].max()
                for k in np.flatnonzero(moving | (perturb == "spherical dg/dh")))
    assert worst > 100 * TOL_COMPLEX


@pytest.mark.parametrize("t", [100.0, 250.0, 500.0, 560.0, 1000.0])
def test_central_difference_cross_check(model, route, t):
    """True central differences agree with F to 1e-4 (looser; measured ≤ 2.1e-6)."""
    s, ctx = _at(route, t)
    F = error_dynamics(model, ctx).F[0]
    steps = np.r_[CD_NAV_STEPS, [st.sigma for st in model.states[10:]]]
    assert np.all(steps > 0)
    J = nr.central_difference_jacobian(model, s.lat[0], s.lon[0], s.h[0], s.v_n[0], s.q_nb[0],
                                       s.f_b[0], s.w_ib_b[0], steps)
    err, _ = _relative_error(J, F, _groups(model))
    i, j = np.unravel_index(np.argmax(err), err.shape)
    assert err.max() <= TOL_CENTRAL, (f"t = {t} s: ∂{model.names[i]}/∂{model.names[j]}: "
                                      f"F = {F[i, j]:.6g}, central difference {J[i, j]:.6g}")


def test_no_coriolis_removes_exactly_the_earth_rate_coriolis_terms(complex_step, model, route):
    """``NavOptions(coriolis=False)`` drops exactly the 2ω_ie terms (filter B3).

    ``F_default − F_B3`` must equal the complex-step Jacobian of the error of
    ``−2ω_ie^n(L) × v`` (``−2ω_ie × δv`` and ``−2 δω_ie × v``), and so
    ``F_B3`` equals the Jacobian of the reference with that term removed.
    Same tolerance as the main check.  Measured: the difference equals the
    Coriolis Jacobian to 6e-14 of the 2Ω scale, and F_B3 matches to 4.9e-7.
    """
    t, s = complex_step["t"], complex_step["s"]
    ctx = Context.from_trajectory(s)
    F_b3 = error_dynamics(model, ctx, NavOptions(coriolis=False)).F
    diff = complex_step["F"] - F_b3
    groups = _groups(model)
    for k in range(t.size):
        Jc = np.zeros((model.n, model.n))
        Jc[:10, :10] = nr.complex_step_jacobian(lambda x: nr.coriolis_error(s.lat[k], s.v_n[k], x), 10)
        # only the velocity rows change, and only through δL and δv
        assert np.all(diff[k][np.r_[0:3, 6:model.n]] == 0.0)
        assert np.all(diff[k][:, np.r_[1:3, 6:model.n]] == 0.0)
        scale = np.max(np.abs(Jc[3:6, 3:6]))
        assert np.max(np.abs(diff[k] - Jc)) <= 1e-12 * scale, f"t = {t[k]:.1f} s"
        err, _ = _relative_error(complex_step["J"][k] - Jc, F_b3[k], groups)
        assert err.max() <= TOL_COMPLEX, f"t = {t[k]:.1f} s"
    # the dropped terms are not negligible: 2Ω is 1.5e-4 s⁻¹ on the δv block
    assert np.max(np.abs(diff[:, 3:6, 3:6])) > 1.0e-4
