"""The covariance guard: finite, symmetric, PSD, with the step named.

Every path that produces a covariance checks it here (:func:`check_covariance`,
batched :func:`covariance_status`), and every system it propagates
(:func:`check_system`, :func:`check_finite`).  The PSD test is a Cholesky
factorisation of the correlation matrix, so it is free of units; the
quaternion error of seed 002, eq (14), shares one scale
(:func:`scale_groups`).  Split from :mod:`covtool.lincov.kalman` (which
re-exports these names) so that the Kalman kernel and its guard each stay
one readable module.

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


def symmetrize(P: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``(P + Pᵀ)/2`` over the last two axes.

    Parameters
    ----------
    P : ndarray, shape (..., n, n)
    out : ndarray, shape (..., n, n), optional
        Written with the result (not ``P`` itself); the same operations, so
        the same bits, as a new array.

    Returns
    -------
    ndarray, shape (..., n, n)
        ``out`` when given.
    """
    if out is None:
        return 0.5 * (P + np.swapaxes(P, -1, -2))
    np.add(P, np.swapaxes(P, -1, -2), out=out)
    out *= 0.5
    return out


def covariance_root(P: np.ndarray, support=None) -> np.ndarray:
    """Principal square root of a PSD matrix (or stack): ``S = V diag(√w₊) Vᵀ``, ``S Sᵀ = P``.

    The factor for drawing ``x = S z``, ``z ~ N(0, I)``, with covariance
    ``P``.  Unlike an eigenvector factor ``V diag(√w)`` (whose columns are
    fixed only up to rotations inside an eigenspace, so by round-off where
    eigenvalues are equal: three identical sensor axes, a stop) or a
    Cholesky factor (undefined for a singular ``P``), the principal root is
    unique and continuous in ``P``, singular or not: a round-off change of
    ``P`` (another BLAS, another integrator) changes the draws of one seed
    by round-off, not to other, equivalent draws.

    Parameters
    ----------
    P : ndarray, shape (..., n, n)
        Symmetric PSD (symmetrised here; eigenvalues below zero, round-off,
        are taken as zero).
    support : array_like of int, shape (s,), optional
        States outside which ``P`` is zero (at every matrix of the stack):
        the root is computed on ``P[support, support]`` and only its
        ``support`` columns are returned, so ``s`` normal numbers per draw
        instead of ``n`` (its other columns are zero).

    Returns
    -------
    ndarray, shape (..., n, n), or (..., n, s) with ``support``
        ``S`` (or ``S[..., :, support]``), with ``S Sᵀ = P``.

    Notes
    -----
    ``P`` must be finite: the callers pass covariances already checked
    (:func:`check_system`); for a non-finite ``P`` numpy's ``eigh`` raises
    ``LinAlgError`` or returns NaN.  Near a null direction the root is
    Hölder-½ in ``P``: a round-off eigenvalue ``ε`` there gives ``√ε``.
    """
    P = symmetrize(np.asarray(P, float))
    n = P.shape[-1]
    if support is None:
        w, V = np.linalg.eigh(P)
        return (V * np.sqrt(np.clip(w, 0.0, None))[..., None, :]) @ np.swapaxes(V, -1, -2)
    s = np.asarray(support, int)
    w, V = np.linalg.eigh(P[..., s[:, None], s[None, :]])
    out = np.zeros(P.shape[:-2] + (n, s.size))
    out[..., s, :] = (V * np.sqrt(np.clip(w, 0.0, None))[..., None, :]) @ np.swapaxes(V, -1, -2)
    return out


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
    d = np.diagonal(X, axis1=1, axis2=2)
    # A state whose row and column are zero in every matrix of the chunk (a random constant's in Q_d:
    # 36 of 58) can hold no non-finite entry and no asymmetry: every non-zero entry, NaN and ±inf
    # included, is in the block of the live states, so the finiteness and exact-symmetry screens run
    # on that block (a copy a few times smaller), the copy the Cholesky factorises anyway.  A state
    # with a non-zero variance somewhere is live (every state of a covariance history): the rows and
    # columns are searched only when some variance is zero throughout.
    live = (d != 0).any(axis=0)
    if not live.all():
        nz = (X != 0).any(axis=0)
        live = nz.any(axis=0) | nz.any(axis=1)
    live = np.flatnonzero(live)
    # a copy (unless only screened): the Cholesky below shifts its diagonal in place
    Y = X[:, live[:, None], live[None, :]] if live.size < n else X.copy() if psd else X
    finite = np.isfinite(Y).all(axis=(1, 2))
    if not finite.all():
        for i in np.flatnonzero(~finite):
            bad = ~np.isfinite(X[i])
            dbad = np.diagonal(bad)
            s = int(np.argmax(dbad)) if dbad.any() else int(np.argmax(bad.sum(axis=1)))
            code[i], state[i] = NONFINITE, s
            value[i] = X[i, s, int(np.argmax(bad[s]))]
    with np.errstate(invalid="ignore"):
        s = np.sqrt(np.abs(d)) if scale is None else np.where(np.isfinite(scale), scale, 0.0)
    for g in groups:
        s[:, g] = s[:, g].max(axis=1, keepdims=True)
    s = np.where(s > 0, s, 1.0)
    # own scaling (s² = |P_ii|): any negative variance fails; a group or a given scale allows −tol·s²
    floor = -tol * s * s
    # symmetry relative to σ_i σ_j, computed (on the whole matrix) only for matrices that are not
    # exactly symmetric
    for i in np.flatnonzero(finite & ~(Y == np.swapaxes(Y, 1, 2)).all(axis=(1, 2))):
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
    if not cand.size or not live.size:
        return                                  # (an empty block: every matrix zero, trivially PSD)
    # Cholesky of S (C + tol I) S = P + tol S²: it exists iff λ_min(C) > −tol, and Cholesky's
    # backward error is invariant under the diagonal scaling S, so C itself need not be formed.
    # A dead state adds an isolated tol·1 to the diagonal, which changes nothing: factorised on the
    # live block (over every matrix of the chunk: a superset of the candidates' live states)
    if cand.size < X.shape[0]:
        Y = Y[cand]
    np.einsum("kii->ki", Y)[...] += tol * (s[cand] if live.size == n else s[cand][:, live]) ** 2
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
    ValueError
        ``Phi`` or ``Qd`` is a streamed stack (guarded as it is made, never here).
    """
    for stack in (Phi, Qd):
        if stack is not None and not isinstance(stack, np.ndarray) and hasattr(stack, "shape") \
                and hasattr(stack, "__getitem__"):
            # a streamed system (covtool.lincov.streamed.StreamedSystem) is guarded chunk by chunk as it is
            # made; checking it here would build the whole (N, n, n) stack it exists to avoid
            raise ValueError(f"{what}: a streamed system is guarded as it is made; pass system_checked=True")
    if P0 is not None:
        check_covariance(P0, f"{what}: P0", names=names)
    if Phi is not None:
        check_finite(Phi, f"{what}: Φ of the step", names=names, times=times)
    if Qd is not None:
        check_covariance(Qd, f"{what}: Q_d of the step", names=names, times=times)
    if R is not None:
        check_covariance(R, f"{what}: R", names=measurement_names)
