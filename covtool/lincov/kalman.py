"""The Kalman kernel: gain and updates in one place (the guard beside it).

Seed 002, eq (7) (gain, :func:`kalman_gain`), eq (8) and the Joseph form
(filter update, :func:`filter_update`), eq (16) (the truth under a filter's
gain, :func:`truth_update`), eq (6a) (:func:`predict`); the guard every
covariance passes (finite, symmetric, PSD: :func:`check_covariance`, with
:func:`symmetrize`) lives in :mod:`covtool.lincov.guard` and is re-exported
here.  The Joseph / eq (16) update is written once, in its
batched low-rank product form (:func:`joseph_update`, any gain, ``D = I``
or a selection or a general ``D``); the single-case functions call it.
The step-by-step reference (:mod:`covtool.lincov.reference`), the batched
engine (:mod:`covtool.lincov.batch`), the error budget, the Monte Carlo
feedback filters, the dual-IMU whitener and the timed on-board cycle
(:mod:`covtool.analysis.cost`) call these.  The discretisation of
eq (6b)–(6d) lives in :mod:`covtool.lincov.discretize`.

Entry checks: the update functions check the shapes (``ValueError``) and
that the posterior is finite (:class:`NumericalError`), naming the step
(``what``); the PSD test costs a Cholesky factorisation, more than a
rank-m update, so the callers run :func:`check_covariance` at their record
steps and every few updates.

Pure numeric core: arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np

from covtool.errors import NumericalError
from covtool.lincov.guard import (  # noqa: F401 - re-exported: the kernel's users import the guard from here
    PSD_TOL, SYM_TOL, OK, NONFINITE, ASYMMETRIC, NEGATIVE_VARIANCE, NOT_PSD, _CHUNK, QUATERNION_ERROR,
    scale_groups, running_scale, symmetrize, covariance_root, CovarianceStatus, covariance_status, _status_chunk,
    check_covariance, locate, time_text, check_finite, check_system,
)


def _check_shapes(what: str, P=None, K=None, H=None, R=None, D=None) -> None:
    """Raise ValueError unless the update's matrices fit together.

    Cheap (shapes only): the kernel's entry check.  ``P`` (..., n, n),
    ``H`` (m, n) or (..., m, n), ``R`` (..., m, m), ``K`` (..., n_f, m),
    ``D`` (n, n_f).
    """
    def sh(x):
        return None if x is None else np.shape(x)

    p, k, h, r, d = sh(P), sh(K), sh(H), sh(R), sh(D)
    problems = []
    if p is not None and (len(p) < 2 or p[-1] != p[-2]):
        problems.append(f"P has shape {p}, not (..., n, n)")
    if h is not None and len(h) < 2:
        problems.append(f"H has shape {h}, not (m, n)")
    if not problems and p is not None and h is not None and h[-1] != p[-1]:
        problems.append(f"H has {h[-1]} columns for {p[-1]} states")
    if r is not None and (len(r) < 2 or r[-1] != r[-2] or (h is not None and r[-1] != h[-2])):
        problems.append(f"R has shape {r} for {h[-2] if h is not None and len(h) >= 2 else '?'} measurements")
    if k is not None and h is not None and len(k) >= 2 and len(h) >= 2 and k[-1] != h[-2]:
        problems.append(f"K has {k[-1]} columns for {h[-2]} measurements")
    if d is not None and p is not None and k is not None and len(d) == 2 and (d[0] != p[-1] or d[1] != k[-2]):
        problems.append(f"D has shape {d}, not ({p[-1]}, {k[-2]})")
    elif d is None and p is not None and k is not None and len(k) >= 2 and k[-2] != p[-1]:
        problems.append(f"K has {k[-2]} rows for {p[-1]} states")
    if problems:
        raise ValueError((f"{what}: " if what else "") + "; ".join(problems))


def innovation_covariance(P: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Innovation covariance ``S = H P Hᵀ + R``, symmetrised (seed 002, eq (7)).

    Parameters
    ----------
    P : ndarray, shape (..., n, n)
    H : ndarray, shape (m, n)
    R : ndarray, shape (..., m, m)

    Returns
    -------
    ndarray, shape (..., m, m)
    """
    return symmetrize(H @ P @ np.swapaxes(H, -1, -2) + R)


def gain_from_innovation(S: np.ndarray, HP: np.ndarray) -> np.ndarray:
    """Gain ``K = (H P)ᵀ S⁻¹`` from ``S = H P Hᵀ + R`` and ``H P`` (seed 002, eq (7)).

    The unchecked core of :func:`kalman_gain`, for callers that form ``S``
    and ``H P`` themselves (the batched engine) and name their own step.

    Parameters
    ----------
    S : ndarray, shape (..., m, m)
    HP : ndarray, shape (..., m, n)

    Returns
    -------
    ndarray, shape (..., n, m)

    Raises
    ------
    numpy.linalg.LinAlgError
        ``S`` is singular.
    """
    return np.swapaxes(np.linalg.solve(S, HP), -1, -2)


