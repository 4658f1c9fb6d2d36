"""The flagship's numbers stay the same: a regression record at 6 min.

``tests/data/flagship_6min.json`` holds every numeric summary cell of
``studies/zupt_filter_order.toml`` run for 6 min (one ZUPT stop, at 5 min).
It is a record of the code's own output, not an independent truth: it
catches an unintended change of numbers (a refactor, a library upgrade).
Regenerate it only when a change of numbers is intended, and say why in
the commit::

    PYTHONPATH=. python tests/test_regression.py --regenerate

The full regression over every shipped study is ``benchmarks/regression.py``.
"""

from __future__ import annotations

import json
import math
import sys
import tomllib
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
FLAGSHIP = ROOT / "studies" / "zupt_filter_order.toml"
RECORD = Path(__file__).resolve().parent / "data" / "flagship_6min.json"
RTOL = 1e-9


def flagship_summary() -> pd.DataFrame:
    import covtool

    decl = tomllib.loads(FLAGSHIP.read_text())
    decl["study"]["duration"] = "6 min"
    decl["output"]["report_times"] = ["6 min"]
    decl["filters"]["file"] = str(FLAGSHIP.parent / decl["filters"]["file"])
    decl["impact"] = {"filters": []}          # the impact table is not in the summary
    return covtool.run_study(decl).summary


def numeric_columns(df: pd.DataFrame) -> dict:
    return {str(c): [None if not math.isfinite(x) else float(x) for x in df[c].astype(float)]
            for c in df.columns if pd.api.types.is_numeric_dtype(df[c]) and not pd.api.types.is_bool_dtype(df[c])}


def test_flagship_6min_summary_matches_the_record():
    record = json.loads(RECORD.read_text())
    s = flagship_summary()
    assert list(s["case"]) == record["cases"]
    now = numeric_columns(s)
    assert set(now) == set(record["columns"])
    worst = 0.0
    for col, before in record["columns"].items():
        for i, (a, b) in enumerate(zip(before, now[col])):
            assert (a is None) == (b is None), f"{col}[{i}]: {a} before, {b} now"
            if a is not None and max(abs(a), abs(b)) > 0:
                d = abs(a - b) / max(abs(a), abs(b))
                assert d <= RTOL, f"{col}[{i}] ({record['cases'][i]}): {a!r} before, {b!r} now (rel. {d:.2e})"
                worst = max(worst, d)


if __name__ == "__main__" and sys.argv[1:] == ["--regenerate"]:
    s = flagship_summary()
    RECORD.write_text(json.dumps({"study": "studies/zupt_filter_order.toml at 6 min",
                                  "cases": list(s["case"]), "columns": numeric_columns(s)}, indent=1) + "\n")
    print(f"wrote {RECORD}")
