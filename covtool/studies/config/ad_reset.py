"""Sections of the A/D-reset accelerometer-board study (seed 000).

``[board]``, ``[output_filter]``, ``[navigation]`` with its gains and
prefilter, ``[alignment]``, ``[sweeps]`` and the ``[reference]`` tables
(seed 000's figures and Tables 1-3).
"""

from __future__ import annotations

import math

from typing import ClassVar

from covtool.studies.config.field_types import F, Integer, Number, OneOf, Quantity, Raw, Section, Text


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
