"""One strip of window rows computed: the window loop of :meth:`~aerialmtl.inference.model.Predictor.compute`
and its stitch stage.

Windows read (:class:`~aerialmtl.inference.reader.WindowReader`) → batches submitted to the engine (up to
:attr:`~aerialmtl.inference.runner.ModelRunner.in_flight` ahead) → statistics checked
(:mod:`~aerialmtl.inference.sanity`) → the shadow step where it is on → stitched
(:class:`~aerialmtl.inference.stitch.Stitcher`) and the finished blocks handed to the job's writer. The stitching
runs in a thread of its own (:class:`_StitchStage`) on a GPU or a host of :data:`STITCH_THREAD_CORES` cores or
more, while this thread reads, submits and collects the next batches.

The predictor is seen through :class:`StripModel` (what a strip reads of it): this module sits below
:mod:`~aerialmtl.inference.model` (the inference layers, pyproject.toml).
"""

from __future__ import annotations

import os
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import torch

from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.formats.prediction import LayerSpec
from aerialmtl.inference.engines import Pending
from aerialmtl.inference.ortho import OrthoInput
from aerialmtl.inference.reader import Aoi, ReadWindow, WindowReader
from aerialmtl.inference.runner import ModelRunner
from aerialmtl.inference.sanity import check_finite_outputs, check_height_range, rescaled
from aerialmtl.inference.settings import PredictSettings
from aerialmtl.inference.stitch import Block, Stitcher
from aerialmtl.inference.sun_choice import SunChoice
from aerialmtl.inference.windows import Plan
from aerialmtl.models.calibration import Calibration
from aerialmtl.models.mc_dropout import McStatistics
from aerialmtl.progress import tqdm_auto as tqdm
from aerialmtl.sun.position import Sun

if TYPE_CHECKING:
    from aerialmtl.inference.shadows import ShadowStep


@dataclass
class StripResult:
    """What one strip of window rows (or the whole raster) computed; travels between ranks.

    Attributes:
        windows_computed: windows run through the model.
        timings: seconds per stage (see :class:`~aerialmtl.inference.job.PredictResult`).
        row_start: the first grid row the strip wrote (its staging files are named after it).
    """

    windows_computed: int
    timings: dict[str, float]
    row_start: int = 0


def _stats_window(stats: McStatistics, n: int) -> McStatistics:
    """The statistics of window ``n`` of a batch (views)."""
    return stats.map(lambda t: t[n])


class StripModel(Protocol):
    """What a strip reads of the predictor (:class:`~aerialmtl.inference.model.Predictor`)."""

    settings: PredictSettings
    meta: ModelMeta
    device: torch.device
    checkpoint_name: str
    shadows: ShadowStep | None
    layers: tuple[LayerSpec, ...]
    num_classes: int
    calibration: Calibration | None

    @property
    def runner(self) -> ModelRunner:
        """The model runner (built once)."""
        ...

    def resolved_batch_size(self, plan: Plan) -> int:
        """Windows per model call for windows of ``plan``."""
        ...

    def sun_for(self, src: OrthoInput) -> SunChoice | None:
        """The sun of ``src``, or ``None`` when the shadow features are off."""
        ...

    def sun_off(self, src: OrthoInput, note: str) -> None:
        """Switch the shadow layers off for ``src`` (its own shadows disagree with its sun), said once."""
        ...


