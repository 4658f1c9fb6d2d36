"""Study inputs: the ``[study]`` header, the truth model with overrides, trajectory, output times, input files."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from covtool.errors import StudyFileError
from covtool.io.config import check_keys, file_sha256, quantity, resolve_input, table
from covtool.io.library import load_model_by_name
from covtool.io.names import check_study_name
from covtool.lincov.model.spec import Model
from covtool.units import OUTPUT_LENGTHS

__all__ = [
    "study_header", "load_truth",
]


def study_config(decl, where: str):
    """The study's typed configuration: ``decl`` itself, or the dict parsed once.

    Parameters
    ----------
    decl : dict or covtool.studies.config.StudyConfig
        A study declaration (TOML tables) or its configuration.
    where : str
        The study file, for messages.

    Returns
    -------
    StudyConfig
        Of the kind named by ``[study] kind`` (:func:`covtool.studies.config.load_config`).

    Raises
    ------
    StudyFileError
        Naming the file, the table, the key and the problem.
    """
    from covtool.studies.config import StudyConfig, load_config

    return decl if isinstance(decl, StudyConfig) else load_config(decl, where)


def study_header(decl, where: str) -> dict:
    """``[study]`` (:class:`covtool.studies.config.StudySection`) as a dict.

    ``decl`` is a study declaration (only its ``[study]`` is parsed) or a
    configuration.  Keys ``kind``, ``name`` (checked to be a safe file
    name, default the study file's stem), ``description``, ``duration`` and
    ``dt`` [s], ``discretization``, ``max_memory`` [bytes] or None.
    """
    from covtool.studies.config import StudyConfig, StudySection, parse_section

    if isinstance(decl, StudyConfig):
        sec = decl.study
    else:
        sec = parse_section(StudySection, table(decl["study"], f"{where}: [study]", StudyFileError), where, "study")
    return {
        "kind": sec.kind,
        "name": check_study_name({} if sec.name_ is None else {"name": sec.name_}, where, StudyFileError,
                                 default=sec.kind),
        "description": sec.description,
        "duration": sec.duration,
        "dt": sec.dt,
        "discretization": sec.discretization,
        "max_memory": sec.max_memory,
    }


#: the keys of one ``[truth.override.<state or block>]`` table
OVERRIDE_KEYS = ("sigma", "tau", "distance", "rw")


def load_truth(decl, where: str, base_dir, *, for_filters: bool = False, grade=None):
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
    decl : dict or StudyConfig or TruthSection
        The declaration (only ``[truth]`` is parsed), its configuration or
        its ``[truth]`` section.
    for_filters : bool
        Also return the model the filters are built from.
    grade : GradeEntry or dict, optional
        An IMU grade (``name``, ``scale``, optional ``override``, ``arw``,
        ``vrw``; trade grid, aided): every sensor state's σ and random walk
        and the ARW and VRW × ``grade.scale`` (:func:`graded`), then the
        grade's own overrides, ARW and VRW; the filters follow the grade.

    Returns
    -------
    Model, or (Model, Model) with ``for_filters``
        The truth; with ``for_filters`` also the filters' model: the truth
        itself with ``override_filters = true`` or a grade, else the truth
        model file as declared (with ``only``), without the study's
        overrides.

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
    from covtool.studies.config import StudyConfig, TruthSection, parse_section

    if isinstance(decl, StudyConfig):
        tr = decl.truth
    elif isinstance(decl, TruthSection):
        tr = decl
    else:
        tr = parse_section(TruthSection, decl.get("truth", {}), where, "truth")
    model = load_model_by_name(tr.model, base_dir=base_dir, where=f"{where}: [truth] model")
    nominal = model
    model, overridden = apply_overrides(model, tr.override, tr.arw, tr.vrw, f"{where}: [truth.override")
    follow = tr.override_filters
    if grade is not None:
        g = grade if isinstance(grade, dict) else {**grade.model_dump(by_alias=True)}
        gw = f"{where}: [[grade]] {g['name']!r}"
        model = graded(model, g["scale"])
        arw = None if g.get("arw") is None else quantity(g["arw"], "angle_random_walk", f"{gw} arw",
                                                         StudyFileError, nonnegative=True)
        vrw = None if g.get("vrw") is None else quantity(g["vrw"], "velocity_random_walk", f"{gw} vrw",
                                                         StudyFileError, nonnegative=True)
        model, _ = apply_overrides(model, g.get("override"), arw, vrw, f"{gw} override", state_tables=False)
        # the designer is assumed to know the grade's IMU: the filters follow the grade
        overridden, follow = True, True
    if tr.only is not None:
        try:
            model = model.only(tr.only)
            nominal = nominal.only(tr.only)
        except KeyError as exc:
            raise StudyFileError(f"{where}: [truth] only",
                                 f"unknown state or block {exc.args[0]!r} of truth model {model.name!r}") from None
    if not for_filters:
        return model
    return model, (model if follow or not overridden else nominal)


#: truth-model block kinds an IMU grade does not scale (they are not IMU errors)
UNSCALED_KINDS = ("navigation", "gravity_disturbance")


def graded(model: Model, scale: float) -> Model:
    """The model of another IMU grade: every sensor error × ``scale``.

    Every state's 1σ and random-walk intensity (except the blocks of kind
    :data:`UNSCALED_KINDS`) and the ARW and VRW are multiplied by
    ``scale`` [-], in SI.
    """
    if scale == 1.0:
        return model
    states = [s if s.kind in UNSCALED_KINDS else dataclasses.replace(s, sigma=s.sigma * scale, rw=s.rw * scale)
              for s in model.states]
    return model.replace_states(states, arw=model.arw * scale, vrw=model.vrw * scale)


def apply_overrides(model: Model, overrides, arw, vrw, table_where: str, *, state_tables: bool = True):
    """``model`` with per-state or per-block overrides (datasheet units) and ARW/VRW [SI] applied.

    ``overrides`` maps a state or block name to a table of ``sigma``,
    ``tau``, ``distance`` and ``rw``; block tables apply first, a state's own
    table wins key by key.  ``table_where`` prefixes the messages
    (``"s.toml: [truth.override"``, completed as ``.<name>]``; with
    ``state_tables=False`` as `` <name>``).  Returns ``(model, changed)``.
    """
    from covtool.io.model_file import _PROCESS_KEYS, _RW_DIM

    def wname(nm):
        return f"{table_where}.{nm}]" if state_tables else f"{table_where} {nm}"

    states = list(model.states)
    ix = model.index
    blocks = model.block_names()
    overrides = table(overrides or {}, f"{table_where}]" if state_tables else table_where, StudyFileError)
    # block tables first, then state tables on top: a state's own value wins
    per_state: dict[str, dict] = {}
    origin: dict[tuple, str] = {}
    for nm, ov in sorted(overrides.items(), key=lambda kv: kv[0] in ix):
        w = wname(nm)
        if nm in ix:
            targets = [nm]
        elif nm in blocks:
            targets = [s.name for s in states if s.block == nm]
        else:
            raise StudyFileError(w, f"unknown state or block {nm!r} of truth model {model.name!r} "
                                 f"(blocks: {', '.join(blocks)})")
        table(ov, w, StudyFileError)
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
    changes = {k: v for k, v in (("arw", arw), ("vrw", vrw)) if v is not None}
    changed = bool(per_state or changes)
    if changed:
        model = model.replace_states(states, **changes)
    return model, changed


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


def load_trajectory(decl, where, base_dir, dt, duration=None):
    """The study's ``[trajectory]``; it must last at least ``duration`` [s] if given.

    ``decl`` is a declaration, a configuration or a ``[trajectory]``
    section (:data:`covtool.studies.config.Trajectory`).  A built-in
    profile takes every parameter from its declaration
    (:class:`~covtool.studies.config.LandVehicle`,
    :class:`~covtool.studies.config.Static`: the one home of the route's
    defaults); segments and CSV files are read by
    :mod:`covtool.io.trajectory`.
    """
    from covtool.io.trajectory import builtin_trajectory, csv_trajectory, from_segments
    from covtool.studies.config import CsvTrajectory, LandVehicle, parse_trajectory, Static, StudyConfig

    if isinstance(decl, StudyConfig):
        sec = decl.trajectory
    elif isinstance(decl, dict):
        sec = parse_trajectory(decl.get("trajectory", {"builtin": "land_vehicle"}), where)
    else:
        sec = decl
    w = f"{where}: [trajectory]"
    if isinstance(sec, (LandVehicle, Static)):
        params = {k: getattr(sec, k) for k in type(sec).model_fields if k not in ("builtin", "name_")}
        traj = builtin_trajectory(sec.builtin, params, where=f"{w}: builtin {sec.builtin!r}", dt=dt,
                                  name=sec.name_ or "", duration=duration)
    elif isinstance(sec, CsvTrajectory):
        traj = csv_trajectory(sec.csv, where=w, base_dir=base_dir, max_gap=sec.max_gap, name=sec.name_ or "")
    else:
        traj = from_segments(sec.segment, sec.initial, dt=dt, name=sec.name_ or "segments", where=w)
    if duration is not None and traj.t[-1] < duration - 1e-9:
        raise StudyFileError(f"{where}: [study] duration",
                             f"{duration:g} s is longer than the trajectory ({traj.t[-1]:g} s)")
    return traj


#: ``[output] units``: the length unit of figures and charts (the paper's feet, or metres)
LENGTH_UNITS = OUTPUT_LENGTHS                        # one home: covtool.units


def length_unit(decl, where, default: str = "ft") -> str:
    """``[output] units``: ``"ft"`` (seed 002's unit, the default) or ``"m"``.

    Figures, workbook charts and fitted curves of a study give every
    length in this unit; tables keep both.  ``decl`` is a declaration or
    a configuration.

    Raises
    ------
    StudyFileError
        Not one of ``"ft"``, ``"m"``.
    """
    from covtool.studies.config import OutputSection, parse_section, StudyConfig

    if isinstance(decl, StudyConfig):
        out = getattr(decl, "output", None)
        return out.units if out is not None else default
    out = decl.get("output", {})
    u = out.get("units", default) if isinstance(out, dict) else default
    if u not in LENGTH_UNITS:
        parse_section(OutputSection, {"units": u}, where, "output")
    return u


def output_options(decl, where, duration):
    """``[output]``: ``(history_every [s], report_times [s])``, the times each within the study.

    ``decl`` is a declaration (only ``[output]`` is parsed) or a configuration.

    Raises
    ------
    StudyFileError
        A bad key or value, a time listed twice or after the end of the study.
    """
    from covtool.studies.config import OutputSection, parse_section, StudyConfig

    if isinstance(decl, StudyConfig):
        sec = decl.output
    else:
        out = decl.get("output", {})
        sec = parse_section(OutputSection, out, where, "output")
        for i, x in enumerate(sec.report_times or ()):
            if x > duration + 1e-9:
                raise StudyFileError(f"{where}: [output] report_times[{i}]",
                                     f"{out['report_times'][i]!r} is after the end of the study ({duration:g} s)")
    # any spacing is bounded: the history never holds more rows than grid steps
    return sec.history_every, list(sec.report_times) if sec.report_times is not None else [duration]


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
