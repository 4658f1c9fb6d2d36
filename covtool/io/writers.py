"""Write a :class:`~covtool.results.StudyResult` to an output directory.

Outputs: ``summary.csv``, one CSV per table, ``<name>.xlsx`` workbook with a
provenance sheet, one PNG per figure, and ``resolved_study.toml``.  Everything
is staged and moved into place atomically (:mod:`covtool.io.atomic`).
"""

from __future__ import annotations

import datetime as _dt
import platform
from pathlib import Path

import tomli_w

from .. import __version__
from ..results import StudyResult
from .atomic import staging_dir
from .workbook import build_workbook


def _toml_safe(obj):
    if isinstance(obj, dict):
        return {str(k): _toml_safe(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, (list, tuple)):
        return [_toml_safe(v) for v in obj]
    if hasattr(obj, "item"):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def provenance_rows(result: StudyResult) -> dict:
    """Provenance key/value rows: tool version, time, platform, resolved study."""
    rows = {
        "tool": "covtool",
        "tool_version": __version__,
        "study": result.name,
        "kind": result.kind,
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "platform": platform.platform(),
    }
    rows.update(result.provenance)
    rows["resolved_study"] = tomli_w.dumps(_toml_safe(result.resolved))
    return rows


def write_outputs(result: StudyResult, out_dir, *, figures: bool = True) -> list[Path]:
    """Write all outputs of ``result`` into ``out_dir``; return the file paths."""
    out_dir = Path(out_dir)
    written = []
    with staging_dir(out_dir) as stage:
        for name, df in result.tables.items():
            df.to_csv(stage / f"{name}.csv", index=False)
        build_workbook(result.tables, provenance_rows(result), result.charts, path=stage / f"{result.name}.xlsx")
        (stage / "resolved_study.toml").write_text(
            f"# resolved by covtool {__version__}\n" + tomli_w.dumps(_toml_safe(result.resolved)), encoding="utf-8")
        if figures and result.figures:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
            for name, make in result.figures.items():
                fig = make()
                fig.savefig(stage / f"{name}.png", dpi=120, bbox_inches="tight")
                plt.close(fig)
        written = [out_dir / p.relative_to(stage) for p in sorted(stage.rglob("*")) if p.is_file()]
    return written
