"""The commit stage of a predict job: each whole input's COGs, styles, STAC item and ``prediction.json`` written
(:meth:`InputJob.commit_files <aerialmtl.inference.job.InputJob.commit_files>`) after its strip, on a GPU in a
thread beside the next input's strip (:func:`commits_in_thread`), the results reported in input order
(:class:`Commits`; used by :mod:`aerialmtl.inference.jobs`).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import torch

from aerialmtl.inference.job import InputJob, PredictResult, StripResult


def commits_in_thread(device: torch.device) -> bool:
    """Whether whole inputs are committed in a thread beside the next input's strip (:class:`_Commits`).

    On a GPU: the strip leaves the host's cores to the COG build, which took 41 % of the wall after the strip
    on an H200 (issue 46; the overlap itself is not measured on a GPU). Not on a CPU, whose strip already keeps
    every core busy: 4 inputs of 4096², near-null model, T = 1, 2 cores (AMD EPYC): 0.99× the wall for +137 MiB
    peak memory (bench/results/predict.md).
    """
    return device.type == "cuda"


class Commits:
    """The commits of whole inputs, each (where :func:`commits_in_thread`) run in a thread beside the next input's
    strip.

    An input's commit (its COGs: compression and overviews on every host core, then the styles, the STAC item and
    ``prediction.json``; :meth:`InputJob.commit_files <aerialmtl.inference.job.InputJob.commit_files>`) runs after
    its strip. In a thread, at most one commit runs while the next strip computes; the results still come in input
    order, each once its files are at their final paths (:meth:`settle`, called after the next strip and at the
    end). A failed commit aborts its own files only; in one process it stops the run (the strip that ran beside it
    is aborted too), with several ranks it is counted among the rank's failures. When the run stops for another
    reason (an error, Ctrl-C), the commit in flight is still finished and reported (:meth:`close`): its input was
    computed whole. Without the thread each commit runs and is settled at once, as the strip ends.

    Args:
        committed: receives each committed input's result, in the main thread.
        raise_failures: raise a commit's error (one process) instead of returning it (several ranks).
        in_thread: commit beside the next strip.
    """

    def __init__(self, committed: Callable[[PredictResult], None], raise_failures: bool, in_thread: bool) -> None:
        self.committed, self.raise_failures, self.in_thread = committed, raise_failures, in_thread
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="aerialmtl-commit") if in_thread else None
        self._pending: tuple[Future[tuple[dict[str, Path], int, dict[str, float]]], InputJob, str,
                             dict[str, Any]] | None = None

    def start(self, job: InputJob, strip: StripResult, started: float, ortho: str) -> None:
        """Commit ``job``'s one strip: in the thread, or here (:meth:`settle` the one before first)."""
        assert self._pending is None, "settle the previous commit first"
        future: Future[tuple[dict[str, Path], int, dict[str, float]]]
        fields: dict[str, Any] = {}
        try:
            fields = job.model.record_settings(job.src)  # the model's state is read here, in the main thread
            if self._pool is not None:
                future = self._pool.submit(job.commit_files, [strip], started=started, fields=fields)
            else:
                future = Future()
                future.set_result(job.commit_files([strip], started=started, fields=fields))
        except Exception as exc:  # the input's failure, reported by settle as one from the thread
            job.abort()  # as commit_files does when it fails (a second abort removes nothing)
            future = Future()
            future.set_exception(exc)
        except BaseException:
            job.abort()
            raise
        self._pending = (future, job, ortho, fields)

    def settle(self) -> tuple[str, str] | None:
        """Wait for the commit in flight, if any, and report its result.

        Returns:
            ``(input, message)`` of a failed commit when failures are not raised, else ``None``.
        """
        if self._pending is None:
            return None
        future, job, ortho, fields = self._pending
        try:
            files, computed, timings = future.result()
        except Exception as exc:
            self._pending = None
            if self.raise_failures:
                raise
            return ortho, one_line(exc)
        self._pending = None
        self.committed(job.result(files, computed, timings, fields))
        return None

    def close(self) -> None:
        """After a stop: finish and report the commit in flight (its failure as a warning), end the thread."""
        wait = True
        try:
            if self._pending is not None:
                ortho = self._pending[2]
                try:
                    failure = self.settle()
                except Exception as exc:
                    failure = ortho, one_line(exc)
                if failure is not None:
                    warnings.warn(f"input '{failure[0]}' was not written either: {failure[1]}", UserWarning,
                                  stacklevel=2)
        except BaseException:  # a second Ctrl-C while waiting: the thread ends its commit before the process exits
            wait = False
            raise
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=wait)


def one_line(exc: BaseException) -> str:
    """``exc``'s message on one line (its class's name when it has none)."""
    return " ".join(str(exc).split()) or exc.__class__.__name__


__all__ = ["Commits", "commits_in_thread", "one_line"]
