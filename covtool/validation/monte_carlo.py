"""Monte Carlo validation: real feedback filters on a simulated INS.

Pure numeric core (arrays in, arrays out): an ensemble of M nonlinear
strapdown INS runs (:mod:`covtool.nav.strapdown`) driven by an IMU simulator
(:mod:`covtool.nav.imu.simulator`) with errors drawn from a truth model
(:mod:`covtool.validation.sensor_errors`), each optionally aided by a reduced
ZUPT Kalman filter that runs as a *real* indirect feedback filter (seed 002,
Fig 1, eq (6)–(10); :mod:`covtool.validation.feedback`).  For every case and
grid time the ensemble sums ``Σx`` and ``Σx²`` of the NED position errors,
the velocity errors and the attitude errors (``φ = −2R(q)ᵀδq``) are kept
(:class:`EnsembleSums`, additive over chunks of runs), and the sums of NEES
values of the filter's claimed covariance and of the linear analysis's
truth covariance (:class:`covtool.analysis.consistency.Nees`); the χ² bounds
they are compared with are in :mod:`covtool.analysis.consistency`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from covtool.nav import attitude as quat, earth, strapdown as sd
from covtool.validation.feedback import compensate_cases, FeedbackFilter, RecordContext, SensorFeedback

__all__ = [
    "QUANTITIES", "EnsembleCase", "EnsembleSums", "Zupt", "run_ensemble", "simulate_chunk", "initial_states",
    "reference_along",
    "reference_inputs",
]


#: quantities summed per grid time: NED position [m], NED velocity [m/s], tilts and azimuth [rad]
QUANTITIES = ("north", "east", "down", "vn", "ve", "vd", "tilt_n", "tilt_e", "azimuth")


_NAV = sd.NAV_STATES


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


class Zupt:
    """The ZUPT as a measurement of the ensemble loop (seed 002, eq (9)).

    The measurement hook of :func:`run_ensemble`: while the vehicle stands
    still the true velocity is zero, so the residual of a run is its own
    velocity ``z = v̂ⁿ + v`` [m/s], ``v ~ N(0, R)`` one draw per update shared
    by the cases (common random numbers).  A hook has:

    * ``filter_states``: filter states that belong to the measurement (its
      own error states), not fed back into the INS or the IMU compensation;
    * ``start(cases, n_runs, steps, rng)``: before the first step;
    * ``residual(k, i, state, rows) -> ndarray, shape (M, m)``: the residual
      of case ``i`` at update step ``k`` from its runs' navigation state;
    * ``estimated(k, i, xh)``: the case's estimate ``x̂ = K z`` (n_f columns);
    * ``advance(k0, k1)``: the grid steps ``k0 … k1 − 1`` were integrated.

    Parameters
    ----------
    R : ndarray, shape (3, 3)
        True ZUPT noise. [m²/s²]
    noise : bool
        False: noise-free ZUPTs.
    """

    filter_states: tuple = ()

    def __init__(self, R, noise: bool = True):
        self.R = np.asarray(R, float)
        self.noise = bool(noise)
        self._v: dict = {}

    def start(self, cases, n_runs: int, steps, rng) -> None:
        # every update's noise drawn at once, in step order (the stream of the chunk's ZUPT noise)
        if self.noise:
            Lr = np.linalg.cholesky(self.R)
            self._v = {k: rng.standard_normal((n_runs, 3)) @ Lr.T for k in steps}

    def residual(self, k: int, i: int, state, rows) -> np.ndarray:
        z = state.v_n[rows] - 0.0                           # ZUPT: the true velocity is zero
        return z + self._v[k] if self.noise else z

    def estimated(self, k: int, i: int, xh) -> None:
        pass

    def advance(self, k0: int, k1: int) -> None:
        pass


def _truth_frames(traj, t, mounting=None):
    tr = sd.truth_state(traj, t, mounting=mounting)
    rm, rn = earth.radii(tr.lat)
    return tr, rm + tr.h, (rn + tr.h) * np.cos(tr.lat), quat.attitude_error_matrix(tr.q)


def _spans(N: int, dt: float, upd_steps) -> tuple:
    """Record length (grid steps) and the spans ``(k, b)`` of :func:`run_ensemble`.

    A span runs from grid step ``k`` to ``b`` with no update strictly inside
    and within one 60-s IMU record.
    """
    chunk_steps = max(1, int(round(60.0 / dt)))
    upd_after = np.array(sorted(upd_steps) + [N], int)
    spans, k = [], 0
    while k < N:
        b = min(int(upd_after[np.searchsorted(upd_after, k, side="right")]), (k // chunk_steps + 1) * chunk_steps, N)
        spans.append((k, b))
        k = b
    return chunk_steps, spans


def reference_along(traj, t, update_steps, filter_names, *, imu_rate: float, samples_per_step: int, model=None,
                    process_dt: float = 0.1, mounting=None) -> dict:
    """What every chunk of runs samples from the trajectory, sampled once.

    The exact IMU increments, the reference attitude, gravity and speed the
    sensor errors need (the simulator's ``truth_cache``), and the
    :class:`RecordContext` of every span of the feedback compensation: they
    depend on the trajectory, the grid and the update steps, never on the
    runs, so a study computes them once and hands them to every chunk
    (:func:`simulate_chunk`, ``task["reference"]``).  The very calls a chunk
    would make are made here, so the values are the same bit for bit.

    It needs the cases only through their update steps and the states
    their filters feed back (:func:`reference_inputs`), so a study can
    sample it before the cases' gains exist (in another process, while it
    computes them).

    Parameters
    ----------
    traj, t, imu_rate, samples_per_step, model, process_dt, mounting
        As for :func:`simulate_chunk` and :func:`run_ensemble`.
    update_steps : sequence of int
        The steps at which some filter updates (the keys of the gains).
    filter_names : sequence of list of str
        The state names of each feedback filter.

    Returns
    -------
    dict
        ``truth``: the filled ``truth_cache``; ``contexts``: ``(k, b)`` →
        :class:`RecordContext` of each span (only when a filter feeds back
        gravity-disturbance or Markov-in-distance states).
    """
    from covtool.nav.imu.simulator import ImuSimulator
    from covtool.validation.sensor_errors import SensorErrors

    t = np.asarray(t, float)
    dt = float(t[1] - t[0])
    cache = {}
    errors = SensorErrors(model, np.zeros((1, model.n)), None, noise=False, process_dt=process_dt) \
        if model is not None else None
    sim = ImuSimulator(traj, imu_rate, t0=float(t[0]), duration=float(t[-1] - t[0]), errors=errors,
                       mounting=mounting, truth_cache=cache)
    sim.initial_state()
    N = t.size - 1
    chunk_steps, spans = _spans(N, dt, sorted({int(k) for k in update_steps}))
    spr = int(round(dt / sim.dt))
    sim.fill_cache(chunk=spr * chunk_steps)           # the calls of a chunk's pass, without its errors
    contexts = None
    need = [SensorFeedback(model, names, 1) for names in filter_names] if model else []
    if any(f.n and f.needs_context for f in need):
        contexts = {}
        for k, b in spans:
            buf_k0 = (k // chunk_steps) * chunk_steps
            buf_t0 = sim.t0 + (buf_k0 * spr) * sim.dt         # ImuSimulator.records, then ImuRecord.slice
            rec_t0 = buf_t0 + ((k - buf_k0) * spr) * sim.dt
            contexts[(k, b)] = RecordContext.along(traj, rec_t0, sim.dt, (b - k) * spr, sim.mounting)
    return {"truth": cache, "contexts": contexts}


class SharedReference:
    """A :func:`reference_along` written once to a file that every chunk of runs maps, not copies.

    The reference (the trajectory at the IMU rate: about 180 bytes a sample,
    1.5 GB over 24 h at 100 Hz) would otherwise be pickled into every chunk
    in flight and unpickled by every worker.  Here it is pickled once
    (protocol 5) with its arrays' buffers out of band, after the pickle in
    the same file; a worker maps the file read-only and the arrays are
    views of the mapping, so the processes of one machine share its pages.
    The values are those of the reference, bit for bit.

    Parameters
    ----------
    reference : dict
        :func:`reference_along`'s result.
    path : path
        The file (inside the study's output directory); :meth:`remove` deletes it.
    """

    _ALIGN = 64

    def __init__(self, reference: dict, path):
        import pickle
        from pathlib import Path

        self.path = Path(path)
        buffers = []
        head = pickle.dumps(reference, protocol=5, buffer_callback=buffers.append)
        raws = [b.raw() for b in buffers]
        index, off = [], 0
        for r in raws:
            off = -(-off // self._ALIGN) * self._ALIGN
            index.append((off, r.nbytes))
            off += r.nbytes
        meta = pickle.dumps((head, index), protocol=5)
        start = self._start(len(meta))
        with open(self.path, "wb") as f:
            f.write(len(meta).to_bytes(8, "little"))
            f.write(meta)
            for (o, _), r in zip(index, raws):
                f.seek(start + o)
                f.write(r)
            f.truncate(start + off)

    @classmethod
    def _start(cls, meta_len: int) -> int:
        return -(-(8 + meta_len) // cls._ALIGN) * cls._ALIGN

    def load(self) -> dict:
        """The reference, its arrays read-only views of the mapped file."""
        import pickle

        with open(self.path, "rb") as f:
            n = int.from_bytes(f.read(8), "little")
            head, index = pickle.loads(f.read(n))
        start = self._start(n)
        mm = np.memmap(self.path, mode="r", dtype=np.uint8) if index else None
        return pickle.loads(head, buffers=[mm[start + o:start + o + size] for o, size in index])

    def remove(self) -> None:
        """Delete the file (a missing one is fine)."""
        self.path.unlink(missing_ok=True)


def reference_inputs(cases) -> tuple[list, list]:
    """``(update_steps, filter_names)`` of :func:`reference_along` for the ensemble ``cases``.

    Parameters
    ----------
    cases : sequence of EnsembleCase

    Returns
    -------
    update_steps : list of int
        Sorted steps of every feedback filter's gains.
    filter_names : list of list of str
        Each feedback filter's state names, in the cases' order.
    """
    steps = sorted({int(k) for c in cases if c.filter is not None for k in c.filter.gains})
    return steps, [list(c.filter.names) for c in cases if c.filter is not None]


def run_ensemble(sim, x0, cases, t, *, samples_per_step: int, R=None, rng=None, measurement_noise: bool = True,
                 model=None, record_errors: bool | str = False, measurement=None, contexts: dict | None = None):
    """Run every case of an ensemble in lock step on shared IMU data.

    The one ensemble loop of the Monte Carlo: ZUPT filters (``R``) and
    filters with declared measurements (``measurement``,
    :class:`covtool.validation.aided.DeclaredMeasurements`) run through it.

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
    R : ndarray, shape (3, 3), optional
        True ZUPT measurement noise [m²/s²] (the measurement is then
        :class:`Zupt`).
    rng : numpy.random.Generator or int, optional
        Measurement noise (one draw per update, shared by the cases) and
        whatever else the measurement hook draws.
    measurement_noise : bool
        False: noise-free ZUPTs (deterministic checks).
    measurement : object, optional
        The measurement hook (:class:`Zupt` describes its methods) instead
        of ``R``.
    model : covtool.lincov.model.spec.Model
        The truth model (required when a filter feeds back sensor states or
        NEES involves them).
    record_errors : bool or "quantities"
        Also return the errors of every run at every grid time: True the
        ten navigation errors (memory ``(N+1)·M·10`` per case; for tests),
        ``"quantities"`` the nine :data:`QUANTITIES` (NED metres, m/s, rad).
    contexts : dict, optional
        The :class:`RecordContext` of each span, ``reference_along(...)["contexts"]``
        (computed here when not given).

    Returns
    -------
    sums : dict of str to EnsembleSums
    errors : dict of str to ndarray, shape (N+1, M, 10) or (N+1, M, 9)
        Only if ``record_errors``.

    Raises
    ------
    ValueError
        A grid that is not uniform or not a whole number of navigation
        steps, an IMU simulator that does not cover it, neither or both of
        ``R`` and ``measurement``.
    """
    from covtool.analysis.consistency import REDUCED_NAV    # with scipy.special (0.2 s): not at a chunk worker's import

    if (R is None) == (measurement is None):
        raise ValueError("run_ensemble: give exactly one of R (ZUPT) and measurement")
    meas = Zupt(R, measurement_noise) if measurement is None else measurement
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
    # all cases in one navigation state: case i holds rows i·M … (i+1)·M − 1, so one strapdown
    # step advances every run of every case (the step cost is mostly per call, not per run)
    s0 = sim.initial_state(x0[:, :10])
    state = sd.NavState(s0.t, *(np.concatenate([a] * C) for a in (s0.lat, s0.lon, s0.h, s0.v_n, s0.q,
                                                                   s0.dtheta_prev, s0.dv_prev)))
    run = []
    own = set(meas.filter_states)           # the measurement's own error states: estimated by the hook
    for i, c in enumerate(cases):
        f = c.filter
        sens = [nm for nm in f.names if nm not in own] if f is not None else []
        fb = SensorFeedback(model, sens, M) if any(nm not in _NAV for nm in sens) else None
        run.append({"case": c, "rows": slice(i * M, (i + 1) * M), "fb": fb,
                    "nav_cols": [f.names.index(nm) if nm in f.names else -1 for nm in _NAV] if f else None,
                    "sens_cols": [f.names.index(nm) for nm in fb.names] if fb is not None else [],
                    "sums": EnsembleSums.zeros(N + 1, c.nees),
                    "nees_pos": {key: {int(st): j for j, st in enumerate(v.steps)} for key, v in c.nees.items()},
                    "errors": np.empty((N + 1, M, 9 if record_errors == "quantities" else 10))
                    if record_errors else None})
    upd_steps = sorted({k for c in cases if c.filter is not None for k in c.filter.gains})
    meas.start(cases, M, upd_steps, rng)
    need_ctx = any(r["fb"] is not None and r["fb"].needs_context for r in run)
    truth_idx = model.index if model is not None else {}

    CM = C * M

    def observe(ks, st):
        """Add the errors of ``st`` (grid steps ``ks``, rows g-major: (G·C·M,)) to the sums."""
        ks = np.asarray(ks, int)
        G = ks.size
        ti = sd.NavState(float(t[ks[0]]), np.repeat(tr.lat[ks], CM), np.repeat(tr.lon[ks], CM),
                         np.repeat(tr.h[ks], CM), np.repeat(tr.v_n[ks], CM, axis=0), np.repeat(tr.q[ks], CM, axis=0),
                         None, None)
        E = sd.nav_errors(st, ti).reshape(G, CM, 10)
        PHI = np.einsum("gij,grj->gri", Aq[ks], E[:, :, 6:10])
        X_all = np.concatenate([(E[:, :, 0] * rmh[ks, None])[..., None], (E[:, :, 1] * rnhc[ks, None])[..., None],
                                -E[:, :, 2:3], E[:, :, 3:6], PHI], axis=-1)
        for r in run:
            e, phi, X = E[:, r["rows"]], PHI[:, r["rows"]], X_all[:, r["rows"]]
            if r["errors"] is not None:
                r["errors"][ks] = X if record_errors == "quantities" else e
            s = r["sums"]
            s.s1[ks] += X.sum(axis=1)
            s.s2[ks] += (X * X).sum(axis=1)
            s.s_ne[ks] += np.einsum("gm,gm->g", X[:, :, 0], X[:, :, 1])
            for key, spec in r["case"].nees.items():
                for g, k in enumerate(ks):
                    j = r["nees_pos"][key].get(int(k))
                    if j is None:
                        continue
                    vec = np.empty((M, len(spec.labels)))
                    for col, lab in enumerate(spec.labels):
                        if lab in REDUCED_NAV[:6]:
                            vec[:, col] = e[g, :, _NAV.index(lab)]
                        elif lab in ("phiN", "phiE", "phiD"):
                            vec[:, col] = phi[g, :, "NED".index(lab[-1])]
                        else:
                            # a random constant: its truth is x0, its estimate ĉ does not change between
                            # updates, so the ĉ at the end of the span is the one at this grid step
                            fb = r["fb"]
                            est = fb.c[:, fb.names.index(lab)] if fb is not None and lab in fb.names else 0.0
                            vec[:, col] = x0[:, truth_idx[lab]] - est
                    u = np.einsum("ij,mj->mi", spec.W[j], vec / spec.scale[j])
                    s.nees[key][j] += float(np.sum(u * u))

    def update(k):
        dx = None
        for ci, r in enumerate(run):
            f = r["case"].filter
            if f is None or k not in f.gains:
                continue
            z = meas.residual(k, ci, state, r["rows"])
            xh = z @ f.gains[k].T                                       # x̂ = K z, (M, n_f)
            if dx is None:
                dx = np.zeros((C * M, 10))
            for i, col in enumerate(r["nav_cols"]):
                if col >= 0:
                    dx[r["rows"], i] = xh[:, col]
            if r["fb"] is not None:
                r["fb"].add(xh[:, r["sens_cols"]])
            meas.estimated(k, ci, xh)
        return state if dx is None else sd.correct(state, dx)

    # The run advances in spans of grid steps with no update inside: the feedback estimates then
    # follow their mean dynamics, so a whole span is compensated, turned into body increments and
    # integrated (compiled strapdown kernel) at once, and its grid states are observed together.
    # The IMU records keep their 60-s chunking (the random draws do not depend on the spans).
    chunk_steps, spans = _spans(N, dt, upd_steps)
    records = sim.records(chunk=spr * chunk_steps)
    buf, buf_k0 = None, 0
    # the increments the strapdown reads, one buffer for the whole pass: the raw record in rows 0 … M−1
    # (cases without sensor feedback), then each sensor-feedback case's compensated increments
    fed = [r for r in run if r["fb"] is not None]
    src_th = np.empty(((1 + len(fed)) * M, spr * chunk_steps, 3))
    src_dv = np.empty_like(src_th)
    slot = {id(r): (1 + j) * M for j, r in enumerate(fed)}
    run_rows = np.concatenate([slot.get(id(r), 0) + np.arange(M) for r in run]).astype(np.int64)
    k = 0
    for k, b in spans + [(N, N)]:
        state = update(k)
        observe([k], state)
        if k == N:
            break
        if buf is None or k >= buf_k0 + chunk_steps:
            buf, buf_k0 = next(records), (k // chunk_steps) * chunk_steps
        rec = buf.slice((k - buf_k0) * spr, (b - buf_k0) * spr)
        K = (b - k) * spr
        ctx = None
        if need_ctx:
            ctx = contexts.get((k, b)) if contexts is not None else None
            if ctx is None:
                ctx = RecordContext.along(sim.traj, rec.t0, h, K, sim.mounting)
        dth, dvv = src_th[:, :K], src_dv[:, :K]
        dth[:M] = rec.dtheta
        dvv[:M] = rec.dv
        if fed:
            compensate_cases([r["fb"] for r in fed], dth[:M], dvv[:M], h, ctx, out=(dth[M:], dvv[M:]))
        hist = sd.run(state, type(rec)(rec.t0, h, dth, dvv), n, every=spr // n, rows=run_rows)
        if b - k > 1:
            G = b - k - 1
            inner = sd.NavState(float(t[k + 1]), hist.lat[1:b - k].reshape(-1), hist.lon[1:b - k].reshape(-1),
                                hist.h[1:b - k].reshape(-1), hist.v_n[1:b - k].reshape(G * CM, 3),
                                hist.q[1:b - k].reshape(G * CM, 4), None, None)
            observe(np.arange(k + 1, b), inner)
        state = hist.state(-1).replace(t=float(t[b]), dtheta_prev=dth[run_rows, -1, :],
                                       dv_prev=dvv[run_rows, -1, :])
        meas.advance(k, b)
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
        ``process_dt``; optionally ``reference`` (:func:`reference_along`:
        the trajectory sampled once for all chunks).

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
    from covtool.validation.sensor_errors import SensorErrors

    t0 = time.perf_counter()
    _, r_sensor, r_meas = _streams(task["seed"], task["chunk"])
    traj, model, t = task["traj"], task["model"], np.asarray(task["t"], float)
    M = int(task["runs"])
    x0 = initial_states(model, M, task["seed"], task["chunk"], traj.sample([t[0]]).q_nb[0])
    errors = SensorErrors(model, x0, r_sensor, noise=task.get("sensor_noise", True),
                          process_dt=task.get("process_dt", 0.1))
    ref = task.get("reference")
    if isinstance(ref, SharedReference):
        ref = ref.load()
    cache = ImuSimulator.adopt_cache(ref["truth"], traj) if ref is not None else None
    sim = ImuSimulator(traj, task["imu_rate"], t0=float(t[0]), duration=float(t[-1] - t[0]), errors=errors,
                       truth_cache=cache)
    sums = run_ensemble(sim, x0, task["cases"], t, samples_per_step=task["samples_per_step"], R=task["R"],
                        rng=r_meas, measurement_noise=task.get("measurement_noise", True), model=model,
                        contexts=ref["contexts"] if ref is not None else None)
    return {"sums": {k: v.to_json() for k, v in sums.items()}, "seconds": time.perf_counter() - t0}


def _streams(seed, chunk):
    """The chunk's three random streams: initial states, sensor noise, ZUPT noise."""
    ss = np.random.SeedSequence(seed, spawn_key=(int(chunk),))
    return tuple(np.random.default_rng(s) for s in ss.spawn(3))


def initial_states(model, runs: int, seed, chunk: int, q0) -> np.ndarray:
    """The initial error states a chunk of runs draws (:func:`simulate_chunk`).

    Parameters
    ----------
    model : covtool.lincov.model.spec.Model
        The truth model (its P0 at the initial attitude).
    runs : int
        Runs M of the chunk.
    seed : int
        The study seed.
    chunk : int
        The chunk index.
    q0 : ndarray, shape (4,)
        True initial attitude ``q_nb``.

    Returns
    -------
    ndarray, shape (M, n_truth)
        Exactly the draws the chunk's runs start from, so the study can form
        their sample second moments (the conditional linear prediction,
        ``docs/monte_carlo.md``) without storing them.
    """
    from covtool.validation.sensor_errors import sample_states

    return sample_states(model, int(runs), _streams(seed, chunk)[0], q0=q0)
