"""Navigation-error metrics from covariances: CEP, probable error, attitude σ.

All inputs SI; outputs SI unless a name says otherwise.  A metric of a
covariance that is not finite, symmetric and PSD
(:func:`covtool.lincov.kalman.covariance_status`) is NaN, never 0.

Domain of the linear error model
--------------------------------
The error model (seed 002, eq (1)–(5)) keeps the first order of small-angle
expansions; :func:`validity` says where a covariance leaves that domain.
The criterion is the same for every error: the neglected second-order term
stays below 5 % of the first-order term for a 3σ error (99.7 % of the
errors of each axis), i.e. ``3σ·c ≤ 0.05`` with ``c`` the ratio of the two
terms per unit error.

* Position, horizontal and vertical, as an angle ``x = σ/R``: gravity
  ``μ/r²`` gives ``c = 3/2`` (``g(R+δh) = g(1 − 2x + 3x² …)``); the
  longitude rate ``v_E/(R cos L)`` gives ``c = tan L + 1/(2 tan L)``, 3/2 at
  45° latitude.  ``x ≤ 0.05/4.5 = 1.1 %``: :data:`POSITION_LIMIT` =
  :data:`ALTITUDE_LIMIT` = 1 % of the equatorial radius (63.8 km).  An
  unaided vertical channel diverges as ``cosh(√2 ω_s t)`` and is the usual
  way to get there.
* Attitude (tilts and azimuth): ``Ĉ = (I − [φ×]) C`` drops ``½[φ×]²``, so
  ``c = 1/2`` and ``σ ≤ 0.05/1.5 = 0.033 rad``: :data:`ATTITUDE_LIMIT`
  (1.9°).
"""

from __future__ import annotations

import numpy as np
from scipy.special import erf

from covtool.lincov.dynamics import attitude_errors
from covtool.lincov.kalman import covariance_status, running_scale, symmetrize
from covtool.nav import earth

#: probable-error factor: P(|x| < 0.6745 σ) = 0.5 for a normal variable
PE_FACTOR = 0.6744897501960817
_GL_X, _GL_W = np.polynomial.legendre.leggauss(96)

#: largest horizontal position 1σ (per axis) of the linear error model's domain (module notes) [m]
POSITION_LIMIT = 0.01 * earth.A
#: largest altitude 1σ of the linear error model's domain (module notes) [m]
ALTITUDE_LIMIT = 0.01 * earth.A
#: largest tilt or azimuth 1σ of the linear error model's domain (module notes) [rad]
ATTITUDE_LIMIT = 0.05 / 1.5


def _circle_probability(r, s1, s2):
    """P(|x| ≤ r) for x ~ N(0, diag(s1², s2²)), s1 ≥ s2 > 0 (vectorised).

    Integrated along the *minor* axis, x₂ = s2·U·sin θ with U = min(r/s2, 12):
    the integrand φ(U sin θ) U cos θ · erf(√(r² − x₂²)/(√2 s1)) is smooth for
    every eccentricity (no unresolved erf edge when s2 ≪ s1, and no square-root
    end point when U = r/s2).
    """
    th = 0.5 * np.pi * _GL_X                              # θ ∈ (−π/2, π/2)
    r = np.asarray(r)[..., None]
    s1 = np.asarray(s1)[..., None]
    s2 = np.asarray(s2)[..., None]
    U = np.minimum(r / s2, 12.0)
    u = U * np.sin(th)
    x2 = s2 * u
    weight = U * np.cos(th) * np.exp(-0.5 * u * u) / np.sqrt(2 * np.pi)
    inner = erf(np.sqrt(np.clip(r * r - x2 * x2, 0.0, None)) / (np.sqrt(2.0) * s1))
    return 0.5 * np.pi * np.sum(_GL_W * weight * inner, axis=-1)


