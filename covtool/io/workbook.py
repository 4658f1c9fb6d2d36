"""Deliverable workbooks built with openpyxl.

Every sheet has a frozen, bold header row whose labels carry units in
brackets, a sensible number format and auto-sized columns.  Native Excel line
charts can be added from chart specs so that the customer's copy redraws from
the sheet data.

Every string (header, label, provenance) is a text cell, never a formula,
and a NaN or infinity is the text ``NaN``/``inf``, never an empty cell: see
:mod:`covtool.io.cells` for the rules.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
from openpyxl import Workbook
from openpyxl.cell.cell import Cell
from openpyxl.chart import LineChart, Reference, ScatterChart, Series
from openpyxl.styles import Font
from openpyxl.utils import get_column_letter

from covtool.io.cells import is_formula_like, nonfinite_text, printable

_MAX_SHEET = 31


def sheet_title(name: str) -> str:
    """Excel-safe sheet title (≤ 31 characters, no ``[]:*?/\\``)."""
    bad = '[]:*?/\\'
    t = "".join("_" if c in bad else c for c in name)
    return t[:_MAX_SHEET]


def _number_format(series: pd.Series) -> str | None:
    if not pd.api.types.is_float_dtype(series):
        return None
    vals = np.abs(series.to_numpy(dtype=float))
    vals = vals[np.isfinite(vals) & (vals > 0)]
    if vals.size == 0:
        return "0.000"
    lo, hi = vals.min(), vals.max()
    if hi >= 1e6 or lo < 1e-3:
        return "0.000E+00"
    if hi >= 100:
        return "0.0"
    return "0.0000"


def write_dataframe(ws, df: pd.DataFrame, *, index: bool = False) -> None:
    """Write ``df`` to worksheet ``ws`` with header styling and formats.

    Strings become text cells (:func:`text_cell`), NaN/inf the text
    ``NaN``/``inf``/``-inf``, finite numbers numbers.
    """
    if index:
        df = df.reset_index()
    ws.append([text_cell(ws, str(c)) for c in df.columns])
    for cell in ws[1]:
        cell.font = Font(bold=True)
    for row in df.itertuples(index=False, name=None):
        ws.append([_cell(ws, v) for v in row])
    ws.freeze_panes = "A2"
    for j, col in enumerate(df.columns, start=1):
        fmt = _number_format(df.iloc[:, j - 1])
        letter = get_column_letter(j)
        if fmt:
            for (cell,) in ws.iter_rows(min_row=2, max_row=len(df) + 1, min_col=j, max_col=j):
                cell.number_format = fmt
        width = max(len(str(col)), *(len(_fmt_str(v)) for v in df.iloc[:200, j - 1])) if len(df) else len(str(col))
        ws.column_dimensions[letter].width = min(max(10, width + 2), 60)


def text_cell(ws, text: str) -> Cell:
    """A text cell holding ``text`` exactly, never a formula.

    ``data_type`` is set to ``'s'`` after the value (openpyxl would infer a
    formula from a leading ``=``); formula-like text also gets Excel's
    quote prefix so that editing the cell keeps it text.  XML-illegal
    control characters become ``\\xNN`` escapes.
    """
    text = printable(text)
    c = Cell(ws, value=text)
    c.data_type = "s"
    if is_formula_like(text):
        c.quotePrefix = True
    return c


def _cell(ws, v):
    if v is None or v is pd.NA or v is pd.NaT:
        return None
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (np.floating, float)):
        v = float(v)
        return v if math.isfinite(v) else text_cell(ws, nonfinite_text(v))
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, int):
        return v
    if isinstance(v, str):
        return text_cell(ws, v)
    if isinstance(v, (pd.Timestamp, np.datetime64)):
        return pd.Timestamp(v).to_pydatetime()
    return text_cell(ws, str(v))


def _fmt_str(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def add_line_chart(wb, spec: dict) -> None:
    """Add a native scatter-with-lines chart.

    Parameters
    ----------
    wb : openpyxl.Workbook
    spec : dict
        ``{"sheet": data sheet, "x": x column header, "y": [y column headers],
        "title": str, "x_title": str, "y_title": str, "anchor": "H2",
        "target": sheet to place the chart on (default: data sheet),
        "log_x": bool}``
    """
    ws = wb[sheet_title(spec["sheet"])]
    headers = [c.value for c in ws[1]]
    n = ws.max_row
    chart = ScatterChart()
    chart.title = spec.get("title")
    chart.style = 13
    chart.x_axis.title = spec.get("x_title", spec["x"])
    chart.y_axis.title = spec.get("y_title")
    chart.height, chart.width = 9, 18
    if spec.get("log_x"):
        chart.x_axis.scaling.logBase = 10
    xcol = headers.index(spec["x"]) + 1
    xref = Reference(ws, min_col=xcol, min_row=2, max_row=n)
    for y in spec["y"]:
        ycol = headers.index(y) + 1
        yref = Reference(ws, min_col=ycol, min_row=1, max_row=n)
        s = Series(yref, xref, title_from_data=True)
        s.marker.symbol = spec.get("marker", "none")
        s.smooth = False
        chart.series.append(s)
    chart.x_axis.delete = False
    chart.y_axis.delete = False
    target = wb[sheet_title(spec.get("target", spec["sheet"]))] if spec.get("target") else ws
    target.add_chart(chart, spec.get("anchor", "H2"))


def build_workbook(tables: dict[str, pd.DataFrame], provenance: dict, charts=(), path: Path | None = None) -> Workbook:
    """Build a workbook from tables, provenance rows and chart specs."""
    wb = Workbook()
    wb.remove(wb.active)
    for name, df in tables.items():
        ws = wb.create_sheet(sheet_title(name))
        write_dataframe(ws, df)
    ws = wb.create_sheet("provenance")
    write_dataframe(ws, pd.DataFrame({"key": [str(k) for k in provenance],
                                      "value": [str(v) for v in provenance.values()]}, dtype=object))
    ws.column_dimensions["B"].width = 100
    for spec in charts:
        add_line_chart(wb, spec)
    if path is not None:
        wb.save(path)
    return wb


__all__ = ["build_workbook", "add_line_chart", "write_dataframe", "text_cell", "sheet_title", "LineChart"]
