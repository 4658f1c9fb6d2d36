"""Equivalent white noise of dropped states (seed 002, eq (11)–(13)).

The rules (pointwise eq (11)–(13), matched over each ZUPT interval, or
absorbed into the kept states' P0) are described in
``docs/equivalent_noise.md``; :func:`covtool.lincov.reduced.build_filter`
applies them to every state a filter drops.

Pure numeric core: arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np

from covtool.lincov.dynamics import NoiseSource


# ---------------------------------------------------------------------------
# equivalent white noise, seed 002 eq (11)-(13)
# ---------------------------------------------------------------------------

#: ways of applying eq (11)-(13) (``equivalent_noise`` in a filter file); see docs/equivalent_noise.md
EWN_MODES = ("interval", "pointwise", "matched")


def equivalent_white_noise(state, dt_s: float, mean_speed: float | None = None) -> tuple[float, str]:
    """Equivalent white-noise PSD of a dropped state (seed 002, eq (11)–(13)).

    The scalar rule as printed: the PSD for a *constant* unit coupling over
    one full ZUPT interval.  ``equivalent_noise = "pointwise"`` injects it
    through the coupling at every step; the default (``"interval"``,
    :func:`equivalent_noise_source`) applies the same matching rule over
    each actual ZUPT interval.

    Parameters
    ----------
    state : covtool.lincov.model.spec.State
    dt_s : float
        ZUPT interval Δt_s. [s]
    mean_speed : float, optional
        Mean speed while moving, for Markov-in-distance states (τ = d/v̄). [m/s]

    Returns
    -------
    q_eq : float
        PSD of the equivalent white noise. [SI²·s]
    rule : str
        The rule applied, for the record.

    Notes
    -----
    * first-order Markov, eq (11): ``Q_eq = 2 τ P0`` (the low-frequency PSD of
      the Markov process).  Seed 002 §2.3 states it for a source whose band
      is wider than the system's; a Markov process with ``τ > Δt_s/2`` is
      nearly constant over one ZUPT interval, so eq (12) applies instead.
      Together: ``Q_eq = P0 · min(2τ, Δt_s)``, continuous at ``τ = Δt_s/2``.
      Markov-in-distance states use ``τ = d / v̄`` with the mean moving speed;
    * random constant, eq (12): ``Q_eq = P0 Δt_s`` (a white noise whose
      integral over Δt_s has the same variance as that of the constant,
      ``P0 Δt_s²``);
    * random walk, eq (13) ``Q_eq = P0 Δt_s²`` as printed is dimensionally an
      PSD only if ``P0`` is the walk's diffusion rate ``q_rw`` [unit²/s]; covtool
      reads it so, and adds the eq (12) term for the walk's initial σ:
      ``Q_eq = σ0² Δt_s + q_rw Δt_s²``.
    """
    P0 = state.sigma**2
    regime, tau, kind = ewn_regime(state, dt_s, mean_speed)
    if regime == "markov":
        return 2.0 * tau * P0, f"eq (11) {kind}: 2*tau*P0 (tau = {tau:g} s <= dt_s/2)"
    if regime == "random_walk":
        return P0 * dt_s + state.rw**2 * dt_s**2, "eq (12)+(13) random walk: sigma0^2*dt_s + q_rw*dt_s^2"
    if tau is not None:
        return P0 * dt_s, (f"eq (12) {kind} with tau = {tau:g} s > dt_s/2: constant over a ZUPT interval, "
                           "P0*dt_s")
    if kind:
        return P0 * dt_s, f"eq (12) random constant ({kind}): P0*dt_s"
    return P0 * dt_s, "eq (12) random constant: P0*dt_s"


def ewn_regime(state, dt_s: float, mean_speed: float | None = None) -> tuple[str, float | None, str]:
    """Which of eq (11)–(13) a dropped state falls under.

    Returns
    -------
    regime : {"markov", "constant", "random_walk"}
        ``"markov"``: eq (11), a Markov source with ``τ ≤ Δt_s/2`` that
        decorrelates within a ZUPT interval; ``"constant"``: eq (12), a
        random constant or a Markov source that stays (nearly) constant over
        an interval; ``"random_walk"``: eq (13).
    tau : float or None
        Correlation time (``d / v̄`` for Markov-in-distance states). [s]
    kind : str
        Description for the rule text.
    """
    tau, kind = None, ""
    if state.process == "markov":
        tau, kind = state.tau, "Markov"
    elif state.process == "markov_distance":
        if not mean_speed:
            return "constant", None, "vehicle never moves"
        tau = state.distance / mean_speed
        kind = f"Markov in distance (tau = d/v_mean = {tau:.0f} s)"
    elif state.process == "random_walk":
        return "random_walk", None, "random walk"
    if tau is not None and 2.0 * tau <= dt_s:
        return "markov", tau, kind
    return "constant", tau, kind


def uses_constant_rule(state, dt_s: float, mean_speed: float | None = None) -> bool:
    """True if the state falls under eq (12), the random-constant rule (:func:`ewn_regime`)."""
    return ewn_regime(state, dt_s, mean_speed)[0] == "constant"


def zupt_intervals(update_steps, t: np.ndarray, interval: float) -> np.ndarray:
    """Grid indices bounding the ZUPT intervals of a schedule.

    Parameters
    ----------
    update_steps : array_like of int
        Grid indices of the ZUPT updates.
    t : ndarray, shape (N+1,)
        Time grid. [s]
    interval : float
        Declared ZUPT interval Δt_s (only to tell one stop's window from
        evenly spaced single updates). [s]

    Returns
    -------
    ndarray of int, shape (K+1,)
        ``0``, the last update of every stop's group, and ``N``: interval
        ``i`` is the propagation steps ``bounds[i] … bounds[i+1]−1``.

    Notes
    -----
    The updates of one stop form a group (a window at ``rate``); an interval
    runs from the end of one group to the end of the next, so the regular
    intervals are Δt_s long whatever the window, the first runs from t = 0 to
    the first stop (``[zupt] first``), and a tail after the last update is an
    interval of its own.  Groups are separated by gaps larger than 1.5× the
    smallest gap; if the updates are evenly spaced, each is its own group
    when the spacing is at least Δt_s/2 (one update per stop), else they
    are all one window.
    """
    t = np.asarray(t, float)
    N = t.size - 1
    u = np.unique(np.asarray(update_steps, int))
    u = u[(u > 0) & (u <= N)]
    if u.size == 0:
        return np.array([0, N])
    gaps = np.diff(t[u])
    if gaps.size and gaps.max() > 1.5 * gaps.min():
        brk = gaps > 1.5 * gaps.min()
    else:
        brk = gaps >= 0.5 * interval
    ends = u[np.r_[brk, True]]
    return np.unique(np.r_[0, ends, N]).astype(int)


def _interval_index(bounds: np.ndarray, n_steps: int) -> np.ndarray:
    """Interval number of every propagation step."""
    return np.searchsorted(bounds, np.arange(n_steps), side="right") - 1


def interval_mean(col: np.ndarray, dt_steps: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interval-mean coupling and interval length of every step.

    Parameters
    ----------
    col : ndarray, shape (N, n_f)
        Coupling ``c(t)`` of a dropped state into the kept states.
    dt_steps : ndarray, shape (N,)
        Step lengths. [s]
    bounds : ndarray of int
        :func:`zupt_intervals`.

    Returns
    -------
    cbar : ndarray, shape (N, n_f)
        ``c̄_i = (1/Δt_i) ∫_i c dt`` of the interval each step lies in.
    dti : ndarray, shape (N,)
        ``Δt_i`` of that interval. [s]
    """
    N = col.shape[0]
    k = _interval_index(bounds, N)
    integ, length = _interval_sums(col * dt_steps[:, None], dt_steps, bounds)
    safe = np.where(length > 0, length, 1.0)
    return (integ / safe[:, None])[k], length[k]


