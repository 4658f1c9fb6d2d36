"""Shared study plumbing: header, truth model with overrides, grid, dynamics, tables."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from ..covariance import check_covariance, check_system
from ..discretize import discretize
from ..dynamics import Context, NavOptions, error_dynamics
from ..errors import ModelFileError, StudyFileError, UnitError, ValidityWarning
from ..io.config import check_keys, quantity
from ..metrics import first_invalid, nav_metrics, validity, validity_text
from ..model.library import load_model_by_name
from ..model.spec import Model
from ..units import from_si, parse_quantity

FT = 0.3048
ARCMIN = np.pi / 180 / 60
ARCSEC = ARCMIN / 60


def progress_bar(total: int, desc: str, enabled: bool):
    """A tqdm bar shown only if the work lasts longer than about one second."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, disable=not enabled, delay=1.0, leave=False, unit="step")


def study_header(decl: dict, where: str, extra_keys=()) -> dict:
    """Validate ``[study]``: name, kind, duration, dt, discretization."""
    st = decl["study"]
    check_keys(st, {"kind", "name", "description", "duration", "dt", "discretization", *extra_keys},
               f"{where}: [study]", StudyFileError)
    out = {
        "kind": st["kind"],
        "name": st.get("name", Path(where).stem if where != "<study>" else st["kind"]),
        "description": st.get("description", ""),
        "duration": quantity(st.get("duration", "30 min"), "time", f"{where}: [study] duration", StudyFileError,
                             positive=True),
        "dt": quantity(st.get("dt", "1 s"), "time", f"{where}: [study] dt", StudyFileError, positive=True),
        "discretization": st.get("discretization", "van_loan"),
    }
    if out["discretization"] not in ("van_loan", "taylor"):
        raise StudyFileError(f"{where}: [study] discretization",
                             f"{out['discretization']!r} is not 'van_loan' or 'taylor'")
    return out


def load_truth(decl: dict, where: str, base_dir) -> Model:
    """The study's truth model with ``only`` and per-state ``override`` applied.

    ``[truth]`` keys: ``model`` (library name or path), ``only`` (list of
    sources to keep, see :meth:`Model.only`), ``[truth.override.<state>]``
    with ``sigma``, ``tau``, ``distance`` or ``rw`` in datasheet units, and
    ``arw``/``vrw``.
    """
    tr = decl.get("truth", {})
    check_keys(tr, {"model", "only", "override", "arw", "vrw"}, f"{where}: [truth]", StudyFileError)
    name = tr.get("model", "sdins58")
    try:
        model = load_model_by_name(name, base_dir=base_dir)
    except ModelFileError:
        raise
    states = list(model.states)
    ix = model.index
    for nm, ov in (tr.get("override") or {}).items():
        w = f"{where}: [truth.override.{nm}]"
        if nm not in ix:
            raise StudyFileError(w, f"unknown state {nm!r} of truth model {model.name!r}")
        check_keys(ov, {"sigma", "tau", "distance", "rw"}, w, StudyFileError)
        s = states[ix[nm]]
        ch = {}
        if "sigma" in ov:
            ch["sigma"] = quantity(ov["sigma"], s.dimension, f"{w} sigma", StudyFileError, nonnegative=True)
        if "tau" in ov:
            ch["tau"] = quantity(ov["tau"], "time", f"{w} tau", StudyFileError, positive=True)
        if "distance" in ov:
            ch["distance"] = quantity(ov["distance"], "length", f"{w} distance", StudyFileError, positive=True)
        if "rw" in ov:
            from ..model.loader import _RW_DIM
            ch["rw"] = quantity(ov["rw"], _RW_DIM.get(s.dimension, s.dimension), f"{w} rw", StudyFileError,
                                nonnegative=True)
        states[ix[nm]] = dataclasses.replace(s, **ch)
    changes = {}
    if "arw" in tr:
        changes["arw"] = quantity(tr["arw"], "angle_random_walk", f"{where}: [truth] arw", StudyFileError,
                                  nonnegative=True)
    if "vrw" in tr:
        changes["vrw"] = quantity(tr["vrw"], "velocity_random_walk", f"{where}: [truth] vrw", StudyFileError,
                                  nonnegative=True)
    model = model.replace_states(states, **changes)
    if "only" in tr:
        only = tr["only"]
        if not isinstance(only, list):
            raise StudyFileError(f"{where}: [truth] only", "expected a list of state/block names")
        try:
            model = model.only(only)
        except KeyError as exc:
            raise StudyFileError(f"{where}: [truth] only",
                                 f"unknown state or block {exc.args[0]!r} of truth model {model.name!r}") from None
    return model


