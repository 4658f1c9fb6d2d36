"""The model library: truth models, filters and IMU grades, found by name."""

from __future__ import annotations

import importlib.resources
import os
from pathlib import Path

import pandas as pd

from covtool.errors import InputError, ModelFileError
from covtool.io.config import is_library_name, resolve_input
from covtool.io.model_file import load_model


def default_model_dir() -> Path:
    """The model library: ``$COVTOOL_MODELS``, else the package data ``covtool.models``.

    The repository's top-level ``models/`` folder ships as the package
    ``covtool.models`` (``pip install .`` or ``pip install -e .``) and is
    found with :func:`importlib.resources.files`; a source checkout used
    without installing (``PYTHONPATH``) falls back to the ``models/``
    beside the ``covtool`` package.  Never the current directory: a study
    must give the same answer wherever it is run from.  A path given in a
    study or filter file resolves against that file's folder
    (:func:`resolve_model_path`) and comes before the library.
    """
    env = os.environ.get("COVTOOL_MODELS")
    if env:
        return Path(env)
    try:
        return Path(str(importlib.resources.files("covtool.models")))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / "models"


def model_files(directory=None) -> list[Path]:
    """All truth-model files in the library (filter declarations live in ``models/filters``)."""
    d = Path(directory) if directory else default_model_dir()
    return sorted(p for p in d.glob("*.toml"))


def resolve_model_path(name_or_path, directory=None, *, base_dir=None, where=None) -> Path:
    """Absolute path of a model given by library name or by path.

    Parameters
    ----------
    name_or_path : str or Path
        A bare library name (``"sdins58"``: no suffix, no separator) is
        looked up in ``directory`` (default :func:`default_model_dir`).
        Anything else is a path; a relative one resolves against
        ``base_dir``, the directory of the file that names it (the current
        directory only when no file names it: the command line, a dict).
    where : str, optional
        Error-message location (default: the name itself).

    Raises
    ------
    ModelFileError
        No such model, naming where it looked.
    """
    w = where or str(name_or_path)
    if isinstance(name_or_path, Path):
        name_or_path = str(name_or_path)
    if not isinstance(name_or_path, str) or not name_or_path.strip():
        raise ModelFileError(w, f"{name_or_path!r} is not a model name or file")
    if is_library_name(name_or_path):
        d = Path(directory) if directory else default_model_dir()
        c = d / f"{name_or_path}.toml"
        if c.is_file():
            return Path(os.path.abspath(c))
        known = ", ".join(p.stem for p in model_files(d)) or "none"
        raise ModelFileError(w, f"no such model {name_or_path!r} in the library {str(d)!r} (known: {known}); "
                             "a file needs a path, e.g. 'm.toml'")
    return resolve_input(name_or_path, base_dir, w, ModelFileError, what="model file")


def load_model_by_name(name_or_path, directory=None, *, base_dir=None, where=None):
    """Load a library model by name or path (see :func:`resolve_model_path`)."""
    return load_model(resolve_model_path(name_or_path, directory, base_dir=base_dir, where=where))


def list_models(directory=None) -> pd.DataFrame:
    """The library's contents: truth models, filters and IMU grades, one row each.

    Parameters
    ----------
    directory : path, optional
        The library (default :func:`default_model_dir`): ``*.toml`` truth
        models, ``filters/*.toml`` filter files, ``imu/*.toml`` IMU grades.

    Returns
    -------
    pandas.DataFrame
        Columns ``kind`` (``"truth model"``, ``"filter"``, ``"IMU grade"``),
        ``name``, ``states`` (of the truth model, kept by the filter, of the
        grade's error model), ``description`` and ``file``.  A filter file
        that names no truth (it projects whichever truth a study runs) is
        listed against the library's first valid truth model.  A file that does
        not validate is listed once, its description ``INVALID:`` and the
        error.
    """
    from covtool.io.config import load_toml
    from covtool.io.filters import load_filters
    from covtool.io.imu_grade import load_imu_grade

    d = Path(directory) if directory else default_model_dir()
    rows = []

    def row(kind, name, states, description, path):
        rows.append({"kind": kind, "name": name, "states": states, "description": description, "file": str(path)})

    for p in model_files(d):
        try:
            m = load_model(p)
            row("truth model", m.name, m.n, m.description, p)
        except InputError as exc:
            row("truth model", p.stem, 0, f"INVALID: {exc}", p)
    truths = [r["name"] for r in rows if not r["description"].startswith("INVALID")]
    for p in sorted((d / "filters").glob("*.toml")):
        try:
            decl = load_toml(p, ModelFileError)
            named = {f["truth"] for f in decl.get("filter", []) if isinstance(f, dict) and "truth" in f}
            if len(named) > 1:
                raise ModelFileError(f"{p}: truth", f"the filters name {len(named)} truth models "
                                     f"({', '.join(sorted(map(repr, named)))}); listing needs one")
            # a file that names no truth projects whichever truth a study runs: listed against the library's first
            name = named.pop() if named else (truths[0] if truths else None)
            if name is None:
                raise ModelFileError(str(p), "no valid truth model in the library to project the filters of")
            truth = load_model_by_name(name, d, base_dir=p.parent, where=f"{p}: truth")
            for fname, spec in load_filters(p, truth).items():
                row("filter", fname, len(spec.kept), f"{spec.description} (of {truth.name})", p)
        except InputError as exc:
            row("filter", p.stem, 0, f"INVALID: {exc}", p)
    for p in sorted((d / "imu").glob("*.toml")):
        try:
            g = load_imu_grade(str(p))
            row("IMU grade", g.name, g.to_model().n, g.description, p)
        except InputError as exc:
            row("IMU grade", p.stem, 0, f"INVALID: {exc}", p)
    return pd.DataFrame(rows, columns=["kind", "name", "states", "description", "file"])


def markdown_table(model) -> str:
    """The state table of ``model`` as a Markdown table (for docs/)."""
    df = model.state_table()
    lines = ["| # | state | symbol | meaning | 1σ | unit | process | τ / distance | source |",
             "|---|---|---|---|---|---|---|---|---|"]
    for i, r in df.iterrows():
        corr = ""
        if r["tau [s]"] == r["tau [s]"]:
            corr = f"τ = {r['tau [s]']:g} s"
        elif r["corr. distance [m]"] == r["corr. distance [m]"]:
            corr = f"d = {r['corr. distance [m]'] / 1000:g} km"
        lines.append(f"| {i + 1} | `{r['state']}` | {r['symbol']} | {r['meaning']} | {r['sigma']:.4g} | "
                     f"{r['unit'] or '–'} | {r['process']} | {corr or '–'} | {r['source']} |")
    return "\n".join(lines) + "\n"
