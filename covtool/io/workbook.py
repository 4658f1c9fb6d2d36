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


#: significant digits shown by a cell's number format (the cell keeps full precision)
DISPLAY_DIGITS = 4


def number_format(v: float) -> str:
    """Excel number format showing ``v`` to :data:`DISPLAY_DIGITS` significant digits.

    The cell stores the full double; only the display is rounded
    (``14.999999999999996`` shows as ``15.00``).  Magnitudes below 1e-3
    or from 1e6 up use scientific notation.

    Parameters
    ----------
    v : float
        A finite value.

    Returns
    -------
    str
        ``"0"``, ``"0.00"``, ``"0.000E+00"``, ...
    """
    a = abs(v)
    if a == 0.0:
        return "0"
    if a < 1e-3 or a >= 1e6:
        return "0." + "0" * (DISPLAY_DIGITS - 1) + "E+00"
    decimals = max(0, DISPLAY_DIGITS - 1 - math.floor(math.log10(a)))
    return "0." + "0" * decimals if decimals else "0"


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
        letter = get_column_letter(j)
        if pd.api.types.is_float_dtype(df.iloc[:, j - 1]) or df.iloc[:, j - 1].dtype == object:
            for (cell,) in ws.iter_rows(min_row=2, max_row=len(df) + 1, min_col=j, max_col=j):
                if isinstance(cell.value, float) and math.isfinite(cell.value):
                    cell.number_format = number_format(cell.value)
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
        return f"{v:.{DISPLAY_DIGITS + 2}g}"
    return str(v)


def _row_runs(ws, col: int, first: int, last: int) -> list[tuple[object, int, int]]:
    """Contiguous runs ``(value, first row, last row)`` of column ``col``."""
    runs: list[list] = []
    for r in range(first, last + 1):
        v = ws.cell(row=r, column=col).value
        if runs and runs[-1][0] == v:
            runs[-1][2] = r
        else:
            runs.append([v, r, r])
    seen = [v for v, _, _ in runs]
    if len(seen) != len(set(seen)):
        raise ValueError(f"sheet {ws.title!r}: rows of one {ws.cell(row=1, column=col).value!r} are not contiguous")
    return [tuple(x) for x in runs]


def add_line_chart(wb, spec: dict) -> ScatterChart:
    """Add a native scatter-with-lines chart drawn from sheet cells.

    Parameters
    ----------
    wb : openpyxl.Workbook
    spec : dict
        ``{"sheet": data sheet, "x": x column header, "y": [y column headers],
        "group": column whose values name the cases (one series per case
        and y column, over that case's rows; the rows of a case must be
        contiguous), "where": {column: value} (only the rows holding it),
        "skip": rows left out at the start of each group (a zero at t = 0
        has no place on a log axis),
        "title": str, "x_title": str, "y_title": str, "anchor": "H2" or
        (row, column) counted from 1,
        "target": sheet to place the chart on (default: data sheet;
        created, empty, if it is not a table),
        "log_x": bool, "log_y": bool (base-10 axes, as the PNG's),
        "marker": symbol, "series": {y column: {"x": its own x column,
        "rows": number of rows it spans, "marker": symbol, "line": False
        for points only}}}``

    Returns
    -------
    openpyxl.chart.ScatterChart
        The chart added.

    Raises
    ------
    ValueError
        A header named by the spec is not in the sheet, or the rows of
        one group are not contiguous (a programming error of the runner).
    """
    ws = wb[sheet_title(spec["sheet"])]
    headers = [c.value for c in ws[1]]

    def col(name):
        if name not in headers:
            raise ValueError(f"sheet {ws.title!r} has no column {name!r} for the chart {spec.get('title')!r}")
        return headers.index(name) + 1

    first, last = 2, ws.max_row
    where = spec.get("where") or {}
    if where:
        (wcol, wval), = where.items()
        runs = [r for r in _row_runs(ws, col(wcol), first, last) if r[0] == wval]
        if not runs:
            raise ValueError(f"sheet {ws.title!r}: no row with {wcol} = {wval!r}")
        _, first, last = runs[0]
    groups = _row_runs(ws, col(spec["group"]), first, last) if spec.get("group") else [(None, first, last)]
    chart = ScatterChart()
    chart.title = spec.get("title")
    chart.style = 13
    chart.x_axis.title = spec.get("x_title", spec["x"])
    chart.y_axis.title = spec.get("y_title")
    chart.height, chart.width = 9, 18
    if spec.get("log_x"):
        chart.x_axis.scaling.logBase = 10
    if spec.get("log_y"):
        chart.y_axis.scaling.logBase = 10
    ys = list(spec["y"])
    opts = spec.get("series", {})
    for gval, r0g, r1 in groups:
        for y in ys:
            o = opts.get(y, {})
            ycol = col(y)
            r0 = r0g + spec.get("skip", 0)
            last = min(r1, r0 + o["rows"] - 1) if "rows" in o else r1
            xref = Reference(ws, min_col=col(o.get("x", spec["x"])), min_row=r0, max_row=last)
            title = y if gval is None else (str(gval) if len(ys) == 1 else f"{gval}: {y}")
            s = Series(Reference(ws, min_col=ycol, min_row=r0, max_row=last), xref, title=title)
            s.marker.symbol = o.get("marker", spec.get("marker", "none"))
            if o.get("line") is False:
                s.graphicalProperties.line.noFill = True
            s.smooth = False
            chart.series.append(s)
    chart.x_axis.delete = False
    chart.y_axis.delete = False
    target = ws
    if spec.get("target"):
        tname = sheet_title(spec["target"])
        target = wb[tname] if tname in wb.sheetnames else wb.create_sheet(tname)
    anchor = spec.get("anchor", "H2")
    if not isinstance(anchor, str):
        anchor = f"{get_column_letter(anchor[1])}{anchor[0]}"
    target.add_chart(chart, anchor)
    return chart