def standard_update(P: np.ndarray, K: np.ndarray, HP: np.ndarray, *, sym: bool = True) -> np.ndarray:
    """Seed 002 eq (8): ``P − K H P`` (optimal gain only), batched.

    Parameters
    ----------
    P : ndarray, shape (..., n, n)
    K : ndarray, shape (..., n, m)
    HP : ndarray, shape (..., m, n)
        ``H P``.
    sym : bool
        Return ``(P + Pᵀ)/2`` of the result.

    Returns
    -------
    ndarray, shape (..., n, n)
    """
    out = P - K @ HP
    return symmetrize(out) if sym else out


def kalman_gain(Pf: np.ndarray, Hf: np.ndarray, R: np.ndarray, *, S: np.ndarray | None = None,
                what: str = "") -> np.ndarray:
    """Kalman gain ``K = P Hᵀ (H P Hᵀ + R)⁻¹`` (seed 002, eq (7)).

    Parameters
    ----------
    Pf : ndarray, shape (..., n, n)
        One covariance or a stack (a batch of cases).
    Hf : ndarray, shape (m, n)
    R : ndarray, shape (..., m, m)
    S : ndarray, shape (..., m, m), optional
        The innovation covariance if already formed
        (:func:`innovation_covariance`).
    what : str
        Names the filter and step in error messages (a prefix).

    Returns
    -------
    ndarray, shape (..., n, m)

    Raises
    ------
    ValueError
        Shapes that do not fit.
    NumericalError
        ``S`` is singular or not finite.
    """
    _check_shapes(what, P=Pf, H=Hf, R=R)
    S = innovation_covariance(Pf, Hf, R) if S is None else S
    if not np.all(np.isfinite(S)):
        raise NumericalError(f"{what + ': ' if what else ''}innovation covariance H P Hᵀ + R is not finite")
    try:
        return gain_from_innovation(S, Hf @ Pf)
    except np.linalg.LinAlgError:
        raise NumericalError(f"{what + ': ' if what else ''}innovation covariance H P Hᵀ + R is singular") from None


def selection(D: np.ndarray):
    """``(k0, k1)`` if ``D`` selects the consecutive truth states ``k0:k1``, else None.

    Parameters
    ----------
    D : ndarray, shape (n, n_f)
        Map from filter states onto truth states (seed 002, eq (16)).

    Returns
    -------
    tuple of int or None
    """
    D = np.asarray(D, float)
    n, nf = D.shape
    cols = np.flatnonzero(D[:, 0]) if nf else []
    if len(cols) != 1 or cols[0] + nf > n:
        return None
    k0 = int(cols[0])
    E = np.zeros_like(D)
    E[k0:k0 + nf] = np.eye(nf)
    return (k0, k0 + nf) if np.array_equal(D, E) else None


def joseph_update(P, K, H, R, sel=None, symmetrize=True, *, HP=None):
    """Joseph form / eq (16) update of a stack, in place: the one home.

    ``P⁺ = (I − D K H) P (I − D K H)ᵀ + D K R Kᵀ Dᵀ`` (seed 002, eq (16);
    the Joseph form of the filter's own update with ``D = I``), for any
    gain, optimal or not.

    Parameters
    ----------
    P : ndarray, shape (B, n, n)
        Prior covariances; overwritten (they must be owned by the caller).
    K : ndarray, shape (B, n_f, m)
        Gains; with ``sel = None`` and a general ``D`` pass ``D K``
        (shape (B, n, m)).
    H : ndarray, shape (m, n)
    R : ndarray, shape (B, m, m) or (m, m)
        Measurement noise covariance.
    sel : (int, int), optional
        ``D`` is the selection of truth states ``k0:k1`` (:func:`selection`);
        ``None`` means ``D = I`` (or ``K`` is already ``D K``).
    symmetrize : bool
        Return ``(P + Pᵀ)/2`` (exactly symmetric; one more pass over ``P``).
    HP : ndarray, shape (B, m, n), optional
        ``H P`` if the caller has formed it (for the gain).

    Returns
    -------
    ndarray, shape (B, n, n)
        ``P`` itself, or a new exactly symmetric array if ``symmetrize``.

    Notes
    -----
    ``A = I − D K H`` is the identity plus a rank-m term, so the product
    form is evaluated without forming ``A``: ``Y = P − D K (H P)``, then
    ``Y Aᵀ = Y − (Y Hᵀ)(D K)ᵀ``, then ``+ D K R (D K)ᵀ``: ``O(m n²)``
    per case instead of ``O(n³)``, only the rows and columns ``k0:k1``
    change.  It keeps the Joseph form's round-off behaviour: the error of
    ``Y`` is multiplied by ``Aᵀ``, which attenuates it in the measured
    directions.  (The algebraically equal ``P + X + Xᵀ`` with
    ``X = (D K S/2 − P Hᵀ)(D K)ᵀ`` does not: for a fix that shrinks a
    variance 10⁴-fold it is off by 4e-9 relative where this form agrees
    with the information form to round-off; tests/test_aiding_engine.py.)
    """
    k0, k1 = sel if sel is not None else (0, P.shape[1])
    Kt = np.swapaxes(K, -1, -2)
    P[:, k0:k1, :] -= K @ (H @ P if HP is None else HP)        # Y = (I − D K H) P
    P[:, :, k0:k1] -= (P @ H.T) @ Kt                           # Y (I − D K H)ᵀ
    P[:, k0:k1, k0:k1] += K @ R @ Kt                           # + D K R Kᵀ Dᵀ
    if not symmetrize:
        return P
    return 0.5 * (P + np.swapaxes(P, 1, 2))


