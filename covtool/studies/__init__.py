"""Study runners: one module per study kind, dispatched on ``[study] kind``.

A runner module exposes ``run(decl: dict, *, path: Path | None, progress: bool)
-> StudyResult``.  Runners compute only; :mod:`covtool.io.writers` writes.
"""

from __future__ import annotations

import copy
import importlib
from pathlib import Path

from ..errors import StudyFileError
from ..io.config import load_toml

#: study kind -> runner module (imported lazily)
RUNNERS = {
    "pure_ins": "covtool.studies.nav_covariance",
    "zupt_filter_order": "covtool.studies.zupt",
    "ad_reset": "covtool.studies.ad_reset",
    "zupt_sensitivity": "covtool.studies.sensitivity",
    "error_budget": "covtool.studies.budget",
    "trade_grid": "covtool.studies.trade",
    "monte_carlo": "covtool.studies.monte_carlo",
    "dual_imu": "covtool.studies.dual_imu",
}


def load_study(path_or_dict):
    """Return ``(declaration dict, path or None)``."""
    if isinstance(path_or_dict, dict):
        return copy.deepcopy(path_or_dict), None
    path = Path(path_or_dict)
    return load_toml(path, StudyFileError), path


def run_study(path_or_dict, *, progress: bool = False, **overrides):
    """Run a study declaration; see :func:`covtool.run_study`."""
    decl, path = load_study(path_or_dict)
    where = str(path) if path else "<study>"
    study = decl.get("study")
    if not isinstance(study, dict) or "kind" not in study:
        raise StudyFileError(where, "missing [study] table with a 'kind' key "
                             f"(one of: {', '.join(sorted(RUNNERS))})")
    for k, v in overrides.items():
        study[k] = v
    kind = study["kind"]
    if kind not in RUNNERS:
        raise StudyFileError(f"{where}: [study]", f"unknown kind {kind!r} (one of: {', '.join(sorted(RUNNERS))})")
    module = importlib.import_module(RUNNERS[kind])
    return module.run(decl, path=path, progress=progress)
