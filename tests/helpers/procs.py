"""``aerialmtl`` run as a user runs it: a separate process (``python -m aerialmtl``), optionally as another user."""

from __future__ import annotations

import functools
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path

import pytest

#: The repository root (put first on the subprocess's PYTHONPATH, so that it runs this tree).
ROOT = Path(__file__).resolve().parents[2]
#: The unprivileged account the permission cases run as (``nobody``, which every Linux has).
OTHER_UID = 65534
#: ``setpriv`` arguments that drop the capabilities by which root ignores file permissions (read, write, search,
#: unlink in a sticky folder): root then meets permissions as the owner uid 0, like any user.
NO_OVERRIDE = ["setpriv", "--bounding-set", "-dac_override,-dac_read_search,-fowner"]
#: What a process run as another user must be able to import for the permission cases to mean anything.
PROBE = "import click, numpy, rasterio, torch, aerialmtl.cli, aerialmtl.inference.jobs"


@functools.cache
def unprivileged_prefix() -> tuple[list[str], int] | None:
    """How to run a process without root's permission overrides, and the uid whose files it may not write:
    as ``nobody`` where ``nobody`` can run this interpreter (files of root are then foreign), else as root without
    its override capabilities (files of ``nobody`` are then foreign; the interpreter may sit under ``/root``,
    mode 0700); ``None`` where neither works (not root, no ``setpriv``).
    """
    if not hasattr(os, "geteuid") or os.geteuid() != 0 or shutil.which("setpriv") is None:
        return None
    as_nobody = ["setpriv", f"--reuid={OTHER_UID}", f"--regid={OTHER_UID}", "--clear-groups"]
    # The probe imports what a predict run imports, with a HOME of its own as the tests give: an interpreter that
    # starts is not enough (CI's site-packages may be unreadable to nobody while its python binary is not).
    with tempfile.TemporaryDirectory(prefix="aerialmtl-probe-") as home:
        os.chmod(home, 0o1777)
        for prefix, foreign in ((as_nobody, 0), (NO_OVERRIDE, OTHER_UID)):
            probe = subprocess.run([*prefix, sys.executable, "-c", PROBE], capture_output=True, timeout=120,
                                   env=env(HOME=home), cwd=home, check=False)
            if probe.returncode == 0:
                return prefix, foreign
    return None


def env(**extra: str) -> dict[str, str]:
    """The environment of a subprocess: this one, this tree first on the path, one thread, plus ``extra``."""
    out = dict(os.environ)
    out.update(PYTHONPATH=os.pathsep.join([str(ROOT), out.get("PYTHONPATH", "")]).rstrip(os.pathsep),
               OMP_NUM_THREADS="1", AERIALMTL_PROGRESS="json")
    out.update(extra)
    return out


def aerialmtl(*args: object, environ: Mapping[str, str] | None = None, timeout: float = 600,
              as_other_user: bool = False, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """``python -m aerialmtl ARGS`` in a new process; ``as_other_user`` runs it without root's permission overrides
    (:func:`unprivileged_prefix`; call :func:`other_user_or_skip` first). A run that exceeds ``timeout`` raises
    ``subprocess.TimeoutExpired`` (a hang).
    """
    cmd = [sys.executable, "-m", "aerialmtl", *map(str, args)]
    if as_other_user:
        found = unprivileged_prefix()
        assert found is not None, "call other_user_or_skip() first"
        cmd = [*found[0], *cmd]
    return subprocess.run(cmd, capture_output=True, text=True, env=dict(environ or env()), timeout=timeout,
                          cwd=cwd, check=False)


def other_user_or_skip() -> int:
    """The uid whose files a process run ``as_other_user`` may not write (see :func:`unprivileged_prefix`); skips
    the test where no such process can be run (not root, or no util-linux ``setpriv``).
    """
    found = unprivileged_prefix()
    if found is None:
        pytest.skip("needs root and util-linux's setpriv to run a process without root's permission overrides")
    return found[1]


def one_line(text: str) -> str:
    """``text`` with every run of white space as one space (messages wrap in terminals)."""
    return " ".join(text.split())
