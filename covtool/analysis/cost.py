"""FLOPs and time of one on-board filter cycle (seed 002 Table 4).

Seed 002 Table 4 gives the time of one filter cycle on an 8 MHz Intel
8086/8087 (A 22.62 s, B3 0.74 s, C 0.29 s, D 0.08 s).  The machine-independent
measure is the floating-point operation count of the cycle, given here in
closed form as a function of the filter order ``n`` (= n_f), the number of
measurements ``m`` and the number of Taylor terms ``N_t``; the time on this
machine is that of covtool's kernel doing the same cycle (:func:`time_cycle`).

Counting convention
-------------------
Every scalar add, subtract, multiply and divide is one FLOP, so a
multiply-add counts 2 and a dense product ``(a×b)(b×c)`` costs ``2abc``
(the count of the naive triple loop ``acc += x*y``).  Matrices are dense:
no use is made of symmetry or of the sparsity of ``F_f`` or of the ZUPT
``H`` (a 1988 on-board code with general matrix routines, as the paper's
n³-like times suggest).

One cycle
---------
One propagation step of the filter with its on-board discretisation, then
one ZUPT update (:func:`onboard_cycle` computes the same numbers with the
kernel; tests/test_flops.py counts these loops operation by operation):

=====================  ===========================================  ====================================
step                   operations                                   FLOPs
=====================  ===========================================  ====================================
Φ_f, eq (6b)           A = Δt F; Φ = I + A; T = A; for                n² + n + (N_t−2)(2n³ + 2n²)
                       i = 2…N_t−1: T = (T A)/i, Φ += T
Q_f, eq (6c)–(6d)      C = Qc; Q = Δt C; c = Δt; for                  n² + (N_t−2)(2n³ + 3n² + 2)
                       i = 2…N_t−1: G = F C, C = G + Gᵀ,
                       c = c Δt / i, Q += c C
propagation, eq (6a)   P = (Φ P) Φᵀ + Q                              4n³ + n²
gain, eq (7)           U = P Hᵀ; S = H U + R; LU of S (no           2n²m + 2nm² + m² + m(m−1)/2
                       pivoting); K from S Kᵀ = Uᵀ                   + m(m−1)(2m−1)/3 + n(2m² − m)
update, eq (8)         P = P − K (H P)                               4mn² + n²
update, Joseph         A = I − K H; P = A P Aᵀ + (K R) Kᵀ            4n³ + 4n²m + 2nm² + 2n²
=====================  ===========================================  ====================================

``N_t`` is the number of terms of eq (6b) (``i = 0 … N_t−1``, ``N_t ≥ 2``).
The leading term is ``2(2N_t − 2)n³`` for the Taylor series plus ``4n³``
(``8n³`` with Joseph) for propagation and update, so the cost grows as n³.
"""

from __future__ import annotations

import timeit

import numpy as np

from covtool.errors import InputError
from covtool.lincov import discretize
from covtool.lincov.kalman import filter_update, kalman_gain, predict

#: Seed 002 Table 4: time of one filter cycle on an 8 MHz 8086/8087. [s]
PAPER_TABLE4_SECONDS = {"A": 22.62, "B3": 0.74, "C": 0.29, "D": 0.08}
#: and the filter orders of Table 1
PAPER_TABLE4_STATES = {"A": 58, "B3": 22, "C": 16, "D": 10}


def _check(n, m=1, order=2):
    if int(n) != n or n < 1 or int(m) != m or m < 1:
        raise ValueError(f"n and m must be positive integers, got n = {n!r}, m = {m!r}")
    if int(order) != order or order < 2:
        raise ValueError(f"the Taylor series needs at least 2 terms (N_t ≥ 2), got {order!r}")


def phi_flops(n: int, order: int) -> int:
    """FLOPs of Φ_f by eq (6b) with ``order`` terms (see module table)."""
    _check(n, 1, order)
    return n * n + n + (order - 2) * (2 * n**3 + 2 * n * n)


def qd_flops(n: int, order: int) -> int:
    """FLOPs of Q_f by eq (6c)–(6d) with ``order`` terms."""
    _check(n, 1, order)
    return n * n + (order - 2) * (2 * n**3 + 3 * n * n + 2)


def propagation_flops(n: int) -> int:
    """FLOPs of ``Φ P Φᵀ + Q`` (eq (6a))."""
    _check(n)
    return 4 * n**3 + n * n


def gain_flops(n: int, m: int) -> int:
    """FLOPs of the gain, eq (7), with an unpivoted LU solve."""
    _check(n, m)
    lu = m * (m - 1) // 2 + (m - 1) * m * (2 * m - 1) // 3
    return 2 * n * n * m + 2 * n * m * m + m * m + lu + n * (2 * m * m - m)


def update_flops(n: int, m: int, form: str = "joseph") -> int:
    """FLOPs of the covariance update: eq (8) or Joseph form."""
    _check(n, m)
    if form == "standard":
        return 4 * m * n * n + n * n
    if form == "joseph":
        return 4 * n**3 + 4 * n * n * m + 2 * n * m * m + 2 * n * n
    raise ValueError(f"unknown update form {form!r} (joseph, standard)")


def cycle_flops(n: int, m: int, order: int, form: str = "joseph") -> dict:
    """FLOPs of one on-board filter cycle, by step.

    Parameters
    ----------
    n : int
        Filter order n_f.
    m : int
        Measurements per update (3 for a ZUPT).
    order : int
        Taylor terms N_t of eq (6b)–(6d) (≥ 2).
    form : {"joseph", "standard"}

    Returns
    -------
    dict of str to int
        ``phi``, ``qd``, ``propagation``, ``gain``, ``update`` and ``total``.
    """
    out = {"phi": phi_flops(n, order), "qd": qd_flops(n, order), "propagation": propagation_flops(n),
           "gain": gain_flops(n, m), "update": update_flops(n, m, form)}
    out["total"] = sum(out.values())
    return out


