"""Linear Monte Carlo: the null distribution of the ensemble statistics.

The nonlinear Monte Carlo (:mod:`covtool.validation.monte_carlo`) is judged by
statistics of its ensemble mean squares over time (the share of time points
inside the χ² bounds, the time-mean normalised mean square).  Their null
distribution under a correct model is not a textbook law: the time points are
strongly correlated and the drawn constants persist.  This module samples it
directly from the *linear* error-state system of the same setup, which is what
the covariance analysis claims the errors obey:

* between measurements ``x_{k+1} = Φ_k x_k + w_k``, ``w_k ~ N(0, Q_d,k)``
  (seed 002, eq (15));
* at a measurement of the filter ``x ← x − D K (H x + v)``, ``v ~ N(0, R)``,
  with the filter's own gain ``K`` (eq (7)), the truth ``H`` and ``R``
  (eq (16) is the covariance of exactly this recursion).  ``H`` and ``R``
  may be one pair for every update (ZUPT) or one pair per update step
  (declared measurements, issue 15: several kinds stacked, a time-varying
  ``H`` with attitude and lever arms, columns on the measurements' own
  error states appended to the truth).

Each replica is an ensemble of ``M`` runs, like the nonlinear study; the runs
start either from given initial states (the draws of the nonlinear study, for
the conditional comparison: only the driven part is resampled) or from fresh
draws of ``P0``.  All replicas and runs are one matrix ``(n, R·M)``, and the
cases share the driving and measurement noise (common random numbers, as in the
nonlinear ensemble).  The sensor rows of a truth Φ are mostly diagonal
(constants, Markov and random-walk states): the rows with off-diagonal entries
are multiplied as a block, the others elementwise, which is exact.
"""

from __future__ import annotations

import queue
import threading

import numpy as np
from threadpoolctl import threadpool_limits

from covtool.lincov.kalman import covariance_root
from covtool.nav import attitude as quat, earth

__all__ = ["output_rows", "noise_factors", "linear_mean_squares"]


#: the compared quantities and the output rows they sum (rows of :func:`output_rows`)
GROUPS = {"horizontal": (0, 1), "altitude": (2,), "azimuth": (3,)}


def output_rows(lat, h, q_nb) -> np.ndarray:
    """Rows mapping the navigation states to the compared errors.

    Parameters
    ----------
    lat, h : ndarray, shape (N+1,)
        Reference latitude [rad] and height [m].
    q_nb : ndarray, shape (N+1, 4)
        Reference attitude.

    Returns
    -------
    ndarray, shape (N+1, 4, 10)
        North, east, down position error [m] (``δN = (R_M+h) δL``,
        ``δE = (R_N+h) cos L δl``, ``δD = −δh``) and azimuth error [rad]
        (third row of ``φ = −2 R(q)ᵀ δq``) from the ten navigation states
        of seed 002 eq (14).  ``C P Cᵀ`` gives the σ of
        :func:`covtool.analysis.metrics.nav_metrics`.
    """
    lat, h = np.asarray(lat, float), np.asarray(h, float)
    rm, rn = earth.radii(lat)
    C = np.zeros((lat.size, 4, 10))
    C[:, 0, 0] = rm + h
    C[:, 1, 1] = (rn + h) * np.cos(lat)
    C[:, 2, 2] = -1.0
    C[:, 3, 6:10] = quat.attitude_error_matrix(np.asarray(q_nb, float))[:, 2, :]
    return C


