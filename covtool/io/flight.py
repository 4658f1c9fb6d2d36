"""Flight-profile declarations (datasheet units) and the built-in high-dynamics flight.

:func:`flight_from_config` validates a study file's flight table and builds
the profile with :func:`covtool.nav.trajectory.flight.flight`; the built-in
:func:`high_dynamics_flight` (seed 001's verification flight) is declared
the same way, in datasheet units.
"""

from __future__ import annotations

from covtool.errors import TrajectoryError
from covtool.io.config import LIMITS, quantity
from covtool.io.trajectory import check_trajectory_keys as _check, trajectory_quantity
from covtool.nav.trajectory.core import Trajectory
from covtool.nav.trajectory.flight import (DEFAULT_TRANSITION, flight, Segment, TONE_KINDS,
                                           VibrationInterval, VibrationTone)

__all__ = [
    "high_dynamics_flight", "flight_from_config", "SEGMENT_KEYS", "FLIGHT_BUILTINS",
]


#: flight segment kind -> allowed keys
SEGMENT_KEYS = {
    "stand": ("kind", "duration"),
    "fly": ("kind", "duration", "to_speed", "to_pitch", "to_roll", "turn", "transition"),
}
_SEGMENT_DIMS = {"duration": "time", "to_speed": "velocity", "to_pitch": "angle", "to_roll": "angle",
                 "turn": "angle", "transition": "time"}
_INITIAL_DIMS = {"lat": "angle", "lon": "angle", "h": "length", "heading": "angle", "pitch": "angle"}
_VIB_DIMS = {"start": "time", "duration": "time", "ramp": "time"}
_TONE_DIMS = dict(zip(TONE_KINDS, ("angle", "acceleration")))


#: the built-in profile's segments (datasheet units), see :func:`high_dynamics_flight`
HIGH_DYNAMICS_SEGMENTS = (
    {"kind": "stand", "duration": "12 s"},
    {"kind": "fly", "duration": "6 s", "to_speed": "650 m/s", "turn": "25 deg", "transition": "1 s"},
    {"kind": "fly", "duration": "4 s", "to_pitch": "0 deg", "to_speed": "640 m/s", "transition": "1 s"},
    {"kind": "fly", "duration": "3 s", "to_roll": "360 deg", "transition": "0.5 s"},
    {"kind": "fly", "duration": "1.5 s", "to_roll": "420 deg", "transition": "0.5 s"},
    {"kind": "fly", "duration": "5 s", "turn": "60 deg", "transition": "1 s"},
    {"kind": "fly", "duration": "1.5 s", "to_roll": "360 deg", "transition": "0.5 s"},
    {"kind": "fly", "duration": "10 s", "turn": "-10 deg", "transition": "2 s"},
    {"kind": "fly", "duration": "5 s", "to_speed": "800 m/s", "turn": "-40 deg", "transition": "1 s"},
    {"kind": "fly", "duration": "3 s", "to_pitch": "15 deg", "transition": "1 s"},
    {"kind": "fly", "duration": "3 s", "to_pitch": "0 deg", "transition": "1 s"},
    {"kind": "fly", "duration": "4 s", "turn": "45 deg", "to_speed": "780 m/s", "transition": "1 s"},
    {"kind": "fly", "duration": "4 s", "turn": "-45 deg", "transition": "1 s"},
    {"kind": "fly", "duration": "5 s", "to_speed": "760 m/s"},
)
#: the built-in profile's vibration interval (during the 10 s cruise)
HIGH_DYNAMICS_VIBRATION = {
    "start": "33 s", "duration": "10 s", "ramp": "1 s",
    "tone": [
        {"kind": "angular", "axis": "x", "amplitude": "0.2 mrad", "frequency": "17 Hz"},
        {"kind": "angular", "axis": "y", "amplitude": "0.15 mrad", "frequency": "23 Hz"},
        {"kind": "angular", "axis": "z", "amplitude": "0.1 mrad", "frequency": "29 Hz"},
        {"kind": "linear", "axis": "x", "amplitude": "1 g", "frequency": "13 Hz"},
        {"kind": "linear", "axis": "y", "amplitude": "0.5 g", "frequency": "19 Hz"},
        {"kind": "linear", "axis": "z", "amplitude": "0.8 g", "frequency": "31 Hz"},
    ],
}
#: the built-in profile's start (a launcher at 36.37 N, 127.36 E)
HIGH_DYNAMICS_INITIAL = {"lat": "36.37 deg", "lon": "127.36 deg", "h": "60 m", "heading": "45 deg",
                         "pitch": "10 deg"}


