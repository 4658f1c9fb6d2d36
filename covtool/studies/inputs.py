"""Study inputs: the ``[study]`` header, the truth model with overrides, trajectory, output times, input files."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from covtool.errors import StudyFileError
from covtool.io.config import (check_keys, choice, file_sha256, names, quantity, quantity_list,
                               resolve_input, string, table)
from covtool.io.library import load_model_by_name
from covtool.io.names import check_study_name
from covtool.lincov.model.spec import Model
from covtool.studies.resources import parse_bytes

__all__ = [
    "study_header", "load_truth",
]


def study_header(decl: dict, where: str, extra_keys=()) -> dict:
    """Validate ``[study]``: name, kind, duration, dt, discretization, max_memory."""
    st = table(decl["study"], f"{where}: [study]", StudyFileError)
    check_keys(st, {"kind", "name", "description", "duration", "dt", "discretization", "max_memory", *extra_keys},
               f"{where}: [study]", StudyFileError)
    w = f"{where}: [study]"
    out = {
        "kind": st["kind"],
        "name": check_study_name(st, where, StudyFileError, default=st["kind"]),
        "description": string(st.get("description", ""), f"{w} description", StudyFileError),
        "duration": quantity(st.get("duration", "30 min"), "time", f"{w} duration", StudyFileError, positive=True),
        "dt": quantity(st.get("dt", "1 s"), "time", f"{w} dt", StudyFileError, positive=True),
        "discretization": choice(st.get("discretization", "van_loan"), ("van_loan", "taylor"),
                                 f"{w} discretization", StudyFileError),
        "max_memory": (parse_bytes(st["max_memory"], f"{w} max_memory", StudyFileError)
                       if "max_memory" in st else None),
    }
    if out["dt"] > out["duration"] * (1 + 1e-12):
        raise StudyFileError(f"{w} dt", f"{st.get('dt', '1 s')!r} is longer than the duration "
                             f"({out['duration']:g} s): one step would hold F constant over the whole study")
    return out


def load_truth(decl: dict, where: str, base_dir) -> Model:
    """The study's truth model with ``only`` and per-state ``override`` applied.

    ``[truth]`` keys: ``model`` (library name, or a path relative to the
    study file), ``only`` (list of sources to keep, see :meth:`Model.only`),
    ``[truth.override.<state>]`` with ``sigma`` and the parameter of the
    state's own process (``tau`` for ``markov``, ``distance`` for
    ``markov_distance``, ``rw`` for ``random_walk``) in datasheet units, and
    ``arw``/``vrw``.

    Raises
    ------
    StudyFileError
        Unknown key or state, a bad value, or a process parameter on a state
        whose process does not use it (it would be ignored).
    ModelFileError
        The model file itself is invalid or missing.
    """
    from covtool.io.model_file import _PROCESS_KEYS, _RW_DIM

    tr = table(decl.get("truth", {}), f"{where}: [truth]", StudyFileError)
    check_keys(tr, {"model", "only", "override", "arw", "vrw"}, f"{where}: [truth]", StudyFileError)
    name = tr.get("model", "sdins58")
    model = load_model_by_name(name, base_dir=base_dir, where=f"{where}: [truth] model")
    states = list(model.states)
    ix = model.index
    for nm, ov in table(tr.get("override") or {}, f"{where}: [truth.override]", StudyFileError).items():
        w = f"{where}: [truth.override.{nm}]"
        if nm not in ix:
            raise StudyFileError(w, f"unknown state {nm!r} of truth model {model.name!r}")
        check_keys(ov, {"sigma", "tau", "distance", "rw"}, w, StudyFileError)
        s = states[ix[nm]]
        for key, needs in _PROCESS_KEYS.items():
            if key in ov and s.process != needs:
                raise StudyFileError(f"{w} {key}", f"'{key}' applies only to process {needs!r}; state {nm!r} "
                                     f"follows process {s.process!r}")
        ch = {}
        if "sigma" in ov:
            ch["sigma"] = quantity(ov["sigma"], s.dimension, f"{w} sigma", StudyFileError, nonnegative=True)
            if s.dimension == "quaternion" and ch["sigma"] > 1.0:
                raise StudyFileError(f"{w} sigma", f"{ov['sigma']!r} is above 1; a unit quaternion's component "
                                     "cannot exceed 1")
        if "tau" in ov:
            ch["tau"] = quantity(ov["tau"], "time", f"{w} tau", StudyFileError, positive=True)
        if "distance" in ov:
            ch["distance"] = quantity(ov["distance"], "length", f"{w} distance", StudyFileError, positive=True)
        if "rw" in ov:
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
        only = names(tr["only"], f"{where}: [truth] only", StudyFileError, what="state or block name")
        try:
            model = model.only(only)
        except KeyError as exc:
            raise StudyFileError(f"{where}: [truth] only",
                                 f"unknown state or block {exc.args[0]!r} of truth model {model.name!r}") from None
    return model


def input_file(label: str, path) -> dict:
    """Provenance rows of one input file: its absolute path and SHA-256."""
    p = Path(os.path.abspath(path))
    return {f"{label}_file": str(p), f"{label}_file_sha256": file_sha256(p)}


def study_inputs(path, decl: dict, truth: Model | None = None, filter_file=None) -> dict:
    """Provenance rows of every input file of a study: absolute path and SHA-256.

    The study file, the truth model file, the filter file and a trajectory
    CSV, each as resolved (relative paths against the study file).
    """
    rows = {}
    if path is not None:
        rows.update(input_file("study", path))
    if truth is not None and Path(truth.path).is_file():
        rows.update(input_file("truth_model", truth.path))
    if filter_file is not None:
        rows.update(input_file("filter", filter_file))
    traj = decl.get("trajectory")
    if isinstance(traj, dict) and isinstance(traj.get("csv"), str):
        base = Path(path).parent if path is not None else None
        rows.update(input_file("trajectory", resolve_input(traj["csv"], base, "[trajectory] csv", StudyFileError)))
    return rows


def report_times(decl_out: dict, where: str, duration: float) -> list[float]:
    """``[output] report_times`` in seconds, each within the study (default: the end)."""
    if "report_times" not in decl_out:
        return [duration]
    w = f"{where}: [output] report_times"
    out = quantity_list(decl_out["report_times"], "time", w, StudyFileError, limit="report_times",
                        nonnegative=True)
    for i, (v, x) in enumerate(zip(decl_out["report_times"], out)):
        if x > duration + 1e-9:
            raise StudyFileError(f"{w}[{i}]", f"{v!r} is after the end of the study ({duration:g} s)")
    if len(set(out)) != len(out):
        raise StudyFileError(w, f"a time is listed twice in {decl_out['report_times']!r}")
    return out


def load_trajectory(decl, where, base_dir, dt, duration=None):
    """The study's ``[trajectory]``; it must last at least ``duration`` [s] if given."""
    from covtool.io.trajectory import trajectory_from_config

    cfg = decl.get("trajectory", {"builtin": "land_vehicle"})
    traj = trajectory_from_config(cfg, where=f"{where}: [trajectory]", base_dir=base_dir, dt=dt)
    if duration is not None and traj.t[-1] < duration - 1e-9:
        raise StudyFileError(f"{where}: [study] duration",
                             f"{duration:g} s is longer than the trajectory ({traj.t[-1]:g} s)")
    return traj


