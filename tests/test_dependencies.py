"""Every library the package imports is one it declares: a fresh virtualenv that installs ``aerialmtl`` (and the
extra a feature names) has every module that feature imports.

Once ``predict --sun auto`` imported pvlib (and pandas under it) while ``pyproject.toml`` declared neither: the
tests passed where both happened to be installed and failed on CI's fresh clone. This reads every ``import`` in
the package's source and maps each third-party module to the distribution that provides it.
"""

from __future__ import annotations

import ast
import re
import sys
from importlib.metadata import packages_distributions, requires
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Modules that no pip distribution provides, with why the package may import them.
NOT_FROM_PIP = {
    "qgis": "QGIS's own Python (the QGIS plugin runs inside QGIS)",
    "processing": "QGIS's own Python (the QGIS plugin runs inside QGIS)",
}


def imported_top_level_modules(package: Path) -> dict[str, str]:
    """``{top-level module: first file importing it}`` for every absolute import in ``package``'s sources."""
    found: dict[str, str] = {}
    for path in sorted(package.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            for name in names:
                found.setdefault(name.split(".")[0], str(path.relative_to(ROOT)))
    return found


def declared_distributions() -> set[str]:
    """Normalised names of the distributions the installed ``aerialmtl`` declares (``pyproject.toml`` as
    installed), required and in every extra."""
    specs = requires("aerialmtl") or []
    return {_normalise(re.split(r"[\s<>=!~\[;(]", spec, maxsplit=1)[0]) for spec in specs}


def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def test_every_third_party_import_is_a_declared_dependency() -> None:
    providers = packages_distributions()
    declared = declared_distributions()
    undeclared = []
    for module, where in imported_top_level_modules(ROOT / "aerialmtl").items():
        if module in sys.stdlib_module_names or module == "aerialmtl" or module in NOT_FROM_PIP:
            continue
        # a module not installed here (an optional extra's) is taken to be its distribution's name
        dists = {_normalise(d) for d in providers.get(module, [module])}
        if not dists & declared:
            undeclared.append(f"{module} ({where}): from {sorted(dists)}, not declared by the installed aerialmtl")
    assert not undeclared, ("the package imports libraries it does not declare (a fresh install lacks them): "
                            + "; ".join(undeclared) + ". Add each to [project] dependencies in pyproject.toml, or "
                            "to the extra of the feature that imports it, and reinstall (pip install -e .)")
