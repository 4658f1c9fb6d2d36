"""Consistency statistics: NEES and the χ² bounds of an ensemble against a covariance.

Bounds at confidence ``1 − α`` (:func:`rms_bounds`, :func:`nees_bounds`):

* RMS of a scalar zero-mean normal error over ``N`` runs:
  ``N·RMS²/σ² ~ χ²_N``, so ``σ √(χ²_{N,α/2}/N) … σ √(χ²_{N,1−α/2}/N)``;
* radial horizontal RMS: ``Σ(δN² + δE²) = Σ λ₁u₁² + λ₂u₂²`` with ``λ`` the
  eigenvalues of the 2×2 horizontal covariance.  It is replaced by the
  moment-matched ``σ_h² χ²_ν/ν`` with ``ν = N (λ₁+λ₂)²/(λ₁²+λ₂²)``
  (Satterthwaite): ``2N`` for a circular error, ``N`` for a degenerate one
  (:func:`horizontal_dof`).  Using 2N for an elongated error would make the
  bounds too narrow;
* mean NEES of dimension ``d`` over ``N`` runs: ``N ε̄ ~ χ²_{Nd}``
  (:class:`Nees`: the whitening of a covariance history at grid times).

References
----------
Y. Bar-Shalom, X. R. Li, T. Kirubarajan, *Estimation with Applications to
Tracking and Navigation*, Wiley 2001, §5.4 (NEES and its χ² bounds).
F. E. Satterthwaite, "An approximate distribution of estimates of variance
components", Biometrics Bulletin 2(6), 1946.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from covtool.lincov.kalman import symmetrize
from covtool.nav import attitude as quat

__all__ = [
    "REDUCED_NAV", "Nees", "rms_bounds", "horizontal_dof", "nees_bounds", "nees_whitening",
    "expected_nees", "reduction_matrix", "inside_fraction", "normalised_mean_square", "null_test",
]


#: the navigation part of a NEES vector: the quaternion error reduced to the attitude error φ
REDUCED_NAV = ("dL", "dl", "dh", "dvN", "dvE", "dvD", "phiN", "phiE", "phiD")


# --------------------------------------------------------------------------
# ensemble
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class Nees:
    """Whitening of a covariance history for NEES at grid times.

    The error vector is the reduced vector of ``labels``: navigation errors
    with the quaternion error replaced by ``φ`` (:data:`REDUCED_NAV`), then
    sensor states (actual error ``x − ĉ``; random constants only, whose
    truth is known in every run).

    Attributes
    ----------
    labels : tuple of str
    steps : ndarray of int, shape (J,)
        Grid indices at which NEES is evaluated.
    scale : ndarray, shape (J, d)
        ``√diag`` of the reduced covariance.
    W : ndarray, shape (J, d, d)
        Whitening of the scaled covariance: ``ε = ‖W (e/scale)‖²``; rows of
        zero eigenvalues are zero.
    dof : ndarray of int, shape (J,)
        Rank of the reduced covariance (the χ² dimension).
    """

    labels: tuple
    steps: np.ndarray
    scale: np.ndarray
    W: np.ndarray
    dof: np.ndarray


def reduction_matrix(names, labels, q) -> np.ndarray:
    """Map a state vector onto a reduced NEES vector.

    Parameters
    ----------
    names : sequence of str
        State names of the covariance (filter or truth order).
    labels : sequence of str
        Reduced labels: :data:`REDUCED_NAV` members and state names.
    q : ndarray, shape (4,)
        True attitude (for ``φ = −2R(q)ᵀδq``).

    Returns
    -------
    ndarray, shape (len(labels), len(names))
    """
    names = list(names)
    T = np.zeros((len(labels), len(names)))
    A = quat.attitude_error_matrix(np.asarray(q, float))
    qi = [names.index(n) for n in ("dq0", "dq1", "dq2", "dq3")]
    for r, lab in enumerate(labels):
        if lab in ("phiN", "phiE", "phiD"):
            T[r, qi] = A["NED".index(lab[-1])]
        else:
            T[r, names.index(lab)] = 1.0
    return T


def nees_whitening(P, names, labels, steps, q, *, rtol: float = 1e-10) -> Nees:
    """Whitening matrices of a covariance history for NEES.

    Parameters
    ----------
    P : ndarray, shape (N+1, n, n), or :class:`covtool.lincov.history.AtSteps`
        Covariance history (filter or truth), read at ``steps`` only (``P[k]``).
    names : sequence of str
        Its state names.
    labels : sequence of str
        The NEES vector (:func:`reduction_matrix`).
    steps : array_like of int
        Grid indices at which NEES is wanted.
    q : ndarray, shape (N+1, 4)
        True attitude at the grid times.
    rtol : float
        Eigenvalues below ``rtol`` times the largest (of the correlation
        matrix) count as zero: that direction is dropped and the dof reduced.

    Returns
    -------
    Nees
    """
    steps = np.asarray(steps, int)
    d = len(labels)
    scale = np.zeros((steps.size, d))
    W = np.zeros((steps.size, d, d))
    dof = np.zeros(steps.size, int)
    for j, k in enumerate(steps):
        T = reduction_matrix(names, labels, q[k])
        Pr = symmetrize(T @ P[k] @ T.T)
        s = np.sqrt(np.clip(np.diag(Pr), 0.0, None))
        s = np.where(s > 0, s, 1.0)
        C = Pr / np.outer(s, s)
        w, V = np.linalg.eigh(C)
        keep = w > rtol * max(w.max(), 1e-300)
        Wk = (V[:, keep] / np.sqrt(w[keep])).T
        W[j, :Wk.shape[0]] = Wk
        scale[j] = s
        dof[j] = int(keep.sum())
    return Nees(tuple(labels), steps, scale, W, dof)


def expected_nees(spec: Nees, P, names, q):
    """Mean NEES the linear analysis predicts for true covariance P.

    Parameters
    ----------
    spec : Nees
        Whitening of the covariance being tested (e.g. the filter's claim).
    P : ndarray, shape (N+1, n, n), or :class:`covtool.lincov.history.AtSteps`
        Covariance of the actual errors of the same states (e.g. the truth
        covariance under the filter's gains restricted to the filter's
        states, ``Dᵀ P D``), read at ``spec.steps`` only.
    names : sequence of str
        State names of ``P``.
    q : ndarray, shape (N+1, 4)
        True attitude at the grid times.

    Returns
    -------
    mean : ndarray, shape (J,)
        ``E[ε] = tr B`` with ``B = W Σ Wᵀ`` and ``Σ`` the scaled reduced ``P``.
    dof : ndarray, shape (J,)
        ``(tr B)² / tr B²``: the per-run degrees of freedom of the scaled χ²
        with the same mean and variance as ``ε`` (Satterthwaite); equal to
        ``spec.dof`` when ``P`` is the covariance being tested.
    """
    mean = np.zeros(spec.steps.size)
    dof = np.zeros(spec.steps.size)
    for j, k in enumerate(spec.steps):
        T = reduction_matrix(names, spec.labels, q[k])
        Sig = symmetrize(T @ P[k] @ T.T) / np.outer(spec.scale[j], spec.scale[j])
        B = spec.W[j] @ Sig @ spec.W[j].T
        tr = np.trace(B)
        mean[j] = tr
        dof[j] = tr**2 / np.sum(B * B) if tr > 0 else 1.0
    return mean, dof


# --------------------------------------------------------------------------
# χ² bounds
# --------------------------------------------------------------------------


def rms_bounds(sigma, n_runs: int, dof_per_run=1.0, confidence: float = 0.95):
    """Two-sided χ² bounds of an ensemble RMS.

    Parameters
    ----------
    sigma : array_like
        Predicted σ (for the radial horizontal error, ``√(σ_N² + σ_E²)``).
    n_runs : int
        Number of runs N.
    dof_per_run : array_like
        Degrees of freedom per run (1 for a scalar; :func:`horizontal_dof`
        for the radial horizontal error).
    confidence : float

    Returns
    -------
    lo, hi : ndarray
        ``σ √(χ²_{ν,α/2}/ν)`` and ``σ √(χ²_{ν,1−α/2}/ν)`` with
        ``ν = N · dof_per_run``.
    """
    a = 1.0 - confidence
    nu = np.asarray(n_runs * np.asarray(dof_per_run, float))
    sigma = np.asarray(sigma, float)
    return (sigma * np.sqrt(chi2_quantile(0.5 * a, nu) / nu),
            sigma * np.sqrt(chi2_quantile(1.0 - 0.5 * a, nu) / nu))


def chi2_quantile(q, nu):
    """Quantile ``q`` of the χ² law with ``nu`` degrees of freedom.

    ``2 P⁻¹(ν/2, q)`` with the inverse regularised lower incomplete gamma
    function ``scipy.special.gammaincinv``: exactly what
    ``scipy.stats.chi2.ppf`` computes (bit for bit, for ``0 < q < 1`` and
    ``ν > 0``), without importing ``scipy.stats`` (0.4-0.6 s, on the
    serial path after a Monte Carlo ensemble).

    Parameters
    ----------
    q : array_like
        Probability, in (0, 1).
    nu : array_like
        Degrees of freedom, > 0.

    Returns
    -------
    ndarray
    """
    from scipy.special import gammaincinv

    return 2.0 * gammaincinv(0.5 * np.asarray(nu, float), q)


def horizontal_dof(P2) -> np.ndarray:
    """Satterthwaite degrees of freedom per run of ``δN² + δE²``.

    Parameters
    ----------
    P2 : ndarray, shape (..., 2, 2)
        Horizontal position covariance. [m²]

    Returns
    -------
    ndarray, shape (...)
        ``(λ₁+λ₂)²/(λ₁²+λ₂²)`` ∈ [1, 2]: 2 for a circular error, 1 for a
        degenerate one (1 where the covariance is zero).
    """
    w = np.clip(np.linalg.eigvalsh(symmetrize(np.asarray(P2, float))), 0.0, None)
    num = w.sum(axis=-1) ** 2
    den = (w * w).sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)


def nees_bounds(dof, n_runs: int, confidence: float = 0.95, mean=None):
    """χ² bounds of the mean NEES over N runs.

    Parameters
    ----------
    dof : array_like
        Degrees of freedom per run ``d`` (the NEES dimension when the tested
        covariance is the true one).
    n_runs : int
    confidence : float
    mean : array_like, optional
        Expected NEES when the tested covariance is not the true one
        (:func:`expected_nees`; ``dof`` is then its Satterthwaite dof).

    Returns
    -------
    lo, hi : ndarray
        ``m χ²_{Nd,α/2}/(Nd)`` and ``m χ²_{Nd,1−α/2}/(Nd)`` with ``m = d``
        unless given: for a consistent covariance ``N ε̄ ~ χ²_{Nd}``.
    """
    a = 1.0 - confidence
    d = np.asarray(dof, float)
    m = d if mean is None else np.asarray(mean, float)
    nd = d * n_runs
    return m * chi2_quantile(0.5 * a, nd) / nd, m * chi2_quantile(1.0 - 0.5 * a, nd) / nd


def inside_fraction(x, lo, hi, *, rtol: float = 1e-12) -> dict:
    """Fractions of points inside, above and below ``[lo, hi]``.

    Points where ``hi == 0`` (a zero predicted σ, e.g. the initial position)
    count as inside when ``x`` is zero to ``rtol`` of the largest ``x``.
    """
    x, lo, hi = (np.asarray(a, float) for a in (x, lo, hi))
    tol = rtol * max(float(np.max(np.abs(x))) if x.size else 0.0, 1e-300)
    above = x > hi + tol
    below = x < lo - tol
    n = max(x.size, 1)
    return {"inside": 1.0 - (above.sum() + below.sum()) / n, "above": above.sum() / n, "below": below.sum() / n,
            "points": int(x.size)}


# --------------------------------------------------------------------------
# the acceptance test of a Monte Carlo cell against its null distribution
# --------------------------------------------------------------------------


def normalised_mean_square(ms, sigma, points) -> np.ndarray:
    """Time mean of the normalised ensemble mean square.

    ``T = (1/K) Σ_t m(t)/σ²(t)`` over the ``K`` test points: 1 in
    expectation when ``σ²`` is the expectation of the mean square ``m``
    (docs/monte_carlo.md, "The acceptance test").

    Parameters
    ----------
    ms : ndarray, shape (..., N+1)
        Ensemble mean squares (``RMS²``).
    sigma : ndarray, shape (N+1,)
        Predicted σ.
    points : ndarray of bool or int, shape (N+1,) or (K,)
        The test points (zero-σ points must be excluded).

    Returns
    -------
    ndarray, shape (...)
    """
    s2 = np.asarray(sigma, float)[points] ** 2
    return np.mean(np.asarray(ms, float)[..., points] / s2, axis=-1)


def null_test(ms, ms_null, sigma, lo, hi, points, alpha: float) -> dict:
    """One Monte Carlo cell against the null distribution of its statistics.

    Parameters
    ----------
    ms : ndarray, shape (N+1,)
        Observed ensemble mean square of the cell (``RMS²``).
    ms_null : ndarray, shape (R, N+1)
        The same of ``R`` replicas of the linear Monte Carlo under the model
        (:func:`covtool.validation.linear_mc.linear_mean_squares`).
    sigma : ndarray, shape (N+1,)
        Predicted σ (its square is the expected mean square).
    lo, hi : ndarray, shape (N+1,)
        Per-point RMS bounds (:func:`rms_bounds`).
    points : ndarray of bool, shape (N+1,)
        Test points.
    alpha : float
        False-alarm rate of this cell's test (the study's family rate
        divided by the number of cells: Bonferroni).

    Returns
    -------
    dict
        ``inside``: observed share of points inside ``[lo, hi]``;
        ``inside_null_p5``: its null 5th percentile; ``inside_p``: one-sided
        p-value ``(1 + #{F_r ≤ F})/(R + 1)`` (too few points inside);
        ``T``: :func:`normalised_mean_square`; ``T_null_mean``,
        ``T_null_std``: its null mean and standard deviation over the
        replicas; ``z = (T − 1)/T_null_std``; ``p``: two-sided p-value of
        ``z`` (normal law: ``T`` is a mean over N independent runs);
        ``T_p_empirical``: two-sided rank p-value among the replicas;
        ``reject``: ``p < alpha``.

    Raises
    ------
    ValueError
        Fewer than 10 replicas (the null standard deviation would be
        meaningless).
    """
    from scipy.special import ndtr                  # ndtr(−|z|) is scipy.stats.norm.sf(|z|), bit for bit

    ms_null = np.asarray(ms_null, float)
    R = ms_null.shape[0]
    if R < 10:
        raise ValueError(f"null_test: {R} replicas of the linear Monte Carlo; at least 10 are needed")
    pts = np.asarray(points, bool)
    x, lo, hi = np.sqrt(np.asarray(ms, float)), np.asarray(lo, float), np.asarray(hi, float)
    F = inside_fraction(x[pts], lo[pts], hi[pts])["inside"]
    xr = np.sqrt(ms_null[:, pts])
    Fr = np.mean((xr >= lo[pts]) & (xr <= hi[pts]), axis=1)
    T = float(normalised_mean_square(ms, sigma, pts))
    Tr = normalised_mean_square(ms_null, sigma, pts)
    s = float(np.std(Tr, ddof=1))
    z = (T - 1.0) / s if s > 0 else (0.0 if T == 1.0 else np.inf)
    p = float(2.0 * ndtr(-abs(z)))
    lower = (1 + np.sum(Tr <= T)) / (R + 1)
    upper = (1 + np.sum(Tr >= T)) / (R + 1)
    return {"inside": float(F), "inside_null_p5": float(np.percentile(Fr, 5)),
            "inside_null_median": float(np.median(Fr)), "inside_p": float((1 + np.sum(Fr <= F)) / (R + 1)),
            "T": T, "T_null_mean": float(np.mean(Tr)), "T_null_std": s, "z": float(z), "p": p,
            "T_p_empirical": float(min(1.0, 2.0 * min(lower, upper))), "alpha": float(alpha),
            "reject": bool(p < alpha), "replicas": int(R)}