def onboard_cycle(F, Qc, dt, P, H, R, order: int, form: str = "joseph"):
    """One on-board filter cycle, by covtool's kernel.

    Eq (6b)–(6d) with ``order`` terms by
    :func:`covtool.lincov.discretize.taylor`, eq (6a) by
    :func:`covtool.lincov.kalman.predict`, eq (7) by
    :func:`~covtool.lincov.kalman.kalman_gain` and eq (8) or the Joseph
    form by :func:`~covtool.lincov.kalman.filter_update`: the same
    numbers as the dense algorithm of the module table, whose operations
    :func:`cycle_flops` counts (the kernel's Joseph update is its rank-m
    form, cheaper than the table's ``4n³``; the count describes the
    paper's general-matrix code).

    Parameters
    ----------
    F, Qc : ndarray, shape (n, n)
        Filter dynamics and continuous noise PSD at this step.
    dt : float
        Step. [s]
    P : ndarray, shape (n, n)
        Posterior covariance of the previous cycle.
    H : ndarray, shape (m, n)
    R : ndarray, shape (m, m)
    order : int
        Taylor terms N_t (≥ 2).
    form : {"joseph", "standard"}

    Returns
    -------
    P : ndarray, shape (n, n)
        Posterior covariance after propagation and the update.
    K : ndarray, shape (n, m)
        The gain, eq (7).

    Raises
    ------
    InputError
        An ``order`` whose series diverges over ``dt``
        (:func:`covtool.lincov.discretize.taylor`).
    """
    Phi, Qd = discretize.taylor(F[None], Qc[None], dt, order, what="on-board cycle")   # eq (6b)-(6d)
    P = predict(Phi[0], P, Qd[0])                                                     # eq (6a)
    K = kalman_gain(P, H, R, what="on-board cycle")                                     # eq (7)
    return filter_update(P, K, H, R, form, what="on-board cycle"), K                    # eq (8) / Joseph


def time_cycle(F, Qc, dt, P, H, R, order: int, form: str = "joseph", *, repeats: int = 7,
               min_time: float = 0.02) -> float:
    """Median wall time of :func:`onboard_cycle` on this machine. [s]

    timeit-style: the loop count is raised until one repeat lasts at least
    ``min_time``; the median over ``repeats`` repeats divided by the loop count
    is returned.  It times covtool's kernel, whose Joseph update is the
    rank-m form (``O(n² m)``, not the table's ``4n³``) and whose series
    balances ``F`` first: :func:`cycle_flops` divided by this time is an
    effective rate of the paper's dense algorithm, not the kernel's own.  Run it with one BLAS thread (an on-board processor has one;
    :func:`covtool.studies.run_study` limits the pool).  A benchmark figure,
    never asserted in tests.
    """
    args = (np.asarray(F, float), np.asarray(Qc, float), float(dt), np.asarray(P, float),
            np.asarray(H, float), np.asarray(R, float), int(order), form)
    timer = timeit.Timer(lambda: onboard_cycle(*args))
    number = _autorange(timer, min_time)
    times = timer.repeat(repeat=repeats, number=number)
    return float(np.median(times)) / number


def _autorange(timer, min_time):
    number = 1
    while True:
        t = timer.timeit(number)
        if t >= min_time:
            return number
        number *= 2 if t > 0.2 * min_time else 10


def taylor_terms(F, Qc, dt, *, steps=None) -> int:
    """Number of terms covtool's adaptive eq (6b)–(6d) series takes.

    The most over the steps of the stack, from
    :func:`covtool.lincov.discretize.taylor_terms` (the series stops when its
    tail is provably below 2⁻⁵³ of the sum).

    Parameters
    ----------
    F, Qc : ndarray, shape (N, n, n)
    dt : float or ndarray, shape (N,)
        Step lengths. [s]
    steps : ndarray of int, shape (N,), optional
        The grid step of each entry, named in the error (default: its index).

    Returns
    -------
    int
        N_t (terms ``i = 0 … N_t−1``).

    Raises
    ------
    InputError
        A step the series only reaches by scaling and squaring (``νΔt`` above
        :data:`covtool.lincov.discretize.THETA`): one on-board cycle of
        :func:`cycle_flops` has no squarings, so its count would be wrong;
        give the number of terms explicitly.
    """
    info = discretize.taylor_terms(F, Qc, dt)
    if info.squarings.any():
        k = int(np.argmax(info.squarings))
        raise InputError("taylor_order = \"auto\"",
                         f"at step {k if steps is None else int(steps[k])} (νΔt = {info.norm_dt[k]:.3g} > {discretize.THETA:g}) the adaptive series is "
                         f"summed over Δt/{2 ** int(info.squarings[k])} and squared, which the one-cycle FLOP count "
                         "does not describe; give the number of terms N_t")
    return int(info.terms.max())


def power_law(n, y) -> tuple[float, float]:
    """Least-squares ``y = a nᵖ`` in log-log; returns ``(p, a)``."""
    p, la = np.polyfit(np.log(np.asarray(n, float)), np.log(np.asarray(y, float)), 1)
    return float(p), float(np.exp(la))


__all__ = ["PAPER_TABLE4_SECONDS", "PAPER_TABLE4_STATES", "phi_flops", "qd_flops", "propagation_flops",
           "gain_flops", "update_flops", "cycle_flops", "onboard_cycle", "time_cycle", "taylor_terms",
           "power_law"]