def compute_strip(p: StripModel, src: OrthoInput, rows: tuple[int, int], write: Callable[[Block], None],
                  progress: bool = True) -> StripResult:
    """Read, run and stitch window rows ``rows = [start, stop)`` of ``src``'s plan (inside the settings' AOI).

    Each finished block goes to ``write`` (the job's writer: :class:`~aerialmtl.inference.job.InputJob`).

    The window rows before ``start`` that reach into it
    (:attr:`~aerialmtl.inference.windows.WindowRow.sources`) are computed too, so a strip gives exactly
    the output rows a whole-raster run gives.

    Returns:
        the windows computed and the stage times (``read``, ``model``, ``stitch_write``; seconds).
    """
    start, stop = rows
    stitcher = Stitcher(src.plan, p.layers, p.num_classes, p.device, start, stop, calibration=p.calibration)
    loop = _StripLoop(p, src, stitcher, write, progress, range(stitcher.first_row, stop))
    try:
        loop.run()
        if not stitcher.finished:  # pragma: no cover - the reader yields every window of the rows
            raise RuntimeError("stitcher did not receive every window")
    finally:
        loop.bar.close()
    return StripResult(loop.computed, loop.timings)


class _StripLoop:
    """The window loop of :func:`compute_strip`, with the stage times.

    Windows read → batches submitted to the engine (up to
    :attr:`~aerialmtl.inference.runner.ModelRunner.in_flight` ahead) → statistics checked → stitched, and blocks
    handed to ``write``, by :class:`_StitchStage` (in a thread of its own: :func:`stitch_in_thread`).
    """

    def __init__(self, predictor: StripModel, src: OrthoInput, stitcher: Stitcher, write: Callable[[Block], None],
                 progress: bool, todo_rows: range) -> None:
        self.p, self.src, self.stitcher, self.write = predictor, src, stitcher, write
        self.runner = predictor.runner
        self.n_cols = len(src.plan.cols.starts)
        self.batch_size = predictor.resolved_batch_size(src.plan)
        self.timings = {"read": 0.0, "model": 0.0, "stitch_write": 0.0}
        self.computed = 0
        # batches submitted to the engine, oldest first: (windows in plan order, pending statistics, validity)
        self.queue: deque[tuple[list[ReadWindow], Pending | None, torch.Tensor | None]] = deque()
        self.todo_rows = todo_rows
        self.stage: _StitchStage | None = None
        self.bar = tqdm(total=len(todo_rows) * self.n_cols, unit="win", desc=src.name, disable=not progress,
                        dynamic_ncols=True)

    def run(self) -> None:
        """Compute the window rows ``todo_rows`` of the plan.

        This thread reads, submits and collects the model's batches while :class:`_StitchStage` stitches and
        writes the finished ones, in a thread of its own on a GPU or a host of :data:`STITCH_THREAD_CORES` cores
        or more (:func:`stitch_in_thread`).
        """
        p, src, todo_rows = self.p, self.src, self.todo_rows
        aoi_mask = Aoi(p.settings.aoi, src.grid) if p.settings.aoi is not None else None
        depth = max(4, 2 * self.batch_size)  # windows read ahead: a batch being computed and the next one
        reader = WindowReader(src, list(p.meta.bands), todo_rows, aoi_mask, threads=p.settings.reader_threads,
                              depth=depth, pin=p.device.type == "cuda")
        # the shadow step runs with the stitching: in the stage's thread, so that this one goes on driving the
        # engine (its MC decoding waits for this thread) while a batch's shadows are computed; the input's sun is
        # chosen (and said, or refused) here first, before any window
        p.sun_for(src)
        self.stage = stage = _StitchStage(self, stitch_in_thread(p.device) or p.shadows is not None)
        try:
            with reader:
                waiting: list[ReadWindow] = []  # read windows not yet handed to the stitcher, in plan order
                for win in reader:
                    waiting.append(win)
                    todo = [w for w in waiting if w.data is not None]
                    if len(todo) < self.batch_size and win.j != self.n_cols - 1:
                        continue
                    self.submit(waiting, todo)
                    waiting = []
                    while len(self.queue) > self.runner.in_flight:
                        self.finish_oldest()
                while self.queue:
                    self.finish_oldest()
                self.timings["read"] = reader.seconds_reading
            stage.finish()
        finally:
            stage.stop()
        # in its own thread (overlapping ``model``), the shadow step's seconds apart
        self.timings["stitch_write"] = stage.seconds - self.timings.get("shadows", 0.0)

    def submit(self, windows: list[ReadWindow], todo: list[ReadWindow]) -> None:
        """Queue ``windows``, starting the statistics of those with data (``todo``) on the engine."""
        if not todo:
            self.queue.append((windows, None, None))
            return
        t0 = time.perf_counter()
        raw, valid = self.runner.to_device([w.data for w in todo if w.data is not None], [w.valid for w in todo])
        x = self.runner.normalise(rescaled(raw, self.src.rescale), valid)
        keys = [w.i * self.n_cols + w.j for w in todo]
        self.queue.append((windows, self.runner.submit(x, keys), valid))
        self.timings["model"] += time.perf_counter() - t0
        self.computed += len(todo)

    def finish_oldest(self) -> None:
        """Wait for the oldest batch's statistics, check them, and hand its windows to the stitch stage."""
        windows, pending, valid = self.queue.popleft()
        stats = None
        if pending is not None:
            t0 = time.perf_counter()
            stats = pending.result()
            assert valid is not None
            check_finite_outputs(stats, valid, self.p.checkpoint_name)
            check_height_range(stats, valid, self.p.checkpoint_name, self.p.meta)
            self.timings["model"] += time.perf_counter() - t0
        assert self.stage is not None
        self.stage.put((windows, stats, valid))

    def shadows(self, windows: list[ReadWindow], stats: McStatistics, valid: torch.Tensor) -> None:
        """The shadow layers (and fusion) of the batch's computed windows (:mod:`aerialmtl.inference.shadows`)."""
        from aerialmtl.inference.shadows import unit_colours  # imported with the step (Predictor._shadow_step)

        t0 = time.perf_counter()
        choice = self.p.sun_for(self.src)
        sun = None
        if choice is not None and choice.on:
            assert choice.grid_azimuth_deg is not None and choice.elevation_deg is not None
            sun = Sun(choice.grid_azimuth_deg % 360.0, choice.elevation_deg)
        rgb = []
        for w in windows:
            if w.data is not None:
                data = w.data.numpy() if isinstance(w.data, torch.Tensor) else w.data
                rgb.append(unit_colours(data[:3], self.src.rescale, self.p.meta.input_dtype))
        assert self.p.shadows is not None
        if sun is not None and choice is not None:  # a sun taken on trust: checked on the orthophoto's shadows
            off = self.p.shadows.check_sun(str(self.src.path), sun, choice.source, stats, rgb, valid)
            if off is not None:
                self.p.sun_off(self.src, off)
                sun = None
        self.p.shadows.apply(stats, rgb, valid, sun, self.src.name)
        self.timings["shadows"] = self.timings.get("shadows", 0.0) + time.perf_counter() - t0

    def flush(self, windows: list[ReadWindow], stats: McStatistics | None, valid: torch.Tensor | None) -> None:
        """Hand ``windows`` to the stitcher and the finished blocks to ``write`` (by :class:`_StitchStage`), after
        the shadow step where it is on (:meth:`shadows`: it may move the heights, with fusion, so it comes first).

        ``stats`` holds the statistics of the windows with data, in order.
        """
        if stats is not None and self.p.shadows is not None:
            assert valid is not None
            self.shadows(windows, stats, valid)
        n = 0
        for w in windows:
            if w.data is None:
                blocks = self.stitcher.add(w.i, w.j, None, None)
            else:
                assert stats is not None and valid is not None
                blocks = self.stitcher.add(w.i, w.j, _stats_window(stats, n), valid[n])
                n += 1
            for block in blocks:
                self.write(block)
        self.bar.update(len(windows))


