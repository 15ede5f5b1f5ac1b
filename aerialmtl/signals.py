"""Stop signals: SIGTERM and SIGHUP end a run the way Ctrl-C does.

``timeout``, SLURM, ``kill`` and closing a terminal send SIGTERM or SIGHUP. Python's default for them is
to end the process at once, skipping every ``finally``: hidden staging files stay behind and a tile folder
is left half made. :func:`install_stop_signals` turns them into :class:`Stopped`, a
:class:`KeyboardInterrupt`, so every clean-up that handles Ctrl-C handles them too (staging files removed,
the last whole checkpoint kept) and the command line ends with the Ctrl-C message and exit code
``128 + signal`` (143 for SIGTERM, 129 for SIGHUP, 130 for Ctrl-C).

Python runs signal handlers in the main thread only; the reader and writer threads of ``predict`` keep
going until the main thread, interrupted, shuts them down in its clean-up (as for Ctrl-C).

Under ``torchrun`` a SIGTERM usually means that torchrun stops the survivors because another process
failed; :func:`install_stop_signals` with ``distributed=True`` raises
:class:`~aerialmtl.errors.PeerFailure` for it instead, whose message says so.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from types import FrameType
from typing import Any

#: The signals handled like Ctrl-C (SIGHUP does not exist on Windows).
STOP_SIGNALS: tuple[int, ...] = tuple(
    s for s in (getattr(signal, "SIGTERM", None), getattr(signal, "SIGHUP", None)) if s is not None)


class Stopped(KeyboardInterrupt):
    """The process received a stop signal (SIGTERM, SIGHUP, or SIGINT for Ctrl-C).

    Attributes:
        signum: the signal number.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum

    @property
    def exit_code(self) -> int:
        """The shell's exit code of a process ended by this signal: ``128 + signum``."""
        return 128 + self.signum


def _raise_stopped(signum: int, frame: FrameType | None) -> None:
    raise Stopped(signum)


def install_stop_signals(distributed: bool = False,
                         on_peer_stop: Callable[[], BaseException] | None = None) -> bool:
    """Make SIGTERM and SIGHUP raise :class:`Stopped` in the main thread.

    Args:
        distributed: this process is one of a torchrun job: SIGTERM raises ``on_peer_stop()`` (torchrun
            stops the survivors of a failed job with it).
        on_peer_stop: the exception to raise for SIGTERM in a distributed run.

    Returns:
        False when called outside the main thread (nothing installed; Python allows handlers only there).
    """
    if threading.current_thread() is not threading.main_thread():
        return False
    def _peer_stop(signum: int, frame: FrameType | None) -> None:
        assert on_peer_stop is not None
        raise on_peer_stop()

    for signum in STOP_SIGNALS:
        peer = distributed and on_peer_stop is not None and signum == getattr(signal, "SIGTERM", None)
        signal.signal(signum, _peer_stop if peer else _raise_stopped)
    return True


@contextlib.contextmanager
def stop_signals() -> Iterator[None]:
    """:func:`install_stop_signals` for the block, the previous handlers restored after it."""
    previous: dict[int, Any] = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    installed = install_stop_signals()
    try:
        yield
    finally:
        if installed:
            for signum, handler in previous.items():
                signal.signal(signum, handler)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Hold Ctrl-C, SIGTERM and SIGHUP for the block and deliver one that arrived right after it.

    For writes done by C++ code (``torch.save`` into a file object): an exception raised inside them by a
    signal handler comes out as a ``RuntimeError`` ("unexpected pos ..."), which would end the run as an
    unexpected error (exit 1) instead of an interruption (130/143/129). Only the main thread sets handlers;
    elsewhere the block runs unchanged.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []
    signums = tuple(dict.fromkeys((int(signal.SIGINT), *STOP_SIGNALS)))
    previous: dict[int, Any] = {s: signal.getsignal(s) for s in signums}

    def hold(signum: int, frame: FrameType | None) -> None:
        got.append(signum)

    for signum in signums:
        signal.signal(signum, hold)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if got:  # replay the first one with the handler it was meant for
        handler = previous[got[0]]
        if callable(handler):
            handler(got[0], None)
        elif handler == signal.SIG_DFL:
            signal.raise_signal(got[0])


def stop_signal(exc: BaseException | None) -> int:
    """The signal behind an interruption: ``exc``'s when it is (or wraps) :class:`Stopped`, else SIGINT."""
    seen = 0
    while exc is not None and seen < 8:
        if isinstance(exc, Stopped):
            return exc.signum
        exc = exc.__context__ or exc.__cause__
        seen += 1
    return int(signal.SIGINT)


__all__ = ["STOP_SIGNALS", "Stopped", "deferred", "install_stop_signals", "stop_signal", "stop_signals"]
