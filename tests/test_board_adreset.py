"""Tests of covtool.board.adreset: simulator vs eq (1)-(10).

The board simulator is checked against eq (1)-(10).

Oracles: the board's true velocity increments integrate the input exactly;
the simulator's errors equal the analytic expressions of seed 000, eq (6),
(8), (9) and (10), and respect the bound of eq (7).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from covtool.board import adreset

FS = 2400.0
DT = 1.0 / FS
N_T = 1066.5
SF = 0.9 * DT * 169.6280987  # reset period = 2 pi/omega_n at 0.9 m/s^2 (study file)


def _profile(n=6000, seed=1):
    """Acceleration profile with sign changes, ramps and steps."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    return 3.0 * np.sin(2 * np.pi * 1.3 * t) + 0.7 * np.sign(np.sin(2 * np.pi * 0.4 * t)) \
        + 0.2 * rng.standard_normal(n)


@pytest.mark.parametrize("n_e", [21.33, -20.0, 106.65])
def test_true_increments_integrate_input_exactly(n_e):
    a = _profile()
    rec = adreset.simulate_board(a, dt=DT, sf=SF, n_t=N_T, n_e=n_e)
    # eq (3)-(4) with the true N_t: Delta Vel = a dT to rounding
    np.testing.assert_allclose(rec.d_vel_true, a * DT, rtol=0, atol=1e-14)
    np.testing.assert_allclose(rec.d_v_ad * SF / N_T, a * DT, rtol=0, atol=1e-14)
    # the AD value stays within the comparator band
    assert np.all(np.abs(rec.ad) < N_T)
    # resets happen, in both directions
    assert rec.d_r.max() >= 1 and rec.d_r.min() <= -1


@pytest.mark.parametrize("n_e", [21.33, -20.0, 106.65])
def test_velocity_error_matches_eq6_eq8_and_bound_eq7(n_e):
    a = _profile()
    rec = adreset.simulate_board(a, dt=DT, sf=SF, n_t=N_T, n_e=n_e)
    np.testing.assert_allclose(rec.d_vel_error, adreset.velocity_increment_error(rec.d_ad, SF, N_T, n_e),
                               rtol=1e-12, atol=1e-17)
    np.testing.assert_allclose(rec.vel_error, adreset.velocity_error(rec.ad, SF, N_T, n_e),
                               rtol=1e-9, atol=1e-15)
    # first-order forms differ by the factor N_hat / N_t
    approx = adreset.velocity_error(rec.ad, SF, N_T, n_e, exact=False)
    np.testing.assert_allclose(approx, rec.vel_error * (N_T + n_e) / N_T, rtol=1e-9, atol=1e-15)
    bound = adreset.velocity_error_bound(SF, N_T, n_e)
    assert np.abs(rec.d_vel_error).max() <= bound * (1 + 1e-12)
    assert np.abs(rec.vel_error).max() <= bound * (1 + 1e-12)
    # the velocity error does not drift: it reaches the bound (a sawtooth), not beyond
    assert np.abs(rec.vel_error).max() > 0.9 * bound
    assert bound == pytest.approx(SF * abs(n_e) / (N_T + n_e))
    assert adreset.velocity_error_bound(SF, N_T, n_e, exact=False) == pytest.approx(SF * abs(n_e) / N_T)


