"""Property test: every exact discretiser against a 50-digit eigen-decomposition (issue 9, acceptance 2).

Random stable systems ``ẋ = F x + w`` of the kind covtool discretises: a
navigation block (a Schuler-like oscillator ``[[0, 1], [−ω², 0]]``, an
integrator, a damped state) driven through random couplings by sensor
states that are first-order Gauss–Markov, with time constants from 10 ms
(stiff) to 3 h, optionally coupled among themselves; random PSD ``Q_c`` of
any rank; steps from 0.01 s to 1000 s (five decades).  ``Δt/τ`` thus runs
from 1e-6 to 1e5.

Reference, independent of the code under test: with ``F = V Λ V⁻¹``
(``mpmath.eig``, 50 digits; the eigenvalues are distinct by construction)::

    Φ   = V e^{ΛΔt} V⁻¹
    Q_d = V (Q̃ ∘ G) Vᴴ,   Q̃ = V⁻¹ Q_c V⁻ᴴ,   G_ij = (e^{(λ_i + λ̄_j)Δt} − 1)/(λ_i + λ̄_j)

(``G_ij = Δt·expm1(z)/z``, exact for ``z → 0``).

Requirement: ``van_loan``, the adaptive ``taylor``, ``block_triangular``
(when ``F`` has its structure), ``per_source``
(each noise column) and ``discretize_difference`` agree with the reference to
1e-9: Φ column-wise relative (``max_i |ΔΦ_ij| / max_i |Φ_ij|``), Q_d in
correlation scaling (``|ΔQ_ij| / √(Q_ii Q_jj)``).  For stable ``F`` none may
refuse.
"""

from __future__ import annotations

import mpmath as mp
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from covtool.dualnav.difference import discretize_difference
from covtool.lincov.discretize import block_triangular, is_block_triangular, per_source, taylor, van_loan

TOL = 1e-9


@st.composite
def systems(draw):
    """``(F, Q_c, Δt, k)``: ``k`` navigation states, then the sensor states."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    nav = draw(st.sampled_from(["oscillator", "integrator", "oscillator+damped"]))
    m = draw(st.integers(1, 3))
    coupled = draw(st.booleans())                       # sensors coupled among themselves
    if nav == "oscillator":
        w = 10 ** rng.uniform(-3.5, -1.5)               # Schuler: 1.24e-3 rad/s
        A = np.array([[0.0, 1.0], [-w * w, 0.0]])
    elif nav == "integrator":
        A = np.zeros((1, 1))
    else:
        w = 10 ** rng.uniform(-3.5, -1.5)
        A = np.array([[0.0, 1.0, 0.0], [-w * w, 0.0, 0.0], [0.0, 0.0, -10 ** rng.uniform(-4, -1)]])
        A[2, :2] = rng.uniform(-1, 1, 2) * 1e-3
    k = A.shape[0]
    # distinct Gauss–Markov rates, log-uniform τ in [10 ms, 3 h], at least a factor 1.5 apart
    logtau = np.sort(rng.uniform(-2.0, 4.0, m))
    logtau = logtau[0] + np.concatenate([[0.0], np.cumsum(np.maximum(np.diff(logtau), 0.18))])
    D = np.diag(-1.0 / 10**logtau)
    if coupled:
        D += np.triu(rng.uniform(-1, 1, (m, m)) * np.abs(np.diag(D))[None, :], 1)
    n = k + m
    F = np.zeros((n, n))
    F[:k, :k] = A
    F[:k, k:] = rng.uniform(-1, 1, (k, m)) * 10 ** rng.uniform(-2, 1, (1, m))
    F[k:, k:] = D
    rank = draw(st.integers(0, k))
    L = rng.standard_normal((k, rank)) * 10 ** rng.uniform(-3, 0, (1, rank))
    Qc = np.zeros((n, n))
    Qc[:k, :k] = L @ L.T
    q = 2.0 * 10 ** rng.uniform(-2, 0, m) / 10**logtau          # 2σ²/τ, σ from 0.1 to 1
    q[rng.uniform(size=m) < 0.25] = 0.0                            # some random constants... with a rate
    Qc[k:, k:] = np.diag(q)
    if not Qc.any():
        Qc[k, k] = q.max() if q.max() > 0 else 1.0
    dt = float(10 ** draw(st.floats(-2.0, 3.0)))
    return F, Qc, dt, k


def _reference(F, Qc, dt, columns=None):
    """Φ, Q_d (and Q_d of each column ``g`` of ``columns``) by eigen-decomposition, 50 digits."""
    with mp.workdps(50):
        n = F.shape[0]
        lam, V = mp.eig(mp.matrix(F.tolist()))
        Vi = V**-1
        h = mp.mpf(dt)
        Phi = V * mp.diag([mp.exp(x * h) for x in lam]) * Vi
        G = mp.matrix(n, n)
        for i in range(n):
            for j in range(n):
                z = (lam[i] + mp.conj(lam[j])) * h
                G[i, j] = h if z == 0 else h * mp.expm1(z) / z

        def integral(Q):
            Qt = Vi * mp.matrix(Q.tolist()) * Vi.H
            return V * mp.matrix([[Qt[i, j] * G[i, j] for j in range(n)] for i in range(n)]) * V.H

        def real(M):
            return np.array([[float(mp.re(M[i, j])) for j in range(n)] for i in range(n)])

        out = [real(Phi), real(integral(Qc))]
        if columns is not None:
            out.append([real(integral(np.outer(g, g) * w)) for g, w in columns])
        return out


def _phi_error(A, B):
    den = np.maximum(np.max(np.abs(B), axis=0), 1e-12 * np.abs(B).max())
    return float(np.max(np.max(np.abs(A - B), axis=0) / den))


def _q_error(A, B):
    d = np.sqrt(np.clip(np.diag(B), 0.0, None))
    d = np.maximum(d, 1e-12 * d.max()) if d.max() > 0 else np.ones_like(d)
    return float(np.max(np.abs(A - B) / d[:, None] / d[None, :]))


@settings(max_examples=40, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(systems())
def test_every_discretiser_matches_the_eigen_reference(system):
    F, Qc, dt, k = system
    w, U = np.linalg.eigh(Qc)
    keep = w > 1e-14 * w.max()
    G, psd = U[:, keep], w[keep]
    Phi_r, Q_r, Q_cols = _reference(F, Qc, dt, list(zip(G.T, psd)))
    F3, Q3 = F[None], Qc[None]
    results = {"van_loan": van_loan(F3, Q3, dt), "taylor": taylor(F3, Q3, dt),
               "discretize_difference": discretize_difference(F3, Q3, dt, nav=k)[:2]}
    if is_block_triangular(F3, Q3, k):
        results["block_triangular"] = block_triangular(F3, Q3, dt, k)
    for name, (Phi, Qd) in results.items():
        assert _phi_error(Phi[0], Phi_r) <= TOL, name
        assert _q_error(Qd[0], Q_r) <= TOL, name
    Qs = per_source(F3, G[None], psd[None], dt)
    for p, Qp in enumerate(Q_cols):
        assert _q_error(Qs[0, p], Qp) <= TOL, p
