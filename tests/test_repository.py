"""The clone holds what the repository means to hold: no test output, report or run folder at its root.

A test that wrote into the working directory once left ``report.json``, ``report.md`` and two plots at the
root, and they were committed: a newcomer saw them in the clone. Two checks keep that from coming back:
the committed top-level entries are exactly those listed here (a new one is added here, on purpose), and
:func:`conftest.pytest_sessionfinish` fails a run whose tests left a new file or folder at the root.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: What the repository means to hold at its top level (files and folders tracked by git).
TOP_LEVEL = frozenset({
    ".ci", ".gitignore", "LICENSE", "README.md", "pyproject.toml", "mkdocs.yml", "docs_hooks.py",
    "aerialmtl", "bench", "configs", "docs", "experiments", "notebooks", "samples", "tests",
})


def tracked_top_level() -> set[str]:
    """The first path component of every file git tracks in this checkout."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout (an sdist or an unpacked copy): nothing tracked to check")
    out = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z"], capture_output=True, check=True).stdout
    return {p.split("/", 1)[0] for p in out.decode().split("\0") if p}


def test_the_clone_root_holds_only_what_the_repository_means_to_hold() -> None:
    extra = sorted(tracked_top_level() - TOP_LEVEL)
    assert not extra, (f"committed at the repository root but not meant to be there: {extra}; if it is test or "
                       "run output, `git rm` it and make the code that wrote it write into tmp_path; if it "
                       "belongs, add it to TOP_LEVEL in tests/test_repository.py")
