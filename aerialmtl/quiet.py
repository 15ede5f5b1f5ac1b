"""Warnings silenced for one block of code, safely beside the package's other threads: :func:`ignoring_warnings`.

``warnings.catch_warnings`` is not thread-safe: it saves the process's list of warning filters when its block
starts and puts that list back when it ends. Two threads whose blocks overlap without nesting (A starts, B
starts, A ends, B ends) leave A's filter in place for the rest of the process. ``predict`` met it: its reader
threads open their rasters in a block that ignores rasterio's ``NotGeoreferencedWarning`` while the main thread
read the checkpoint in a block that ignores ``UserWarning``; in 2 runs of 80 on 2 busy cores the reader's block
saved the main thread's list, put it back last, and every later warning of the run (a cache that cannot be
written, a fallback) was lost. Every block of the package that silences warnings goes through this module's
lock, so no two of them overlap. The exceptions are blocks that enclose every thread they could meet: the
command's own (:func:`aerialmtl.cli.main`, entered before its threads start and left after they end) and the sun
process's recording block (:mod:`aerialmtl.training.sun_beside`, around the whole fit in a process of its own).
"""

from __future__ import annotations

import contextlib
import threading
import warnings
from collections.abc import Iterator

#: Held while a block of :func:`ignoring_warnings` runs (re-entrant: such blocks may nest in one thread).
LOCK = threading.RLock()


@contextlib.contextmanager
def ignoring_warnings(*categories: type[Warning]) -> Iterator[None]:
    """Ignore warnings of ``categories`` (every warning when none is given) in the block; the filters are the
    process's own again afterwards, whatever other threads do meanwhile.

    A thread entering such a block waits while another thread is in one (the blocks are short: opening a
    raster, reading a checkpoint, tracing a model for OpenVINO).
    """
    with LOCK, warnings.catch_warnings():
        for category in categories or (Warning,):
            warnings.simplefilter("ignore", category)
        yield


__all__ = ["LOCK", "ignoring_warnings"]
