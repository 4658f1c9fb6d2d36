"""Tables for the terminal: key columns, sensible digits, within a width.

The files (CSV, workbook) hold every column at full precision; the console
shows what fits in :data:`WIDTH` columns, with four significant digits,
wrapped headers and a line naming the columns left out.
"""

from __future__ import annotations

import math
import re
import shutil
import textwrap

__all__ = ["WIDTH", "KEY_COLUMNS", "console_width", "format_number", "console_table"]

#: default width of console tables [characters]
WIDTH = 110

#: columns left out first when a table is too wide: explanations, check figures and the
#: repeated "nominal run" figures, which the files keep
_SECONDARY = re.compile(r"top sources|residual|nominal run|\bnote\b|\bsource\b|provenance|description"
                        r"|wall time|flops", re.IGNORECASE)
#: columns never left out: whether the row's numbers can be trusted
_KEY = re.compile(r"^(validity|status)$", re.IGNORECASE)
_UNIT = re.compile(r"^(.*\S) \[[^\]]*\]$")
#: longest text cell shown [characters]
MAX_TEXT = 36

#: per study kind, the summary columns the console shows first (after the first column), when present;
#: the others follow while there is room
KEY_COLUMNS = {
    # seed 002 Fig 8 and Table 4: the largest sensitivity of each channel and the cost per cycle
    "zupt_sensitivity": ["states [-]", "CEP [ft]", "alt PE [ft]", "azimuth 1sigma [arcmin]",
                         "max sensitivity horizontal [-]", "max sensitivity altitude [-]", "FLOPs/cycle [FLOP]"],
    # seed 002 Table 3
    "zupt_filter_order": ["states", "CEP [ft]", "alt PE [ft]", "azimuth 1sigma [arcmin]"],
    # the cases' parameters, then the three figures of merit
    "trade_grid": ["grade", "ZUPT interval [min]", "filter", "ZUPT sigma [ft/s]", "Q scale", "CEP [ft]",
                   "alt PE [ft]", "azimuth 1sigma [arcmin]"],
}


def console_width(default: int = WIDTH) -> int:
    """Width for console tables: the terminal's, between 100 and 120 (``default`` if unknown)."""
    cols = shutil.get_terminal_size((default, 24)).columns
    return max(100, min(120, cols))


def format_number(x) -> str:
    """A number to four significant digits; whole numbers up to 1e9 without exponent.

    ``14.999999999999996`` → ``15``; ``4281.289`` → ``4281``;
    ``123456.7`` → ``123457``; ``1.029629e-14`` → ``1.03e-14``; NaN → ``NaN``.
    """
    if isinstance(x, (bool,)) or x is None:
        return str(x)
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if math.isnan(v):
        return "NaN"
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if isinstance(x, int) or (hasattr(x, "dtype") and getattr(x.dtype, "kind", "") in "iu"):
        return str(int(x))
    if 1e4 <= abs(v) < 1e9:
        return f"{v:.0f}"
    return f"{v:.4g}"


def _cells(col: pd.Series, max_text: int = MAX_TEXT) -> tuple[list[str], bool]:
    """Formatted cells of one column and whether it is right-aligned (numeric)."""
    import pandas as pd          # here: `covtool show` and `new` print without pandas

    numeric = pd.api.types.is_numeric_dtype(col) and not pd.api.types.is_bool_dtype(col)
    out = []
    for v in col.tolist():
        if isinstance(v, float) or numeric:
            out.append(format_number(v))
        else:
            t = "" if v is None else " ".join(str(v).split())
            out.append(t if len(t) <= max_text else t[:max_text - 1] + "…")
    return out, numeric


def _header(name: str, width: int) -> list[str]:
    return textwrap.wrap(str(name), width=max(width, 1), break_long_words=False, break_on_hyphens=False) or [""]


