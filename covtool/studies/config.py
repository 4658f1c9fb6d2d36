"""Typed study configurations: one frozen declaration per study kind and per section.

Every key a study file may hold is declared here once, with its type or unit
dimension, its default, its range and its meaning (the field description).
The declarations

* parse a study file into a frozen, typed configuration
  (:func:`load_config`; pydantic v2, ``extra="forbid"``), each field
  validated by the typed field helpers of :mod:`covtool.io.config`, so the
  messages are the ones the runners give (file, section, key, problem);
* generate the study-file reference ``docs/study_files.md``
  (:mod:`covtool.studies.reference`) and the commented starting file of
  ``covtool new KIND``;
* dump a configuration back to TOML (:func:`dump_config`): quantities as SI
  strings that parse back exactly, so load -> dump -> load is the identity.

Quantities are held in SI (``covtool.units``); the defaults are written in
datasheet units, as a user writes them.
"""

from __future__ import annotations

import math
import re
from typing import Annotated, Any, ClassVar, Literal, Union

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, model_validator
from pydantic_core import PydanticCustomError

from covtool.errors import InputError, StudyFileError
from covtool.io import config as fields
from covtool.io.config import LIMITS
from covtool.lincov.measurements import KINDS as MEASUREMENT_KINDS, WHEN
from covtool.units import DIMENSIONS

__all__ = ["si_text", "Section", "KINDS", "SECTIONS", "load_config", "dump_config", "config_class", "parse_section"]


# ---------------------------------------------------------------------------
# field types: each validator is one of covtool.io.config's typed helpers
# ---------------------------------------------------------------------------

class _Problem(InputError):
    """A field helper's refusal inside a pydantic validator (no location yet)."""


def _wrap(check):
    def validate(value):
        try:
            return check(value)
        except InputError as exc:
            # exc.where is the helper's own suffix (``[i]`` of a list item), "" otherwise
            raise PydanticCustomError("covtool", "{problem}", {"problem": exc.problem,
                                                               "suffix": exc.where or ""}) from None
    return validate


class Kind:
    """What a field holds, for the reference: ``"time"``, ``"integer"``, ``"list of names"``, ..."""

    def __init__(self, text: str, dimension: str | None = None, range_text: str = ""):
        self.text, self.dimension, self.range_text = text, dimension, range_text


def Quantity(dimension: str, *, positive=False, nonnegative=False, hi=None, why=""):
    """A quantity in SI from a datasheet string (``"5 min"``); see :func:`covtool.io.config.quantity`."""
    rng = "> 0" if positive else ">= 0" if nonnegative else ""
    if hi is not None:
        rng = (rng + " and " if rng else "") + f"<= {hi:g} (SI)"
    return Annotated[float, BeforeValidator(_wrap(lambda v: fields.quantity(
        v, dimension, "", _Problem, positive=positive, nonnegative=nonnegative, hi=hi, why=why))),
        Kind(f"quantity ({dimension})", dimension, rng)]


def QuantityList(dimension: str, *, limit=None, **kw):
    """A non-empty list of quantities in SI."""
    return Annotated[tuple[float, ...], BeforeValidator(_wrap(lambda v: tuple(fields.quantity_list(
        v, dimension, "", _Problem, limit=limit, **kw)))), Kind(f"list of quantities ({dimension})", dimension)]


def Integer(*, limit=None, lo=None, hi=None):
    """An integer in a range (a :data:`~covtool.io.config.LIMITS` entry or ``lo``/``hi``)."""
    b = LIMITS.get(limit)
    lo_, hi_ = (b.lo if b else lo), (b.hi if b else hi)
    rng = f"{lo_:g}..{hi_:g}" if lo_ is not None and hi_ is not None else ""
    return Annotated[int, BeforeValidator(_wrap(lambda v: fields.integer(v, "", _Problem, lo=lo, hi=hi,
                                                                           limit=limit))),
                     Kind("integer", None, rng + (f" ({b.reason})" if b else ""))]


def Number(*, lo=None, hi=None, lo_open=False, hi_open=False, why=""):
    """A finite bare number in a range."""
    parts = [p for p in ((("> " if lo_open else ">= ") + f"{lo:g}") if lo is not None else "",
                         (("< " if hi_open else "<= ") + f"{hi:g}") if hi is not None else "") if p]
    return Annotated[float, BeforeValidator(_wrap(lambda v: fields.number(
        v, "", _Problem, lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open, why=why))),
        Kind("number", None, " and ".join(parts) + (f" ({why})" if why else ""))]


Bool = Annotated[bool, BeforeValidator(_wrap(lambda v: fields.boolean(v, "", _Problem))), Kind("true or false")]


def Text(*, nonempty=False):
    return Annotated[str, BeforeValidator(_wrap(lambda v: fields.string(v, "", _Problem, nonempty=nonempty))),
                     Kind("string")]


def OneOf(*options):
    shown = ", ".join(repr(o) if isinstance(o, str) else str(o).lower() for o in options)
    return Annotated[Any, BeforeValidator(_wrap(lambda v: fields.choice(v, options, "", _Problem))),
                     Kind(f"one of {shown}")]


def Names(*, known=None, nonempty=True, what="name"):
    return Annotated[tuple[str, ...], BeforeValidator(_wrap(lambda v: tuple(fields.names(
        v, "", _Problem, known=known, nonempty=nonempty, what=what)))), Kind(f"list of {what}s")]


def Table(what: str):
    """A TOML table validated by the runner (its keys are declared by a nested section)."""
    return Annotated[dict, BeforeValidator(_wrap(lambda v: fields.table(v, "", _Problem))), Kind(what)]


def _memory(v):
    from covtool.studies.resources import parse_bytes

    return parse_bytes(v, "", _Problem)


