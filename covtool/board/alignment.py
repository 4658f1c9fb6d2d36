"""Closed-loop leveling alignment driven by the AD-reset error.

The horizontal (leveling) alignment of seed 000, eq (21)-(25), feeds the
velocity error back through the gains ``k`` and ``k^b``.  Laplace-
transformed it is a second-order loop (eq (26)); the bilinear transform
gives the discrete loop of eq (27).  The AD-reset acceleration error of
eq (10), block-averaged to the navigation rate, drives it.

Conventions
-----------
SI inside: tilt angles [rad], accelerations [m/s^2], ``k`` [1/s],
``k^b`` [1/m] (so that ``k^b g`` is [1/s^2]).  ``dt`` here is the
alignment/navigation interval, not the board's acquisition interval.
"""

from __future__ import annotations

import math

import numpy as np

from covtool.units import G0
from covtool.board import adreset
from covtool.board.output_filter import butterworth_filter, filter_signal, moving_average_decimate

__all__ = [
    "leveling_loop",
    "leveling_tf",
    "tustin_coefficients",
    "leveling_tf_discrete",
    "prefilter",
    "impulse_peak_continuous",
    "navigation_rate_error",
    "alignment_extrema",
]


def _check_gains(k: float, kb: float, g: float) -> None:
    for name, v in (("k", k), ("kb", kb), ("g", g)):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive finite number, got {v!r}")


def leveling_loop(k: float, kb: float, g: float = G0):
    """Two-axis leveling loop as a python-control state space.

    Parameters
    ----------
    k : float
        Velocity-damping gain of eq (24). [1/s]
    kb : float
        Control-rate gain ``k^b`` of eq (23). [1/m]
    g : float
        Gravity. [m/s^2]

    Returns
    -------
    control.StateSpace
        States ``phi_x, phi_y, dv_x, dv_y``; inputs ``acc_e_x, acc_e_y``
        [m/s^2]; outputs ``phi_x, phi_y`` [rad].

    Notes
    -----
    Seed 000, eq (21)-(25) with the earth-rate terms (the ``alpha(s)``,
    ``beta(s)`` of eq (26)) left out, since they do not involve the
    accelerometer error: eq (21)-(22) give ``dphi_x/dt = w_x^c`` and
    ``dphi_y/dt = w_y^c``; eq (23) ``w_x^c = -k^b dV_y``,
    ``w_y^c = k^b dV_x``; differentiating eq (24)-(25),
    ``d(dV_x)/dt = -g phi_y + Acc_e,x - k dV_x`` and
    ``d(dV_y)/dt = g phi_x + Acc_e,y - k dV_y``.
    """
    import control

    _check_gains(k, kb, g)
    a = np.array([
        [0.0, 0.0, 0.0, -kb],
        [0.0, 0.0, kb, 0.0],
        [0.0, -g, -k, 0.0],
        [g, 0.0, 0.0, -k],
    ])
    b = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    c = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
    return control.ss(a, b, c, np.zeros((2, 2)), states=["phi_x", "phi_y", "dv_x", "dv_y"],
                      inputs=["acc_e_x", "acc_e_y"], outputs=["phi_x", "phi_y"], name="leveling")


def leveling_tf(k: float, kb: float, g: float = G0):
    """Tilt response to the accelerometer error, continuous time.

    Returns
    -------
    control.TransferFunction
        ``Phi_y(s) / Acc_e,x(s) = k^b / (s^2 + k s + k^b g)``
        (seed 000, eq (26)); ``Phi_x / Acc_e,y`` is its negative.
    """
    import control

    _check_gains(k, kb, g)
    return control.tf([kb], [1.0, k, kb * g])


def tustin_coefficients(k: float, kb: float, g: float, dt: float) -> tuple[float, float, float]:
    """Coefficients c1, c2, d of the discrete loop of eq (27).

    Parameters
    ----------
    k, kb, g : float
        Loop gains [1/s], [1/m] and gravity [m/s^2].
    dt : float
        Alignment/navigation interval. [s]

    Returns
    -------
    (c1, c2, d) : tuple of float
        ``H2(z) = k^b d (1 + z^-1)^2 / (1 - c1 z^-1 + c2 z^-2)``.

    Notes
    -----
    Substituting ``s = (2/dt)(1 - z^-1)/(1 + z^-1)`` in
    ``s^2 + k s + k^b g`` and multiplying by ``(dt^2/4)(1 + z^-1)^2``:

    ``(1 - z^-1)^2 + k (dt/2)(1 - z^-2) + k^b g (dt^2/4)(1 + z^-1)^2``.

    With ``D = 1 + k dt/2 + k^b g dt^2/4``:
    ``c1 = (2 - k^b g dt^2/2) / D``,
    ``c2 = (1 - k dt/2 + k^b g dt^2/4) / D``, ``d = (dt^2/4) / D``.
    The scan prints c1's numerator as ``2 + k dt/2 - k^b g dt^2/4``: the
    ``k`` terms of the ``z^-1`` coefficient cancel (``1 - z^-2`` has none)
    and the ``k^b g`` term is ``2 (dt^2/4)``, not ``dt^2/4``.
    """
    _check_gains(k, kb, g)
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt!r}")
    kk = kb * g * dt * dt / 4.0
    den = 1.0 + k * dt / 2.0 + kk
    return (2.0 - 2.0 * kk) / den, (1.0 - k * dt / 2.0 + kk) / den, (dt * dt / 4.0) / den


