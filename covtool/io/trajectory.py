"""Trajectory declarations of study files (``[trajectory]`` tables).

Three sources, each with datasheet units: a list of *segments*
(:func:`from_segments`), a built-in profile with its parameters
(:data:`BUILTINS`) or a CSV file (:mod:`covtool.io.trajectory_csv`);
:func:`trajectory_from_config` dispatches.  Every value is validated here,
with the file, the key and the problem named, before any computation.
"""

from __future__ import annotations

import math
from pathlib import Path

from covtool.errors import TrajectoryError
from covtool.io.config import check_keys, integer, quantity, resolve_input
from covtool.io.trajectory_csv import load_trajectory_csv
from covtool.nav.trajectory.core import Trajectory, trajectory_fields
from covtool.nav.trajectory.profiles import land_vehicle, static_profile
from covtool.nav.trajectory.segments import (check_position, check_positive, ProfileBuilder, SEGMENT_KINDS,
                                             TRANSITION)

__all__ = [
    "from_segments", "trajectory_from_config", "builtin_trajectory", "csv_trajectory", "BUILTINS",
]


# --------------------------------------------------------------------------
# declarations (study files)
# --------------------------------------------------------------------------

_SEGMENT_DIMS = {"duration": "time", "to_speed": "velocity", "acceleration": "acceleration",
                 "transition": "time", "rate": "angular_rate", "angle": "angle", "grade": "dimensionless"}
_INITIAL_KEYS = {"lat": "angle", "lon": "angle", "h": "length", "heading": "angle", "speed": "velocity"}

#: built-in profile -> {parameter: dimension}
BUILTINS = {
    "land_vehicle": {
        "cycles": "int", "period": "time", "stop_duration": "time", "distance": "length",
        "accel_duration": "time", "turn_rate": "angular_rate", "turn_angle": "angle",
        "grade": "dimensionless", "grade_duration": "time",
        "lat": "angle", "lon": "angle", "h": "length", "heading": "angle",
    },
    "static": {"duration": "time", "lat": "angle", "lon": "angle", "h": "length", "heading": "angle"},
}


def trajectory_quantity(value, dimension, where):
    return quantity(value, dimension, where, TrajectoryError)


def check_trajectory_keys(d, allowed, where):
    check_keys(d, allowed, where, TrajectoryError)


