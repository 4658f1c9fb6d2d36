"""The dual-navigation comparison of two IMU records, end to end (seed 001, method II).

:func:`run_dual` aligns both IMUs (:mod:`~covtool.dualnav.alignment`),
navigates both on the main interval (:mod:`covtool.nav.strapdown`), forms the
difference and its predicted covariance (:mod:`~covtool.dualnav.difference`),
whitens and tests it and estimates a g-sensitivity (:mod:`~covtool.dualnav.monitor`),
for records already bridged over their gaps (:mod:`~covtool.dualnav.gaps`).

Pure numeric core: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from covtool.dualnav.alignment import triad_alignment
from covtool.dualnav.difference import difference_model, DifferenceModel, ImuLinearization, nav_difference
from covtool.dualnav.gaps import BridgedLog, CLOCK_PPM_TOL, clock_rate
from covtool.dualnav.monitor import (flagged_intervals, gsens_estimates, GsensEstimate, Innovations,
                                     innovations, Whitener, window_test)
from covtool.errors import InputError
from covtool.lincov.dynamics import Context
from covtool.lincov.model.spec import Model
from covtool.nav import attitude as quat, strapdown as sd
from covtool.nav.imu.simulator import ImuRecord

__all__ = [
    "ppm_text", "DualSetup", "DualRun", "run_dual",
]


# --------------------------------------------------------------------------
# the whole comparison
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class DualSetup:
    """Everything the comparison needs besides the IMU data (SI).

    Attributes
    ----------
    main_model, kimu_model : Model
        Error models of the two IMUs (:meth:`ImuGrade.to_model`).
    main_mounting, kimu_mounting : ndarray, shape (4,)
        Declared ``q_bs`` of each sensor frame in the vehicle body.
    ratio : int
        KIMU samples per main sample (seed 001: 4).
    align_time : float
        Alignment window at the start of the logs (vehicle at rest). [s]
    lat, lon, h : float
        Input position at the start. [rad], [rad], [m]
    heading : float
        Input heading of the vehicle body x axis. [rad]
    heading_sigma : float
        Its 1σ (shared by both alignments). [rad]
    substep : int
        Main intervals per step of the linear model.
    compare_every : int
        Main intervals per comparison epoch (a multiple of ``substep``).
    components : tuple of int
        Compared components (indices into :data:`DIFF_NAMES`).
    noise : ndarray, shape (9,)
        1σ comparison noise per component.
    window : int
        Epochs per window of the χ² test.
    false_alarm : float
        Design probability of a false alarm per flight, for each of the
        window test and the g-sensitivity detection.
    candidates : tuple of (int, int)
        g-sensitive scale-factor hypotheses ``(gyro axis, accel axis)``.
    """

    main_model: Model
    kimu_model: Model
    main_mounting: np.ndarray
    kimu_mounting: np.ndarray
    ratio: int
    align_time: float
    lat: float
    lon: float
    h: float
    heading: float
    heading_sigma: float
    substep: int
    compare_every: int
    components: tuple
    noise: np.ndarray
    window: int
    false_alarm: float
    candidates: tuple


@dataclass
class DualRun:
    """Outcome of one comparison (M runs of the same flight).

    Attributes
    ----------
    t : ndarray, shape (J+1,)
        Comparison epochs. [s]
    z : ndarray, shape (M, J+1, 9)
        Differences main − KIMU (all nine components).
    model : DifferenceModel
    envelope : ndarray, shape (J+1, m)
        Predicted 1σ of each compared component (open loop).
    inn : Innovations
    window_stat : ndarray, shape (M, N_w)
    window_threshold : float
    flagged : ndarray of bool, shape (M, N_w)
    intervals : list of list of (float, float)
        Flagged spans of every run.
    gsens : GsensEstimate
    main, kimu : covtool.nav.strapdown.NavHistory
        The two solutions at the epochs.
    unused : dict of str to (int, int)
        Samples of each log before and after the compared span (outside the
        common span of the logs, or after the last whole comparison
        interval): reported, never silently dropped.
    clock : dict of str to float
        ``main``, ``kimu``: each log's measured clock offset from its
        nominal rate; ``mismatch``: the main period over ``ratio`` KIMU
        periods, minus one. [ppm]
    """

    t: np.ndarray
    z: np.ndarray
    model: DifferenceModel
    envelope: np.ndarray
    inn: Innovations
    window_stat: np.ndarray
    window_threshold: float
    flagged: np.ndarray
    intervals: list
    gsens: GsensEstimate
    main: sd.NavHistory
    kimu: sd.NavHistory
    unused: dict = field(default_factory=dict)
    clock: dict = field(default_factory=dict)


def as_runs(x):
    x = np.asarray(x)
    return x if x.ndim == 3 else x[None]


def _subsample(hist: sd.NavHistory, idx) -> sd.NavHistory:
    return sd.NavHistory(hist.t[idx], hist.lat[idx], hist.lon[idx], hist.h[idx], hist.v_n[idx], hist.q[idx])


def _final_state(hist: sd.NavHistory, rec: ImuRecord) -> sd.NavState:
    """Last state of a run, with the record's last sample as "previous"."""
    return sd.NavState(float(hist.t[-1]), hist.lat[-1], hist.lon[-1], hist.h[-1], hist.v_n[-1], hist.q[-1],
                       np.array(rec.dtheta[:, -1]), np.array(rec.dv[:, -1]))


