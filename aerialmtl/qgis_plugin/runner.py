"""Run an ``aerialmtl`` command line, follow its JSON progress, stop it on request.

No QGIS here: the algorithm hands in callbacks (progress, messages, "was Cancel pressed?"), and the tests
drive it with plain functions.

The command writes its progress on stderr as one JSON object per line (``aerialmtl --progress json``:
``{"stage", "done", "total", "unit"}``), its errors as one line starting with ``Error:``, its fallbacks as
lines starting with ``warning:``, and its results on stdout. Cancel sends SIGTERM, which aerialmtl handles
like Ctrl-C: the run stops at the next step, removes what it had started to write, and exits with 143.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import IO, Any

#: Seconds to wait after SIGTERM before the process is killed (its clean-up takes well under that).
TERMINATE_GRACE_S = 60.0


@dataclass(frozen=True)
class Progress:
    """One progress line of the command: ``done`` of ``total`` steps of ``stage``."""

    stage: str
    done: int
    total: int | None
    unit: str = ""

    @property
    def percent(self) -> float | None:
        """``done / total`` in percent (0-100), or ``None`` when the total is unknown."""
        if not self.total:
            return None
        return max(0.0, min(100.0, 100.0 * self.done / self.total))


def parse_progress(line: str) -> Progress | None:
    """The :class:`Progress` of a JSON progress line, ``None`` for any other line (or a malformed one)."""
    text = line.strip()
    if not text.startswith("{"):
        return None
    try:
        obj = json.loads(text)
        done = int(obj["done"])
        total = None if obj.get("total") is None else int(obj["total"])
        return Progress(str(obj.get("stage", "")), done, total, str(obj.get("unit", "")))
    except (ValueError, KeyError, TypeError):
        return None


@dataclass
class RunResult:
    """How a command ended.

    Attributes:
        returncode: the exit status (143 after Cancel: SIGTERM).
        canceled: Cancel was pressed and the process was stopped.
        error: the command's one-line error (without ``Error:``), or ``""``.
        stdout: the lines the command printed on stdout (its results).
        warnings: its ``warning:`` lines.
        last_progress: the last progress line seen.
    """

    returncode: int
    canceled: bool = False
    error: str = ""
    stdout: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    last_progress: Progress | None = None

    @property
    def ok(self) -> bool:
        """The command ran to its end."""
        return self.returncode == 0 and not self.canceled

    def message(self) -> str:
        """What to tell the user when the command did not succeed."""
        if self.canceled:  # the command says what it left (predict/tile: nothing; train: whole checkpoints)
            return f"canceled: {self.error}" if self.error else "canceled"
        if self.error:
            return self.error
        return f"aerialmtl ended with exit status {self.returncode}"


def _pump(stream: IO[str], name: str, lines: queue.Queue[tuple[str, str | None]]) -> None:
    """Put every line of ``stream`` on ``lines`` as (name, line), then (name, None) at its end."""
    try:
        for line in stream:
            lines.put((name, line.rstrip("\r\n")))
    finally:
        lines.put((name, None))


def run_command(
    argv: Sequence[str],
    on_progress: Callable[[Progress], None] = lambda p: None,
    on_message: Callable[[str, str], None] = lambda kind, text: None,
    is_canceled: Callable[[], bool] = lambda: False,
    env: dict[str, str] | None = None,
    poll_s: float = 0.1,
    grace_s: float = TERMINATE_GRACE_S,
) -> RunResult:
    """Run ``argv`` to its end (or until ``is_canceled()``), reporting progress and messages as they come.

    Args:
        argv: the command line (:func:`~.spec.command_line`).
        on_progress: called with every progress line.
        on_message: called with ``("info" | "warning" | "error", text)`` for every other line.
        is_canceled: polled every ``poll_s`` seconds; once true, the process gets SIGTERM (and SIGKILL
            after ``grace_s`` seconds if it has not ended by then).
        env: the process environment (default: this one's). ``PYTHONUNBUFFERED=1`` is added so that lines
            arrive when they are written.
        poll_s: how often to check for Cancel.
        grace_s: how long a stopped process may take to clean up.

    Raises:
        OSError: the program could not be started (e.g. ``aerialmtl`` is not installed at that path).
    """
    environment = dict(os.environ if env is None else env)
    environment["PYTHONUNBUFFERED"] = "1"
    popen_kwargs: dict[str, Any] = {}
    if sys.platform == "win32":  # pragma: no cover - the signal group differs on Windows
        popen_kwargs["creationflags"] = subprocess.CREATE_NEW_PROCESS_GROUP
    proc = subprocess.Popen(list(argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                            text=True, encoding="utf-8", errors="replace", bufsize=1, env=environment, **popen_kwargs)
    lines: queue.Queue[tuple[str, str | None]] = queue.Queue()
    assert proc.stdout is not None and proc.stderr is not None
    pumps = [threading.Thread(target=_pump, args=(s, n, lines), daemon=True)
             for s, n in ((proc.stdout, "stdout"), (proc.stderr, "stderr"))]
    for t in pumps:
        t.start()
    result = RunResult(returncode=0)
    open_streams = 2
    stop_sent_at: float | None = None
    while open_streams:
        if stop_sent_at is None and is_canceled():
            result.canceled = True
            stop_sent_at = time.monotonic()
            _terminate(proc)
        elif stop_sent_at is not None and proc.poll() is None and time.monotonic() - stop_sent_at > grace_s:
            proc.kill()
        try:
            name, line = lines.get(timeout=poll_s)
        except queue.Empty:
            continue
        if line is None:
            open_streams -= 1
            continue
        _dispatch(name, line, result, on_progress, on_message)
    result.returncode = proc.wait()
    for t in pumps:
        t.join()
    proc.stdout.close()
    proc.stderr.close()
    return result


def _terminate(proc: subprocess.Popen[str]) -> None:
    """Ask the process to stop the way ``kill``/SLURM do: SIGTERM (CTRL_BREAK on Windows)."""
    if proc.poll() is not None:
        return
    if sys.platform == "win32":  # pragma: no cover
        proc.send_signal(signal.CTRL_BREAK_EVENT)
    else:
        proc.send_signal(signal.SIGTERM)


def _dispatch(name: str, line: str, result: RunResult, on_progress: Callable[[Progress], None],
              on_message: Callable[[str, str], None]) -> None:
    """Sort one output line into progress, an error, a warning or information."""
    if not line.strip():
        return
    progress = parse_progress(line) if name == "stderr" else None
    if progress is not None:
        result.last_progress = progress
        on_progress(progress)
    elif name == "stderr" and line.startswith("Error:"):
        result.error = line[len("Error:"):].strip()
        on_message("error", result.error)
    elif name == "stderr" and line.startswith("warning:"):
        text = line[len("warning:"):].strip()
        result.warnings.append(text)
        on_message("warning", text)
    else:
        if name == "stdout":
            result.stdout.append(line)
        on_message("info", line)