def from_segments(segments, initial, *, dt=1.0, name="", where="trajectory") -> Trajectory:
    """Trajectory from segment declarations with datasheet units.

    Parameters
    ----------
    segments : list of dict
        E.g. ``{"kind": "turn", "rate": "3 deg/s", "angle": "90 deg"}``;
        kinds and keys in :data:`SEGMENT_KINDS`.
    initial : dict
        ``lat``, ``lon``, ``h`` (required), ``heading`` and ``speed``
        (default 0).
    dt : float
        Time step of the returned grid. [s]
    name : str
        Label.
    where : str
        Location prefix of error messages.

    Returns
    -------
    Trajectory
        Its :meth:`~Trajectory.sample` evaluates the profile exactly.

    Raises
    ------
    TrajectoryError
        Unknown kind or key, missing or inconsistent keys, bad units,
        non-positive durations, or an impossible sequence (e.g. a stand
        while moving).

    Notes
    -----
    * ``accelerate``/``decelerate``: ``to_speed`` and one of ``duration``
      or ``acceleration`` (the plateau acceleration); the acceleration ramps
      take ``transition`` (default 3 s).
    * ``turn``: two of ``rate``, ``angle``, ``duration`` (right positive);
      the yaw rate ramps take ``transition`` (default 3 s).
    * ``grade``: ``grade`` (rise/run, e.g. ``"5 %"``) or ``angle``; the
      pitch moves from its current value to the grade angle over
      ``transition`` (default 5 s), holds, and returns to level within
      ``duration``; with ``level_off = false`` it stays on the grade, so
      later segments (a turn: a helical ramp) run on it.  Vertical velocity
      is ``−s sin θ``.
    """
    check_trajectory_keys(initial, _INITIAL_KEYS, f"{where}: initial")
    init = {}
    for key, dim in _INITIAL_KEYS.items():
        if key in initial:
            init[key] = trajectory_quantity(initial[key], dim, f"{where}: initial: {key}")
        elif key in ("lat", "lon", "h"):
            raise TrajectoryError(f"{where}: initial", f"missing required key {key!r}")
    b = ProfileBuilder(init["lat"], init["lon"], init["h"], init.get("heading", 0.0),
                 init.get("speed", 0.0), where=f"{where}: initial")
    if not isinstance(segments, (list, tuple)) or not segments:
        raise TrajectoryError(f"{where}: segment", "expected a non-empty list of segments")
    for i, seg in enumerate(segments):
        w = f"{where}: segment[{i}]"
        if not isinstance(seg, dict):
            raise TrajectoryError(w, f"expected a table, got {type(seg).__name__}")
        kind = seg.get("kind")
        if kind not in SEGMENT_KINDS:
            raise TrajectoryError(w, f"unknown segment kind {kind!r} (one of: "
                                  f"{', '.join(sorted(SEGMENT_KINDS))})")
        w = f"{w} ({kind})"
        check_trajectory_keys(seg, SEGMENT_KINDS[kind], w)
        v = {k: trajectory_quantity(x, _SEGMENT_DIMS[k], f"{w}: {k}") for k, x in seg.items() if k in _SEGMENT_DIMS}
        if "level_off" in seg:
            if not isinstance(seg["level_off"], bool):
                raise TrajectoryError(f"{w}: level_off", f"{seg['level_off']!r} is not true or false")
            v["level_off"] = seg["level_off"]
        if kind in ("stand", "cruise"):
            if "duration" not in v:
                raise TrajectoryError(w, "missing required key 'duration'")
            getattr(b, kind)(v["duration"], w)
        elif kind in ("accelerate", "decelerate"):
            if "to_speed" not in v:
                raise TrajectoryError(w, "missing required key 'to_speed'")
            b.accelerate(v["to_speed"], duration=v.get("duration"), acceleration=v.get("acceleration"),
                         transition=v.get("transition", TRANSITION[kind]),
                         decelerate=kind == "decelerate", where=w)
        elif kind == "turn":
            b.turn(rate=v.get("rate"), angle=v.get("angle"), duration=v.get("duration"),
                   transition=v.get("transition", TRANSITION[kind]), where=w)
        else:  # grade
            if ("grade" in v) == ("angle" in v):
                raise TrajectoryError(w, "give exactly one of 'grade' and 'angle'")
            if "duration" not in v:
                raise TrajectoryError(w, "missing required key 'duration'")
            angle = math.atan(v["grade"]) if "grade" in v else v["angle"]
            b.grade(angle, v["duration"], transition=v.get("transition", TRANSITION[kind]),
                    level_off=v.get("level_off", True), where=w)
    return b.build(dt=dt, name=name, where=where)


def trajectory_from_config(cfg: dict, *, where: str, base_dir: Path | None, dt: float,
                           duration: float | None = None) -> Trajectory:
    """Trajectory from a study-file table.

    Parameters
    ----------
    cfg : dict
        One of ``{builtin = "land_vehicle", ...parameters}``,
        ``{builtin = "static", duration, lat, lon, h, heading}``,
        ``{segment = [...], initial = {...}}`` or ``{csv = "file.csv"}``
        (with an optional ``max_gap = "5 s"``: the longest time step that
        may be interpolated, see :func:`load_trajectory_csv`); each may
        carry ``name``.  Parameters use datasheet units.
    where : str
        Location prefix of error messages (``"studies/x.toml: [trajectory]"``).
    base_dir : Path or None
        Directory against which a relative ``csv`` path is resolved
        (the current directory if None).
    dt : float
        Time step of generated profiles (a CSV keeps its own grid). [s]
    duration : float, optional
        The study's duration: the ``static`` builtin's span when its own
        ``duration`` is not given (else 30 min). [s]

    Returns
    -------
    Trajectory

    Raises
    ------
    TrajectoryError
        Naming ``where``, the key and the problem.
    """
    if not isinstance(cfg, dict):
        raise TrajectoryError(where, f"expected a table, got {type(cfg).__name__}")
    sources = [k for k in ("builtin", "segment", "csv") if k in cfg]
    if len(sources) != 1:
        raise TrajectoryError(where, "give exactly one of 'builtin', 'segment' and 'csv' "
                              f"(got {', '.join(map(repr, sources)) or 'none'})")
    name = cfg.get("name", "")
    if not isinstance(name, str):
        raise TrajectoryError(f"{where}: name", f"{name!r} is not a string")
    source = sources[0]
    if source == "segment":
        check_trajectory_keys(cfg, ("segment", "initial", "name"), where)
        if "initial" not in cfg:
            raise TrajectoryError(where, "missing required key 'initial'")
        return from_segments(cfg["segment"], cfg["initial"], dt=dt, name=name or "segments", where=where)
    if source == "csv":
        check_trajectory_keys(cfg, ("csv", "name", "max_gap"), where)
        max_gap = None
        if "max_gap" in cfg:
            max_gap = trajectory_quantity(cfg["max_gap"], "time", f"{where}: max_gap")
        return csv_trajectory(cfg["csv"], where=where, base_dir=base_dir, max_gap=max_gap, name=name)
    builtin = cfg["builtin"]
    if builtin not in BUILTINS:
        raise TrajectoryError(f"{where}: builtin", f"unknown builtin {builtin!r} (one of: "
                              f"{', '.join(sorted(BUILTINS))})")
    spec = BUILTINS[builtin]
    w = f"{where}: builtin {builtin!r}"
    check_trajectory_keys(cfg, set(spec) | {"builtin", "name"}, w)
    params = {}
    for key, dim in spec.items():
        if key not in cfg:
            continue
        if dim == "int":
            params[key] = integer(cfg[key], f"{w}: {key}", TrajectoryError, limit=key)
        else:
            params[key] = trajectory_quantity(cfg[key], dim, f"{w}: {key}")
    if "lon" in params and not abs(params["lon"]) <= math.pi:
        raise TrajectoryError(f"{w}: lon", f"{cfg['lon']!r} is not within ±180 deg")
    return builtin_trajectory(builtin, params, where=w, dt=dt, name=name, duration=duration)


