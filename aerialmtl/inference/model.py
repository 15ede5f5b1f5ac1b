"""Streaming prediction of orthophotos: the model, loaded once, that computes strips of window rows.

A :class:`Predictor` is a model loaded once with its settings (:class:`~aerialmtl.inference.settings.PredictSettings`
and what they resolved to), its output schema (:attr:`Predictor.layers`) and its fingerprint: it computes any
number of orthophotos. What runs once per input — claiming the prediction folder, the writer's staging files,
the commit and ``prediction.json`` — is the job's (:class:`~aerialmtl.inference.job.InputJob`); the whole
raster is the one-strip case, and a ``torchrun`` rank computes one strip of the window rows of an input it
shares (:mod:`aerialmtl.inference.jobs`). The orthophoto's header is read once into an
:class:`~aerialmtl.inference.ortho.OrthoInput` (grid, bands, window plan, value check) that travels
through the job.

A strip is read → model → stitch → write, each stage overlapping the others:

1. :class:`~aerialmtl.inference.reader.WindowReader` reads and decodes the windows of the plan
   (:func:`~aerialmtl.inference.windows.plan_windows`) on the prediction grid at the model's GSD in
   background threads, a few windows ahead;
2. :class:`~aerialmtl.inference.runner.ModelRunner` normalises them on the device and runs the model in
   batches of windows of one window row (plain forward for T = 1, MC dropout for T > 1);
3. :class:`~aerialmtl.inference.stitch.Stitcher` blends the window statistics on the device (in a thread of
   its own while the model computes the next batches, on a GPU or a host of 4 cores or more) and hands back
   finished blocks in their output dtypes, following one output schema
   (:func:`~aerialmtl.formats.prediction.prediction_layers`);
4. the job's :class:`~aerialmtl.inference.writer.PredictionWriter` writes the blocks into staging files
   in a background thread; at the commit it converts every layer to a COG (the layers in parallel, each
   on several threads) and renames everything into place at once.

Device, precision, autocast, the compile fallback and the GDAL settings come from
:mod:`aerialmtl.runtime`, as for training.

Memory holds a few windows (reader queue, accumulators, blocks in flight) plus the rows two window rows
share (a few KiB per raster column): it does not grow with the raster height, and barely with its
width. Windows with no valid input pixel (nodata, outside the AOI) are not computed.

:func:`~aerialmtl.inference.jobs.predict_raster` is the one-call form and
:func:`~aerialmtl.inference.jobs.predict_many` its many-input form (in one process or many, torchrun); this
module imports neither the job nor the jobs (an import-linter contract, pyproject.toml).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import queue
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from aerialmtl import runtime
from aerialmtl.formats import checkpoint as checkpoint_format  # read_model at call time: tests patch it
from aerialmtl.formats.checkpoint import ModelMeta, model_fingerprint
from aerialmtl.formats.prediction import PROVENANCE_KEY, RECORD_KEYS, LayerSpec, prediction_layers
from aerialmtl.formats.stac import model_summary
from aerialmtl.inference import stitch_kernel
from aerialmtl.inference.engine_choice import choose_engine, cold_cache_choice
from aerialmtl.inference.engines import Pending, cache_root, openvino_available
from aerialmtl.inference.model_record import CheckpointModel, make_record, read_record, resolve_model, write_record
from aerialmtl.inference.ortho import OrthoInput
from aerialmtl.inference.reader import Aoi, ReadWindow, WindowReader
from aerialmtl.inference.runner import ModelRunner, auto_batch_size
from aerialmtl.inference.sanity import check_calibration, check_finite_outputs, check_height_range, rescaled
from aerialmtl.inference.settings import PredictSettings, ResolvedSettings, settings_of
from aerialmtl.inference.stitch import Block, Stitcher
from aerialmtl.inference.sun_choice import SunChoice, choose_sun
from aerialmtl.inference.windows import Plan
from aerialmtl.io.fingerprint import file_fingerprint, input_fingerprint
from aerialmtl.models import class_kernel
from aerialmtl.models.mc_dropout import McStatistics
from aerialmtl.progress import tqdm_auto as tqdm
from aerialmtl.sun.position import Sun

if TYPE_CHECKING:
    from aerialmtl.inference.shadows import ShadowStep

log = logging.getLogger(__name__)

#: MC-dropout samples when the caller does not say otherwise and the model has dropout.
DEFAULT_MC_SAMPLES = 30


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


def _load(checkpoint: str | Path | tuple[torch.nn.Module, ModelMeta], warm: bool = False
          ) -> tuple[torch.nn.Module | CheckpointModel, ModelMeta, str, str | None]:
    """``(model, meta, name, fingerprint)`` of ``checkpoint``.

    The fingerprint is that of the checkpoint bytes loaded (``None`` for a model given in memory: computed from its
    weights when needed).

    With ``warm`` (a run that may use the OpenVINO engine), a checkpoint file whose record is beside the engine
    cache (:mod:`aerialmtl.inference.model_record`) is not loaded: its bytes are hashed, and the model is a
    :class:`~aerialmtl.inference.model_record.CheckpointModel` that loads them only if something needs the
    weights; a checkpoint loaded here gets its record for the next run.
    """
    if isinstance(checkpoint, tuple):
        model, meta = checkpoint
        return model, meta, "<in-memory model>", None
    if warm:
        root = cache_root()
        try:
            digest: str | None = checkpoint_format.file_sha256(checkpoint)
        except OSError:  # read_model says what is wrong with the file
            digest = None
        record = read_record(digest, root) if digest is not None and root is not None else None
        if digest is not None and record is not None:
            return CheckpointModel(checkpoint, digest, record), record.meta, str(checkpoint), digest
    model, meta, loaded = checkpoint_format.read_model(checkpoint)
    if warm:
        made = make_record(model, meta)
        if made is not None and root is not None:
            write_record(loaded, made, root)
    return model, meta, str(checkpoint), loaded


def _stats_window(stats: McStatistics, n: int) -> McStatistics:
    """The statistics of window ``n`` of a batch (views)."""
    return stats.map(lambda t: t[n])


# ---- the predictor -----------------------------------------------------------------------------
class Predictor:
    """A model ready to predict orthophotos: read → model → stitch (the job writes).

    Args:
        checkpoint: checkpoint path, or ``(model, meta)`` already loaded.
        settings: predict's settings (:class:`~aerialmtl.inference.settings.PredictSettings`; default: its
            defaults).
        checkpoint_name: the checkpoint's name in ``prediction.json`` and in messages (default: its path, or
            ``<in-memory model>``).
        options: the Python API's keywords, one per field of the settings (named like them), applied over
            ``settings`` (:meth:`~aerialmtl.inference.settings.PredictSettings.with_options`).

    What ``auto`` and the defaults resolve to is :attr:`resolved` (and, one by one, :attr:`device`,
    :attr:`engine`, :attr:`precision`, :attr:`threads`, :attr:`mc`).
    """

    def __init__(self, checkpoint: str | Path | tuple[torch.nn.Module, ModelMeta],
                 settings: PredictSettings | None = None, *, checkpoint_name: str | None = None,
                 **options: Any) -> None:
        self.settings = s = settings_of(settings, options)
        self.device = runtime.resolve_device(s.device)
        #: Inference threads and streams (:func:`aerialmtl.runtime.resolve_threads`).
        self.threads = runtime.resolve_threads(s.threads)
        if self.threads.source != "auto" and self.device.type == "cpu":
            torch.set_num_threads(self.threads.threads)
        warm = s.engine in ("auto", "openvino") and self.device.type == "cpu" and openvino_available()
        model, self.meta, name, loaded_fingerprint = _load(checkpoint, warm=warm)
        #: The engine that runs the model (a name of :data:`~aerialmtl.inference.engines.ENGINES`).
        #: Engine and precision, and why (``auto``: measured per CPU kind, :mod:`~aerialmtl.inference.engine_choice`).
        self.choice = choose_engine(s.engine, s.precision, self.device, model)
        self.engine, self.precision = self.choice.engine, self.choice.precision
        if self.engine == "torch":
            model = resolve_model(model)
        if s.compile and self.engine != "torch":
            warnings.warn("‹compile› applies to the torch engine; the OpenVINO engine compiles the model itself",
                          UserWarning, stacklevel=2)
        self.checkpoint_name = checkpoint_name or name
        self._checkpoint = checkpoint
        self._loaded = model  # as loaded: the torch engine is built from it if a cold cache turns auto to torch
        self._fingerprint: str | None = loaded_fingerprint  # of the bytes loaded, not of the path at commit
        self.mc = s.mc if s.mc is not None else (DEFAULT_MC_SAMPLES if self.meta.model.dropout > 0 else 1)
        if s.calibration:
            check_calibration(self.meta, self.checkpoint_name)
        self.calibration = self.meta.calibration if s.calibration else None
        self.calibration_available = self.meta.calibration is not None
        #: What the settings resolved to.
        self.resolved = ResolvedSettings(self.device, self.engine, self.precision, self.threads, self.mc)
        # the checkpoint hashed once: provenance and the OpenVINO cache's key
        weights_key = self.fingerprint if self.engine == "openvino" else None
        self.runner = ModelRunner(model, self.meta, s, self.resolved, weights_key)
        tasks = tuple(self.meta.model.tasks)
        self.num_classes = self.meta.classes.num_classes if self.meta.classes is not None and "classes" in tasks else 0
        #: The shadow features (:mod:`aerialmtl.inference.shadows`), ``None`` when off for the whole run.
        self.shadows = self._shadow_step()
        self._suns: dict[str, SunChoice] = {}
        #: The output schema: one :class:`LayerSpec` per layer, in file order.
        self.layers: tuple[LayerSpec, ...] = prediction_layers(tasks, self.meta.classes, self.mc, s.probabilities,
                                                                 aleatoric=self.meta.model.aleatoric, tta=s.tta,
                                                                 unfamiliarity=self.meta.familiarity is not None,
                                                                 shadows=self.shadows is not None)
        if self.meta.familiarity is None:  # said once per run (and in prediction.json's model summary)
            log.info("%s holds no feature density: no unfamiliarity layer (a model trained with this version "
                     "fits one after training)", self.checkpoint_name)
        self._batch: dict[tuple[int, int], int] = {}
        if self.device.type == "cpu":  # the kernels loaded before any output exists (class_kernel.prepare)
            if self.mc > 1:
                class_kernel.prepare()
            if "classes" in self.meta.model.tasks:
                stitch_kernel.prepare()

    @property
    def aoi(self) -> str | Path | None:
        """The AOI of the settings (windows outside it are not computed)."""
        return self.settings.aoi

    def _shadow_step(self) -> ShadowStep | None:
        """The shadow features of this run, or ``None`` when they are off.

        On unless ``--sun none``, for a height model whose checkpoint holds the training area's shadow classifier
        (``meta.sun``; fitted by ``train`` since this version).
        """
        s, sun = self.settings, self.meta.sun
        if s.sun == "none" or "height" not in self.meta.model.tasks:
            return None
        if sun is None or sun.shadow_model is None:
            why = ("holds no sun fit (trained before this version: `aerialmtl train` fits one)" if sun is None else
                   f"has no shadow classifier: {sun.reason}")
            if s.sun != "auto" or s.shadow_fusion:
                warnings.warn(f"--sun {s.sun}: {self.checkpoint_name} {why}; no shadow layers", UserWarning,
                              stacklevel=3)
            return None
        from aerialmtl.inference.shadows import ShadowStep  # scipy and the sun's kernels: only a run that casts shadows
        from aerialmtl.sun.colour import ShadowModel

        return ShadowStep(ShadowModel.from_dict(sun.shadow_model), self.meta.gsd, s.shadow_fusion,
                          workers=self.threads.threads)

    def sun_for(self, src: OrthoInput) -> SunChoice | None:
        """The sun of ``src``, or ``None`` when the shadow features are off for the run.

        Chosen by :func:`~aerialmtl.inference.sun_choice.choose_sun`, once per input, and said once.
        """
        if self.shadows is None:
            return None
        key = str(src.path)
        if key not in self._suns:
            choice = choose_sun(self.settings.sun, self.settings.acquired, src.path, src.grid, src.tags,
                                self.meta.sun)
            self._suns[key] = choice
            if choice.on:
                log.info("%s: %s", src.name, choice.note)
            else:
                warnings.warn(f"{src.name}: no shadow features: {choice.note}", UserWarning, stacklevel=2)
        return self._suns[key]

    @property
    def model(self) -> torch.nn.Module:
        """The prepared model the runner predicts with."""
        return self.runner.model

    # ---- inputs -----------------------------------------------------------------------------------
    def open(self, ortho: str | Path | OrthoInput, warn: bool = True) -> OrthoInput:
        """Read the header of ``ortho`` and a sample of its values once.

        :meth:`OrthoInput.open <aerialmtl.inference.ortho.OrthoInput.open>` reads them; an :class:`OrthoInput` is
        returned as it is.

        Args:
            ortho: the orthophoto.
            warn: warn when it is resampled to the model's GSD or has bands the model does not read.

        Raises:
            AlignmentError / InputError: unusable georeferencing or bands, or values unlike the training
                data's (:func:`~aerialmtl.inference.sanity.check_input_values`; messages name the fix).
        """
        if isinstance(ortho, OrthoInput):
            return ortho
        src = OrthoInput.open(ortho, self.meta, self.settings.window, self.settings.overlap,
                               rescale_input=self.settings.rescale_input)
        if warn:
            src.warn_resampled(self.meta, stacklevel=4)
            src.warn_unused_bands(self.meta, stacklevel=4)
        return src

    def resolved_batch_size(self, plan: Plan) -> int:
        """Windows per model call for windows of ``plan`` (resolves ``"auto"`` once per window size)."""
        if self.settings.batch_size != "auto":
            return int(self.settings.batch_size)
        key = (plan.rows.size, plan.cols.size)
        if key not in self._batch:
            self._batch[key] = auto_batch_size(lambda: self.runner.net, self.meta.model.in_channels, *key,
                                               self.device, self.precision)
        return self._batch[key]

    def fit_engine(self, srcs: Sequence[OrthoInput]) -> None:
        """With ``engine: auto``, settle the engine for the job of predicting ``srcs`` once its size is known.

        OpenVINO on a cold cache gives way to the torch engine when compiling first would make the job slower than
        torch (:func:`~aerialmtl.inference.engine_choice.cold_cache_choice`, which :attr:`choice` then says).
        Called by the jobs (:mod:`aerialmtl.inference.jobs`) before anything is computed.
        """
        cached = getattr(self.runner.engine, "cached", None)
        if self.settings.engine != "auto" or not srcs or not callable(cached):
            return
        shapes = {(src.plan.rows.size, src.plan.cols.size) for src in srcs}
        warm = all(cached(h, w, self.mc) for h, w in shapes)
        work = sum(src.plan.num_windows * src.plan.rows.size * src.plan.cols.size for src in srcs) / 1e6
        passes = self.mc * (8 if self.settings.tta else 1)
        choice = cold_cache_choice(self.choice, self.settings.precision, self.device, work, passes, warm)
        if choice is self.choice:
            return
        self.choice = choice
        self.engine, self.precision = choice.engine, choice.precision
        self.resolved = ResolvedSettings(self.device, self.engine, self.precision, self.threads, self.mc)
        self.runner = ModelRunner(resolve_model(self._loaded), self.meta, self.settings, self.resolved)
        self._batch.clear()

    # ---- computing --------------------------------------------------------------------------------
    def compute(self, src: OrthoInput, rows: tuple[int, int], write: Callable[[Block], None], *,
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
        stitcher = Stitcher(src.plan, self.layers, self.num_classes, self.device, start, stop,
                            calibration=self.calibration)
        loop = _StripLoop(self, src, stitcher, write, progress, range(stitcher.first_row, stop))
        try:
            loop.run()
            if not stitcher.finished:  # pragma: no cover - the reader yields every window of the rows
                raise RuntimeError("stitcher did not receive every window")
        finally:
            loop.bar.close()
        return StripResult(loop.computed, loop.timings)

    # ---- run information --------------------------------------------------------------------------
    @property
    def fingerprint(self) -> str:
        """The model's fingerprint (SHA-256).

        Of the checkpoint bytes that were loaded (:func:`~aerialmtl.formats.checkpoint.read_checkpoint`), or of the
        weights of a model given in memory.
        """
        if self._fingerprint is None:
            assert isinstance(self._checkpoint, tuple)
            self._fingerprint = model_fingerprint(*self._checkpoint)
        return self._fingerprint

    def provenance(self, src: OrthoInput) -> dict[str, Any]:
        """What makes the maps of ``src`` (``provenance`` in prediction.json, :mod:`aerialmtl.formats.prediction`)."""
        s = self.settings
        settings = s.provenance(self._ran_as(), shadows=self.shadows is not None, aoi=file_fingerprint(s.aoi),
                                calibration=self.calibration is not None,
                                input_rescale=None if src.rescale is None else list(src.rescale))
        return {
            "checkpoint": self.fingerprint,
            "settings": settings,
            "input": src.fingerprint if src.fingerprint is not None else input_fingerprint(src.path),
        }

    def record_settings(self, src: OrthoInput) -> dict[str, Any]:
        """The model's and the settings' fields of ``src``'s ``prediction.json``.

        See :class:`~aerialmtl.formats.prediction.PredictionRecord` (the job adds the input's and the run's): the
        settings with what they resolved to (:meth:`PredictSettings.record
        <aerialmtl.inference.settings.PredictSettings.record>`).
        """
        settings = self.settings.record(self._ran_as(), self.resolved_batch_size(src.plan))
        return {
            "checkpoint": self.checkpoint_name,
            "model": model_summary(self.meta),
            **{k: v for k, v in settings.items() if k in RECORD_KEYS},
            "mc_samples": settings["mc"],
            "sun_setting": settings["sun"],
            "settings": settings,
            "engine_choice": self.choice.as_dict(),
            "calibration": self.calibration_info(),
            **({"sun": choice.record()} if (choice := self.sun_for(src)) is not None else {}),
            PROVENANCE_KEY: self.provenance(src),
        }

    def _ran_as(self) -> ResolvedSettings:
        """What the settings resolved to, with the engine that ran (``torch`` if ``auto`` fell back)."""
        return dataclasses.replace(self.resolved, engine=self.runner.engine.name)

    def calibration_info(self) -> dict[str, Any]:
        """``prediction.json``'s ``calibration``: whether the checkpoint's calibration was applied, and which."""
        cal = self.meta.calibration
        if cal is None:
            return {"applied": False, "reason": "the checkpoint has no calibration"}
        on = self.calibration is not None
        info: dict[str, Any] = {"applied": on and (cal.height_applied or cal.spread_applied),
                                "height_map_applied": on and cal.height_applied,
                                "spread_map_applied": on and cal.spread_applied,
                                "method": cal.method, "n_pixels": cal.n_pixels, "source": cal.source,
                                "summary": cal.summary()}
        if cal.height_applied:
            info["height_knots_m"] = [list(cal.height_x), list(cal.height_y)]
        if cal.spread_applied:
            info.update({"std_scale": cal.std_scale, "std_floor_m": cal.std_floor} if not cal.std_edges else
                        {"std_range_edges_m": list(cal.std_edges), "std_scales": list(cal.std_scales),
                         "std_floors_m": list(cal.std_floors)})
        if on and not (cal.height_applied or cal.spread_applied):
            info["reason"] = f"validation kept neither part: {cal.notes}"
        if self.calibration is None:
            info["reason"] = "switched off (--no-calibration)"
        return info


class _StripLoop:
    """The window loop of :meth:`Predictor.compute`, with the stage times.

    Windows read → batches submitted to the engine (up to
    :attr:`~aerialmtl.inference.runner.ModelRunner.in_flight` ahead) → statistics checked → stitched, and blocks
    handed to ``write``, by :class:`_StitchStage` (in a thread of its own: :func:`stitch_in_thread`).
    """

    def __init__(self, predictor: Predictor, src: OrthoInput, stitcher: Stitcher, write: Callable[[Block], None],
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
        self.p.shadows.apply(stats, rgb, valid, sun)
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


__all__ = ["DEFAULT_MC_SAMPLES", "STITCH_THREAD_CORES", "Predictor", "StripResult", "stitch_in_thread"]
