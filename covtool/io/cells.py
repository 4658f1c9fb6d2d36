"""Cell values a spreadsheet shows as written: text never runs, NaN never hides.

Rules shared by the workbook (:mod:`covtool.io.workbook`) and the CSV files
(:func:`write_csv`):

Text
    Spreadsheets evaluate a cell whose text starts with ``=``, ``+``, ``-``,
    ``@``, a tab or a carriage return (and their full-width forms, which
    Excel's East-Asian input methods also accept) as a formula.  Following
    the OWASP *CSV Injection* guidance:

    * xlsx: every string is written as a text cell (``data_type = 's'``),
      never as a formula, and formula-like text also gets Excel's
      *quote prefix* style (``quotePrefix``: the cell is shown and kept as
      text even when edited, like typing a leading apostrophe).  The value
      is exactly the user's text;
    * CSV: formula-like text gets a leading apostrophe (``'=1+2``) and every
      text field is wrapped in double quotes (``csv.QUOTE_NONNUMERIC``; a
      minimally quoted field would not protect a CR inside it).  A reader
      gets the user's text back by removing that one apostrophe
      (:func:`csv_text_value`).

    Control characters other than tab, LF and CR cannot be stored in xlsx
    (XML 1.0); in both formats they are written as the escape ``\\xNN``.
    XML reads a CR in a workbook cell back as LF (line-end normalisation).
Numbers
    Finite numbers stay numbers.  A NaN or infinity where a number was
    expected is never an empty cell or 0: the workbook shows the text
    ``NaN``, ``inf`` or ``-inf``; the CSV holds ``"nan"``, ``inf`` or
    ``-inf`` (which ``float()`` and pandas parse back as the float).  ``None`` (no value,
    e.g. text that does not apply) is an empty cell in both.
"""

from __future__ import annotations

import csv
import math
import re

import numpy as np
import pandas as pd

#: first characters that make a spreadsheet evaluate a cell as a formula
FORMULA_TRIGGERS = ("=", "+", "-", "@", "\t", "\r", "\uff1d", "\uff0b", "\uff0d", "\uff20")

#: characters XML 1.0 (and so xlsx) cannot hold
_ILLEGAL = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]")

#: NaN/inf as workbook text
NONFINITE_TEXT = {"nan": "NaN", "inf": "inf", "-inf": "-inf"}
#: NaN as CSV text (inf/-inf are written as ``inf``/``-inf``)
CSV_NAN = "nan"


def is_formula_like(text: str) -> bool:
    """True if a spreadsheet would evaluate ``text`` as a formula."""
    return bool(text) and text.startswith(FORMULA_TRIGGERS)


def printable(text: str) -> str:
    """``text`` with XML-illegal control characters as ``\\xNN`` escapes."""
    return _ILLEGAL.sub(lambda m: f"\\x{ord(m.group()):02x}", text)


def nonfinite_text(x: float) -> str:
    """Workbook text of a NaN or infinite float: ``NaN``, ``inf``, ``-inf``."""
    if math.isnan(x):
        return NONFINITE_TEXT["nan"]
    return NONFINITE_TEXT["inf"] if x > 0 else NONFINITE_TEXT["-inf"]


def csv_text(text: str) -> str:
    """CSV form of a user string: printable, formula-like text behind ``'``."""
    text = printable(text)
    return "'" + text if is_formula_like(text) else text


def csv_text_value(field: str) -> str:
    """Inverse of :func:`csv_text` for a field read back with the csv module."""
    if field.startswith("'") and is_formula_like(field[1:]):
        return field[1:]
    return field


def _csv_value(v):
    if v is None or v is pd.NA or v is pd.NaT:
        return ""
    if isinstance(v, str):
        return csv_text(v)
    if isinstance(v, (float, np.floating)):
        v = float(v)
        return CSV_NAN if math.isnan(v) else v
    if isinstance(v, (list, tuple, dict, set)):
        return csv_text(str(v))
    return v


def csv_frame(df: pd.DataFrame) -> pd.DataFrame:
    """Copy of ``df`` with every text value and header made CSV-safe.

    Numeric columns are kept as they are (``to_csv`` writes NaN with
    ``na_rep``); object columns are mapped value by value.
    """
    out = df.copy()
    out.columns = [csv_text(str(c)) for c in df.columns]
    for j in range(df.shape[1]):
        col = df.iloc[:, j]
        if not (pd.api.types.is_numeric_dtype(col) or pd.api.types.is_bool_dtype(col)):
            out.isetitem(j, col.map(_csv_value).astype(object))
    return out


def write_csv(df: pd.DataFrame, path) -> None:
    """Write ``df`` as CSV with safe text and NaN as ``nan``.

    Parameters
    ----------
    df : DataFrame
        Any table of a :class:`~covtool.results.StudyResult`.
    path : path-like
        Destination (inside a staging directory: the caller moves it).
    """
    csv_frame(df).to_csv(path, index=False, na_rep=CSV_NAN, quoting=csv.QUOTE_NONNUMERIC)


__all__ = ["FORMULA_TRIGGERS", "is_formula_like", "printable", "nonfinite_text", "csv_text", "csv_text_value",
           "csv_frame", "write_csv", "NONFINITE_TEXT", "CSV_NAN"]
