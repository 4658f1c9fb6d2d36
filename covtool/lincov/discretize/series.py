"""The series of eq (6b)–(6d) with balancing, scaling, squaring.

Balancing ``F̃ = D⁻¹ F D`` (:func:`balancing`), the scaling ``h = Δt/2^s``
with ``νh ≤ θ`` (:func:`scaling`), the adaptive base-step series of
seed 002, eq (6b)–(6d) summed until its rigorous tail bound is below
``2⁻⁵³`` of the sum (:func:`_series`), and the squaring
``Φ(2h) = Φ(h)²``, ``Q_d(2h) = Φ(h) Q_d(h) Φ(h)ᵀ + Q_d(h)``
(:func:`_square`).  The notes of :mod:`covtool.lincov.discretize` explain
why.
"""
from __future__ import annotations

import numpy as np

from covtool.errors import NumericalError
from covtool.lincov.discretize.steps import StepInfo, _check_result, _step_where
from covtool.lincov.discretize.limits import MAX_ORDER, MAX_TERMS, THETA, UNIT_ROUNDOFF  # noqa: F401 - re-exported


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
    # max_k |F_k| = |max(max_k F_k, −min_k F_k)| exactly: two reductions instead of a temporary |F|
    # of the whole stack (the outer abs makes every zero +0.0, as |F| does)
    E = np.abs(np.maximum(F.max(axis=0), -F.min(axis=0)))
    if not np.any(E):
        return np.ones(F.shape[1])
    from scipy.linalg import matrix_balance        # imported when used: `covtool models` reaches this module

    _, (d, _) = matrix_balance(E, permute=False, separate=True)
    return np.asarray(d, float)


def _balanced(F, Qc, d):
    B = F * (d[None, :] / d[:, None])
    Qb = None if Qc is None else Qc * (1.0 / (d[:, None] * d[None, :]))
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
    if R.shape[2] > R.shape[1]:
        # more seeds than states (a source's columns): the closure of (I | P) by squaring, a few
        # n × n products, then one product with the seeds, instead of an n × k product per path
        # length.  The same set: both are the states some path of couplings leads to.
        C = P | np.eye(P.shape[1], dtype=bool)
        while True:
            Cn = C @ C
            if np.array_equal(Cn, C):
                break
            C = Cn
        R = C @ R
    else:
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
            ok |= hw[:, 0, 0] == 0.0                    # h = 0 (Δt = 0): every term past i = 0 is zero
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


def random_constants(F: np.ndarray, Qc: np.ndarray) -> np.ndarray:
    """States with a zero ``F`` row and no noise at every step: random constants.

    The sensor states (:func:`sensor_states`) whose diagonal entries are zero too.

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    return ~((np.asarray(F) != 0).any(axis=(0, 2)) | (np.asarray(Qc) != 0).any(axis=(0, 2))
             | (np.asarray(Qc) != 0).any(axis=(0, 1)))
