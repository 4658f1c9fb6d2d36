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


def study_header(decl: dict, where: str) -> dict:
    """Validate ``[study]`` (:class:`covtool.studies.config.StudySection`): the header as a dict.

    Keys ``kind``, ``name`` (checked to be a safe file name, default the
    study file's stem), ``description``, ``duration`` and ``dt`` [s],
    ``discretization``, ``max_memory`` [bytes] or None.
    """
    from covtool.studies.config import StudySection, parse_section

    st = table(decl["study"], f"{where}: [study]", StudyFileError)
    sec = parse_section(StudySection, st, where, "study")
    w = f"{where}: [study]"
    out = {
        "kind": sec.kind,
        "name": check_study_name(st, where, StudyFileError, default=st["kind"]),
        "description": sec.description,
        "duration": sec.duration,
        "dt": sec.dt,
        "discretization": sec.discretization,
        "max_memory": sec.max_memory,
    }
    if out["dt"] > out["duration"] * (1 + 1e-12):
        raise StudyFileError(f"{w} dt", f"{st.get('dt', '1 s')!r} is longer than the duration "
                             f"({out['duration']:g} s): one step would hold F constant over the whole study")
    return out


#: the ``[truth]`` keys
TRUTH_KEYS = ("model", "only", "override", "arw", "vrw", "override_filters")
#: the keys of one ``[truth.override.<state or block>]`` table
OVERRIDE_KEYS = ("sigma", "tau", "distance", "rw")


def load_truth(decl: dict, where: str, base_dir, *, for_filters: bool = False):
    """The study's truth model with ``only`` and ``override`` applied.

    ``[truth]`` keys: ``model`` (library name, or a path relative to the
    study file), ``only`` (list of sources to keep, see :meth:`Model.only`),
    ``[truth.override.<state>]`` with ``sigma`` and the parameter of the
    state's own process (``tau`` for ``markov``, ``distance`` for
    ``markov_distance``, ``rw`` for ``random_walk``) in datasheet units,
    ``[truth.override.<block>]`` (``gyro_bias``: the same values for every
    state of the block; a state's own table wins, key by key), ``arw`` and
    ``vrw``, and ``override_filters``.

    Parameters
    ----------
    for_filters : bool
        Also return the model the filters are built from.

    Returns
    -------
    Model, or (Model, Model) with ``for_filters``
        The truth; with ``for_filters`` also the filters' model: the truth
        itself with ``override_filters = true``, else the truth model file
        as declared (with ``only``), without the study's overrides.

    Notes
    -----
    The rule for the filters (``[truth] override_filters``, default
    ``false``): the truth model is the real IMU, a filter file is a design.
    An override in a study says how the real sensors depart from the design
    values, so by default the filters keep the model file's values for
    their P0, their kept states' dynamics and the equivalent noise of the
    states they drop (seed 002, eq (11)-(13)): the analysis shows the
    mismatch, which is what a navigation engineer asks an override for.
    ``override_filters = true`` builds the filters from the overridden truth
    instead (the designer knows the actual sensors; the trade grid's IMU
    grades work this way).

    Raises
    ------
    StudyFileError
        Unknown key, state or block, a bad value, or a process parameter on
        a state whose process does not use it (it would be ignored).
    ModelFileError
        The model file itself is invalid or missing.
    """
    from covtool.io.config import boolean
    from covtool.io.model_file import _PROCESS_KEYS, _RW_DIM

    tr = table(decl.get("truth", {}), f"{where}: [truth]", StudyFileError)
    check_keys(tr, set(TRUTH_KEYS), f"{where}: [truth]", StudyFileError)
    name = tr.get("model", "sdins58")
    model = load_model_by_name(name, base_dir=base_dir, where=f"{where}: [truth] model")
    follow = boolean(tr.get("override_filters", False), f"{where}: [truth] override_filters", StudyFileError)
    nominal = model
    states = list(model.states)
    ix = model.index
    blocks = model.block_names()
    overrides = table(tr.get("override") or {}, f"{where}: [truth.override]", StudyFileError)
    # block tables first, then state tables on top: a state's own value wins
    per_state: dict[str, dict] = {}
    origin: dict[tuple, str] = {}
    for nm, ov in sorted(overrides.items(), key=lambda kv: kv[0] in ix):
        w = f"{where}: [truth.override.{nm}]"
        if nm in ix:
            targets = [nm]
        elif nm in blocks:
            targets = [s.name for s in states if s.block == nm]
        else:
            raise StudyFileError(w, f"unknown state or block {nm!r} of truth model {model.name!r} "
                                 f"(blocks: {', '.join(blocks)})")
        check_keys(ov, set(OVERRIDE_KEYS), w, StudyFileError)
        for key in ov:
            for t in targets:
                per_state.setdefault(t, {})[key] = ov[key]
                origin[(t, key)] = w
    for nm, ov in per_state.items():
        s = states[ix[nm]]
        for key, needs in _PROCESS_KEYS.items():
            if key in ov and s.process != needs:
                w = origin[(nm, key)]
                raise StudyFileError(f"{w} {key}", f"'{key}' applies only to process {needs!r}; state {nm!r} "
                                     f"follows process {s.process!r}")
        ch = {}
        if "sigma" in ov:
            w = origin[(nm, "sigma")]
            ch["sigma"] = quantity(ov["sigma"], s.dimension, f"{w} sigma", StudyFileError, nonnegative=True)
            if s.dimension == "quaternion" and ch["sigma"] > 1.0:
                raise StudyFileError(f"{w} sigma", f"{ov['sigma']!r} is above 1; a unit quaternion's component "
                                     "cannot exceed 1")
        if "tau" in ov:
            ch["tau"] = quantity(ov["tau"], "time", f"{origin[(nm, 'tau')]} tau", StudyFileError, positive=True)
        if "distance" in ov:
            ch["distance"] = quantity(ov["distance"], "length", f"{origin[(nm, 'distance')]} distance",
                                      StudyFileError, positive=True)
        if "rw" in ov:
            ch["rw"] = quantity(ov["rw"], _RW_DIM.get(s.dimension, s.dimension), f"{origin[(nm, 'rw')]} rw",
                                StudyFileError, nonnegative=True)
        states[ix[nm]] = dataclasses.replace(s, **ch)
    changes = {}
    if "arw" in tr:
        changes["arw"] = quantity(tr["arw"], "angle_random_walk", f"{where}: [truth] arw", StudyFileError,
                                  nonnegative=True)
    if "vrw" in tr:
        changes["vrw"] = quantity(tr["vrw"], "velocity_random_walk", f"{where}: [truth] vrw", StudyFileError,
                                  nonnegative=True)
    overridden = bool(per_state or changes)
    if overridden:
        model = model.replace_states(states, **changes)
    if "only" in tr:
        only = names(tr["only"], f"{where}: [truth] only", StudyFileError, what="state or block name")
        try:
            model = model.only(only)
            nominal = nominal.only(only)
        except KeyError as exc:
            raise StudyFileError(f"{where}: [truth] only",
                                 f"unknown state or block {exc.args[0]!r} of truth model {model.name!r}") from None
    if not for_filters:
        return model
    return model, (model if follow or not overridden else nominal)