def high_dynamics_flight(*, dt=0.1, vibration=True, name="high_dynamics_flight") -> Trajectory:
    """Built-in high-dynamics flight (seed 001's verification flight).

    A 12 s stand on a launcher at 10 deg elevation (alignment), a 6 s boost
    to 650 m/s (about 11 g) with a 25 deg heading change, pitch-over, a
    full roll at ~180 deg/s, a 60 deg bank with a 60 deg turn (~14 g), a
    10 s cruise with flight vibration (angular and linear tones, 13–31 Hz),
    a 3 g sustain boost with a 40 deg turn, a pull-up and S-turns: 67 s.

    Parameters
    ----------
    dt : float
        Grid step. [s]
    vibration : bool
        Include the vibration interval.
    name : str

    Returns
    -------
    Trajectory
    """
    cfg = {"segment": [dict(s) for s in HIGH_DYNAMICS_SEGMENTS], "initial": dict(HIGH_DYNAMICS_INITIAL)}
    if vibration:
        cfg["vibration"] = [dict(HIGH_DYNAMICS_VIBRATION)]
    return flight_from_config(cfg, where="high_dynamics_flight", dt=dt, name=name)


#: built-in flight profiles
FLIGHT_BUILTINS = {"high_dynamics_flight": high_dynamics_flight}




