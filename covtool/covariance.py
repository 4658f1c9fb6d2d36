"""Covariance propagation: pure INS and the truth under a filter's gains.

Pure numeric core: arrays in, arrays out (seed 002, eq (6)–(8), (15)–(16)).

Time grid: ``t_0 … t_N``; ``Φ_k, Q_k`` propagate ``t_k → t_{k+1}``.  A
measurement flagged at ``t_k`` is processed at ``t_k`` before propagating on.
Histories store the *posterior* covariance at each grid time (and the prior at
update times separately, for the saw-tooth plots).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import NumericalError


def _sym(P):
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def check_covariance(P: np.ndarray, what: str, tol: float = 1e-9) -> None:
    """Raise :class:`NumericalError` if ``P`` is not symmetric PSD.

    Parameters
    ----------
    P : ndarray, shape (n, n)
    what : str
        Names the step, e.g. ``"filter B1: Joseph update at t = 300.0 s"``.
    tol : float
        Relative tolerance on asymmetry and on negative eigenvalues (relative
        to the largest diagonal element after scaling by the diagonal).
    """
    if not np.all(np.isfinite(P)):
        raise NumericalError(f"{what}: covariance has non-finite entries")
    d = np.sqrt(np.clip(np.diag(P), 0.0, None))
    s = np.where(d > 0, d, 1.0)
    R = P / s[:, None] / s[None, :]
    asym = np.max(np.abs(R - R.T)) if R.size else 0.0
    if asym > tol:
        raise NumericalError(f"{what}: covariance lost symmetry (max relative asymmetry {asym:.3g})")
    if np.any(np.diag(P) < -tol * max(1.0, np.max(np.abs(np.diag(P))))):
        raise NumericalError(f"{what}: covariance has a negative variance")
    w = np.linalg.eigvalsh(_sym(R))
    if w.size and w.min() < -max(tol, 1e-9) * max(1.0, w.max()):
        raise NumericalError(f"{what}: covariance lost positive semi-definiteness "
                             f"(min eigenvalue of the correlation matrix {w.min():.3g})")


def propagate(Phi: np.ndarray, Qd: np.ndarray, P0: np.ndarray) -> np.ndarray:
    """Pure propagation ``P_{k+1} = Φ_k P_k Φ_kᵀ + Q_k`` (seed 002, eq (15)).

    Parameters
    ----------
    Phi, Qd : ndarray, shape (N, n, n)
    P0 : ndarray, shape (n, n)

    Returns
    -------
    ndarray, shape (N+1, n, n)
    """
    N, n, _ = Phi.shape
    out = np.empty((N + 1, n, n))
    P = out[0] = _sym(np.asarray(P0, float))
    for k in range(N):
        P = Phi[k] @ P @ Phi[k].T + Qd[k]
        out[k + 1] = P = _sym(P)
    return out


@dataclass
class FilterRun:
    """Histories of a truth-under-filter covariance run.

    Attributes
    ----------
    P_truth : ndarray, shape (N+1, n, n)
        Truth covariance (posterior at update times), eq (15)–(16).
    P_filter : ndarray, shape (N+1, n_f, n_f)
        The filter's own covariance, eq (6a)–(8).
    prior_truth, prior_filter : dict of int to ndarray
        Priors at the update steps.
    gains : dict of int to ndarray, shape (n_f, m)
        Filter gains at the update steps, eq (7).
    """

    P_truth: np.ndarray
    P_filter: np.ndarray
    prior_truth: dict
    prior_filter: dict
    gains: dict


def kalman_gain(Pf: np.ndarray, Hf: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Kalman gain ``K = P Hᵀ (H P Hᵀ + R)⁻¹`` (seed 002, eq (7))."""
    S = Hf @ Pf @ Hf.T + R
    return np.linalg.solve(S, Hf @ Pf).T


def filter_update(Pf, K, Hf, R, form: str = "joseph"):
    """Filter covariance update: Joseph form or seed 002 eq (8)."""
    if form == "joseph":
        A = np.eye(Pf.shape[0]) - K @ Hf
        return _sym(A @ Pf @ A.T + K @ R @ K.T)
    if form == "standard":
        return _sym(Pf - K @ Hf @ Pf)
    raise ValueError(f"unknown update form {form!r} (joseph, standard)")


