"""One configuration per study kind, and the registry.

The ZUPT kinds (zupt_filter_order: seed 002 §3.1, Table 3, eq (15)-(16);
error_budget; zupt_sensitivity: §3.2, Fig 8, Table 4; monte_carlo;
magnitude_sweep; trade_grid), pure_ins, aided (issue 15), dual_imu
(seed 001) and ad_reset (seed 000); :data:`KINDS` maps a kind to its
class, :data:`SECTIONS` lists every section class (for the reference).
"""

from __future__ import annotations

from typing import ClassVar

from pydantic import Field, model_validator
from pydantic_core import PydanticCustomError

from covtool.errors import StudyFileError
from covtool.studies.config.field_types import F, Raw, Section
from covtool.studies.config.sections import (
    AdResetStudySection, FiltersSection, OutputSection, StudySection, StudySectionShort, Trajectory, TruthSection,
    ZuptSection,
)
from covtool.studies.config.zupt import (
    BudgetFilters, BudgetSection, CostSection, GradeEntry, GridSection, ImpactSection, MagnitudeSweep,
    MonteCarloSection,
    SensitivitySweep,
)
from covtool.studies.config.dual_imu import (
    Comparison, DualAlignment, FlightTrajectory, Gaps, ImuSection, Monitor, Simulation,
)
from covtool.studies.config.ad_reset import Board, BoardAlignment, BoardNavigation, OutputFilter, Reference, Sweeps
from covtool.studies.config.aided import (AidedFiltersSection, AidedGrade, AidingMix, MeasurementEntry,
                                          MeasurementSweep)
from covtool.studies.config import ad_reset, aided, dual_imu, sections, zupt


class StudyConfig(Section):
    """A whole study file: one attribute per section."""

    kind_doc: ClassVar[str] = ""
    #: top-level lists of tables (``[[key]]``): key -> Section class of one entry
    lists: ClassVar[dict] = {}
    #: keys a dump leaves out (set by the runner, refused in the file): table -> keys
    dump_omit: ClassVar[dict] = {}

    @model_validator(mode="wrap")
    @classmethod
    def _report_times_within_study(cls, data, handler):
        self = handler(data)
        out, st = getattr(self, "output", None), getattr(self, "study", None)
        duration = getattr(st, "duration", None)
        if out is None or duration is None or out.report_times is None:
            return self
        raw = data.get("output") if isinstance(data, dict) else None
        shown = raw.get("report_times") if isinstance(raw, dict) else None
        for i, x in enumerate(out.report_times):
            if x > duration + 1e-9:
                v = shown[i] if isinstance(shown, list) and i < len(shown) else f"{x:g} s"
                raise PydanticCustomError("covtool", "{problem}", {
                    "problem": f"{v!r} is after the end of the study ({duration:g} s)",
                    "suffix": f": [output] report_times[{i}]"})
        return self


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
    filters: BudgetFilters = F({}, BudgetFilters.doc)
    budget: BudgetSection = F({}, BudgetSection.doc)
    lists: ClassVar[dict] = {"measurement": MeasurementEntry}
    measurement: tuple[MeasurementEntry, ...] | None = Field(None, min_length=1, description=(
        "Declared measurements instead of [zupt] (issue 15, as in the aided kind): [[measurement]] tables; their "
        "error states and white noise R become sources (covtool.studies.aided_budget)."))


class ZuptSensitivityConfig(ZuptStudyConfig):
    kind_doc: ClassVar[str] = "Filter tuning sensitivity (seed 002 §3.2, Fig 8) and cost (Table 4)."
    sweep: SensitivitySweep = F({}, SensitivitySweep.doc)
    cost: CostSection = F({}, CostSection.doc)