@pytest.mark.parametrize("accel", [0.37, -2.5, 10.0, 20.0])
def test_constant_input_error_is_eq10_pulse_train(accel):
    n_e = 53.325
    n = 3000
    rec = adreset.simulate_board(np.full(n, accel), dt=DT, sf=SF, n_t=N_T, n_e=n_e)
    acc_err = rec.d_vel_error / DT
    # eq (9), exact and to first order
    np.testing.assert_allclose(acc_err, adreset.acceleration_error(rec.d_r, rec.d_v_ad, SF, N_T, n_e, DT),
                               rtol=1e-9, atol=1e-9)
    approx = adreset.acceleration_error(rec.d_r, rec.d_v_ad, SF, N_T, n_e, DT, exact=False)
    assert np.abs(approx - acc_err).max() < 0.06 * np.abs(acc_err).max()
    # eq (10) with the pulses where the board fired them
    pulses = adreset.reset_pulse_indices(accel, n, SF, DT)
    np.testing.assert_array_equal(np.nonzero(rec.d_r)[0], np.unique(pulses))
    model = adreset.pulse_train_error(n, accel, sf=SF, n_t=N_T, n_e=n_e, dt=DT, pulses=pulses)
    np.testing.assert_allclose(acc_err, model, rtol=1e-9, atol=1e-9)
    # spacing alternates between floor and ceil of N_a = SF/(|a| dT)
    n_a = adreset.reset_period(accel, SF, DT)
    gaps = set(np.diff(pulses).tolist())
    assert gaps <= {math.floor(n_a), math.ceil(n_a)}
    # the mean error vanishes: its integral over any window is within the bound of eq (7)
    bound = adreset.velocity_error_bound(SF, N_T, n_e)
    window = acc_err[pulses[2] + 1:]
    assert abs(window.sum() * DT) <= bound * (1 + 1e-9)
    assert abs(window.mean()) <= bound / (window.size * DT) * (1 + 1e-9)


def test_pulse_height_and_constant_scale_as_alpha_over_one_plus_alpha():
    for alpha in (0.02, 0.05, 0.10, -0.01875):
        s = adreset.pulse_height(SF, N_T, alpha * N_T, DT)
        assert s == pytest.approx(SF / DT * alpha / (1 + alpha))
        assert adreset.constant_error(2.0, N_T, alpha * N_T) == pytest.approx(-2.0 * alpha / (1 + alpha))
        assert adreset.constant_error(2.0, N_T, alpha * N_T, exact=False) == pytest.approx(-2.0 * alpha)
    # the mean of the pulse train cancels the constant term
    a = 1.7
    s = adreset.pulse_height(SF, N_T, 20.0, DT)
    assert s / adreset.reset_period(a, SF, DT) == pytest.approx(-adreset.constant_error(a, N_T, 20.0))


def test_scale_factor_and_reset_period_roundtrip():
    sf = adreset.scale_factor_from_reset_period(0.9, 169.6280987, DT)
    assert sf == pytest.approx(SF)
    assert adreset.reset_period(0.9, sf, DT) == pytest.approx(169.6280987)
    assert adreset.reset_period_samples(20.0, sf, DT) == 7
    assert adreset.reset_period_samples(20.0, sf, DT, "round") == 8
    assert adreset.reset_period_samples(-5.0, sf, DT, "ceil") == 31
    assert math.isinf(adreset.reset_period(0.0, sf, DT))


def test_pulse_train_default_period_is_floor():
    x = adreset.pulse_train_error(100, 10.0, sf=SF, n_t=N_T, n_e=20.0, dt=DT)
    peaks = np.nonzero(x > x.min() + 1)[0]
    assert np.all(np.diff(peaks) == 15)
    assert np.allclose(adreset.pulse_train_error(10, 0.0, sf=SF, n_t=N_T, n_e=20.0, dt=DT), 0.0)


