"""Shared sections of the study files, and the trajectory.

``[study]`` (the propagation step and the truth's discretisation: Van Loan
or the series of seed 002 eq (6b)-(6d)), ``[output]``, ``[truth]`` with its
overrides, ``[filters]``, ``[zupt]`` (Δt_s of seed 002 eq (12)-(13), R of
eq (7)), and the ``[trajectory]`` variants (land vehicle, static, segments,
CSV) with the ``Trajectory`` union that picks one by its keys.
"""

from __future__ import annotations

import math

from typing import Annotated, Any, ClassVar, Literal, Union

from pydantic import BeforeValidator, ConfigDict, Field, model_validator
from pydantic_core import PydanticCustomError

from covtool.studies.config.field_types import (
    Bool, F, Integer, Kind, Memory, Names, OneOf, Quantity, QuantityList, Raw, Section, Text,
)


def _problem(problem: str, suffix: str = "") -> PydanticCustomError:
    """A refusal inside a validator: ``suffix`` names the key after the table (``" dt"``)."""
    return PydanticCustomError("covtool", "{problem}", {"problem": problem, "suffix": suffix})


# ---------------------------------------------------------------------------
# shared sections
# ---------------------------------------------------------------------------

class StudySection(Section):
    name: ClassVar[str] = "study"
    doc: ClassVar[str] = "What the study is and its time grid."
    kind: OneOf("pure_ins", "zupt_filter_order", "ad_reset", "zupt_sensitivity", "error_budget", "trade_grid",
                "monte_carlo", "dual_imu", "magnitude_sweep", "aided") = F(..., "The study kind: the runner and "
                                                                           "its tables.")
    # checked by covtool.io.names.check_study_name (a safe file name), which knows the file's stem
    name_: Annotated[Any, Kind("string (a file name)")] = Field(None, alias="name", description=(
        "Name of the outputs (`<name>.xlsx`): letters, digits, `_`, `-`, `.`; default: the study file's stem."))
    description: Text() = F("", "One line shown in the workbook's provenance.")
    duration: Quantity("time", positive=True) = F("30 min", "Length of the study (the propagation span).")
    dt: Quantity("time", positive=True) = F("1 s", "Propagation step: F is held constant over one step; "
                                                    "ZUPT updates fall on this grid.")
    discretization: OneOf("van_loan", "taylor") = F("van_loan", "How the truth's Φ and Q_d are computed: "
                                                               "exact (Van Loan) or the series of seed 002 "
                                                               "eq (6b)-(6d).")
    max_memory: Memory | None = F(None, "Memory the study may use ('6 GB'); default: what the machine has free. "
                                        "Refused before computing when the estimate exceeds it.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)

    @model_validator(mode="wrap")
    @classmethod
    def _dt_within_duration(cls, data, handler):
        self = handler(data)
        if self.dt > self.duration * (1 + 1e-12):
            shown = data.get("dt", "1 s") if isinstance(data, dict) else f"{self.dt:g} s"
            raise _problem(f"{shown!r} is longer than the duration ({self.duration:g} s): one step would hold "
                           "F constant over the whole study", " dt")
        return self


class StudySectionShort(Section):
    """``[study]`` of the board and dual-IMU kinds: no time grid (their grid comes from the IMU rates)."""

    name: ClassVar[str] = "study (dual_imu)"
    doc: ClassVar[str] = "What the study is (the time grid comes from the sensor rates)."
    kind: OneOf("ad_reset", "dual_imu") = F(..., "The study kind.")
    # (the board and dual-IMU kinds take no duration, dt, discretization or max_memory)
    # checked by covtool.io.names.check_study_name (a safe file name), which knows the file's stem
    name_: Annotated[Any, Kind("string (a file name)")] = Field(None, alias="name", description=(
        "Name of the outputs (`<name>.xlsx`): letters, digits, `_`, `-`, `.`; default: the study file's stem."))
    description: Text() = F("", "One line shown in the workbook's provenance.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


class AdResetStudySection(StudySectionShort):
    name: ClassVar[str] = "study (ad_reset)"
    title: Text() | None = F(None, "Figure title (default: the name).")


class OutputSection(Section):
    name: ClassVar[str] = "output"
    doc: ClassVar[str] = "What the tables hold."
    history_every: Quantity("time", positive=True) = F("10 s", "Spacing of the rows of `history.csv`.")
    report_times: QuantityList("time", limit="report_times", nonnegative=True) | None = F(
        None, "Times of the summary rows, each within the study (default: the end).")
    units: OneOf("ft", "m") = F("ft", "Length unit of the figures and workbook charts (seed 002's feet, or "
                                      "metres); the tables keep both.")

    @model_validator(mode="wrap")
    @classmethod
    def _times_once(cls, data, handler):
        self = handler(data)
        if self.report_times is not None and len(set(self.report_times)) != len(self.report_times):
            shown = data["report_times"] if isinstance(data, dict) and "report_times" in data else \
                [f"{x:g} s" for x in self.report_times]
            raise _problem(f"a time is listed twice in {shown!r}", " report_times")
        return self


class OverrideEntry(Section):
    name: ClassVar[str] = "truth.override.<state or block>"
    doc: ClassVar[str] = ("Changes to one truth state, or to every state of one block (`gyro_bias`); a state's "
                          "own table wins over its block's, key by key. Values in the state's datasheet units.")
    sigma: Raw = F(None, "Initial 1σ (or the steady-state 1σ of a Gauss–Markov state), in the state's unit; "
                         ">= 0 (a quaternion component <= 1).")
    tau: Quantity("time", positive=True) | None = F(None, "Correlation time of a `markov` state.")
    distance: Quantity("length", positive=True) | None = F(None, "Correlation distance of a "
                                                                 "`markov_distance` state.")
    rw: Raw = F(None, "Random-walk intensity of a `random_walk` state (e.g. '0.01 deg/h/sqrt(h)'); >= 0.")


def _model_name(v):
    if not isinstance(v, str) or not v.strip():
        raise _problem(f"{v!r} is not a model name or file")
    return v


_ModelName = Annotated[str, BeforeValidator(_model_name), Kind("string")]


class TruthSection(Section):
    name: ClassVar[str] = "truth"
    doc: ClassVar[str] = "The truth model: the real IMU and environment."
    nested: ClassVar[dict] = {"override": OverrideEntry}
    model: _ModelName = F("sdins58", "A library model name (`covtool models`) or a path relative to "
                                     "the study file.")
    only: Names(what="state or block name") | None = F(None, "Keep only these error sources (states, blocks, "
                                                             "'arw', 'vrw'); every other is zeroed.")
    # checked against the model's states (their dimensions) by covtool.studies.inputs.apply_overrides
    override: Annotated[Any, Kind("table of [truth.override.<state or block>] tables")] = F(
        {}, "Per-state or per-block changes, see [truth.override.<state or block>].")
    arw: Quantity("angle_random_walk", nonnegative=True) | None = F(None, "Gyro angle random walk "
                                                                          "('0.002 deg/sqrt(h)').")
    vrw: Quantity("velocity_random_walk", nonnegative=True) | None = F(None, "Accelerometer velocity random "
                                                                             "walk ('10 ug/sqrt(Hz)').")
    override_filters: Bool = F(False, "Whether the overrides also reach the filters (their P0, kept dynamics "
                                      "and equivalent noise). Default false: the truth is the real IMU, a filter "
                                      "file is a design, and an override shows how the filters fare when the "
                                      "sensors depart from the design values.")


class FiltersSection(Section):
    name: ClassVar[str] = "filters"
    doc: ClassVar[str] = "The filters run against the truth (see 'Filter files' below)."
    file: Raw = F(None, "A filter file or a list of them: paths relative to the study file, or names of the "
                        "library's filter files ('zupt_filters'); a filter's `base` may name a filter of any of "
                        "them. Default: the library's zupt_filters.", example="zupt_filters")
    cases: Names(nonempty=False, what="filter") | None = F(None, "Filters to run, each once (default: every "
                                                                 "filter of the files).")
    pure_ins: Bool = F(True, "Also propagate the unaided INS (a reference case).")


class ZuptSection(Section):
    name: ClassVar[str] = "zupt"
    doc: ClassVar[str] = "Zero-velocity updates at the trajectory's stops."
    interval: Quantity("time", positive=True) = F("5 min", "Δt_s of seed 002 eq (12)-(13): a stop every "
                                                           "interval.")
    duration: Quantity("time", nonnegative=True) = F("30 s", "Measurement window ending at each stop's ZUPT "
                                                             "time; shorter than the interval.")
    rate: Quantity("frequency", positive=True) = F("1 Hz", "Updates per second inside the window (at most "
                                                           "1/dt).")
    sigma: Quantity("velocity", positive=True) = F("0.01 ft/s", "True ZUPT noise 1σ per axis (R); > 0, since "
                                                                "R = 0 makes eq (7)'s S singular.")
    first: Quantity("time", positive=True) | None = F(None, "Time of the first ZUPT (default: the interval); "
                                                            "within the study.")


# ---------------------------------------------------------------------------
# trajectory
# ---------------------------------------------------------------------------

def _lon_within(data, self):
    if self.lon is not None and not abs(self.lon) <= math.pi:
        shown = data.get("lon") if isinstance(data, dict) else f"{self.lon:g} rad"
        raise _problem(f"{shown!r} is not within ±180 deg", " lon")
    return self


class LandVehicle(Section):
    name: ClassVar[str] = "trajectory (builtin = \"land_vehicle\")"
    doc: ClassVar[str] = ("The built-in ZUPT land-vehicle route (stands in for seed 002 Fig 3): `cycles` periods "
                          "of drive then stop; a drive is accelerate, cruise, turn, cruise, grade, cruise, turn, "
                          "cruise, decelerate.")
    builtin: Literal["land_vehicle"] = F("land_vehicle", "The route.")
    name_: Text() | None = Field(None, alias="name", description="Label of the trajectory.")
    cycles: Integer(limit="cycles") = F(6, "Number of drive/stop cycles.")
    period: Quantity("time") = F("5 min", "Cycle length: a stop every period (match [zupt] interval).")
    stop_duration: Quantity("time") = F("90 s", "Standstill at the end of each cycle.")
    distance: Quantity("length") = F("15 km", "Total distance driven; sets the cruise speed.")
    accel_duration: Quantity("time") = F("20 s", "Duration of each start and stop manoeuvre.")
    turn_rate: Quantity("angular_rate") = F("5 deg/s", "Peak yaw rate of every turn.")
    turn_angle: Quantity("angle") = F("90 deg", "Angle of every turn (they alternate left and right).")
    grade: Quantity("dimensionless") = F(0.04, "Road grade (rise over run, '4 %') of the hill in each drive "
                                               "(climb on odd cycles, descend on even ones).")
    grade_duration: Quantity("time") = F("60 s", "Duration of each hill, transitions included.")
    lat: Quantity("angle") = F("36.37 deg", "Start latitude.")
    lon: Quantity("angle") = F("127.36 deg", "Start longitude (within ±180 deg).")
    h: Quantity("length") = F("60 m", "Start height.")
    heading: Quantity("angle") = F("0 deg", "Initial heading.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)

    @model_validator(mode="wrap")
    @classmethod
    def _lon(cls, data, handler):
        return _lon_within(data, handler(data))


class Static(Section):
    name: ClassVar[str] = "trajectory (builtin = \"static\")"
    doc: ClassVar[str] = "Standing still (alignment, a bench test)."
    builtin: Literal["static"] = F("static", "The profile.")
    name_: Text() | None = Field(None, alias="name", description="Label of the trajectory.")
    duration: Quantity("time") | None = F(None, "Span; default: the study's duration.")
    lat: Quantity("angle") = F(..., "Latitude.", example="37 deg")
    lon: Quantity("angle") = F(..., "Longitude (within ±180 deg).", example="127 deg")
    h: Quantity("length") = F(..., "Height.", example="50 m")
    heading: Quantity("angle") = F("0 deg", "Heading.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)

    @model_validator(mode="wrap")
    @classmethod
    def _lon(cls, data, handler):
        return _lon_within(data, handler(data))


class Initial(Section):
    name: ClassVar[str] = "trajectory.initial"
    doc: ClassVar[str] = "Start of a segment trajectory."
    lat: Quantity("angle") = F(..., "Latitude.", example="37 deg")
    lon: Quantity("angle") = F(..., "Longitude.", example="127 deg")
    h: Quantity("length") = F(..., "Height.", example="50 m")
    heading: Quantity("angle") = F("0 deg", "Heading.")
    speed: Quantity("velocity") = F("0 m/s", "Speed.")


class Segment(Section):
    name: ClassVar[str] = "[trajectory.segment]]"
    doc: ClassVar[str] = ("One piece of a segment trajectory; `kind` is stand, cruise, accelerate, decelerate, "
                          "turn or grade. accelerate/decelerate: `to_speed` and one of `duration` or "
                          "`acceleration`; turn: two of `rate`, `angle`, `duration`; grade: `grade` or `angle`, "
                          "and `duration`.")
    kind: OneOf("stand", "cruise", "accelerate", "decelerate", "turn", "grade") = F(..., "The segment kind.",
                                                                                  example="stand")
    duration: Quantity("time") | None = F(None, "Duration.")
    to_speed: Quantity("velocity") | None = F(None, "Speed at the end (accelerate/decelerate).")
    acceleration: Quantity("acceleration") | None = F(None, "Plateau acceleration (accelerate/decelerate).")
    transition: Quantity("time") | None = F(None, "Ramp time of the acceleration, yaw rate or pitch "
                                                  "(default 3 s, 5 s for a grade).")
    rate: Quantity("angular_rate") | None = F(None, "Yaw rate of a turn (right positive).")
    angle: Quantity("angle") | None = F(None, "Angle of a turn, or pitch of a grade.")
    grade: Quantity("dimensionless") | None = F(None, "Rise over run of a grade ('5 %').")
    level_off: Bool = F(True, "A grade returns to level within its duration (false: stays on the grade).")


class Segments(Section):
    name: ClassVar[str] = "trajectory (segment = [...])"
    doc: ClassVar[str] = "A trajectory written as segments."
    nested: ClassVar[dict] = {"initial": Initial, "segment": [Segment]}
    segment: Raw = F(..., "The segments, in order: [[trajectory.segment]] tables.")
    initial: Raw = F(..., "The start: [trajectory.initial].")
    name_: Text() | None = Field(None, alias="name", description="Label of the trajectory.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


class CsvTrajectory(Section):
    name: ClassVar[str] = "trajectory (csv = \"file.csv\")"
    doc: ClassVar[str] = "A trajectory read from a CSV file (time, position, velocity, attitude columns)."
    csv: Text(nonempty=True) = F(..., "Path of the CSV, relative to the study file.", example="route.csv")
    # > 0, checked where the file is read (covtool.io.trajectory.csv_trajectory), as for a CSV named elsewhere
    max_gap: Quantity("time") | None = F(None, "Longest time step that may be interpolated (> 0).")
    name_: Text() | None = Field(None, alias="name", description="Label of the trajectory.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


#: the forms of ``[trajectory]``
TRAJECTORIES = (LandVehicle, Static, Segments, CsvTrajectory)


def _trajectory(v):
    if isinstance(v, TRAJECTORIES):          # a typed section (a configuration varied by model_copy)
        return v
    if not isinstance(v, dict):
        raise PydanticCustomError("covtool", "{problem}", {"problem": f"expected a table, got {type(v).__name__}"})
    sources = [k for k in ("builtin", "segment", "csv") if k in v]
    if len(sources) != 1:
        raise PydanticCustomError("covtool", "{problem}", {"problem": "give exactly one of 'builtin', 'segment' "
                                  f"and 'csv' (got {', '.join(map(repr, sources)) or 'none'})"})
    if sources[0] == "builtin":
        cls = {"land_vehicle": LandVehicle, "static": Static}.get(v["builtin"])
        if cls is None:
            raise PydanticCustomError("covtool", "{problem}", {"problem": f"unknown builtin {v['builtin']!r} "
                                      "(one of: land_vehicle, static)"})
    else:
        cls = Segments if sources[0] == "segment" else CsvTrajectory
    return cls.model_validate(v)


Trajectory = Annotated[Union[LandVehicle, Static, Segments, CsvTrajectory], BeforeValidator(_trajectory),
                       Kind("table")]
