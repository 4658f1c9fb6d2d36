"""The time grid of a study and the truth on it: motion per step, discretisation, initial covariance."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from covtool.analysis.metrics import first_invalid, nav_metrics, validity_text
from covtool.errors import CovtoolError, StudyFileError
from covtool.lincov.discretize import discretize
from covtool.lincov.discretize.steps import on_grid
from covtool.lincov.dynamics import Context, error_dynamics, NavOptions
from covtool.lincov.kalman import check_covariance, check_system
from covtool.lincov.model.spec import Model
from covtool.nav import attitude as quat, earth
from covtool.studies.resources import DISCRETIZE_CHUNK, progress_bar

__all__ = [
    "time_grid", "truth_system", "truth_stream", "discretize_steps", "check_step_motion", "step_motion", "initial_covariance",
]


def time_grid(duration: float, dt: float, where: str = "<study>") -> np.ndarray:
    """Grid ``0, dt, …, duration`` (the last step shortened if needed).

    Parameters
    ----------
    duration, dt : float
        Span and step. [s]
    where : str
        File named in error messages.

    Returns
    -------
    ndarray, shape (N+1,)
        ``duration`` or ``dt`` not finite and positive, or ``dt > duration``.
    """
    for key, x in (("duration", duration), ("dt", dt)):
        if not (np.isfinite(x) and x > 0):
            raise StudyFileError(f"{where}: [study] {key}", f"{x!r} s must be finite and positive")
    if dt > duration * (1 + 1e-12):
        raise StudyFileError(f"{where}: [study] dt", f"{dt:g} s is longer than the duration ({duration:g} s)")
    n = int(np.floor(duration / dt + 1e-9))
    t = np.arange(n + 1) * dt
    if duration - t[-1] > 1e-9 * dt:
        t = np.append(t, duration)
    return t


def midpoint_context(traj, t: np.ndarray) -> Context:
    """Trajectory at the step mid-points (F is held constant over a step)."""
    tm = 0.5 * (t[:-1] + t[1:])
    return Context.from_trajectory(traj.sample(tm))


#: largest rotation of the vehicle (body relative to the navigation frame) F may be held over: 0.1 rad
MAX_STEP_ROTATION = 0.1
#: largest change of the specific force ``f^n`` within a step, relative to g, F may be held over
MAX_STEP_FORCE_CHANGE = 0.1


@dataclass(frozen=True)
class StepMotion:
    """Motion inside each step of a grid (what holding F constant ignores).

    Attributes
    ----------
    rotation : ndarray, shape (N,)
        ``Δt × max |ω_nb|`` over the step: the most the body can turn
        relative to the navigation frame within it. [rad]
    force : ndarray, shape (N,)
        ``max |f^n(t) − f^n(t_mid)| / g`` over the step. [-]
    peak_rate : float
        Largest ``|ω_nb|`` along the grid's span. [rad/s]
    peak_force_rate : float
        Largest ``|ḟ^n|/g`` along the span (finite differences). [1/s]
    """

    rotation: np.ndarray
    force: np.ndarray
    peak_rate: float
    peak_force_rate: float

    def largest_dt(self) -> float:
        """Largest step that meets both limits anywhere on the span. [s]

        ``Δθ ≤ Δt max|ω_nb|`` and ``|f^n(t) − f^n(t_m)| ≤ max|ḟ^n| Δt/2``.
        """
        dts = [MAX_STEP_ROTATION / self.peak_rate if self.peak_rate > 0 else np.inf,
               2.0 * MAX_STEP_FORCE_CHANGE / self.peak_force_rate if self.peak_force_rate > 0 else np.inf]
        return float(min(dts))


def step_motion(traj, t: np.ndarray, *, resolution: float = 0.25) -> StepMotion:
    """Rotation and specific-force change inside each step of ``t``.

    Parameters
    ----------
    traj : Trajectory
    t : ndarray, shape (N+1,)
        Grid. [s]
    resolution : float
        Largest spacing of the samples inside a step (at least 8 per step;
        the trajectory's own samples are added). [s]

    Returns
    -------
    StepMotion
    """
    t = np.asarray(t, float)
    dt = np.diff(t)
    span = t[-1] - t[0]
    res = max(resolution, span / 2e5)
    k = np.maximum(8, np.ceil(dt / res)).astype(int)
    k += k % 2                                             # the mid-point is a sample
    pieces = [t[i] + dt[i] * np.arange(k[i]) / k[i] for i in range(dt.size)]
    own = traj.t[(traj.t > t[0]) & (traj.t < t[-1])]
    s = np.unique(np.concatenate(pieces + [own, t[-1:]]))
    smp = traj.sample(s)
    C = quat.dcm(smp.q_nb)                                 # C_b^n
    w_in = earth.earth_rate_n(smp.lat) + earth.transport_rate_n(smp.lat, smp.h, smp.v_n)
    w_nb = smp.w_ib_b - np.einsum("kji,kj->ki", C, w_in)
    rate = np.linalg.norm(w_nb, axis=1)
    f_n = np.einsum("kij,kj->ki", C, smp.f_b)
    g = earth.gravity(smp.lat, smp.h)
    first = np.searchsorted(s, t[:-1])
    last = np.searchsorted(s, t[1:])                       # the step's end sample (shared)
    mid = np.searchsorted(s, 0.5 * (t[:-1] + t[1:]))
    seg = np.repeat(np.arange(dt.size), last - first + 1)
    pos = np.concatenate([np.arange(a, b + 1) for a, b in zip(first, last)])
    rot = np.zeros(dt.size)
    np.maximum.at(rot, seg, rate[pos])
    df = np.linalg.norm(f_n[pos] - f_n[mid][seg], axis=1) / g[mid][seg]
    force = np.zeros(dt.size)
    np.maximum.at(force, seg, df)
    jerk = np.linalg.norm(np.diff(f_n, axis=0), axis=1) / np.diff(s) / g[1:]
    return StepMotion(rot * dt, force, float(rate.max()), float(jerk.max(initial=0.0)))


def check_step_motion(traj, t: np.ndarray, where: str = "<study>") -> StepMotion:
    """Refuse a grid whose steps hold F constant over too much motion.

    Parameters
    ----------
    traj : Trajectory
    t : ndarray, shape (N+1,)
        Grid. [s]
    where : str
        File named in the error message.

    Returns
    -------
    StepMotion

    Raises
    ------
    StudyFileError
        ``[study] dt``: one line with the time of the first offending step,
        the rotation (or specific-force change) in it and the largest
        acceptable ``dt``.

    Notes
    -----
    F is evaluated at the step mid-point ``t_m`` and held over the step
    (:func:`truth_system`).  Over a step in which the body turns through
    ``Δθ = Δt max|ω_nb|`` (:class:`StepMotion`):

    * the quaternion-error block ``½Ω(ω_ib)`` rotates ``δq`` through
      ``ω(t_m)Δt`` instead of ``∫ω dt``, an error ``ε ≤ Δθ`` (a rate step
      inside the step; ``ε = O(ω̈Δt³)`` for smooth rates).  The attitude
      error is rotated off the ``q``-orthogonal subspace by ``ε/2``, and a
      fraction ``sin²(ε/2) ≤ (Δθ/2)²`` of its variance about that axis
      moves into the quaternion-norm direction, where no attitude error is
      seen: an unaided azimuth σ shrinks (0.099′ instead of 9.98′ at 5 min
      with 60 s steps on the land-vehicle route);
    * the sensor-error columns ``C_b^n`` and the body-frame specific force
      and rate are off by ``|C(t) − C(t_m)| ≤ Δθ`` relative within the step
      (``Δθ²/24`` on average for a steady turn);
    * the tilt-to-velocity coupling ``f^n ×`` is off by
      ``|f^n(t) − f^n(t_m)|/g`` relative to the Schuler coupling ``g``.
      Velocity-direction terms (transport rate, Coriolis) are 1e-4 of that
      and are not checked.

    With ``Δθ ≤ 0.1 rad`` (5.7°) and ``|Δf^n| ≤ 0.1 g`` per step the
    worst-case (rate or force step inside a step) errors are below
    ``(Δθ/2)² = 0.25 %`` of the attitude variance leaking out per step and
    10 % of that step's sensor and force coupling.  What remains on smooth
    motion is the rotation mismatch ``ε ≈ |Δω̇| Δt²/8`` at the kinks of the
    rate profile, which turns part of the (large) azimuth error into tilt.
    Measured on the land-vehicle route (5°/s turns with 3-s ramps, so
    ``dt ≤ 1.14 s``), pure INS at 5 min against ``dt = 0.1 s``, every
    accepted step tried (0.3 … 1.14 s): azimuth within 5e-6, CEP within
    2e-4, tilt within 1.7e-3 (relative; the 58-state model at 1 s: 1e-8,
    5e-5, 2e-5).  Refused steps: 5 s loses 2 % of the azimuth, 60 s 99 %.
    Splitting a 1.14-s step into ten brings the tilt error to 2e-6.
    """
    m = step_motion(traj, t)
    bad_r = m.rotation > MAX_STEP_ROTATION * (1 + 1e-9)
    bad_f = m.force > MAX_STEP_FORCE_CHANGE * (1 + 1e-9)
    if bad_r.any() or bad_f.any():
        k = int(np.argmax(bad_r | bad_f))
        dt = t[k + 1] - t[k]
        ok = m.largest_dt()
        e = 10.0 ** (np.floor(np.log10(ok)) - 2)           # rounded down to 3 significant digits
        ok = np.floor(ok / e * (1 + 1e-12)) * e
        if bad_r[k]:
            what = (f"the vehicle turns by up to {np.degrees(m.rotation[k]):.3g}° in the step from "
                    f"{t[k]:g} s to {t[k + 1]:g} s (peak rate {np.degrees(m.rotation[k] / dt):.3g}°/s), more than "
                    f"{np.degrees(MAX_STEP_ROTATION):.3g}° per step")
        else:
            what = (f"the specific force changes by {m.force[k]:.3g} g in the step from {t[k]:g} s to "
                    f"{t[k + 1]:g} s, more than {MAX_STEP_FORCE_CHANGE:g} g per step")
        raise StudyFileError(f"{where}: [study] dt",
                             f"{dt:g} s holds the error dynamics F constant over too much motion: {what}; "
                             f"the largest acceptable dt is {ok:.3g} s")
    return m


#: chunks of :func:`discretize_chunked` from which half are discretised in a forked child
SPLIT_CHUNKS = 4
#: states from which :func:`discretize_chunked` splits its chunks (smaller systems are cheaper than the fork)
SPLIT_STATES = 40


def discretize_chunked(F, Qc, dt, method, order=None, *, progress=False, desc="discretising", chunk=DISCRETIZE_CHUNK,
                       what="", times=None, first: int = 0):
    """Discretise in chunks (bounded memory) with a progress bar.

    BLAS is limited to one thread: for these 58–116-wide matrices OpenBLAS's
    thread pool was measured 3–10× slower on a loaded 2-core machine.
    ``what`` and ``times`` (start time of each step [s]) name the system
    and the step in error messages, the step counted on the whole grid:
    ``first`` is the grid step of ``F[0]`` (a chunk of a streamed grid).

    A system of :data:`SPLIT_STATES` states or more in :data:`SPLIT_CHUNKS`
    chunks or more is split: the second half of the chunks goes to a
    forked child (:func:`covtool.forked.split`) that writes its Φ, Q_d into
    the same shared arrays (:func:`covtool.forked.shared_empty`).  The
    chunks are those of one process, so the numbers are bit for bit the
    same; where no fork is possible or useful (:func:`covtool.forked.can_split`)
    everything runs here.

    Returns
    -------
    Phi, Qd : ndarray, shape (N, n, n)
        Float64.

    Raises
    ------
    covtool.errors.NumericalError
        From :func:`covtool.lincov.discretize.discretize`, the earliest
        failing step's (this process's half first).
    """
    from threadpoolctl import threadpool_limits

    from covtool.forked import can_split, shared_empty, split

    N = F.shape[0]
    starts = list(range(0, N, chunk))
    # two halves of the chunks at once, in this process and a forked child, when there are enough:
    # every chunk is discretised exactly as in one process (the same chunks, one BLAS thread each), so
    # the numbers are too
    parallel = len(starts) >= SPLIT_CHUNKS and F.shape[1] >= SPLIT_STATES and can_split()
    try:
        Phi = shared_empty(F.shape, float, shared=parallel)
        Qd = shared_empty(F.shape, float, shared=parallel)
    except OSError:                                         # no shared mapping now: one process
        parallel = False
        Phi, Qd = np.empty(F.shape), np.empty(F.shape)
    dt = np.broadcast_to(np.asarray(dt, float), (N,))
    with progress_bar(N, desc, progress) as bar, threadpool_limits(limits=1, user_api="blas"):
        def run(part, here=True):
            for a in part:
                b = min(N, a + chunk)
                try:
                    Phi[a:b], Qd[a:b] = discretize(F[a:b], Qc[a:b], dt[a:b], method, order, what=what,
                                                   times=None if times is None else times[a:b])
                except (CovtoolError, ValueError) as e:
                    on_grid(e, first + a)
                    raise
                if here:
                    bar.update(b - a)

        if parallel:
            # scipy.linalg (the balancing of covtool.lincov.discretize.series.balancing, imported on first
            # use) imported once, before the fork, not once in each process (0.07-0.15 s)
            import scipy.linalg  # noqa: F401

            half = (len(starts) + 1) // 2
            split(lambda p: run(*p), [(starts[:half], True), (starts[half:], False)])
            bar.update(N - starts[half])
        else:
            run(starts)
    return Phi, Qd


def truth_system(model: Model, traj, t: np.ndarray, method: str, *, options=NavOptions(), progress=False,
                 where: str = "<study>"):
    """Truth Φ, Q_d along the grid, plus the mid-point context and dynamics.

    The grid is first checked against the motion (:func:`check_step_motion`);
    ``where`` names the study file in that error.

    Raises
    ------
    NumericalError
        Φ or Q_d of a step is not finite (Q_d: symmetric, PSD), naming the
        study ``where``, the step's time and the state.
    """
    check_step_motion(traj, t, where)
    ctx = midpoint_context(traj, t)
    dyn = error_dynamics(model, ctx, options)
    Phi, Qd = discretize_chunked(dyn.F, dyn.Qc, np.diff(t), method, progress=progress, desc="truth Φ, Q",
                                 what=f"{where}: truth model {model.name!r}", times=t[:-1])
    # guarded once here; the runs that share them are told so (system_checked)
    check_system(f"{where}: truth model {model.name!r}", Phi, Qd, names=model.names, times=t)
    return ctx, dyn, Phi, Qd


def discretize_steps(F, Qc, t: np.ndarray, a: int, b: int, method: str, order=None, *, what: str, label: str,
                     names=None):
    """Φ, Q_d of the grid steps ``a … b−1`` from their F, Q_c, guarded: one chunk of a streamed study.

    Parameters
    ----------
    F, Qc : ndarray, shape (b − a, n, n)
        The steps' dynamics (seed 002 eq (1)–(5)).
    t : ndarray, shape (N+1,)
        The whole grid [s]; errors name the step and time on it.
    a, b : int
        The steps.
    method, order
        The discretisation (:func:`discretize_chunked`).
    what, label : str
        Name the system in a discretisation error and in the guard's.
    names : sequence of str, optional
        State names, for the guard's message.

    Returns
    -------
    Phi, Qd : ndarray, shape (b − a, n, n)

    Raises
    ------
    NumericalError
        A step's F, Φ or Q_d is not finite (Q_d: symmetric, PSD), naming its grid step and time.
    """
    Phi, Qd = discretize_chunked(F, Qc, np.diff(t[a:b + 1]), method, order, what=what, times=t[a:b], first=a)
    check_system(label, Phi, Qd, names=names, times=t[a:b + 1])
    return Phi, Qd


def truth_stream(model: Model, traj, t: np.ndarray, method: str, *, pool=None, where: str = "<study>"):
    """The truth of :func:`truth_system`, streamed in time: nothing of size N × n² is built at once.

    The grid is checked against the motion first (:func:`check_step_motion`).

    Parameters
    ----------
    model : Model
    traj : trajectory
    t : ndarray, shape (N+1,)
        The grid. [s]
    method : str
        The study's discretisation.
    pool : covtool.lincov.streamed.ChunkPool, optional
        Budget of the chunks held for later runs (None: every chunk).
    where : str
        The study file, for messages.

    Returns
    -------
    ctx : Context
        Trajectory at the step mid-points.
    dyn : covtool.lincov.dynamics.DynamicsStream
        F, Q_c under the default navigation options (as :func:`truth_system`'s), chunk by chunk.
    system : covtool.lincov.streamed.StreamedSystem
        Φ, Q_d (``system.Phi[k]``, ``system.Qd[k]``), each chunk discretised
        as :func:`truth_system` does (the same values) and guarded when made.

    Raises
    ------
    NumericalError
        When a chunk is made: Φ or Q_d of a step is not finite (Q_d:
        symmetric, PSD), naming the study, the step's time and the state.
    """
    from covtool.lincov.dynamics import DynamicsStream
    from covtool.lincov.streamed import StreamedSystem

    check_step_motion(traj, t, where)
    ctx = midpoint_context(traj, t)
    dyn = DynamicsStream(model, ctx, NavOptions())
    what = f"{where}: truth model {model.name!r}"

    def make(a, b):
        d = dyn.chunk(a, b)
        return discretize_steps(d.F, d.Qc, t, a, b, method, what=what, label=what, names=model.names)

    return ctx, dyn, StreamedSystem(make, t.size - 1, model.n, pool=pool)


def initial_covariance(truth: Model, nodes, where: str) -> np.ndarray:
    """The truth P0 at the first trajectory node, guarded.

    Parameters
    ----------
    truth : Model
    nodes : covtool.nav.trajectory.core.Trajectory
        The trajectory sampled on the study grid.
    where : str
        The study file, for messages.

    Returns
    -------
    ndarray, shape (n, n)

    Raises
    ------
    NumericalError
        P0 is not finite, symmetric and PSD (names the state).
    StudyFileError
        P0 is already outside the linear error model's domain
        (:func:`covtool.analysis.metrics.validity`), e.g. an initial azimuth 1σ of 83°.
    """
    P0 = truth.initial_covariance(nodes.q_nb[0])
    check_covariance(P0, f"{where}: truth model {truth.name!r}: P0", names=truth.names)
    m = nav_metrics(P0[None], nodes.lat[:1], nodes.h[:1], nodes.q_nb[:1])
    first = first_invalid(m, [0.0])
    if first:
        text = validity_text(first)
        sig = (f" (initial 1sigma: azimuth {np.degrees(m['sigma_azimuth'][0]):.3g} deg, tilts "
               f"{np.degrees(m['sigma_tilt_n'][0]):.3g}/{np.degrees(m['sigma_tilt_e'][0]):.3g} deg, "
               f"position {max(m['sigma_north'][0], m['sigma_east'][0]):.4g} m, altitude {m['sigma_down'][0]:.4g} m)")
        raise StudyFileError(f"{where}: [truth]", "the initial covariance of truth model "
                             f"{truth.name!r} is outside the linear error model's domain: "
                             + text.replace(" from t = 0.0 min", "") + sig)
    return P0


def record_steps(t: np.ndarray, every: float | None, report_steps) -> np.ndarray:
    """Grid indices a study records: the history spacing, the report steps, the first and the last.

    Parameters
    ----------
    t : ndarray, shape (N+1,)
        Time grid. [s]
    every : float or None
        ``[output] history_every`` [s]; None or 0 records every step.
    report_steps : iterable of int

    Returns
    -------
    ndarray of int, increasing
        The steps :func:`covtool.studies.tables.history_frame` writes (the
        multiples of ``every`` and the last) and the report steps.
    """
    if every:
        k = np.round(t / every)
        sel = np.isclose(t, k * every)
    else:
        sel = np.ones(t.shape, bool)
    sel[[0, -1]] = True
    sel[np.asarray(list(report_steps), int)] = True
    return np.flatnonzero(sel)
