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

from covtool.lincov.batch import sandwich
from covtool.lincov.discretize import per_source
from covtool.lincov.dynamics import NoiseSource
from covtool.lincov.kalman import symmetrize


# ---------------------------------------------------------------------------
# discretisation and composition of the per-source noise


def compose_noise(Phi: np.ndarray, F: np.ndarray, factors: list, dt, ev, *, chunk: int = 1000) -> np.ndarray:
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

    Returns
    -------
    ndarray, shape (J, K, n, n)
        ``Q_{a→b},j = Σ_k Φ_{k+1→b} Q_k,j Φ_{k+1→b}ᵀ`` for each source j and
        interval ``[ev_i, ev_{i+1})``, as :func:`covtool.lincov.batch.compose`
        computes it for the total.
    """
    return _compose_noise(Phi, F, factors, dt, ev, chunk)


#: bytes the per-source series of :func:`compose_noise` may hold at once
COMPOSE_WORKSPACE = 32e6
#: (chunk, J, n, n)-sized stacks alive at once inside :func:`covtool.lincov.discretize.per_source`
_STACKS = 6


def _compose_noise(Phi, F, factors, dt, ev, chunk):
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
    acc = np.zeros((J, n, n))
    i = 0
    # per step the series holds four (k, n, terms) stacks (terms ≈ 15-25 at νh ≤ θ) and (J, n, n)
    # sums: bound them by COMPOSE_WORKSPACE
    per_step = 8 * (4 * 25 * n * G.shape[2] + _STACKS * J * n * n)
    chunk = max(1, min(chunk, int(COMPOSE_WORKSPACE // per_step)))
    for a in range(0, N, chunk):
        b = min(N, a + chunk)
        Qj = per_source(F[a:b], G[a:b], psd[a:b], dt[a:b], what="error budget: per-source Q_d",
                        groups=starts)                                        # (c, J, n, n)
        for s in range(a, b):
            acc = sandwich(Phi[s], acc) + Qj[s - a]
            if s + 1 == ev[i + 1]:
                out[:, i] = symmetrize(acc)
                acc = np.zeros((J, n, n))
                i += 1
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
    """

    def __init__(self, components, coef, n):
        self.components = components
        self.coef = np.asarray(coef, float)
        K = components[0][0].shape[0] if components else 0
        self.shape = (self.coef.shape[0], K, n, n)

    def __getitem__(self, key):
        if not (isinstance(key, tuple) and len(key) == 2 and key[0] == slice(None)):
            raise IndexError("CombinedNoise supports Q[:, i] only")
        i = key[1]
        out = np.zeros((self.shape[0],) + self.shape[2:])
        for c, (Q, ix) in enumerate(self.components):
            w = self.coef[:, c]
            if np.any(w != 0):
                out[:, ix[:, None], ix[None, :]] += w[:, None, None] * Q[i][None]
        return out


def compose_transition(Phi, ev):
    K = len(ev) - 1
    n = Phi.shape[1]
    out = np.empty((K, n, n))
    for i in range(K):
        A = np.eye(n)
        for k in range(ev[i], ev[i + 1]):
            A = Phi[k] @ A
        out[i] = A
    return out


def restricted_noise(name, sources, rows):
    """One noise factor from NoiseSources, restricted to ``rows``."""
    G = np.concatenate([s.G[:, rows, :] for s in sources], axis=2)
    psd = np.concatenate([s.psd for s in sources], axis=1)
    return NoiseSource(name, G, psd)
