"""Integrate-and-reset accelerometer board and its AD-reset error.

The accelerometer current is integrated on a capacitor; a comparator at
``±V_bound`` fires a reset pulse that removes a fixed charge, worth
``N_t`` AD counts.  The navigation computer forms each velocity increment
from the reset-pulse count and the AD value (seed 000, eq (1)-(5)).  If the
AD counts per reset pulse are mis-known, ``N_hat = N_t + N_e``, the
velocity error stays bounded (eq (6)-(8)) and the acceleration error is a
constant plus a reset-pulse train (eq (9)-(10)).

Conventions
-----------
SI inside: accelerations [m/s^2], velocities [m/s], times [s].  AD values
and ``N_t``, ``N_e``, ``V_bound`` are in AD counts; ``SF`` is the velocity
worth of one reset pulse [m/s/pulse].  Samples are indexed ``k`` (or ``n``)
at the board's acquisition interval ``dt``.

References
----------
seed 000: Sung, Lee, Lee, Park, "Effects of accelerometer signal processing
errors on inertial navigation systems" (2006).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "BoardRecord",
    "scale_factor_from_reset_period",
    "reset_period",
    "reset_period_samples",
    "reset_pulse_indices",
    "simulate_board",
    "velocity_increment",
    "velocity_increment_error",
    "velocity_error",
    "velocity_error_bound",
    "acceleration_error",
    "pulse_height",
    "constant_error",
    "pulse_train_error",
    "velocity_error_sigma",
    "suggested_time_constant",
]

_ROUNDINGS = ("floor", "round", "ceil")


def _check_positive(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return value


def _n_hat(n_t: float, n_e: float) -> float:
    n_hat = float(n_t) + float(n_e)
    if not n_hat > 0:
        raise ValueError(f"n_t + n_e must be positive, got {n_t!r} + {n_e!r}")
    return n_hat


def scale_factor_from_reset_period(accel: float, period: float, dt: float) -> float:
    """Scale factor SF that gives a reset period at an acceleration.

    Parameters
    ----------
    accel : float
        Input acceleration at which the reset period is ``period``. [m/s^2]
    period : float
        Reset period at ``accel``. [samples]
    dt : float
        Board acquisition interval. [s]

    Returns
    -------
    float
        SF, the velocity worth of one reset pulse. [m/s]

    Notes
    -----
    One reset pulse is worth ``SF`` of velocity (seed 000, eq (4)), so a
    constant input ``a`` fires a pulse every ``SF / (|a| dt)`` samples.
    Inverting at ``(a*, N*)`` gives ``SF = a* N* dt``.  Seed 000 states that
    the reset period equals ``2 pi / omega_n`` at about 0.9 m/s^2.
    """
    return _check_positive("accel", abs(accel)) * _check_positive("period", period) * _check_positive("dt", dt)


def reset_period(accel, sf: float, dt: float):
    """Reset-pulse period for a constant input acceleration.

    Parameters
    ----------
    accel : float or ndarray
        Input acceleration. [m/s^2]
    sf : float
        Velocity worth of one reset pulse. [m/s]
    dt : float
        Board acquisition interval. [s]

    Returns
    -------
    float or ndarray
        ``N_a = SF / (|a| dt)``; infinite at zero input. [samples]

    Notes
    -----
    Seed 000, eq (10): ``N_a`` is inversely proportional to the input.
    """
    a = np.abs(np.asarray(accel, dtype=float))
    with np.errstate(divide="ignore"):
        out = sf / (a * dt)
    return float(out) if out.ndim == 0 else out


def reset_period_samples(accel: float, sf: float, dt: float, rounding: str = "floor") -> int:
    """Reset period rounded to whole samples.

    Parameters
    ----------
    accel : float
        Input acceleration (non-zero). [m/s^2]
    sf, dt : float
        Scale factor [m/s] and acquisition interval [s].
    rounding : {'floor', 'round', 'ceil'}
        How the real-valued period is made an integer.

    Returns
    -------
    int
        Period of the idealised pulse train of seed 000, eq (10). [samples]

    Notes
    -----
    Eq (10) writes the pulse train as ``sum_k delta[n - n_R0 - k N_a]``,
    which needs an integer ``N_a``.  A real board alternates between
    ``floor(N_a)`` and ``ceil(N_a)`` (see :func:`reset_pulse_indices`).
    """
    if rounding not in _ROUNDINGS:
        raise ValueError(f"rounding must be one of {_ROUNDINGS}, got {rounding!r}")
    if accel == 0:
        raise ValueError("the reset period is infinite at zero input acceleration")
    n_a = reset_period(accel, sf, dt)
    n = {"floor": math.floor, "round": round, "ceil": math.ceil}[rounding](n_a)
    return max(int(n), 1)


def reset_pulse_indices(accel: float, n_samples: int, sf: float, dt: float, phase: float = 0.0) -> np.ndarray:
    """Samples at which a board fires reset pulses, constant input.

    Parameters
    ----------
    accel : float
        Constant input acceleration. [m/s^2]
    n_samples : int
        Number of samples.
    sf, dt : float
        Scale factor [m/s] and acquisition interval [s].
    phase : float
        Initial capacitor charge as a fraction of one reset pulse, in
        ``[0, 1)``.

    Returns
    -------
    ndarray of int
        Sample indices ``k`` whose interval ``(t_{k-1}, t_k]`` contains a
        reset (one entry per pulse, sign not included).

    Notes
    -----
    This is the closed-form equivalent of :func:`simulate_board` for a
    constant input with ``V_bound = N_t``: the charge after ``k + 1``
    samples is ``phase + (k + 1) |a| dt / SF`` pulses, and a pulse fires each
    time it crosses an integer.  The spacing alternates between
    ``floor(N_a)`` and ``ceil(N_a)`` samples.
    """
    if not 0.0 <= phase < 1.0:
        raise ValueError(f"phase must be in [0, 1), got {phase!r}")
    charge = phase + np.arange(1, n_samples + 1) * (abs(accel) * dt / sf)
    counts = np.floor(charge + 1e-12)
    steps = np.diff(np.concatenate(([0.0], counts))).astype(int)
    return np.repeat(np.arange(n_samples), steps)


@dataclass(frozen=True)
class BoardRecord:
    """Sample-by-sample output of the accelerometer board.

    Attributes
    ----------
    d_r : ndarray of int, shape (n,)
        Reset-pulse count increment per sample, ``Delta R``.
    ad : ndarray, shape (n,)
        AD value (capacitor voltage) at the end of each sample. [counts]
    d_ad : ndarray, shape (n,)
        AD increment per sample, ``Delta AD``. [counts]
    d_v_ad : ndarray, shape (n,)
        Input-driven voltage increment ``Delta R N_t + Delta AD``. [counts]
    d_vel : ndarray, shape (n,)
        Velocity increment computed with ``N_hat``. [m/s]
    d_vel_true : ndarray, shape (n,)
        Velocity increment computed with the true ``N_t``. [m/s]
    """

    d_r: np.ndarray
    ad: np.ndarray
    d_ad: np.ndarray
    d_v_ad: np.ndarray
    d_vel: np.ndarray
    d_vel_true: np.ndarray

    @property
    def d_vel_error(self) -> np.ndarray:
        """Velocity-increment error ``Delta Vel_e`` (eq 6). [m/s]"""
        return self.d_vel - self.d_vel_true

    @property
    def vel_error(self) -> np.ndarray:
        """Accumulated velocity error ``Vel_e,k`` (eq 8). [m/s]"""
        return np.cumsum(self.d_vel_error)


def simulate_board(accel, *, dt: float, sf: float, n_t: float, n_e: float = 0.0,
                   v_bound: float | None = None, ad0: float = 0.0) -> BoardRecord:
    """Simulate the integrate-and-reset board sample by sample.

    Parameters
    ----------
    accel : array_like, shape (n,)
        Input acceleration, held constant over each sample. [m/s^2]
    dt : float
        Acquisition interval. [s]
    sf : float
        Velocity worth of one reset pulse. [m/s]
    n_t : float
        True AD counts per reset pulse, ``N_t``. [counts]
    n_e : float
        Error of the AD counts per pulse used by the computer. [counts]
    v_bound : float, optional
        Comparator threshold ``V_bound``; default ``N_t``.  Must exceed
        ``N_t / 2`` so that one reset returns the voltage inside the band.
        [counts]
    ad0 : float
        Initial AD value, ``|ad0| < v_bound``. [counts]

    Returns
    -------
    BoardRecord

    Notes
    -----
    Seed 000, eq (1): the capacitor voltage integrates the accelerometer
    current; in AD counts the charge per sample is ``a dt N_t / SF``.
    Eq (2): at ``+V_bound`` a reset removes ``N_t`` counts and the pulse
    count goes up by one, at ``-V_bound`` it adds ``N_t`` and the count goes
    down.  Eq (3): ``Delta V = Delta R N_t + Delta AD``.  Eq (4): the
    computer forms ``Delta Vel = SF (Delta R + Delta AD / N_hat)`` with
    ``N_hat = N_t + N_e``.
    """
    a = np.asarray(accel, dtype=float)
    if a.ndim != 1:
        raise ValueError(f"accel must be one-dimensional, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("accel must be finite")
    dt = _check_positive("dt", dt)
    sf = _check_positive("sf", sf)
    n_t = _check_positive("n_t", n_t)
    n_hat = _n_hat(n_t, n_e)
    vb = n_t if v_bound is None else float(v_bound)
    if not vb > n_t / 2:
        raise ValueError(f"v_bound must exceed n_t/2 = {n_t / 2:g} counts, got {vb!r}")
    if not abs(ad0) < vb:
        raise ValueError(f"|ad0| must be below v_bound = {vb:g} counts, got {ad0!r}")

    charge = a * (dt * n_t / sf)
    n = a.size
    d_r = np.zeros(n, dtype=np.int64)
    ad = np.empty(n)
    v = float(ad0)
    for k in range(n):
        v += charge[k]
        r = 0
        while v >= vb:
            v -= n_t
            r += 1
        while v <= -vb:
            v += n_t
            r -= 1
        d_r[k] = r
        ad[k] = v
    d_ad = np.diff(np.concatenate(([float(ad0)], ad)))
    return BoardRecord(
        d_r=d_r,
        ad=ad,
        d_ad=d_ad,
        d_v_ad=d_r * n_t + d_ad,
        d_vel=velocity_increment(d_r, d_ad, sf, n_hat),
        d_vel_true=velocity_increment(d_r, d_ad, sf, n_t),
    )


def velocity_increment(d_r, d_ad, sf: float, n_ad: float):
    """Velocity increment from reset count and AD increment.

    Parameters
    ----------
    d_r : array_like
        Reset-pulse count increment ``Delta R``.
    d_ad : array_like
        AD increment ``Delta AD``. [counts]
    sf : float
        Velocity worth of one reset pulse. [m/s]
    n_ad : float
        AD counts per reset pulse used in the computation. [counts]

    Returns
    -------
    ndarray
        ``Delta Vel = SF (Delta R + Delta AD / N)`` (seed 000, eq (4)). [m/s]
    """
    return sf * (np.asarray(d_r, dtype=float) + np.asarray(d_ad, dtype=float) / n_ad)


def velocity_increment_error(d_ad, sf: float, n_t: float, n_e: float, *, exact: bool = True):
    """Velocity-increment error from a mis-known N.

    Parameters
    ----------
    d_ad : array_like
        AD increment. [counts]
    sf, n_t, n_e : float
        Scale factor [m/s], true counts per pulse and its error [counts].
    exact : bool
        ``True``: ``SF dAD (1/N_hat - 1/N_t)``; ``False``: the first-order
        form ``-SF N_e dAD / N_t^2``.

    Returns
    -------
    ndarray
        ``Delta Vel_e`` (seed 000, eq (6)). [m/s]
    """
    d_ad = np.asarray(d_ad, dtype=float)
    if exact:
        return sf * d_ad * (1.0 / _n_hat(n_t, n_e) - 1.0 / n_t)
    return -sf * n_e / n_t**2 * d_ad


def velocity_error(ad, sf: float, n_t: float, n_e: float, *, ad0: float = 0.0, exact: bool = True):
    """Accumulated velocity error from the AD value.

    Parameters
    ----------
    ad : array_like
        AD value at ``t_k``. [counts]
    sf, n_t, n_e : float
        Scale factor [m/s], true counts per pulse and its error [counts].
    ad0 : float
        AD value at the start of the sum. [counts]
    exact : bool
        Exact or first-order form (see :func:`velocity_increment_error`).

    Returns
    -------
    ndarray
        ``Vel_e,k = sum_i Delta Vel_e,i = -SF N_e AD_k / N_t^2``
        (seed 000, eq (8)): the reset terms cancel, the sum telescopes. [m/s]
    """
    return velocity_increment_error(np.asarray(ad, dtype=float) - ad0, sf, n_t, n_e, exact=exact)


def velocity_error_bound(sf: float, n_t: float, n_e: float, *, v_bound: float | None = None,
                         exact: bool = True) -> float:
    """Bound on the AD-reset velocity error.

    Parameters
    ----------
    sf, n_t, n_e : float
        Scale factor [m/s], true counts per pulse and its error [counts].
    v_bound : float, optional
        Largest AD magnitude (the comparator threshold); default ``N_t``.
        [counts]
    exact : bool
        ``True``: ``SF |N_e| V_b / (N_t N_hat)``; ``False``: the paper's
        first-order ``SF |N_e| V_b / N_t^2``.

    Returns
    -------
    float
        Bound on ``|Delta Vel_e|`` and on ``|Vel_e,k|`` (from rest). [m/s]

    Notes
    -----
    Seed 000, eq (7): with ``|Delta AD| <= N_t``,
    ``|Delta Vel_e| <= SF |N_e| / N_t``; eq (8) gives the same bound on the
    accumulated error because ``|AD_k| <= V_bound = N_t``.
    """
    vb = n_t if v_bound is None else v_bound
    denom = n_t * _n_hat(n_t, n_e) if exact else n_t**2
    return float(sf * abs(n_e) * vb / denom)


def acceleration_error(d_r, d_v_ad, sf: float, n_t: float, n_e: float, dt: float, *, exact: bool = True):
    """Acceleration error split into reset and voltage terms.

    Parameters
    ----------
    d_r : array_like
        Reset-pulse count increment.
    d_v_ad : array_like
        Input-driven voltage increment ``Delta R N_t + Delta AD``. [counts]
    sf, n_t, n_e : float
        Scale factor [m/s], true counts per pulse and its error [counts].
    dt : float
        Acquisition interval. [s]
    exact : bool
        ``True``: ``(SF/dt)(dR N_e/N_hat - dV_AD N_e/(N_t N_hat))``;
        ``False``: the paper's last line with ``N_t N_hat ~ N_t^2``.

    Returns
    -------
    ndarray
        ``Acc_e,k`` (seed 000, eq (9)). [m/s^2]
    """
    n_hat = _n_hat(n_t, n_e)
    d_r = np.asarray(d_r, dtype=float)
    d_v_ad = np.asarray(d_v_ad, dtype=float)
    second = n_e / (n_t * n_hat) if exact else n_e / n_t**2
    return sf / dt * (d_r * n_e / n_hat - d_v_ad * second)


def pulse_height(sf: float, n_t: float, n_e: float, dt: float) -> float:
    """Height S of each reset pulse in the acceleration error.

    Returns
    -------
    float
        ``S = SF N_e / (N_hat dt)`` (seed 000, eq (10)). [m/s^2]
    """
    return float(sf * n_e / (_n_hat(n_t, n_e) * dt))


def constant_error(accel, n_t: float, n_e: float, *, exact: bool = True):
    """Constant part of the acceleration error.

    Parameters
    ----------
    accel : float or ndarray
        Input acceleration. [m/s^2]
    n_t, n_e : float
        True counts per pulse and its error. [counts]
    exact : bool
        ``True``: ``-a N_e / N_hat``; ``False``: ``-a N_e / N_t``.

    Returns
    -------
    float or ndarray
        ``E_Ne a`` of seed 000, eq (10), with ``Delta V_AD = a dt N_t / SF``
        substituted. [m/s^2]

    Notes
    -----
    With the exact form, the mean of the pulse train, ``S / N_a``, cancels
    this constant: the mean acceleration error is zero, as the bounded
    velocity error of eq (8) requires.
    """
    return -np.asarray(accel, dtype=float) * n_e / (_n_hat(n_t, n_e) if exact else n_t)


def pulse_train_error(n_samples: int, accel: float, *, sf: float, n_t: float, n_e: float, dt: float,
                      period: int | None = None, n_r0: int | None = None,
                      pulses: np.ndarray | None = None, exact: bool = True) -> np.ndarray:
    """Acceleration error as constant plus reset-pulse train.

    Parameters
    ----------
    n_samples : int
        Length of the sequence.
    accel : float
        Constant input acceleration. [m/s^2]
    sf, n_t, n_e, dt : float
        Board parameters.
    period : int, optional
        Integer pulse period ``N_a`` [samples]; default
        ``floor(SF / (|a| dt))``.
    n_r0 : int, optional
        First pulse ``n_R0`` [samples]; default ``period - 1``.
    pulses : ndarray of int, optional
        Explicit pulse indices (overrides ``period`` and ``n_r0``), e.g.
        from :func:`reset_pulse_indices`.
    exact : bool
        Form of the constant term (see :func:`constant_error`).

    Returns
    -------
    ndarray, shape (n_samples,)
        ``Acc_e[n] = E a u[n] + S sgn(a) sum_k delta[n - n_R0 - k N_a]``
        (seed 000, eq (10)). [m/s^2]
    """
    out = np.full(n_samples, float(constant_error(accel, n_t, n_e, exact=exact)))
    if accel == 0:
        return out
    if pulses is None:
        if period is None:
            period = reset_period_samples(accel, sf, dt, "floor")
        if n_r0 is None:
            n_r0 = period - 1
        pulses = np.arange(n_r0, n_samples, period)
    np.add.at(out, np.asarray(pulses, dtype=int), math.copysign(1.0, accel) * pulse_height(sf, n_t, n_e, dt))
    return out


def velocity_error_sigma(sf: float, n_t: float, n_e: float, *, v_bound: float | None = None,
                         distribution: str = "uniform") -> float:
    """1-sigma of the bounded AD-reset velocity error.

    Parameters
    ----------
    sf : float
        Velocity worth of one reset pulse. [m/s]
    n_t : float
        True AD counts per reset pulse. [counts]
    n_e : float
        Error of the counts per pulse (1-sigma or design value). [counts]
    v_bound : float, optional
        Comparator threshold; default ``N_t``. [counts]
    distribution : {'uniform', 'sawtooth'}
        ``'uniform'``: the error is taken uniform on ``[-B, B]``, the right
        zero-mean model when the sign of the specific force is not known in
        advance, ``sigma = B / sqrt(3)``.  ``'sawtooth'``: the input sign
        is known, the error sweeps ``[0, B]`` (or ``[-B, 0]``) linearly
        between resets; returns the spread about its mean, ``B / sqrt(12)``
        (the mean ``B / 2`` is then a bias, not noise).

    Returns
    -------
    float
        Standard deviation of the AD-reset velocity error. [m/s]

    Notes
    -----
    ``B`` is the bound of seed 000, eq (7)-(8) (exact form, see
    :func:`velocity_error_bound`).  Between resets the AD value ramps
    linearly through a band of ``N_t`` counts; with an unknown phase it is
    uniform over that band, so the velocity error of eq (8) is uniform.
    With ``'uniform'``, 3/4 of the variance is the band's mean (a random
    constant while the specific force keeps its sign) and 1/4 the
    sawtooth (see :func:`suggested_time_constant`).  ``n_e`` may be the
    1-sigma of the N error: ``B`` is linear in ``|N_e|``.
    """
    bound = velocity_error_bound(sf, n_t, n_e, v_bound=v_bound)
    if distribution == "uniform":
        return bound / math.sqrt(3.0)
    if distribution == "sawtooth":
        return bound / math.sqrt(12.0)
    raise ValueError(f"distribution must be 'uniform' or 'sawtooth', got {distribution!r}")


def suggested_time_constant(sf: float, specific_force: float, *, tau_max: float = math.inf) -> float:
    """Time constant of the sawtooth part of the AD-reset error.

    Parameters
    ----------
    sf : float
        Velocity worth of one reset pulse. [m/s]
    specific_force : float
        Nominal specific force along the accelerometer axis. [m/s^2]
    tau_max : float
        Cap for near-zero specific force, where the sawtooth stalls and the
        error is a random constant in practice (e.g. the study duration).
        [s]

    Returns
    -------
    float
        ``tau = SF / (6 |f|)``, capped at ``tau_max``. [s]

    Notes
    -----
    The error of seed 000, eq (8) is ``-SF N_e AD_k / N_t^2``; while the
    specific force keeps its sign, ``AD_k`` is its mean (``+-N_t/2``) plus
    a sawtooth of period ``T_R = SF / |f|`` (one reset pulse).  The mean
    part is a random constant carrying 3/4 of the variance of
    :func:`velocity_error_sigma`; the sawtooth carries 1/4.  A sawtooth
    with uniformly distributed phase has the autocorrelation
    ``R(tau) = sigma^2 (1 - 6|tau|/T_R + 6 tau^2/T_R^2)`` on
    ``|tau| <= T_R``; the first-order Markov process with the same variance
    and initial slope ``-6 sigma^2 / T_R`` has ``tau = T_R / 6``.  This is
    the time constant of that sawtooth part only (about 1 ms at 1 g,
    1 s at 1 mg with SF = 0.064 m/s).
    """
    sf = _check_positive("sf", sf)
    f = abs(float(specific_force))
    if f == 0:
        return float(tau_max)
    return float(min(sf / (6.0 * f), tau_max))