Memory = Annotated[float, BeforeValidator(_wrap(_memory)), Kind("memory size ('6 GB', '512 MiB')", "memory")]

#: any TOML value, validated by the runner (a list of tables, a value of the truth state's dimension)
Raw = Annotated[Any, Kind("see the description")]


def F(default=..., doc: str = "", example=None):
    """A declared field: its default (datasheet units) and meaning; ``example`` for ``covtool new``."""
    extra = {"example": example} if example is not None else None
    return Field(default, description=doc, json_schema_extra=extra)


class Section(BaseModel):
    """One table of a study file: frozen, unknown keys refused, defaults validated."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)

    #: ``[name]`` of the table in a study file
    name: ClassVar[str] = ""
    #: what the table is for (first line of its reference entry)
    doc: ClassVar[str] = ""
    #: nested tables: key -> Section class (a list of tables for ``[[key]]``)
    nested: ClassVar[dict] = {}


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


class TruthSection(Section):
    name: ClassVar[str] = "truth"
    doc: ClassVar[str] = "The truth model: the real IMU and environment."
    nested: ClassVar[dict] = {"override": OverrideEntry}
    model: Text(nonempty=True) = F("sdins58", "A library model name (`covtool models`) or a path relative to "
                                              "the study file.")
    only: Names(what="state or block name") | None = F(None, "Keep only these error sources (states, blocks, "
                                                             "'arw', 'vrw'); every other is zeroed.")
    override: Table("table of [truth.override.<state or block>] tables") = F(
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
    max_gap: Quantity("time", positive=True) | None = F(None, "Longest time step that may be interpolated.")
    name_: Text() | None = Field(None, alias="name", description="Label of the trajectory.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


#: the forms of ``[trajectory]``
TRAJECTORIES = (LandVehicle, Static, Segments, CsvTrajectory)


def _trajectory(v):
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


# ---------------------------------------------------------------------------
# kind-specific sections
# ---------------------------------------------------------------------------

class ImpactSection(Section):
    name: ClassVar[str] = "impact"
    doc: ClassVar[str] = "The dropped-state impact table (covtool.lincov.impact)."
    filters: Names(nonempty=False, what="filter") | None = F(None, "Reduced filters to analyse (default: every "
                                                                   "reduced filter of the run; [] for none).")


class BudgetSection(Section):
    name: ClassVar[str] = "budget"
    doc: ClassVar[str] = "The error budget: each source's share of the navigation errors."
    resolution: OneOf("block", "state") = F("block", "One row per block of the truth model, or per state.")
    top: Integer(limit="budget_top") = F(8, "Sources shown in the stacked figure.")


class Scales(Section):
    name: ClassVar[str] = "sweep.scales"
    doc: ClassVar[str] = "The log-spaced grid of scale factors."
    from_: Number(lo=LIMITS["filter_scale"].lo, hi=LIMITS["filter_scale"].hi) = Field(
        0.01, alias="from", description="Smallest scale.")
    to: Number(lo=LIMITS["filter_scale"].lo, hi=LIMITS["filter_scale"].hi) = F(100, "Largest scale.")
    per_decade: Integer(limit="per_decade") = F(4, "Scales per decade.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


class SensitivitySweep(Section):
    name: ClassVar[str] = "sweep (zupt_sensitivity)"
    doc: ClassVar[str] = "Scale each filter's P0, Q_f or R_f and watch the navigation errors (seed 002 §3.2)."
    nested: ClassVar[dict] = {"scales": Scales}
    parameters: Names(known=["P0", "Q", "R"], what="parameter") = F(["P0", "Q", "R"], "Filter parameters "
                                                                                      "scaled, one at a time.")
    scales: Table("[sweep.scales] table") = F({"from": 0.01, "to": 100, "per_decade": 4},
                                              "The scale grid, see [sweep.scales].")
    fit_degree: Integer(limit="fit_degree") = F(5, "Degree of the log-log polynomial fitted to each curve.")
    discretization: OneOf("declared", "van_loan", "taylor") = F("declared", "The filters' discretisation in the "
                                                                            "sweep ('declared': their own).")


class CostSection(Section):
    name: ClassVar[str] = "cost"
    doc: ClassVar[str] = "Computational cost of each filter (seed 002 Table 4)."
    measure: Bool = F(True, "Time one filter cycle on this machine.")
    repeats: Integer(limit="repeats") = F(7, "Timings per filter (the median is reported).")
    taylor_order: Raw = F("auto", "'auto' or the Taylor terms of eq (6b) used for the flop count (2..40).")
    paper_seconds: Table("table filter = seconds") | None = F(None, "The paper's Table 4 times, compared with the "
                                                             "flop counts (default: seed 002's).")


class MonteCarloSection(Section):
    name: ClassVar[str] = "monte_carlo"
    doc: ClassVar[str] = "Monte Carlo validation against a nonlinear strapdown."
    runs: Integer(limit="mc_runs") = F(..., "Number of runs.", example=50)
    runs_per_chunk: Integer(limit="mc_runs_per_chunk") = F(50, "Runs per worker task.")
    seed: Integer(limit="seed") = F(1, "Seed of the random streams.")
    imu_rate: Quantity("frequency", positive=True, hi=LIMITS["imu_rate"].hi, why=LIMITS["imu_rate"].reason) = F(
        "100 Hz", "Simulated IMU sample rate (a whole multiple of samples_per_step per grid step).")
    samples_per_step: Integer(lo=1, hi=64) = F(4, "IMU samples per navigation step.")
    confidence: Number(lo=0.0, hi=1.0, lo_open=True, hi_open=True) = F(0.95, "Level of the RMS and NEES bands.")
    nees_every: Quantity("time", positive=True) | None = F(None, "Spacing of the NEES samples (default: "
                                                                 "[output] history_every).")
    sensor_noise: Bool = F(True, "Inject the sensors' white noise (ARW/VRW).")
    measurement_noise: Bool = F(True, "Add the ZUPT noise to the measurements.")
    process_dt: Quantity("time", positive=True) = F("0.1 s", "Step of the sensor error processes (>= one IMU "
                                                             "sample).")


class SweepGroup(Section):
    name: ClassVar[str] = "[sweep.group]]"
    doc: ClassVar[str] = "States swept together (one magnitude for all)."
    name_: Text(nonempty=True) = Field(..., alias="name", description="Label of the group.",
                                       json_schema_extra={"example": "gyro misalignment"})
    states: Names(what="state or block name") = F(..., "States or blocks of one dimension, each with σ > 0.",
                                                   example=["gyro_mis"])

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


class MagnitudeSweep(Section):
    name: ClassVar[str] = "sweep (magnitude_sweep)"
    doc: ClassVar[str] = "Set each group's 1σ to every value and find where the navigation errors grow."
    nested: ClassVar[dict] = {"group": [SweepGroup]}
    values: Raw = F(..., "The magnitudes (in the groups' unit), >= 0.", example=["5 arcsec", "30 arcsec"])
    threshold: Number(lo=1.0, lo_open=True) = F(1.5, "Error growth over the nominal that marks a magnitude as "
                                                     "significant.")
    group: Raw = F(..., "The groups: [[sweep.group]] tables.")


class GridSection(Section):
    name: ClassVar[str] = "grid"
    doc: ClassVar[str] = "The trade grid's axes: cases are their product with the grades and filters."
    zupt_interval: QuantityList("time", limit="grid_axis", positive=True) = F(..., "ZUPT intervals (one truth "
                                                                                   "system each).",
                                                                              example=["3 min", "5 min"])
    zupt_sigma: QuantityList("velocity", limit="grid_axis", positive=True) | None = F(
        None, "True ZUPT σ, assumed alike by the filter (default: [zupt] sigma).")
    p0_scale: Raw = F([1.0], "Scales of the filters' P0.")
    q_scale: Raw = F([1.0], "Scales of the filters' Q_f.")
    r_scale: Raw = F([1.0], "Scales of the filters' R_f.")
    cruise_speed: Quantity("velocity", positive=True) = F("45 km/h", "land_vehicle: cruise speed for every "
                                                                     "interval.")


class GradeEntry(Section):
    name: ClassVar[str] = "[grade]]"
    doc: ClassVar[str] = ("An IMU grade: every sensor σ, random walk, ARW and VRW × scale, then explicit "
                          "changes; the filters follow the grade (the designer knows the IMU).")
    name_: Text(nonempty=True) = Field(..., alias="name", description="Label of the grade.",
                                       json_schema_extra={"example": "navigation"})
    scale: Number(lo=LIMITS["grade_scale"].lo, hi=LIMITS["grade_scale"].hi) = F(1.0, "Factor on every sensor "
                                                                                     "error.")
    description: Text() = F("", "One line for the grade table.")
    override: Table("table of state tables") = F({}, "As [truth.override.<state or block>].")
    arw: Raw = F(None, "Gyro ARW of the grade.")
    vrw: Raw = F(None, "Accelerometer VRW of the grade.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


class ImuUnit(Section):
    name: ClassVar[str] = "imu.main / imu.kimu"
    doc: ClassVar[str] = "One IMU of the pair."
    grade: Text(nonempty=True) | None = F(None, "IMU grade: a library name (`covtool models`) or a path "
                                                "relative to the study file (default: main_imu, kimu).")
    mounting: Raw = F(["0 deg", "0 deg", "0 deg"], "[roll, pitch, yaw] of the sensor frame in the body.")
    ratio: Integer(limit="kimu_ratio") | None = F(None, "imu.kimu only: KIMU samples per main sample "
                                                        "(default 4; must match the grades' rates).")


class ImuSection(Section):
    name: ClassVar[str] = "imu"
    doc: ClassVar[str] = "The two IMUs compared (seed 001)."
    nested: ClassVar[dict] = {"main": ImuUnit, "kimu": ImuUnit}
    main: Table("[imu.main] table") = F({}, "The main IMU.")
    kimu: Table("[imu.kimu] table") = F({}, "The KIMU.")


class FlightSegment(Section):
    name: ClassVar[str] = "[trajectory.segment]] (flight)"
    doc: ClassVar[str] = "One piece of a flight: `stand` (duration) or `fly`."
    kind: OneOf("stand", "fly") = F(..., "The segment kind.", example="stand")
    duration: Quantity("time") | None = F(None, "Duration.")
    to_speed: Quantity("velocity") | None = F(None, "fly: speed at the end.")
    to_pitch: Quantity("angle") | None = F(None, "fly: pitch at the end.")
    to_roll: Quantity("angle") | None = F(None, "fly: roll at the end.")
    turn: Quantity("angle") | None = F(None, "fly: heading change.")
    transition: Quantity("time") | None = F(None, "fly: ramp time of the changes.")


class FlightInitial(Section):
    name: ClassVar[str] = "trajectory.initial (flight)"
    doc: ClassVar[str] = "Start of a flight."
    lat: Quantity("angle") = F(..., "Latitude.", example="36.37 deg")
    lon: Quantity("angle") = F(..., "Longitude.", example="127.36 deg")
    h: Quantity("length") = F(..., "Height.", example="60 m")
    heading: Quantity("angle") = F("0 deg", "Heading.")
    pitch: Quantity("angle") = F("0 deg", "Pitch.")


class FlightTrajectory(Section):
    name: ClassVar[str] = "trajectory (dual_imu flight)"
    doc: ClassVar[str] = ("The flight of a dual-IMU study: `builtin = \"high_dynamics_flight\"` (seed 001's "
                          "profile), or `segment` and `initial`.")
    nested: ClassVar[dict] = {"initial": FlightInitial, "segment": [FlightSegment]}
    builtin: OneOf("high_dynamics_flight") | None = F(None, "A built-in flight.", example="high_dynamics_flight")
    vibration: Raw = F(True, "Add the flight's vibration to the sensed motion (true/false, or a vibration "
                             "table for a segment flight).")
    segment: Raw = F(None, "The segments: [[trajectory.segment]] tables.")
    initial: Raw = F(None, "The start: [trajectory.initial].")
    name_: Text() | None = Field(None, alias="name", description="Label of the flight.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


class DualAlignment(Section):
    name: ClassVar[str] = "alignment (dual_imu)"
    doc: ClassVar[str] = "Initial alignment of the pair."
    duration: Quantity("time", positive=True) = F("10 s", "Alignment duration.")
    heading_sigma: Quantity("angle", nonnegative=True) = F("0.1 deg", "Heading 1σ after alignment.")
    lat: Quantity("angle") | None = F(None, "Start latitude (default: the trajectory's).")
    lon: Quantity("angle") | None = F(None, "Start longitude.")
    h: Quantity("length") | None = F(None, "Start height.")
    heading: Quantity("angle") | None = F(None, "Start heading.")


class Comparison(Section):
    name: ClassVar[str] = "comparison"
    doc: ClassVar[str] = "The navigation difference between the two IMUs."
    interval: Quantity("time", positive=True) = F("1 s", "Comparison interval (whole main samples).")
    model_step: Quantity("time", positive=True) = F("0.04 s", "Model step (an even number of main samples "
                                                              "dividing the interval).")
    components: Names(known=["position", "velocity", "attitude"], what="component") = F(
        ["velocity", "attitude"], "Compared components.")
    noise: Table("table position/velocity/attitude = 1σ") = F({}, "Comparison noise 1σ per component (default "
                                                                  "1 mm, 0.1 mm/s, 2 urad).")


class Monitor(Section):
    name: ClassVar[str] = "monitor"
    doc: ClassVar[str] = "The g-sensitivity fault monitor."
    window: Quantity("time", positive=True) = F("10 s", "Test window (whole comparison intervals).")
    false_alarm: Number(lo=0.0, hi=1.0, lo_open=True, hi_open=True, why="a probability") = F(
        0.01, "False-alarm probability per window.")
    candidates: Raw = F("all", "'all' or a list of gyro/accel axis pairs such as ['z/x'].")


class Gaps(Section):
    name: ClassVar[str] = "gaps"
    doc: ClassVar[str] = "Bridging data gaps."
    policy: OneOf("interpolate", "hold", "skip") = F("interpolate", "How a gap is bridged.")
    window: Integer(limit="gap_window") = F(10, "Samples averaged by a bridge.")
    trials: Integer(limit="gap_trials") = F(8, "Trial bridges per side for the error prediction.")


class Fault(Section):
    name: ClassVar[str] = "simulation.fault"
    doc: ClassVar[str] = "The injected g-sensitivity fault."
    gyro: Raw = F(..., "Gyro axis ('x', 'y', 'z').", example="z")
    accel: Raw = F(..., "Accelerometer axis.", example="x")
    coefficient: Raw = F(..., "g-sensitivity ('10 deg/h/g').", example="10 deg/h/g")


class GapEntry(Section):
    name: ClassVar[str] = "[simulation.gap]]"
    doc: ClassVar[str] = "A data gap in one IMU."
    imu: OneOf("main", "kimu") = F(..., "The IMU.", example="main")
    start: Quantity("time", nonnegative=True) = F(..., "Start.", example="60 s")
    duration: Quantity("time", positive=True) = F(..., "Duration.", example="1 s")


class Simulation(Section):
    name: ClassVar[str] = "simulation"
    doc: ClassVar[str] = "Simulated flights."
    nested: ClassVar[dict] = {"fault": Fault, "gap": [GapEntry]}
    runs: Integer(limit="dual_runs") = F(100, "Fault-free flights.")
    fault_runs: Integer(limit="dual_runs") = F(20, "Flights with the injected fault (needs "
                                                   "[simulation.fault]).")
    batch: Integer(limit="dual_batch") = F(50, "Flights per batch.")
    seed: Integer(limit="seed") = F(1, "Seed of the random streams.")
    fault: Raw = F(None, "[simulation.fault].")
    gap: Raw = F([], "[[simulation.gap]] tables.")


# the accelerometer-board study (seed 000)

class Board(Section):
    name: ClassVar[str] = "board"
    doc: ClassVar[str] = "The A/D-reset accelerometer board (seed 000)."
    sample_rate: Quantity("frequency", positive=True) = F(..., "Board sample rate.", example="2400 Hz")
    n_t: Number(lo=0.0, lo_open=True) = F(..., "Nominal counts N_t.", example=1066.5)
    error_ratios: Raw = F(..., "Reset scale-error ratios, each non-zero within (-0.5, 0.5).", example=[0.02, 0.05, 0.10])
    n_e_stated: Number() | None = F(None, "Stated error counts (default error_ratios[0]·n_t).")
    v_bound: Number(lo=0.0, lo_open=True) | None = F(None, "Counter bound, > n_t/2 (default n_t).")
    reset_period_reference: Quantity("acceleration", positive=True) | None = F(
        None, "Input at which N_a = 2π/ω_n (give this or scale_factor).", example="0.9 m/s^2")
    scale_factor: Quantity("velocity", positive=True) | None = F(None, "Velocity per reset pulse.")
    period_rounding: OneOf("floor", "round", "ceil") = F("floor", "How the reset period rounds to samples.")


class OutputFilter(Section):
    name: ClassVar[str] = "output_filter"
    doc: ClassVar[str] = "The board's second-order output filter."
    cutoff: Quantity("frequency", positive=True) = F(..., "Cut-off (below half the sample rate).",
                                                     example="20 Hz")
    damping: Number(lo=0.0, lo_open=True) = F(1 / math.sqrt(2), "Damping ratio.")


class BoardNavigation(Section):
    name: ClassVar[str] = "navigation"
    doc: ClassVar[str] = "The navigation computer's input."
    rate: Quantity("frequency", positive=True) = F(..., "Navigation rate (divides the board rate).",
                                                   example="100 Hz")
    decimation: OneOf("moving_average") = F("moving_average", "Decimation filter.")


class Gains(Section):
    name: ClassVar[str] = "alignment.coarse / alignment.fine"
    doc: ClassVar[str] = "Alignment loop gains."
    k: Number(lo=0.0, lo_open=True) = F(..., "Loop gain.", example=1.0)
    kb_g: Number(lo=0.0, lo_open=True) = F(..., "Bias gain per g.", example=0.25)


class Prefilter(Section):
    name: ClassVar[str] = "alignment.prefilter"
    doc: ClassVar[str] = "Alignment prefilter."
    cutoff: Quantity("frequency", positive=True) = F(..., "Cut-off (below half the navigation rate).",
                                                     example="0.1 Hz")
    order: OneOf(1, 2) = F(1, "Filter order.")


class BoardAlignment(Section):
    name: ClassVar[str] = "alignment (ad_reset)"
    doc: ClassVar[str] = "Leveling alignment of the board."
    nested: ClassVar[dict] = {"coarse": Gains, "fine": Gains, "prefilter": Prefilter}
    gravity: Quantity("acceleration", positive=True) = F("1 g", "Gravity magnitude.")
    coarse: Raw = F(..., "[alignment.coarse].")
    fine: Raw = F(..., "[alignment.fine].")
    prefilter: Raw = F(..., "[alignment.prefilter].")


class Sweeps(Section):
    name: ClassVar[str] = "sweeps"
    doc: ClassVar[str] = "Ranges of the board figures."
    fig2: Raw = F(..., "[low, high] input accelerations of Fig 2 (N_a > 2π/ω_n).",
                  example=["0.05 m/s^2", "0.9 m/s^2"])
    fig3: Raw = F(..., "[low, high] pulse periods N_a in samples (low >= 2).", example=[2, 400])
    fig4: Raw = F(..., "[low, high] accelerations of Fig 4 (N_a < 2π/ω_n).", example=["0.9 m/s^2", "20 m/s^2"])
    fig5: Raw = F(..., "[low, high] accelerations of Fig 5.", example=["0.5 mg", "5 mg"])
    points: Integer(lo=5, hi=2000) = F(60, "Points per curve.")


class ReferenceTable(Section):
    name: ClassVar[str] = "reference.<fig2 | table1 | table2 | table3>"
    doc: ClassVar[str] = "The paper's printed values, compared with the computed ones."
    accelerations: Raw = F(None, "Input accelerations (tables).")
    amplitude: Raw = F(..., "Printed values, one per error ratio (rows per acceleration for tables).")
    unit: Text(nonempty=True) = F(..., "Unit of the printed values.")
    note: Text() = F("", "Where the values are printed.")


class Reference(Section):
    name: ClassVar[str] = "reference"
    doc: ClassVar[str] = "Optional printed values of seed 000."
    nested: ClassVar[dict] = {"fig2": ReferenceTable, "table1": ReferenceTable, "table2": ReferenceTable,
                              "table3": ReferenceTable}
    fig2: Raw = F(None, "[reference.fig2].")
    table1: Raw = F(None, "[reference.table1].")
    table2: Raw = F(None, "[reference.table2].")
    table3: Raw = F(None, "[reference.table3].")


# the aided-navigation study (issue 15, covtool.studies.aided)

def _three(dimension: str):
    """Three quantities (body x, y, z), as the aided parser requires of a lever arm."""
    def check(v):
        if not isinstance(v, list) or len(v) != 3:
            raise _Problem("", f"expected three lengths (body x, y, z), got {v!r}")
        return tuple(fields.quantity_list(v, dimension, "", _Problem))
    return Annotated[tuple[float, ...], BeforeValidator(_wrap(check)),
                     Kind(f"three quantities ({dimension}): body x, y, z", dimension)]


class FilterVariant(Section):
    name: ClassVar[str] = "[filters.variant]]"
    doc: ClassVar[str] = ("A filter that drops measurement-error states from a base filter; the dropped states' "
                          "variance widens the filter's R (covtool.lincov.aided.build_epochs).")
    name_: Text(nonempty=True) = Field(..., alias="name", description="Label of the variant (a new filter name).",
                                       json_schema_extra={"example": "B1 no GNSS errors"})
    base: Text(nonempty=True) = F(..., "The filter it starts from (a case of the filter files).", example="B1")
    drop: Names(what="measurement-error state") = F(..., "Measurement-error states removed "
                                                         "(`<measurement>_<error>`).", example=["gnss_N"])

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


class AidedFiltersSection(FiltersSection):
    name: ClassVar[str] = "filters (aided)"
    doc: ClassVar[str] = ("The filters run against the truth and the measurements (see 'Filter files' below); "
                          "each keeps every measurement-error state unless a variant drops it.")
    nested: ClassVar[dict] = {"variant": [FilterVariant]}
    ewn_interval: Quantity("time", positive=True) | None = F(None, "Δt_s of seed 002 eq (11)-(13) for the INS "
                                                                   "states a filter drops (default: the duration "
                                                                   "over the number of update epochs).")
    variant: Annotated[tuple[FilterVariant, ...], Kind("list of [[filters.variant]] tables")] = F(
        (), "Filters dropping measurement-error states: [[filters.variant]] tables.")


class MeasurementError(Section):
    name: ClassVar[str] = "measurement.errors.<error>"
    doc: ClassVar[str] = ("One own error state of a measurement, named `<measurement>_<error>`; the errors each "
                          "kind has are in docs/aiding.md (e.g. odometer: scale_factor, boresight_pitch, "
                          "boresight_yaw; gnss_position: N, E, D).")
    sigma: Raw = F(..., "Initial 1σ (steady-state 1σ of a markov state), in the error's unit (checked by the "
                        "runner against the kind); >= 0.", example="1000 ppm")
    process: OneOf("constant", "markov") = F("constant", "The error's process.")
    tau: Quantity("time", positive=True) | None = F(None, "Correlation time; markov only, and required there.")

    @model_validator(mode="after")
    def _tau(self):
        if self.process == "markov" and self.tau is None:
            raise PydanticCustomError("covtool", "{problem}", {"problem": "a markov error needs 'tau'"})
        if self.process != "markov" and self.tau is not None:
            raise PydanticCustomError("covtool", "{problem}", {"problem": "only a markov state has a correlation "
                                                                          "time (tau)"})
        return self


class MeasurementSchedule(Section):
    name: ClassVar[str] = "measurement.schedule"
    doc: ClassVar[str] = ("When a measurement updates (an inline table): every `period` (or at `rate`) from "
                          "`start` to `end` when the vehicle is moving, stationary or always, except in the "
                          "`outages`; `at` adds single times.")
    period: Quantity("time", positive=True) | None = F(None, "Time between updates (default 1 s); not with "
                                                             "`rate`.")
    rate: Quantity("frequency", positive=True) | None = F(None, "Updates per second; not with `period`.")
    start: Quantity("time") = F("0 s", "First possible update.")
    end: Quantity("time") | None = F(None, "Last possible update (default: the end of the study).")
    when: OneOf(*WHEN) = F("always", "Vehicle state required for an update (stationary: at the stops).")
    outages: Raw = F([], "List of [start, end] times without updates.")
    at: QuantityList("time") | None = F(None, "Extra update times.")

    @model_validator(mode="after")
    def _one_spacing(self):
        if self.period is not None and self.rate is not None:
            raise PydanticCustomError("covtool", "{problem}", {"problem": "give period or rate, not both"})
        return self


#: a measurement's name: it prefixes its error states' names (``odo_scale_factor``)
MEASUREMENT_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


def _measurement_name(v):
    name = fields.string(v, "", _Problem, nonempty=True)
    if not MEASUREMENT_NAME.match(name):
        raise _Problem("", f"{name!r} must start with a letter and hold only letters, digits and _")
    return name


class MeasurementEntry(Section):
    name: ClassVar[str] = "[measurement]]"
    doc: ClassVar[str] = ("One aiding measurement (covtool.lincov.measurements, docs/aiding.md): its kind, "
                          "white noise, lever arm, own error states and schedule.")
    nested: ClassVar[dict] = {"errors": MeasurementError, "schedule": MeasurementSchedule}
    name_: Annotated[str, BeforeValidator(_wrap(_measurement_name)), Kind("string (a letter, then letters, "
                                                                          "digits and `_`)")] = Field(
        ..., alias="name", description="Label, and prefix of its error states (`<name>_<error>`).",
        json_schema_extra={"example": "gnss"})
    kind: OneOf(*MEASUREMENT_KINDS) = F(..., "The measurement kind.", example="gnss_position")
    sigma: Raw = F(..., "True white-noise 1σ (R): one value, or one per component, in the kind's unit; > 0.",
                   example="1 m")
    filter_sigma: Raw = F(None, "The 1σ the filters assume (default: sigma); as sigma.")
    lever_arm: _three("length") | None = F(None, "Body-frame arm from the IMU to the sensing point (kinds with a "
                                                 "lever arm only; default zero).")
    errors: Annotated[dict[str, MeasurementError], Kind("table of [measurement.errors.<error>] tables")] = F(
        {}, "Own error states: [measurement.errors.<error>] tables.")
    schedule: Annotated[MeasurementSchedule, Kind("inline table, see [measurement.schedule]")] = F(
        {}, "When it updates, see [measurement.schedule] (default: every 1 s).")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


class AidedGrade(Section):
    name: ClassVar[str] = "[grade]] (aided)"
    doc: ClassVar[str] = ("An IMU grade: every sensor σ, random walk, ARW and VRW of the truth × scale; the filters "
                          "follow the grade. Default: one grade, the truth as declared.")
    name_: Text(nonempty=True) = Field(..., alias="name", description="Label of the grade (unique).",
                                       json_schema_extra={"example": "navigation"})
    scale: Number(lo=1e-3, hi=1e3, why="a grade scales every sensor error") = F(..., "Factor on every sensor "
                                                                                      "error.", example=1.0)
    description: Text() = F("", "One line for the tables.")

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


# ---------------------------------------------------------------------------
# one configuration per study kind
# ---------------------------------------------------------------------------

class StudyConfig(Section):
    """A whole study file: one attribute per section."""

    kind_doc: ClassVar[str] = ""
    #: top-level lists of tables (``[[key]]``): key -> Section class of one entry
    lists: ClassVar[dict] = {}


def _S(cls, default=None, doc=""):
    return Field(default_factory=dict if default is None else None, description=doc or cls.doc,
                 json_schema_extra={"section": cls.__name__})


class PureInsConfig(StudyConfig):
    kind_doc: ClassVar[str] = "The unaided INS on a trajectory: the truth model propagated without aiding."
    study: StudySection
    trajectory: Trajectory = F({"builtin": "land_vehicle"}, "The trajectory (default: the land-vehicle route).")
    truth: TruthSection = F({}, TruthSection.doc)
    output: OutputSection = F({}, OutputSection.doc)


class ZuptStudyConfig(StudyConfig):
    """The sections of every ZUPT study kind."""

    study: StudySection
    trajectory: Trajectory = F({"builtin": "land_vehicle"}, "The trajectory (default: the land-vehicle route).")
    truth: TruthSection = F({}, TruthSection.doc)
    filters: FiltersSection = F({}, FiltersSection.doc)
    zupt: ZuptSection = F({}, ZuptSection.doc)
    output: OutputSection = F({}, OutputSection.doc)


class ZuptFilterOrderConfig(ZuptStudyConfig):
    kind_doc: ClassVar[str] = ("Reduced-order filters run against the truth (seed 002 §3.1, Table 3, Figs 6-7): "
                               "the truth propagated under each filter's gains, eq (15)-(16).")
    impact: ImpactSection = F({}, ImpactSection.doc)


class ErrorBudgetConfig(ZuptStudyConfig):
    kind_doc: ClassVar[str] = ("Error budget: each error source's share of the navigation errors, pure INS and "
                               "filters ([filters] cases may list \"pure_ins\").")
    budget: BudgetSection = F({}, BudgetSection.doc)


class ZuptSensitivityConfig(ZuptStudyConfig):
    kind_doc: ClassVar[str] = "Filter tuning sensitivity (seed 002 §3.2, Fig 8) and cost (Table 4)."
    sweep: SensitivitySweep = F({}, SensitivitySweep.doc)
    cost: CostSection = F({}, CostSection.doc)


class MonteCarloConfig(ZuptStudyConfig):
    kind_doc: ClassVar[str] = ("Monte Carlo validation: sampled errors through a nonlinear strapdown and the "
                               "filters, compared with the linear covariance (RMS and NEES bands).")
    monte_carlo: MonteCarloSection


class MagnitudeSweepConfig(ZuptStudyConfig):
    kind_doc: ClassVar[str] = "Sweep the magnitude of groups of error sources (e.g. misalignments)."
    sweep: MagnitudeSweep


class TradeGridConfig(ZuptStudyConfig):
    kind_doc: ClassVar[str] = ("Trade grid: IMU grade × ZUPT interval × filter × tuning, run in chunks "
                               "(resumable store).")
    grid: GridSection
    lists: ClassVar[dict] = {"grade": GradeEntry}
    grade: Raw = F([{"name": "navigation", "scale": 1}], "The IMU grades: [[grade]] tables.")


class AidedConfig(StudyConfig):
    kind_doc: ClassVar[str] = ("Aided navigation (issue 15): reduced filters against the truth with declared "
                               "measurements (ZUPT, CUPT, odometer, NHC, GNSS, baro, heading) on schedules with "
                               "outages, filter variants dropping measurement-error states, IMU grades.")
    lists: ClassVar[dict] = {"measurement": MeasurementEntry, "grade": AidedGrade}
    study: StudySection
    trajectory: Trajectory = F({"builtin": "land_vehicle"}, "The trajectory (default: the land-vehicle route).")
    truth: TruthSection = F({}, TruthSection.doc)
    filters: AidedFiltersSection = F({}, AidedFiltersSection.doc)
    measurement: tuple[MeasurementEntry, ...] = Field(..., min_length=1, description=(
        "The measurements, at least one: [[measurement]] tables with unique names."))
    grade: tuple[AidedGrade, ...] | None = Field(None, min_length=1, description=(
        "IMU grades: [[grade]] tables (default: one grade, the truth as declared)."))
    output: OutputSection = F({}, OutputSection.doc)

    @model_validator(mode="after")
    def _unique(self):
        for what, items in (("measurement", self.measurement), ("grade", self.grade or ())):
            seen = [x.name_ for x in items]
            j = next((j for j, n in enumerate(seen) if n in seen[:j]), None)
            if j is not None:               # named as the runner does: the second entry's name
                raise PydanticCustomError("covtool", "{problem}", {
                    "problem": f"{seen[j]!r} is used twice", "suffix": f": [[{what}]] #{j + 1} name"})
        return self


class DualImuConfig(StudyConfig):
    kind_doc: ClassVar[str] = "Dual-IMU comparison and g-sensitivity fault monitor (seed 001)."
    study: StudySectionShort
    trajectory: FlightTrajectory = F({"builtin": "high_dynamics_flight"}, FlightTrajectory.doc)
    imu: ImuSection = F({}, ImuSection.doc)
    alignment: DualAlignment = F({}, DualAlignment.doc)
    comparison: Comparison = F({}, Comparison.doc)
    monitor: Monitor = F({}, Monitor.doc)
    gaps: Gaps = F({}, Gaps.doc)
    simulation: Simulation = F({}, Simulation.doc)


class AdResetConfig(StudyConfig):
    kind_doc: ClassVar[str] = "The A/D-reset accelerometer board (seed 000): scale error, alignment."
    study: AdResetStudySection
    board: Board
    output_filter: OutputFilter
    navigation: BoardNavigation
    alignment: BoardAlignment
    sweeps: Sweeps
    reference: Reference = F({}, Reference.doc)


#: study kind -> its configuration class
KINDS: dict[str, type[StudyConfig]] = {
    "pure_ins": PureInsConfig, "zupt_filter_order": ZuptFilterOrderConfig, "error_budget": ErrorBudgetConfig,
    "zupt_sensitivity": ZuptSensitivityConfig, "monte_carlo": MonteCarloConfig,
    "magnitude_sweep": MagnitudeSweepConfig, "trade_grid": TradeGridConfig, "dual_imu": DualImuConfig,
    "ad_reset": AdResetConfig, "aided": AidedConfig,
}

#: every Section class, for the reference
SECTIONS = tuple(c for c in list(globals().values())
                 if isinstance(c, type) and issubclass(c, Section) and c not in (Section, StudyConfig)
                 and not issubclass(c, StudyConfig))


def config_class(kind: str) -> type[StudyConfig]:
    """The configuration class of a study kind (StudyFileError if unknown)."""
    if kind not in KINDS:
        raise StudyFileError("[study] kind", f"unknown kind {kind!r} (one of: {', '.join(sorted(KINDS))})")
    return KINDS[kind]


# ---------------------------------------------------------------------------
# parse, dump
# ---------------------------------------------------------------------------

def _keys(cls) -> list[str]:
    return [f.alias or n for n, f in cls.model_fields.items()]


def _where(where: str, loc) -> str:
    parts = [x for x in loc if not (isinstance(x, str) and x.startswith("function-"))]
    if not parts or isinstance(parts[0], int):
        return where
    if len(parts) > 1 and isinstance(parts[1], int):      # an entry of a list of tables: [[measurement]] #2
        head, parts = f"[[{parts[0]}]] #{parts[1] + 1}", parts[2:]
    else:
        head, parts = f"[{parts[0]}]", parts[1:]
    rest = ".".join(str(x) for x in parts if not isinstance(x, int))
    return f"{where}: {head}" + (f" {rest}" if rest else "") + "".join(f" #{x + 1}" for x in parts
                                                                        if isinstance(x, int))


def parse_section(cls: type[Section], value, where: str, section: str, error=StudyFileError):
    """One table parsed into ``cls``; a refusal is one ``error`` naming the file, table and key.

    Unknown keys are refused first, with the allowed keys (as
    :func:`covtool.io.config.check_keys` does).
    """
    w = f"{where}: [{section}]"
    fields.table(value, w, error)
    fields.check_keys(value, _keys(cls), w, error)
    try:
        return cls.model_validate(value)
    except ValidationError as exc:
        _raise(exc, where, (section,), error)


def _raise(exc: ValidationError, where: str, prefix: tuple, error):
    e = exc.errors(include_url=False)[0]
    loc = prefix + tuple(e["loc"])
    if e["type"] == "missing":
        raise error(_where(where, loc[:-1]), f"missing required key {loc[-1]!r}") from None
    if e["type"] == "extra_forbidden":
        raise error(_where(where, loc[:-1]), f"unknown key {loc[-1]!r}") from None
    if e["type"] == "covtool":
        raise error(_where(where, loc) + e["ctx"].get("suffix", ""), e["ctx"]["problem"]) from None
    raise error(_where(where, loc), e["msg"]) from None


def load_config(decl: dict, where: str = "<study>") -> StudyConfig:
    """A study declaration parsed into its kind's typed, frozen configuration.

    Parameters
    ----------
    decl : dict
        The study file's TOML tables.
    where : str
        The study file, for messages.

    Returns
    -------
    StudyConfig
        E.g. :class:`ZuptFilterOrderConfig`; sections are attributes.

    Raises
    ------
    StudyFileError
        Naming the file, the table, the key and the problem.
    """
    st = decl.get("study")
    if not isinstance(st, dict) or "kind" not in st:
        raise StudyFileError(where, "missing [study] table with a 'kind' key "
                             f"(one of: {', '.join(sorted(KINDS))})")
    if st["kind"] not in KINDS:
        raise StudyFileError(f"{where}: [study]", f"unknown kind {st['kind']!r} (one of: {', '.join(sorted(KINDS))})")
    cls = KINDS[st["kind"]]
    fields.check_keys(decl, _keys(cls), where, StudyFileError)
    for key, f in cls.model_fields.items():
        ann = f.annotation
        if isinstance(ann, type) and issubclass(ann, Section) and key in decl:
            fields.table(decl[key], f"{where}: [{key}]", StudyFileError)
            fields.check_keys(decl[key], _keys(ann), f"{where}: [{key}]", StudyFileError)
    try:
        return cls.model_validate(decl)
    except ValidationError as exc:
        _raise(exc, where, (), StudyFileError)


def si_text(value: float, dimension: str):
    """An SI value as a quantity string that parses back exactly (a bare number when dimensionless)."""
    unit = "Hz" if dimension == "frequency" else DIMENSIONS[dimension][0]   # '1/s' is not a unit string
    if value == 0 or not unit:
        return float(value)
    return f"{float(value)!r} {unit}"


def _dump(model: BaseModel) -> dict:
    out = {}
    for name, f in type(model).model_fields.items():
        v = getattr(model, name)
        if v is None:
            continue
        key = f.alias or name
        kind = next((m for m in f.metadata if isinstance(m, Kind)), None)
        if kind is None:
            for arg in getattr(f.annotation, "__args__", ()):
                kind = next((m for m in getattr(arg, "__metadata__", ()) if isinstance(m, Kind)), kind)
        if isinstance(v, BaseModel):
            out[key] = _dump(v)
        elif isinstance(v, tuple) and v and all(isinstance(x, BaseModel) for x in v):
            out[key] = [_dump(x) for x in v]
        elif isinstance(v, dict) and v and all(isinstance(x, BaseModel) for x in v.values()):
            out[key] = {k: _dump(x) for k, x in v.items()}
        elif kind is not None and kind.dimension and kind.dimension != "memory":
            out[key] = [si_text(x, kind.dimension) for x in v] if isinstance(v, tuple) else \
                si_text(v, kind.dimension)
        elif kind is not None and kind.dimension == "memory":
            out[key] = f"{v!r} B"
        elif isinstance(v, tuple):
            out[key] = list(v)
        else:
            out[key] = v
    return out


def dump_config(config: StudyConfig) -> dict:
    """The TOML tables of a configuration: every field, defaults filled in, quantities as exact SI strings."""
    return _dump(config)