def test_velocity_error_sigma_and_time_constant():
    bound = adreset.velocity_error_bound(SF, N_T, 21.33)
    assert adreset.velocity_error_sigma(SF, N_T, 21.33) == pytest.approx(bound / math.sqrt(3))
    assert adreset.velocity_error_sigma(SF, N_T, 21.33, distribution="sawtooth") == pytest.approx(
        bound / math.sqrt(12))
    # Monte Carlo: random AD phase in [-N_t, N_t] (unknown input sign) is uniform error
    rng = np.random.default_rng(0)
    ad = rng.uniform(-N_T, N_T, 200_000)
    v = adreset.velocity_error(ad, SF, N_T, 21.33)
    assert v.std() == pytest.approx(adreset.velocity_error_sigma(SF, N_T, 21.33), rel=0.01)
    # sawtooth autocorrelation: initial slope -6 sigma^2 / T_R matches tau = T_R / 6
    f = 9.80665
    t_r = SF / f
    tau = adreset.suggested_time_constant(SF, f)
    assert tau == pytest.approx(t_r / 6)
    n = 6000
    phase = np.linspace(0, 1, n, endpoint=False)
    saw = phase - 0.5
    lag = 10  # samples of T_R / n
    r = np.mean(saw * np.roll(saw, -lag)) / np.var(saw)
    assert r == pytest.approx(1 - 6 * lag / n + 6 * (lag / n) ** 2, abs=1e-6)
    assert adreset.suggested_time_constant(SF, 0.0, tau_max=1800.0) == 1800.0
    assert adreset.suggested_time_constant(SF, 1e-9, tau_max=1800.0) == 1800.0


@pytest.mark.parametrize("kwargs, match", [
    ({"sf": -1.0}, "sf must be a positive"),
    ({"dt": 0.0}, "dt must be a positive"),
    ({"n_t": float("nan")}, "n_t must be a positive"),
    ({"n_e": -2000.0}, "n_t \\+ n_e must be positive"),
    ({"v_bound": 400.0}, "v_bound must exceed"),
    ({"ad0": 2000.0}, "ad0"),
])
def test_simulate_board_rejects_bad_parameters(kwargs, match):
    args = {"dt": DT, "sf": SF, "n_t": N_T, "n_e": 20.0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        adreset.simulate_board(np.ones(10), **args)


def test_other_errors_are_raised():
    with pytest.raises(ValueError, match="one-dimensional"):
        adreset.simulate_board(np.ones((2, 2)), dt=DT, sf=SF, n_t=N_T)
    with pytest.raises(ValueError, match="finite"):
        adreset.simulate_board(np.array([1.0, np.inf]), dt=DT, sf=SF, n_t=N_T)
    with pytest.raises(ValueError, match="rounding must be"):
        adreset.reset_period_samples(1.0, SF, DT, "nearest")
    with pytest.raises(ValueError, match="infinite at zero"):
        adreset.reset_period_samples(0.0, SF, DT)
    with pytest.raises(ValueError, match="phase must be"):
        adreset.reset_pulse_indices(1.0, 10, SF, DT, phase=1.0)
    with pytest.raises(ValueError, match="distribution must be"):
        adreset.velocity_error_sigma(SF, N_T, 20.0, distribution="normal")
    with pytest.raises(ValueError, match="accel must be a positive"):
        adreset.scale_factor_from_reset_period(0.0, 169.6, DT)


def test_uniform_error_is_three_quarters_random_constant():
    """Eq (8) error is 3/4 random constant, 1/4 sawtooth.

    Random input sign and reset phase: the ensemble autocorrelation is 3/4
    (the band's mean) + 1/4 of the sawtooth's, never below 5/8.
    """
    rng = np.random.default_rng(5)
    m = 400_000
    sign = rng.choice([-1.0, 1.0], m)
    phase = rng.uniform(0, 1, m)

    def vel(lag):  # lag as a fraction of the reset period T_R
        return adreset.velocity_error(sign * N_T * np.mod(phase + lag, 1.0), SF, N_T, 21.33)

    v0 = vel(0.0)
    var = np.mean(v0**2)
    assert math.sqrt(var) == pytest.approx(adreset.velocity_error_sigma(SF, N_T, 21.33), rel=5e-3)
    for lag, expected in ((0.5, 0.75 - 0.125), (0.25, 0.75 + 0.25 * (1 - 1.5 + 0.375)), (1.0, 1.0)):
        assert np.mean(v0 * vel(lag)) / var == pytest.approx(expected, abs=5e-3)