#: Batches of checked statistics waiting for the stitch stage at most (each holds its windows' statistics:
#: ~80 MiB per 1024² window with 20 classes); the model loop waits beyond.
STITCH_QUEUE = 2
#: Host cores from which a CPU run stitches in a thread of its own (a CUDA run always does: the host then only
#: feeds the device); a one-core host stitches in the model loop, unless the shadow step is on: it runs in the
#: stage (:meth:`_StripLoop.flush`), and in the loop it kept the engine's MC decoding waiting (2 cores, 2048²,
#: T = 8: +16 % for the shadow layers inline). On 2 quiet cores the thread took the near-null pipeline (8192²,
#: T = 1) from 12.4-13.7 to 11.5-12.3 s for +4 % CPU time and ~140 MiB; on 2 cores oversubscribed 7× (load 15)
#: it had gained nothing for +8 % CPU time (bench/results/predict.md, issue 46).
STITCH_THREAD_CORES = 2
_END = None


def stitch_in_thread(device: torch.device, cores: int | None = None) -> bool:
    """Whether a strip on ``device`` stitches in a thread of its own (:data:`STITCH_THREAD_CORES`).

    ``cores``: the host cores this process may use (default: its CPU affinity).
    """
    if device.type == "cuda":
        return True
    if cores is None:
        try:
            cores = len(os.sched_getaffinity(0))
        except AttributeError:  # pragma: no cover - not Linux
            cores = os.cpu_count() or 1
    return cores >= STITCH_THREAD_CORES


