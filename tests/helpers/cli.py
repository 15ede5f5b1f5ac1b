"""The ``aerialmtl`` command run in-process, as the console script runs it."""

from __future__ import annotations

import pytest


def run_cli(capsys: pytest.CaptureFixture, *args: object) -> tuple[int, str, str]:
    """Run ``aerialmtl ARGS`` in-process like the console script; returns (exit code, stdout, stderr)."""
    from aerialmtl.cli import main

    capsys.readouterr()
    try:
        main([str(a) for a in args])
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out, err = capsys.readouterr()
    return code, out, err
