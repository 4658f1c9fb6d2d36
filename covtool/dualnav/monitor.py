"""Monitoring the difference: Kalman whitening, the χ² window test, GLR estimation.

:func:`innovations` whitens the difference with the Kalman filter of the
difference model (:class:`Whitener`, the kernel of :mod:`covtool.lincov.kalman`);
:func:`window_test` flags the windows whose normalised innovations leave the
predicted χ² envelope; :func:`gsens_estimates` detects a g-sensitive gyro
scale-factor error of the KIMU and estimates its coefficient by generalised
least squares on the fault signatures (Willsky & Jones 1976).

References
----------
A. S. Willsky and H. L. Jones, "A generalized likelihood ratio approach to
the detection and estimation of jumps in linear systems", IEEE Trans.
Automatic Control 21(1), 1976.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import weakref

import numpy as np
# the χ² inverse survival function itself (what scipy.stats.chi2.isf calls), without importing scipy.stats
from scipy.special import chdtri

from covtool.dualnav.difference import DifferenceModel
from covtool.errors import NumericalError
from covtool.lincov.kalman import (check_covariance, check_finite, filter_update, innovation_covariance,
                                   kalman_gain, predict, time_text)

__all__ = [
    "AXES", "Innovations", "Whitener", "innovations", "window_test", "flagged_intervals",
    "GsensEstimate", "gsens_estimates", "candidate_label",
]


AXES = "xyz"


_EPS = np.zeros((3, 3, 3))
_EPS[0, 1, 2] = _EPS[1, 2, 0] = _EPS[2, 0, 1] = 1.0
_EPS[0, 2, 1] = _EPS[2, 1, 0] = _EPS[1, 0, 2] = -1.0


def candidate_label(pair) -> str:
    """``"z/x"``: g-sensitive scale factor of gyro z driven by f_x."""
    return f"{AXES[pair[0]]}/{AXES[pair[1]]}"


# --------------------------------------------------------------------------
# whitening, envelope test and g-sensitivity estimation
# --------------------------------------------------------------------------


@dataclass
class Innovations:
    """Innovations of the difference under the no-fault model.

    Attributes
    ----------
    nu : ndarray, shape (M, J+1, m)
        Innovations ``z_j − H_j x̂_j⁻``.
    S : ndarray, shape (J+1, m, m)
        Their predicted covariance ``H P⁻ Hᵀ + R``.
    nis : ndarray, shape (M, J+1)
        Normalised innovation squared ``νᵀ S⁻¹ ν`` (χ²(m) per epoch).
    rho : ndarray, shape (J+1, m, n_c)
        Fault signatures: the innovation mean per unit coefficient of each
        candidate.
    """

    nu: np.ndarray
    S: np.ndarray
    nis: np.ndarray
    rho: np.ndarray


class Whitener:
    """Kalman filter of a DifferenceModel, one epoch at a time.

    Parameters
    ----------
    model : DifferenceModel
        Treated as immutable: the covariance side of the filter is kept
        with it (see Notes).
    n_runs : int
        Runs M whitened at once (they share the gains).

    Notes
    -----
    :meth:`update` forms the innovation of epoch j and the fault
    signatures (Willsky & Jones 1976): a constant fault ``c`` adds
    ``ρ_j c`` to the innovations with ``ρ_j = H_j μ_j``,
    ``μ_{j+1} = Φ_j (I − K_j H_j) μ_j + Γ_j``, ``μ_0 = 0``.
    :meth:`take_navigation` hands the estimated navigation errors over for
    feedback (seed 002, eq (10): ``x ← x − x̂``) and zeroes them in the
    estimate; in the linear model this leaves the innovations unchanged, and
    it keeps the two solutions close to their linearisation so that the
    second-order terms (``½ φ×(φ×f)`` at 10–20 g) stay negligible.
    Gain and Joseph-form update by :func:`covtool.lincov.kalman.kalman_gain`
    and :func:`~covtool.lincov.kalman.filter_update`; the model (P0, Φ, Q_d,
    R) is checked on entry and the covariance after every update and
    prediction (:func:`~covtool.lincov.kalman.check_covariance`), naming the
    epoch time and the joint state.

    The covariance side (``P``, ``S``, ``K``, ``μ``, ``ρ`` and the
    second-order attitude terms) does not depend on the data.  The first
    Whitener of a model records it, epoch by epoch, and later Whiteners of
    the same model that take the same steps (update 0, predict 0, update 1,
    …) replay the record instead of recomputing it (issue 13: the batches of
    a study share one model); the numbers are the same, computed once.  A
    Whitener that departs from the recorded steps computes its own.

    Raises
    ------
    NumericalError
        A model matrix or a covariance is not finite, symmetric and PSD.
    """

    def __init__(self, model: DifferenceModel, n_runs: int):
        J1, m, nc = model.t.size, model.m, len(model.candidates)
        record = getattr(model, "_whitener_record", None)
        if record is None:
            what = "dual-IMU whitener"
            check_covariance(model.P0, f"{what}: P0", names=model.names)
            check_finite(model.Phi, f"{what}: Φ of the epoch interval", names=model.names, times=model.t)
            check_covariance(model.Qd, f"{what}: Q_d of the epoch interval", names=model.names,
                             times=model.t)
            check_covariance(model.R, f"{what}: comparison noise R")
            record = _CovarianceRecord(owner=weakref.ref(self))
            model._whitener_record = record      # not a dataclass field: dataclasses.replace drops it
        self._record = record
        self._step = 0                            # steps taken (updates and predictions)
        self._replay = True                       # still on the recorded path
        self.model = model
        self.P = model.P0.copy()
        self.x = np.zeros((int(n_runs), model.n))
        self.mu = np.zeros((model.n, nc))
        self.nu = np.empty((int(n_runs), J1, m))
        self.S = np.empty((J1, m, m))
        self.nis = np.empty((int(n_runs), J1))
        self.rho = np.empty((J1, m, nc))

    def _recorded(self, kind: str, j: int):
        """The recorded outcome of this step, or None (then compute it)."""
        rec = self._record
        if self._replay and self._step < len(rec.steps):
            if rec.steps[self._step][:2] == (kind, j):
                return rec.steps[self._step][2]
            self._replay = False              # departs from the record: computes its own from here
        return None

    def _keep(self, kind: str, j: int, outcome) -> None:
        rec = self._record
        if self._replay and rec.owner() is self and self._step == len(rec.steps):
            rec.steps.append((kind, j, outcome))
        else:
            self._replay = False

    def update(self, j: int, z) -> np.ndarray:
        """Process epoch ``j``'s compared difference (M, m); return ν."""
        model = self.model
        H = model.H[j]
        att = [i for i, c in enumerate(model.components) if c >= 6]
        second = bool(att) and model.Hphi is not None
        outcome = self._recorded("update", j)
        if outcome is None:
            P = self.P
            R = model.R.copy()
            eps_pab = None
            if second:
                # z_att = φ_m − φ_k + ½ φ_m × φ_k: Gaussian second-order mean and covariance
                ax = [model.components[i] - 6 for i in att]
                Hm, Hk = model.Hphi[j, 0], model.Hphi[j, 1]
                Pa, Pb, Pab = Hm @ P @ Hm.T, Hk @ P @ Hk.T, Hm @ P @ Hk.T
                eps_pab = np.einsum("ijk,jk->i", _EPS, Pab)
                cov = 0.25 * (np.einsum("ijk,lmn,jm,kn->il", _EPS, _EPS, Pa, Pb)
                              + np.einsum("ijk,lmn,jn,mk->il", _EPS, _EPS, Pab, Pab))
                R[np.ix_(att, att)] += cov[np.ix_(ax, ax)]
            S = innovation_covariance(P, H, R)
            K = kalman_gain(P, H, R, S=S)
            P_new = filter_update(P, K, H, R, "joseph")
            check_covariance(P_new, f"dual-IMU whitener: after the update at "
                             f"{time_text(float(model.t[j]))}", names=model.names)
            rho = H @ self.mu
            mu_new = self.mu - K @ (H @ self.mu)                # (I − K H) μ
            outcome = (S, K, eps_pab, P_new, mu_new, rho)
            self._keep("update", j, outcome)
        S, K, eps_pab, P_new, mu_new, rho = outcome
        self._step += 1
        zhat = self.x @ H.T
        if second:
            ax = [model.components[i] - 6 for i in att]
            a, b = self.x @ model.Hphi[j, 0].T, self.x @ model.Hphi[j, 1].T
            mean = 0.5 * (np.cross(a, b) + eps_pab)
            zhat[:, att] += mean[:, ax]
        v = np.asarray(z, float) - zhat
        self.nu[:, j] = v
        self.S[j] = S
        self.nis[:, j] = np.einsum("mi,mi->m", v, np.linalg.solve(S, v.T).T)
        self.rho[j] = rho
        self.x = self.x + v @ K.T
        self.P = P_new
        self.mu = mu_new
        return v

    def take_navigation(self):
        """Hand over the navigation-error estimates (M, 10) each."""
        nm = self.model.n_main
        dm = self.x[:, :10].copy()
        dk = self.x[:, nm:nm + 10].copy()
        self.x[:, :10] = 0.0
        self.x[:, nm:nm + 10] = 0.0
        return dm, dk

    def predict(self, j: int) -> None:
        """Propagate from epoch ``j`` to ``j + 1``."""
        model = self.model
        Phi = model.Phi[j]
        outcome = self._recorded("predict", j)
        if outcome is None:
            P_new = predict(Phi, self.P, model.Qd[j])
            check_covariance(P_new, f"dual-IMU whitener: after the prediction at "
                             f"{time_text(float(model.t[j + 1]))}", names=model.names)
            outcome = (P_new, Phi @ self.mu + model.Gamma[j])
            self._keep("predict", j, outcome)
        self._step += 1
        self.x = self.x @ Phi.T
        self.P, self.mu = outcome

    def result(self) -> "Innovations":
        """The innovations processed so far."""
        return Innovations(self.nu, self.S, self.nis, self.rho)


