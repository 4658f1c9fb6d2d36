"""Sections of the aided-navigation study (issue 15, covtool.studies.aided).

Filter variants and ``[filters]`` (Δt_s of seed 002 eq (11)-(13) for the
dropped INS states), the measurement errors and schedules, the
``[[measurement]]`` entries (their names: ``MEASUREMENT_NAME``) and the
``[[grade]]`` entries.
"""

from __future__ import annotations

import re

from typing import Annotated, ClassVar

from pydantic import BeforeValidator, ConfigDict, Field, model_validator
from pydantic_core import PydanticCustomError

from covtool.io import config as fields
from covtool.lincov.measurements import KINDS as MEASUREMENT_KINDS, WHEN
from covtool.studies.config.field_types import (
    F, Kind, Names, Number, OneOf, Quantity, QuantityList, Raw, Section, Text, _Problem, _wrap,
)
from covtool.studies.config.sections import FiltersSection


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


class MeasurementSweep(Section):
    name: ClassVar[str] = "sweep (aided)"
    doc: ClassVar[str] = ("Scale one declared measurement's white-noise σ and rerun every [filters] case "
                          "(covtool.studies.aided_sweep.parse_sweep): the measurement_sweep table and figure.")
    measurement: Text(nonempty=True) = F(..., "The [[measurement]] whose σ is scaled.", example="gnss")
    what: OneOf("sigma", "filter_sigma") = F("sigma", "'sigma': the sensor's σ (truth R and filter R_f together); "
                                                      "'filter_sigma': only the σ the filters assume.")
    scales: Raw = F({"from": 0.1, "to": 10, "per_decade": 2}, "A [sweep.scales]-style table {from, to, "
                    "per_decade} (log grid through ×1) or a list of positive factors (×1 is added).")


class AidingMix(Section):
    name: ClassVar[str] = "[aiding]] (trade_grid)"
    doc: ClassVar[str] = ("An aiding mix of the trade grid (issue 15): measurements added to the ZUPTs of every "
                          "interval, named in [grid] aiding (\"none\": the ZUPTs alone).")
    nested: ClassVar[dict] = {"measurement": [MeasurementEntry]}
    name_: Text(nonempty=True) = Field(..., alias="name", description="Label of the mix (not \"none\").",
                                       json_schema_extra={"example": "odometer"})
    measurement: tuple[MeasurementEntry, ...] = Field(..., min_length=1, description=(
        "Its measurements: [[aiding.measurement]] tables, as [[measurement]] in the aided kind."))

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, populate_by_name=True)