def _closed_loop(model, rec_m, rec_k, sm, sk, r, ce, setup, q_ref_m, q_ref_k) -> Innovations:
    """Whiten with the navigation-error estimates fed back at every epoch."""
    J1 = model.t.size
    M = max(sm.n_runs, sk.n_runs, rec_m.dtheta.shape[0], rec_k.dtheta.shape[0])
    w = Whitener(model, M)
    comps = list(setup.components)

    def signed(state, q_ref):
        # δq is defined against the reference quaternion's sign
        flip = np.sum(state.q * q_ref, axis=-1) < 0
        return state.replace(q=np.where(flip[:, None], -state.q, state.q)) if flip.any() else state

    for j in range(J1):
        if j:
            a = (j - 1) * ce
            rm = rec_m.slice(a, a + ce)
            rk = rec_k.slice(a * r, (a + ce) * r)
            sm = _final_state(sd.run(sm, rm, 1, every=ce), rm)
            sk = _final_state(sd.run(sk, rk, r, every=ce), rk)
        hm_ = sd.NavHistory(np.array([sm.t]), sm.lat[None], sm.lon[None], sm.h[None], sm.v_n[None], sm.q[None])
        hk_ = sd.NavHistory(np.array([sk.t]), sk.lat[None], sk.lon[None], sk.h[None], sk.v_n[None], sk.q[None])
        z = nav_difference(hm_, hk_, setup.main_mounting, setup.kimu_mounting)[0][:, comps]
        w.update(j, z)
        dm, dk = w.take_navigation()
        sm = sd.correct(signed(sm, q_ref_m[j]), dm)
        sk = sd.correct(signed(sk, q_ref_k[j]), dk)
        if j < J1 - 1:
            w.predict(j)
    return w.result()