def time_grid(duration: float, dt: float) -> np.ndarray:
    """Grid ``0, dt, …, duration`` (the last step shortened if needed)."""
    n = int(np.floor(duration / dt + 1e-9))
    t = np.arange(n + 1) * dt
    if duration - t[-1] > 1e-9 * dt:
        t = np.append(t, duration)
    return t


def midpoint_context(traj, t: np.ndarray) -> Context:
    """Trajectory at the step mid-points (F is held constant over a step)."""
    tm = 0.5 * (t[:-1] + t[1:])
    return Context.from_trajectory(traj.sample(tm))


def discretize_chunked(F, Qc, dt, method, order=None, *, progress=False, desc="discretising", chunk=150):
    """Discretise in chunks (bounded memory) with a progress bar.

    BLAS is limited to one thread: for these 58–116-wide matrices OpenBLAS's
    thread pool was measured 3–10× slower on a loaded 2-core machine.
    """
    from threadpoolctl import threadpool_limits

    N = F.shape[0]
    Phi = np.empty_like(F)
    Qd = np.empty_like(F)
    dt = np.broadcast_to(np.asarray(dt, float), (N,))
    with threadpool_limits(limits=1, user_api="blas"), progress_bar(N, desc, progress) as bar:
        for a in range(0, N, chunk):
            b = min(N, a + chunk)
            Phi[a:b], Qd[a:b] = discretize(F[a:b], Qc[a:b], dt[a:b], method, order)
            bar.update(b - a)
    return Phi, Qd


def truth_system(model: Model, traj, t: np.ndarray, method: str, *, options=NavOptions(), progress=False,
                 where: str = "<study>"):
    """Truth Φ, Q_d along the grid, plus the mid-point context and dynamics.

    Raises
    ------
    NumericalError
        Φ or Q_d of a step is not finite (Q_d: symmetric, PSD), naming the
        study ``where``, the step's time and the state.
    """
    ctx = midpoint_context(traj, t)
    dyn = error_dynamics(model, ctx, options)
    Phi, Qd = discretize_chunked(dyn.F, dyn.Qc, np.diff(t), method, progress=progress, desc="truth Φ, Q")
    # guarded once here; the runs that share them are told so (system_checked)
    check_system(f"{where}: truth model {model.name!r}", Phi, Qd, names=model.names, times=t)
    return ctx, dyn, Phi, Qd


