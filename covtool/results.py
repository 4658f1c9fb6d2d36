"""Result objects returned by every study runner.

Runners compute; they never open files.  A :class:`StudyResult` carries the
tables (pandas DataFrames, SI or explicitly-unit-labelled columns), figure
builders and the resolved configuration; :mod:`covtool.io.writers` turns it
into files.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import pandas as pd


@dataclass
class StudyResult:
    """Everything a study produced.

    Attributes
    ----------
    name : str
        Study name (used for file names).
    kind : str
        Study kind (``pure_ins``, ``zupt_filter_order``, ``ad_reset``, ...).
    tables : dict of str to DataFrame
        Output tables.  ``"summary"`` is always present and is written to
        ``summary.csv``; every table becomes a workbook sheet and a CSV file.
        Column headers carry their unit in brackets, e.g. ``"cep [ft]"``.
    figures : dict of str to callable
        ``name -> f()`` returning a :class:`matplotlib.figure.Figure`; each is
        saved as ``<name>.png``.  Built lazily so the numeric API never imports
        matplotlib.
    resolved : dict
        The fully resolved study declaration (defaults filled in), for provenance.
    provenance : dict
        Extra provenance rows (model hashes, tool version, timings).
    charts : list of dict
        Optional native Excel chart specifications for the workbook writer
        (see :func:`covtool.io.workbook.add_line_chart`).
    data : dict
        Raw numeric results (arrays) for the Python API; not written.
    """

    name: str
    kind: str
    tables: dict[str, pd.DataFrame]
    figures: dict[str, Callable[[], Any]] = field(default_factory=dict)
    resolved: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    charts: list = field(default_factory=list)
    data: dict = field(default_factory=dict)

    @property
    def summary(self) -> pd.DataFrame:
        """The summary table."""
        return self.tables["summary"]
