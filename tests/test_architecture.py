"""The house plan holds: imports run one way and the numeric core reads no files.

The contracts are declared in ``pyproject.toml`` (``[tool.importlinter]``)
and checked with import-linter over the whole import graph, indirect
imports included: ``nav <- lincov <- analysis <- validation | dualnav <-
plotting <- studies <- cli``; ``io`` is imported by ``studies`` and ``cli``
only; ``board`` is independent of the covariance analysis; the execution
backends know no study.  A second test keeps every subpackage inside the
plan, so a new folder cannot slip past the contracts.
"""

from __future__ import annotations

import pkgutil
import tomllib
from pathlib import Path

import covtool

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = ROOT / "pyproject.toml"


def test_import_contracts_are_kept(capsys):
    import importlinter.api  # noqa: F401  (configures import-linter's adapters)
    from importlinter.application.use_cases import lint_imports

    ok = lint_imports(config_filename=str(PYPROJECT), cache_dir=None, no_logo=True)
    report = capsys.readouterr().out
    assert ok, report
    assert "0 broken" in report


def test_every_part_of_the_package_is_in_a_contract():
    cfg = tomllib.loads(PYPROJECT.read_text())["tool"]["importlinter"]
    named = set()
    for c in cfg["contracts"]:
        for layer in c.get("layers", []):
            named |= {m.strip() for m in layer.replace(":", "|").split("|")}
        named |= set(c.get("source_modules", [])) | set(c.get("forbidden_modules", []))
    parts = {f"covtool.{m.name}" for m in pkgutil.iter_modules(covtool.__path__)} - {"covtool.__main__"}
    assert parts - named == set(), f"outside every import contract: {sorted(parts - named)}"
    assert named - parts == set(), f"contracts name modules that do not exist: {sorted(named - parts)}"


def test_every_package_ships():
    """``[tool.setuptools] packages`` lists every folder of the package and the model library."""
    cfg = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]
    on_disk = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "covtool").rglob("__init__.py")}
    mapped = {pkg for pkg, folder in cfg["package-dir"].items() if (ROOT / folder / "__init__.py").is_file()}
    assert set(cfg["packages"]) == on_disk | mapped
    assert mapped == {"covtool.models", "covtool.models.filters", "covtool.models.imu"}
    for pkg in mapped:
        assert list((ROOT / cfg["package-dir"][pkg]).glob("*.toml")), pkg
        assert cfg["package-data"][pkg] == ["*.toml"]
