"""The trade grid's aiding mixes, run with the aided machinery (issue 15).

Holds the ``[grid] aiding`` axis of :mod:`covtool.studies.trade_grid`: the
``[[aiding]]`` tables' validation (:func:`parse_aiding`), the check of their
schedules against a trajectory (:func:`aiding_problem`) and the truth under a
filter with the ZUPTs plus one mix for every trade-grid case
(:func:`trade_cases`); the measurements are declared and parsed as in the
``aided`` kind (:func:`covtool.studies.aided.parse_measurement`).  Moved
unchanged out of :mod:`covtool.studies.aided` to keep each module under 600
lines (issue 12).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from covtool.errors import NumericalError, StudyFileError, SystemCheckError
from covtool.io.config import check_keys, require, string, table
from covtool.lincov.aided import augment, build_epochs, error_processes, Jacobians, propagate_aided
from covtool.lincov.streamed import ScaledSteps
from covtool.studies.aided import NAV, parse_measurement

def parse_aiding(decl: dict, axis, where: str) -> list:
    """``[grid] aiding = [...]`` and the ``[[aiding]]`` tables -> one entry per axis value.

    ``"none"`` is the ZUPT schedule alone; every other value names an
    ``[[aiding]]`` table (``name`` and ``[[aiding.measurement]]`` tables,
    declared as in the aided kind) whose measurements are added to the
    ZUPTs of each interval.

    Returns
    -------
    list of dict
        ``{"name": str, "measurement": list of dict}`` (the declarations,
        validated; the workers parse them again).

    Raises
    ------
    StudyFileError
        ``aiding`` not a non-empty list of names, a name without its table,
        a table never used or declared twice, a bad measurement.
    """
    w = f"{where}: [grid] aiding"
    if not isinstance(axis, list) or not axis or not all(isinstance(a, str) for a in axis):
        raise StudyFileError(w, f"expected a non-empty list of names (\"none\" or an [[aiding]] name), got {axis!r}")
    if len(set(axis)) != len(axis):
        raise StudyFileError(w, f"{next(a for j, a in enumerate(axis) if a in axis[:j])!r} is listed twice")
    tables_ = decl.get("aiding", [])
    if not isinstance(tables_, list):
        raise StudyFileError(f"{where}: [[aiding]]", "expected an array of tables ([[aiding]] name = ...)")
    mixes = {}
    for j, a in enumerate(tables_):
        wa = f"{where}: [[aiding]] #{j + 1}"
        a = table(a, wa, StudyFileError)
        check_keys(a, {"name", "measurement"}, wa, StudyFileError)
        nm = string(require(a, "name", wa, StudyFileError), f"{wa} name", StudyFileError, nonempty=True)
        if nm == "none" or nm in mixes:
            raise StudyFileError(f"{wa} name", f"{nm!r} is " + ("reserved (the ZUPTs alone)" if nm == "none"
                                                                else "declared twice"))
        meas = a.get("measurement")
        if not isinstance(meas, list) or not meas:
            raise StudyFileError(f"{where}: [[aiding]] {nm!r}", "needs at least one [[aiding.measurement]]")
        parsed = [parse_measurement(m, i, f"{where}: [[aiding]] {nm!r}") for i, m in enumerate(meas)]
        names_ = ["zupt"] + [m.name for m, _ in parsed]
        dup = next((x for i, x in enumerate(names_) if x in names_[:i]), None)
        if dup is not None:
            raise StudyFileError(f"{where}: [[aiding]] {nm!r} [[measurement]] {dup!r}",
                                 "the name is used twice (\"zupt\" is the grid's own ZUPT)")
        mixes[nm] = list(meas)
    unknown = [a for a in axis if a != "none" and a not in mixes]
    if unknown:
        raise StudyFileError(w, f"{unknown[0]!r} has no [[aiding]] table (declared: "
                             f"{', '.join(sorted(mixes)) or 'none'})")
    unused = [m for m in mixes if m not in axis]
    if unused:
        raise StudyFileError(f"{where}: [[aiding]] {unused[0]!r}", "is not in [grid] aiding")
    return [{"name": a, "measurement": mixes.get(a, [])} for a in axis]


def aiding_problem(aiding: dict, t, nodes, where: str) -> None:
    """Check every schedule of an aiding mix against one trajectory (before any work is sent out)."""
    for i, m in enumerate(aiding["measurement"]):
        meas, sch = parse_measurement(m, i, f"{where}: [[aiding]] {aiding['name']!r}")
        p = sch.problem(t, nodes)
        if p is not None:
            raise StudyFileError(f"{where}: [[aiding]] {aiding['name']!r} [[measurement]] {meas.name!r} schedule", p)


def trade_cases(S, f: str, cases: list, aiding: dict, rec, label: str) -> list:
    """The truth under filter ``f`` with the ZUPTs plus an aiding mix, one run per trade-grid case.

    Parameters
    ----------
    S : covtool.studies.zupt_setup.ZuptSetup
        The (grade, interval) system of the chunk.
    f : str
        Filter name.
    cases : list of dict
        ``_sigma`` (true ZUPT σ [m/s]), ``P0 scale``, ``Q scale``, ``R scale``.
    aiding : dict
        ``{"name", "measurement"}`` (:func:`parse_aiding`).
    rec : sequence of int
        Recorded grid indices.
    label : str
        For messages.

    Returns
    -------
    list of (P_truth, P_filter, status)
        Navigation blocks, shape (r, 10, 10) each, per case; a case whose
        covariance fails the guard has NaN blocks and the guard's message
        as status (the grid goes on), otherwise status ``"ok"``.

    Notes
    -----
    The filter scales as the ZUPT trade grid's: ``P_f(0) × p0`` (its
    kept measurement-error states too), ``Q_f × q`` (and their driving
    noise), every measurement's ``R_f × r``; the ZUPT's filter σ is the
    filter's declared ``zupt_sigma`` or the true one.  Eq (11)–(13) of the
    dropped INS states is matched over the ZUPT intervals (the filter as
    the ZUPT grid builds it).
    """
    from covtool.lincov.measurements import Zupt

    where = S.where
    plan = [parse_measurement(m, i, f"{where}: [[aiding]] {aiding['name']!r}")
            for i, m in enumerate(aiding["measurement"])]
    states = [s for m, _ in plan for s in m.states]
    names_all = list(S.truth.names) + [s.name for s in states]
    steps = [sch.steps(S.t, S.nodes) for _, sch in plan]
    # streamed in time: the truth's and the filter's Φ, Q_d made chunk by chunk, held for the next cases and
    # filters while the setup's pool has room (ZuptSetup.streamed_system); F and Q_c never over the grid
    truth, fsys = S.streamed_system(), S.streamed_system(f)
    fm = S.filter_stream(f)[0]
    spec = S.specs[f]
    dt = np.diff(S.t)
    err = error_processes(states, dt)[:2]
    P0a, Pf_e, D = augment(S.P0, fm.D, states, [s.name for s in states])
    fnames = list(fm.names) + [s.name for s in states]
    nf0 = fm.P0.shape[0]
    jac = Jacobians(S.nodes)               # the measurement Jacobians: the cases differ in their σ only
    out = []
    for c in cases:
        sig = float(c["_sigma"])
        fsig = sig if spec.zupt_sigma is None else float(spec.zupt_sigma)
        r = float(c["R scale"])
        z = Zupt(name="zupt", sigma=np.full(3, sig), filter_sigma=np.full(3, fsig * np.sqrt(r)))
        pairs = [(z, S.update_steps)] + [
            (dataclasses.replace(m, filter_sigma=np.asarray(m.sigma if m.filter_sigma is None else m.filter_sigma,
                                                            float) * np.sqrt(r)), st)
            for (m, _), st in zip(plan, steps)]
        Pf0 = np.zeros((len(fnames),) * 2)
        Pf0[:nf0, :nf0], Pf0[nf0:, nf0:] = fm.P0 * c["P0 scale"], Pf_e * c["P0 scale"]
        q = float(c["Q scale"])
        epochs = build_epochs(pairs, S.nodes, names_all, fnames, jacobians=jac)
        try:
            run_ = propagate_aided(truth.Phi, truth.Qd, P0a, fsys.Phi, fsys.Qd if q == 1.0 else ScaledSteps(fsys.Qd, q),
                                   Pf0, D, epochs, err=err, err_f=(err[0], err[1] * q), record=rec, form=spec.update,
                                   label=f"{label}: case {c['case']}", times=S.t, names=names_all,
                                   filter_names=fnames, system_checked=True, keep=NAV)
        except SystemCheckError:
            raise                          # the model's own Φ or Q_d: the study stops, as on the whole grid
        except NumericalError as exc:
            nan = np.full((len(rec), 10, 10), np.nan)
            out.append((nan, nan, str(exc)))
            continue
        out.append((run_.P_truth[:, :10, :10], run_.P_filter[:, :10, :10], "ok"))
    return out