@dataclass
class _CovarianceRecord:
    """The data-independent steps of the first :class:`Whitener` of a model."""

    owner: weakref.ref                             # the Whitener that records
    steps: list = field(default_factory=list)     # (kind, epoch, outcome) in the order taken


def innovations(model: DifferenceModel, z) -> Innovations:
    """Whiten open-loop differences with the model's Kalman filter.

    Parameters
    ----------
    model : DifferenceModel
    z : array_like, shape (M, J+1, m) or (J+1, m)
        Compared components of the difference at the epochs.

    Returns
    -------
    Innovations
        Under the model ``ν_j ~ N(0, S_j)``, independent over j.

    Raises
    ------
    ValueError
        ``z`` does not have one row per epoch and one column per compared
        component.
    """
    z = np.asarray(z, float)
    if z.ndim == 2:
        z = z[None]
    M, J1, m = z.shape
    if J1 != model.t.size or m != model.m:
        raise ValueError(f"z must have shape (M, {model.t.size}, {model.m}), got {z.shape}")
    w = Whitener(model, M)
    for j in range(J1):
        w.update(j, z[:, j])
        if j < J1 - 1:
            w.predict(j)
    return w.result()


def window_test(nis, dof: int, window: int, false_alarm: float):
    """Sliding-window χ² test of the normalised innovations.

    Parameters
    ----------
    nis : ndarray, shape (M, J+1)
        Normalised innovations squared, χ²(dof) each under the model.
    dof : int
        Degrees of freedom per epoch (compared components m).
    window : int
        Epochs per window.
    false_alarm : float
        Design probability of one or more alarms in a fault-free flight.

    Returns
    -------
    stat : ndarray, shape (M, N_w)
        Window sums ``Σ νᵀS⁻¹ν`` (χ²(dof·window) each under the model).
    threshold : float
        ``χ²⁻¹(1 − α/N_w; dof·window)``: Bonferroni over the N_w windows,
        so that P(any alarm | no fault) ≤ α.
    flagged : ndarray of bool, shape (M, N_w)

    Raises
    ------
    ValueError
        The window is longer than the record or α is not in (0, 1).
    """
    nis = np.atleast_2d(np.asarray(nis, float))
    J1 = nis.shape[1]
    window = int(window)
    if not 1 <= window <= J1:
        raise ValueError(f"window of {window} epochs does not fit {J1} epochs")
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f"false-alarm probability must be in (0, 1), got {false_alarm!r}")
    if not np.isfinite(nis).all():
        m, j = np.argwhere(~np.isfinite(nis))[0]
        raise NumericalError(f"window test: the normalised innovation of run {m} at epoch {j} is not finite (the "
                             "navigation or the filter diverged); no alarm decision can be reported")
    c = np.concatenate([np.zeros((nis.shape[0], 1)), np.cumsum(nis, axis=1)], axis=1)
    stat = c[:, window:] - c[:, :-window]
    Nw = stat.shape[1]
    thr = float(chdtri(dof * window, false_alarm / Nw))
    return stat, thr, stat > thr