def noise_factors(Qd) -> list:
    """Square-root factors ``L_k`` with ``L_k L_kᵀ = Q_d,k``: principal roots, continuous in ``Q_d``.

    Parameters
    ----------
    Qd : ndarray, shape (N, n, n)

    Returns
    -------
    list of ndarray, shape (n, s)
        The principal square root of each step's ``Q_d``
        (:func:`covtool.lincov.kalman.covariance_root`), its columns on the
        ``s`` states with a noise variance at some step (the others are
        zero: 22 of 58 for ``sdins58``, whose ``Q_d`` has rank 19).  Unlike
        an eigenvector factor it is unique where eigenvalues are equal, so
        the draws of one seed change with ``Q_d`` continuously (by
        round-off for a round-off change of the inputs).
    """
    Qd = np.asarray(Qd, float)
    N = Qd.shape[0]
    support = np.flatnonzero(np.any(np.diagonal(Qd, axis1=1, axis2=2) > 0, axis=0)) if N else np.zeros(0, int)
    if support.size == 0:
        return [np.zeros((Qd.shape[1], 0)) for _ in range(N)]
    # 1800 small eigenproblems: OpenBLAS's thread pool only adds contention (20x slower on a loaded machine)
    with threadpool_limits(limits=1, user_api="blas"):
        S = covariance_root(Qd, support)
    return [np.ascontiguousarray(x) for x in S]


def _split_mask(Phi) -> np.ndarray:
    """Off-diagonal entries of a stack of Φ that are non-zero at some step, shape (n, n) of bool."""
    n = Phi.shape[1]
    return np.abs(Phi).max(axis=0) * (1.0 - np.eye(n)) > 0


def _split_rows(off):
    """Rows with off-diagonal entries (:func:`_split_mask`) and the diagonal rest."""
    dense = np.flatnonzero(off.any(axis=1))
    diag = np.setdiff1d(np.arange(off.shape[0]), dense)
    return dense, diag


#: steps of Φ and Q_d read at once by :func:`linear_mean_squares`
READ_CHUNK = 600


def _read_chunks(Phi, Qd, N: int, size: int = READ_CHUNK):
    """``(a, b, Φ[a:b], Q_d[a:b])`` over the steps: slices of whole-grid stacks, or a streamed system's steps
    (:class:`covtool.lincov.streamed.StreamedSystem`, read one step at a time) stacked a chunk at a time."""
    for a in range(0, N, size):
        b = min(N, a + size)
        if isinstance(Phi, np.ndarray) and isinstance(Qd, np.ndarray):
            yield a, b, Phi[a:b], np.asarray(Qd[a:b], float)
        else:
            yield a, b, np.stack([Phi[k] for k in range(a, b)]), np.stack([Qd[k] for k in range(a, b)])


def _per_step(H, R, upd, n):
    """``{k: (H_k, chol R_k)}`` over the update steps, from one pair or per-step dicts.

    One pair (arrays) serves every step with one Cholesky factor (the ZUPT
    case, unchanged); dicts give each update step its own pair.
    """
    if not upd:
        return {}
    if H is None or R is None:
        raise ValueError("linear_mean_squares: H and R are required with updates")
    if isinstance(H, dict) != isinstance(R, dict):
        raise ValueError("linear_mean_squares: give H and R both as arrays or both as dicts of update steps")
    if not isinstance(H, dict):
        H = np.asarray(H, float)
        Lr = np.linalg.cholesky(np.asarray(R, float))
        if H.ndim != 2 or H.shape[1] != n or Lr.shape[0] != H.shape[0]:
            raise ValueError(f"linear_mean_squares: H has shape {H.shape} and R {Lr.shape}, expected (m, {n}) "
                             "and (m, m)")
        return {k: (H, Lr) for k in upd}
    missing = [k for k in upd if k not in H or k not in R]
    if missing:
        raise ValueError(f"linear_mean_squares: no H or R at update step {missing[0]}")
    out = {}
    for k in upd:
        Hk, Rk = np.asarray(H[k], float), np.asarray(R[k], float)
        if Hk.ndim != 2 or Hk.shape[1] != n or Rk.shape != (Hk.shape[0],) * 2:
            raise ValueError(f"linear_mean_squares: at update step {k} H has shape {Hk.shape} and R {Rk.shape}, "
                             f"expected (m, {n}) and (m, m)")
        out[k] = (Hk, np.linalg.cholesky(Rk))
    return out