def cep(P2: np.ndarray) -> np.ndarray:
    """Exact circular error probable of a 2-D normal error.

    Parameters
    ----------
    P2 : ndarray, shape (..., 2, 2)
        Horizontal position covariance. [m²]

    Returns
    -------
    ndarray, shape (...)
        Radius of the circle centred on the truth that contains the error
        with probability 0.5. [m]

    Notes
    -----
    With principal σ₁ ≥ σ₂, ``P(|x| ≤ r) = ∫ φ(x₂/σ₂)/σ₂ · erf(√(r² − x₂²)/(√2 σ₁)) dx₂``
    over the minor axis (see :func:`_circle_probability`), evaluated by
    96-point Gauss–Legendre and solved for 0.5 by safeguarded Newton
    iteration: bisection whenever a Newton step leaves the bracket or after
    12 steps; converged only on the residual |P − ½| < 1e-14 or a bracket
    narrower than 1e-13 r (a Newton step's size is no test: for σ₂ ≪ σ₁ the
    density around the circle is a spike that quadrature can overestimate).  Limits:
    ``√(2 ln 2) σ = 1.1774 σ`` (circular), ``0.6745 σ₁`` (σ₂ → 0).  The common
    rule ``0.589(σ₁+σ₂)`` is within 3 % only for σ₂/σ₁ > 0.3.  NaN where
    ``P2`` is not finite, symmetric and PSD (never 0).
    """
    P2, valid = _valid(P2)
    w = np.linalg.eigvalsh(symmetrize(P2))
    w = np.clip(w, 0.0, None)
    s1 = np.sqrt(w[..., 1])
    s2 = np.sqrt(w[..., 0])
    out = np.where(valid, 0.0, np.nan)
    pos = s1 > 0
    if not np.any(pos):
        return out
    a, b = s1[pos], s2[pos]
    b = np.maximum(b, a * 1e-9)
    lo = 0.9 * PE_FACTOR * a
    hi = 1.01 * np.sqrt(2 * np.log(2)) * np.hypot(a, b)
    r = np.clip(0.589 * (a + b), lo, hi)
    # a point stops as soon as it has converged: iterating it further lets the forced
    # bisection (after 12 steps) move it off its root, and costs every point ~40 steps
    act = np.arange(r.size)
    for it in range(200):
        ra, aa, ba, la, ha = r[act], a[act], b[act], lo[act], hi[act]
        f = _circle_probability(ra, aa, ba) - 0.5
        la = np.where(f < 0, ra, la)
        ha = np.where(f < 0, ha, ra)
        lo[act], hi[act] = la, ha
        conv = (np.abs(f) < 1e-14) | (ha - la <= 1e-13 * ha)
        if conv.all():
            break
        keep = ~conv
        act, ra, aa, ba, la, ha, f = act[keep], ra[keep], aa[keep], ba[keep], la[keep], ha[keep], f[keep]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            r_new = ra - f / _circle_density(ra, aa, ba)
        # Newton while it stays inside the bracket and early on; the circle density
        # is a narrow spike for very elongated ellipses, so fall back to bisection
        bad = ~((r_new > la) & (r_new < ha)) | (it >= 12)
        r[act] = np.where(bad, 0.5 * (la + ha), r_new)
    out[pos] = r
    return out


def _circle_density(r, s1, s2):
    """d/dr P(|x| ≤ r): the normal density integrated around the circle of radius r."""
    th = np.pi * (_GL_X + 1.0)                            # θ ∈ (0, 2π)
    r_ = np.asarray(r)[..., None]
    x1 = r_ * np.cos(th)
    x2 = r_ * np.sin(th)
    s1_ = np.asarray(s1)[..., None]
    s2_ = np.asarray(s2)[..., None]
    p = np.exp(-0.5 * ((x1 / s1_) ** 2 + (x2 / s2_) ** 2)) / (2 * np.pi * s1_ * s2_)
    return np.pi * r * np.sum(_GL_W * p, axis=-1)


