"""Second-order IIR output filter and the filtered pulse error.

The body-acceleration output and the alignment both pass the board's
acceleration error through a second-order IIR filter (seed 000, eq (11)).
This module builds the filter as a python-control transfer function, gives
its impulse response exactly (eq (12)) and approximately (eq (13)), and the
periodic steady state of a filtered pulse train (eq (15)-(16)), its zeros
and extrema (eq (17)-(18)) and the amplitude regimes (eq (19)-(20)).

Conventions
-----------
``n`` and ``N_a`` are in samples of the filter's own rate.  ``zeta`` is the
pole radius and ``omega_n`` the pole angle [rad/sample], as in eq (11).
Amplitudes here are per unit pulse height; multiply by ``S`` of eq (10)
(:func:`covtool.board.adreset.pulse_height`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import optimize, signal

__all__ = [
    "SecondOrderFilter",
    "butterworth_filter",
    "impulse_response",
    "isolated_extrema",
    "isolated_amplitude",
    "periodic_error",
    "zero_point",
    "extremum_point",
    "regime_thresholds",
    "amplitude_closed_form",
    "pulse_train",
    "periodic_extrema",
    "filter_signal",
    "moving_average_decimate",
]


@dataclass(frozen=True)
class SecondOrderFilter:
    """Second-order IIR filter of seed 000, eq (11).

    ``H(z) = b (1 + z^-1)^2 / (1 - 2 zeta cos(omega_n) z^-1 + zeta^2 z^-2)``

    Parameters
    ----------
    b : float
        Numerator gain.
    zeta : float
        Pole radius, ``0 < zeta < 1``.
    omega_n : float
        Pole angle. [rad/sample]
    dt : float
        Sample interval. [s]
    """

    b: float
    zeta: float
    omega_n: float
    dt: float

    def __post_init__(self):
        if not 0.0 < self.zeta < 1.0:
            raise ValueError(f"zeta must be in (0, 1), got {self.zeta!r}")
        if not 0.0 < self.omega_n < math.pi:
            raise ValueError(f"omega_n must be in (0, pi), got {self.omega_n!r}")
        if not self.dt > 0:
            raise ValueError(f"dt must be positive, got {self.dt!r}")

    @property
    def num(self) -> np.ndarray:
        """Numerator coefficients in powers of ``z^-1``."""
        return self.b * np.array([1.0, 2.0, 1.0])

    @property
    def den(self) -> np.ndarray:
        """Denominator coefficients in powers of ``z^-1``."""
        return np.array([1.0, -2.0 * self.zeta * math.cos(self.omega_n), self.zeta**2])

    @cached_property
    def tf(self):
        """The filter as a python-control ``TransferFunction``."""
        import control

        return control.tf(self.num, self.den, self.dt)

    @property
    def dc_gain(self) -> float:
        """``H(1)``."""
        return float(self.num.sum() / self.den.sum())

    @property
    def ringing_period(self) -> float:
        """``2 pi / omega_n``, the second zero of eq (13). [samples]"""
        return 2.0 * math.pi / self.omega_n

    @classmethod
    def from_coefficients(cls, num, den, dt: float) -> "SecondOrderFilter":
        """Build from ``b (1, 2, 1)`` / ``(1, a1, a2)`` coefficients."""
        num = np.asarray(num, dtype=float) / den[0]
        den = np.asarray(den, dtype=float) / den[0]
        if not np.allclose(num, num[0] * np.array([1.0, 2.0, 1.0]), rtol=1e-9, atol=0):
            raise ValueError(f"numerator must be b*(1, 2, 1), got {num}")
        zeta = math.sqrt(den[2])
        return cls(b=float(num[0]), zeta=zeta, omega_n=math.acos(-den[1] / (2.0 * zeta)), dt=dt)


def butterworth_filter(cutoff: float, sample_rate: float, *, damping: float = 1 / math.sqrt(2)) -> SecondOrderFilter:
    """Design the eq (11) filter from a cutoff and a sample rate.

    Parameters
    ----------
    cutoff : float
        -3 dB cutoff frequency (for the default damping). [Hz]
    sample_rate : float
        Filter sample rate. [Hz]
    damping : float
        Damping ratio of the analog prototype; ``1/sqrt(2)`` is Butterworth.

    Returns
    -------
    SecondOrderFilter
        Unit DC gain, poles ``zeta exp(+-j omega_n)``.

    Notes
    -----
    The analog prototype ``w^2 / (s^2 + 2 d w s + w^2)`` with the
    pre-warped ``w = (2/T) tan(pi f_c T)`` is mapped by the bilinear
    transform ``s = (2/T)(1 - z^-1)/(1 + z^-1)``.  With
    ``K = tan(pi f_c T)`` and ``D = 1 + 2 d K + K^2``:
    ``b = K^2 / D``, ``2 zeta cos(omega_n) = 2 (1 - K^2) / D``,
    ``zeta^2 = (1 - 2 d K + K^2) / D``.  The double zero at ``z = -1``
    gives eq (11)'s ``(1 + z^-1)^2``.
    """
    if not (cutoff > 0 and sample_rate > 0 and cutoff < sample_rate / 2):
        raise ValueError(f"need 0 < cutoff < sample_rate/2, got cutoff={cutoff!r}, sample_rate={sample_rate!r}")
    if not damping > 0:
        raise ValueError(f"damping must be positive, got {damping!r}")
    k = math.tan(math.pi * cutoff / sample_rate)
    d = 1.0 + 2.0 * damping * k + k * k
    a1 = 2.0 * (k * k - 1.0) / d
    a2 = (1.0 - 2.0 * damping * k + k * k) / d
    if a1 * a1 >= 4.0 * a2:
        raise ValueError(f"damping {damping!r} gives real poles; eq (11) needs a complex pair")
    return SecondOrderFilter.from_coefficients([k * k / d, 2 * k * k / d, k * k / d], [1.0, a1, a2], 1.0 / sample_rate)


def impulse_response(filt: SecondOrderFilter, n, *, approx: bool = False) -> np.ndarray:
    """Impulse response of the eq (11) filter.

    Parameters
    ----------
    filt : SecondOrderFilter
    n : array_like
        Sample indices (real values allowed for ``approx=True``).
    approx : bool
        ``False``: exact inverse z-transform (seed 000, eq (12), corrected,
        see Notes).  ``True``: eq (13), valid for small ``omega_n``.

    Returns
    -------
    ndarray
        ``h[n]``, zero for ``n < 0``.

    Notes
    -----
    Dividing eq (11) gives ``H = b/zeta^2 + R(z)``; inverting ``R`` with
    ``1/(1 - 2 zeta c z^-1 + zeta^2 z^-2) <-> zeta^n sin(w(n+1))/sin w``
    (``c = cos w``, ``w = omega_n``) gives

    ``h[n] = (b/zeta^2) delta[n] + (b/zeta^2) zeta^n {(zeta^2-1) cos(w n)
    + ((zeta^2+1) cos w + 2 zeta) / sin(w) * sin(w n)} u[n]``.

    Eq (12) as printed has ``(zeta+1)^2 cos w`` in place of
    ``(zeta^2+1) cos w + 2 zeta``; the two differ by
    ``2 zeta (1 - cos w) ~ zeta w^2``, below the accuracy of eq (13).
    Eq (13) keeps only the sine term, ``C zeta^n sin(w n)`` with
    ``C = b (zeta+1)^2 cos(w) / (zeta^2 sin(w))``.
    """
    n = np.asarray(n, dtype=float)
    z, w, b = filt.zeta, filt.omega_n, filt.b
    step = (n >= 0).astype(float)
    zn = np.where(n >= 0, z ** np.maximum(n, 0.0), 0.0)
    if approx:
        c = b * (z + 1) ** 2 * math.cos(w) / (z * z * math.sin(w))
        return c * zn * np.sin(w * n) * step
    cs, sn = _exact_coefficients(filt)
    tail = zn * (cs * np.cos(w * n) + sn * np.sin(w * n))
    return (b / z**2) * (n == 0) + tail * step


def _exact_coefficients(filt: SecondOrderFilter) -> tuple[float, float]:
    """Cosine and sine coefficients of the exact h[n] tail."""
    z, w, b = filt.zeta, filt.omega_n, filt.b
    return b * (z * z - 1) / z**2, b * ((z * z + 1) * math.cos(w) + 2 * z) / (z * z * math.sin(w))


def isolated_extrema(filt: SecondOrderFilter) -> tuple[float, float]:
    """Maximum and minimum points of eq (13), from eq (14).

    Returns
    -------
    (float, float)
        ``n`` of the first maximum (``k = 0``) and minimum (``k = 1``).
        [samples]

    Notes
    -----
    Seed 000, eq (14): ``n = {atan(-omega_n / ln zeta) + k pi} / omega_n``.
    """
    base = math.atan(-filt.omega_n / math.log(filt.zeta))
    return base / filt.omega_n, (base + math.pi) / filt.omega_n


def isolated_amplitude(filt: SecondOrderFilter, *, method: str = "closed_form") -> float:
    """Peak-to-peak response to one unit pulse (no interference).

    Parameters
    ----------
    filt : SecondOrderFilter
    method : {'closed_form', 'exact'}
        ``'closed_form'``: eq (13) at the eq (14) points;
        ``'exact'``: max minus min of the exact ``h[n]`` over integers.

    Returns
    -------
    float
        ``max h - min h``; times ``S`` gives the amplitude of Fig 2.
    """
    if method == "closed_form":
        n_max, n_min = isolated_extrema(filt)
        h = impulse_response(filt, [n_max, n_min], approx=True)
        return float(h[0] - h[1])
    if method == "exact":
        n = np.arange(int(50.0 / -math.log(filt.zeta)) + 10)
        h = impulse_response(filt, n)
        return float(h.max() - h.min())
    raise ValueError(f"method must be 'closed_form' or 'exact', got {method!r}")


def _ab(filt: SecondOrderFilter, n_a: float) -> tuple[float, float]:
    q = filt.zeta**n_a
    return 1.0 - q * math.cos(filt.omega_n * n_a), q * math.sin(filt.omega_n * n_a)


def periodic_error(filt: SecondOrderFilter, n_a: float, n, *, approx: bool = True) -> np.ndarray:
    """Periodic steady state of a filtered unit pulse train.

    Parameters
    ----------
    filt : SecondOrderFilter
    n_a : float
        Pulse period ``N_a`` [samples]; must be an integer when
        ``approx=False``.
    n : array_like
        Points in ``[0, N_a - 1]`` (real values allowed for ``approx``).
    approx : bool
        ``True``: seed 000, eq (16) (eq (13) summed).  ``False``: eq (15)
        summed in closed form with the exact ``h`` of eq (12).

    Returns
    -------
    ndarray
        ``e[n] = sum_i h[n + i N_a]`` (eq (15)).

    Notes
    -----
    With ``q = zeta^N_a exp(j omega_n N_a)``,
    ``sum_i zeta^(n+iN) exp(j omega_n (n+iN)) = zeta^n exp(j omega_n n)/(1-q)``.
    The sine part gives eq (16), in which the scan's ``zeta^N`` is
    ``zeta^N_a``; the cosine part and the ``delta[n]`` term (at ``n = 0``
    only) complete the exact sum.  The ``delta`` term, ``b/zeta^2``, is what
    eq (13) drops; it is negligible against the isolated peak but comparable
    to the ripple when ``N_a`` is a few samples, so eq (16) then
    overestimates the amplitude.
    """
    n = np.asarray(n, dtype=float)
    z, w = filt.zeta, filt.omega_n
    if approx:
        c = filt.b * (z + 1) ** 2 * math.cos(w) / (z * z * math.sin(w))
        q = z**n_a
        den = 1.0 - 2.0 * q * math.cos(w * n_a) + q * q
        return c / den * z**n * (q * np.sin(w * (n_a - n)) + np.sin(w * n))
    if n_a != int(n_a) or n_a < 1:
        raise ValueError(f"the exact periodic sum needs an integer period >= 1, got {n_a!r}")
    geo = z**n * np.exp(1j * w * n) / (1.0 - z**n_a * np.exp(1j * w * n_a))
    cs, sn = _exact_coefficients(filt)
    return (filt.b / z**2) * (n == 0) + cs * geo.real + sn * geo.imag


def zero_point(filt: SecondOrderFilter, n_a: float, k: int) -> float:
    """Zero of the periodic error eq (16), ``Z(N_a, k)``.

    Returns
    -------
    float
        ``Z = {atan(-zeta^N sin(omega_n N) / (1 - zeta^N cos(omega_n N)))
        + k pi} / omega_n`` with ``N = N_a``. [samples]

    Notes
    -----
    Seed 000, eq (17), re-derived: eq (16) vanishes where
    ``sin(w n)(1 - zeta^N cos wN) + zeta^N sin(wN) cos(w n) = 0``.  The scan
    prints the argument as ``zeta^N / (zeta^N cos(wN) + 1)``; it has lost
    the factor ``sin(wN)`` and the sign of the ``1``.
    """
    a, bb = _ab(filt, n_a)
    return (math.atan(-bb / a) + k * math.pi) / filt.omega_n


def extremum_point(filt: SecondOrderFilter, n_a: float, k: int) -> float:
    """Extremum of the periodic error eq (16), ``D(N_a, k)``.

    Returns
    -------
    float
        ``D = {atan((w A + ln(zeta) B) / (w B - ln(zeta) A)) + k pi} / w``
        with ``A = 1 - zeta^N cos(wN)``, ``B = zeta^N sin(wN)``. [samples]

    Notes
    -----
    Seed 000, eq (18), re-derived from
    ``d/dn [zeta^n (A sin wn + B cos wn)] = 0``.  Dividing numerator and
    denominator by ``-cos(wN)`` gives the printed form, except that the
    denominator's ``w tan(wN)`` term carries a minus sign in the
    derivation.  As ``N_a -> inf`` it tends to eq (14).
    """
    a, bb = _ab(filt, n_a)
    w, lz = filt.omega_n, math.log(filt.zeta)
    return (math.atan((w * a + lz * bb) / (w * bb - lz * a)) + k * math.pi) / w


def regime_thresholds(filt: SecondOrderFilter) -> dict[str, float]:
    """Periods D0, Z1, D1 that separate the regimes of eq (20).

    Returns
    -------
    dict
        ``{"D0", "Z1", "D1"}``: the ``N_a`` solving ``D(N_a, 0) = N_a - 1``,
        ``Z(N_a, 1) = N_a - 1`` and ``D(N_a, 1) = N_a - 1``. [samples]

    Notes
    -----
    Seed 000, eq (19) orders them as
    ``0 < D0 < Z1 < pi/omega_n < D1 < 2 pi/omega_n``.
    """
    half = math.pi / filt.omega_n

    def root(fun, lo, hi):
        grid = np.linspace(lo, hi, 2000)
        vals = np.array([fun(x) for x in grid])
        ok = np.isfinite(vals)
        for i in range(len(grid) - 1):
            if ok[i] and ok[i + 1] and vals[i] * vals[i + 1] <= 0 and abs(vals[i] - vals[i + 1]) < half:
                return float(optimize.brentq(fun, grid[i], grid[i + 1], xtol=1e-10))
        raise ValueError("no regime threshold found in the search interval")

    return {
        "D0": root(lambda x: extremum_point(filt, x, 0) - (x - 1), 1.5, 2 * half),
        "Z1": root(lambda x: zero_point(filt, x, 1) - (x - 1), 1.5, 3 * half),
        "D1": root(lambda x: extremum_point(filt, x, 1) - (x - 1), 1.5, 4 * half),
    }


def amplitude_closed_form(filt: SecondOrderFilter, n_a: float, thresholds: dict | None = None) -> float:
    """Peak-to-peak of the periodic error by the regimes of eq (20).

    Parameters
    ----------
    filt : SecondOrderFilter
    n_a : float
        Pulse period. [samples]
    thresholds : dict, optional
        Output of :func:`regime_thresholds` (computed if omitted).

    Returns
    -------
    float
        Amplitude per unit pulse height, eq (16) evaluated at the points
        of eq (20):

        * ``N_a <= D0``: ``e[N_a-1] - e[0]``
        * ``D0 < N_a <= Z1``: ``e[D(N_a,0)] - e[0]``
        * ``Z1 < N_a <= D1``: ``e[D(N_a,0)] - e[N_a-1]``
        * ``N_a > D1``: ``e[D(N_a,0)] - e[D(N_a,1)]``
    """
    t = thresholds or regime_thresholds(filt)

    def e(x):
        return float(periodic_error(filt, n_a, x, approx=True))

    if n_a <= t["D0"]:
        return e(n_a - 1) - e(0)
    d0 = extremum_point(filt, n_a, 0)
    if n_a <= t["Z1"]:
        return e(d0) - e(0)
    if n_a <= t["D1"]:
        return e(d0) - e(n_a - 1)
    return e(d0) - e(extremum_point(filt, n_a, 1))


def pulse_train(n_samples: int, period: int, first: int = 0) -> np.ndarray:
    """Unit pulse train ``sum_k delta[n - first - k period]``."""
    if period < 1:
        raise ValueError(f"period must be >= 1, got {period!r}")
    x = np.zeros(n_samples)
    x[first::period] = 1.0
    return x


def filter_signal(system, x) -> np.ndarray:
    """Run a SISO discrete python-control system over a sequence.

    Parameters
    ----------
    system : control.TransferFunction or SecondOrderFilter
        Discrete-time SISO system.
    x : array_like, shape (n,)
        Input sequence at the system's sample rate.

    Returns
    -------
    ndarray, shape (n,)
        Output from rest.  Uses the transfer function's own coefficients
        with :func:`scipy.signal.lfilter` (identical to
        ``control.forced_response``, much faster for long sequences).
    """
    tf = system.tf if isinstance(system, SecondOrderFilter) else system
    num = np.atleast_1d(np.squeeze(tf.num[0][0])).astype(float)
    den = np.atleast_1d(np.squeeze(tf.den[0][0])).astype(float)
    # python-control stores powers of z; pad to powers of z^-1
    num = np.concatenate((np.zeros(len(den) - len(num)), num))
    return signal.lfilter(num, den, np.asarray(x, dtype=float))


def periodic_extrema(system, period: int, *, factor: int = 1, settle: int | None = None) -> tuple[float, float]:
    """Max and min of a filtered unit pulse train, time domain.

    Parameters
    ----------
    system : control.TransferFunction or SecondOrderFilter
        Discrete SISO system at the pulse-train rate.
    period : int
        Pulse period. [samples]
    factor : int
        If > 1, the output is block-averaged over ``factor`` samples and
        downsampled (:func:`moving_average_decimate`) before the extrema
        are taken -- the navigation-rate output of seed 000, Fig 4.
    settle : int, optional
        Samples simulated before the measured window; default enough for
        the slowest pole to decay by ``1e-12``.

    Returns
    -------
    (float, float)
        Maximum and minimum in steady state, over one full period of the
        (decimated) output, ``lcm(period, factor)`` samples.
    """
    tf = system.tf if isinstance(system, SecondOrderFilter) else system
    if period < 1 or factor < 1:
        raise ValueError(f"period and factor must be >= 1, got {period!r}, {factor!r}")
    if settle is None:
        r = float(np.max(np.abs(tf.poles())))
        settle = int(math.ceil(math.log(1e-12) / math.log(r))) if r > 0 else 10
    window = period * factor // math.gcd(period, factor)
    n_total = (int(math.ceil(settle / window)) + 1) * window
    y = filter_signal(tf, pulse_train(n_total, period))[-window:]
    if factor > 1:
        y = moving_average_decimate(y, factor)
    return float(y.max()), float(y.min())


def moving_average_decimate(x, factor: int) -> np.ndarray:
    """Block moving average then downsample by an integer factor.

    Parameters
    ----------
    x : array_like, shape (n,)
    factor : int
        Samples per output sample; trailing samples that do not fill a
        block are dropped.

    Returns
    -------
    ndarray, shape (n // factor,)
        ``y[m] = mean(x[m factor : (m+1) factor])`` -- the navigation-rate
        output of seed 000, Fig 4 (dotted).
    """
    x = np.asarray(x, dtype=float)
    if factor < 1:
        raise ValueError(f"factor must be >= 1, got {factor!r}")
    n = x.size // factor * factor
    return x[:n].reshape(-1, factor).mean(axis=1)
