"""Shared study plumbing: header, truth model with overrides, grid, dynamics, tables."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd

from ..discretize import discretize
from ..dynamics import Context, NavOptions, error_dynamics
from ..errors import ModelFileError, StudyFileError, UnitError
from ..io.config import check_keys, quantity
from ..io.names import check_study_name
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
        "name": check_study_name(st, where, StudyFileError, default=st["kind"]),
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


def truth_system(model: Model, traj, t: np.ndarray, method: str, *, options=NavOptions(), progress=False):
    """Truth Φ, Q_d along the grid, plus the mid-point context and dynamics."""
    ctx = midpoint_context(traj, t)
    dyn = error_dynamics(model, ctx, options)
    Phi, Qd = discretize_chunked(dyn.F, dyn.Qc, np.diff(t), method, progress=progress, desc="truth Φ, Q")
    return ctx, dyn, Phi, Qd


def history_frame(case: str, t: np.ndarray, m: dict, every: float | None = None) -> pd.DataFrame:
    """History table with SI and paper units in the headers."""
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
    return df


def summary_row(case: str, m: dict, k: int, t: float, distance: float | None) -> dict:
    """Table 3 columns at grid index ``k``."""
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
           "parse_quantity", "from_si", "UnitError", "FT", "ARCMIN", "ARCSEC"]