def cep_approx(P2: np.ndarray) -> np.ndarray:
    """The ``0.589 (σ₁ + σ₂)`` CEP rule of thumb, for comparison. [m]

    NaN where ``P2`` is not finite, symmetric and PSD.
    """
    P2, valid = _valid(P2)
    w = np.clip(np.linalg.eigvalsh(symmetrize(P2)), 0.0, None)
    return np.where(valid, 0.589 * (np.sqrt(w[..., 0]) + np.sqrt(w[..., 1])), np.nan)


def _valid(P, groups=(), scale=None):
    """``(P with invalid matrices zeroed, valid mask)`` (:func:`covariance_status`)."""
    P = np.asarray(P, float)
    valid = covariance_status(P, groups=groups, scale=scale).ok
    if not valid.all():
        P = np.where(valid[..., None, None], P, 0.0)
    return P, valid


def ned_position_covariance(P_pos: np.ndarray, lat, h) -> np.ndarray:
    """Covariance of the NED position error in metres from (δL, δl, δh).

    ``δN = (R_M+h) δL``, ``δE = (R_N+h) cos L δl``, ``δD = −δh``.

    Parameters
    ----------
    P_pos : ndarray, shape (..., 3, 3)
    lat, h : array_like, shape (...)

    Returns
    -------
    ndarray, shape (..., 3, 3)  [m²]
    """
    rm, rn = earth.radii(lat)
    T = np.zeros(np.shape(lat) + (3, 3))
    T[..., 0, 0] = rm + h
    T[..., 1, 1] = (rn + h) * np.cos(lat)
    T[..., 2, 2] = -1.0
    return T @ P_pos @ np.swapaxes(T, -1, -2)


