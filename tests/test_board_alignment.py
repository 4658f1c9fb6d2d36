"""Tests of covtool.board.alignment: seed 000, eq (21)-(27).

Oracles: the state-space loop built from eq (22)-(25) against the transfer
function of eq (26); the hand-derived Tustin coefficients of eq (27)
against python-control's own ``sample_system``; closed-form impulse peaks
against python-control's impulse response.
"""

from __future__ import annotations

import math

import control
import numpy as np
import pytest

from covtool.board import adreset
from covtool.board import alignment as al
from covtool.board.output_filter import filter_signal

G = 9.80665
K, KB = 4.0, 4.0 / G


def _coeffs(tf):
    return np.squeeze(tf.num[0][0]), np.squeeze(tf.den[0][0])


def test_state_space_loop_is_eq26():
    sys = al.leveling_loop(K, KB, G)
    assert sys.state_labels == ["phi_x", "phi_y", "dv_x", "dv_y"]
    tf = control.ss2tf(sys)
    ref = al.leveling_tf(K, KB, G)
    w = 1j * np.array([0.01, 0.3, 2.0, 7.0])
    # Phi_y / Acc_e,x = +H2, Phi_x / Acc_e,y = -H2, no cross-coupling
    np.testing.assert_allclose(tf[1, 0](w), ref(w), rtol=1e-9)
    np.testing.assert_allclose(tf[0, 1](w), -ref(w), rtol=1e-9)
    np.testing.assert_allclose(np.abs(tf[0, 0](w)), 0, atol=1e-12)
    np.testing.assert_allclose(np.abs(tf[1, 1](w)), 0, atol=1e-12)
    # k = 4, k^b = 4/g: double pole at -2 rad/s (critically damped)
    np.testing.assert_allclose(np.sort(ref.poles().real), [-2, -2], atol=1e-6)


@pytest.mark.parametrize("dt", [0.01, 0.0025, 1 / 2400, 0.1])
@pytest.mark.parametrize("k, kb_g", [(4.0, 4.0), (1.0, 0.25), (0.5, 2.0)])
def test_tustin_eq27_matches_python_control(dt, k, kb_g):
    kb = kb_g / G
    mine = al.leveling_tf_discrete(k, kb, G, dt)
    ref = control.sample_system(al.leveling_tf(k, kb, G), dt, method="tustin")
    n1, d1 = _coeffs(mine)
    n2, d2 = _coeffs(ref)
    np.testing.assert_allclose(d1, d2 / d2[0], rtol=1e-10, atol=1e-15)
    # python-control goes through a state-space realisation and loses ~1e-8 at tiny dt
    np.testing.assert_allclose(n1, n2 / d2[0], rtol=1e-6, atol=1e-18)
    assert control.dcgain(mine) == pytest.approx(1 / G, rel=1e-9)


def test_printed_c1_has_a_sign_slip():
    dt = 0.01
    kk = KB * G * dt**2 / 4
    den = 1 + K * dt / 2 + kk
    printed_c1 = (2 + K * dt / 2 - kk) / den
    c1, c2, d = al.tustin_coefficients(K, KB, G, dt)
    assert printed_c1 != pytest.approx(c1, rel=1e-3)
    # the printed form puts a pole outside the unit circle: the loop would diverge
    assert np.max(np.abs(np.roots([1, -printed_c1, c2]))) > 1
    assert np.max(np.abs(np.roots([1, -c1, c2]))) < 1


@pytest.mark.parametrize("k, kb_g", [(4.0, 4.0), (1.0, 4.0), (6.0, 4.0), (1.0, 0.25)])
def test_impulse_peak_closed_form(k, kb_g):
    kb = kb_g / G
    t = np.linspace(0, 30 / (k / 2), 200001)
    r = control.impulse_response(al.leveling_tf(k, kb, G), T=t)
    assert al.impulse_peak_continuous(k, kb, G) == pytest.approx(np.max(r.outputs), rel=1e-6)


