"""Tests of covtool.board.output_filter: seed 000, eq (11)-(20).

Oracles: scipy's and python-control's own filter designs and simulations,
the inverse z-transform checked sample by sample, brute-force sums and
brute-force extrema of the closed forms.
"""

from __future__ import annotations

import math

import control
import numpy as np
import pytest
from scipy import signal

from covtool.board import output_filter as of

FS = 2400.0


@pytest.fixture(scope="module")
def filt():
    return of.butterworth_filter(20.0, FS)


@pytest.fixture(scope="module")
def thresholds(filt):
    return of.regime_thresholds(filt)


@pytest.mark.parametrize("fc, fs", [(20.0, 2400.0), (0.1, 100.0), (150.0, 1000.0)])
def test_design_matches_scipy_and_python_control(fc, fs):
    f = of.butterworth_filter(fc, fs)
    b, a = signal.butter(2, fc / (fs / 2))
    np.testing.assert_allclose(f.num, b, rtol=1e-10)
    np.testing.assert_allclose(f.den, a, rtol=1e-10)
    w = 2 * math.pi * fc
    analog = control.tf([w * w], [1, math.sqrt(2) * w, w * w])
    d = control.sample_system(analog, 1 / fs, method="tustin", prewarp_frequency=w)
    np.testing.assert_allclose(np.squeeze(d.num[0][0]), f.num, rtol=1e-9)
    np.testing.assert_allclose(np.squeeze(d.den[0][0]), f.den, rtol=1e-9)
    assert f.dc_gain == pytest.approx(1.0, rel=1e-8)  # den sums to ~1e-5 at 0.1 Hz: cancellation
    # -3 dB at the cutoff, poles at zeta exp(+-j omega_n)
    h = f.tf(np.exp(2j * math.pi * fc / fs))
    assert abs(h) == pytest.approx(1 / math.sqrt(2), rel=1e-9)
    poles = np.sort_complex(f.tf.poles())
    assert abs(poles[0]) == pytest.approx(f.zeta) and abs(np.angle(poles[1])) == pytest.approx(f.omega_n)


def test_20hz_filter_numbers(filt):
    # small-omega_n regime of the paper: omega_n of order 1e-2
    assert filt.omega_n == pytest.approx(0.03704, abs=1e-5)
    assert filt.zeta == pytest.approx(0.96365, abs=1e-5)
    assert filt.ringing_period == pytest.approx(169.63, abs=0.01)


def test_exact_impulse_response_is_inverse_z_transform(filt):
    n = np.arange(600)
    x = (n == 0).astype(float)
    h_lfilter = of.filter_signal(filt, x)
    np.testing.assert_allclose(of.impulse_response(filt, n), h_lfilter, rtol=0, atol=1e-15)
    # python-control's discrete impulse has area 1, i.e. height 1/dt
    r = control.impulse_response(filt.tf, T=n * filt.dt)
    np.testing.assert_allclose(np.squeeze(r.outputs) * filt.dt, h_lfilter, rtol=0, atol=1e-13)
    assert of.impulse_response(filt, [-3, -1]).tolist() == [0.0, 0.0]


def test_printed_eq12_is_off_by_order_omega_squared(filt):
    z, w, b = filt.zeta, filt.omega_n, filt.b
    n = np.arange(400)
    printed = (b / z**2) * (n == 0) + (b / z**2) * (z + 1) * z**n * (
        (z - 1) * np.cos(w * n) + (z + 1) / math.tan(w) * np.sin(w * n))
    exact = of.impulse_response(filt, n)
    err = np.abs(printed - exact).max() / exact.max()
    assert 1e-5 < err < 2 * w**2


def test_eq13_approximates_eq12(filt):
    n = np.arange(1, 800)
    exact = of.impulse_response(filt, n)
    approx = of.impulse_response(filt, n, approx=True)
    assert np.abs(exact - approx).max() < 0.05 * exact.max()