class _StitchStage:
    """The stitch stage of a strip, in a thread of its own.

    Batches of checked statistics, in plan order, are stitched (:meth:`_StripLoop.flush`) and their finished
    blocks handed to the writer while the model loop reads, submits and collects the next batches (torch and
    GDAL release Python's GIL while they work).

    An error here (a block the writer refused, a stitching error) is raised in the model loop at its next
    :meth:`put` or at :meth:`finish`; :meth:`stop` (always called, also on Ctrl-C) ends the thread before the
    job aborts the writer.
    """

    def __init__(self, loop: _StripLoop, threaded: bool = True) -> None:
        self.loop = loop
        self.seconds = 0.0  # busy stitching and writing
        self.error: BaseException | None = None
        self._queue: queue.Queue[tuple[list[ReadWindow], McStatistics | None, torch.Tensor | None] | None] = \
            queue.Queue(maxsize=STITCH_QUEUE)
        self._cancel = threading.Event()
        self._thread = threading.Thread(target=self._work, name="aerialmtl-stitch", daemon=True)
        self.threaded = threaded
        if threaded:
            self._thread.start()

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is _END:
                return
            if self.error is not None or self._cancel.is_set():
                continue  # drained: the model loop raises the error or has stopped
            t0 = time.perf_counter()
            try:
                self.loop.flush(*item)
            except BaseException as exc:  # raised in the model loop
                self.error = exc
            self.seconds += time.perf_counter() - t0

    def _raise(self) -> None:
        if self.error is not None:
            raise self.error

    def put(self, item: tuple[list[ReadWindow], McStatistics | None, torch.Tensor | None]) -> None:
        """Queue a batch for stitching, or raise an earlier batch's error.

        Waits while :data:`STITCH_QUEUE` are queued. Without a thread (:func:`stitch_in_thread`), the batch is
        stitched here.
        """
        if not self.threaded:
            t0 = time.perf_counter()
            self.loop.flush(*item)
            self.seconds += time.perf_counter() - t0
            return
        while True:
            self._raise()
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def finish(self) -> None:
        """Wait until every queued batch is stitched and written to the writer; raises their error."""
        if not self.threaded:
            return
        self._queue.put(_END)
        self._thread.join()
        self._raise()

    def stop(self) -> None:
        """End the thread (the batches still queued are dropped); returns once it has ended."""
        if not self._thread.is_alive():
            return
        self._cancel.set()
        while self._thread.is_alive():
            try:
                self._queue.put(_END, timeout=0.1)
                break
            except queue.Full:
                continue
        self._thread.join()


__all__ = ["STITCH_QUEUE", "STITCH_THREAD_CORES", "StripModel", "StripResult", "compute_strip", "stitch_in_thread"]