def linear_mean_squares(Phi, Qd, cases, C, *, runs: int, replicas: int, rng, x0=None, P0=None, H=None, R=None,
                        factors=None, block: int = 20000, groups=None) -> dict:
    """Ensemble mean squares of replicas of a linear Monte Carlo.

    Parameters
    ----------
    Phi, Qd : ndarray, shape (N, n, n), or streamed stacks
        Truth transition and noise (seed 002, eq (15)): whole-grid stacks,
        or a :class:`covtool.lincov.streamed.StreamedSystem`'s ``Phi``,
        ``Qd`` (read a chunk of :data:`READ_CHUNK` steps at a time; nothing of
        size N × n² is made).
    cases : dict of str to dict of int to ndarray or None
        For each case the correction gain at each update step ``k``:
        ``G_k = D K_k`` (n × m; eq (10), (16)); ``None`` or ``{}``: pure INS.
    C : ndarray, shape (N+1, 4, p)
        :func:`output_rows` (``p = 10``): north, east, down, azimuth rows
        acting on the first ``p`` states.
    runs : int
        Runs M per replica (the study's N).
    replicas : int
    rng : numpy.random.Generator or int
    x0 : ndarray, shape (M, n), optional
        The runs' initial states, the same in every replica (conditional
        null: only the driven part is sampled).
    P0 : ndarray, shape (n, n), optional
        Draw the initial states of every run of every replica from
        ``N(0, P0)`` instead (unconditional null).
    H : ndarray, shape (m, n), or dict of int to ndarray, shape (m_k, n)
        Truth measurement matrix (required with updates): one for every
        update, or one per update step (declared measurements: the truth
        ``H`` of the stacked epoch, error-state columns included).
    R : ndarray, shape (m, m), or dict of int to ndarray, shape (m_k, m_k)
        True measurement noise, as ``H``.
    factors : list of ndarray, optional
        :func:`noise_factors` of ``Qd`` (computed if not given).
    block : int
        Columns (runs × replicas) propagated together (memory
        ``8·n·block`` bytes per case).
    groups : dict of str to tuple of int, optional
        The compared quantities and the rows of ``C`` whose mean squares
        they sum (0 north, 1 east, 2 down, 3 azimuth); default
        :data:`GROUPS`.

    Returns
    -------
    dict of str to ndarray, shape (replicas, N+1, n_groups)
        Per case, the ensemble mean square ``(1/M) Σ_i y_i(t)²`` of each
        group of each replica; by default the horizontal (``δN² + δE²``)
        [m²], altitude [m²] and azimuth [rad²] errors (:data:`GROUPS`
        order).

    Raises
    ------
    ValueError
        Neither or both of ``x0`` and ``P0``; shapes that do not agree;
        updates without ``H`` and ``R`` (or without them at one of the
        update steps).
    """
    if isinstance(Phi, np.ndarray) or not hasattr(Phi, "shape"):
        Phi = np.asarray(Phi, float)
    N, n, _ = Phi.shape
    if (x0 is None) == (P0 is None):
        raise ValueError("linear_mean_squares: give exactly one of x0 (conditional) and P0 (unconditional)")
    if x0 is not None:
        x0 = np.asarray(x0, float)
        if x0.shape != (runs, n):
            raise ValueError(f"linear_mean_squares: x0 has shape {x0.shape}, expected ({runs}, {n})")
    C = np.asarray(C, float)
    if C.ndim != 3 or C.shape[:2] != (N + 1, 4) or C.shape[2] > n:
        raise ValueError(f"linear_mean_squares: C has shape {C.shape}, expected ({N + 1}, 4, p ≤ {n})")
    rng = np.random.default_rng(rng)
    upd = sorted({int(k) for g in cases.values() if g for k in g})
    meas = _per_step(H, R, upd, n)
    groups = dict(GROUPS if groups is None else groups)
    if not groups or any(not rows or any(int(i) not in range(4) for i in rows) for rows in groups.values()):
        raise ValueError(f"linear_mean_squares: groups {groups} must name rows 0..3 of C")
    # Φ and Q_d are read a chunk of steps at a time (whole-grid stacks or streamed systems, read step by
    # step): nothing of size N × n² is made here.  First the structure over every step ...
    off = np.zeros((n, n), bool)
    noisy = np.zeros(n, bool)
    with threadpool_limits(limits=1, user_api="blas"):
        for _, _, Ph, Q in _read_chunks(Phi, Qd, N):
            off |= _split_mask(Ph)
            noisy |= np.any(np.diagonal(Q, axis1=1, axis2=2) > 0, axis=0)
    # states ordered dense rows first, so both parts are contiguous slices (exact: a permutation)
    dense, diag = _split_rows(off)
    # then the diagonal rows that receive noise, so the noise is added to one leading block of rows
    # (a state with a zero Q_d diagonal at every step gets no noise: its row of Q_d, and of L, is zero)
    diag = np.concatenate([diag[noisy[diag]], diag[~noisy[diag]]])
    perm = np.concatenate([dense, diag])
    nw = int(np.flatnonzero(noisy[perm])[-1]) + 1 if noisy.any() else 0
    nd = dense.size
    # ... then per step, in single precision: the statistics need ~1e-3, float32 keeps 1e-7 per step and
    # halves the cost
    f4 = np.float32
    Pd = np.empty((N, nd, n), f4)                                   # the dense rows, permuted columns
    dd = np.empty((N, diag.size), f4)                               # the diagonal of the other rows
    Lp = []
    support = np.flatnonzero(noisy)
    with threadpool_limits(limits=1, user_api="blas"):
        for a, b, Ph, Q in _read_chunks(Phi, Qd, N):
            Pd[a:b] = Ph[:, dense][:, :, perm]
            dd[a:b] = Ph[:, diag, diag]
            if factors is not None:
                Lc = factors[a:b]
            elif support.size:
                Lc = covariance_root(Q, support)                    # noise_factors, a chunk at a time
            else:
                Lc = np.zeros((b - a, n, 0))
            Lp.extend(np.ascontiguousarray(f[perm][:nw], dtype=f4) for f in Lc)
    # the trailing diagonal rows with φ = 1 at every step (random constants, 36 of 58 for sdins58) are
    # left alone: multiplying by 1 is exact, and skipping it saves most of the elementwise traffic
    moving = np.flatnonzero(np.any(dd != 1, axis=0))
    ne = nd + (int(moving[-1]) + 1 if moving.size else 0)
    dd = np.ascontiguousarray(dd[:, :ne - nd])
    G = {c: ({k: np.asarray(g, f4)[perm] for k, g in cases[c].items()} if cases[c] else {}) for c in cases}
    # one converted pair per distinct (H, R) object: the ZUPT case converts its single pair once
    conv = {}
    for k, (Hk, Lk) in meas.items():
        if id(Hk) not in conv:
            conv[id(Hk)] = (np.ascontiguousarray(Hk[:, perm], dtype=f4), Lk.astype(f4))
    meas = {k: conv[id(Hk)] for k, (Hk, _) in meas.items()}
    # output rows act on the ten navigation states; in the permuted order
    Cp = np.zeros((N + 1, 4, n))
    Cp[:, :, np.argsort(perm)[:C.shape[2]]] = C
    used = np.flatnonzero(np.abs(Cp).max(axis=(0, 1)) > 0)
    Cp = np.ascontiguousarray(Cp[:, :, used], dtype=f4)
    used = slice(0, used.size) if np.array_equal(used, np.arange(used.size)) else used
    if P0 is not None:
        L0 = covariance_root(P0)[perm]                          # continuous in P0 (see noise_factors)
    names = list(cases)
    with threadpool_limits(limits=1, user_api="blas"):
        # small matrices: OpenBLAS's thread pool is many times slower than one thread on a loaded machine
        return _sample(names, G, meas, Lp, nw, Pd, dd, nd, ne, Cp, used, N, n, runs, replicas, rng,
                       block, None if x0 is None else x0[:, perm], None if P0 is None else L0,
                       [tuple(int(i) for i in rows) for rows in groups.values()])