def nav_metrics(P: np.ndarray, lat, h, q, distance=None, *, scale=None) -> dict:
    """Standard navigation metrics from a covariance history.

    Parameters
    ----------
    P : ndarray, shape (N, n, n)
        Covariance history; the first 10 states are seed 002's eq (14).
    lat, h : ndarray, shape (N,)
    q : ndarray, shape (N, 4)
        Attitude quaternion (for δq → tilt/azimuth).
    distance : ndarray, shape (N,), optional
        Distance travelled. [m]
    scale : ndarray, shape (N, 10), optional
        σ the validity check scales the navigation states by; default
        :func:`covtool.lincov.kalman.running_scale` of ``P``.  Give the
        running scale of the whole history when ``P`` is a few points taken
        from it, so that they are judged as in the history.

    Returns
    -------
    dict of ndarray, shape (N,)
        ``sigma_north``, ``sigma_east``, ``sigma_down`` [m]; ``sigma_vn``,
        ``sigma_ve``, ``sigma_vd`` [m/s]; ``sigma_tilt_n``, ``sigma_tilt_e``,
        ``sigma_azimuth`` [rad]; ``cep`` [m], ``cep_rule`` [m], ``alt_pe`` [m],
        ``sigma_horizontal`` (RMS radial) [m]; ``cep_pct_distance`` [%].
        Every metric is NaN at the times where the navigation block
        ``P[:, :10, :10]`` is not finite, symmetric and PSD (its states
        scaled by the largest σ they have had in ``P``, so along a history
        a σ swinging through zero is not taken for round-off trouble).
    """
    P = np.asarray(P, float)[:, :10, :10]
    # δq0…δq3 scaled together, each state by the largest σ it has had (covtool.lincov.kalman.running_scale):
    # the upstream guard has judged every covariance by its own σ; this catches what it did not see
    P, valid = _valid(P, [np.arange(6, 10)], running_scale(P) if scale is None else scale)
    Pn = ned_position_covariance(P[:, :3, :3], lat, h)
    Pphi = attitude_errors(P[:, 6:10, 6:10], q)
    sd = lambda M, i: np.sqrt(np.clip(M[:, i, i], 0.0, None))  # noqa: E731
    out = {
        "sigma_north": sd(Pn, 0), "sigma_east": sd(Pn, 1), "sigma_down": sd(Pn, 2),
        "sigma_vn": sd(P, 3), "sigma_ve": sd(P, 4), "sigma_vd": sd(P, 5),
        "sigma_tilt_n": sd(Pphi, 0), "sigma_tilt_e": sd(Pphi, 1), "sigma_azimuth": sd(Pphi, 2),
    }
    out["cep"] = cep(Pn[:, :2, :2])
    out["cep_rule"] = cep_approx(Pn[:, :2, :2])
    out["alt_pe"] = PE_FACTOR * out["sigma_down"]
    out["sigma_horizontal"] = np.sqrt(Pn[:, 0, 0] + Pn[:, 1, 1])
    if distance is not None:
        d = np.asarray(distance, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            out["cep_pct_distance"] = np.where(d > 0, 100.0 * out["cep"] / d, np.nan)
    if not valid.all():
        for v in out.values():
            v[~valid] = np.nan
    return out


#: the domain tests of :func:`validity`: name, metrics compared, limit, description
VALIDITY_TESTS = (
    ("position", ("sigma_north", "sigma_east"), POSITION_LIMIT,
     f"horizontal position 1sigma > 1 % of the Earth radius ({POSITION_LIMIT / 1e3:.1f} km)"),
    ("altitude", ("sigma_down",), ALTITUDE_LIMIT,
     f"altitude 1sigma > {ALTITUDE_LIMIT / 1e3:.1f} km (vertical channel diverged)"),
    ("attitude", ("sigma_tilt_n", "sigma_tilt_e", "sigma_azimuth"), ATTITUDE_LIMIT,
     f"attitude 1sigma > {ATTITUDE_LIMIT:.3g} rad ({np.degrees(ATTITUDE_LIMIT):.2g} deg)"),
)


def validity(m: dict) -> dict:
    """Where the metrics leave the linear error model's domain.

    Parameters
    ----------
    m : dict of ndarray, shape (...)
        From :func:`nav_metrics`.

    Returns
    -------
    dict of str to ndarray of bool, shape (...)
        ``position``: ``max(σ_N, σ_E) >`` :data:`POSITION_LIMIT`;
        ``altitude``: ``σ_D >`` :data:`ALTITUDE_LIMIT`; ``attitude``: a tilt
        or the azimuth ``>`` :data:`ATTITUDE_LIMIT` (module notes).  NaN
        metrics are not flagged here (the guard flags them).
    """
    out = {}
    for name, keys, limit, _ in VALIDITY_TESTS:
        x = np.zeros(np.shape(m[keys[0]]), bool)
        for k in keys:
            with np.errstate(invalid="ignore"):
                x |= np.asarray(m[k]) > limit
        out[name] = x
    return out


def first_invalid(m: dict, t) -> dict:
    """First time each domain test of :func:`validity` fails.

    Parameters
    ----------
    m : dict of ndarray, shape (N,)
        From :func:`nav_metrics` along a history.
    t : ndarray, shape (N,)
        Times of the history. [s]

    Returns
    -------
    dict of str to float
        Test name -> first time [s] it fails; tests that never fail are
        left out.
    """
    t = np.asarray(t, float)
    out = {}
    for name, flags in validity(m).items():
        hit = np.flatnonzero(flags)
        if hit.size:
            out[name] = float(t[hit[0]])
    return out


def validity_text(first: dict, until: float = np.inf) -> str:
    """``"<test> from t = … min; …"`` for the tests failed by ``until``.

    Parameters
    ----------
    first : dict of str to float
        From :func:`first_invalid`.
    until : float
        Only failures at or before this time are listed. [s]

    Returns
    -------
    str
        ``"ok"`` if the covariance stayed in the domain (a table cell is
        never left empty); failures in the order they happened.
    """
    desc = {name: d for name, _, _, d in VALIDITY_TESTS}
    hits = sorted((v, k) for k, v in first.items() if v <= until + 1e-9)
    return "; ".join(f"{desc[k]} from t = {v / 60:.1f} min" for v, k in hits) or "ok"