def console_table(df: pd.DataFrame, *, width: int = WIDTH, max_rows: int | None = None,
                  file_hint: str = "the output files", max_text: int = MAX_TEXT, stretch: str | None = None,
                  fold_constant: bool = True, prefer=()) -> str:
    """Render ``df`` for the terminal within ``width`` columns.

    Parameters
    ----------
    df : pandas.DataFrame
    width : int
        Largest line length. [characters]
    max_rows : int, optional
        Show the first ``max_rows`` rows and a line counting the rest.
    file_hint : str
        Where the full table is (named in the note on omitted columns).
    max_text : int
        Longest text cell shown; longer ones end in "…". [characters]
    stretch : str, optional
        A text column that is cut to the width left by the others instead
        of being left out (a description).
    fold_constant : bool
        Say a column with the same value in every row once, below the
        table, instead of in every row.
    prefer : sequence of str
        Columns shown first, after the first column, in this order (those
        present; :data:`KEY_COLUMNS` of the study kind).

    Returns
    -------
    str
        Numbers to four significant digits (:func:`format_number`), text
        cut at ``max_text`` characters, headers wrapped to their
        column.  A column with the same value in every row is said once
        below the table.  Columns that do not fit are left out (an
        explanation, a check figure or a quantity repeated in another
        unit first; ``validity`` and ``status`` never) and named in a
        last line.
    """
    first = list(df.columns[:1])
    front = [c for c in prefer if c in df.columns and c not in first]
    df = df[first + front + [c for c in df.columns[1:] if c not in front]]
    shown = df if max_rows is None or len(df) <= max_rows else df.head(max_rows)
    cols, same = [], []
    seen_base = set()
    for k, name in enumerate(df.columns):
        cells, right = _cells(shown[name], max_text)
        full, _ = _cells(df[name], max_text)
        if fold_constant and k > 0 and len(df) > 1 and len(set(full)) == 1 and not _KEY.match(str(name)):
            same.append(f"{name} = {full[0]}")       # the same in every row: said once, below the table
            continue
        m = _UNIT.match(str(name))
        twin = bool(m) and m.group(1) in seen_base   # the same quantity again in another unit
        if m:
            seen_base.add(m.group(1))
        w = max([len(c) for c in cells] + [len(word) for word in str(name).split()])
        cols.append({"name": str(name), "cells": cells, "right": right, "width": w,
                     "secondary": (twin or bool(_SECONDARY.search(str(name)))) and name not in front,
                     "key": bool(_KEY.match(str(name)))})

    def total(cs):
        return sum(c["width"] for c in cs) + 2 * (len(cs) - 1)

    for c in cols:
        if c["name"] == stretch and total(cols) > width:
            room = max(12, width - (total(cols) - c["width"]))
            c["cells"] = [t if len(t) <= room else t[:room - 1] + "…" for t in c["cells"]]
            c["width"] = max([len(t) for t in c["cells"]] + [len(w) for w in c["name"].split()])
    kept = list(cols)
    omitted = []
    # leave out explanations first (right to left), then the rightmost columns; the first column stays
    for secondary in (True, False):
        for c in reversed(cols[1:]):
            if total(kept) <= width:
                break
            if c in kept and not c["key"] and (not secondary or c["secondary"]):
                kept.remove(c)
                omitted.append(c["name"])
    heads = [_header(c["name"], c["width"]) for c in kept]
    depth = max(len(h) for h in heads)
    lines = []
    for k in range(depth):
        parts = []
        for c, h in zip(kept, heads):
            text = h[k - (depth - len(h))] if k >= depth - len(h) else ""
            parts.append(text.rjust(c["width"]) if c["right"] else text.ljust(c["width"]))
        lines.append("  ".join(parts).rstrip())
    lines.append("  ".join("-" * c["width"] for c in kept))
    for i in range(len(shown)):
        parts = [c["cells"][i].rjust(c["width"]) if c["right"] else c["cells"][i].ljust(c["width"]) for c in kept]
        lines.append("  ".join(parts).rstrip())
    if len(shown) < len(df):
        n = len(df) - len(shown)
        lines.append(f"... {n} more row{'s' if n > 1 else ''} in {file_hint}")
    if same:
        lines += textwrap.wrap(f"every row: {'; '.join(same)}", width=width, break_long_words=False)
    if omitted:
        order = [c["name"] for c in cols if c["name"] in omitted]
        lines += textwrap.wrap(f"({len(order)} more column{'s' if len(order) > 1 else ''} in {file_hint}: "
                               f"{'; '.join(order)})", width=width, break_long_words=False)
    return "\n".join(lines)
