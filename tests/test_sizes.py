"""The package stays readable: no module of ``aerialmtl/`` over 600 lines, no function over 80 (issue 60).

A module or function that grows past its size is split along its concepts (one concept per module,
``docs/CONTRACTS.md``), not by line count. None is over now; one that must stay over for a while (a split
under way) is named below with its size, may only shrink, and leaves its list once it is within the limit (the
check says so).
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "aerialmtl"
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80

#: Modules still over :data:`MAX_MODULE_LINES` (path under the repository root → most lines allowed now).
MODULES_STILL_OVER: dict[str, int] = {}
#: Functions still over :data:`MAX_FUNCTION_LINES` (``path::qualified name`` → most lines allowed now).
FUNCTIONS_STILL_OVER: dict[str, int] = {}


def _modules() -> dict[str, Path]:
    root = PACKAGE.parent
    return {p.relative_to(root).as_posix(): p for p in sorted(PACKAGE.rglob("*.py"))}


def module_lines() -> dict[str, int]:
    """Lines of every module of the package, by path under the repository root."""
    return {name: len(path.read_text(encoding="utf-8").splitlines()) for name, path in _modules().items()}


def function_lines() -> dict[str, int]:
    """Lines of every function and method (``def`` to its last line, decorators not counted).

    Keyed ``path::Class.method`` (nested functions: ``path::outer.inner``).
    """
    out: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str, name: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                qual = f"{prefix}.{child.name}" if prefix else child.name
                if not isinstance(child, ast.ClassDef):
                    out[f"{name}::{qual}"] = (child.end_lineno or child.lineno) - child.lineno + 1
                visit(child, qual, name)
            else:
                visit(child, prefix, name)

    for name, path in _modules().items():
        visit(ast.parse(path.read_text(encoding="utf-8"), str(path)), "", name)
    return out


def _check(sizes: dict[str, int], limit: int, still_over: dict[str, int], what: str) -> list[str]:
    """What is over ``limit`` (or over its size in ``still_over``), and what ``still_over`` names needlessly."""
    problems = []
    for name, n in sorted(sizes.items()):
        if name not in still_over and n > limit:
            problems.append(f"{name} has {n} lines, over {limit}: split it along its concepts")
        elif name in still_over and n > still_over[name]:
            problems.append(f"{name} grew to {n} lines (at most {still_over[name]} until it is split below {limit}): "
                            "split it along its concepts")
    for name in sorted(still_over):
        n = sizes.get(name)
        if n is None or n <= limit:
            problems.append(f"{name} is {'gone' if n is None else f'{n} lines'}: remove it from {what} in "
                            "tests/test_sizes.py")
    return problems


def test_no_module_of_the_package_passes_600_lines() -> None:
    problems = _check(module_lines(), MAX_MODULE_LINES, MODULES_STILL_OVER, "MODULES_STILL_OVER")
    assert not problems, "\n".join(problems)


def test_no_function_of_the_package_passes_80_lines() -> None:
    problems = _check(function_lines(), MAX_FUNCTION_LINES, FUNCTIONS_STILL_OVER, "FUNCTIONS_STILL_OVER")
    assert not problems, "\n".join(problems)
