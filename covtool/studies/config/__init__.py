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

Layout
------
``field_types`` (field types and :class:`Section`), ``sections`` (the shared
sections and the trajectory), ``zupt``, ``dual_imu``, ``ad_reset`` and
``aided`` (the sections of those study kinds), ``kinds`` (one configuration
per kind, :data:`KINDS`, :data:`SECTIONS`), ``parse`` (load, parse, dump).
Every name is re-exported here.
"""

from covtool.studies.config.field_types import (  # noqa: F401
    Bool, F, Integer, Kind, Memory, Names, Number, OneOf, Quantity, QuantityList, Raw, Section, Table, Text,
    _memory, _Problem, _wrap,
)
from covtool.studies.config.sections import (  # noqa: F401
    AdResetStudySection, CsvTrajectory, FiltersSection, Initial, LandVehicle, OutputSection, OverrideEntry, Segment,
    Segments, Static, StudySection, StudySectionShort, TRAJECTORIES, Trajectory, TruthSection, ZuptSection,
    _trajectory,
)
from covtool.studies.config.zupt import (  # noqa: F401
    BudgetFilters, BudgetSection, CostSection, GradeEntry, GridSection, ImpactSection, MagnitudeSweep,
    MonteCarloSection, Scales, SensitivitySweep, SweepGroup,
)
from covtool.studies.config.dual_imu import (  # noqa: F401
    Comparison, DualAlignment, Fault, FlightInitial, FlightSegment, FlightTrajectory, GapEntry, Gaps, ImuSection,
    ImuUnit, Monitor, Simulation,
)
from covtool.studies.config.ad_reset import (  # noqa: F401
    Board, BoardAlignment, BoardNavigation, Gains, OutputFilter, Prefilter, Reference, ReferenceTable, Sweeps,
)
from covtool.studies.config.aided import (  # noqa: F401
    AidedFiltersSection, AidedGrade, FilterVariant, MEASUREMENT_NAME, MeasurementEntry, MeasurementError,
    MeasurementSchedule, _measurement_name, _three,
)
from covtool.studies.config.kinds import (  # noqa: F401
    AdResetConfig, AidedConfig, config_class, DualImuConfig, ErrorBudgetConfig, KINDS, MagnitudeSweepConfig,
    MonteCarloConfig, PureInsConfig, SECTIONS, StudyConfig, TradeGridConfig, ZuptFilterOrderConfig,
    ZuptSensitivityConfig, ZuptStudyConfig, _S,
)
from covtool.studies.config.parse import (  # noqa: F401
    dump_config, load_config, parse_section, parse_trajectory, _dump, _keys, _raise, _where,
)

__all__ = ["Section", "KINDS", "SECTIONS", "load_config", "dump_config", "config_class", "parse_section"]