def flagged_intervals(flagged, t_epochs, window: int):
    """Merge flagged windows into time intervals.

    Parameters
    ----------
    flagged : ndarray of bool, shape (N_w,)
        Window w covers epochs ``w … w + window − 1``.
    t_epochs : ndarray, shape (J+1,)
    window : int

    Returns
    -------
    list of (float, float)
        ``(start, end)`` times of the merged flagged spans. [s]
    """
    out = []
    for w in np.flatnonzero(flagged):
        a, b = float(t_epochs[w]), float(t_epochs[w + window - 1])
        if out and a <= out[-1][1] + 1e-9:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


@dataclass
class GsensEstimate:
    """GLS estimates of the g-sensitive scale-factor candidates.

    Attributes
    ----------
    candidates : tuple of (int, int)
    estimate : ndarray, shape (M, n_c)
        Single-fault estimates ``ĉ = bᵀ/A_cc``. [1/(m/s²)]
    sigma : ndarray, shape (n_c,)
        Their 1σ from the predicted covariance, ``A_cc^{-1/2}``.
    glr : ndarray, shape (M, n_c)
        Generalised likelihood ratios ``b_c²/A_cc`` (χ²(1) with no fault).
    threshold : float
        ``χ²⁻¹(1 − α/n_c; 1)``.
    detected : ndarray of bool, shape (M,)
        Largest GLR above the threshold.
    identified : ndarray of int, shape (M,)
        Candidate with the largest GLR.
    information : ndarray, shape (n_c, n_c)
        ``A = Σ ρᵀ S⁻¹ ρ`` (joint Fisher information).
    """

    candidates: tuple
    estimate: np.ndarray
    sigma: np.ndarray
    glr: np.ndarray
    threshold: float
    detected: np.ndarray
    identified: np.ndarray
    information: np.ndarray