def truth_update(P, D, K, H, R):
    """Truth covariance at a measurement under the filter's gain (seed 002, eq (16)).

    ``P⁺ = (I − D K H) P (I − D K H)ᵀ + D K R Kᵀ Dᵀ``, with ``K`` the filter's
    gain, ``H`` the truth measurement matrix and ``D`` (n × n_f) the map from
    filter states onto truth states.  It holds for any gain: the correction
    ``x ← x − D K z`` of eq (10) with ``z = H x + v``.
    """
    DK = D @ K
    A = np.eye(P.shape[0]) - DK @ H
    return _sym(A @ P @ A.T + DK @ R @ DK.T)


def propagate_with_filter(Phi, Qd, P0, Phi_f, Qd_f, Pf0, H, Hf, D, R, update_steps,
                          *, Rf=None, form: str = "joseph", check: bool = True, label: str = "filter",
                          times=None) -> FilterRun:
    """Truth covariance under a (reduced) filter's gains with feedback.

    Parameters
    ----------
    Phi, Qd : ndarray, shape (N, n, n)
        Truth transition and noise (eq (15)).
    P0 : ndarray, shape (n, n)
    Phi_f, Qd_f : ndarray, shape (N, n_f, n_f)
        The filter's own model (eq (6a)–(6d)).
    Pf0 : ndarray, shape (n_f, n_f)
    H : ndarray, shape (m, n)
        Truth measurement matrix (velocity-error rows for ZUPT).
    Hf : ndarray, shape (m, n_f)
        The filter's measurement matrix.
    D : ndarray, shape (n, n_f)
        Map of filter states onto truth states (eq (10)).
    R : ndarray, shape (m, m)
        True measurement noise (enters eq (16)).
    update_steps : iterable of int
        Grid indices k at which a measurement is processed.
    Rf : ndarray, shape (m, m), optional
        Measurement noise the filter assumes (eq (7)); default ``R``.
    form : {"joseph", "standard"}
        Filter covariance update form (eq (8) is ``"standard"``).
    check : bool
        Check symmetry and PSD of both covariances after every update.
    label : str
        Names the filter in error messages.
    times : ndarray, shape (N+1,), optional
        Grid times, for error messages.

    Returns
    -------
    FilterRun

    Notes
    -----
    Between measurements the feedback filter's estimate is zero (eq (9)–(10)),
    so only covariances are propagated.  At a measurement the filter computes
    ``K`` from its own ``P_f`` (eq (7)), updates ``P_f`` (eq (8) or Joseph), and
    the truth is corrected by eq (16): only the truth states the filter
    estimates (rows of ``D``) are reset; unmodelled states keep running.
    """
    N, n, _ = Phi.shape
    nf = Phi_f.shape[1]
    upd = set(int(k) for k in update_steps)
    PT = np.empty((N + 1, n, n))
    PF = np.empty((N + 1, nf, nf))
    prior_t, prior_f, gains = {}, {}, {}
    Rf = R if Rf is None else Rf
    P = _sym(np.asarray(P0, float))
    Pf = _sym(np.asarray(Pf0, float))
    for k in range(N + 1):
        if k in upd:
            prior_t[k], prior_f[k] = P, Pf
            K = kalman_gain(Pf, Hf, Rf)
            gains[k] = K
            Pf = filter_update(Pf, K, Hf, Rf, form)
            P = truth_update(P, D, K, H, R)
            if check:
                t = f"t = {times[k]:.1f} s" if times is not None else f"step {k}"
                check_covariance(Pf, f"{label}: filter covariance after the {form} update at {t}")
                check_covariance(P, f"{label}: truth covariance after the eq (16) update at {t}")
        PT[k], PF[k] = P, Pf
        if k < N:
            P = _sym(Phi[k] @ P @ Phi[k].T + Qd[k])
            Pf = _sym(Phi_f[k] @ Pf @ Phi_f[k].T + Qd_f[k])
    return FilterRun(PT, PF, prior_t, prior_f, gains)