def _update(P, DK, H, R, sel, what):
    """One posterior through :func:`joseph_update` (B = 1), finite-checked."""
    P = np.array(P, float)
    with np.errstate(over="ignore", invalid="ignore"):          # a non-finite result is reported below
        out = joseph_update(P[None], np.asarray(DK, float)[None], H, np.asarray(R, float)[None], sel)[0]
    if not np.all(np.isfinite(out)):
        raise NumericalError(f"{what}: the updated covariance is not finite")
    return out


def filter_update(Pf, K, Hf, R, form: str = "joseph", *, what: str = "filter update"):
    """Filter covariance update: Joseph form or seed 002 eq (8).

    Parameters
    ----------
    Pf : ndarray, shape (n, n)
        Prior covariance.
    K : ndarray, shape (n, m)
        Gain (any gain for the Joseph form; the optimal one for eq (8)).
    Hf : ndarray, shape (m, n)
    R : ndarray, shape (m, m)
    form : {"joseph", "standard"}
        ``(I − K H) P (I − K H)ᵀ + K R Kᵀ`` (:func:`joseph_update`) or
        eq (8) ``P − K H P``.
    what : str
        Names the filter and step in error messages.

    Returns
    -------
    ndarray, shape (n, n)
        Symmetrised posterior.

    Raises
    ------
    ValueError
        Shapes that do not fit, or an unknown ``form``.
    NumericalError
        A non-finite posterior.
    """
    _check_shapes(what, P=Pf, K=K, H=Hf, R=R)
    if form == "joseph":
        return _update(Pf, K, Hf, R, None, what)
    if form == "standard":
        with np.errstate(over="ignore", invalid="ignore"):
            out = standard_update(Pf, K, Hf @ Pf)
        if not np.all(np.isfinite(out)):
            raise NumericalError(f"{what}: the updated covariance is not finite")
        return out
    raise ValueError(f"unknown update form {form!r} (joseph, standard)")


def truth_update(P, D, K, H, R, *, what: str = "truth update"):
    """Truth covariance under the filter's gain (seed 002, eq (16)).

    ``P⁺ = (I − D K H) P (I − D K H)ᵀ + D K R Kᵀ Dᵀ``, with ``K`` the filter's
    gain, ``H`` the truth measurement matrix and ``D`` (n × n_f) the map from
    filter states onto truth states.  It holds for any gain: the correction
    ``x ← x − D K z`` of eq (10) with ``z = H x + v``.  Computed by
    :func:`joseph_update` (the selection fast path when ``D`` selects
    consecutive states).

    Parameters
    ----------
    P : ndarray, shape (n, n)
    D : ndarray, shape (n, n_f)
    K : ndarray, shape (n_f, m)
    H : ndarray, shape (m, n)
    R : ndarray, shape (m, m)
    what : str
        Names the case and step in error messages.

    Returns
    -------
    ndarray, shape (n, n)
        Symmetrised posterior.

    Raises
    ------
    ValueError
        Shapes that do not fit.
    NumericalError
        A non-finite posterior.
    """
    _check_shapes(what, P=P, K=K, H=H, R=R, D=D)
    sel = selection(D)
    return _update(P, K if sel is not None else np.asarray(D, float) @ K, H, R, sel, what)


def predict(Phi: np.ndarray, P: np.ndarray, Qd: np.ndarray) -> np.ndarray:
    """Covariance propagation ``Φ P Φᵀ + Q_d``, symmetrised (seed 002, eq (6a)).

    Parameters
    ----------
    Phi, P, Qd : ndarray, shape (..., n, n)

    Returns
    -------
    ndarray, shape (..., n, n)
    """
    return symmetrize(Phi @ P @ np.swapaxes(Phi, -1, -2) + Qd)