#: longest text an Excel cell holds
EXCEL_CELL_MAX = 32767
#: longest provenance piece written to one cell (below :data:`EXCEL_CELL_MAX`, with room for escapes)
PROVENANCE_PIECE = 8000


def provenance_frame(provenance: dict) -> pd.DataFrame:
    """Provenance rows split so that no cell is cut at Excel's limit.

    Each value is split at its line ends, one row per line (a resolved
    study reads as its TOML), and a line longer than
    :data:`PROVENANCE_PIECE` characters into several rows.  Columns:
    ``key``, ``value``, ``part`` (1, 2, ... within the key) and
    ``continues`` (``True`` when the next part continues the same line).
    :func:`read_provenance` joins them back exactly.

    Parameters
    ----------
    provenance : dict of str to object
        Values are written as ``str(value)``.

    Returns
    -------
    DataFrame
    """
    keys, vals, parts, cont = [], [], [], []
    for k, v in provenance.items():
        lines = str(v).split("\n")
        n = 0
        for line in lines:
            pieces = [line[i:i + PROVENANCE_PIECE] for i in range(0, len(line), PROVENANCE_PIECE)] or [""]
            for j, piece in enumerate(pieces):
                n += 1
                keys.append(str(k))
                vals.append(piece)
                parts.append(n)
                cont.append(j < len(pieces) - 1)
    return pd.DataFrame({"key": keys, "value": vals, "part": parts, "continues": cont}).astype(
        {"key": object, "value": object})


def read_provenance(ws) -> dict[str, str]:
    """Provenance values from a sheet written by :func:`build_workbook`.

    Parameters
    ----------
    ws : openpyxl worksheet
        The ``provenance`` sheet.

    Returns
    -------
    dict of str to str
        Each key's parts joined back (the inverse of :func:`provenance_frame`).
    """
    out: dict[str, str] = {}
    joiner: dict[str, str] = {}
    for key, value, _part, continues in ws.iter_rows(min_row=2, max_col=4, values_only=True):
        value = "" if value is None else str(value)
        out[key] = out[key] + joiner[key] + value if key in out else value
        joiner[key] = "" if continues else "\n"
    return out


def build_workbook(tables: dict[str, pd.DataFrame], provenance: dict, charts=(), path: Path | None = None) -> Workbook:
    """Build a workbook from tables, provenance rows and chart specs.

    The provenance sheet is split by :func:`provenance_frame`, so that a
    value longer than Excel's 32 767-character cell is kept whole.
    """
    wb = Workbook()
    wb.remove(wb.active)
    for name, df in tables.items():
        ws = wb.create_sheet(sheet_title(name))
        write_dataframe(ws, df)
    ws = wb.create_sheet("provenance")
    write_dataframe(ws, provenance_frame(provenance))
    ws.column_dimensions["B"].width = 100
    for spec in charts:
        add_line_chart(wb, spec)
    if path is not None:
        wb.save(path)
    return wb


__all__ = ["build_workbook", "add_line_chart", "provenance_frame", "read_provenance", "number_format", "write_dataframe", "text_cell", "sheet_title", "LineChart"]