def _interval_sums(x: np.ndarray, dt_steps: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sums of the rows of ``x`` over each interval of ``bounds``, and the intervals' lengths.

    Each interval's rows are added in step order, as ``np.add.at`` adds them
    (the same bits), by one reduction per interval instead of one Python
    level addition per step.
    """
    b = np.asarray(bounds, int)
    dt_steps = np.asarray(dt_steps, float)
    N = x.shape[0]
    k = _interval_index(b, N)
    length = np.bincount(k, weights=dt_steps, minlength=b.size - 1)
    if x.ndim == 1:
        return np.bincount(k, weights=x, minlength=b.size - 1), length
    out = np.zeros((b.size - 1,) + x.shape[1:])
    for i, (lo, hi) in enumerate(zip(b[:-1], b[1:])):
        if hi > lo:
            out[i] = x[lo:hi].sum(axis=0)          # along the outer axis: added row after row
    return out, length


def tail_integral(col: np.ndarray, dt_steps: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """``∫_t^{t_end} c ds`` from each step's mid-point to the end of its interval.

    Returns
    -------
    ndarray, shape (N, n_f)
    """
    w = col * dt_steps[:, None]
    out = np.empty_like(col)
    for i in range(len(bounds) - 1):
        a, b = bounds[i], bounds[i + 1]
        rev = np.cumsum(w[a:b][::-1], axis=0)[::-1]          # ∫ from the step's start to the end
        out[a:b] = rev - 0.5 * w[a:b]
    return out


def pointwise_overstatement(col: np.ndarray, dt_steps: np.ndarray, bounds: np.ndarray,
                            dt_s: float) -> tuple[float, float]:
    """How far the pointwise form overstates eq (12)'s matching rule.

    Per interval the pointwise noise integrates to ``P0 Δt_s ∫|c|² dt`` where
    the rule asks for ``P0 |∫c dt|²``.

    Returns
    -------
    overall : float
        ``Σ_i Δt_s ∫_i |c|² / Σ_i |∫_i c|²`` (inf if the coupling integrates to 0).
    worst : float
        Largest ratio of one interval with a non-zero coupling.
    """
    integ = _interval_sums(col * dt_steps[:, None], dt_steps, bounds)[0]
    sq = _interval_sums(np.sum(col**2, axis=1) * dt_steps, dt_steps, bounds)[0]
    num = dt_s * sq
    den = np.sum(integ**2, axis=1)
    tot = float(num.sum() / den.sum()) if den.sum() > 0 else (np.inf if num.sum() > 0 else 1.0)
    on = num > 0
    with np.errstate(divide="ignore"):
        r = np.where(den[on] > 0, num[on] / np.where(den[on] > 0, den[on], 1.0), np.inf)
    return tot, float(r.max()) if r.size else 1.0


def equivalent_noise_source(state, col: np.ndarray, dt_steps: np.ndarray, bounds: np.ndarray, *,
                            dt_s: float, mean_speed: float | None = None,
                            mode: str = "interval") -> tuple[NoiseSource, str]:
    """Equivalent white noise of one dropped state as a driving-noise source.

    Parameters
    ----------
    state : covtool.lincov.model.spec.State
    col : ndarray, shape (N, n_f)
        ``F_kept,j(t)``: how the dropped state drives the kept states (for
        ``"matched"``: the residual after absorption).
    dt_steps : ndarray, shape (N,)
        Step lengths. [s]
    bounds : ndarray of int
        ZUPT intervals (:func:`zupt_intervals`).
    dt_s : float
        Declared ZUPT interval (regime of eq (11); the pointwise PSD). [s]
    mean_speed : float, optional
        Mean moving speed (Markov-in-distance states). [m/s]
    mode : {"interval", "pointwise", "matched"}

    Returns
    -------
    source : covtool.lincov.dynamics.NoiseSource
        ``Q_c += G diag(psd) Gᵀ`` with ``G`` of shape ``(N, n_f, k)``.
    rule : str

    Notes
    -----
    Seed 002 eq (12) matches the white noise's integral over a ZUPT interval
    to that of the dropped random constant, ``P0 (∫c dt)(∫c dt)ᵀ``.  Over
    interval ``i`` of length Δt_i, a white noise of PSD ``q = P0 Δt_i``
    injected through the interval-mean coupling ``c̄_i`` integrates to
    ``q Δt_i c̄_i c̄_iᵀ = P0 (∫_i c)(∫_i c)ᵀ``: the rule holds exactly for any
    ``c(t)``, and for a constant ``c`` on a full interval this is the
    printed ``P0 Δt_s c cᵀ``.  Markov sources with ``τ ≤ Δt_s/2``
    (eq (11)) decorrelate within the interval, so the pointwise
    ``2τP0 c(t)c(t)ᵀ`` is their local white-noise equivalent.  A random
    walk (eq (13)) splits into its value at the interval start (variance
    ``σ0² + q_rw t_a``, eq (12) through ``c̄_i``) and the increment since,
    whose integrated effect ``∫ C(s) dW`` with ``C(s) = ∫_s^{t_b} c`` is a
    white noise of PSD ``q_rw`` through ``C``.  Derivation:
    ``docs/equivalent_noise.md``.
    """
    N, nf = col.shape
    P0 = state.sigma**2
    if mode == "pointwise":
        q, rule = equivalent_white_noise(state, dt_s, mean_speed)
        return NoiseSource(state.name, col[:, :, None].copy(), np.full((N, 1), q)), rule + "; pointwise"
    regime, tau, kind = ewn_regime(state, dt_s, mean_speed)
    if regime == "markov":
        return (NoiseSource(state.name, col[:, :, None].copy(), np.full((N, 1), 2.0 * tau * P0)),
                f"eq (11) {kind}: 2*tau*P0 through c(t) (tau = {tau:g} s <= dt_s/2: decorrelates within "
                "the interval)")
    cbar, dti = interval_mean(col, dt_steps, bounds)
    if regime == "random_walk":
        t0 = np.r_[0.0, np.cumsum(dt_steps)][bounds[_interval_index(bounds, N)]]
        G = np.stack([cbar, tail_integral(col, dt_steps, bounds)], axis=2)
        psd = np.stack([(P0 + state.rw**2 * t0) * dti, np.full(N, state.rw**2)], axis=1)
        return (NoiseSource(state.name, G, psd),
                "eq (12)+(13) random walk, interval-matched: (sigma0^2 + q_rw t_a)*dt_i through the "
                "interval-mean coupling + q_rw through the tail integral of c")
    what = "random constant" if tau is None else f"{kind}, tau = {tau:g} s > dt_s/2"
    if kind == "vehicle never moves":
        what = "random constant (vehicle never moves)"
    return (NoiseSource(state.name, cbar[:, :, None], (P0 * dti)[:, None]),
            f"eq (12) {what}, interval-matched: P0*dt_i through the interval-mean coupling")


def absorbed_coupling(col: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a dropped state's coupling into a part the kept states absorb and a residual.

    Parameters
    ----------
    col : ndarray, shape (N, n_f)
        ``F_kept,j(t)``: how dropped state ``j`` drives the kept states.
    B : ndarray, shape (N, n_f, n_s)
        Couplings of the kept sensor states.

    Returns
    -------
    alpha : ndarray, shape (n_s,)
        Constant least-squares coefficients: over the trajectory,
        ``F_kept,j(t) ≈ B(t) α``.  A random constant ``x_j`` then acts exactly
        like the kept states shifted by ``α x_j``.
    resid : ndarray, shape (N, n_f)
        ``F_kept,j(t) − B(t) α``: the part no kept state can represent; only
        this part is turned into equivalent white noise.

    Notes
    -----
    Example: an accelerometer misalignment ``m_xz`` couples as
    ``C_b^n [f_z, 0, 0]ᵀ``; on a level land vehicle ``f_z ≈ −g``, so it is the
    x-bias coupling times ``−g`` and is absorbed by ``B_x`` with α ≈ −g.
    Rows are scaled by their RMS so velocity and quaternion rows weigh alike.
    """
    N, nf, ns = B.shape
    scale = np.sqrt(np.mean(B**2, axis=(0, 2)) + np.mean(col**2, axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    A = (B / scale[None, :, None]).reshape(N * nf, ns)
    y = (col / scale[None, :]).reshape(N * nf)
    alpha, *_ = np.linalg.lstsq(A, y, rcond=1e-10)
    resid = col - np.einsum("tfs,s->tf", B, alpha)
    return alpha, resid