def gsens_estimates(inn: Innovations, candidates, false_alarm: float, *, strict: bool = True) -> GsensEstimate:
    """Detect and estimate a g-sensitive scale factor (GLR/GLS).

    Parameters
    ----------
    inn : Innovations
    candidates : sequence of (int, int)
    false_alarm : float
        Design probability of a detection in a fault-free flight
        (Bonferroni over the candidates).
    strict : bool
        Raise if a candidate has no signature; otherwise its estimate is
        NaN, its σ infinite and its GLR 0.

    Returns
    -------
    GsensEstimate

    Notes
    -----
    With ``ν_j = ν_j⁰ + ρ_j c`` and ``ν_j⁰ ~ N(0, S_j)`` white, the GLS
    estimate of a single candidate is ``ĉ = Σ ρᵀS⁻¹ν / Σ ρᵀS⁻¹ρ`` with
    variance ``1/Σ ρᵀS⁻¹ρ``; the GLR ``(Σ ρᵀS⁻¹ν)²/Σ ρᵀS⁻¹ρ`` is χ²(1)
    without a fault.  The nuisance errors (biases, scale factors, mass
    unbalance …) are estimated along by the filter, so their correlation
    with the fault is accounted for.
    """
    cands = tuple(candidates)
    nc = len(cands)
    if nc == 0:
        raise ValueError("no g-sensitivity candidates")
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f"false-alarm probability must be in (0, 1), got {false_alarm!r}")
    Sinv_rho = np.linalg.solve(inn.S, inn.rho)                         # (J, m, nc)
    A = np.einsum("jmc,jmd->cd", inn.rho, Sinv_rho)
    b = np.einsum("Mjm,jmc->Mc", inn.nu, Sinv_rho)
    diag = np.diag(A).copy()
    dead = diag <= 0
    if strict and dead.any():
        bad = [candidate_label(cands[i]) for i in np.flatnonzero(dead)]
        raise ValueError(f"g-sensitivity candidates {', '.join(bad)} have no signature in this flight "
                         "(the product ω_i f_j is zero throughout)")
    safe = np.where(dead, 1.0, diag)
    est = np.where(dead, np.nan, b / safe)
    sigma = np.where(dead, np.inf, 1.0 / np.sqrt(safe))
    glr = np.where(dead, 0.0, b**2 / safe)
    if not np.isfinite(glr).all():
        m = int(np.argwhere(~np.isfinite(glr))[0, 0])
        raise NumericalError(f"g-sensitivity test: the GLR statistic of run {m} is not finite (the navigation or "
                             "the filter diverged); no detection can be reported")
    thr = float(chdtri(1, false_alarm / nc))
    best = np.argmax(glr, axis=1)
    detected = glr[np.arange(glr.shape[0]), best] > thr
    return GsensEstimate(cands, est, sigma, glr, thr, detected, best, A)