class MonteCarloConfig(ZuptStudyConfig):
    kind_doc: ClassVar[str] = ("Monte Carlo validation: sampled errors through a nonlinear strapdown and the "
                               "filters, compared with the linear covariance (RMS and NEES bands).")
    monte_carlo: MonteCarloSection
    lists: ClassVar[dict] = {"measurement": MeasurementEntry}
    measurement: tuple[MeasurementEntry, ...] | None = Field(None, min_length=1, description=(
        "Declared measurements instead of [zupt] (issue 15, as in the aided kind): [[measurement]] tables, applied "
        "by their nonlinear functions to the strapdown truth (covtool.studies.aided_monte_carlo)."))

    @model_validator(mode="wrap")
    @classmethod
    def _monte_carlo_given(cls, data, handler):
        if isinstance(data, dict) and "monte_carlo" not in data:
            raise PydanticCustomError("covtool", "{problem}", {
                "problem": "missing [monte_carlo] table (runs = ..., imu_rate = ..., ...)", "suffix": ""})
        return handler(data)


class MagnitudeSweepConfig(ZuptStudyConfig):
    kind_doc: ClassVar[str] = "Sweep the magnitude of groups of error sources (e.g. misalignments)."
    sweep: MagnitudeSweep

    @model_validator(mode="wrap")
    @classmethod
    def _sweep_given(cls, data, handler):
        if isinstance(data, dict) and "sweep" not in data:
            raise PydanticCustomError("covtool", "{problem}", {
                "problem": "missing [sweep] table (values = [...], [[sweep.group]] ...)", "suffix": ": [sweep]"})
        return handler(data)


class TradeGridConfig(ZuptStudyConfig):
    kind_doc: ClassVar[str] = ("Trade grid: IMU grade × ZUPT interval × filter × tuning, run in chunks "
                               "(resumable store).")
    grid: GridSection
    lists: ClassVar[dict] = {"grade": GradeEntry, "aiding": AidingMix}
    dump_omit: ClassVar[dict] = {"zupt": ("interval",), "trajectory": ("period", "cycles", "distance")}
    grade: Raw = F([{"name": "nominal", "scale": 1}], "The IMU grades: [[grade]] tables, each name once.")
    aiding: tuple[AidingMix, ...] | None = Field(None, min_length=1, description=(
        "Aiding mixes named in [grid] aiding: [[aiding]] tables (issue 15)."))

    @model_validator(mode="wrap")
    @classmethod
    def _trade_grid(cls, data, handler):
        if isinstance(data, dict):
            if "grid" not in data:
                raise PydanticCustomError("covtool", "{problem}", {
                    "problem": "missing [grid] table (zupt_interval = [...], ...)", "suffix": ""})
            zc, traj = data.get("zupt"), data.get("trajectory", {"builtin": "land_vehicle"})
            if isinstance(zc, dict) and "interval" in zc:
                raise PydanticCustomError("covtool", "{problem}", {
                    "problem": "the ZUPT interval is a grid axis: give it as [grid] zupt_interval = [...]",
                    "suffix": ": [zupt] interval"})
            if isinstance(traj, dict) and traj.get("builtin") == "land_vehicle":
                for key in ("period", "cycles", "distance"):
                    if key in traj:
                        raise PydanticCustomError("covtool", "{problem}", {
                            "problem": "is set per ZUPT interval by the trade grid (period = interval; distance "
                                       "from [grid] cruise_speed)", "suffix": f": [trajectory] {key}"})
            if not (isinstance(data.get("grade"), tuple) and all(isinstance(g, GradeEntry) for g in data["grade"])):
                data = {**data, "grade": zupt.grade_entries(data.get("grade", [{"name": "nominal", "scale": 1.0}]))}
        return handler(data)


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
    sweep: MeasurementSweep | None = F(None, MeasurementSweep.doc)

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
SECTIONS = tuple(c for m in (sections, zupt, dual_imu, ad_reset, aided) for c in vars(m).values()
                 if isinstance(c, type) and issubclass(c, Section) and c.__module__ == m.__name__)


def config_class(kind: str) -> type[StudyConfig]:
    """The configuration class of a study kind (StudyFileError if unknown)."""
    if kind not in KINDS:
        raise StudyFileError("[study] kind", f"unknown kind {kind!r} (one of: {', '.join(sorted(KINDS))})")
    return KINDS[kind]
