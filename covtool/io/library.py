"""The model library: ``models/*.toml`` found by name."""

from __future__ import annotations

import importlib.resources
import os
from pathlib import Path

import pandas as pd

from covtool.errors import ModelFileError
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
    """One row per model file: name, states, description, file."""
    rows = []
    for p in model_files(directory):
        try:
            m = load_model(p)
            rows.append({"model": m.name, "states": m.n, "description": m.description, "file": str(p)})
        except ModelFileError as exc:
            rows.append({"model": p.stem, "states": 0, "description": f"INVALID: {exc}", "file": str(p)})
    return pd.DataFrame(rows)


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