def flight_from_config(cfg: dict, *, where: str, dt: float, name: str | None = None) -> Trajectory:
    """Flight profile from a study-file table.

    Parameters
    ----------
    cfg : dict
        ``{builtin = "high_dynamics_flight", vibration = true}`` or
        ``{segment = [...], initial = {...}, vibration = [...]}`` with
        datasheet units: segments ``{kind = "fly", duration, to_speed,
        to_pitch, to_roll, turn, transition}`` or ``{kind = "stand",
        duration}``; ``initial`` ``lat, lon, h`` (required), ``heading``,
        ``pitch``; vibration intervals ``{start, duration, ramp, tone = [{kind,
        axis, amplitude, frequency, phase}]}``.  ``name`` optional.
    where : str
        Error-message prefix (``"studies/x.toml: [trajectory]"``).
    dt : float
        Grid step. [s]
    name : str, optional
        Label (overrides ``cfg["name"]``).

    Returns
    -------
    Trajectory

    Raises
    ------
    TrajectoryError
        Naming ``where``, the key and the problem.
    """
    _check(cfg, {"builtin", "segment", "initial", "vibration", "name"}, where)
    label = name or cfg.get("name") or "flight"
    if not isinstance(label, str):
        raise TrajectoryError(f"{where}: name", f"{label!r} is not a string")
    if "builtin" in cfg:
        extra = set(cfg) - {"builtin", "vibration", "name"}
        if extra:
            raise TrajectoryError(where, f"'builtin' takes only 'vibration' and 'name' (got {sorted(extra)})")
        b = cfg["builtin"]
        if b not in FLIGHT_BUILTINS:
            raise TrajectoryError(f"{where}: builtin", f"unknown flight profile {b!r} (one of: "
                                  f"{', '.join(sorted(FLIGHT_BUILTINS))})")
        vib = cfg.get("vibration", True)
        if not isinstance(vib, bool):
            raise TrajectoryError(f"{where}: vibration", f"{vib!r} is not true or false")
        return FLIGHT_BUILTINS[b](dt=dt, vibration=vib, name=cfg.get("name") or b)
    for key in ("segment", "initial"):
        if key not in cfg:
            raise TrajectoryError(where, f"missing required key {key!r} (or give 'builtin')")
    init = cfg["initial"]
    _check(init, set(_INITIAL_DIMS), f"{where}: initial")
    iv = {}
    for key, dim in _INITIAL_DIMS.items():
        if key in init:
            iv[key] = trajectory_quantity(init[key], dim, f"{where}: initial: {key}")
        elif key in ("lat", "lon", "h"):
            raise TrajectoryError(f"{where}: initial", f"missing required key {key!r}")
    segs = cfg["segment"]
    if not isinstance(segs, list) or not segs:
        raise TrajectoryError(f"{where}: segment", "expected a non-empty list of segments")
    segments = []
    for i, s in enumerate(segs):
        w = f"{where}: segment[{i}]"
        if not isinstance(s, dict):
            raise TrajectoryError(w, f"expected a table, got {type(s).__name__}")
        kind = s.get("kind")
        if kind not in SEGMENT_KEYS:
            raise TrajectoryError(w, f"unknown segment kind {kind!r} (one of: {', '.join(sorted(SEGMENT_KEYS))})")
        w = f"{w} ({kind})"
        _check(s, SEGMENT_KEYS[kind], w)
        if "duration" not in s:
            raise TrajectoryError(w, "missing required key 'duration'")
        v = {k: trajectory_quantity(x, _SEGMENT_DIMS[k], f"{w}: {k}") for k, x in s.items() if k != "kind"}
        segments.append(Segment(kind, v["duration"], v.get("to_speed"), v.get("to_pitch"), v.get("to_roll"),
                                v.get("turn", 0.0), v.get("transition", DEFAULT_TRANSITION)))
    vib_cfg = cfg.get("vibration", [])
    if isinstance(vib_cfg, dict):
        vib_cfg = [vib_cfg]
    if not isinstance(vib_cfg, list):
        raise TrajectoryError(f"{where}: vibration", "expected a table or a list of tables")
    vibration = []
    for k, vc in enumerate(vib_cfg):
        w = f"{where}: vibration[{k}]"
        _check(vc, set(_VIB_DIMS) | {"tone"}, w)
        for key in ("start", "duration", "tone"):
            if key not in vc:
                raise TrajectoryError(w, f"missing required key {key!r}")
        vv = {key: trajectory_quantity(vc[key], dim, f"{w}: {key}") for key, dim in _VIB_DIMS.items() if key in vc}
        tones = []
        if not isinstance(vc["tone"], list) or not vc["tone"]:
            raise TrajectoryError(f"{w}: tone", "expected a non-empty list of tones")
        for j, tc in enumerate(vc["tone"]):
            wt = f"{w}: tone[{j}]"
            _check(tc, {"kind", "axis", "amplitude", "frequency", "phase"}, wt)
            for key in ("kind", "axis", "amplitude", "frequency"):
                if key not in tc:
                    raise TrajectoryError(wt, f"missing required key {key!r}")
            if not isinstance(tc["kind"], str) or tc["kind"] not in _TONE_DIMS:
                raise TrajectoryError(f"{wt}: kind", f"{tc['kind']!r} is not 'angular' or 'linear'")
            # the increment quadrature takes nodes in proportion to the highest tone frequency
            lim = LIMITS["imu_rate"]
            freq = quantity(tc["frequency"], "frequency", f"{wt}: frequency", TrajectoryError, positive=True,
                            hi=lim.hi, why="the IMU increments are integrated through every tone cycle")
            tones.append(VibrationTone(tc["kind"], tc["axis"], trajectory_quantity(tc["amplitude"], _TONE_DIMS[tc["kind"]],
                                                                   f"{wt}: amplitude"),
                                       freq,
                                       trajectory_quantity(tc.get("phase", 0.0), "angle", f"{wt}: phase")))
        vibration.append(VibrationInterval(vv["start"], vv["duration"], vv.get("ramp", 1.0), tuple(tones)))
    return flight(segments, lat=iv["lat"], lon=iv["lon"], h=iv["h"], heading=iv.get("heading", 0.0),
                  pitch=iv.get("pitch", 0.0), vibration=vibration, dt=dt, name=label, where=where)
