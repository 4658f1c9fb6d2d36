"""Filter-tuning sensitivity: sweep grids, batched runs, fits.

Seed 002 §3.2 (Fig 8) scales the filter's assumed P_f(0), Q_f and R_f one at
a time from ×1/100 to ×100 and fits the 30-min RMS navigation error by least
squares.  This module is the numeric core of that study:

* :func:`scale_grid` and :func:`sweep_cases` build the grid of cases;
* :func:`run_sweep` runs every case of one filter in a single batched
  engine call (the truth Φ and Q are shared; only the gains differ);
* :func:`fit_loglog` fits ``log10 err`` by a polynomial in ``log10 scale``;
* :func:`sensitivity_figures` turns a swept curve into the scalar figures.

Pure numeric core: arrays in, arrays out.

Definitions
-----------
*Primary sensitivity* of a filter to a parameter p (P0, Q or R), for an
error metric e (horizontal RMS or altitude RMS at the report time)::

    S_p = max(e(s_max), e(s_min)) / e(1) − 1

with ``s_min, s_max`` the ends of the grid (×1/100 and ×100 in the paper):
the worst relative growth of the true error when the filter's assumed p is
wrong by the full sweep factor in either direction.  ``S_p = 0.5`` means
the error grows by 50 %.  It can be negative for a sub-optimal filter whose
nominal tuning is not the best one.

*Secondary*: the mean absolute log-log slope ``⟨|d log e / d log s|⟩`` over
the grid (finite differences), an elasticity averaged over the sweep.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.polynomial import polynomial as npoly

from covtool.lincov.batch import run_batch, System

#: parameters a sweep may scale: the filter's P_f(0), Q_f and R_f
PARAMETERS = ("P0", "Q", "R")


def scale_grid(start: float, stop: float, per_decade: int) -> np.ndarray:
    """Log-spaced scale factors from ``start`` to ``stop``.

    The grid is ``10^(k/per_decade)`` for integer ``k``.

    Parameters
    ----------
    start, stop : float
        Grid ends; each must be a power of ``10^(1/per_decade)`` (so that
        the grid is exact and contains ×1) and ``start ≤ 1 ≤ stop``. [-]
    per_decade : int
        Points per decade (≥ 1).

    Returns
    -------
    ndarray, shape (n_scales,)
        Increasing scales, with exactly 1.0 at the nominal point. [-]

    Raises
    ------
    ValueError
        Ends not positive, not bracketing 1, or not on the grid.
    """
    if int(per_decade) != per_decade or per_decade < 1:
        raise ValueError(f"per_decade must be a positive integer, got {per_decade!r}")
    if not (start > 0 and stop > 0):
        raise ValueError(f"scales must be positive, got from = {start!r}, to = {stop!r}")
    if not start <= 1.0 <= stop or start == stop:
        raise ValueError(f"the grid must bracket the nominal x1 (from = {start:g}, to = {stop:g})")
    ka = np.log10(start) * per_decade
    kb = np.log10(stop) * per_decade
    for k, v in ((ka, start), (kb, stop)):
        if abs(k - round(k)) > 1e-9:
            raise ValueError(f"{v:g} is not on a grid of {per_decade} points per decade "
                             f"(10^(k/{per_decade}) for integer k)")
    k = np.arange(round(ka), round(kb) + 1)
    s = 10.0 ** (k / per_decade)
    s[k == 0] = 1.0
    return s


@dataclass(frozen=True)
class SweepCases:
    """The cases of a one-at-a-time sweep (nominal case shared).

    Attributes
    ----------
    parameters : tuple of str
        Swept parameters, subset of ``("P0", "Q", "R")``.
    scales : ndarray, shape (n_scales,)
    p0, q, r : ndarray, shape (B,)
        Scale of P_f(0), Q_f and R_f in each batched case. [-]
    index : ndarray of int, shape (n_parameters, n_scales)
        Batched case of (parameter, scale); every parameter's ×1 points to
        the one nominal case.
    """

    parameters: tuple
    scales: np.ndarray
    p0: np.ndarray
    q: np.ndarray
    r: np.ndarray
    index: np.ndarray

    @property
    def n_cases(self) -> int:
        return self.p0.size

    def labels(self) -> list[str]:
        """``"nominal"`` or ``"P0 x0.01"``, ``"Q x100"``, … per batched case."""
        out = []
        for a in zip(self.p0, self.q, self.r):
            scaled = [f"{p} x{s:g}" for p, s in zip(PARAMETERS, a) if s != 1.0]
            out.append(", ".join(scaled) or "nominal")
        return out


def sweep_cases(parameters, scales) -> SweepCases:
    """One-at-a-time cases: each parameter swept, the others at ×1.

    The nominal case (all ×1) is batched once: ``B = 1 + n_par·(n_scales − 1)``
    when the grid contains 1.
    """
    parameters = tuple(parameters)
    for p in parameters:
        if p not in PARAMETERS:
            raise ValueError(f"unknown sweep parameter {p!r} (one of: {', '.join(PARAMETERS)})")
    scales = np.asarray(scales, float)
    rows = [(1.0, 1.0, 1.0)]
    index = np.empty((len(parameters), scales.size), int)
    for i, p in enumerate(parameters):
        for j, s in enumerate(scales):
            if s == 1.0:
                index[i, j] = 0
                continue
            rows.append((s if p == "P0" else 1.0, s if p == "Q" else 1.0, s if p == "R" else 1.0))
            index[i, j] = len(rows) - 1
    a = np.array(rows)
    return SweepCases(parameters, scales, a[:, 0], a[:, 1], a[:, 2], index)


def run_sweep(truth: System, P0: np.ndarray, H: np.ndarray, R: np.ndarray, D: np.ndarray,
              filt: System, Pf0: np.ndarray, Hf: np.ndarray, Rf: np.ndarray, cases: SweepCases,
              update_steps, record_steps, *, form: str = "joseph", keep=slice(0, 10), on_invalid: str = "flag",
              label: str = "sweep", names=None, filter_names=None, times=None):
    """Truth covariance under one filter for every case, batched.

    Parameters
    ----------
    truth, filt : System
        Composed truth and (unscaled) filter systems on the same event grid.
    P0 : ndarray, shape (n, n)
        Truth initial covariance (never scaled).
    H, R : ndarray, shape (m, n), (m, m)
        Truth measurement matrix and true measurement noise (never scaled).
    D : ndarray, shape (n, n_f)
    Pf0, Hf, Rf : ndarray, shape (n_f, n_f), (m, n_f), (m, m)
        The filter's nominal P_f(0), measurement matrix and assumed R_f.
    cases : SweepCases
    update_steps, record_steps : iterable of int
    form : {"joseph", "standard"}
    keep : slice or index array
        Recorded sub-block (default: the 10 navigation states).
    on_invalid : {"flag", "raise"}
        A case whose covariance fails the guard is flagged (its records NaN,
        ``status`` says why) and the sweep goes on (default), or raises
        :class:`covtool.errors.NumericalError` (:func:`covtool.lincov.batch.run_batch`).
    label : str
        Names the sweep in messages; ``names``, ``filter_names`` and
        ``times`` (grid times [s]) name the states and the time.

    Returns
    -------
    covtool.lincov.batch.BatchResult
        ``P_truth`` has shape (B, n_rec, k, k) with B = ``cases.n_cases``;
        ``status`` names the flagged cases.

    Notes
    -----
    Scaling Q_f by c scales every composed interval noise by c (it is linear
    in Q_f), so the engine's ``q_scale`` is exact.
    """
    Pf0s = cases.p0[:, None, None] * np.asarray(Pf0, float)[None]
    Rfs = cases.r[:, None, None] * np.asarray(Rf, float)[None]
    return run_batch(truth, P0, H, R, D, update_steps, record_steps, filt=filt, Pf0=Pf0s, Hf=Hf, Rf=Rfs,
                     q_scale=cases.q, form=form, keep=keep, on_invalid=on_invalid, label=label,
                     cases=cases.labels(), names=names, filter_names=filter_names, times=times)


@dataclass(frozen=True)
class LogLogFit:
    """Least-squares fit ``log10 e = Σ_k c_k (log10 s)^k``.

    Attributes
    ----------
    coef : ndarray, shape (degree+1,)
        ``c_0 … c_degree`` (ascending powers of ``x = log10 s``).
    resid_rms : float
        RMS residual in ``log10 e`` [dex]; ×ln(10)·100 ≈ percent.
    r2 : float
        Coefficient of determination in ``log10 e`` (NaN if the data are flat).
    max_abs_resid : float
        Largest residual [dex].
    """

    coef: np.ndarray
    resid_rms: float
    r2: float
    max_abs_resid: float

    @property
    def degree(self) -> int:
        return self.coef.size - 1

    def __call__(self, scale) -> np.ndarray:
        """Fitted error at ``scale`` (same unit as the fitted data)."""
        return 10.0 ** npoly.polyval(np.log10(np.asarray(scale, float)), self.coef)

    def log_slope(self, scale) -> np.ndarray:
        """``d log e / d log s`` of the fit at ``scale``. [-]"""
        return npoly.polyval(np.log10(np.asarray(scale, float)), npoly.polyder(self.coef))


def fit_loglog(scale, err, degree: int = 3) -> LogLogFit:
    """Fit a swept error curve by a polynomial in log-log space.

    Parameters
    ----------
    scale : array_like, shape (k,)
        Scale factors (> 0). [-]
    err : array_like, shape (k,)
        Errors (> 0), any unit.
    degree : int
        Polynomial degree in ``x = log10 scale``; needs ``k ≥ degree + 1``.

    Returns
    -------
    LogLogFit

    Notes
    -----
    Errors of a mistuned filter change by orders of magnitude less than the
    scale does and saturate at both ends, so ``log10 e`` against
    ``log10 s`` is smooth and well conditioned on ``x ∈ [−2, 2]``; an
    ordinary (unweighted) least-squares polynomial is fitted there.
    """
    x = np.log10(np.asarray(scale, float))
    e = np.asarray(err, float)
    if x.shape != e.shape or x.ndim != 1:
        raise ValueError("scale and err must be 1-D arrays of the same length")
    if np.any(~np.isfinite(x)) or np.any(e <= 0) or np.any(~np.isfinite(e)):
        raise ValueError("scale and err must be finite and positive")
    if int(degree) != degree or degree < 0:
        raise ValueError(f"degree must be a non-negative integer, got {degree!r}")
    if x.size < degree + 1:
        raise ValueError(f"{x.size} points cannot determine a degree-{degree} fit")
    y = np.log10(e)
    coef = npoly.polyfit(x, y, int(degree))
    res = y - npoly.polyval(x, coef)
    ss_res = float(res @ res)
    ss_tot = float(((y - y.mean()) ** 2).sum())
    r2 = 1.0 - ss_res / ss_tot if ss_tot > 1e-24 * max(1.0, float(y @ y)) else float("nan")
    return LogLogFit(coef, float(np.sqrt(ss_res / y.size)), r2, float(np.max(np.abs(res))))


def sensitivity_figures(scales, err) -> dict:
    """Scalar sensitivity figures of one swept curve.

    Parameters
    ----------
    scales : array_like, shape (k,)
        Increasing scales containing 1. [-]
    err : array_like, shape (k,)
        Error at each scale (> 0).

    Returns
    -------
    dict
        ``nominal`` (e(1)), ``low`` and ``high`` (e at the grid ends),
        ``rel_low`` = e(s_min)/e(1), ``rel_high`` = e(s_max)/e(1),
        ``primary`` = max(rel_low, rel_high) − 1 (the module's primary
        definition), ``mean_log_slope`` = mean |Δlog e/Δlog s| over the grid.
    """
    s = np.asarray(scales, float)
    e = np.asarray(err, float)
    i1 = np.flatnonzero(s == 1.0)
    if i1.size != 1:
        raise ValueError("the scale grid must contain the nominal 1 exactly once")
    e1 = e[i1[0]]
    lo, hi = e[0] / e1, e[-1] / e1
    slope = np.abs(np.diff(np.log10(e)) / np.diff(np.log10(s)))
    return {"nominal": float(e1), "low": float(e[0]), "high": float(e[-1]), "rel_low": float(lo),
            "rel_high": float(hi), "primary": float(max(lo, hi) - 1.0),
            "mean_log_slope": float(np.mean(slope)) if slope.size else 0.0}


__all__ = ["PARAMETERS", "scale_grid", "SweepCases", "sweep_cases", "run_sweep", "LogLogFit", "fit_loglog",
           "sensitivity_figures"]