def _sample(names, G, meas, Lp, nw, Pd, dd, nd, ne, Cp, used, N, n, runs, replicas, rng, block, x0p, L0, rows):
    out = {c: np.empty((replicas, N + 1, len(rows))) for c in names}
    per = max(1, block // runs)                   # replicas per block
    blocks = [(r0, min(per, replicas - r0)) for r0 in range(0, replicas, per)]
    # the random draws (a third of the work) are made by a second thread, in their one order, while
    # this one propagates the cases: the numbers are those of drawing them in the loop
    draws = _prefetch(_draws([nr * runs for _, nr in blocks], meas, Lp, N, n, rng, L0))
    try:
        for r0, nr in blocks:
            X0 = next(draws) if L0 is not None else np.tile(x0p.T, (1, nr)).astype(np.float32)
            X = {c: X0.copy() for c in names}
            for k in range(N + 1):
                v, W = next(draws)
                if v is not None:
                    Hp = meas[k][0]
                    for c in names:
                        g = G[c].get(k)
                        if g is not None:
                            X[c] -= g @ (Hp @ X[c] + v)
                for c in names:
                    Y = Cp[k] @ X[c][used]
                    Y *= Y
                    ms = Y.reshape(4, nr, runs).mean(axis=2, dtype=np.float64)
                    o = out[c][r0:r0 + nr, k]
                    for j, rs in enumerate(rows):
                        o[:, j] = ms[rs[0]] if len(rs) == 1 else ms[list(rs)].sum(axis=0)
                if k == N:
                    break
                for c in names:
                    x = X[c]
                    top = Pd[k] @ x
                    x[nd:ne] *= dd[k][:, None]
                    x[:nd] = top
                    if W is not None:
                        x[:nw] += W
    finally:
        draws.close()
    return out


def _normal32(rng, shape):
    """``rng.standard_normal(shape, dtype=float32)``, drawn a row at a time.

    The same numbers (the rows fill in order); numpy holds the GIL while it
    draws, and a row at a time lets the propagating thread run in between.
    """
    Z = np.empty(shape, np.float32)
    for row in Z.reshape(-1, shape[-1]):
        rng.standard_normal(dtype=np.float32, out=row)
    return Z


def _draws(sizes, meas, Lp, N, n, rng, L0):
    """Every draw of :func:`_sample`, in its order: per block of ``B`` columns the initial
    states (only with ``L0``), then per step ``(v, W)``, the measurement noise ``L_r w`` at
    an update step (else None) and the driving noise ``L_k w`` (None at the last step or
    without noise)."""
    for B in sizes:
        if L0 is not None:
            yield (L0 @ rng.standard_normal((n, B))).astype(np.float32)
        for k in range(N + 1):
            v = W = None
            if k in meas:
                Lr = meas[k][1]
                v = Lr @ _normal32(rng, (Lr.shape[0], B))
            if k < N and Lp[k].shape[1]:
                W = Lp[k] @ _normal32(rng, (Lp[k].shape[1], B))
            yield v, W


class _prefetch:
    """Iterate ``gen`` in a background thread, at most ``depth`` items ahead.

    ``next()`` returns its items in order (re-raising its error);
    ``close()`` stops the thread.
    """

    def __init__(self, gen, depth: int = 4):
        self._q = queue.Queue(depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(gen,), name="linear_mc_draws", daemon=True)
        self._thread.start()

    def _run(self, gen):
        try:
            for item in gen:
                if not self._put((True, item)):
                    return
            self._put((False, StopIteration()))
        except BaseException as exc:           # handed to the consumer
            self._put((False, exc))

    def _put(self, item) -> bool:
        while not self._stop.is_set():
            try:
                self._q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def __next__(self):
        ok, item = self._q.get()
        if not ok:
            raise item
        return item

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