def test_eq14_extrema_of_eq13(filt):
    n_max, n_min = of.isolated_extrema(filt)
    x = np.linspace(0, 250, 500001)
    h = of.impulse_response(filt, x, approx=True)
    assert n_max == pytest.approx(x[h.argmax()], abs=1e-3)
    assert n_min == pytest.approx(x[h.argmin()], abs=1e-3)
    # closed form and exact isolated amplitude agree to 0.2 %
    assert of.isolated_amplitude(filt) == pytest.approx(of.isolated_amplitude(filt, method="exact"), rel=2e-3)


@pytest.mark.parametrize("n_a", [3.0, 7.6, 15.0, 30.5, 61.0, 95.0, 150.0, 400.0])
def test_eq16_is_eq15_with_eq13(filt, n_a):
    n = np.linspace(0, n_a - 1, 37)
    brute = sum(of.impulse_response(filt, n + i * n_a, approx=True) for i in range(4000))
    np.testing.assert_allclose(of.periodic_error(filt, n_a, n), brute, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("n_a", [1, 2, 7, 15, 61, 170, 300])
def test_exact_periodic_sum_equals_time_domain(filt, n_a):
    n = np.arange(n_a)
    brute = sum(of.impulse_response(filt, n + i * n_a) for i in range(int(3000 / n_a) + 2))
    exact = of.periodic_error(filt, n_a, n, approx=False)
    np.testing.assert_allclose(exact, brute, rtol=1e-9, atol=1e-14)
    hi, lo = of.periodic_extrema(filt, n_a)
    assert hi == pytest.approx(exact.max(), rel=1e-9) and lo == pytest.approx(exact.min(), rel=1e-9, abs=1e-15)


@pytest.mark.parametrize("n_a", [20.0, 60.0, 84.0, 100.0, 140.0, 200.0])
def test_eq17_zero_and_eq18_extremum(filt, n_a):
    e = lambda x: float(of.periodic_error(filt, n_a, x))  # noqa: E731
    for k in (0, 1):
        z = of.zero_point(filt, n_a, k)
        assert abs(e(z)) < 1e-12
        d = of.extremum_point(filt, n_a, k)
        slope = (e(d + 1e-4) - e(d - 1e-4)) / 2e-4
        assert abs(slope) < 1e-9
    # large N_a: eq (18) tends to eq (14)
    assert of.extremum_point(filt, 5000.0, 0) == pytest.approx(of.isolated_extrema(filt)[0], rel=1e-9)


def test_eq19_ordering(filt, thresholds):
    t = thresholds
    half = math.pi / filt.omega_n
    assert 0 < t["D0"] < t["Z1"] < t["D1"] < 2 * half
    assert half < t["D1"]
    # the paper's Z1 < pi/omega_n holds for a continuous index; with the end point N_a - 1 it
    # sits about one sample above
    assert abs(t["Z1"] - half) < 1.5
    assert of.zero_point(filt, t["Z1"], 1) == pytest.approx(t["Z1"] - 1, abs=1e-8)
    assert of.extremum_point(filt, t["D1"], 1) == pytest.approx(t["D1"] - 1, abs=1e-8)


@pytest.mark.parametrize("n_a", [2.5, 5.0, 10.0, 15.3, 30.0, 61.0, 85.0, 88.0, 95.0, 106.0, 120.0, 169.6, 400.0])
def test_eq20_against_brute_force_extrema(filt, thresholds, n_a):
    x = np.linspace(0, n_a - 1, 100001)
    e = of.periodic_error(filt, n_a, x)
    brute = e.max() - e.min()
    cf = of.amplitude_closed_form(filt, n_a, thresholds)
    if thresholds["Z1"] < n_a <= thresholds["D1"]:
        # eq (20) takes the minimum at n = N_a - 1; e keeps falling to n = N_a (= e[0]),
        # which eq (20) misses by less than 0.5 %
        assert cf <= brute and cf == pytest.approx(brute, rel=5e-3)
    else:
        assert cf == pytest.approx(brute, rel=1e-6)


def test_eq16_overestimates_short_periods(filt):
    # eq (13) drops the b/zeta^2 feed-through; at a few samples per pulse that is
    # comparable to the ripple, so eq (16)/(20) overestimates the amplitude
    for n_a, lo, hi in ((7, 1.3, 1.5), (15, 1.1, 1.2), (61, 1.0, 1.03)):
        hi_td, lo_td = of.periodic_extrema(filt, n_a)
        ratio = of.amplitude_closed_form(filt, n_a) / (hi_td - lo_td)
        assert lo < ratio < hi


def test_filter_signal_matches_forced_response(filt):
    rng = np.random.default_rng(3)
    u = rng.standard_normal(300)
    r = control.forced_response(filt.tf, T=np.arange(300) * filt.dt, U=u)
    np.testing.assert_allclose(of.filter_signal(filt, u), np.squeeze(r.outputs), rtol=1e-10, atol=1e-13)
    strictly_proper = control.tf([0.5], [1, -0.5], 0.1)  # y[n] = 0.5 y[n-1] + 0.5 u[n-1]
    r = control.forced_response(strictly_proper, T=np.arange(300) * 0.1, U=u)
    np.testing.assert_allclose(of.filter_signal(strictly_proper, u), np.squeeze(r.outputs), rtol=1e-10,
                               atol=1e-13)


def test_moving_average_decimate_and_decimated_extrema(filt):
    x = np.arange(10.0)
    np.testing.assert_allclose(of.moving_average_decimate(x, 3), [1.0, 4.0, 7.0])
    np.testing.assert_allclose(of.moving_average_decimate(x, 1), x)
    # averaging cannot widen the range
    hi, lo = of.periodic_extrema(filt, 15)
    hin, lon = of.periodic_extrema(filt, 15, factor=24)
    assert lo <= lon <= hin <= hi
    # a whole number of periods per block leaves nothing but the mean
    hin, lon = of.periodic_extrema(filt, 6, factor=24)
    assert hin - lon < 1e-12 and hin == pytest.approx(1 / 6)


@pytest.mark.parametrize("call, match", [
    (lambda: of.butterworth_filter(1300.0, FS), "cutoff < sample_rate/2"),
    (lambda: of.butterworth_filter(20.0, FS, damping=0.0), "damping must be positive"),
    (lambda: of.butterworth_filter(20.0, FS, damping=2.0), "real poles"),
    (lambda: of.SecondOrderFilter(0.1, 1.2, 0.1, 1.0), "zeta must be"),
    (lambda: of.SecondOrderFilter(0.1, 0.9, 4.0, 1.0), "omega_n must be"),
    (lambda: of.SecondOrderFilter(0.1, 0.9, 0.1, 0.0), "dt must be positive"),
    (lambda: of.SecondOrderFilter.from_coefficients([1, 1, 1], [1, -1.5, 0.6], 1.0), "numerator must be"),
    (lambda: of.isolated_amplitude(of.butterworth_filter(20.0, FS), method="x"), "method must be"),
    (lambda: of.periodic_error(of.butterworth_filter(20.0, FS), 7.5, [0], approx=False), "integer period"),
    (lambda: of.pulse_train(10, 0), "period must be"),
    (lambda: of.periodic_extrema(of.butterworth_filter(20.0, FS), 0), "period and factor"),
    (lambda: of.moving_average_decimate([1.0], 0), "factor must be"),
])
def test_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_regime_threshold_search_failure():
    # a filter whose ringing is too short for the search interval to bracket a root
    f = of.SecondOrderFilter(0.25, 0.05, 3.0, 1.0)
    with pytest.raises(ValueError, match="no regime threshold"):
        of.regime_thresholds(f)
