"""Regression record of every shipped study: same numbers before and after a change.

Run from the repository root (not part of the test suite)::

    python benchmarks/regression.py --save /tmp/before.json     # record with the current code
    python benchmarks/regression.py --compare /tmp/before.json  # rerun, report the differences

Every study in ``studies/`` is run through :func:`covtool.run_study` and
every numeric cell of every table it returns (the summary and the other
sheets) is dumped, column by column, to a JSON file.  ``--compare`` reruns
the studies and prints, per study, the largest relative difference
``|a - b| / max(|a|, |b|, 1e-15 · c / rtol)`` over its cells, ``c`` the
largest magnitude in the cell's table among the columns of its unit: a cell
must agree to ``rtol`` of itself or to ``1e-15`` (a few units in the last
place) of that scale, whichever is larger, because a cell far below its
scale (an error-budget contribution at a zero crossing, beside the total) is
formed by sums at that scale; a budget's 1σ-equivalent, the square root
of a variance contribution, is compared as that variance (0 when both are 0; a NaN must stay a NaN at
the same place; the figure without that floor is printed too), the cell where it occurs, and whether the
study stays within ``--rtol`` (default 1e-9).  Round-off check figures
(``ROUNDOFF``: relative residuals of order 1e-15 .. 1e-11, which any change
of operation order changes wholesale) must stay below 1e-10 before and after.  The exit status is 1 when a
study departs, has a different set of cells, or fails.

Shortened where the full run is long (the shortening is the same for the
record and the comparison, so the numbers compare like with like):

* ``monte_carlo_validation``: 20 runs (one chunk) instead of 200;
* ``dual_imu_flight``: 10 fault-free and 4 faulty flights instead of 1000 and 100;
* ``trade_grid``: a 2 × 6 × 2 × 2 × 2 sub-grid (ZUPT interval 4 and 6 min,
  all filters, grades navigation and tactical, ZUPT σ 0.003 and 0.03 ft/s,
  Q scale 0.3 and 3), 96 of the 1296 cases;
* ``zupt_sensitivity``: the on-board cycle timing (a measured wall time) is
  switched off, everything else as shipped.

Columns of measured wall-clock times (``MEASURED``) are left out.  The
other studies run as shipped.  About 3-4 min on a 2-core machine.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
STUDIES = ROOT / "studies"


def shortened(name: str, decl: dict) -> dict:
    """The declaration of study ``name`` as the regression record runs it."""
    if name == "monte_carlo_validation":
        decl["monte_carlo"].update(runs=20, runs_per_chunk=20)
    elif name == "dual_imu_flight":
        decl["simulation"].update(runs=10, fault_runs=4, batch=10)
    elif name == "trade_grid":
        decl["grid"].update(zupt_interval=["4 min", "6 min"], zupt_sigma=["0.003 ft/s", "0.03 ft/s"],
                            q_scale=[0.3, 3.0])
        decl["grade"] = [g for g in decl["grade"] if g["name"] in ("navigation", "tactical")]
    elif name == "zupt_sensitivity":
        decl["cost"]["measure"] = False
    return decl


def absolute(decl: dict, base: Path) -> dict:
    """Input-file paths made absolute (the declaration is run as a dict)."""
    def fix(tab, key):
        v = tab.get(key) if isinstance(tab, dict) else None
        if isinstance(v, str) and ("/" in v or v.endswith(".toml") or v.endswith(".csv")):
            p = Path(v)
            tab[key] = str(p if p.is_absolute() else (base / p).resolve())

    fix(decl.get("truth"), "model")
    fix(decl.get("filters"), "file")
    fix(decl.get("trajectory"), "csv")
    for key in ("main", "kimu"):
        fix((decl.get("imu") or {}).get(key), "grade")
    return decl


#: columns that hold a measured wall-clock time, not a computed number
MEASURED = ("wall time",)
#: columns that are round-off check figures (relative residuals of order 1e-15 .. 1e-11): any change
#: of operation order changes them wholesale, so they must stay at round-off, below ROUNDOFF_LEVEL,
#: before and after
ROUNDOFF = ("filter noise vs its own Q_f (max rel.)", "sum-to-total residual (same Q_d)",
            "sum vs nominal run residual")
ROUNDOFF_LEVEL = 1e-10


#: absolute round-off allowed of every cell, relative to the largest magnitude of its unit in its table (a few
#: units in the last place of that scale: a cell formed by sums at that scale carries at least this much)
SCALE_ROUNDOFF = 1e-15
#: columns that are the square root of a variance contribution (a budget's 1σ-equivalent): compared squared
SQUARE_ROOTS = ("1sigma-equivalent",)


def unit_of(column: str) -> str:
    """The bracketed unit at the end of a column name (``"total [ft^2]"`` → ``"ft^2"``), else the name."""
    head, sep, tail = column.rpartition("[")
    return tail.rstrip("]") if sep and column.endswith("]") else column


def measured(column: str) -> bool:
    return any(m in column for m in MEASURED)


def numeric_cells(result) -> dict:
    """``{table: {column: [float or None for NaN]}}`` of a study result."""
    out = {}
    for tname, df in result.tables.items():
        cols = {}
        for col in df.columns:
            s = df[col]
            if measured(str(col)):
                continue
            if pd.api.types.is_bool_dtype(s.dtype):
                continue
            if not pd.api.types.is_numeric_dtype(s.dtype):
                # an object column counts when every cell is a number or missing
                vals = s.to_list()
                if not vals or not all(v is None or (isinstance(v, (int, float, np.number))
                                                     and not isinstance(v, (bool, np.bool_))) for v in vals):
                    continue
                s = pd.Series([np.nan if v is None else float(v) for v in vals])
            cols[str(col)] = [None if not math.isfinite(float(x)) else float(x) for x in s.to_numpy()]
        if cols:
            out[tname] = cols
    return out


def run_all(only=None) -> dict:
    import covtool

    record = {}
    for path in sorted(STUDIES.glob("*.toml")):
        name = path.stem
        if only and name not in only:
            continue
        decl = absolute(shortened(name, tomllib.loads(path.read_text())), path.parent)
        t0 = time.perf_counter()
        try:
            result = covtool.run_study(decl)
        except Exception as exc:                      # reported, and a failure of the comparison
            record[name] = {"error": f"{type(exc).__name__}: {exc}"}
            print(f"{name:36s} FAILED: {exc}", flush=True)
            continue
        record[name] = numeric_cells(result)
        n = sum(len(v) for t in record[name].values() for v in t.values())
        print(f"{name:36s} {n:7d} cells  {time.perf_counter() - t0:6.1f} s", flush=True)
    return record


def compare(before: dict, after: dict, rtol: float) -> bool:
    ok = True
    print(f"\n{'study':36s} {'cells':>7s} {'max rel. diff':>14s}  where")
    for name in sorted(set(before) | set(after)):
        a, b = before.get(name), after.get(name)
        if a is None or b is None or "error" in a or "error" in b:
            print(f"{name:36s} missing or failed: before {a and a.get('error', 'ok')}, after {b and b.get('error', 'ok')}")
            ok = False
            continue
        worst, where, n, shape = 0.0, "", 0, []
        worst_abs, where_abs = 0.0, ""
        strict, where_strict = 0.0, ""
        scales = {}
        for rec in (a, b):
            for t, cols in rec.items():
                for c, vals in cols.items():
                    m = max((abs(z) for z in vals if z is not None), default=0.0)
                    scales[(t, unit_of(c))] = max(scales.get((t, unit_of(c)), 0.0), m)
        for t in sorted(set(a) | set(b)):
            for c in sorted(c for c in set(a.get(t, {})) | set(b.get(t, {})) if not measured(c)):
                x, y = a.get(t, {}).get(c), b.get(t, {}).get(c)
                if x is None or y is None or len(x) != len(y):
                    shape.append(f"{t}:{c}")
                    continue
                # a cell far below the largest value of its unit in its table (an error-budget contribution at
                # a zero crossing, next to the total) is formed by sums at that scale: it is compared to rtol of
                # itself or to SCALE_ROUNDOFF of that scale, whichever is larger
                floor = SCALE_ROUNDOFF / rtol * scales.get((t, unit_of(c)), 0.0)
                if any(r in c for r in SQUARE_ROOTS):
                    # √ of a variance contribution: compared as that variance, on its squared scale
                    x = [None if z is None else z * abs(z) for z in x]
                    y = [None if z is None else z * abs(z) for z in y]
                    floor = SCALE_ROUNDOFF / rtol * scales.get((t, unit_of(c)), 0.0) ** 2
                for i, (u, v) in enumerate(zip(x, y)):
                    n += 1
                    if u is None or v is None:
                        d = 0.0 if u is v else math.inf
                    elif c in ROUNDOFF:
                        if max(abs(u), abs(v)) >= worst_abs:
                            worst_abs, where_abs = max(abs(u), abs(v)), f"{t}[{c!r}][{i}]"
                        continue
                    else:
                        m = max(abs(u), abs(v))
                        d = 0.0 if m == 0 else abs(u - v) / max(m, floor)
                        if m and abs(u - v) / m > strict:
                            strict, where_strict = abs(u - v) / m, f"{t}[{c!r}][{i}]"

                    if d > worst:
                        worst, where = d, f"{t}[{c!r}][{i}]"
        good = worst <= rtol and worst_abs < ROUNDOFF_LEVEL and not shape
        ok &= good
        print(f"{name:36s} {n:7d} {worst:14.3e}  {where or '-'}{'' if good else '  DEPARTS'}"
              + (f"  cells differ: {shape[:5]}" if shape else "")
              + (f"\n{'':36s} {'':7s} {strict:14.3e}  without the column floor: {where_strict}"
                 if strict > worst else "")
              + (f"\n{'':36s} {'':7s} {worst_abs:14.3e}  largest round-off check figure, before or after: "
                 f"{where_abs}" if where_abs else ""))
    return ok


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--save", metavar="JSON", help="run every study and write the record")
    g.add_argument("--compare", metavar="JSON", help="rerun and compare with a record")
    p.add_argument("--rtol", type=float, default=1e-9, help="largest relative difference accepted (1e-9)")
    p.add_argument("--only", nargs="*", help="study names (file stems) to run")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    if args.save:
        record = run_all(args.only)
        Path(args.save).write_text(json.dumps(record))
        print(f"wrote {args.save} in {time.perf_counter() - t0:.0f} s")
        return 0 if not any("error" in v for v in record.values()) else 1
    before = json.loads(Path(args.compare).read_text())
    if args.only:
        before = {k: v for k, v in before.items() if k in args.only}
    after = run_all(args.only)
    ok = compare(before, after, args.rtol)
    print(f"\n{'all studies agree' if ok else 'DIFFERENCES'} (rtol {args.rtol:g}) in {time.perf_counter() - t0:.0f} s")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