def run_dual(main: BridgedLog, kimu: BridgedLog, setup: DualSetup, *, heading=None,
             gap_noise=True, feedback=True, model: DifferenceModel | None = None) -> DualRun:
    """Align, navigate, compare and test the two IMUs.

    Parameters
    ----------
    main, kimu : BridgedLog
        The two logs on their grids, from the start of the alignment
        window (the vehicle at rest); increments of shape (K, 3) or
        (M, K, 3).  The KIMU's samples are assigned to the main intervals by
        :func:`covtool.nav.strapdown.group_samples` (seed 001 Fig 7).
    setup : DualSetup
    heading : array_like, shape (M,), optional
        Per-run input heading (simulated input errors); default
        ``setup.heading``.
    gap_noise : bool
        Add each bridged gap's predicted extra error to the process noise.
    feedback : bool
        Whiten with the estimated navigation errors fed back into both
        solutions at every epoch (:class:`Whitener`); False whitens the
        open-loop difference (exact only while the errors are small enough
        for the linear model).
    model : DifferenceModel, optional
        A difference model built by an earlier call on logs of the same
        motion, epochs and gaps (e.g. the first batch of a study); it is
        used as is instead of linearising along this call's run 0.

    Returns
    -------
    DualRun
        ``z`` is always the open-loop difference (what seed 001 Figs 13–15
        compare); the innovations come from the feedback pass.

    Raises
    ------
    InputError
        The logs do not overlap, are too short for the alignment and one
        comparison window, the alignment is not a whole number of main
        samples, or the KIMU does not deliver ``ratio`` samples per main
        interval (named by :func:`~covtool.nav.strapdown.group_samples`).  Each
        message names the log it is about (:attr:`BridgedLog.where`); when
        the logs cannot be paired because their clocks drift apart by more
        than :data:`CLOCK_PPM_TOL`, the one further from its nominal rate is
        named with both measured rates.
    ValueError
        ``compare_every`` not a multiple of ``substep``, or ``substep`` odd.
    """
    r = int(setup.ratio)
    hm = main.dt
    clock = _clocks(main, kimu, r)
    name_m = main.where or "main log"
    name_k = kimu.where or "KIMU log"
    # main intervals (t_k − h, t_k]: keep those the KIMU log covers entirely (h the main log's own period)
    edges = np.concatenate([[main.t[0] - (main.period or hm)], main.t])
    tol = 1e-6 * kimu.dt
    e0 = int(np.searchsorted(edges, kimu.t[0] - kimu.dt - tol, side="left"))
    e1 = int(np.searchsorted(edges, kimu.t[-1] + tol, side="right")) - 1
    if e1 - e0 < 1:
        def label(log, what):
            return f"the {what} log {log.where} " if log.where else f"the {what} log "

        raise InputError("logs", f"{label(main, 'main')}[{edges[0]:.9g}, {edges[-1]:.9g}] s and "
                         f"{label(kimu, 'KIMU')}[{kimu.t[0] - kimu.dt:.9g}, {kimu.t[-1]:.9g}] s share no main interval")
    sel = (kimu.t > edges[e0] + tol) & (kimu.t <= edges[e1] + tol)
    try:
        groups = sd.group_samples(kimu.t[sel], edges[e0:e1 + 1], where="KIMU log")
    except ValueError as exc:
        problem = str(exc).removeprefix("KIMU log: ")
        if abs(clock["mismatch"]) > CLOCK_PPM_TOL:
            # the logs drift apart: blame the one whose clock is further from its nominal rate
            main_worse = abs(clock["main"]) >= abs(clock["kimu"])
            culprit, other = (name_m, name_k) if main_worse else (name_k, name_m)
            ppm_c, ppm_o = (clock["main"], clock["kimu"]) if main_worse else (clock["kimu"], clock["main"])
            raise InputError(culprit, f"its clock runs {ppm_text(ppm_c)} ppm off its nominal rate ({other}: "
                             f"{ppm_text(ppm_o)} ppm), so the logs drift apart by {ppm_text(clock['mismatch'])} ppm "
                             f"and cannot be paired sample by sample ({problem})") from None
        raise InputError(name_k, problem) from None
    if groups.shape[1] != r:
        raise InputError(name_k, f"delivers {groups.shape[1]} samples per main interval, the study declares "
                         f"a rate ratio of {r}")
    k_idx = np.flatnonzero(sel)[groups.ravel()]
    m_th = as_runs(main.dtheta)[:, e0:e1]
    m_dv = as_runs(main.dv)[:, e0:e1]
    # the KIMU samples in main-interval order: a view when they are one run of consecutive samples (always,
    # after bridging), else a gathered copy
    k_take = slice(int(k_idx[0]), int(k_idx[-1]) + 1) if np.all(np.diff(k_idx) == 1) else k_idx
    k_th = as_runs(kimu.dtheta)[:, k_take]
    k_dv = as_runs(kimu.dv)[:, k_take]
    Mr = max(m_th.shape[0], k_th.shape[0])
    t_start = float(edges[e0])
    n_align = int(round(setup.align_time / hm))
    if abs(n_align * hm - setup.align_time) > 1e-6 * hm:
        raise InputError("alignment time", f"{setup.align_time:g} s is not a whole number of main samples "
                         f"({hm:g} s)")
    ce, sub = int(setup.compare_every), int(setup.substep)
    if ce % sub or sub % 2:
        raise ValueError("compare_every must be a multiple of substep, and substep even")
    n_nav = ((m_th.shape[1] - n_align) // ce) * ce
    if n_nav < setup.window * ce:
        raise InputError("logs", f"{(m_th.shape[1] - n_align) * hm:.3g} s of data after the {setup.align_time:g} s "
                         f"alignment is shorter than one comparison window ({setup.window * ce * hm:g} s)")
    hk = hm / r
    # each IMU aligns on its own: levelling + the input heading through its declared mounting
    psi = np.broadcast_to(np.asarray(setup.heading if heading is None else heading, float), (Mr,))
    f_m = m_dv[:, :n_align].sum(axis=1) / setup.align_time
    f_k = k_dv[:, :n_align * r].sum(axis=1) / setup.align_time
    q_m0 = triad_alignment(np.broadcast_to(f_m, (Mr, 3)), psi, setup.main_mounting)
    q_k0 = triad_alignment(np.broadcast_to(f_k, (Mr, 3)), psi, setup.kimu_mounting)
    t_nav0 = t_start + n_align * hm

    def state0(q, prev_th, prev_dv):
        M = q.shape[0]
        z3 = np.zeros((M, 3))
        return sd.NavState(t_nav0, np.full(M, setup.lat), np.full(M, setup.lon), np.full(M, setup.h), z3, q,
                           np.broadcast_to(prev_th, (M, 3)).copy(), np.broadcast_to(prev_dv, (M, 3)).copy())

    rec_m = ImuRecord(t_nav0, hm, m_th[:, n_align:n_align + n_nav], m_dv[:, n_align:n_align + n_nav])
    rec_k = ImuRecord(t_nav0, hk, k_th[:, n_align * r:(n_align + n_nav) * r],
                      k_dv[:, n_align * r:(n_align + n_nav) * r])
    half = sub // 2
    hist_m = sd.run(state0(q_m0, m_th[:, n_align - 1], m_dv[:, n_align - 1]), rec_m, 1, every=half)
    hist_k = sd.run(state0(q_k0, k_th[:, n_align * r - 1], k_dv[:, n_align * r - 1]), rec_k, r, every=half)
    ep = np.arange(0, hist_m.t.size, ce // half)
    mid = np.arange(1, hist_m.t.size, 2)
    em, ek = _subsample(hist_m, ep), _subsample(hist_k, ep)
    z = np.swapaxes(nav_difference(em, ek, setup.main_mounting, setup.kimu_mounting), 0, 1)   # (M, J+1, 9)
    q_ref_m = em.q[:, 0]
    if model is not None:
        if model.t.size != em.t.size or np.max(np.abs(model.t - em.t)) > 1e-9 * max(1.0, abs(em.t[-1])):
            raise ValueError("the given difference model has other epochs than these logs")
        q_ref_k = _to_kimu(q_ref_m, setup)
        return _finish(model, main, kimu, setup, rec_m, rec_k, state0, q_m0, q_k0, m_th, m_dv, k_th, k_dv, n_align,
                       r, ce, q_ref_m, q_ref_k, z, em, ek, e0, k_idx, clock, feedback, n_nav)
    # linearisation along run 0: each IMU's own attitude and mean rates over every step
    N = n_nav // sub
    T = sub * hm

    def mean_rates(th, dv, per):
        return (th[0].reshape(N, per, 3).sum(axis=1) / T, dv[0].reshape(N, per, 3).sum(axis=1) / T)

    w_m, f_ms = mean_rates(rec_m.dtheta, rec_m.dv, sub)
    w_k, f_ks = mean_rates(rec_k.dtheta, rec_k.dv, sub * r)
    wk_s = rec_k.dtheta[0].reshape(N, sub * r, 3) / hk
    fk_s = rec_k.dv[0].reshape(N, sub * r, 3) / hk
    products = np.einsum("nsi,nsj->nij", wk_s, fk_s) / (sub * r)
    lat_mid, h_mid, v_mid = hist_m.lat[mid, 0], hist_m.h[mid, 0], hist_m.v_n[mid, 0]
    # one attitude reference for both IMUs (the main solution, carried to the KIMU frame through the
    # declared mountings): references that differ by the open-loop difference itself would put
    # (difference × common error × f) terms into the model
    def to_kimu(q):
        return _to_kimu(q, setup)

    q_ref_k = to_kimu(q_ref_m)
    ctx_m = Context(lat_mid, h_mid, v_mid, hist_m.q[mid, 0], f_ms, w_m)
    ctx_k = Context(lat_mid, h_mid, v_mid, to_kimu(hist_m.q[mid, 0]), f_ks, w_k)
    rest = []
    for q0, f0, th, per in ((q_m0, f_m, m_th, 1), (q_k0, f_k, k_th, r)):
        w0 = th[0, :n_align * per].sum(axis=0) / setup.align_time
        rest.append(Context([setup.lat], [setup.h], np.zeros((1, 3)), q0[:1], f0[:1], w0[None]))
    lin_m = ImuLinearization(setup.main_model, ctx_m, q_ref_m, rest[0], setup.align_time, float(psi[0]),
                             setup.main_mounting)
    lin_k = ImuLinearization(setup.kimu_model, ctx_k, q_ref_k, rest[1], setup.align_time, float(psi[0]),
                             setup.kimu_mounting)
    extra = []
    if gap_noise:
        for log, name in ((main, "main"), (kimu, "kimu")):
            for g in log.gaps:
                jj = int(np.floor((g.after - t_nav0) / (ce * hm)))
                if g.before <= t_nav0:
                    continue   # bridged inside the alignment window: in the levelling mean only
                extra.append((name, min(max(jj, 0), em.t.size - 2), g.sigma_attitude, g.sigma_velocity))
    model = difference_model(lin_m, lin_k, t_epochs=em.t, lat_epochs=em.lat[:, 0], h_epochs=em.h[:, 0],
                             substeps_per_epoch=ce // sub, dt_sub=T, heading_sigma=setup.heading_sigma,
                             products=products, candidates=setup.candidates, components=setup.components,
                             noise=setup.noise, extra_noise=extra)
    return _finish(model, main, kimu, setup, rec_m, rec_k, state0, q_m0, q_k0, m_th, m_dv, k_th, k_dv, n_align, r, ce,
                   q_ref_m, q_ref_k, z, em, ek, e0, k_idx, clock, feedback, n_nav)


def _to_kimu(q, setup):
    """The main IMU's attitude carried to the KIMU frame through the declared mountings."""
    out = q if setup.main_mounting is None else quat.mul(q, quat.conj(np.asarray(setup.main_mounting, float)))
    return out if setup.kimu_mounting is None else quat.mul(out, np.asarray(setup.kimu_mounting, float))


def _finish(model, main, kimu, setup, rec_m, rec_k, state0, q_m0, q_k0, m_th, m_dv, k_th, k_dv, n_align, r, ce,
            q_ref_m, q_ref_k, z, em, ek, e0, k_idx, clock, feedback, n_nav) -> DualRun:
    """Innovations, window test and g-sensitivity estimates of :func:`run_dual`."""
    if feedback:
        inn = _closed_loop(model, rec_m, rec_k, state0(q_m0, m_th[:, n_align - 1], m_dv[:, n_align - 1]),
                           state0(q_k0, k_th[:, n_align * r - 1], k_dv[:, n_align * r - 1]), r, ce, setup,
                           q_ref_m, q_ref_k)
    else:
        inn = innovations(model, z[..., list(setup.components)])
    stat, thr, flagged = window_test(inn.nis, model.m, setup.window, setup.false_alarm)
    intervals = [flagged_intervals(f, em.t, setup.window) for f in flagged]
    gs = gsens_estimates(inn, setup.candidates, setup.false_alarm, strict=False)
    env = np.sqrt(np.diagonal(model.open_loop(), axis1=1, axis2=2))
    used_k = k_idx[:(n_align + n_nav) * r]
    unused = {"main": (e0, main.t.size - (e0 + n_align + n_nav)),
              "kimu": (int(used_k[0]), kimu.t.size - int(used_k[-1]) - 1)}
    return DualRun(em.t, z, model, env, inn, stat, thr, flagged, intervals, gs, em, ek, unused, clock)


def ppm_text(x: float) -> str:
    """Clock offset as signed text, 0.1 ppm resolution.

    ``+200.0``; a value that rounds to zero is ``+0.0``, never ``-0.0``.
    """
    return f"{round(float(x), 1) + 0.0:+.1f}"


def _clocks(main: BridgedLog, kimu: BridgedLog, ratio: int) -> dict:
    """Each log's clock offset from its nominal rate, and their mismatch. [ppm]"""
    p_m = main.period if main.period is not None else clock_rate(main.t, main.dt)[0]
    p_k = kimu.period if kimu.period is not None else clock_rate(kimu.t, kimu.dt)[0]
    return {"main": (p_m / main.dt - 1.0) * 1e6, "kimu": (p_k / kimu.dt - 1.0) * 1e6,
            "mismatch": (p_m / (ratio * p_k) - 1.0) * 1e6}