def input_file(label: str, path) -> dict:
    """Provenance rows of one input file: its absolute path and SHA-256."""
    p = Path(os.path.abspath(path))
    return {f"{label}_file": str(p), f"{label}_file_sha256": file_sha256(p)}


def study_inputs(path, decl: dict, truth: Model | None = None, filter_file=None) -> dict:
    """Provenance rows of every input file of a study: absolute path and SHA-256.

    The study file, the truth model file, the filter file(s) (a path or a
    sequence of paths: ``filter_file``, ``filter_2_file``, ...), a
    trajectory CSV, each as resolved (relative paths against the study
    file), and the covtool source (:func:`covtool.version.source_revision`).
    """
    rows = {}
    if path is not None:
        rows.update(input_file("study", path))
    if truth is not None and Path(truth.path).is_file():
        rows.update(input_file("truth_model", truth.path))
    if filter_file is not None:
        files = [filter_file] if isinstance(filter_file, (str, os.PathLike)) else list(filter_file)
        for i, f in enumerate(files):
            rows.update(input_file("filter" if i == 0 else f"filter_{i + 1}", f))
    traj = decl.get("trajectory")
    if isinstance(traj, dict) and isinstance(traj.get("csv"), str):
        base = Path(path).parent if path is not None else None
        rows.update(input_file("trajectory", resolve_input(traj["csv"], base, "[trajectory] csv", StudyFileError)))
    return rows


def report_times(decl_out: dict, where: str, duration: float, parsed=None) -> list[float]:
    """``[output] report_times`` in seconds, each within the study (default: the end)."""
    if "report_times" not in decl_out:
        return [duration]
    w = f"{where}: [output] report_times"
    out = list(parsed) if parsed is not None else quantity_list(
        decl_out["report_times"], "time", w, StudyFileError, limit="report_times", nonnegative=True)
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
    traj = trajectory_from_config(cfg, where=f"{where}: [trajectory]", base_dir=base_dir, dt=dt, duration=duration)
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
    from covtool.studies.config import OutputSection, parse_section

    out = decl.get("output", {})
    sec = parse_section(OutputSection, out, where, "output")
    length_unit(decl, where)
    # any spacing is bounded: the history never holds more rows than grid steps
    return sec.history_every, report_times(out, where, duration, sec.report_times)


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
