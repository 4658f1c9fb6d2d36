"""Exact discretisation of a scalar error state (measurement-error states, issue 15).

A measurement's own error states (odometer scale factor, GNSS Markov position
error, barometric bias, ...) are scalar and uncoupled, so their transition and
driving noise over a step have closed forms: random constant ``(1, 0)``,
random walk ``(1, rw² dt)``, first-order Gauss–Markov
``(e^{−dt/τ}, σ²(1 − e^{−2dt/τ}))`` (the Van Loan integral of seed 002,
eq (6c)–(6d), for a 1 × 1 system).  This is the discretisers' home for them.
"""

from __future__ import annotations

import numpy as np

from covtool.lincov.model.spec import State


def transition(state: State, dt: float) -> tuple[float, float]:
    """Exact ``(φ, q_d)`` of a scalar measurement-error state over ``dt`` [s].

    Random constant: ``(1, 0)``; first-order Gauss–Markov:
    ``(e^{−dt/τ}, σ²(1 − e^{−2dt/τ}))``; random walk: ``(1, rw² dt)``.
    """
    if state.process == "markov":
        a = np.exp(-dt / state.tau)
        return float(a), float(state.sigma**2 * -np.expm1(-2.0 * dt / state.tau))
    if state.process == "random_walk":
        return 1.0, float(state.rw**2 * dt)
    return 1.0, 0.0
