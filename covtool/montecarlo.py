"""Monte Carlo validation: real feedback filters on a simulated INS.

Pure numeric core (arrays in, arrays out): an ensemble of M nonlinear
strapdown INS runs (:mod:`covtool.strapdown`) driven by an IMU simulator with
errors drawn from a truth model (:mod:`covtool.imu`), each optionally aided by
a reduced ZUPT Kalman filter that runs as a *real* indirect feedback filter
(seed 002, Fig 1, eq (6)–(10)), and the statistics that compare the ensemble
with the linear covariance analysis (:mod:`covtool.covariance`).

The feedback filter
-------------------
*Covariance and gain.*  The filter propagates its covariance with its own
model, ``P_f ← Φ_f P_f Φ_fᵀ + Q_f`` (eq (6a)–(6d)), and at a ZUPT computes
``K = P_f H_fᵀ (H_f P_f H_fᵀ + R_f)⁻¹`` (eq (7)) and updates ``P_f`` (eq (8)
or Joseph).  ``F_f`` is evaluated along the **reference trajectory**, not
along each run's own navigation solution.  The two differ by the navigation
errors (feet, arcminutes), a second-order change of the gains; with the
reference the covariance and the gains are the same for every run, so they
are computed once for the whole ensemble (:meth:`FeedbackFilter.design`),
and the ensemble tests exactly what the linear analysis assumes (eq (16)
takes ``K`` from one filter covariance history).

*Measurement.*  At a ZUPT the vehicle is known to stand still, so the
measurement is the INS velocity itself, ``z = v̂^n − 0 + ν``, ``ν ~ N(0, R)``
with the *study's* (true) ``R``; the filter's gain may assume another
``R_f``.  The estimate is ``x̂ = K z``: the filter's prior estimate is zero
because every earlier estimate was fed back (eq (9)).

*Feedback* (eq (10), ``x ← x − D x̂``):

* navigation states: :func:`covtool.nav.strapdown.correct` subtracts
  ``(δL̂, δl̂, δĥ, δv̂, δq̂)`` from the navigation state (quaternion
  renormalised);
* sensor and environment states: every run keeps an accumulated estimate
  ``ĉ`` of each sensor state its filter carries (:class:`SensorFeedback`);
  an update adds ``x̂_s`` to ``ĉ``.  Every IMU sample is then compensated
  through the same block sensitivities that inject the errors
  (:mod:`covtool.lincov.model.blocks`, :class:`covtool.validation.sensor_errors.SensorErrors`)::

      Δθ_c = Δθ − h S_g(f̄, ω̄) ĉ_g,     Δv_c = Δv − h S_a(f̄, ω̄) ĉ_a
             − h C_n^b diag(g, g, −1) ĉ_grav − Δĉ_AD

  with ``f̄ = Δv/h``, ``ω̄ = Δθ/h`` the raw measured sample means (what an
  on-board system has).  The residual sensor error is then
  ``S (x − ĉ)`` to first order: the truth state after feedback is
  ``x − ĉ``, exactly the ``x ← x − x̂`` of eq (10).
* Between updates ``ĉ`` follows the *mean* dynamics of its state, so that
  ``x − ĉ`` obeys the truth model's ``ẋ = F x + w``: random constants and
  random walks stay, first-order Markov states decay as ``e^{−Δt/τ}``
  (in distance: ``e^{−Δd/d}``).  The AD-reset state is a velocity error
  whose rate is a specific-force error, so only the *change* of ``ĉ``
  between updates is subtracted from the increments, never its jump at an
  update.  The gravity term is rotated with the reference attitude (an
  on-board system would use its own; the difference is arcmin × µGal).

Statistics
----------
For every case and grid time the ensemble sums ``Σx`` and ``Σx²`` of the
NED position errors, the velocity errors and the attitude errors
(``φ = −2R(q)ᵀδq``) are kept (:class:`EnsembleSums`, additive over chunks of
runs), and the sums of NEES values of the filter's claimed covariance and of
the linear analysis's truth covariance (:class:`Nees`).

Bounds at confidence ``1 − α`` (:func:`rms_bounds`, :func:`nees_bounds`):

* RMS of a scalar zero-mean normal error over ``N`` runs:
  ``N·RMS²/σ² ~ χ²_N``, so ``σ √(χ²_{N,α/2}/N) … σ √(χ²_{N,1−α/2}/N)``;
* radial horizontal RMS: ``Σ(δN² + δE²) = Σ λ₁u₁² + λ₂u₂²`` with ``λ`` the
  eigenvalues of the 2×2 horizontal covariance.  It is replaced by the
  moment-matched ``σ_h² χ²_ν/ν`` with ``ν = N (λ₁+λ₂)²/(λ₁²+λ₂²)``
  (Satterthwaite): ``2N`` for a circular error, ``N`` for a degenerate one
  (:func:`horizontal_dof`).  Using 2N for an elongated error would make the
  bounds too narrow;
* mean NEES of dimension ``d`` over ``N`` runs: ``N ε̄ ~ χ²_{Nd}``.

References
----------
Y. Bar-Shalom, X. R. Li, T. Kirubarajan, *Estimation with Applications to
Tracking and Navigation*, Wiley 2001, §5.4 (NEES and its χ² bounds).
F. E. Satterthwaite, "An approximate distribution of estimates of variance
components", Biometrics Bulletin 2(6), 1946.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from covtool.nav import earth
from covtool.nav import attitude as quat
from covtool.nav import strapdown as sd
from covtool.lincov.kalman import (check_system, check_covariance, filter_update, kalman_gain, symmetrize,
                                   time_text)
from covtool.errors import NumericalError
from covtool.lincov.reduced import zupt_matrices
from covtool.lincov.model.blocks import BLOCK_KINDS, gravity_sensitivity

__all__ = [
    "QUANTITIES", "REDUCED_NAV", "FeedbackFilter", "SensorFeedback", "Nees", "EnsembleCase", "EnsembleSums",
    "run_ensemble", "simulate_chunk", "rms_bounds", "horizontal_dof", "nees_bounds", "nees_whitening", "expected_nees",
    "reduction_matrix", "inside_fraction", "RecordContext",
]

#: quantities summed per grid time: NED position [m], NED velocity [m/s], tilts and azimuth [rad]
QUANTITIES = ("north", "east", "down", "vn", "ve", "vd", "tilt_n", "tilt_e", "azimuth")
#: the navigation part of a NEES vector: the quaternion error reduced to the attitude error φ
REDUCED_NAV = ("dL", "dl", "dh", "dvN", "dvE", "dvD", "phiN", "phiE", "phiD")
_NAV = sd.NAV_STATES


# --------------------------------------------------------------------------
# the filter (covariance and gains: the same for every run)
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class FeedbackFilter:
    """A ZUPT feedback filter's gain schedule and claimed covariance.

    Attributes
    ----------
    name : str
    names : tuple of str
        The filter's states (truth state names, seed 002 eq (14) order first).
    gains : dict of int to ndarray, shape (n_f, 3)
        ``K`` at each update grid index (eq (7)).
    P : ndarray, shape (N+1, n_f, n_f)
        The filter's own (claimed) covariance at every grid time, posterior
        at update times.
    """

    name: str
    names: tuple
    gains: dict
    P: np.ndarray

    @classmethod
    def design(cls, name, names, Phi_f, Qd_f, P0, Rf, update_steps, *, form: str = "joseph",
               times=None) -> "FeedbackFilter":
        """Run the filter's covariance recursion (seed 002, eq (6)–(8)).

        Parameters
        ----------
        name : str
        names : sequence of str
            Filter state names (must contain the velocity states).
        Phi_f, Qd_f : ndarray, shape (N, n_f, n_f)
            The filter's own transition and noise along the reference
            trajectory (eq (6b)–(6d)).
        P0 : ndarray, shape (n_f, n_f)
        Rf : ndarray, shape (3, 3)
            Measurement noise the filter assumes.
        update_steps : iterable of int
            Grid indices of the ZUPT updates.
        form : {"joseph", "standard"}
        times : ndarray, shape (N+1,), optional
            Grid times, for error messages. [s]

        Returns
        -------
        FeedbackFilter

        Raises
        ------
        NumericalError
            An input (P0, Φ_f, Q_f, R_f) or a covariance of the history is
            not finite, symmetric and PSD (:func:`covtool.lincov.kalman.check_covariance`);
            the message names the filter, the time and the state.

        Notes
        -----
        The operations are those of
        :func:`covtool.lincov.reference.propagate_with_filter`, in the same order,
        so ``P`` and ``gains`` equal its ``P_filter`` and ``gains`` bit for bit.
        """
        names = tuple(names)
        Hf = zupt_matrices(names)
        N, nf, _ = Phi_f.shape
        if nf != len(names):
            raise ValueError(f"filter {name!r}: Phi_f has {nf} states, names has {len(names)}")
        label = f"Monte Carlo filter {name}"
        check_system(label, Phi=Phi_f, Qd=Qd_f, P0=P0, R=Rf, names=names, times=times)
        upd = set(int(k) for k in update_steps)
        P = np.full((N + 1, nf, nf), np.nan)
        gains = {}
        Pf = symmetrize(np.asarray(P0, float))
        k = 0
        try:
            with np.errstate(over="ignore", invalid="ignore"):   # a blow-up is reported by the guard
                for k in range(N + 1):
                    if k in upd:
                        K = kalman_gain(Pf, Hf, Rf)
                        gains[k] = K
                        Pf = filter_update(Pf, K, Hf, Rf, form)
                    P[k] = Pf
                    if k < N:
                        Pf = symmetrize(Phi_f[k] @ Pf @ Phi_f[k].T + Qd_f[k])
        except NumericalError as exc:
            check_covariance(P[:k], label, names=names, times=times)
            when = time_text(float(times[k])) if times is not None else f"step {k}"
            raise NumericalError(f"{label}: gain at {when}: {exc}") from None
        check_covariance(P, label, names=names, times=times)
        return cls(name, names, gains, P)


# --------------------------------------------------------------------------
# sensor-error feedback into the IMU increments
# --------------------------------------------------------------------------


@dataclass
class _Block:
    kind: str
    sensor: str
    sensitivity: object
    cols: np.ndarray        # columns within the block kept by the filter
    idx: np.ndarray         # positions in the feedback vector


class SensorFeedback:
    """Accumulated sensor-error estimates of M runs, fed back.

    Parameters
    ----------
    model : covtool.lincov.model.spec.Model
        The truth model (states, blocks, processes).
    names : sequence of str
        The filter's states; the non-navigation ones are fed back here.
    n_runs : int

    Attributes
    ----------
    names : tuple of str
        The fed-back states, in filter order.
    c : ndarray, shape (M, n_s)
        Accumulated estimate ``ĉ`` of each state at the current time.
    """

    def __init__(self, model, names, n_runs: int):
        self.names = tuple(n for n in names if n not in _NAV)
        ix = model.index
        for n in self.names:
            if n not in ix:
                raise ValueError(f"filter state {n!r} is not a state of truth model {model.name!r}")
        self.c = np.zeros((int(n_runs), len(self.names)))
        pos = {n: j for j, n in enumerate(self.names)}
        self.blocks: list[_Block] = []
        for block in model.block_names():
            members = [s for s in model.states if s.block == block]
            kept = [(k, pos[s.name]) for k, s in enumerate(members) if s.name in pos]
            if not kept or members[0].kind == "navigation":
                continue
            bk = BLOCK_KINDS[members[0].kind]
            self.blocks.append(_Block(bk.kind, bk.sensor, bk.sensitivity, np.array([k for k, _ in kept]),
                                      np.array([j for _, j in kept])))
        states = [model.states[ix[n]] for n in self.names]
        self.tau = np.array([s.tau if s.process == "markov" else np.inf for s in states])
        self.dist = np.array([s.distance if s.process == "markov_distance" else np.inf for s in states])
        self.dynamic = np.isfinite(self.tau) | np.isfinite(self.dist)
        self.needs_context = any(b.sensor == "gravity" for b in self.blocks) or bool(np.isfinite(self.dist).any())

    @property
    def n(self) -> int:
        return len(self.names)

    def add(self, dx) -> None:
        """Accumulate the estimates of one update, ``ĉ ← ĉ + x̂_s``."""
        self.c = self.c + dx

    def _factors(self, t_rel, d_rel):
        """Mean-dynamics factors ``e^{−t/τ − d/D}``, shape (k, n_s)."""
        with np.errstate(divide="ignore"):
            return np.exp(-np.asarray(t_rel)[:, None] / self.tau[None, :]
                          - np.asarray(d_rel)[:, None] / self.dist[None, :])

    def compensate(self, dtheta, dv, h: float, ctx: "RecordContext | None" = None):
        """Compensated increments of one record; advances ``ĉ`` to its end.

        Parameters
        ----------
        dtheta, dv : ndarray, shape (M, k, 3)
            Raw increments of the record. [rad], [m/s]
        h : float
            Sample period. [s]
        ctx : RecordContext, optional
            Reference attitude, gravity and distance in the record (needed
            for gravity-disturbance and Markov-in-distance states).

        Returns
        -------
        dtheta_c, dv_c : ndarray, shape (M, k, 3)
        """
        if not self.n:
            return dtheta, dv
        M, k, _ = dtheta.shape
        if self.needs_context and ctx is None:
            raise ValueError("gravity-disturbance and Markov-in-distance feedback need the record context")
        t_mid = (np.arange(k) + 0.5) * h
        t_edge = np.arange(k + 1) * h
        d_mid = ctx.d_mid if ctx is not None else np.zeros(k)
        d_edge = ctx.d_edge if ctx is not None else np.zeros(k + 1)
        dyn = self.dynamic.any()
        f_mid = self._factors(t_mid, d_mid) if dyn else None            # (k, n_s)
        f_edge = self._factors(t_edge, d_edge) if dyn else None         # (k+1, n_s)
        fbar = (dv / h).reshape(M * k, 3)
        wbar = (dtheta / h).reshape(M * k, 3)
        corr = {"gyro": np.zeros((M, k, 3)), "accel": np.zeros((M, k, 3))}
        ad = np.zeros((M, k, 3))
        for b in self.blocks:
            c = self.c[:, b.idx]                                       # (M, nb)
            if b.sensor == "ad_reset":
                # δΔv = Δe per sample: the change of ĉ under its mean dynamics
                step = f_edge[1:, b.idx] - f_edge[:-1, b.idx]          # (k, nb)
                for j, col in enumerate(b.cols):
                    ad[:, :, col] += c[:, j, None] * step[None, :, j]
                continue
            cs = c[:, None, :] * f_mid[None, :, b.idx] if self.dynamic[b.idx].any() else c[:, None, :]
            if b.sensor == "gravity":
                S = ctx.gravity_sensitivity[:, :, b.cols]             # (k, 3, nb)
                corr["accel"] += np.einsum("kin,mkn->mki", S, np.broadcast_to(cs, (M, k, b.idx.size)))
                continue
            S = b.sensitivity(fbar, wbar).reshape(M, k, 3, -1)[..., b.cols]
            corr[b.sensor] += np.einsum("mkin,mkn->mki", S, np.broadcast_to(cs, (M, k, b.idx.size)))
        if dyn:
            self.c = self.c * f_edge[-1][None, :]
        return dtheta - h * corr["gyro"], dv - h * corr["accel"] - ad


@dataclass(frozen=True)
class RecordContext:
    """Reference quantities inside one record (shared by all runs).

    Attributes
    ----------
    d_mid, d_edge : ndarray, shape (k,), (k+1,)
        Distance travelled since the record start at the sample mid-points
        and edges. [m]
    gravity_sensitivity : ndarray, shape (k, 3, 3)
        ``C_n^b diag(g, g, −1)`` at the sample mid-points (reference
        attitude and normal gravity).
    """

    d_mid: np.ndarray
    d_edge: np.ndarray
    gravity_sensitivity: np.ndarray

    @classmethod
    def along(cls, traj, t0: float, h: float, k: int, mounting=None) -> "RecordContext":
        """Context of ``k`` samples of period ``h`` from ``t0``."""
        te = t0 + h * np.arange(k + 1)
        tm = t0 + h * (np.arange(k) + 0.5)
        hi = float(traj.t[-1])
        se = traj.sample(np.minimum(te, hi))
        sm = traj.sample(np.minimum(tm, hi))
        q = sm.q_nb if mounting is None else quat.mul(sm.q_nb, mounting)
        S = np.einsum("kji,kjl->kil", quat.dcm(q), gravity_sensitivity(earth.gravity(sm.lat, sm.h)))
        return cls(sm.distance - se.distance[0], se.distance - se.distance[0], S)


# --------------------------------------------------------------------------
# ensemble
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class Nees:
    """Whitening of a covariance history for NEES at grid times.

    The error vector is the reduced vector of ``labels``: navigation errors
    with the quaternion error replaced by ``φ`` (:data:`REDUCED_NAV`), then
    sensor states (actual error ``x − ĉ``; random constants only, whose
    truth is known in every run).

    Attributes
    ----------
    labels : tuple of str
    steps : ndarray of int, shape (J,)
        Grid indices at which NEES is evaluated.
    scale : ndarray, shape (J, d)
        ``√diag`` of the reduced covariance.
    W : ndarray, shape (J, d, d)
        Whitening of the scaled covariance: ``ε = ‖W (e/scale)‖²``; rows of
        zero eigenvalues are zero.
    dof : ndarray of int, shape (J,)
        Rank of the reduced covariance (the χ² dimension).
    """

    labels: tuple
    steps: np.ndarray
    scale: np.ndarray
    W: np.ndarray
    dof: np.ndarray


def reduction_matrix(names, labels, q) -> np.ndarray:
    """Map a state vector onto a reduced NEES vector.

    Parameters
    ----------
    names : sequence of str
        State names of the covariance (filter or truth order).
    labels : sequence of str
        Reduced labels: :data:`REDUCED_NAV` members and state names.
    q : ndarray, shape (4,)
        True attitude (for ``φ = −2R(q)ᵀδq``).

    Returns
    -------
    ndarray, shape (len(labels), len(names))
    """
    names = list(names)
    T = np.zeros((len(labels), len(names)))
    A = quat.attitude_error_matrix(np.asarray(q, float))
    qi = [names.index(n) for n in ("dq0", "dq1", "dq2", "dq3")]
    for r, lab in enumerate(labels):
        if lab in ("phiN", "phiE", "phiD"):
            T[r, qi] = A["NED".index(lab[-1])]
        else:
            T[r, names.index(lab)] = 1.0
    return T


def nees_whitening(P, names, labels, steps, q, *, rtol: float = 1e-10) -> Nees:
    """Whitening matrices of a covariance history for NEES.

    Parameters
    ----------
    P : ndarray, shape (N+1, n, n)
        Covariance history (filter or truth).
    names : sequence of str
        Its state names.
    labels : sequence of str
        The NEES vector (:func:`reduction_matrix`).
    steps : array_like of int
        Grid indices at which NEES is wanted.
    q : ndarray, shape (N+1, 4)
        True attitude at the grid times.
    rtol : float
        Eigenvalues below ``rtol`` times the largest (of the correlation
        matrix) count as zero: that direction is dropped and the dof reduced.

    Returns
    -------
    Nees
    """
    steps = np.asarray(steps, int)
    d = len(labels)
    scale = np.zeros((steps.size, d))
    W = np.zeros((steps.size, d, d))
    dof = np.zeros(steps.size, int)
    for j, k in enumerate(steps):
        T = reduction_matrix(names, labels, q[k])
        Pr = symmetrize(T @ P[k] @ T.T)
        s = np.sqrt(np.clip(np.diag(Pr), 0.0, None))
        s = np.where(s > 0, s, 1.0)
        C = Pr / np.outer(s, s)
        w, V = np.linalg.eigh(C)
        keep = w > rtol * max(w.max(), 1e-300)
        Wk = (V[:, keep] / np.sqrt(w[keep])).T
        W[j, :Wk.shape[0]] = Wk
        scale[j] = s
        dof[j] = int(keep.sum())
    return Nees(tuple(labels), steps, scale, W, dof)


def expected_nees(spec: Nees, P, names, q):
    """Mean NEES the linear analysis predicts for true covariance P.

    Parameters
    ----------
    spec : Nees
        Whitening of the covariance being tested (e.g. the filter's claim).
    P : ndarray, shape (N+1, n, n)
        Covariance of the actual errors of the same states (e.g. the truth
        covariance under the filter's gains restricted to the filter's
        states, ``Dᵀ P D``).
    names : sequence of str
        State names of ``P``.
    q : ndarray, shape (N+1, 4)
        True attitude at the grid times.

    Returns
    -------
    mean : ndarray, shape (J,)
        ``E[ε] = tr B`` with ``B = W Σ Wᵀ`` and ``Σ`` the scaled reduced ``P``.
    dof : ndarray, shape (J,)
        ``(tr B)² / tr B²``: the per-run degrees of freedom of the scaled χ²
        with the same mean and variance as ``ε`` (Satterthwaite); equal to
        ``spec.dof`` when ``P`` is the covariance being tested.
    """
    mean = np.zeros(spec.steps.size)
    dof = np.zeros(spec.steps.size)
    for j, k in enumerate(spec.steps):
        T = reduction_matrix(names, spec.labels, q[k])
        Sig = symmetrize(T @ P[k] @ T.T) / np.outer(spec.scale[j], spec.scale[j])
        B = spec.W[j] @ Sig @ spec.W[j].T
        tr = np.trace(B)
        mean[j] = tr
        dof[j] = tr**2 / np.sum(B * B) if tr > 0 else 1.0
    return mean, dof


@dataclass(frozen=True)
class EnsembleCase:
    """One case of an ensemble run.

    Attributes
    ----------
    name : str
    filter : FeedbackFilter or None
        None: pure (unaided) INS.  Only ``names`` and ``gains`` are used
        here (``P`` may be empty); see :meth:`FeedbackFilter.design`.
    nees : dict of str to Nees
        NEES specifications to accumulate, e.g. ``{"filter": …, "truth": …}``.
    """

    name: str
    filter: FeedbackFilter | None = None
    nees: dict = field(default_factory=dict)


@dataclass
class EnsembleSums:
    """Ensemble sums of one case, additive over chunks of runs.

    Attributes
    ----------
    n_runs : int
    s1, s2 : ndarray, shape (N+1, 9)
        ``Σ x`` and ``Σ x²`` over runs of :data:`QUANTITIES` at each grid time.
    s_ne : ndarray, shape (N+1,)
        ``Σ δN δE``.
    nees : dict of str to ndarray, shape (J,)
        ``Σ ε`` over runs at the NEES steps.
    """

    n_runs: int
    s1: np.ndarray
    s2: np.ndarray
    s_ne: np.ndarray
    nees: dict = field(default_factory=dict)

    @classmethod
    def zeros(cls, n_times: int, nees: dict | None = None) -> "EnsembleSums":
        z = len(QUANTITIES)
        return cls(0, np.zeros((n_times, z)), np.zeros((n_times, z)), np.zeros(n_times),
                   {k: np.zeros(v.steps.size) for k, v in (nees or {}).items()})

    def __add__(self, other: "EnsembleSums") -> "EnsembleSums":
        return EnsembleSums(self.n_runs + other.n_runs, self.s1 + other.s1, self.s2 + other.s2,
                            self.s_ne + other.s_ne, {k: self.nees[k] + other.nees[k] for k in self.nees})

    def to_json(self) -> dict:
        return {"n_runs": self.n_runs, "s1": self.s1.tolist(), "s2": self.s2.tolist(), "s_ne": self.s_ne.tolist(),
                "nees": {k: v.tolist() for k, v in self.nees.items()}}

    @classmethod
    def from_json(cls, d: dict) -> "EnsembleSums":
        return cls(int(d["n_runs"]), np.array(d["s1"], float), np.array(d["s2"], float), np.array(d["s_ne"], float),
                   {k: np.array(v, float) for k, v in d["nees"].items()})

    def rms(self, quantity: str) -> np.ndarray:
        """Ensemble RMS about zero of a quantity.

        One of :data:`QUANTITIES`, or ``"horizontal"`` (radial).
        """
        if quantity == "horizontal":
            return np.sqrt((self.s2[:, 0] + self.s2[:, 1]) / self.n_runs)
        return np.sqrt(self.s2[:, QUANTITIES.index(quantity)] / self.n_runs)

    def mean(self, quantity: str) -> np.ndarray:
        """Ensemble mean of one of :data:`QUANTITIES`."""
        return self.s1[:, QUANTITIES.index(quantity)] / self.n_runs


def _truth_frames(traj, t, mounting=None):
    tr = sd.truth_state(traj, t, mounting=mounting)
    rm, rn = earth.radii(tr.lat)
    return tr, rm + tr.h, (rn + tr.h) * np.cos(tr.lat), quat.attitude_error_matrix(tr.q)


def run_ensemble(sim, x0, cases, t, *, samples_per_step: int, R, rng=None, measurement_noise: bool = True,
                 model=None, record_errors: bool = False):
    """Run every case of an ensemble in lock step on shared IMU data.

    Parameters
    ----------
    sim : covtool.nav.imu.simulator.ImuSimulator
        Raw IMU increments of the M runs (sensor errors included); one pass
        of its records drives every case, so all cases see the same sensor
        realisations (common random numbers).
    x0 : ndarray, shape (M, n_truth)
        The truth states of the runs (initial navigation errors in the first
        ten columns; random-constant sensor states for NEES).
    cases : sequence of EnsembleCase
    t : ndarray, shape (N+1,)
        Uniform grid of the linear analysis: updates and statistics at
        these times. [s]
    samples_per_step : int
        IMU samples per navigation step n (``dt·rate`` must be a multiple).
    R : ndarray, shape (3, 3)
        True ZUPT measurement noise. [m²/s²]
    rng : numpy.random.Generator or int, optional
        Measurement noise (one draw per update, shared by the cases).
    measurement_noise : bool
        False: noise-free ZUPTs (deterministic checks).
    model : covtool.lincov.model.spec.Model
        The truth model (required when a filter feeds back sensor states or
        NEES involves them).
    record_errors : bool
        Also return the navigation errors of every run at every grid time
        (memory ``(N+1)·M·10`` per case; for tests).

    Returns
    -------
    sums : dict of str to EnsembleSums
    errors : dict of str to ndarray, shape (N+1, M, 10)
        Only if ``record_errors``.
    """
    rng = np.random.default_rng(rng)
    t = np.asarray(t, float)
    dt = float(t[1] - t[0])
    if not np.allclose(np.diff(t), dt, rtol=0, atol=1e-9 * dt):
        raise ValueError("the Monte Carlo grid must be uniform")
    h = sim.dt
    per_step = dt / h
    spr = int(round(per_step))
    n = int(samples_per_step)
    if abs(per_step - spr) > 1e-6 or spr % n:
        raise ValueError(f"a grid step of {dt:g} s holds {per_step:g} IMU samples, not a multiple of "
                         f"{n} samples per navigation step")
    if abs(sim.t0 - t[0]) > 1e-9 or sim.t0 + sim.n_samples * h < t[-1] - 1e-6 * h:
        raise ValueError("the IMU simulator does not cover the grid")
    M = sim.n_runs
    C = len(cases)
    x0 = np.asarray(x0, float)
    N = t.size - 1
    tr, rmh, rnhc, Aq = _truth_frames(sim.traj, t, sim.mounting)
    Lr = np.linalg.cholesky(np.asarray(R, float)) if measurement_noise else None
    # all cases in one navigation state: case i holds rows i·M … (i+1)·M − 1, so one strapdown
    # step advances every run of every case (the step cost is mostly per call, not per run)
    s0 = sim.initial_state(x0[:, :10])
    state = sd.NavState(s0.t, *(np.concatenate([a] * C) for a in (s0.lat, s0.lon, s0.h, s0.v_n, s0.q,
                                                                   s0.dtheta_prev, s0.dv_prev)))
    run = []
    for i, c in enumerate(cases):
        f = c.filter
        fb = SensorFeedback(model, f.names, M) if f is not None and any(nm not in _NAV for nm in f.names) else None
        run.append({"case": c, "rows": slice(i * M, (i + 1) * M), "fb": fb,
                    "nav_cols": [f.names.index(nm) if nm in f.names else -1 for nm in _NAV] if f else None,
                    "sens_cols": [f.names.index(nm) for nm in fb.names] if fb is not None else [],
                    "sums": EnsembleSums.zeros(N + 1, c.nees),
                    "nees_pos": {key: {int(st): j for j, st in enumerate(v.steps)} for key, v in c.nees.items()},
                    "errors": np.empty((N + 1, M, 10)) if record_errors else None})
    upd_steps = sorted({k for c in cases if c.filter is not None for k in c.filter.gains})
    noise = {k: rng.standard_normal((M, 3)) @ Lr.T for k in upd_steps} if Lr is not None else {}
    need_ctx = any(r["fb"] is not None and r["fb"].needs_context for r in run)
    truth_idx = model.index if model is not None else {}

    def observe(k):
        ti = sd.NavState(float(t[k]), tr.lat[k:k + 1], tr.lon[k:k + 1], tr.h[k:k + 1], tr.v_n[k:k + 1],
                         tr.q[k:k + 1], np.zeros((1, 3)), np.zeros((1, 3)))
        E = sd.nav_errors(state, ti)
        PHI = E[:, 6:10] @ Aq[k].T
        X_all = np.column_stack([E[:, 0] * rmh[k], E[:, 1] * rnhc[k], -E[:, 2], E[:, 3:6], PHI])
        for r in run:
            e, phi, X = E[r["rows"]], PHI[r["rows"]], X_all[r["rows"]]
            if r["errors"] is not None:
                r["errors"][k] = e
            s = r["sums"]
            s.s1[k] += X.sum(axis=0)
            s.s2[k] += (X * X).sum(axis=0)
            s.s_ne[k] += float(np.dot(X[:, 0], X[:, 1]))
            for key, spec in r["case"].nees.items():
                j = r["nees_pos"][key].get(k)
                if j is None:
                    continue
                vec = np.empty((M, len(spec.labels)))
                for col, lab in enumerate(spec.labels):
                    if lab in REDUCED_NAV[:6]:
                        vec[:, col] = e[:, _NAV.index(lab)]
                    elif lab in ("phiN", "phiE", "phiD"):
                        vec[:, col] = phi[:, "NED".index(lab[-1])]
                    else:
                        fb = r["fb"]
                        est = fb.c[:, fb.names.index(lab)] if fb is not None and lab in fb.names else 0.0
                        vec[:, col] = x0[:, truth_idx[lab]] - est
                u = np.einsum("ij,mj->mi", spec.W[j], vec / spec.scale[j])
                s.nees[key][j] += float(np.sum(u * u))

    def update(k):
        dx = None
        for r in run:
            f = r["case"].filter
            if f is None or k not in f.gains:
                continue
            z = state.v_n[r["rows"]] - 0.0                              # ZUPT: the true velocity is zero
            if Lr is not None:
                z = z + noise[k]
            xh = z @ f.gains[k].T                                       # x̂ = K z, (M, n_f)
            if dx is None:
                dx = np.zeros((C * M, 10))
            for i, col in enumerate(r["nav_cols"]):
                if col >= 0:
                    dx[r["rows"], i] = xh[:, col]
            if r["fb"] is not None:
                r["fb"].add(xh[:, r["sens_cols"]])
        return state if dx is None else sd.correct(state, dx)

    records = sim.records(chunk=spr * max(1, int(round(60.0 / dt))))
    buf, pos = None, 0
    for k in range(N + 1):
        state = update(k)
        observe(k)
        if k == N:
            break
        if buf is None or pos >= buf.dtheta.shape[-2]:
            buf, pos = next(records), 0
        rec = buf.slice(pos, pos + spr)
        pos += spr
        ctx = RecordContext.along(sim.traj, rec.t0, h, spr, sim.mounting) if need_ctx else None
        raw_th = np.broadcast_to(rec.dtheta, (M, spr, 3))
        raw_dv = np.broadcast_to(rec.dv, (M, spr, 3))
        parts = [r["fb"].compensate(raw_th, raw_dv, h, ctx) if r["fb"] is not None else (raw_th, raw_dv)
                 for r in run]
        dth = np.concatenate([p[0] for p in parts])
        dvv = np.concatenate([p[1] for p in parts])
        hist = sd.run(state, type(rec)(rec.t0, h, dth, dvv), n, every=10**9)
        state = hist.state(-1).replace(t=float(t[k + 1]), dtheta_prev=dth[:, -1, :].copy(),
                                       dv_prev=dvv[:, -1, :].copy())
    for r in run:
        r["sums"].n_runs = M
    sums = {r["case"].name: r["sums"] for r in run}
    if record_errors:
        return sums, {r["case"].name: r["errors"] for r in run}
    return sums


def simulate_chunk(task: dict) -> dict:
    """One chunk of runs of a Monte Carlo study (runs in a worker).

    Parameters
    ----------
    task : dict
        ``traj``, ``model`` (truth), ``t`` (grid), ``runs`` (M), ``seed``
        (a :class:`numpy.random.SeedSequence` entropy/spawn key pair),
        ``imu_rate``, ``samples_per_step``, ``R``, ``cases`` (list of
        :class:`EnsembleCase`), ``sensor_noise``, ``measurement_noise``,
        ``process_dt``.

    Returns
    -------
    dict
        ``sums``: case → :meth:`EnsembleSums.to_json`; ``seconds``.

    Notes
    -----
    The chunk's three random streams (initial states, sensor noise, ZUPT
    noise) are children of ``SeedSequence(seed, spawn_key=(chunk,))``, so a
    chunk's result depends only on the study seed and its index, never on
    the backend or the order in which chunks finish.
    """
    import time

    from covtool.nav.imu.simulator import ImuSimulator
    from covtool.validation.sensor_errors import SensorErrors, sample_states

    t0 = time.perf_counter()
    ss = np.random.SeedSequence(task["seed"], spawn_key=(int(task["chunk"]),))
    r_x0, r_sensor, r_meas = (np.random.default_rng(s) for s in ss.spawn(3))
    traj, model, t = task["traj"], task["model"], np.asarray(task["t"], float)
    M = int(task["runs"])
    x0 = sample_states(model, M, r_x0, q0=traj.sample([t[0]]).q_nb[0])
    errors = SensorErrors(model, x0, r_sensor, noise=task.get("sensor_noise", True),
                          process_dt=task.get("process_dt", 0.1))
    sim = ImuSimulator(traj, task["imu_rate"], t0=float(t[0]), duration=float(t[-1] - t[0]), errors=errors)
    sums = run_ensemble(sim, x0, task["cases"], t, samples_per_step=task["samples_per_step"], R=task["R"],
                        rng=r_meas, measurement_noise=task.get("measurement_noise", True), model=model)
    return {"sums": {k: v.to_json() for k, v in sums.items()}, "seconds": time.perf_counter() - t0}


# --------------------------------------------------------------------------
# χ² bounds
# --------------------------------------------------------------------------


def rms_bounds(sigma, n_runs: int, dof_per_run=1.0, confidence: float = 0.95):
    """Two-sided χ² bounds of an ensemble RMS.

    Parameters
    ----------
    sigma : array_like
        Predicted σ (for the radial horizontal error, ``√(σ_N² + σ_E²)``).
    n_runs : int
        Number of runs N.
    dof_per_run : array_like
        Degrees of freedom per run (1 for a scalar; :func:`horizontal_dof`
        for the radial horizontal error).
    confidence : float

    Returns
    -------
    lo, hi : ndarray
        ``σ √(χ²_{ν,α/2}/ν)`` and ``σ √(χ²_{ν,1−α/2}/ν)`` with
        ``ν = N · dof_per_run``.
    """
    a = 1.0 - confidence
    nu = np.asarray(n_runs * np.asarray(dof_per_run, float))
    sigma = np.asarray(sigma, float)
    return (sigma * np.sqrt(stats.chi2.ppf(0.5 * a, nu) / nu),
            sigma * np.sqrt(stats.chi2.ppf(1.0 - 0.5 * a, nu) / nu))


def horizontal_dof(P2) -> np.ndarray:
    """Satterthwaite degrees of freedom per run of ``δN² + δE²``.

    Parameters
    ----------
    P2 : ndarray, shape (..., 2, 2)
        Horizontal position covariance. [m²]

    Returns
    -------
    ndarray, shape (...)
        ``(λ₁+λ₂)²/(λ₁²+λ₂²)`` ∈ [1, 2]: 2 for a circular error, 1 for a
        degenerate one (1 where the covariance is zero).
    """
    w = np.clip(np.linalg.eigvalsh(symmetrize(np.asarray(P2, float))), 0.0, None)
    num = w.sum(axis=-1) ** 2
    den = (w * w).sum(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)


def nees_bounds(dof, n_runs: int, confidence: float = 0.95, mean=None):
    """χ² bounds of the mean NEES over N runs.

    Parameters
    ----------
    dof : array_like
        Degrees of freedom per run ``d`` (the NEES dimension when the tested
        covariance is the true one).
    n_runs : int
    confidence : float
    mean : array_like, optional
        Expected NEES when the tested covariance is not the true one
        (:func:`expected_nees`; ``dof`` is then its Satterthwaite dof).

    Returns
    -------
    lo, hi : ndarray
        ``m χ²_{Nd,α/2}/(Nd)`` and ``m χ²_{Nd,1−α/2}/(Nd)`` with ``m = d``
        unless given: for a consistent covariance ``N ε̄ ~ χ²_{Nd}``.
    """
    a = 1.0 - confidence
    d = np.asarray(dof, float)
    m = d if mean is None else np.asarray(mean, float)
    nd = d * n_runs
    return m * stats.chi2.ppf(0.5 * a, nd) / nd, m * stats.chi2.ppf(1.0 - 0.5 * a, nd) / nd


def inside_fraction(x, lo, hi, *, rtol: float = 1e-12) -> dict:
    """Fractions of points inside, above and below ``[lo, hi]``.

    Points where ``hi == 0`` (a zero predicted σ, e.g. the initial position)
    count as inside when ``x`` is zero to ``rtol`` of the largest ``x``.
    """
    x, lo, hi = (np.asarray(a, float) for a in (x, lo, hi))
    tol = rtol * max(float(np.max(np.abs(x))) if x.size else 0.0, 1e-300)
    above = x > hi + tol
    below = x < lo - tol
    n = max(x.size, 1)
    return {"inside": 1.0 - (above.sum() + below.sum()) / n, "above": above.sum() / n, "below": below.sum() / n,
            "points": int(x.size)}
