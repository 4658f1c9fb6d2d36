"""Deliverable workbooks written with XlsxWriter.

Every sheet has a frozen, bold header row whose labels carry units in
brackets, a sensible number format and auto-sized columns.  Native Excel line
charts can be added from chart specs so that the customer's copy redraws from
the sheet data.

Every string (header, label, provenance) is a text cell, never a formula,
and a NaN or infinity is the text ``NaN``/``inf``, never an empty cell: see
:mod:`covtool.io.cells` for the rules.

XlsxWriter writes a cell in a few microseconds where openpyxl's element
tree took about 70 (issue 13: the flagship's 31.8 k cells took 3.9 s).  It
is run with every string conversion off (``strings_to_formulas``,
``strings_to_numbers``, ``strings_to_urls``: a string is always written as
text) and in ``constant_memory`` mode (rows are streamed to disk in order;
strings are in-line).  openpyxl still reads workbooks (tests, the store).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pandas as pd

from covtool.io.cells import is_formula_like, nonfinite_text, printable

#: XlsxWriter options: a string is never turned into a formula, number or link; NaN/inf never
#: reach it as numbers (they are written as text); rows are streamed to disk
XLSX_OPTIONS = {"strings_to_formulas": False, "strings_to_urls": False, "strings_to_numbers": False,
                "nan_inf_to_errors": False, "constant_memory": True}
#: number format of a date-time cell (openpyxl's default)
DATETIME_FORMAT = "yyyy-mm-dd h:mm:ss"
#: chart size [px] (18 cm x 9 cm at 96 dpi)
CHART_SIZE = {"width": 680, "height": 340}
#: openpyxl marker symbols (the chart specs' vocabulary) as XlsxWriter marker types
_MARKERS = {"none": "none", "auto": "automatic", "circle": "circle", "square": "square", "diamond": "diamond",
            "triangle": "triangle", "x": "x", "star": "star", "plus": "plus", "dash": "short_dash",
            "dot": "circle"}
_LINE_ENDS = re.compile("\r\n?")

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



class Book:
    """A workbook being written: XlsxWriter's, with each sheet's table.

    The tables are kept so that a chart spec (:func:`add_line_chart`) is
    checked against the sheet's header and rows before the chart is added.

    Parameters
    ----------
    target : path-like or file-like
        Where :meth:`close` writes the file (nothing is written before).
    """

    def __init__(self, target):
        import xlsxwriter

        self.xl = xlsxwriter.Workbook(str(target) if isinstance(target, Path) else target, XLSX_OPTIONS)
        self._sheets: dict[str, object] = {}
        self._tables: dict[str, pd.DataFrame] = {}
        self._formats: dict[tuple, object] = {}

    @property
    def sheetnames(self) -> list[str]:
        """Sheet titles in order."""
        return list(self._sheets)

    def sheet(self, title: str):
        """The worksheet ``title``, added (empty) if it is not there yet."""
        if title not in self._sheets:
            self._sheets[title] = self.xl.add_worksheet(title)
        return self._sheets[title]

    def table(self, title: str) -> pd.DataFrame:
        """The table written on sheet ``title`` (an empty one for a chart sheet)."""
        if title not in self._sheets:
            raise KeyError(f"Worksheet {title} does not exist.")
        return self._tables.get(title, pd.DataFrame())

    def cell_format(self, num_format: str | None = None, bold: bool = False, quote: bool = False):
        """The (shared) cell format with these properties; ``None`` for the default."""
        if num_format is None and not bold and not quote:
            return None
        key = (num_format, bold, quote)
        f = self._formats.get(key)
        if f is None:
            props = {}
            if num_format is not None:
                props["num_format"] = num_format
            if bold:
                props["bold"] = True
            if quote:
                props["quote_prefix"] = True
            f = self._formats[key] = self.xl.add_format(props)
        return f

    def close(self) -> None:
        """Write the file."""
        self.xl.close()


def _text(s: str) -> tuple[str, bool]:
    """Cell text of ``s`` and whether it needs the quote prefix (:func:`text_cell`)."""
    s = printable(s)
    quote = is_formula_like(s)
    # XML reads a CR back as LF (line-end normalisation, as openpyxl's files did); XlsxWriter
    # would write it as the escape _x000D_, which openpyxl does not decode
    return (_LINE_ENDS.sub("\n", s) if "\r" in s else s), quote


def text_cell(text: str) -> tuple[str, bool]:
    """A text cell holding ``text`` exactly, never a formula.

    Returns the text to write and whether the cell gets Excel's quote
    prefix (formula-like text: editing the cell keeps it text).
    XML-illegal control characters become ``\\xNN`` escapes; a CR (alone
    or before an LF) becomes the LF that XML reads back.
    """
    return _text(text)


def _cell_value(v):
    """``(kind, value)`` of the cell for table value ``v``; kind ``None``: no cell.

    Kinds: ``"n"`` number, ``"b"`` Boolean, ``"s"`` text (value, quote),
    ``"d"`` date-time.
    """
    if v is None or v is pd.NA or v is pd.NaT:
        return None, None
    if isinstance(v, (bool, np.bool_)):
        return "b", bool(v)
    if isinstance(v, (np.floating, float)):
        v = float(v)
        return ("n", v) if math.isfinite(v) else ("s", _text(nonfinite_text(v)))
    if isinstance(v, (int, np.integer)):
        return "n", int(v)
    if isinstance(v, str):
        return "s", _text(v)
    if isinstance(v, (pd.Timestamp, np.datetime64)):
        return "d", pd.Timestamp(v).to_pydatetime()
    return "s", _text(str(v))


def _shown(v):
    """The value a cell written for ``v`` holds (for the charts' row groups)."""
    kind, value = _cell_value(v)
    return value[0] if kind == "s" else value


def write_dataframe(book: Book, title: str, df: pd.DataFrame, *, index: bool = False):
    """Write ``df`` to a new sheet ``title`` of ``book``, styled.

    A bold, frozen header row of text cells; strings become text cells
    (:func:`text_cell`), NaN/inf the text ``NaN``/``inf``/``-inf``,
    finite numbers numbers (floats shown to :data:`DISPLAY_DIGITS`
    significant digits, :func:`number_format`); columns sized to their
    first 200 rows.  Rows are written in order (``constant_memory``).

    Returns
    -------
    xlsxwriter.worksheet.Worksheet
    """
    if index:
        df = df.reset_index()
    ws = book.sheet(title)
    book._tables[title] = df
    n = len(df)
    for j, c in enumerate(df.columns):
        text, quote = _text(str(c))
        if text:
            ws.write_string(0, j, text, book.cell_format(bold=True, quote=quote))
        else:
            ws.write_blank(0, j, None, book.cell_format(bold=True))
    writers = {"n": ws.write_number, "b": ws.write_boolean, "s": ws.write_string, "d": ws.write_datetime}
    columns = []
    for j in range(df.shape[1]):
        col = df.iloc[:, j]
        formatted = pd.api.types.is_float_dtype(col) or col.dtype == object
        kind = col.dtype.kind
        if kind in "fiub":                       # numbers and Booleans: no per-value dispatch
            columns.append(_numeric_cells(book, ws, col.tolist(), kind))
            _set_width(ws, j, df.columns[j], col, n)
            continue
        cells = []
        for v in col.array:
            kind, value = _cell_value(v)
            if kind is None or (kind == "s" and not value[0]):       # no value, or an empty text: no cell
                cells.append(None)
            elif kind == "s":
                cells.append((ws.write_string, value[0], book.cell_format(quote=value[1])))
            elif kind == "n" and formatted and isinstance(value, float):
                cells.append((ws.write_number, value, book.cell_format(number_format(value))))
            elif kind == "d":
                cells.append((ws.write_datetime, value, book.cell_format(DATETIME_FORMAT)))
            else:
                cells.append((writers[kind], value, None))
        columns.append(cells)
        _set_width(ws, j, df.columns[j], col, n)
    for i, row in enumerate(zip(*columns), start=1):
        for j, cell in enumerate(row):
            if cell is not None:
                cell[0](i, j, cell[1], cell[2])
    ws.freeze_panes(1, 0)
    return ws


def _numeric_cells(book: Book, ws, values: list, kind: str) -> list:
    """Cells of a float (``f``), integer (``i``, ``u``) or Boolean (``b``) column, as :func:`_cell_value`."""
    if kind == "b":
        return [(ws.write_boolean, v, None) for v in values]
    if kind != "f":
        return [(ws.write_number, v, None) for v in values]
    number, string = ws.write_number, ws.write_string
    formats: dict[str, object] = {}
    cells = []
    for v in values:
        if v - v == 0.0:                         # finite (NaN and inf give NaN)
            nf = number_format(v)
            f = formats.get(nf)
            if f is None:
                f = formats[nf] = book.cell_format(nf)
            cells.append((number, v, f))
        else:
            text, quote = _text(nonfinite_text(v))
            cells.append((string, text, book.cell_format(quote=quote)))
    return cells


def _set_width(ws, j: int, header, col: pd.Series, n: int) -> None:
    """Column ``j`` as wide as its header and first 200 values (10 to 60 characters)."""
    width = max(len(str(header)), *(len(_fmt_str(v)) for v in col.iloc[:200])) if n else len(str(header))
    ws.set_column(j, j, min(max(10, width + 2), 60))


def _fmt_str(v) -> str:
    if isinstance(v, float):
        return f"{v:.{DISPLAY_DIGITS + 2}g}"
    return str(v)


def _row_runs(title: str, df: pd.DataFrame, j: int, first: int, last: int) -> list[tuple[object, int, int]]:
    """Contiguous runs ``(value, first row, last row)`` of column ``j`` (rows counted from 1, header 1)."""
    runs: list[list] = []
    values = df.iloc[first - 2:last - 1, j].tolist()
    for r, v in enumerate(values, start=first):
        v = _shown(v)
        if runs and runs[-1][0] == v:
            runs[-1][2] = r
        else:
            runs.append([v, r, r])
    seen = [v for v, _, _ in runs]
    if len(seen) != len(set(seen)):
        raise ValueError(f"sheet {title!r}: rows of one {_shown(str(df.columns[j]))!r} are not contiguous")
    return [tuple(x) for x in runs]


def _literal_names(name, name_formula):
    """XlsxWriter's ``_process_names`` that keeps every title literal text.

    XlsxWriter turns a chart, axis or series title that looks like a cell
    reference (``x!A1``, ``=Sheet1!$A$1``) into a formula; a title here is
    always the text given (the rules of :mod:`covtool.io.cells`).
    """
    return name, name_formula


def add_line_chart(wb: Book, spec: dict):
    """Add a native scatter-with-lines chart drawn from sheet cells.

    Parameters
    ----------
    wb : Book
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
    xlsxwriter.chart_scatter.ChartScatter
        The chart added.

    Raises
    ------
    ValueError
        A header named by the spec is not in the sheet, or the rows of
        one group are not contiguous (a programming error of the runner).
    """
    title = sheet_title(spec["sheet"])
    df = wb.table(title)
    headers = [_text(str(c))[0] for c in df.columns]

    def col(name):
        if name not in headers:
            raise ValueError(f"sheet {title!r} has no column {name!r} for the chart {spec.get('title')!r}")
        return headers.index(name)

    first, last = 2, len(df) + 1
    where = spec.get("where") or {}
    if where:
        (wcol, wval), = where.items()
        runs = [r for r in _row_runs(title, df, col(wcol), first, last) if r[0] == wval]
        if not runs:
            raise ValueError(f"sheet {title!r}: no row with {wcol} = {wval!r}")
        _, first, last = runs[0]
    groups = _row_runs(title, df, col(spec["group"]), first, last) if spec.get("group") else [(None, first, last)]
    chart = wb.xl.add_chart({"type": "scatter", "subtype": "straight"})
    chart._process_names = _literal_names
    if spec.get("title") is not None:
        chart.set_title({"name": str(spec["title"])})
    chart.set_style(13)
    chart.set_size(CHART_SIZE)
    x_axis = {"name": spec.get("x_title", spec["x"])}
    y_axis = {"name": spec.get("y_title")} if spec.get("y_title") is not None else {}
    if spec.get("log_x"):
        x_axis["log_base"] = 10
    if spec.get("log_y"):
        y_axis["log_base"] = 10
    ys = list(spec["y"])
    opts = spec.get("series", {})
    for gval, r0g, r1 in groups:
        for y in ys:
            o = opts.get(y, {})
            ycol = col(y)
            r0 = r0g + spec.get("skip", 0)
            end = min(r1, r0 + o["rows"] - 1) if "rows" in o else r1
            name = y if gval is None else (str(gval) if len(ys) == 1 else f"{gval}: {y}")
            series = {"name": name, "categories": [title, r0 - 1, col(o.get("x", spec["x"])), end - 1,
                                                   col(o.get("x", spec["x"]))],
                      "values": [title, r0 - 1, ycol, end - 1, ycol],
                      "marker": {"type": _MARKERS.get(o.get("marker", spec.get("marker", "none")), "automatic")},
                      "smooth": False}
            if o.get("line") is False:
                series["line"] = {"none": True}
            chart.add_series(series)
    chart.set_x_axis(x_axis)
    chart.set_y_axis(y_axis)
    target = title
    if spec.get("target"):
        target = sheet_title(spec["target"])
    anchor = spec.get("anchor", "H2")
    ws = wb.sheet(target)
    if isinstance(anchor, str):
        ws.insert_chart(anchor, chart)
    else:
        ws.insert_chart(anchor[0] - 1, anchor[1] - 1, chart)
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


def build_workbook(tables: dict[str, pd.DataFrame], provenance: dict, charts=(), path: Path | None = None) -> Book:
    """Build a workbook from tables, provenance rows and chart specs.

    The provenance sheet is split by :func:`provenance_frame`, so that a
    value longer than Excel's 32 767-character cell is kept whole.

    Parameters
    ----------
    tables : dict of str to DataFrame
        One sheet each, in this order.
    provenance : dict
        The ``provenance`` sheet's rows.
    charts : sequence of dict
        Chart specs (:func:`add_line_chart`).
    path : path-like, optional
        The file written.  Without it the workbook is built in memory and
        returned unclosed (more charts can be added).

    Returns
    -------
    Book
    """
    import io

    book = Book(path if path is not None else io.BytesIO())
    try:
        for name, df in tables.items():
            write_dataframe(book, sheet_title(name), df)
        ws = write_dataframe(book, "provenance", provenance_frame(provenance))
        ws.set_column(1, 1, 100)
        for spec in charts:
            add_line_chart(book, spec)
        if path is not None:
            book.close()
    except BaseException:
        if path is not None:
            Path(path).unlink(missing_ok=True)
        raise
    return book


__all__ = ["Book", "build_workbook", "add_line_chart", "provenance_frame", "read_provenance", "number_format",
           "write_dataframe", "text_cell", "sheet_title", "XLSX_OPTIONS"]