def initial_covariance(truth: Model, nodes, where: str) -> np.ndarray:
    """The truth P0 at the first trajectory node, guarded.

    Parameters
    ----------
    truth : Model
    nodes : covtool.trajectory.Trajectory
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
        (:func:`covtool.metrics.validity`), e.g. an initial azimuth 1σ of 83°.
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


def case_validity(case: str, m: dict, t: np.ndarray, *, warn: bool = True) -> dict:
    """First times a case leaves the linear model's domain; warn once.

    Parameters
    ----------
    case : str
        Case name (in the warning).
    m : dict of ndarray, shape (N,)
        :func:`covtool.metrics.nav_metrics` along the case's history.
    t : ndarray, shape (N,)
        Times of the history. [s]
    warn : bool
        Issue one :class:`covtool.errors.ValidityWarning` naming the case and
        the first time of each failed test.

    Returns
    -------
    dict of str to float
        :func:`covtool.metrics.first_invalid`.
    """
    first = first_invalid(m, t)
    if first and warn:
        warnings.warn(f"{case}: outside the linear error model's domain: {validity_text(first)}",
                      ValidityWarning, stacklevel=2)
    return first


def history_frame(case: str, t: np.ndarray, m: dict, every: float | None = None) -> pd.DataFrame:
    """History table with SI and paper units in the headers.

    The ``validity`` column names the domain tests that fail at each time
    (:func:`covtool.metrics.validity`), empty where the linear model holds.
    """
    sel = np.ones(t.shape, bool)
    if every:
        k = np.round(t / every)
        sel = np.isclose(t, k * every) | (np.arange(t.size) == t.size - 1)
    df = pd.DataFrame({
        "case": case,
        "t [s]": t[sel],
        "t [min]": t[sel] / 60.0,
        "sigma_N [m]": m["sigma_north"][sel],
        "sigma_E [m]": m["sigma_east"][sel],
        "sigma_D [m]": m["sigma_down"][sel],
        "CEP [m]": m["cep"][sel],
        "CEP [ft]": m["cep"][sel] / FT,
        "alt PE [m]": m["alt_pe"][sel],
        "alt PE [ft]": m["alt_pe"][sel] / FT,
        "sigma_vN [m/s]": m["sigma_vn"][sel],
        "sigma_vE [m/s]": m["sigma_ve"][sel],
        "sigma_vD [m/s]": m["sigma_vd"][sel],
        "tilt_N [arcsec]": m["sigma_tilt_n"][sel] / ARCSEC,
        "tilt_E [arcsec]": m["sigma_tilt_e"][sel] / ARCSEC,
        "azimuth [arcmin]": m["sigma_azimuth"][sel] / ARCMIN,
    })
    if "cep_pct_distance" in m:
        df["CEP/distance [%]"] = m["cep_pct_distance"][sel]
    flags = validity(m)
    df["validity"] = [", ".join(name for name, f in flags.items() if f[i]) or "ok" for i in np.flatnonzero(sel)]
    return df


def summary_row(case: str, m: dict, k: int, t: float, distance: float | None, *, first: dict | None = None,
                status: str | None = None) -> dict:
    """Table 3 columns at grid index ``k``.

    Parameters
    ----------
    case : str
    m : dict of ndarray
        :func:`covtool.metrics.nav_metrics`.
    k : int
        Index into ``m``.
    t : float
        Time of index ``k``. [s]
    distance : float or None
        Distance travelled by then. [m]
    first : dict, optional
        :func:`covtool.metrics.first_invalid` of the case; the ``validity``
        column lists the tests failed by ``t`` with their first time.  By
        default the tests at index ``k`` alone.
    status : str, optional
        Adds a ``status`` column (``"ok"`` or the guard's message) for
        studies that flag a failed case instead of stopping.
    """
    row = {
        "case": case,
        "t [min]": t / 60.0,
        "CEP [ft]": m["cep"][k] / FT,
        "CEP [m]": m["cep"][k],
        "alt PE [ft]": m["alt_pe"][k] / FT,
        "alt PE [m]": m["alt_pe"][k],
        "azimuth 1sigma [arcmin]": m["sigma_azimuth"][k] / ARCMIN,
        "tilt N 1sigma [arcsec]": m["sigma_tilt_n"][k] / ARCSEC,
        "tilt E 1sigma [arcsec]": m["sigma_tilt_e"][k] / ARCSEC,
        "CEP rule 0.589(s1+s2) [m]": m["cep_rule"][k],
    }
    if distance:
        row["distance [km]"] = distance / 1000.0
        row["CEP/distance [%]"] = 100.0 * m["cep"][k] / distance
    if first is None:
        first = {name: t for name, f in validity(m).items() if f[k]}
    row["validity"] = validity_text(first, until=t)
    if status is not None:
        row["status"] = status or "ok"
    return row


def report_times(decl_out: dict, where: str, duration: float) -> list[float]:
    """``[output] report_times`` in seconds (default: the end)."""
    out = []
    for i, v in enumerate(decl_out.get("report_times", [])):
        x = quantity(v, "time", f"{where}: [output] report_times[{i}]", StudyFileError, nonnegative=True)
        if x > duration + 1e-9:
            raise StudyFileError(f"{where}: [output] report_times[{i}]",
                                 f"{v!r} is after the end of the study ({duration:g} s)")
        out.append(x)
    return out or [duration]


__all__ = ["study_header", "load_truth", "time_grid", "truth_system", "history_frame", "summary_row",
           "initial_covariance", "case_validity",
           "parse_quantity", "from_si", "UnitError", "FT", "ARCMIN", "ARCSEC"]
