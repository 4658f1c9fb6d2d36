"""Driving noise composed per source over the event grid, and per-member noise views.

The truth's (or a filter's) driving noise is linear in its sources, so each
source's ``Q_d`` is discretised exactly (:func:`covtool.lincov.discretize.per_source`)
and composed over the intervals between events (as :func:`covtool.lincov.batch.compose`
does for the total) once; a batched run then gives each member its own
combination without copies (:class:`MemberNoise`, :class:`CombinedNoise`).
Used by the error budget, the dropped-state impact table and the magnitude sweep.

Pure numeric core: arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np

from covtool.lincov.discretize import per_source
from covtool.lincov.dynamics import NoiseSource
from covtool.lincov.kalman import symmetrize
from covtool.lincov.stacks import gather


# ---------------------------------------------------------------------------
# discretisation and composition of the per-source noise


def compose_noise(Phi: np.ndarray, F: np.ndarray, factors: list, dt, ev, *, chunk: int = 1000,
                  cache: "ComposedCache | None" = None, system=None, rows=None) -> np.ndarray:
    """Per-source noise composed over the event intervals.

    Parameters
    ----------
    Phi, F : ndarray, shape (N, n, n)
        Truth transition (of the study's discretisation) and dynamics.
    factors : list of NoiseSource
    dt : float or ndarray, shape (N,)
    ev : ndarray of int, shape (K+1,)
        Event grid (:func:`covtool.lincov.batch.events`).
    chunk : int
        Steps discretised at once (bounds the memory).
    cache : ComposedCache, optional
        Compositions shared between calls (the dropped-state impact of
        several filters): a factor already composed on the same states of
        the same system is taken from it, not computed again.
    system : hashable, optional
        Names the full system ``Phi``, ``F`` are rows of (with ``cache``);
        calls with equal ``system`` must pass restrictions of the same
        arrays on the same grid ``dt``, ``ev``.
    rows : array_like of int, shape (n,), optional
        The full system's states that ``Phi``'s rows are (with ``cache``;
        default ``0 … n−1``).

    Returns
    -------
    ndarray, shape (J, K, n, n)
        ``Q_{a→b},j = Σ_k Φ_{k+1→b} Q_k,j Φ_{k+1→b}ᵀ`` for each source j and
        interval ``[ev_i, ev_{i+1})``, as :func:`covtool.lincov.batch.compose`
        computes it for the total.
    """
    shared = None
    if cache is not None:
        rows = np.arange(np.shape(Phi)[1]) if rows is None else np.asarray(rows, int)
        shared = (cache, system, rows)
    return _compose_noise(Phi, F, factors, dt, ev, chunk, shared)


class ComposedCache:
    """Composed per-source noise kept between :func:`compose_noise` calls.

    A source's composed noise lives on the states it reaches, ``R``, and
    depends only on ``Φ``, ``F`` restricted to ``R``, its ``G`` rows on ``R``
    and its PSD (module notes of :func:`_compose_noise`): the key is the
    system, ``R`` in the full system's numbering and a digest of ``G`` and
    the PSD, so a reduced filter's space and a larger one that holds the
    same ``R`` share the result.
    """

    def __init__(self):
        self.store: dict = {}
        self.hits = 0

    @staticmethod
    def key(system, states: np.ndarray, G: np.ndarray, psd: np.ndarray, ev, dt) -> tuple:
        """Key of one source composed on ``states`` (full-system indices) over the grid ``ev``, ``dt``.

        ``G`` is the source's rows on ``states``, shape (N, len(states), w).
        """
        G = np.ascontiguousarray(G, float)
        live = np.flatnonzero(_nonzero_rows(G)[1])
        return ComposedCache._key(system, states, G.shape, live, G[:, live, :], psd, ev, dt)

    @staticmethod
    def _key(system, states, shape: tuple, live: np.ndarray, G_live: np.ndarray, psd, ev, dt) -> tuple:
        """:meth:`key` of a ``G`` of shape ``shape`` whose rows ``live`` are ``G_live``, the others zero bit for bit.

        The zero rows (+0.0 at every step and column) are named, not
        digested: the key still determines ``G`` exactly, and a sensor
        source, zero on the navigation states it reaches, digests a
        fraction of the bytes.
        """
        import hashlib

        h = hashlib.blake2b(digest_size=20)
        h.update(repr(tuple(shape)).encode())
        h.update(np.ascontiguousarray(G_live, float))
        for X in (np.asarray(psd, float), np.asarray(ev, int), np.asarray(dt, float)):
            X = np.ascontiguousarray(X)
            h.update(repr(X.shape).encode())
            h.update(X)
        return system, tuple(int(i) for i in states), tuple(int(i) for i in live), h.hexdigest()


def _nonzero_rows(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of a stack ``G`` (shape (N, n, w), float, C-contiguous) with a non-zero entry, and not zero bit for bit.

    Returns ``(seed, live)``, boolean of shape (n,): ``seed`` where some
    entry ``!= 0``, ``live`` where some entry is not +0.0 (``seed`` and the
    rows holding −0.0).  One OR over the steps of the bit patterns gives
    both (an entry ``!= 0`` iff its bits without the sign bit are not all
    zero, NaN included): a fraction of a reduction over the (0, 2) axes.
    """
    N, n, w = G.shape
    bits = np.bitwise_or.reduce(G.view(np.uint64).reshape(N, n * w), axis=0).reshape(n, w)
    return (bits & np.uint64(0x7FFF_FFFF_FFFF_FFFF)).any(axis=1), bits.any(axis=1)


#: bytes the per-source series of :func:`compose_noise` may hold at once
COMPOSE_WORKSPACE = 32e6
#: (chunk, J, n, n)-sized stacks alive at once inside :func:`covtool.lincov.discretize.per_source`
_STACKS = 6


def reached_states(pattern: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """States reached from ``seed`` through the couplings of ``pattern``.

    Parameters
    ----------
    pattern : ndarray of bool, shape (n, n)
        ``pattern[i, j]``: state ``j`` drives state ``i`` at some step.
    seed : ndarray of bool, shape (n,)

    Returns
    -------
    ndarray of bool, shape (n,)
        The smallest set ``R ⊇ seed`` with ``pattern[i, j] ⇒ i ∈ R`` for every
        ``j ∈ R``.
    """
    R = np.asarray(seed, bool).copy()
    P = np.asarray(pattern, bool)
    while True:
        Rn = R | P[:, R].any(axis=1)
        if np.array_equal(Rn, R):
            return R
        R = Rn


def _compose_noise(Phi, F, factors, dt, ev, chunk, shared=None):
    """Per-source noise composed on the states each source reaches.

    A source whose ``G`` has non-zero rows ``S`` drives only the states
    ``R`` reached from ``S`` (:func:`reached_states` over the couplings of
    every step's ``F`` and ``Φ``).  Nothing in ``R`` drives a state outside
    it, so ``F`` and ``Φ`` are block triangular for ``(R, rest)`` (the
    zero block is exact in every discretisation, a sum of products with a
    zero factor), the composed noise is zero outside ``R × R`` and its
    ``R × R`` block is that of the system restricted to ``R``: exact, and
    far cheaper where a sensor source reaches its own state and the 10
    navigation states of a 58-state truth.  Sources that reach the same
    states are composed together.
    """
    N, n, _ = Phi.shape
    J = len(factors)
    K = len(ev) - 1
    out = np.zeros((J, K, n, n))
    if J == 0 or N == 0:
        return out
    if not (np.isfinite(F).all() and np.isfinite(Phi).all()):
        return _compose_block(Phi, F, factors, dt, ev, chunk)          # its checks name the step
    pattern = (F != 0).any(axis=0) | (Phi != 0).any(axis=0)
    sets: dict = {}
    keys = {}
    for j, f in enumerate(factors):
        if np.size(f.G):
            G = np.ascontiguousarray(f.G, float)
            seed, live = _nonzero_rows(G)
        else:
            G, seed = None, np.zeros(n, bool)
        R = reached_states(pattern, seed)
        if shared is not None and R.any():
            cache, system, rows = shared
            idx = np.flatnonzero(R)
            # the key of G's rows on R (ComposedCache.key), its live rows taken from G itself: no copy of the rest
            on = np.flatnonzero(live[idx])
            keys[j] = cache._key(system, rows[idx], (G.shape[0], idx.size, G.shape[2]), on, G[:, idx[on], :],
                                 f.psd, ev, dt)
            if keys[j] in cache.store:
                out[j][:, idx[:, None], idx[None, :]] = cache.store[keys[j]]
                cache.hits += 1
                continue
        sets.setdefault(R.tobytes(), (R, []))[1].append(j)
    for R, js in sets.values():
        idx = np.flatnonzero(R)
        if idx.size == 0:
            continue                                   # a source with a zero G: zero noise
        if idx.size == n:
            out[js] = _compose_block(Phi, F, [factors[j] for j in js], dt, ev, chunk)
        else:
            sub = [NoiseSource(factors[j].name, np.asarray(factors[j].G)[:, idx, :], factors[j].psd) for j in js]
            Qs = _compose_block(gather(Phi, idx), gather(F, idx), sub, dt, ev, chunk)
            for q, j in enumerate(js):
                out[j][:, idx[:, None], idx[None, :]] = Qs[q]
        if shared is not None:
            for j in js:
                shared[0].store[keys[j]] = out[j][:, idx[:, None], idx[None, :]].copy()
    return out


def _compose_block(Phi, F, factors, dt, ev, chunk):
    N, n, _ = Phi.shape
    J = len(factors)
    K = len(ev) - 1
    out = np.zeros((J, K, n, n))
    if J == 0:
        return out
    dt = np.broadcast_to(np.asarray(dt, float), (N,))
    widths = [f.G.shape[2] for f in factors]
    starts = np.r_[0, np.cumsum(widths)[:-1]]
    G = np.concatenate([f.G for f in factors], axis=2)
    psd = np.concatenate([f.psd for f in factors], axis=1)
    # per step the series holds four (k, n, terms) stacks (terms ≈ 15-25 at νh ≤ θ) and (J, n, n)
    # sums: bound them by COMPOSE_WORKSPACE
    per_step = 8 * (4 * 25 * n * G.shape[2] + _STACKS * J * n * n)
    chunk = max(1, min(chunk, int(COMPOSE_WORKSPACE // per_step)))
    fold = _Fold(ev, n, J)
    for a in range(0, N, chunk):
        b = min(N, a + chunk)
        Qj = per_source(F[a:b], G[a:b], psd[a:b], dt[a:b], what="error budget: per-source Q_d",
                        groups=starts)                                        # (c, J, n, n)
        fold.add(a, Phi[a:b], Qj)
    out[:] = np.swapaxes(fold.finish()[1], 0, 1)
    return out


class MemberNoise:
    """Per-member truth noise for ``run_batch``, without copies.

    Behaves like an array of shape ``(B, K, n, n)`` for the indexing
    ``Q[:, i]`` the engine uses; member ``b`` takes ``arrays[b][i]`` or zero.

    Parameters
    ----------
    arrays : list of (ndarray of shape (K, n, n)) or None
    K, n : int
    """

    def __init__(self, arrays: list, K: int, n: int):
        self.arrays = arrays
        self.shape = (len(arrays), K, n, n)

    def __getitem__(self, key):
        if not (isinstance(key, tuple) and len(key) == 2 and key[0] == slice(None)):
            raise IndexError("MemberNoise supports Q[:, i] only")
        i = key[1]
        out = np.zeros((self.shape[0],) + self.shape[2:])
        for b, arr in enumerate(self.arrays):
            if arr is not None:
                out[b] = arr[i]
        return out


class CombinedNoise:
    """Per-member filter noise ``Σ_c coef[b, c] · embed(component_c)``, built per interval.

    Behaves like an array of shape ``(B, K, n, n)`` for ``Q[:, i]``
    (:func:`covtool.lincov.batch.run_batch`'s ``filter_Q``).

    Parameters
    ----------
    components : list of (ndarray of shape (K, m, m), ndarray of int of shape (m,))
        Composed noise and the state indices it lives on.
    coef : ndarray, shape (B, n_components)
    n : int
        Dimension of the embedding space.

    Notes
    -----
    ``coef`` is read once, here: the components are grouped by the states
    they live on and each group's weighted sum is one product.
    """

    def __init__(self, components, coef, n):
        self.components = components
        self.coef = np.asarray(coef, float)
        K = components[0][0].shape[0] if components else 0
        self.shape = (self.coef.shape[0], K, n, n)
        # the components some member weighs, grouped by the states they live on: each group's weighted
        # sum is one product (B, c) @ (c, m²) and one scatter into the embedding, not c scatters
        groups: dict[tuple, list[int]] = {}
        for c, (_Q, ix) in enumerate(components):
            if np.any(self.coef[:, c] != 0):
                groups.setdefault(tuple(np.asarray(ix).tolist()), []).append(c)
        self._groups = [(np.asarray(components[cs[0]][1]), cs, np.ascontiguousarray(self.coef[:, cs]))
                        for cs in groups.values()]

    def __getitem__(self, key):
        if not (isinstance(key, tuple) and len(key) == 2 and key[0] == slice(None)):
            raise IndexError("CombinedNoise supports Q[:, i] only")
        i = key[1]
        out = np.zeros((self.shape[0],) + self.shape[2:])
        for ix, cs, w in self._groups:
            m = ix.size
            Qi = np.stack([self.components[c][0][i] for c in cs]).reshape(len(cs), m * m)
            out[:, ix[:, None], ix[None, :]] += (w @ Qi).reshape(w.shape[0], m, m)
        return out


def compose_transition(Phi, ev):
    """Transition over each event interval, ``Φ_{a→b} = Φ_{b−1} ⋯ Φ_a``.

    Parameters
    ----------
    Phi : ndarray, shape (N, n, n)
    ev : ndarray of int, shape (K+1,)

    Returns
    -------
    ndarray, shape (K, n, n)
    """
    return compose_scan(Phi, None, ev)[0]


def compose_scan(Phi: np.ndarray, Qd, ev, *, chunk: int | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Transition and noise over each event interval, by pairwise reduction.

    Parameters
    ----------
    Phi : ndarray, shape (N, n, n)
        Per-step transition.
    Qd : ndarray, shape (N, n, n) or (N, J, n, n), or None
        Per-step noise (one or ``J`` sources); None for the transition only.
    ev : ndarray of int, shape (K+1,)
        Event grid (:func:`covtool.lincov.batch.events`), increasing.
    chunk : int, optional
        Steps reduced at once (bounds the workspace); all by default.

    Returns
    -------
    Phi_c : ndarray, shape (K, n, n)
    Q_c : ndarray, shape (K, n, n) or (K, J, n, n), or None
        ``Σ_k Φ_{k+1→b} Q_k Φ_{k+1→b}ᵀ`` over ``k ∈ [ev_i, ev_{i+1})``,
        symmetrised, as :func:`covtool.lincov.batch.compose` sums it step
        by step.

    Notes
    -----
    Two consecutive steps compose as
    ``(Φ₂, Q₂)∘(Φ₁, Q₁) = (Φ₂Φ₁, Φ₂Q₁Φ₂ᵀ + Q₂)``, an associative product, so
    each interval is reduced pairwise in ``⌈log₂ L⌉`` batched levels
    instead of ``L`` sequential steps: the same products (every ``Q`` term is
    still a congruence of a PSD matrix), in another order, with round-off
    of the same order (relative 1e-16 per product).

    Random-constant states (``Φ`` rows of the identity,
    :func:`covtool.lincov.batch.dynamic_states`), with ``Q`` zero outside
    the dynamic block, keep that form under the product, as in
    :func:`covtool.lincov.batch.compose`: only the dynamic rows
    ``R = [Φ_dd | Φ_dc]`` are reduced, ``R₂∘R₁ = Φ₂,dd R₁ + [0 | Φ₂,dc]``,
    and ``Q_dd``; exact, ``(n_d/n)²`` of the work (the 58-state truth: 22 of 58).
    """
    Phi = np.asarray(Phi, float)
    N, n, _ = Phi.shape
    single = Qd is not None and np.ndim(Qd) == 3
    J = 0 if Qd is None else (1 if single else np.shape(Qd)[1])
    fold = _Fold(ev, n, J, _constant_rows(Phi, Qd, ev))
    step = max(1, N) if chunk is None else max(1, int(chunk))
    for a in range(0, N, step):
        b = min(N, a + step)
        Q = None if Qd is None else (np.asarray(Qd[a:b], float)[:, None] if single else np.asarray(Qd[a:b], float))
        fold.add(a, Phi[a:b], Q)
    Pc, Qc = fold.finish()
    if Qc is not None and single:
        Qc = Qc[:, 0]
    return Pc, Qc


def _constant_rows(Phi, Qd, ev):
    """``(d, c)`` of :func:`covtool.lincov.batch.dynamic_states` over the steps of ``ev``, if ``Qd`` is zero off ``dd``."""
    from covtool.lincov.batch import dynamic_states

    ev = np.asarray(ev, int)
    if len(ev) < 2:
        return None
    lo, hi = max(int(ev[0]), 0), min(int(ev[-1]), Phi.shape[0])
    dyn = dynamic_states(Phi[lo:hi])
    if dyn is None or Qd is None:
        return dyn
    d = dyn[0]
    mask = np.ones(np.shape(Qd)[-2:], bool)
    mask[np.ix_(d, d)] = False
    for a in range(lo, hi, 256):                              # in chunks: the temporaries stay small
        # a non-zero (or NaN) entry at some step marks its (i, j): reduced over the steps first, contiguous
        if np.any((np.asarray(Qd[a:min(hi, a + 256)]) != 0).any(axis=0)[..., mask]):
            return None
    return dyn


def _reduce(Phi, Q, seg, nd=None):
    """Pairwise reduction of consecutive steps of each segment: one ``(Φ, Q)`` per segment.

    With ``nd``, ``Phi`` holds the dynamic rows only, columns in the order
    (dynamic, constant), and ``Q`` the dynamic block (:func:`compose_scan`).
    """
    while True:
        M = seg.size
        same = seg[1:] == seg[:-1]
        if not same.any():
            return Phi, Q, seg
        first = np.r_[True, ~same]
        start = np.maximum.accumulate(np.where(first, np.arange(M), 0))
        even = (np.arange(M) - start) % 2 == 0
        nxt = np.r_[same, False]                            # a later step of the same segment follows
        left = np.flatnonzero(even & nxt)
        keep = np.flatnonzero(even)
        paired = nxt[keep]                                  # the kept steps that have a partner (left ⊂ keep)
        # the kept steps without a partner (one at most per segment) are copied, the others are the
        # products: no gather of all the kept steps to overwrite most of them
        alone = None if paired.all() else keep[~paired]
        if nd is None:
            A = Phi[left + 1]                               # the later step acts on the earlier one
            prod = A @ Phi[left]
        else:
            A = Phi[left + 1, :, :nd]                       # contiguous: BLAS, not numpy's own loop
            prod = A @ Phi[left]
            prod[:, :, nd:] += Phi[left + 1, :, nd:]
        Phi = _merge(prod, Phi, paired, alone)
        if Q is not None:
            Qn = A[:, None] @ Q[left] @ np.swapaxes(A, 1, 2)[:, None] + Q[left + 1]
            Q = _merge(Qn, Q, paired, alone)
        seg = seg[keep]


def _merge(prod, X, paired, alone):
    """One level of :func:`_reduce`: ``prod`` where ``paired``, the steps ``alone`` of ``X`` elsewhere."""
    if alone is None:
        return prod
    out = np.empty((paired.size,) + prod.shape[1:])
    out[paired] = prod
    out[~paired] = X[alone]
    return out


class _Fold:
    """Running composition over event intervals, fed in chunks of steps (:func:`compose_scan`).

    With ``dyn = (d, c)`` (random constants), the dynamic rows and the
    dynamic block of ``Q`` only.
    """

    def __init__(self, ev, n, J, dyn=None):
        self.ev = np.asarray(ev, int)
        K = len(self.ev) - 1
        self.n, self.J, self.dyn = n, J, dyn
        if dyn is None:
            self.Pc = np.broadcast_to(np.eye(n), (K, n, n)).copy()
            self.Qc = np.zeros((K, J, n, n)) if J else None
        else:
            d, c = dyn
            self.nd, self.perm = d.size, np.r_[d, c]
            self.Pc = np.broadcast_to(np.eye(n)[d][:, self.perm], (K, d.size, n)).copy()
            self.Qc = np.zeros((K, J, d.size, d.size)) if J else None

    def add(self, a, Phi, Q):
        """Steps ``a … a+len(Phi)−1`` (``Q``: shape (c, J, n, n) or None)."""
        steps = a + np.arange(Phi.shape[0])
        seg = np.searchsorted(self.ev, steps, side="right") - 1
        ok = (seg >= 0) & (seg < len(self.ev) - 1)
        if not ok.all():
            Phi, seg = Phi[ok], seg[ok]
            Q = None if Q is None else Q[ok]
        if not seg.size:
            return
        nd = None
        if self.dyn is not None:
            d, nd = self.dyn[0], self.nd
            Phi = Phi[:, d[:, None], self.perm[None, :]]
            Q = None if Q is None else Q[:, :, d[:, None], d[None, :]]
        # _reduce never writes into its inputs (each level works on the gathered copies)
        P, Qr, seg = _reduce(np.asarray(Phi, float), None if Q is None else np.asarray(Q, float), seg, nd)
        # each segment's piece follows what earlier chunks composed of it (identity and zero if nothing)
        old = self.Pc[seg]
        if nd is None:
            self.Pc[seg] = P @ old
        else:
            prod = np.ascontiguousarray(P[:, :, :nd]) @ old
            prod[:, :, nd:] += P[:, :, nd:]
            self.Pc[seg] = prod
            P = np.ascontiguousarray(P[:, :, :nd])
        if Qr is not None:
            self.Qc[seg] = P[:, None] @ self.Qc[seg] @ np.swapaxes(P, 1, 2)[:, None] + Qr

    def finish(self):
        Qc = None if self.Qc is None else symmetrize(self.Qc)
        if self.dyn is None:
            return self.Pc, Qc
        d = self.dyn[0]
        K, n = self.Pc.shape[0], self.n
        Pc = np.broadcast_to(np.eye(n), (K, n, n)).copy()
        Pc[:, d[:, None], self.perm[None, :]] = self.Pc
        if Qc is not None:
            full = np.zeros((K, self.J, n, n))
            full[:, :, d[:, None], d[None, :]] = Qc
            Qc = full
        return Pc, Qc


def restricted_noise(name, sources, rows):
    """One noise factor from NoiseSources, restricted to ``rows``."""
    G = np.concatenate([s.G[:, rows, :] for s in sources], axis=2)
    psd = np.concatenate([s.psd for s in sources], axis=1)
    return NoiseSource(name, G, psd)