def leveling_tf_discrete(k: float, kb: float, g: float, dt: float):
    """Discrete leveling loop of eq (27) as a transfer function.

    Returns
    -------
    control.TransferFunction
        ``H2(z) = Phi_y / Acc_e,x`` at interval ``dt``.
    """
    import control

    c1, c2, d = tustin_coefficients(k, kb, g, dt)
    return control.tf(kb * d * np.array([1.0, 2.0, 1.0]), [1.0, -c1, c2], dt)


def prefilter(cutoff: float, dt: float, order: int = 1):
    """Accelerometer pre-filter applied before the alignment.

    Parameters
    ----------
    cutoff : float
        -3 dB cutoff. [Hz]
    dt : float
        Alignment/navigation interval. [s]
    order : {1, 2}
        1: first-order low-pass ``w/(s + w)``; 2: the Butterworth form of
        eq (11).  Both by the bilinear transform pre-warped at the cutoff.

    Returns
    -------
    control.TransferFunction
        Unit DC gain, discrete at ``dt``.
    """
    import control

    if not (cutoff > 0 and dt > 0 and cutoff < 0.5 / dt):
        raise ValueError(f"need 0 < cutoff < 1/(2 dt), got cutoff={cutoff!r}, dt={dt!r}")
    if order == 1:
        w = 2.0 * math.pi * cutoff
        return control.sample_system(control.tf([w], [1.0, w]), dt, method="tustin", prewarp_frequency=w)
    if order == 2:
        return butterworth_filter(cutoff, 1.0 / dt).tf
    raise ValueError(f"order must be 1 or 2, got {order!r}")


def impulse_peak_continuous(k: float, kb: float, g: float = G0) -> float:
    """Peak of the continuous loop's impulse response.

    Returns
    -------
    float
        ``max_t h(t)`` of ``k^b / (s^2 + k s + k^b g)``. [rad per m/s]

    Notes
    -----
    With ``sigma = k/2`` and ``w0^2 = k^b g``: critically damped
    (``sigma = w0``), ``h = k^b t exp(-sigma t)`` peaks at ``1/sigma`` with
    ``k^b / (e sigma)``; under-damped, ``h = (k^b/w_d) exp(-sigma t)
    sin(w_d t)`` peaks at ``atan(w_d/sigma)/w_d``; over-damped,
    ``h = (k^b/2beta)(exp(-(sigma-beta)t) - exp(-(sigma+beta)t))``
    peaks at ``ln((sigma+beta)/(sigma-beta))/(2 beta)``.  For an isolated
    reset pulse of velocity area ``A`` the tilt amplitude is ``A`` times
    this peak (seed 000, Table 2 at small input).
    """
    _check_gains(k, kb, g)
    sigma = k / 2.0
    w0sq = kb * g
    disc = sigma * sigma - w0sq
    if abs(disc) <= 1e-12 * w0sq:
        return kb / (math.e * sigma)
    if disc < 0:
        wd = math.sqrt(-disc)
        t = math.atan2(wd, sigma) / wd
        return kb / wd * math.exp(-sigma * t) * math.sin(wd * t)
    beta = math.sqrt(disc)
    t = math.log((sigma + beta) / (sigma - beta)) / (2.0 * beta)
    return kb / (2.0 * beta) * (math.exp(-(sigma - beta) * t) - math.exp(-(sigma + beta) * t))


def navigation_rate_error(accel: float, n_nav: int, factor: int, *, sf: float, n_t: float, n_e: float,
                          dt_sensor: float, period: int) -> np.ndarray:
    """AD-reset acceleration error at the navigation rate.

    Parameters
    ----------
    accel : float
        Constant input acceleration. [m/s^2]
    n_nav : int
        Number of navigation samples.
    factor : int
        Sensor samples per navigation sample.
    sf, n_t, n_e : float
        Board parameters (see :mod:`covtool.board.adreset`).
    dt_sensor : float
        Board acquisition interval. [s]
    period : int
        Reset-pulse period. [sensor samples]

    Returns
    -------
    ndarray, shape (n_nav,)
        Eq (10) at the sensor rate, block-averaged over ``factor`` samples
        and downsampled (seed 000, Fig 4 dotted; the input of eq (27)).
        [m/s^2]
    """
    x = adreset.pulse_train_error(n_nav * factor, accel, sf=sf, n_t=n_t, n_e=n_e, dt=dt_sensor, period=period)
    return moving_average_decimate(x, factor)


def alignment_extrema(acc_nav: np.ndarray, loop, pre=None, *, settle: int) -> tuple[float, float]:
    """Steady-state max and min tilt error of the alignment loop.

    Parameters
    ----------
    acc_nav : ndarray
        Acceleration error at the navigation rate. [m/s^2]
    loop : control.TransferFunction
        Discrete loop ``H2(z)`` (:func:`leveling_tf_discrete`).
    pre : control.TransferFunction, optional
        Discrete pre-filter applied first.
    settle : int
        Leading samples discarded as transient.

    Returns
    -------
    (float, float)
        Max and min of ``Phi`` after ``settle``. [rad]
    """
    x = acc_nav if pre is None else filter_signal(pre, acc_nav)
    phi = filter_signal(loop, x)[settle:]
    if phi.size == 0:
        raise ValueError("settle leaves no samples")
    return float(phi.max()), float(phi.min())
