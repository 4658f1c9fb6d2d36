"""Study runners: one module per study kind, named as the kind, dispatched on ``[study] kind``.

A runner module exposes ``run(decl: dict, *, path: Path | None, progress: bool)
-> StudyResult``.  Runners compute only; :mod:`covtool.io.writers` writes.
"""

from __future__ import annotations

import copy
import importlib
import inspect
import os
from pathlib import Path

from covtool.errors import InputError, StudyFileError
from covtool.io.config import load_toml

#: study kinds; each runs in the module of the same name, ``covtool.studies.<kind>`` (imported lazily)
KINDS = ("pure_ins", "zupt_filter_order", "ad_reset", "zupt_sensitivity", "error_budget", "trade_grid", "monte_carlo",
         "dual_imu", "magnitude_sweep", "aided")
#: study kind -> runner module
RUNNERS = {kind: f"covtool.studies.{kind}" for kind in KINDS}
#: kinds whose runners parse their own files (covtool.studies.aided, ad_reset_config, dual_imu_config)
OWN_PARSER = ("aided", "ad_reset", "dual_imu")


def load_study(path_or_dict):
    """Return ``(declaration dict, path or None)``."""
    if isinstance(path_or_dict, dict):
        return copy.deepcopy(path_or_dict), None
    path = Path(path_or_dict)
    return load_toml(path, StudyFileError), path


def run_study(path_or_dict, *, progress: bool = False, backend=None, store=None, resume: bool = False,
              **overrides):
    """Run a study declaration; see :func:`covtool.run_study`.

    ``backend`` (a :mod:`covtool.parallel` backend), ``store`` (directory of
    the incremental result store) and ``resume`` are passed to runners whose
    ``run`` accepts them.  ``store`` is a hint and is dropped for the
    others; asking such a runner for a backend or a resume is an error.
    """
    decl, path = load_study(path_or_dict)
    where = str(path) if path else "<study>"
    study = decl.get("study")
    if not isinstance(study, dict) or "kind" not in study:
        raise StudyFileError(where, "missing [study] table with a 'kind' key "
                             f"(one of: {', '.join(sorted(RUNNERS))})")
    for k, v in overrides.items():
        study[k] = v
    kind = study["kind"]
    if not isinstance(kind, str) or kind not in RUNNERS:
        raise StudyFileError(f"{where}: [study]", f"unknown kind {kind!r} (one of: {', '.join(sorted(RUNNERS))})")
    # the whole file parsed once into its kind's typed configuration, before any computation:
    # every section is refused here, one line naming the file, the table and the key.  The kinds in
    # OWN_PARSER still validate their files with their own parsers (same rules, their messages name a
    # measurement or a board table their way) before computing anything; they take no configuration yet
    from covtool.studies.config import load_config

    config = None if kind in OWN_PARSER else load_config(decl, where)
    module = importlib.import_module(RUNNERS[kind])
    accepts = inspect.signature(module.run).parameters
    options = {k: v for k, v in (("backend", backend), ("store", store), ("resume", resume))
               if v not in (None, False) and k in accepts}
    if "config" in accepts and config is not None:
        options["config"] = config
    refused = [k for k, v in (("backend", backend), ("resume", resume)) if v not in (None, False) and k not in accepts]
    if refused:
        raise InputError(f"{where}: [study] kind", f"{kind!r} runs in-process in one piece; it takes no "
                         f"{' or '.join(refused)} (--workers, --scheduler, --resume)")
    with one_blas_thread():
        result = module.run(decl, path=path, progress=progress, **options)
    if path is not None:
        result.resolved = absolute_paths(result.resolved, path.parent)
    return result


def one_blas_thread():
    """The BLAS thread pool limited to one thread, for the duration of a study.

    The one place the pool is limited in-process (worker processes limit
    theirs in :mod:`covtool.parallel`): covtool's matrices are small to
    medium (n ≤ 116), and OpenBLAS's thread pool was measured 3–30× slower
    than one thread for them on a loaded two-core machine; parallelism comes
    from processes instead.  Used by :func:`run_study` and by
    ``covtool dualnav`` (:func:`covtool.studies.dual_imu.compare_logs`).

    Returns
    -------
    threadpoolctl.threadpool_limits
        A context manager.
    """
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=1, user_api="blas")


def absolute_paths(decl: dict, base_dir) -> dict:
    """A copy of a study declaration with its input-file paths made absolute.

    Relative paths resolve against ``base_dir`` (the study file's
    directory), as the runners resolve them, so that the resolved study
    written beside the results re-runs from anywhere.  Library names
    (``"sdins58"``) stay names.
    """
    from covtool.io.config import is_library_name

    out = copy.deepcopy(decl)

    def absolute(v, library):
        if isinstance(v, str) and v.strip() and not (library and is_library_name(v)):
            p = Path(v).expanduser()
            return str(Path(os.path.abspath(p if p.is_absolute() else Path(base_dir) / p)))
        return v

    def fix(tab, key, library):
        v = tab.get(key) if isinstance(tab, dict) else None
        if isinstance(v, list):
            tab[key] = [absolute(x, library) for x in v]
        elif v is not None:
            tab[key] = absolute(v, library)

    fix(out.get("truth"), "model", True)
    fix(out.get("filters"), "file", True)   # a bare name is a filter file of the library
    fix(out.get("trajectory"), "csv", False)
    imu = out.get("imu")
    if isinstance(imu, dict):
        for key in ("main", "kimu"):
            fix(imu.get(key), "grade", True)
    return out