#: ``[output] units``: the length unit of figures and charts (the paper's feet, or metres)
LENGTH_UNITS = {"ft": 0.3048, "m": 1.0}


def length_unit(decl, where, default: str = "ft") -> str:
    """``[output] units``: ``"ft"`` (seed 002's unit, the default) or ``"m"``.

    Figures and workbook charts of a study draw every length in this unit;
    tables keep both.

    Raises
    ------
    StudyFileError
        Not one of ``"ft"``, ``"m"``.
    """
    out = decl.get("output", {})
    u = out.get("units", default) if isinstance(out, dict) else default
    if u not in LENGTH_UNITS:
        raise StudyFileError(f"{where}: [output] units", f"{u!r} is not a length unit for figures "
                             f"(one of: {', '.join(LENGTH_UNITS)})")
    return u


def output_options(decl, where, duration):
    out = decl.get("output", {})
    check_keys(out, {"history_every", "report_times", "units"}, f"{where}: [output]", StudyFileError)
    length_unit(decl, where)
    # any spacing is bounded: the history never holds more rows than grid steps
    every = quantity(out.get("history_every", "10 s"), "time", f"{where}: [output] history_every",
                     StudyFileError, positive=True)
    return every, report_times(out, where, duration)


def trajectory_csv_sha256(decl: dict, base_dir) -> str:
    """SHA-256 of the study's ``[trajectory] csv`` file (``""`` without one).

    The path is resolved as :func:`covtool.io.trajectory.trajectory_from_config`
    resolves it (relative to the study file's directory).
    """
    traj = decl.get("trajectory")
    if not isinstance(traj, dict) or not isinstance(traj.get("csv"), str):
        return ""
    path = Path(traj["csv"])
    if not path.is_absolute() and base_dir is not None:
        path = Path(base_dir) / path
    return file_sha256(path)