@pytest.mark.parametrize("order", [1, 2])
def test_prefilter(order):
    dt = 0.01
    pre = al.prefilter(0.1, dt, order)
    assert control.dcgain(pre) == pytest.approx(1.0, rel=1e-9)
    h = pre(np.exp(2j * math.pi * 0.1 * dt))
    assert abs(h) == pytest.approx(1 / math.sqrt(2), rel=1e-6)
    if order == 1:
        w = 2 * math.pi * 0.1
        ref = control.sample_system(control.tf([w], [1, w]), dt, "tustin")
        # without pre-warping, the same filter up to the frequency warp (tiny at 0.1 Hz, 100 Hz)
        np.testing.assert_allclose(_coeffs(pre)[1], _coeffs(ref)[1], rtol=1e-5)


def test_navigation_rate_error_preserves_pulse_area():
    fs, m = 2400.0, 24
    sf = 0.0636
    a = 1e-3 * G
    period = adreset.reset_period_samples(a, sf, 1 / fs)
    n_nav = 3 * period // m
    x = al.navigation_rate_error(a, n_nav, m, sf=sf, n_t=1066.5, n_e=21.33, dt_sensor=1 / fs, period=period)
    sensor = adreset.pulse_train_error(n_nav * m, a, sf=sf, n_t=1066.5, n_e=21.33, dt=1 / fs, period=period)
    assert x.sum() * m / fs == pytest.approx(sensor.sum() / fs, rel=1e-12)
    # each pulse lands in a single navigation sample
    s = adreset.pulse_height(sf, 1066.5, 21.33, 1 / fs)
    assert np.count_nonzero(x > x.min() + s / m / 2) == np.count_nonzero(sensor > sensor.min() + s / 2)


def test_isolated_pulse_tilt_amplitude():
    """At 1 mg (pulses 6.5 s apart) the tilt is A times the peak."""
    fs, m, dt_nav = 2400.0, 24, 0.01
    sf = 0.9 / fs * 169.6280987
    n_t, n_e = 1066.5, 21.33
    a = 1e-3 * G
    period = adreset.reset_period_samples(a, sf, 1 / fs)
    loop = al.leveling_tf_discrete(K, KB, G, dt_nav)
    settle = 2000
    n_nav = settle + 2 * period // m
    acc = al.navigation_rate_error(a, n_nav, m, sf=sf, n_t=n_t, n_e=n_e, dt_sensor=1 / fs, period=period)
    hi, lo = al.alignment_extrema(acc, loop, settle=settle)
    area = sf * n_e / (n_t + n_e)
    assert hi - lo == pytest.approx(area * al.impulse_peak_continuous(K, KB, G), rel=5e-3)
    # the pre-filter spreads each pulse and lowers the peak
    pre = al.prefilter(0.1, dt_nav, 1)
    hip, lop = al.alignment_extrema(acc, loop, pre, settle=settle)
    assert 0.2 < (hip - lop) / (hi - lo) < 0.6


def test_discrete_loop_tracks_continuous_loop():
    dt = 0.01
    t = np.arange(0, 10, dt)
    u = np.where((t > 1) & (t < 3), 0.01, 0.0)
    yd = filter_signal(al.leveling_tf_discrete(K, KB, G, dt), u)
    yc = control.forced_response(al.leveling_tf(K, KB, G), T=t, U=u).outputs
    assert np.abs(yd - yc).max() < 2e-3 * np.abs(yc).max()


@pytest.mark.parametrize("call, match", [
    (lambda: al.leveling_loop(-1.0, KB), "k must be a positive"),
    (lambda: al.leveling_tf(K, 0.0), "kb must be a positive"),
    (lambda: al.leveling_tf(K, KB, float("inf")), "g must be a positive"),
    (lambda: al.tustin_coefficients(K, KB, G, 0.0), "dt must be positive"),
    (lambda: al.prefilter(60.0, 0.01), "cutoff < 1/\\(2 dt\\)"),
    (lambda: al.prefilter(0.1, 0.01, order=3), "order must be 1 or 2"),
    (lambda: al.alignment_extrema(np.zeros(5), al.leveling_tf_discrete(K, KB, G, 0.01), settle=5),
     "settle leaves no samples"),
])
def test_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()
