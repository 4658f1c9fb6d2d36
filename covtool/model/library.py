"""The model library: ``models/*.toml`` found by name."""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd

from ..errors import ModelFileError
from .loader import load_model


def default_model_dir() -> Path:
    """The ``models/`` directory: ``$COVTOOL_MODELS``, else ``./models``, else the repo's."""
    env = os.environ.get("COVTOOL_MODELS")
    if env:
        return Path(env)
    cwd = Path.cwd() / "models"
    if cwd.is_dir():
        return cwd
    return Path(__file__).resolve().parents[2] / "models"


def model_files(directory=None) -> list[Path]:
    """All truth-model files in the library (filter declarations live in ``models/filters``)."""
    d = Path(directory) if directory else default_model_dir()
    return sorted(p for p in d.glob("*.toml"))


def resolve_model_path(name_or_path, directory=None, *, base_dir=None) -> Path:
    """Find a model by name (``sdins58``) or path (``models/sdins58.toml``)."""
    p = Path(name_or_path)
    candidates = []
    if p.suffix == ".toml":
        candidates += [p] + ([Path(base_dir) / p] if base_dir else [])
        candidates += [Path(base_dir) / ".." / p] if base_dir else []
    d = Path(directory) if directory else default_model_dir()
    candidates.append(d / f"{name_or_path}.toml")
    if base_dir:
        candidates.append(Path(base_dir).parent / "models" / f"{name_or_path}.toml")
    for c in candidates:
        if c.is_file():
            return c
    raise ModelFileError(str(name_or_path), f"no such model (looked in {d})")


def load_model_by_name(name_or_path, directory=None, *, base_dir=None):
    """Load a library model by name or path."""
    return load_model(resolve_model_path(name_or_path, directory, base_dir=base_dir))


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
