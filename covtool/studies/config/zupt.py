"""Sections of the ZUPT study kinds.

``[impact]`` (zupt_filter_order), ``[budget]`` (error_budget, Fig 4),
``[sweep]`` and ``[cost]`` (zupt_sensitivity: seed 002 §3.2, Fig 8 and
Table 4, Taylor terms of eq (6b)), ``[monte_carlo]``, ``[sweep]`` of
magnitude_sweep, and ``[grid]`` with the ``[[grade]]`` entries of
trade_grid.
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

from pydantic import BeforeValidator, ConfigDict, Field

from covtool.io import config as fields
from covtool.io.config import LIMITS
from covtool.studies.config.sections import FiltersSection
from covtool.studies.config.field_types import (
    _Problem, _wrap, Kind, NumberList,
    Bool, F, Integer, Names, Number, OneOf, Quantity, QuantityList, Raw, Section, Table, Text,
)


def _impact_filters(v):
    if not isinstance(v, list):
        raise _Problem("", "expected a list of filter names")
    return tuple(fields.names(v, "", _Problem, nonempty=False, what="filter"))


_ImpactFilters = Annotated[tuple[str, ...], BeforeValidator(_wrap(_impact_filters)), Kind("list of filters")]


def _budget_cases(v):
    if v == []:            # the pure INS alone: what the runner passes on (it refuses [] in a file itself)
        return ()
    return tuple(fields.names(v, "", _Problem, what='case (a filter or "pure_ins")'))


_BudgetCases = Annotated[tuple[str, ...], BeforeValidator(_wrap(_budget_cases)),
                         Kind('list of cases (filters or "pure_ins")')]


class ImpactSection(Section):
    name: ClassVar[str] = "impact"
    doc: ClassVar[str] = "The dropped-state impact table (covtool.lincov.impact)."
    filters: _ImpactFilters | None = F(None, "Reduced filters to analyse (default: every reduced filter of the "
                                             "run; [] for none).")


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
    null_replicas: Integer(lo=0, hi=100000) = F(100, "Replicas of the linear Monte Carlo giving the null "
                                                   "distribution of the acceptance test (0: bands only; else >= 10).")


class SweepGroup(Section):
    name: ClassVar[str] = "[sweep.group]]"
    doc: ClassVar[str] = "States swept together (one magnitude for all)."
    name_: Text(nonempty=True) = Field(..., alias="name", description="Label of the group.",
                                       json_schema_extra={"example": "gyro misalignment"})
    states: Names(what="state or block name") = F(..., "States or blocks of one dimension, each with σ > 0.",
                                                   example=["gyro_mis"])

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)


def _threshold(v):
    x = fields.number(v, "", _Problem)
    if not x > 1.0:
        raise _Problem("", f"{v!r} is not a number greater than 1")
    return x


_Threshold = Annotated[float, BeforeValidator(_wrap(_threshold)), Kind("number", None, "> 1")]


class MagnitudeSweep(Section):
    name: ClassVar[str] = "sweep (magnitude_sweep)"
    doc: ClassVar[str] = "Set each group's 1σ to every value and find where the navigation errors grow."
    nested: ClassVar[dict] = {"group": [SweepGroup]}
    values: Raw = F(..., "The magnitudes (in the groups' unit), >= 0.", example=["5 arcsec", "30 arcsec"])
    threshold: _Threshold = F(1.5, "Error growth over the nominal that marks a magnitude as significant.")
    group: Raw = F(..., "The groups: [[sweep.group]] tables.")


#: a grid axis of filter-tuning scales: each once, within six decades of the nominal filter
_SCALES = NumberList(limit="grid_axis", bound="filter_scale", unique=True)


class GridSection(Section):
    name: ClassVar[str] = "grid"
    doc: ClassVar[str] = "The trade grid's axes: cases are their product with the grades and filters."
    zupt_interval: QuantityList("time", limit="grid_axis", positive=True, unique=True) = F(
        ..., "ZUPT intervals (one truth system each).", example=["3 min", "5 min"])
    zupt_sigma: QuantityList("velocity", limit="grid_axis", positive=True, unique=True) | None = F(
        None, "True ZUPT σ, assumed alike by the filter (default: [zupt] sigma).")
    p0_scale: _SCALES = F([1.0], "Scales of the filters' P0.")
    q_scale: _SCALES = F([1.0], "Scales of the filters' Q_f.")
    r_scale: _SCALES = F([1.0], "Scales of the filters' R_f.")
    cruise_speed: Quantity("velocity", positive=True) = F("45 km/h", "land_vehicle: cruise speed for every "
                                                                     "interval.")
    aiding: Names(what="aiding mix name") | None = F(None, "Aiding mixes (issue 15): \"none\" (the ZUPTs alone) or "
                                                      "[[aiding]] names; one truth system per mix.")


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


def _no_pure_ins(v):
    raise _Problem("", 'an error budget lists the pure INS as a case: cases = ["pure_ins", ...]')


_NoPureIns = Annotated[Any, BeforeValidator(_wrap(_no_pure_ins)), Kind("(refused)")]


class BudgetFilters(FiltersSection):
    name: ClassVar[str] = "filters (error_budget)"
    doc: ClassVar[str] = ("The cases of the budget: filters and \"pure_ins\" (the unaided INS), listed in "
                          "`cases`; `pure_ins = ...` is refused here.")
    cases: _BudgetCases | None = F(None, "Cases, each once: filter names and \"pure_ins\" (default: every "
                                         "filter and the pure INS).")
    pure_ins: _NoPureIns | None = F(None, "Refused: an error budget lists the pure INS as a case.")


def grade_entries(value) -> tuple:
    """``[[grade]]`` tables parsed into :class:`GradeEntry` (the trade grid's IMU grades).

    Raises
    ------
    pydantic_core.PydanticCustomError
        Its ``suffix`` names the entry (``": [[grade]] #3 name"``): not an
        array of tables, more than :data:`LIMITS` ``["grid_axis"]`` grades, an
        entry without a valid ``name``, a name used twice, an unknown key, an
        ``override`` that is not a table of state tables, a bad ``scale`` or
        ``description``.
    """
    from pydantic_core import PydanticCustomError

    from covtool.errors import InputError
    from covtool.io import config as fields
    from covtool.io.names import check_name

    def refuse(problem, suffix):
        return PydanticCustomError("covtool", "{problem}", {"problem": problem, "suffix": suffix})

    if not isinstance(value, list) or not value:
        raise refuse("expected an array of tables ([[grade]] name = ..., scale = ...)", ": [[grade]]")
    lim = LIMITS["grid_axis"]
    if len(value) > lim.hi:
        raise refuse(f"{len(value)} grades; at most {lim.hi:g} ({lim.reason})", ": [[grade]]")
    out, seen = [], set()
    for i, g in enumerate(value):
        w = f": [[grade]] #{i + 1}"
        try:
            fields.table(g, "", InputError)
            fields.check_keys(g, [f.alias or n for n, f in GradeEntry.model_fields.items()], "", InputError)
            if "name" not in g:
                raise InputError("", "missing 'name' (a non-empty string)")
            name = check_name(g["name"], " name", InputError, what="grade name")
            if name in seen:
                raise InputError(" name", f"grade {name!r} is declared twice")
            seen.add(name)
            ov = g.get("override", {})
            if not isinstance(ov, dict) or not all(isinstance(v, dict) for v in ov.values()):
                raise InputError(" override", "expected a table of state tables, e.g. "
                                 "override = {gyro_bias_z = {sigma = \"1 deg/h\"}}")
            b = LIMITS["grade_scale"]
            fields.number(g.get("scale", 1.0), " scale", InputError, lo=b.lo, hi=b.hi, why=b.reason)
            fields.string(g.get("description", ""), " description", InputError)
        except InputError as exc:
            raise refuse(exc.problem, w + (exc.where or "")) from None
        out.append(GradeEntry.model_validate(g))
    return tuple(out)

