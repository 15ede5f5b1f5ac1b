"""Progress reporting: tqdm bars for people, or one JSON line per step for programs.

Every long loop of aerialmtl (tiling patches, caching them, training steps, predicted windows, building
blocks, evaluated bands) reports through :func:`tqdm` (or :func:`tqdm_auto`), which returns a normal tqdm
bar by default. In **JSON mode** (``aerialmtl --progress json CMD ...``, or ``AERIALMTL_PROGRESS=json`` in
the environment, e.g. for processes started by ``torchrun``) the bar is not drawn; instead every step
writes one line to stderr, for a program that runs the command (the QGIS plugin reads it)::

    {"stage": "train", "done": 12, "total": 600, "unit": "step"}

``stage`` is the bar's description (``tiling``, ``caching train patches``, ``train``, the orthophoto's file
name for ``predict``, ``buildings``, ``evaluate``), ``done`` the steps finished so far, ``total`` the number
of steps of that stage (``null`` when it is not known in advance). A stage starts with a line with
``done`` 0 and its last line has ``done`` equal to ``total`` when it ran to its end. A command may run
several stages one after the other; lines of other kinds (results, ``warning: ...``, ``Error: ...``) never
start with ``{``. ``--quiet`` silences both kinds.

A stage that needs saying what it does before its bar starts (e.g. ``train``'s calibration, feature density
and sun fit after the steps) writes one line with :func:`announce`, through tqdm in bar mode (so it does not
break a bar that is drawn) and as plain text in JSON mode; nothing when progress is off.
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
import threading
from collections.abc import Iterable, Iterator
from typing import Any

from tqdm.auto import tqdm as _auto_tqdm
from tqdm.std import tqdm as _std_tqdm

#: The progress modes: ``bar`` (tqdm bars on stderr) and ``json`` (one JSON line per step on stderr).
MODES = ("bar", "json")
#: Environment variable holding the default mode (read by the command line's ``--progress`` option).
PROGRESS_ENV = "AERIALMTL_PROGRESS"

_mode = "bar"
_write_lock = threading.Lock()


def set_mode(mode: str) -> str:
    """Report progress as ``mode`` (one of :data:`MODES`) from now on; returns the previous mode.

    Raises:
        ValueError: ``mode`` is not one of :data:`MODES`.
    """
    global _mode
    if mode not in MODES:
        raise ValueError(f"progress mode must be one of {', '.join(MODES)}, got {mode!r}")
    previous, _mode = _mode, mode
    return previous


def get_mode() -> str:
    """The current progress mode (see :func:`set_mode`)."""
    return _mode


def progress_line(stage: str, done: int, total: int | None, unit: str) -> str:
    """One JSON progress line (without the newline): ``{"stage", "done", "total", "unit"}``."""
    return json.dumps({"stage": stage, "done": done, "total": total, "unit": unit}, ensure_ascii=False)


class JsonBar(_std_tqdm):
    """A tqdm bar that draws nothing and writes one JSON line (:func:`progress_line`) to stderr per step.

    It takes tqdm's arguments, counts like tqdm (``update``, iteration, ``initial``) and writes a line when
    it starts, after every step and, if steps were counted since the last line, when it closes.
    """

    def __init__(self, iterable: Iterable[Any] | None = None, *args: Any, **kwargs: Any) -> None:
        kwargs["file"] = io.StringIO()  # tqdm's own drawing goes nowhere
        self._emitted: int | None = None
        super().__init__(iterable, *args, **kwargs)
        if not self.disable:
            self._emit()

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        """Draw nothing (tqdm calls this to redraw the bar)."""
        return True

    def _emit(self) -> None:
        total = None if self.total is None else int(self.total)
        line = progress_line(str(self.desc or ""), int(self.n), total, str(self.unit))
        with _write_lock:
            sys.stderr.write(line + "\n")
            sys.stderr.flush()
        self._emitted = int(self.n)

    def update(self, n: float | None = 1) -> bool | None:
        """Count ``n`` more steps and write their line."""
        shown = super().update(n)
        if not self.disable and n:
            self._emit()
        result: bool | None = shown
        return result

    def __iter__(self) -> Iterator[Any]:
        if self.disable:
            yield from self.iterable
            return
        try:
            for obj in self.iterable:
                yield obj
                self.update(1)
        finally:
            self.close()

    def close(self) -> None:
        """Write a last line if steps were counted since the previous one, then close the bar."""
        if not self.disable and self._emitted is not None and self._emitted != int(self.n):
            self._emit()
        super().close()


@contextlib.contextmanager
def above_bars() -> Iterator[None]:
    """Write to stderr inside this block without landing on a progress bar's line: in bar mode the bars on screen
    are cleared first and drawn again after (``tqdm.external_write_mode``), in JSON mode the block holds the lock
    the JSON lines are written under (never inside one). For whole lines only.
    """
    if _mode == "json":
        with _write_lock:
            yield
        return
    with _std_tqdm.external_write_mode(file=sys.stderr):
        yield


def announce(message: str, enabled: bool = True) -> None:
    """Write ``message`` as one line on stderr (the line that starts a stage; see the module docstring), above
    any bar on screen (:func:`above_bars`).

    Nothing when ``enabled`` is false (``--quiet``, or a process other than rank 0). A message that starts with
    ``{`` gets a space before it, so it can never be read as a JSON progress line.
    """
    if not enabled:
        return
    line = " " + message if message.startswith("{") else message
    with above_bars():
        sys.stderr.write(line + "\n")
        sys.stderr.flush()


def tqdm(iterable: Iterable[Any] | None = None, *args: Any, **kwargs: Any) -> Any:
    """A console tqdm bar (``tqdm.tqdm``), or a :class:`JsonBar` in JSON mode; same arguments."""
    cls = JsonBar if _mode == "json" else _std_tqdm
    return cls(iterable, *args, **kwargs)


def tqdm_auto(iterable: Iterable[Any] | None = None, *args: Any, **kwargs: Any) -> Any:
    """A ``tqdm.auto`` bar (a widget in notebooks), or a :class:`JsonBar` in JSON mode; same arguments."""
    cls = JsonBar if _mode == "json" else _auto_tqdm
    return cls(iterable, *args, **kwargs)
