"""Discretisation of ``ẋ = F x + G w``: Van Loan's integral and seed 002's Taylor series.

Every function takes stacks of matrices (leading step axis) and returns
``Φ = e^{FΔt}`` and ``Q_d = ∫₀^Δt e^{Fs} Q_c e^{Fᵀs} ds`` (Van Loan 1978) for
every step.

Exact for any step
------------------
:func:`van_loan`, the adaptive :func:`taylor` (``order=None``),
:func:`block_triangular` and :func:`per_source` are exact to round-off for
any ``Δt``, or raise :class:`~covtool.errors.NumericalError` naming the step
when the result is not representable (an unstable mode that overflows):

1. *Balancing.*  ``F̃ = D⁻¹ F D`` and ``Q̃_c = D⁻¹ Q_c D⁻¹`` with ``D``
   diagonal, made of powers of two (LAPACK ``gebal`` on the envelope
   ``max_k |F_k|`` of the stack): a change of the states' units, exact in
   floating point, after which ``ν = max(‖F̃‖₁, ‖F̃‖_∞) ≥ ‖F̃‖₂`` measures how
   fast the dynamics really are.  For the 58-state INS model ``‖F‖₁`` is
   20–30 s⁻¹ in SI units but ``ν = 0.05–0.14 s⁻¹``, near the rate of its
   fastest Markov state (1/20 s).
2. *Scaling.*  A step with ``νΔt > θ`` (:data:`THETA`) is computed over
   ``h = Δt/2^s``, ``s = ⌈log₂(νΔt/θ)⌉``, so that ``νh ≤ θ``.
3. *Base step*: the series of eq (6b)–(6d) at ``h``, summed until the
   rigorous bound of its tail is below ``2⁻⁵³`` of the sum, column by column
   for Φ and element by element (correlation scaling) for ``Q_d``
   (:func:`_series`).
4. *Squaring*, ``s`` times (an exact identity, the integral over ``[0, 2h]``
   split at ``h``)::

       Φ(2h) = Φ(h)²,    Q_d(2h) = Φ(h) Q_d(h) Φ(h)ᵀ + Q_d(h)

Why: Van Loan's matrix ``[[−F, Q_c], [0, Fᵀ]]Δt`` holds ``e^{−FΔt}``, which
grows as ``e^{Δt/τ}`` for a Markov state of time constant τ; ``Q_d``
recovered as ``Φ · (Φ⁻¹Q_d)`` then has a relative error of about
``2⁻⁵³ e^{2Δt/τ}`` (``Q_vv = 3.55e11`` instead of 22 800 at ``Δt/τ = 30``),
and its normwise accuracy loses the small variances of integrated states at
short steps (3e-10 relative on the altitude variance of an IMU model at
0.04 s).  The series of eq (6b) has terms ``(FΔt)^i/i!`` that grow until
``i ≈ ‖FΔt‖``; summed to a fixed cap (40 terms) it returned ``Q_d = 7.5e15``
for ``F = −1, Δt = 20`` (exact: 1).  Squaring is stable for stable ``F``
(each update adds a PSD term to a contracted PSD matrix) and exact for
unstable ``F`` until ``Φ`` overflows.  So :func:`van_loan` and the adaptive
:func:`taylor` compute the same converged series: the integral of Van Loan
is seed 002's series summed to convergence.

Truncated series (seed 002's filters)
-------------------------------------
``taylor(order=N_t)`` is the paper's deliberate truncation over the whole
``Δt`` (no scaling), which the filters model.  It is refused when it is
meaningless: with ``a = νΔt`` the terms of eq (6b) shrink by at least the
factor ``a/(i+1)`` and those of eq (6c) by ``2a/(i+1)`` per order
(``‖C_i‖ ≤ 2‖F̃‖₂ ‖C_{i−1}‖`` for symmetric ``C``), so for ``2νΔt < N_t``
every omitted term is smaller than the last one kept and the truncation
error is at most the first omitted term over ``1 − 2νΔt/(N_t+1)``.  For
``2νΔt ≥ N_t`` that guarantee is gone, and for a Markov state (``ν = 1/τ``)
the first omitted term of eq (6c) is then really as large as the last one
kept: the series has not begun to converge (for ``N_t = 3``,
``Q_d = q Δt (1 − Δt/τ)`` is negative beyond ``Δt = τ``).  Hence the
refusal criterion ``2νΔt ≥ N_t``, i.e. ``Δt ≥ N_t τ/2`` for the fastest
Markov state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import matrix_balance

from covtool.errors import InputError, NumericalError

#: base-step bound ``νh ≤ θ`` (see the module notes)
THETA = 0.5
#: unit round-off: the adaptive series stops when its tail is below this fraction of the sum
UNIT_ROUNDOFF = 2.0**-53
#: cap of the adaptive base-step series: ``νh ≤ θ`` gains a factor ≥ 10 per term, so reaching it is an error
MAX_TERMS = 40
#: largest fixed order accepted (terms beyond ~30 are below round-off for any step the criterion accepts)
MAX_ORDER = 100
#: relative tolerance of the PSD check of an exact ``Q_d`` (correlation scaling)
PSD_TOL = 1e-9


@dataclass(frozen=True)
class StepInfo:
    """How each step of a stack was discretised.

    Attributes
    ----------
    terms : ndarray of int, shape (N,)
        Terms ``N_t`` of the series eq (6b)–(6d) at the base step
        (``i = 0 … N_t−1``).
    squarings : ndarray of int, shape (N,)
        ``s``: the step was computed over ``Δt/2^s`` and doubled ``s`` times.
    norm_dt : ndarray, shape (N,)
        ``νΔt`` with ``ν = max(‖F̃‖₁, ‖F̃‖_∞)`` of the balanced ``F``. [-]
    """

    terms: np.ndarray
    squarings: np.ndarray
    norm_dt: np.ndarray


# ---------------------------------------------------------------------------
# helpers


def repeated_steps(*stacks):
    """Steps equal to their predecessor in every stack: ``(first, inverse)``.

    Parameters
    ----------
    *stacks : ndarray, shape (N, ...)
        Per-step inputs (``F``, ``Q_c``, ``Δt``, ...), broadcast views allowed.

    Returns
    -------
    first : ndarray of int, shape (M,)
        Steps that differ from the one before (step 0 always).
    inverse : ndarray of int, shape (N,)
        ``first[inverse[k]]`` has exactly the inputs of step ``k``.

    Notes
    -----
    At a stop the vehicle's state, hence ``F`` and ``Q_c``, repeats step
    after step (726 of the flagship's 1800 steps): a discretisation is a
    function of its step's inputs alone, so computing each run of equal
    steps once is exact.  Non-finite entries never compare equal, so a bad
    step is always computed (and reported) itself.
    """
    N = np.shape(stacks[0])[0]
    same = np.ones(max(N - 1, 0), bool)
    for X in stacks:
        X = np.asarray(X)
        X = X.reshape(N, -1) if X.ndim != 1 else X[:, None]
        same &= (X[1:] == X[:-1]).all(axis=1)
    head = np.r_[True, ~same] if N else np.zeros(0, bool)
    return np.flatnonzero(head), np.cumsum(head) - 1


def _dedup(fn, F, others, dt, times, expand):
    """``fn(F, *others, dt, times)`` computed on the distinct steps only, then expanded (exact).

    ``others`` are ``(array, per-step ndim)`` pairs: a stack of the same
    length as ``F``, or one per-step value shared by every step.  A
    step that fails is recomputed on the full stack, so that the error
    names the step of the caller's grid.
    """
    F = np.asarray(F, float)
    if F.ndim != 3 or F.shape[0] < 2:
        return fn(F, *(o for o, _ in others), dt, times)
    N = F.shape[0]
    try:
        dtb = np.broadcast_to(np.asarray(dt, float), (N,))
        oth = [np.broadcast_to(np.asarray(o, float), (N,) + np.shape(o)) if np.ndim(o) == nd
               else np.asarray(o, float) for o, nd in others]
        if any(o.shape[0] != N for o in oth):
            return fn(F, *(o for o, _ in others), dt, times)
    except ValueError:
        return fn(F, *(o for o, _ in others), dt, times)
    first, inv = repeated_steps(F, *oth, dtb)
    if first.size > 0.9 * N:
        return fn(F, *(o for o, _ in others), dt, times)
    tm = None if times is None else np.broadcast_to(np.asarray(times, float), (N,))[first]
    try:
        out = fn(F[first], *(o[first] for o in oth), dtb[first], tm)
    except (NumericalError, ValueError):
        return fn(F, *(o for o, _ in others), dt, times)
    return expand(out, inv)


def _step_where(what, k, dt, times):
    t = f"t = {times[k]:.6g} s, " if times is not None else ""
    return f"{what + ': ' if what else ''}step {k} ({t}Δt = {dt[k]:.6g} s)"


def _prepare(F, Qc, dt, what, times):
    F = np.asarray(F, float)
    if F.ndim != 3 or F.shape[1] != F.shape[2]:
        raise ValueError(f"F must have shape (N, n, n), got {F.shape}")
    N, n, _ = F.shape
    Qc = np.broadcast_to(np.asarray(Qc, float), F.shape)
    dt = np.broadcast_to(np.asarray(dt, float), (N,))
    if times is not None:
        times = np.broadcast_to(np.asarray(times, float), (N,))
    for name, X in (("F", F), ("Q_c", Qc)):
        bad = ~np.isfinite(X).all(axis=(1, 2))
        if bad.any():
            raise NumericalError(f"{_step_where(what, int(np.argmax(bad)), dt, times)}: {name} has non-finite entries")
    bad = ~(np.isfinite(dt) & (dt >= 0))
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(f"{_step_where(what, k, dt, times)}: the step must be finite and non-negative")
    Qs = Qc + np.swapaxes(Qc, 1, 2)
    Qs *= 0.5
    return F, Qs, dt, times


def balancing(F: np.ndarray) -> np.ndarray:
    """Diagonal scaling that balances a stack of dynamics matrices.

    Parameters
    ----------
    F : ndarray, shape (N, n, n)

    Returns
    -------
    ndarray, shape (n,)
        Powers of two ``d``: ``F̃ = D⁻¹ F D`` with ``D = diag(d)`` has rows
        and columns of comparable norm (LAPACK ``gebal`` applied to
        ``max_k |F_k|``, so one ``D`` serves every step).
    """
    E = np.max(np.abs(F), axis=0)
    if not np.any(E):
        return np.ones(F.shape[1])
    _, (d, _) = matrix_balance(E, permute=False, separate=True)
    return np.asarray(d, float)


def _balanced(F, Qc, d):
    B = F * (d[None, :] / d[:, None])
    Qb = Qc * (1.0 / (d[:, None] * d[None, :]))
    absB = np.abs(B)
    nu = np.maximum(absB.sum(axis=-2).max(axis=-1), absB.sum(axis=-1).max(axis=-1))
    return B, Qb, nu


def _unbalance(Phi, Qd, d):
    Phi *= d[:, None] / d[None, :]
    Qd *= d[:, None] * d[None, :]
    return Phi, Qd


def _fro(X):
    return np.sqrt(np.einsum("kij,kij->k", X, X))


def _colmax(X):
    """Largest column 2-norm of each matrix of a stack."""
    return np.sqrt(np.einsum("kij,kij->kj", X, X).max(axis=1))


def reach(B: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """States reached from ``seed`` through the couplings of ``B``.

    Parameters
    ----------
    B : ndarray, shape (N, n, n)
        Dynamics (``B_ij ≠ 0``: state ``j`` drives state ``i``).
    seed : ndarray of bool, shape (N, n) or (N, n, k)

    Returns
    -------
    ndarray of bool, same shape as ``seed``
        True where a path of non-zero couplings leads from a seed state.
    """
    P = B != 0
    R = seed.copy()
    vec = R.ndim == 2
    if vec:
        R = R[:, :, None]
    while True:
        Rn = R | (P @ R)
        if np.array_equal(Rn, R):
            break
        R = Rn
    return R[:, :, 0] if vec else R


def _q_tail_ok(Qt, Qw, rch, r):
    """Tail of ``Q_d`` below ``2⁻⁵³ √(Q_ii Q_jj)`` element by element (see :func:`_series`)."""
    dg = np.einsum("kii->ki", Qw)
    tr = dg.sum(axis=1, keepdims=True)
    started = np.all(~rch | (dg > 0), axis=1)
    s = np.sqrt(np.where(rch, np.maximum(dg, 1e-32 * tr), 1.0))
    X = np.abs(Qt) / s[:, :, None] / s[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        return started & (X.max(axis=(1, 2)) * r / (1.0 - r) <= UNIT_ROUNDOFF)


def _series(B, Qb, h, nu, order=None, minus_identity=False):
    """Partial sums of eq (6b)–(6d) for ``B h``; adaptive when ``order`` is None.

    Returns ``Φ, Q_d, terms, converged`` (``Φ − I`` instead of ``Φ`` with
    ``minus_identity``: the squaring of :func:`_finish` keeps it apart from
    the identity so that the small increments of a very short base step are
    not rounded away).  In the adaptive case a step stops
    once the bound of its remaining tail is below ``2⁻⁵³`` of the sum:

    * Φ, column by column: ``T_{i+1} = (Bh/(i+1)) T_i`` so the tail of
      column ``j`` is at most ``‖T_i e_j‖ r/(1−r)``, ``r = a/(i+1)``,
      ``a = νh ≥ ‖Bh‖₂``, and ``‖Φ e_j‖ ≥ 2 − e^a``;
    * Q_d, element by element in correlation scaling: every state the noise
      reaches (:func:`reach`) has a variance, and the last term times
      ``r/(1−r)``, ``r = 2a/(i+1)``, is below ``2⁻⁵³ √(Q_ii Q_jj)``
      (``‖C_i‖ ≤ 2‖B‖₂‖C_{i−1}‖``: the norm of the tail is so bounded, and
      each element's terms decay with it once the element has started).
    """
    N, n, _ = B.shape
    eye = np.broadcast_to(np.eye(n), B.shape)
    Phi = np.zeros_like(B) if minus_identity else eye.copy()
    Q = np.zeros_like(B)
    adaptive = order is None
    last = MAX_TERMS if adaptive else order
    terms = np.full(N, 0 if adaptive else last, dtype=int)
    done = np.zeros(N, bool)
    if not adaptive and order <= 1:
        return Phi, Q, terms, np.ones(N, bool)
    idx = np.arange(N)                                  # steps still summing
    Bw, hw = B, h[:, None, None]
    T = eye.copy()
    C = Qb.copy()
    coef = hw.copy()                                    # h^i / i!
    Pw, Qw = Phi.copy(), Q.copy()
    a = nu * h
    phi_floor = UNIT_ROUNDOFF * (2.0 - np.exp(np.minimum(a, 1.0)))
    rch = reach(B, np.einsum("kii->ki", Qb) > 0) if adaptive else None
    # no noise (a transition alone): every C_i is zero, skip eq (6c)-(6d)
    noise = bool(np.any(Qb))
    for i in range(1, last):
        T = (Bw @ T) * (hw / i)                         # (6b): F^i h^i / i!
        Pw += T
        if noise:
            Qt = C * coef                               # (6c): C_{i−1} h^i / i!
            Qw += Qt
        if i == last - 1:
            break
        if noise:
            FC = Bw @ C                                 # (6d)
            C = FC + np.swapaxes(FC, 1, 2)
        coef = coef * hw / (i + 1)
        if adaptive:
            ai = a[idx]
            rp, rq = ai / (i + 1), 2.0 * ai / (i + 1)
            with np.errstate(divide="ignore", invalid="ignore"):
                ok = ((rq < 1.0) & (_colmax(T) * rp / (1.0 - rp) <= phi_floor[idx]))
                if noise:
                    ok &= _q_tail_ok(Qt, Qw, rch[idx], rq)
            if ok.any():
                fin = idx[ok]
                Phi[fin], Q[fin], terms[fin], done[fin] = Pw[ok], Qw[ok], i + 1, True
                keep = ~ok
                idx = idx[keep]
                if idx.size == 0:
                    break
                Bw, hw, T, C, coef, Pw, Qw = (x[keep] for x in (Bw, hw, T, C, coef, Pw, Qw))
    if not adaptive:
        return Pw, Qw, terms, np.ones(N, bool)
    if idx.size:
        Phi[idx], Q[idx] = Pw, Qw
    return Phi, Q, terms, done


def _square(E, Qd, s):
    """Double the steps ``s`` times: ``Φ ← Φ²``, ``Q ← Φ Q Φᵀ + Q``; ``E = Φ − I`` in, ``Φ`` out.

    ``Φ`` is carried as its off-diagonal part ``X`` and its diagonal, each
    diagonal element either as ``Φ_ii − 1`` (while below ½ in magnitude) or
    as ``Φ_ii``.  With ``Φ = diag(φ) + X`` the square is
    ``diag(φ² + diag(X²)) + offdiag(φX + Xφ + X²)``:

    * near the identity (a very short base step, forced by a stiff Markov
      state), ``φ_ii − 1`` is doubled as ``2d + d²`` instead of being
      rounded away next to 1 (``expm1`` for scalars) and the off-diagonal
      entries keep their relative precision;
    * a decaying mode (``φ_ii → 0``) is squared as ``φ_ii`` itself, so it
      does not lose its digits to the cancellation ``1 + (−1 + tiny)``.
    """
    N, n, _ = E.shape
    idx = np.arange(n)
    X = E.copy()
    d = np.einsum("kii->ki", E).copy()                 # Φ_ii − 1 where `near`, else Φ_ii
    X[:, idx, idx] = 0.0
    near = np.abs(d) < 0.5
    d[~near] += 1.0
    noise = bool(np.any(Qd))
    for j in range(int(s.max(initial=0))):
        m = s > j
        Xm, dm, nm = X[m], d[m], near[m]
        phi = np.where(nm, 1.0 + dm, dm)
        P = Xm.copy()
        P[:, idx, idx] = phi
        with np.errstate(over="ignore", invalid="ignore"):
            if noise:
                Q = P @ Qd[m] @ np.swapaxes(P, 1, 2) + Qd[m]
                Qd[m] = 0.5 * (Q + np.swapaxes(Q, 1, 2))
            X2 = Xm @ Xm
            dx = np.einsum("kii->ki", X2)
            Xn = phi[:, :, None] * Xm + Xm * phi[:, None, :] + X2
            Xn[:, idx, idx] = 0.0
            dn = np.where(nm, 2.0 * dm + dm * dm + dx, dm * dm + dx)
        grow = nm & (np.abs(dn) >= 0.5)
        dn[grow] += 1.0
        X[m], d[m], near[m] = Xn, dn, nm & ~grow
    X[:, idx, idx] = np.where(near, 1.0 + d, d)
    return X, Qd


def _check_result(Phi, Qd, dt, info, what, times, psd):
    bad = ~(np.isfinite(Phi).all(axis=(1, 2)) & np.isfinite(Qd).all(axis=(1, 2)))
    if bad.any():
        k = int(np.argmax(bad))
        raise NumericalError(f"{_step_where(what, k, dt, times)}: Φ or Q_d overflows (νΔt = "
                             f"{info.norm_dt[k]:.4g}: an unstable mode grows beyond the floating-point "
                             "range over this step); use shorter steps or a shorter span")
    if psd:
        check_qd(Qd, what, dt=dt, times=times)


def check_qd(Qd: np.ndarray, what: str = "", *, dt=None, times=None, tol: float = PSD_TOL) -> None:
    """Raise if a stack of ``Q_d`` is not PSD within ``tol``.

    Parameters
    ----------
    Qd : ndarray, shape (N, n, n)
    what : str
        Names the computation in the message.
    dt, times : ndarray, shape (N,), optional
        Step lengths and start times, for the message. [s]
    tol : float
        Tolerance on the smallest eigenvalue of the correlation-scaled
        ``Q_d`` (a Cholesky factorisation of ``R + tol·I``, cheap for stacks).

    Raises
    ------
    NumericalError
        Naming the first failing step.
    """
    N, n, _ = Qd.shape
    dg = np.einsum("kii->ki", Qd)
    dt = np.broadcast_to(np.nan if dt is None else np.asarray(dt, float), (N,))
    neg = (dg < -tol * np.maximum(np.max(np.abs(dg), axis=1, keepdims=True), np.finfo(float).tiny)).any(axis=1)
    sd = np.sqrt(np.clip(dg, 0.0, None))
    s = np.where(sd > 0, sd, 1.0)
    R = Qd / s[:, :, None] / s[:, None, :]
    idx = np.arange(n)
    R[:, idx, idx] = np.where(sd > 0, 1.0, 0.0) + tol
    try:
        np.linalg.cholesky(R)
        ok = ~neg
    except np.linalg.LinAlgError:
        ok = np.array([_chol_ok(R[k]) for k in range(N)]) & ~neg
    if not ok.all():
        k = int(np.argmax(~ok))
        w = np.linalg.eigvalsh(0.5 * (R[k] + R[k].T)).min() - tol
        raise NumericalError(f"{_step_where(what, k, dt, times)}: Q_d is not positive semi-definite "
                             f"(smallest eigenvalue of its correlation matrix {w:.3g})")


def _chol_ok(A):
    try:
        np.linalg.cholesky(A)
        return True
    except np.linalg.LinAlgError:
        return False


def scaling(nu, dt):
    """Squarings ``s`` and base steps ``h = Δt/2^s`` with ``νh ≤ θ``.

    Parameters
    ----------
    nu : ndarray, shape (N,)
        ``max(‖F̃‖₁, ‖F̃‖_∞)`` of the balanced dynamics. [1/s]
    dt : ndarray, shape (N,)
        Step lengths. [s]

    Returns
    -------
    s : ndarray of int, shape (N,)
    h : ndarray, shape (N,)
    """
    a = nu * dt
    with np.errstate(divide="ignore"):
        s = np.where(a > THETA, np.ceil(np.log2(np.where(a > 0, a, 1.0) / THETA)), 0).astype(int)
    return s, dt / 2.0**s


def _not_converged(done, what, dt, times, nu, h):
    if not done.all():
        k = int(np.argmax(~done))
        raise NumericalError(f"{_step_where(what, k, dt, times)}: the series of eq (6b)-(6d) did not "
                             f"converge in {MAX_TERMS} terms at νh = {nu[k] * h[k]:.3g}")


def _finish(E, Qd, s, d, terms, nu, dt, what, times):
    Phi, Qd = _square(E, Qd, s)
    Phi, Qd = _unbalance(Phi, Qd, d)
    info = StepInfo(terms, s, nu * dt)
    _check_result(Phi, Qd, dt, info, what, times, psd=True)
    return Phi, Qd, info


def sensor_states(F, Qc) -> np.ndarray:
    """States whose ``F`` and ``Q_c`` rows hold only a diagonal entry at every step.

    Random constants (zero row, no noise), random walks and first-order
    Gauss–Markov sensor states: no other state drives them and their noise
    is uncorrelated with the others'.  Moved after the others they make
    ``F = [[A, M], [0, diag(d)]]`` and ``Q_c = blockdiag(Q_A, diag(q))``,
    the form :func:`block_triangular` discretises by blocks.

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    n = F.shape[-1]
    off = ~np.eye(n, dtype=bool)
    return ~(((F != 0) & off).any(axis=(0, 2)) | ((Qc != 0) & off).any(axis=(0, 2)))


#: use the block path of :func:`_exact` when at least this fraction of the states are sensor states
BLOCK_FRACTION = 0.25


def _exact(F, Qc, dt, what, times):
    F, Qc, dt, times = _prepare(F, Qc, dt, what, times)
    sens = sensor_states(F, Qc)
    k = int(np.count_nonzero(~sens))
    if 1 <= k and sens.sum() >= BLOCK_FRACTION * F.shape[1]:
        # the same converged series by blocks (O(k² m) per term instead of O(n³)); exact
        p = np.r_[np.flatnonzero(~sens), np.flatnonzero(sens)]
        ip = np.argsort(p)
        Phi, Qd, inf = _block_triangular(F[:, p][:, :, p], Qc[:, p][:, :, p], dt, k, what, times)
        return Phi[:, ip][:, :, ip], Qd[:, ip][:, :, ip], inf
    d = balancing(F)
    B, Qb, nu = _balanced(F, Qc, d)
    s, h = scaling(nu, dt)
    E, Qd, terms, done = _series(B, Qb, h, nu, minus_identity=True)
    _not_converged(done, what, dt, times, nu, h)
    return _finish(E, Qd, s, d, terms, nu, dt, what, times)


def _block_series(A, M, dd, QA, q, h, nu, rch):
    """The adaptive series of :func:`_series` for ``[[A, M], [0, diag(dd)]]`` by blocks.

    ``Q_c = blockdiag(QA, diag(q))``.  ``T_i`` and ``C_i`` keep the block
    form: ``T = [[TA, TM], [0, diag(TD)]]``, ``C = [[CA, CX], [CXᵀ, diag(CS)]]``
    with ``TA' = A TA``, ``TM' = A TM + M diag(TD)``, ``TD' = d TD`` (times
    ``h/i``) and ``CA' = (A CA + M CXᵀ) + (·)ᵀ``, ``CX' = A CX + M CS + CX D``,
    ``CS' = 2 d CS``.  Same stopping rule, with the norms taken by blocks.
    """
    N, k, _ = A.shape
    m = dd.shape[1]
    hw = h[:, None, None]
    TA = np.broadcast_to(np.eye(k), (N, k, k)).copy()
    TM = np.zeros((N, k, m))
    TD = np.ones((N, m))
    CA, CX, CS = QA.copy(), np.zeros((N, k, m)), q.copy()
    # the sums start from the i = 1 terms: Φ − I (see _square)
    out = [np.zeros((N, k, k)), TM.copy(), np.zeros((N, m)), np.zeros((N, k, k)), np.zeros((N, k, m)),
           np.zeros((N, m))]
    work = [x.copy() for x in out]
    coef = hw.copy()
    a = nu * h
    phi_floor = UNIT_ROUNDOFF * (2.0 - np.exp(np.minimum(a, 1.0)))
    terms = np.zeros(N, int)
    done = np.zeros(N, bool)
    idx = np.arange(N)
    Aw, Mw, dw = A, M, dd
    for i in range(1, MAX_TERMS):
        f = hw / i
        TM = (Aw @ TM + Mw * TD[:, None, :]) * f
        TA = (Aw @ TA) * f
        TD = TD * dw * f[:, :, 0]
        QtA, QtX, QtS = CA * coef, CX * coef, CS * coef[:, :, 0]
        for x, y in zip(work, (TA, TM, TD, QtA, QtX, QtS)):
            x += y
        AC = Aw @ CA + Mw @ np.swapaxes(CX, 1, 2)
        CX = Aw @ CX + Mw * CS[:, None, :] + CX * dw[:, None, :]
        CA = AC + np.swapaxes(AC, 1, 2)
        CS = 2.0 * dw * CS
        coef = coef * hw / (i + 1)
        ai = a[idx]
        rp, rq = ai / (i + 1), 2.0 * ai / (i + 1)
        col = np.maximum(np.einsum("kij,kij->kj", TA, TA).max(axis=1),
                         (np.einsum("kij,kij->kj", TM, TM) + TD**2).max(axis=1, initial=0.0))
        dg = np.concatenate([np.einsum("kii->ki", work[3]), work[5]], axis=1)
        rc = rch[idx]
        started = np.all(~rc | (dg > 0), axis=1)
        sd = np.sqrt(np.where(rc, np.maximum(dg, 1e-32 * dg.sum(axis=1, keepdims=True)), 1.0))
        sa, ss = sd[:, :k], sd[:, k:]
        X = np.maximum((np.abs(QtA) / sa[:, :, None] / sa[:, None, :]).max(axis=(1, 2)),
                       (np.abs(QtX) / sa[:, :, None] / ss[:, None, :]).max(axis=(1, 2), initial=0.0))
        X = np.maximum(X, (np.abs(QtS) / ss**2).max(axis=1, initial=0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            ok = ((rq < 1.0) & (np.sqrt(col) * rp / (1.0 - rp) <= phi_floor[idx]) & started
                  & (X * rq / (1.0 - rq) <= UNIT_ROUNDOFF))
        if ok.any():
            fin = idx[ok]
            for x, y in zip(out, work):
                x[fin] = y[ok]
            terms[fin], done[fin] = i + 1, True
            keep = ~ok
            idx = idx[keep]
            if idx.size == 0:
                break
            work = [x[keep] for x in work]
            Aw, Mw, dw, hw, coef, TA, TM, TD, CA, CX, CS = (
                x[keep] for x in (Aw, Mw, dw, hw, coef, TA, TM, TD, CA, CX, CS))
    if idx.size:
        for x, y in zip(out, work):
            x[idx] = y
    PA, PM, PD, SA, SX, SS = out
    n = k + m
    Phi = np.zeros((N, n, n))
    Q = np.zeros((N, n, n))
    Phi[:, :k, :k], Phi[:, :k, k:] = PA, PM
    Phi[:, k:, k:] = PD[:, :, None] * np.eye(m)
    Q[:, :k, :k], Q[:, :k, k:], Q[:, k:, :k] = SA, SX, np.swapaxes(SX, 1, 2)
    Q[:, k:, k:] = SS[:, :, None] * np.eye(m)
    return Phi, Q, terms, done        # Φ − I (the sums start from the i = 1 terms)


def is_block_triangular(F, Qc, k: int) -> bool:
    """True if ``F = [[A, M], [0, diag(d)]]`` and ``Q_c = blockdiag(Q_A, diag(q))`` after ``k`` states."""
    F = np.asarray(F)
    Qc = np.asarray(Qc)
    n = F.shape[-1]
    off = ~np.eye(n - k, dtype=bool)
    return not (np.any(F[:, k:, :k]) or np.any(F[:, k:, k:][:, off]) or np.any(Qc[:, :k, k:])
                or np.any(Qc[:, k:, k:][:, off]))


def block_triangular(F, Qc, dt, k: int, *, what: str = "", times=None, info: bool = False):
    """Exact ``Φ, Q_d`` of a navigation block driven by scalar sensor states.

    The adaptive series of :func:`taylor` (exact for any step, module
    notes) with its products done by blocks: ``O(k² m)`` per term instead
    of ``O(n³)`` (five times faster for a 10 + 36-state IMU grade model).

    Parameters
    ----------
    F : ndarray, shape (N, n, n)
        ``[[A, M], [0, diag(d)]]``: ``k`` navigation states, ``n − k``
        random-constant, random-walk or first-order Markov sensor states.
    Qc : ndarray, shape (N, n, n)
        ``blockdiag(Q_A, diag(q))``.
    dt : float or ndarray, shape (N,)
        Step lengths. [s]
    k : int
        Navigation states (the first ones).
    what, times, info
        As :func:`taylor`.

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)
    info : StepInfo
        Only with ``info=True``.

    Raises
    ------
    ValueError
        ``F`` or ``Qc`` does not have this structure
        (:func:`is_block_triangular`).
    NumericalError
        As :func:`taylor`.
    """
    Phi, Qd, inf = _dedup(lambda F_, Q_, dt_, t_: _block_triangular(F_, Q_, dt_, k, what, t_), F, [(Qc, 2)], dt,
                          times, _expand_phi_qd)
    return (Phi, Qd, inf) if info else (Phi, Qd)


def _block_triangular(F, Qc, dt, k, what, times):
    F, Qc, dt, times = _prepare(F, Qc, dt, what, times)
    if not is_block_triangular(F, Qc, k):
        raise ValueError(f"F, Q_c are not block triangular with a diagonal sensor block after {k} states")
    d = balancing(F)
    B, Qb, nu = _balanced(F, Qc, d)
    s, h = scaling(nu, dt)
    rch = reach(B, np.einsum("kii->ki", Qb) > 0)
    E, Qd, terms, done = _block_series(B[:, :k, :k], B[:, :k, k:], np.einsum("kii->ki", B[:, k:, k:]),
                                       Qb[:, :k, :k], np.einsum("kii->ki", Qb[:, k:, k:]), h, nu, rch)
    _not_converged(done, what, dt, times, nu, h)
    return _finish(E, Qd, s, d, terms, nu, dt, what, times)


def _hilbert(m: int) -> np.ndarray:
    a = np.arange(m)
    return 1.0 / (a[:, None] + a[None, :] + 1.0)


def per_source(F: np.ndarray, G: np.ndarray, psd: np.ndarray, dt, *, what: str = "",
               times=None, groups=None) -> np.ndarray:
    """Exact ``Q_d`` of each column of a low-rank ``Q_c``, any step.

    Parameters
    ----------
    F : ndarray, shape (N, n, n)
    G : ndarray, shape (N, n, k)
    psd : ndarray, shape (N, k)
    dt : float or ndarray, shape (N,)
        Step lengths. [s]
    what : str
        Names the system in error messages.
    times : ndarray, shape (N,), optional
        Start time of each step, for error messages. [s]
    groups : array_like of int, shape (J,), optional
        Increasing first columns of ``J`` groups of columns (as
        ``np.add.reduceat``): return the ``Q_d`` of each group, summed
        without forming the per-column matrices (the same convergence
        rule, column by column).

    Returns
    -------
    ndarray, shape (N, k, n, n), or (N, J, n, n) with ``groups``
        ``Q_d`` of each column ``G[:, :, p]`` with PSD ``psd[:, p]`` (or of
        each group of columns); they sum to the ``Q_d`` of
        ``Q_c = G diag(psd) Gᵀ``.

    Raises
    ------
    NumericalError
        Non-finite input or result, a series that does not converge, or a
        total ``Q_d`` that is not PSD, naming the step.

    Notes
    -----
    ``Q_d = ∫₀^Δt e^{Fs} G W Gᵀ e^{Fᵀs} ds`` (the Van Loan integral).  With
    ``Ŷ_a = F^a G h^a / a!`` and ``e^{Fs} G = Σ_a Ŷ_a (s/h)^a``::

        Q_d(h) = h Σ_{a,b} Ŷ_a W Ŷ_bᵀ / (a + b + 1)

    which collects the terms of seed 002 eq (6c)–(6d) (``C_{i−1} h^i/i!``
    with ``C_{i−1} = Σ_{a+b=i−1} binom(i−1, a) F^a Q_c Fᵀ^b``) by source
    column instead of by order.  It is linear in ``W`` term by term, costs
    ``n × k`` products instead of ``n × n`` per order, and, the coefficient
    matrix being a Hilbert (Gram) matrix, is positive semi-definite for any
    truncation.  It is evaluated as :func:`covtool.lincov.discretize.taylor` does
    (module notes there): on the balanced system, at ``h = Δt/2^s`` with
    ``νh ≤ θ``, each column summed until the tail of ``Σ_a Ŷ_a`` is provably
    small (``‖Ŷ_{a+1}‖ ≤ ‖Ŷ_a‖ νh/(a+1)``): below ``2⁻⁵³ √(min_r Q_rr/(wh))/2``
    over the states ``r`` the column reaches, which bounds every element's
    error by ``2⁻⁵³ √(Q_ii Q_jj)``; then doubled ``s`` times with
    ``Q_j(2h) = Φ(h) Q_j(h) Φ(h)ᵀ + Q_j(h)``.
    """
    return _dedup(lambda F_, G_, p_, dt_, t_: _per_source(F_, G_, p_, dt_, what, t_, groups), F,
                  [(G, 2), (psd, 1)], dt, times, lambda Q, inv: Q[inv])


def _per_source(F, G, psd, dt, what, times, groups=None):
    F, Qc0, dt, times = _prepare(F, np.zeros(np.shape(F)), dt, what, times)
    N, n, _ = F.shape
    G = np.asarray(G, float)
    psd = np.asarray(psd, float)
    for name, X in (("G", G), ("psd", psd)):
        bad = ~np.isfinite(X.reshape(N, -1)).all(axis=1)
        if bad.any():
            k = int(np.argmax(bad))
            raise NumericalError(f"{_step_where(what, k, dt, times)}: {name} has non-finite entries")
    d = balancing(F)
    B, _, nu = _balanced(F, Qc0, d)
    s, h = scaling(nu, dt)
    hw = h[:, None, None]
    Y = G / d[None, :, None]
    terms = [Y]
    c0 = np.sqrt(np.einsum("kip,kip->kp", Y, Y))       # (N, k) column norms
    a = (nu * h)[:, None]
    rch = reach(B, Y != 0)                               # (N, n, k)
    eps = UNIT_ROUNDOFF * c0                             # first pass: relative to ‖Ŷ_0‖

    def extend(eps):
        while len(terms) < MAX_TERMS:
            i = len(terms) - 1
            r = a / (i + 1)
            with np.errstate(divide="ignore", invalid="ignore"):
                tail = np.sqrt(np.einsum("kip,kip->kp", terms[-1], terms[-1])) * r / (1.0 - r)
            done = np.all((r < 1.0) & (tail <= eps), axis=1)
            if done.all():
                return done
            terms.append((B @ terms[-1]) * (hw / (i + 1)))
        return done

    def weighted():
        m = len(terms)
        Z = np.array(terms)                                 # (m, N, n, k): one GEMM with the Hilbert matrix
        ZH = (_hilbert(m) @ Z.reshape(m, -1)).reshape(Z.shape)
        ZH *= (psd * h[:, None])[None, :, None, :]
        return Z, ZH

    def assemble(Z, ZH):
        # Q_j = Σ_{p ∈ j} w_p Z_p H Z_pᵀ: one (n, m·|j|) × (m·|j|, n) product per group (column) and step
        k = G.shape[2]
        bounds = np.r_[np.arange(k) if groups is None else np.asarray(groups, int), k]
        Q = np.empty((N, len(bounds) - 1, n, n))
        m = Z.shape[0]
        Zt = np.ascontiguousarray(Z.transpose(1, 2, 3, 0))     # (N, n, k, m): a group's columns are one view
        ZHt = np.ascontiguousarray(ZH.transpose(1, 2, 3, 0))
        for j, (a0, b0) in enumerate(zip(bounds[:-1], bounds[1:])):
            A = ZHt[:, :, a0:b0].reshape(N, n, (b0 - a0) * m)
            Bz = Zt[:, :, a0:b0].reshape(N, n, (b0 - a0) * m)
            Qj = A @ np.swapaxes(Bz, 1, 2)
            Q[:, j] = 0.5 * (Qj + np.swapaxes(Qj, 1, 2))
        return Q

    m_done = 0
    for _ in range(3):
        done = extend(eps)
        _not_converged(done, what, dt, times, nu, h)
        if len(terms) == m_done:                            # no new term: the same Q_d, converged
            break
        m_done = len(terms)
        Z, ZH = weighted()
        dg = np.einsum("akip,akip->kpi", ZH, Z)             # diagonal of each column's Q_d
        # correlation scaling: ‖δ(s)‖ ≤ tail on [0, h] gives |ΔQ_ij| ≤ tail √(wh) (√Q_ii + √Q_jj) + …
        qmin = np.where(np.swapaxes(rch, 1, 2), dg, np.inf).min(axis=2)
        wh = np.where(psd > 0, psd, 1.0) * h[:, None]
        with np.errstate(invalid="ignore"):
            need = 0.5 * UNIT_ROUNDOFF * np.sqrt(np.maximum(np.where(np.isfinite(qmin), qmin, 0.0) / wh,
                                                            1e-32 * c0**2))
        need = np.where(psd > 0, need, np.inf)
        if np.all(need >= eps):
            break
        eps = np.minimum(eps, need)
    Q = assemble(Z, ZH)
    if s.any():
        sq = s > 0
        Phi, _, _, ok = _series(B[sq], np.zeros_like(B[sq]), h[sq], nu[sq])
        _not_converged(ok, what, dt[sq], None if times is None else times[sq], nu[sq], h[sq])
        Qs = Q[sq]
        for j in range(int(s.max())):
            mj = s[sq] > j
            P = Phi[mj][:, None]
            with np.errstate(over="ignore", invalid="ignore"):
                X = P @ Qs[mj] @ np.swapaxes(P, -1, -2) + Qs[mj]
                Qs[mj] = 0.5 * (X + np.swapaxes(X, -1, -2))
                Phi[mj] = Phi[mj] @ Phi[mj]
        Q[sq] = Qs
    Q *= (d[:, None] * d[None, :])
    tot = Q.sum(axis=1)
    bad = ~np.isfinite(tot).all(axis=(1, 2))
    if bad.any():
        k = int(np.argmax(bad))
        raise NumericalError(f"{_step_where(what, k, dt, times)}: Q_d overflows (νΔt = {nu[k] * dt[k]:.4g})")
    check_qd(tot, what, dt=dt, times=times)
    return Q


# ---------------------------------------------------------------------------
# public


def van_loan(F: np.ndarray, Qc: np.ndarray, dt, *, what: str = "", times=None, info: bool = False):
    """Exact discretisation: Van Loan's ``Φ`` and ``Q_d`` for any step.

    Parameters
    ----------
    F : ndarray, shape (N, n, n)
        Continuous dynamics matrix, constant over each step.
    Qc : ndarray, shape (N, n, n)
        Continuous noise PSD ``G W Gᵀ``.
    dt : float or ndarray, shape (N,)
        Step lengths. [s]
    what : str
        Names the computation in error messages.
    times : ndarray, shape (N,), optional
        Start time of each step, for error messages. [s]
    info : bool
        Also return a :class:`StepInfo`.

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)
    info : StepInfo
        Only with ``info=True``.

    Raises
    ------
    NumericalError
        Non-finite input, or ``Φ``/``Q_d`` not representable (overflow of an
        unstable mode), naming the step.

    Notes
    -----
    ``Φ = e^{FΔt}`` and ``Q_d = ∫₀^Δt e^{Fs} Q_c e^{Fᵀs} ds`` (Van Loan 1978),
    computed by balancing, scaling, the converged series and squaring
    (module notes); the same numbers as ``taylor(order=None)``.
    """
    Phi, Qd, inf = _dedup(lambda F_, Q_, dt_, t_: _exact(F_, Q_, dt_, what, t_), F, [(Qc, 2)], dt, times,
                          _expand_phi_qd)
    return (Phi, Qd, inf) if info else (Phi, Qd)


def _expand_phi_qd(out, inv):
    Phi, Qd, inf = out
    return Phi[inv], Qd[inv], StepInfo(inf.terms[inv], inf.squarings[inv], inf.norm_dt[inv])


def taylor(F: np.ndarray, Qc: np.ndarray, dt, order: int | None = None, *, what: str = "", times=None,
           info: bool = False):
    """Seed 002's Taylor-series discretisation, eq (6b)–(6d).

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)
    dt : float or ndarray, shape (N,)
        Step lengths. [s]
    order : int, optional
        Number of terms ``N_t`` of eq (6b) (``i = 0 … N_t−1``), the paper's
        truncation over the whole step.  Default: the adaptive series, exact
        for any step (module notes).
    what : str
        Names the filter or system in error messages.
    times : ndarray, shape (N,), optional
        Start time of each step, for error messages. [s]
    info : bool
        Also return a :class:`StepInfo` (the terms used per step).

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)
    info : StepInfo
        Only with ``info=True``.

    Raises
    ------
    InputError
        A fixed ``order`` whose series diverges at some step
        (``2νΔt ≥ N_t``, module notes), naming the step, ``νΔt`` and what to
        change; an ``order`` that is not an integer in ``1 … 100``.
    NumericalError
        Non-finite input or result, naming the step.

    Notes
    -----
    With the scan's Π read as Σ (see BRIEF)::

        Φ   = Σ_{i=0}^{n−1} F^i Δt^i / i!                      (6b)
        Q_d = Σ_{i=1}^{n−1} C_{i−1} Δt^i / i!                  (6c)
        C_0 = Qc,  C_i = F C_{i−1} + (F C_{i−1})ᵀ              (6d)

    ``C_{i−1}`` is the ``(i−1)``-th derivative of ``e^{Fs} Qc e^{Fᵀs}`` at
    ``s = 0``, so (6c) is the Taylor series of the Van Loan integral.  The
    adaptive series sums them at ``h = Δt/2^s`` until the tail bound is
    below ``2⁻⁵³`` and doubles ``s`` times.
    """
    if order is None:
        Phi, Qd, inf = _dedup(lambda F_, Q_, dt_, t_: _exact(F_, Q_, dt_, what, t_), F, [(Qc, 2)], dt, times,
                              _expand_phi_qd)
        return (Phi, Qd, inf) if info else (Phi, Qd)
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) or not 1 <= order <= MAX_ORDER:
        raise InputError(f"{what + ': ' if what else ''}taylor_order",
                         f"{order!r} is not an integer from 1 to {MAX_ORDER}")
    Phi, Qd, inf = _dedup(lambda F_, Q_, dt_, t_: _taylor_fixed(F_, Q_, dt_, order, what, t_), F, [(Qc, 2)], dt,
                          times, _expand_phi_qd)
    return (Phi, Qd, inf) if info else (Phi, Qd)


def _taylor_fixed(F, Qc, dt, order, what, times):
    F, Qc, dt, times = _prepare(F, Qc, dt, what, times)
    d = balancing(F)
    B, Qb, nu = _balanced(F, Qc, d)
    a = nu * dt
    bad = 2.0 * a >= order
    if bad.any():
        k = int(np.argmax(bad))
        t = f"t = {times[k]:.6g} s, " if times is not None else ""
        raise InputError(
            f"{what + ': ' if what else ''}taylor_order",
            f"the {order}-term Taylor series of eq (6b)-(6d) diverges at step {k} ({t}Δt = {dt[k]:.6g} s): "
            f"νΔt = {a[k]:.4g} ≥ N_t/2 = {order / 2:g} (ν: balanced ‖F‖, the fastest rate of the dynamics, "
            f"{nu[k]:.4g} 1/s), its terms grow instead of shrinking; use dt < {0.5 * order / nu.max():.4g} s, "
            f"taylor_order ≥ {int(np.floor(2.0 * a.max())) + 1}, or the exact discretisation "
            "(no taylor_order, or 'van_loan')")
    Phi, Qd, terms, _ = _series(B, Qb, dt, nu, order)
    Phi, Qd = _unbalance(Phi, Qd, d)
    inf = StepInfo(terms, np.zeros(F.shape[0], int), a)
    _check_result(Phi, Qd, dt, inf, what, times, psd=False)
    return Phi, Qd, inf


def taylor_terms(F: np.ndarray, Qc: np.ndarray, dt) -> StepInfo:
    """Terms and squarings the adaptive eq (6b)–(6d) series takes per step.

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)
    dt : float or ndarray, shape (N,)
        Step lengths. [s]

    Returns
    -------
    StepInfo
    """
    return taylor(F, Qc, dt, info=True)[2]


def discretize(F, Qc, dt, method: str = "van_loan", order: int | None = None, *, what: str = "", times=None):
    """Dispatch to :func:`van_loan` or :func:`taylor`.

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)
    dt : float or ndarray, shape (N,)
        Step lengths. [s]
    method : {"van_loan", "taylor"}
    order : int, optional
        Fixed number of Taylor terms (``method = "taylor"`` only).
    what : str
        Names the system in error messages.
    times : ndarray, shape (N,), optional
        Start time of each step, for error messages. [s]

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)

    Raises
    ------
    ValueError
        Unknown method.
    """
    if method == "van_loan":
        return van_loan(F, Qc, dt, what=what, times=times)
    if method == "taylor":
        return taylor(F, Qc, dt, order, what=what, times=times)
    raise ValueError(f"unknown discretisation {method!r} (one of: van_loan, taylor)")


__all__ = ["StepInfo", "THETA", "BLOCK_FRACTION", "balancing", "block_triangular", "check_qd", "discretize",
           "is_block_triangular",
           "per_source", "reach", "repeated_steps", "scaling", "sensor_states", "taylor", "taylor_terms", "van_loan"]
