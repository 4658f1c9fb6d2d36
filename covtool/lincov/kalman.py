"""The Kalman kernel: gain, updates and the covariance guard, in one place.

Seed 002, eq (7) (gain, :func:`kalman_gain`), eq (8) and the Joseph form
(filter update, :func:`filter_update`), eq (16) (the truth under a filter's
gain, :func:`truth_update`), eq (6a) (:func:`predict`), and the guard every
covariance passes (finite, symmetric, PSD: :func:`check_covariance`), with
:func:`symmetrize`.  The Joseph / eq (16) update is written once, in its
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

from dataclasses import dataclass

import numpy as np

from covtool.errors import NumericalError


#: tolerance of the PSD test: the smallest eigenvalue of the correlation matrix
#: ``C = S⁻¹ P S⁻¹`` (``S = diag √|P_ii|``; one σ for the quaternion error,
#: :func:`scale_groups`; the largest σ so far for a pure propagation,
#: :func:`running_scale`; the total's σ for a budget's contributions) must be
#: ≥ −PSD_TOL.  ``C`` has a unit diagonal, so this is relative to the σ's of the
#: states involved and free of units.  Round-off alone stays far inside: an
#: eigenvalue of ``C`` is computed to ``≈ n ε ‖C‖ ≤ n² ε ≈ 7e-13`` (n = 58); measured
#: over every covariance and input Q_d of the shipped studies (pure INS, filter
#: order, equivalent-noise modes, sensitivity sweep, both budgets) −3e-15, and
#: −2.2e-12 for a budget's contributions; −7e-13 for noise-free single-source
#: propagations of 3 h (tests/test_physics.py), −1e-13 for 6 h of pure INS.  1e-9
#: is over a thousand times above these and a thousand times below anything
#: reported (σ's to four to six significant digits).
PSD_TOL = 1e-9
#: tolerance of the symmetry test on ``|C_ij − C_ji|`` (same scaling as PSD_TOL)
SYM_TOL = 1e-9

#: problem codes of :class:`CovarianceStatus`
OK, NONFINITE, ASYMMETRIC, NEGATIVE_VARIANCE, NOT_PSD = 0, 1, 2, 3, 4

#: matrices checked at once (bounds the memory of the correlation matrices)
_CHUNK = 512


#: the quaternion error of seed 002, eq (14): its components share one scale in the guard
QUATERNION_ERROR = ("dq0", "dq1", "dq2", "dq3")


def scale_groups(names, n: int | None = None) -> list:
    """Index groups of states the guard scales by one σ (the largest of the group).

    Parameters
    ----------
    names : sequence of str or None
        State names; joint models may prefix them (``"main:dq0"``).
    n : int, optional
        Number of states when ``names`` is None: a matrix of ten or more
        states is taken to follow covtool's convention (the first ten are
        seed 002's eq (14), ``δq`` at 6–9).

    Returns
    -------
    list of ndarray of int
        One group per quaternion error ``δq0 … δq3`` (seed 002, eq (14)).

    Notes
    -----
    ``|q̂| = |q| = 1`` gives ``q·δq = 0`` to first order: the direction
    ``q`` of the quaternion-error block is a structural null direction of
    every covariance, and ``δq0`` (≈ ``−q⃗·δq⃗/q0``) has a variance near zero.
    Scaled by their own σ, as a correlation matrix does, the round-off of
    that null direction is amplified by ``σ(δq3)²/σ(δq0)²`` (−1e-6 after
    hours of pure INS); scaled together by the block's largest σ, it is
    round-off of the rotation error itself, as it should be.
    """
    if names is None:
        return [np.arange(6, 10)] if n is not None and n >= 10 else []
    names = [str(x) for x in names]
    out = []
    for i in range(len(names) - 3):
        tail = [x.rsplit(":", 1)[-1] for x in names[i:i + 4]]
        prefix = {x[:-3] for x in names[i:i + 4]}
        if tuple(tail) == QUATERNION_ERROR and len(prefix) == 1:
            out.append(np.arange(i, i + 4))
    return out


def running_scale(P: np.ndarray) -> np.ndarray:
    """Largest σ each state has had so far along a history.

    Parameters
    ----------
    P : ndarray, shape (N, n, n)
        Covariance history (time on the first axis).

    Returns
    -------
    ndarray, shape (N, n)
        ``max_{j ≤ k} √|P_j,ii|``: the scale of the round-off of ``P_k,ii``.

    Notes
    -----
    Propagation round-off is absolute at the size the terms had: a state
    whose σ swings through zero (a Schuler oscillation excited by one
    source and no noise) has its variance formed by cancellation there, and
    scaled by its own near-zero σ the correlation matrix is meaningless
    (eigenvalue −0.27 at the equator after 3 h).  Scaled by the largest σ
    it has had, that history stays within 1e-12 of PSD.  Used for pure
    propagation only: after a measurement update a small σ is not the
    result of cancellation and is judged by itself.
    """
    P = np.asarray(P, float)
    with np.errstate(invalid="ignore"):
        d = np.abs(np.diagonal(P, axis1=-2, axis2=-1))
    d = np.where(np.isfinite(d), d, 0.0)
    return np.sqrt(np.maximum.accumulate(d, axis=0))


def symmetrize(P: np.ndarray) -> np.ndarray:
    """``(P + Pᵀ)/2`` over the last two axes.

    Parameters
    ----------
    P : ndarray, shape (..., n, n)

    Returns
    -------
    ndarray, shape (..., n, n)
    """
    return 0.5 * (P + np.swapaxes(P, -1, -2))


@dataclass(frozen=True)
class CovarianceStatus:
    """Outcome of :func:`covariance_status` for a stack of matrices.

    Attributes
    ----------
    code : ndarray of int, shape (...)
        ``OK`` (0), ``NONFINITE``, ``ASYMMETRIC``, ``NEGATIVE_VARIANCE`` or
        ``NOT_PSD`` per matrix, in that order of precedence.
    state : ndarray of int, shape (...)
        The state the problem is in (−1 if OK): the first non-finite
        diagonal entry (else the row with most non-finite entries), the
        row of the largest asymmetry, the most negative variance relative
        to its row, or the largest component of the eigenvector of the most
        negative correlation eigenvalue.
    other : ndarray of int, shape (...)
        The column of the largest asymmetry (−1 otherwise).
    value : ndarray of float, shape (...)
        The offending entry, asymmetry, variance or eigenvalue.
    tol, sym_tol : float
        Tolerances used.
    """

    code: np.ndarray
    state: np.ndarray
    other: np.ndarray
    value: np.ndarray
    tol: float
    sym_tol: float

    @property
    def ok(self) -> np.ndarray:
        """Boolean mask of the matrices that passed, shape (...)."""
        return self.code == OK

    def problem(self, index, names=None) -> str:
        """One-line description of the problem of matrix ``index``."""
        index = tuple(np.atleast_1d(index)) if np.ndim(index) else index

        def nm(i):
            return repr(str(names[i])) if names is not None and 0 <= i < len(names) else f"#{i}"

        c, s, v = int(self.code[index]), int(self.state[index]), float(self.value[index])
        if c == NONFINITE:
            return f"covariance has a non-finite entry ({v}) in state {nm(s)}"
        if c == ASYMMETRIC:
            return (f"covariance lost symmetry (max relative asymmetry {v:.3g} > {self.sym_tol:g}) "
                    f"between states {nm(s)} and {nm(int(self.other[index]))}")
        if c == NEGATIVE_VARIANCE:
            return f"covariance has a negative variance ({v:.3g}) of state {nm(s)}"
        if c == NOT_PSD:
            return (f"covariance lost positive semi-definiteness (min eigenvalue of the correlation "
                    f"matrix {v:.3g} < -{self.tol:g}), mostly in state {nm(s)}")
        return "covariance is valid"


def covariance_status(P: np.ndarray, tol: float = PSD_TOL, *, psd: bool = True,
                      sym_tol: float = SYM_TOL, scale: np.ndarray | None = None, groups=()) -> CovarianceStatus:
    """Finiteness, symmetry and PSD of a stack of covariances.

    Parameters
    ----------
    P : ndarray, shape (..., n, n)
        Covariances, any units per state.
    tol : float
        A matrix is PSD if the smallest eigenvalue of its correlation
        matrix is ≥ −tol (:data:`PSD_TOL`).
    psd : bool
        Test positive semi-definiteness and the sign of the variances
        (False for pieces that may be indefinite, e.g. the cross-covariance
        contribution of a budget); finiteness and symmetry are always tested.
    sym_tol : float
        Largest allowed ``|C_ij − C_ji|``.
    scale : ndarray, shape (..., n), optional
        σ to normalise by instead of ``√|P_ii|`` (e.g. the σ of a total
        whose contributions ``P`` are: a contribution is then PSD, and its
        variances non-negative, relative to the total; zeros count as 1).
    groups : sequence of index arrays
        States scaled together by their largest σ (:func:`scale_groups`:
        the quaternion error, whose norm direction is structurally null).

    Returns
    -------
    CovarianceStatus

    Notes
    -----
    With ``S = diag √|P_ii|`` (1 where ``P_ii = 0``; the largest of a group
    for the states of ``groups``) the correlation matrix ``C = S⁻¹ P S⁻¹``
    has ±1 on its diagonal, so one tolerance serves every state whatever
    its unit or magnitude: a negative variance shows as −1 (below
    ``−tol·S_ii²`` for a grouped or given scale), a correlation beyond ±1 as
    a negative eigenvalue.  PSD is tested by one
    batched Cholesky factorisation of ``C + tol·I`` (it exists iff
    ``λ_min(C) > −tol``); only if it fails are the eigenvalues computed, to
    find the matrices and the state.  Cost: ``n³/3`` per matrix, a sixth of
    an eigenvalue decomposition.
    """
    P = np.asarray(P, dtype=float)
    if P.ndim < 2 or P.shape[-1] != P.shape[-2]:
        raise ValueError(f"a covariance must have shape (..., n, n), got {P.shape}")
    batch, n = P.shape[:-2], P.shape[-1]
    M = int(np.prod(batch, dtype=int))
    X = P.reshape((M, n, n))                # an empty (0 × 0) covariance is trivially valid
    sc = None if scale is None else np.broadcast_to(np.asarray(scale, float), batch + (n,)).reshape((-1, n))
    code = np.zeros(M, np.int8)
    state = np.full(M, -1)
    other = np.full(M, -1)
    value = np.full(M, np.nan)
    if n and M:
        for a in range(0, M, _CHUNK):
            b = min(M, a + _CHUNK)
            _status_chunk(X[a:b], tol, psd, sym_tol, code[a:b], state[a:b], other[a:b], value[a:b],
                          None if sc is None else sc[a:b], groups)
    return CovarianceStatus(code.reshape(batch), state.reshape(batch), other.reshape(batch),
                            value.reshape(batch), tol, sym_tol)


def _status_chunk(X, tol, psd, sym_tol, code, state, other, value, scale=None, groups=()):
    """Fill ``code``, ``state``, ``other``, ``value`` (views) for matrices ``X``."""
    n = X.shape[-1]
    diag = np.arange(n)
    finite = np.isfinite(X).all(axis=(1, 2))
    if not finite.all():
        for i in np.flatnonzero(~finite):
            bad = ~np.isfinite(X[i])
            dbad = np.diagonal(bad)
            s = int(np.argmax(dbad)) if dbad.any() else int(np.argmax(bad.sum(axis=1)))
            code[i], state[i] = NONFINITE, s
            value[i] = X[i, s, int(np.argmax(bad[s]))]
    d = np.diagonal(X, axis1=1, axis2=2)
    with np.errstate(invalid="ignore"):
        s = np.sqrt(np.abs(d)) if scale is None else np.where(np.isfinite(scale), scale, 0.0)
    for g in groups:
        s[:, g] = s[:, g].max(axis=1, keepdims=True)
    s = np.where(s > 0, s, 1.0)
    # own scaling (s² = |P_ii|): any negative variance fails; a group or a given scale allows −tol·s²
    floor = -tol * s * s
    # symmetry relative to σ_i σ_j, computed only for matrices that are not exactly symmetric
    for i in np.flatnonzero(finite & ~(X == np.swapaxes(X, 1, 2)).all(axis=(1, 2))):
        A = (X[i] - X[i].T) / np.outer(s[i], s[i])
        a = float(A.max())
        if a > sym_tol:
            r, q = divmod(int(np.argmax(A)), n)
            code[i], state[i], other[i], value[i] = ASYMMETRIC, r, q, a
    if not psd:
        return
    with np.errstate(invalid="ignore"):
        negative = d < floor
        neg = negative.any(axis=1)
    for i in np.flatnonzero(neg & (code == OK)):
        # the most negative variance relative to its row (unit-free: P_ii / max_j |P_ij|)
        rowmax = np.abs(X[i]).max(axis=1)
        rel = np.where(negative[i], d[i] / np.where(rowmax > 0, rowmax, 1.0), np.inf)
        k = int(np.argmin(rel))
        code[i], state[i], value[i] = NEGATIVE_VARIANCE, k, d[i, k]
    cand = np.flatnonzero(code == OK)
    if not cand.size:
        return
    # Cholesky of S (C + tol I) S = P + tol S²: it exists iff λ_min(C) > −tol, and Cholesky's
    # backward error is invariant under the diagonal scaling S, so C itself need not be formed
    Y = X[cand] if cand.size < X.shape[0] else X.copy()
    Y[:, diag, diag] += tol * s[cand] ** 2
    try:
        np.linalg.cholesky(Y)
        return
    except np.linalg.LinAlgError:
        pass
    C = X[cand] / s[cand][:, :, None] / s[cand][:, None, :]
    w, v = np.linalg.eigh(C)
    for j in np.flatnonzero(w[:, 0] < -tol):
        i = cand[j]
        code[i], state[i], value[i] = NOT_PSD, int(np.argmax(np.abs(v[j, :, 0]))), w[j, 0]


def check_covariance(P: np.ndarray, what: str, tol: float = PSD_TOL, *, names=None, times=None, at=None,
                     psd: bool = True, scale: np.ndarray | None = None) -> None:
    """Raise :class:`NumericalError` unless every ``P`` is a covariance.

    Finite, symmetric and positive semi-definite within ``tol`` (see
    :func:`covariance_status`).

    Parameters
    ----------
    P : ndarray, shape (..., n, n)
        One covariance or a stack (history, batch of cases).
    what : str
        Names the case and the step, e.g.
        ``"filter B1: truth after the eq (16) update"``.
    tol : float
        PSD tolerance on the correlation matrix (:data:`PSD_TOL`).
    names : sequence of str, optional
        State names, to name the state in the message.
    times : array_like, shape (P.shape[0],), optional
        Time of each matrix of a stack (its first axis) [s]; the message
        gives the time of the first bad one.
    at : callable, optional
        ``at(index) -> str`` locating matrix ``index`` (a tuple) of the
        stack, e.g. the case of a batch; used instead of ``times``.
    psd : bool
        Test PSD (finiteness and symmetry are always tested).
    scale : ndarray, shape (..., n), optional
        σ to scale by instead of each matrix's own (:func:`covariance_status`,
        e.g. :func:`running_scale` of a pure propagation).

    Raises
    ------
    NumericalError
        ``"<what> at <t or index>: covariance <problem> … state '<name>'"``,
        for the first bad matrix of the stack (in C order).
    """
    n = np.shape(P)[-1] if np.ndim(P) >= 2 else 0
    st = covariance_status(P, tol, psd=psd, groups=scale_groups(names, n), scale=scale)
    if st.ok.all():
        return
    flat = int(np.flatnonzero(~st.ok.ravel())[0])
    index = np.unravel_index(flat, st.code.shape) if st.code.ndim else ()
    raise NumericalError(f"{what}{locate(index, times, at)}: {st.problem(index, names)}")


def locate(index: tuple, times=None, at=None) -> str:
    """`` at t = … s`` (or ``at(index)``) for the messages of the guard."""
    if at is not None:
        text = at(index)
        return f" {text}" if text else ""
    if times is not None and len(index):
        return f" at {time_text(float(np.asarray(times)[index[0]]))}"
    if len(index):
        return f" (matrix {tuple(int(i) for i in index)})"
    return ""


def time_text(t: float) -> str:
    """``t = 300.0 s`` (with minutes or hours when long) for messages."""
    if abs(t) >= 7200:
        return f"t = {t:.1f} s ({t / 3600:.2f} h)"
    if abs(t) >= 120:
        return f"t = {t:.1f} s ({t / 60:.1f} min)"
    return f"t = {t:.1f} s"


def check_finite(A: np.ndarray, what: str, *, names=None, times=None) -> None:
    """Raise :class:`NumericalError` if ``A`` has a non-finite entry.

    Parameters
    ----------
    A : ndarray, shape (..., n, k)
        E.g. a stack of transition matrices Φ or gains.
    what : str
        Names the matrix, e.g. ``"pure INS: Φ of the step"``.
    names : sequence of str, optional
        Names of the rows.
    times : array_like, shape (A.shape[0],), optional
        Time of each matrix of the stack [s].

    Raises
    ------
    NumericalError
        Names the first matrix, its time and the row.
    """
    A = np.asarray(A, float)
    fin = np.isfinite(A)
    if fin.all():
        return
    bad = np.argwhere(~fin)[0]
    index, row = tuple(bad[:-2]), int(bad[-2])
    state = repr(str(names[row])) if names is not None and row < len(names) else f"#{row}"
    raise NumericalError(f"{what}{locate(index, times)}: non-finite entry ({A[tuple(bad)]}) in the row of "
                         f"state {state}")


def check_system(what: str, Phi=None, Qd=None, *, P0=None, R=None, names=None, times=None,
                 measurement_names=None) -> None:
    """Entry guard of a covariance run: Φ finite, Q_d, P0 and R covariances.

    Parameters
    ----------
    what : str
        Names the run, e.g. ``"filter B1"``.
    Phi, Qd : ndarray, shape (N, n, n), optional
        Transition and process noise of each step (step k from ``times[k]``).
    P0 : ndarray, shape (..., n, n), optional
        Initial covariance(s).
    R : ndarray, shape (..., m, m), optional
        Measurement noise covariance(s).
    names : sequence of str, optional
        State names.
    times : array_like, shape (N+1,), optional
        Grid times [s].
    measurement_names : sequence of str, optional
        Names of the measurement components.

    Raises
    ------
    NumericalError
        From :func:`check_finite` / :func:`check_covariance`.
    """
    if P0 is not None:
        check_covariance(P0, f"{what}: P0", names=names)
    if Phi is not None:
        check_finite(Phi, f"{what}: Φ of the step", names=names, times=times)
    if Qd is not None:
        check_covariance(Qd, f"{what}: Q_d of the step", names=names, times=times)
    if R is not None:
        check_covariance(R, f"{what}: R", names=measurement_names)


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
        return np.swapaxes(np.linalg.solve(S, Hf @ Pf), -1, -2)
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
            out = symmetrize(Pf - K @ (Hf @ Pf))
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