def csv_trajectory(csv, *, where: str, base_dir: Path | None, max_gap: float | None = None,
                   name: str = "") -> Trajectory:
    """A trajectory read from a CSV file named in a study (:func:`load_trajectory_csv`).

    ``csv`` is relative to ``base_dir`` (the study file's folder, never the
    current directory); ``max_gap`` [s] is the longest step that may be
    interpolated; ``name`` relabels it.

    Raises
    ------
    TrajectoryError
        Not a file name, no such file, or a bad file (named with ``where``).
    """
    if max_gap is not None:
        check_positive(max_gap, f"{where}: max_gap")
    path = resolve_input(csv, base_dir, f"{where}: csv", TrajectoryError, must_exist=False)
    try:
        traj = load_trajectory_csv(path, max_gap=max_gap)
    except TrajectoryError as exc:
        raise TrajectoryError(f"{where}: {exc.where}", exc.problem) from None
    return traj if not name else Trajectory(**trajectory_fields(traj), stationary=traj.stationary,
                                            name=name, _source=traj._source)


def builtin_trajectory(builtin: str, params: dict, *, where: str, dt: float, name: str = "",
                       duration: float | None = None) -> Trajectory:
    """A built-in profile from its parameters in SI.

    Parameters
    ----------
    builtin : {"land_vehicle", "static"}
        The profile.
    params : dict
        Its parameters (:data:`BUILTINS`) in SI.  A study passes every
        one, its declaration's values and defaults
        (:class:`covtool.studies.config.LandVehicle`, ``Static``); the route's
        own keyword defaults (:func:`covtool.nav.trajectory.profiles.land_vehicle`)
        fill any left out.
    where : str
        Location prefix of error messages.
    dt : float
        Time step of the profile. [s]
    duration : float, optional
        The ``static`` profile's span when ``params`` has no ``duration``
        (else 30 min). [s]

    Raises
    ------
    TrajectoryError
        A missing position of ``static``, a position off the NED frame's
        domain, or a route that does not fit (:func:`land_vehicle_profile`).
    """
    if builtin == "static":
        for key in ("lat", "lon", "h"):
            if params.get(key) is None:
                raise TrajectoryError(where, f"missing required key {key!r}")
        span = params.get("duration")
        return static_profile(where, duration=(1800.0 if duration is None else duration) if span is None else span,
                              lat=params["lat"], lon=params["lon"], h=params["h"],
                              heading=params.get("heading", 0.0), dt=dt, name=name or "static")
    if "lat" in params or "h" in params:
        check_position(params.get("lat", 0.0), params.get("h", 0.0), where)
    return land_vehicle(dt=dt, name=name or "land_vehicle", where=where, **params)
