"""Streaming prediction of one orthophoto into a prediction folder of Cloud-Optimized GeoTIFFs: the model.

A :class:`Predictor` is a model loaded once with its settings (device, precision, MC samples, windows),
its output schema (:attr:`Predictor.layers`) and its fingerprint: it predicts any number of orthophotos.
What runs once per input — claiming the prediction folder, the writer's staging files, the commit and
``prediction.json`` — is the job's (:class:`~aerialmtl.inference.job.InputJob`): :meth:`Predictor.run`
is one job over the whole raster, and a ``torchrun`` rank computes one strip of the window rows of an
input it shares (:mod:`aerialmtl.inference.jobs`). The orthophoto's header is read once into an
:class:`~aerialmtl.inference.ortho.OrthoInput` (grid, bands, window plan, value check) that travels
through the job.

A strip is read → model → stitch → write, each stage overlapping the others:

1. :class:`~aerialmtl.inference.reader.WindowReader` reads and decodes the windows of the plan
   (:func:`~aerialmtl.inference.windows.plan_windows`) on the prediction grid at the model's GSD in
   background threads, a few windows ahead;
2. :class:`~aerialmtl.inference.runner.ModelRunner` normalises them on the device and runs the model in
   batches of windows of one window row (plain forward for T = 1, MC dropout for T > 1);
3. :class:`~aerialmtl.inference.stitch.Stitcher` blends the window statistics on the device and hands
   back finished blocks in their output dtypes, following one output schema
   (:func:`~aerialmtl.formats.prediction.prediction_layers`);
4. the job's :class:`~aerialmtl.inference.writer.PredictionWriter` writes the blocks into staging files
   in a background thread; at the commit it converts every layer to a COG (the layers in parallel, each
   on several threads) and renames everything into place at once.

Device, precision, autocast, the compile fallback and the GDAL settings come from
:mod:`aerialmtl.runtime`, as for training.

Memory holds a few windows (reader queue, accumulators, blocks in flight) plus the rows two window rows
share (a few KiB per raster column): it does not grow with the raster height, and barely with its
width. Windows with no valid input pixel (nodata, outside the AOI) are not computed.

:func:`predict_raster` is the one-call form; :mod:`aerialmtl.inference.jobs` runs many orthophotos, in
one process or many (torchrun).
"""

from __future__ import annotations

import time
import warnings
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import torch

from aerialmtl import runtime
from aerialmtl.errors import InputError
from aerialmtl.formats.checkpoint import ModelMeta, model_fingerprint
from aerialmtl.formats.prediction import (
    PROVENANCE_KEY,
    LayerSpec,
    file_fingerprint,
    input_fingerprint,
    prediction_layers,
)
from aerialmtl.formats.stac import model_summary
from aerialmtl.inference.engines import Pending, openvino_available, resolve_engine
from aerialmtl.inference.job import InputJob, PredictResult, StripResult
from aerialmtl.inference.model_record import CheckpointModel, resolve_model
from aerialmtl.inference.ortho import OrthoInput
from aerialmtl.inference.reader import Aoi, WindowReader
from aerialmtl.inference.runner import ModelRunner, auto_batch_size
from aerialmtl.inference.sanity import check_calibration, check_finite_outputs, check_height_range, rescaled
from aerialmtl.inference.stitch import Block, Stitcher
from aerialmtl.inference.windows import Plan, check_tiling
from aerialmtl.io.outputs import OutputFolder
from aerialmtl.models import class_kernel
from aerialmtl.models.mc_dropout import McStatistics
from aerialmtl.progress import tqdm_auto as tqdm

#: MC-dropout samples when neither the caller nor the checkpoint says otherwise.
DEFAULT_MC_SAMPLES = 30

BatchSize = int | Literal["auto"]


def _load(checkpoint: str | Path | tuple[torch.nn.Module, ModelMeta], warm: bool = False
          ) -> tuple[torch.nn.Module | CheckpointModel, ModelMeta, str, str | None]:
    """``(model, meta, name, fingerprint)``; the fingerprint is that of the checkpoint bytes loaded (``None`` for a
    model given in memory: computed from its weights when needed).

    With ``warm`` (a run that may use the OpenVINO engine), a checkpoint file whose record is beside the engine
    cache (:mod:`aerialmtl.inference.model_record`) is not loaded: its bytes are hashed, and the model is a
    :class:`~aerialmtl.inference.model_record.CheckpointModel` that loads them only if something needs the
    weights; a checkpoint loaded here gets its record for the next run.
    """
    if isinstance(checkpoint, tuple):
        model, meta = checkpoint
        return model, meta, "<in-memory model>", None
    from aerialmtl.formats.checkpoint import file_sha256, read_model

    if warm:
        from aerialmtl.inference.engines import cache_root
        from aerialmtl.inference.model_record import make_record, read_record, write_record

        root = cache_root()
        try:
            digest: str | None = file_sha256(checkpoint)
        except OSError:  # read_model says what is wrong with the file
            digest = None
        record = read_record(digest, root) if digest is not None else None
        if digest is not None and record is not None:
            return CheckpointModel(checkpoint, digest, record), record.meta, str(checkpoint), digest
    model, meta, loaded = read_model(checkpoint)
    if warm:
        made = make_record(model, meta)
        if made is not None:
            write_record(loaded, made, root)
    return model, meta, str(checkpoint), loaded


def _stats_window(stats: McStatistics, n: int) -> McStatistics:
    """The statistics of window ``n`` of a batch (views)."""
    return McStatistics(*(None if t is None else t[n] for t in (stats.height_mean, stats.height_std, stats.probs,
                                                                 stats.mean_entropy, stats.height_aleatoric)))


# ---- the predictor -----------------------------------------------------------------------------
class Predictor:
    """A model ready to predict orthophotos: read → model → stitch → write.

    Args:
        checkpoint: checkpoint path, or ``(model, meta)`` already loaded.
        mc: MC-dropout samples T (1 = single deterministic pass, no uncertainty layers); default
            :data:`DEFAULT_MC_SAMPLES` when the model has dropout, else 1.
        tile: largest window side in pixels (multiple of 32). 1024 with ``overlap`` 64 computes ≈ 1.14×
            the output pixels (512 → 1.31×).
        overlap: minimum overlap between neighbouring windows in pixels (blended; see
            :mod:`aerialmtl.inference.windows`).
        batch_size: windows per model call, or ``"auto"`` (:func:`~aerialmtl.inference.runner.auto_batch_size`:
            from the free memory on CUDA, :data:`~aerialmtl.inference.runner.CPU_BATCH` on a CPU).
        precision: ``"auto"``, ``"bf16"`` or ``"fp32"``. ``auto`` is bf16 where the hardware computes it
            natively and the engine gains from it: CUDA GPUs with bf16; CPUs with AVX-512-BF16 or AMX on
            the OpenVINO engine; CPUs with AMX on the torch engine (:func:`aerialmtl.runtime.resolve_precision`); fp32
            elsewhere. bf16 is autocast on torch and the inference precision on OpenVINO.
        engine: ``"auto"``, ``"torch"`` or ``"openvino"`` (:mod:`aerialmtl.inference.engines`): ``auto``
            is OpenVINO on a CPU when it is installed (and the model a D3-Net), torch otherwise.
        device: ``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"``.
        probabilities: also write ``class_probabilities.tif`` (K float32 bands).
        max_decode_pixels: bound on the pixels decoded per model call with MC dropout (windows ×
            samples × h × w); default :data:`DECODE_PIXELS` of the device. Bounds memory, not results.
        compile: ``torch.compile`` the model (a warning and the plain model where it is unavailable).
        seed: base seed of the per-window dropout masks (T > 1): the same seed gives the same maps,
            whatever the batch size, device chunking or number of processes.
        checkpoint_name: name recorded in ``prediction.json`` when ``checkpoint`` is a loaded model.
        reader_threads: background threads reading windows.
        calibration: apply the checkpoint's calibration (height map and spread factor fitted on the
            validation split, :mod:`aerialmtl.models.calibration`) when it has one; ``prediction.json``
            records whether it was applied.
        rescale_input: map an orthophoto whose values do not match the training data's onto the training
            range instead of refusing it (:mod:`aerialmtl.inference.sanity`).
        tta: test-time augmentation: each window also flipped and rotated (8 views), combined like MC samples
            into the maps and their spread (:class:`~aerialmtl.inference.runner.ModelRunner`); 8× the work.
        threads: inference threads on a CPU: a number, or ``"auto"``/``None`` (the
            :data:`~aerialmtl.runtime.THREADS_ENV` environment variable, else torch's own count);
            OpenVINO splits them into streams (:func:`aerialmtl.runtime.resolve_threads`), and
            ``prediction.json`` records both.

    The constructor takes each setting as a keyword of its own (18 parameters): they are predict's options,
    one each, which :func:`predict_raster`, :func:`~aerialmtl.inference.jobs.predict_many` and the CLI pass
    on by name.
    """

    def __init__(
        self,
        checkpoint: str | Path | tuple[torch.nn.Module, ModelMeta],
        *,
        mc: int | None = None,
        tile: int = 1024,
        overlap: int = 64,
        batch_size: BatchSize = 2,
        precision: runtime.Precision = "auto",
        device: str = "auto",
        probabilities: bool = False,
        max_decode_pixels: int | None = None,
        compile: bool = False,
        seed: int = 0,
        checkpoint_name: str | None = None,
        reader_threads: int = 2,
        calibration: bool = True,
        rescale_input: bool = False,
        engine: str = "auto",
        tta: bool = False,
        threads: int | str | None = None,
    ) -> None:
        check_tiling(tile, overlap)
        if mc is not None and (not isinstance(mc, int) or mc < 1):
            raise InputError(
                f"‹mc› must be a positive number of MC-dropout samples, got {mc!r}; pass e.g. ‹mc=30› (or 1)",
                param="mc")
        if batch_size != "auto" and (not isinstance(batch_size, int) or batch_size < 1):
            raise InputError(f"‹batch_size› must be ≥ 1 or 'auto', got {batch_size!r}; pass e.g. ‹batch_size=4›",
                             param="batch_size")
        self.device = runtime.resolve_device(device)
        runtime.resolve_precision(precision, self.device)  # a bad value fails before the checkpoint is read
        #: Inference threads and streams (:func:`aerialmtl.runtime.resolve_threads`).
        self.threads = runtime.resolve_threads(threads)
        if self.threads.source != "auto" and self.device.type == "cpu":
            torch.set_num_threads(self.threads.threads)
        warm = engine in ("auto", "openvino") and self.device.type == "cpu" and openvino_available()
        model, self.meta, name, loaded_fingerprint = _load(checkpoint, warm=warm)
        #: The engine that runs the model: ``"torch"`` or ``"openvino"``.
        self.engine = resolve_engine(engine, self.device, model)
        if self.engine == "torch":
            model = resolve_model(model)
        self.precision = runtime.resolve_precision(precision, self.device,
                                                   cpu_bf16=self.engine == "openvino" or runtime.cpu_has_amx())
        if compile and self.engine != "torch":
            warnings.warn("‹compile› applies to the torch engine; the OpenVINO engine compiles the model itself",
                          UserWarning, stacklevel=2)
        self.checkpoint_name = checkpoint_name or name
        self._checkpoint = checkpoint
        self._fingerprint: str | None = loaded_fingerprint  # of the bytes loaded, not of the path at commit
        self.mc = mc if mc is not None else (DEFAULT_MC_SAMPLES if self.meta.model.dropout > 0 else 1)
        self.tile, self.overlap = tile, overlap
        self.batch_size = batch_size
        self.probabilities = probabilities
        self.seed = seed
        self.compile = compile
        self.reader_threads = reader_threads
        if calibration:
            check_calibration(self.meta, self.checkpoint_name)
        self.calibration = self.meta.calibration if calibration else None
        self.calibration_available = self.meta.calibration is not None
        self.rescale_input = rescale_input
        self.tta = bool(tta)
        # the checkpoint hashed once: provenance and the OpenVINO cache's key
        weights_key = self.fingerprint if self.engine == "openvino" else None
        self.runner = ModelRunner(model, self.meta, self.device, self.precision, self.mc, seed, max_decode_pixels,
                                  compile, self.engine, tta=self.tta, fallback=engine == "auto", threads=self.threads,
                                  weights_key=weights_key)
        tasks = tuple(self.meta.model.tasks)
        self.num_classes = self.meta.classes.num_classes if self.meta.classes is not None and "classes" in tasks else 0
        #: The output schema: one :class:`LayerSpec` per layer, in file order.
        self.layers: tuple[LayerSpec, ...] = prediction_layers(tasks, self.meta.classes, self.mc, probabilities,
                                                                 aleatoric=self.meta.model.aleatoric,
                                                                 tta=self.tta)
        self._batch: dict[tuple[int, int], int] = {}
        if self.mc > 1 and self.device.type == "cpu":  # loaded before any output exists (class_kernel.prepare)
            class_kernel.prepare()

    @property
    def model(self) -> torch.nn.Module:
        """The prepared model the runner predicts with."""
        return self.runner.model

    # ---- inputs -----------------------------------------------------------------------------------
    def open(self, ortho: str | Path | OrthoInput, warn: bool = True) -> OrthoInput:
        """Read the header of ``ortho`` and a sample of its values once
        (:meth:`OrthoInput.open <aerialmtl.inference.ortho.OrthoInput.open>`); an :class:`OrthoInput` is
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
        src = OrthoInput.open(ortho, self.meta, self.tile, self.overlap, rescale_input=self.rescale_input)
        if warn:
            src.warn_resampled(self.meta, stacklevel=4)
            src.warn_unused_bands(self.meta, stacklevel=4)
        return src

    def resolved_batch_size(self, plan: Plan) -> int:
        """Windows per model call for windows of ``plan`` (resolves ``"auto"`` once per window size)."""
        if self.batch_size != "auto":
            return int(self.batch_size)
        key = (plan.rows.size, plan.cols.size)
        if key not in self._batch:
            self._batch[key] = auto_batch_size(lambda: self.runner.net, self.meta.model.in_channels, *key,
                                               self.device, self.precision)
        return self._batch[key]

    # ---- computing --------------------------------------------------------------------------------
    def compute(self, src: OrthoInput, rows: tuple[int, int], write: Callable[[Block], None], *,
                aoi: str | Path | None = None, progress: bool = True) -> StripResult:
        """Read, run and stitch window rows ``rows = [start, stop)`` of ``src``'s plan; each finished block
        goes to ``write`` (the job's writer: :class:`~aerialmtl.inference.job.InputJob`).

        The window rows before ``start`` that reach into it
        (:attr:`~aerialmtl.inference.windows.WindowRow.sources`) are computed too, so a strip gives exactly
        the output rows a whole-raster run gives.

        Returns:
            the windows computed and the stage times (``read``, ``model``, ``stitch_write``; seconds).

        Over 80 lines: the window loop and its two stages (``flush``: windows to the stitcher and the blocks
        to ``write``; ``finish_oldest``: an engine's batch checked and flushed) are closures over the
        reader, the stitcher, the queue of batches in flight and the timings; apart, they would pass
        these around on every window.
        """
        plan, grid = src.plan, src.grid
        rescale = src.rescale
        start, stop = rows
        stitcher = Stitcher(plan, self.layers, self.num_classes, self.device, start, stop,
                            calibration=self.calibration)
        batch_size = self.resolved_batch_size(plan)
        aoi_mask = Aoi(aoi, grid) if aoi is not None else None
        todo_rows = range(stitcher.first_row, stop)
        n_cols = len(plan.cols.starts)
        timings = {"read": 0.0, "model": 0.0, "stitch_write": 0.0}
        computed = 0
        bar = tqdm(total=len(todo_rows) * n_cols, unit="win", desc=src.name, disable=not progress,
                   dynamic_ncols=True)
        depth = max(4, 2 * batch_size)  # windows read ahead: a batch being computed and the next one
        reader = WindowReader(src, list(self.meta.bands), todo_rows, aoi_mask, threads=self.reader_threads,
                              depth=depth, pin=self.device.type == "cuda")
        try:
            with reader:
                waiting: list[Any] = []  # read windows not yet handed to the stitcher, in plan order
                # batches submitted to the engine, oldest first: (windows in plan order, pending statistics,
                # validity); up to runner.in_flight of them run while the oldest is stitched
                queue: deque[tuple[list[Any], Pending | None, torch.Tensor | None]] = deque()

                def flush(windows: list[Any], stats: McStatistics | None, valid: torch.Tensor | None) -> None:
                    t0 = time.perf_counter()
                    n = 0
                    for w in windows:
                        if w.data is None:
                            blocks = stitcher.add(w.i, w.j, None, None)
                        else:
                            assert stats is not None and valid is not None
                            blocks = stitcher.add(w.i, w.j, _stats_window(stats, n), valid[n])
                            n += 1
                        for block in blocks:
                            write(block)
                    bar.update(len(windows))
                    timings["stitch_write"] += time.perf_counter() - t0

                def finish_oldest() -> None:
                    windows, pending, valid = queue.popleft()
                    stats = None
                    if pending is not None:
                        t0 = time.perf_counter()
                        stats = pending.result()
                        assert valid is not None
                        check_finite_outputs(stats, valid, self.checkpoint_name)
                        check_height_range(stats, valid, self.checkpoint_name, self.meta)
                        timings["model"] += time.perf_counter() - t0
                    flush(windows, stats, valid)

                for win in reader:
                    waiting.append(win)
                    todo = [w for w in waiting if w.data is not None]
                    row_end = win.j == n_cols - 1
                    if len(todo) < batch_size and not row_end:
                        continue
                    if not todo:
                        queue.append((list(waiting), None, None))
                    else:
                        t0 = time.perf_counter()
                        raw, valid = self.runner.to_device([w.data for w in todo], [w.valid for w in todo])
                        x = self.runner.normalise(rescaled(raw, rescale), valid)
                        queue.append((list(waiting), self.runner.submit(x, [w.i * n_cols + w.j for w in todo]), valid))
                        timings["model"] += time.perf_counter() - t0
                        computed += len(todo)
                    waiting.clear()
                    while len(queue) > self.runner.in_flight:
                        finish_oldest()
                while queue:
                    finish_oldest()
                timings["read"] = reader.seconds_reading
            if not stitcher.finished:  # pragma: no cover - the reader yields every window of the rows
                raise RuntimeError("stitcher did not receive every window")
        finally:
            bar.close()
        return StripResult(computed, timings)

    def run(self, ortho: str | Path | OrthoInput, out: str | Path, *, aoi: str | Path | None = None,
            overwrite: bool = False, progress: bool = True, check_outputs: bool = True) -> PredictResult:
        """Predict ``ortho`` into the prediction folder ``out``: one job (:class:`~aerialmtl.inference.job.InputJob`),
        the whole raster as one strip.

        Args:
            ortho: orthophoto GeoTIFF (any size; read window by window), or an input from :meth:`open`.
            out: prediction folder (see :mod:`aerialmtl.formats.prediction`).
            aoi: optional GeoJSON of polygons; only windows intersecting them are computed, pixels
                outside are nodata.
            overwrite: replace existing outputs instead of raising.
            progress: show a tqdm progress bar.
            check_outputs: refuse existing outputs (off when the caller checked every input already).

        Raises:
            OutputExistsError: outputs exist and ``overwrite`` is false.
            InputError / AlignmentError: unusable inputs (messages name the fix).
        """
        started = time.perf_counter()
        given = ortho.path if isinstance(ortho, OrthoInput) else ortho
        folder = OutputFolder(out, "predict", inputs={"ortho": given, "aoi": aoi}, option="out_dir",
                              what="prediction folder")
        with runtime.gdal_env("predict"), folder:
            job = InputJob(self, self.open(ortho), out, aoi=aoi, overwrite=overwrite)
            strip = job.strip(check_outputs=check_outputs, progress=progress)
            return job.commit([strip], started=started)

    # ---- run information --------------------------------------------------------------------------
    @property
    def fingerprint(self) -> str:
        """The model's fingerprint: SHA-256 of the checkpoint bytes that were loaded
        (:func:`~aerialmtl.formats.checkpoint.read_checkpoint`), or of the weights of a model given in memory.
        """
        if self._fingerprint is None:
            assert isinstance(self._checkpoint, tuple)
            self._fingerprint = model_fingerprint(*self._checkpoint)
        return self._fingerprint

    def provenance(self, src: OrthoInput, aoi: str | Path | None) -> dict[str, Any]:
        """What makes the maps of ``src`` (``provenance`` in prediction.json, :mod:`aerialmtl.formats.prediction`)."""
        native = src.native
        engine = getattr(getattr(self, "runner", None), "engine", None) or getattr(self, "engine", None)
        return {
            "checkpoint": self.fingerprint,
            "settings": {"mc_samples": self.mc, "tta": self.tta, "seed": self.seed, "precision": self.precision,
                         "engine": str(getattr(engine, "name", engine) or "torch"),
                         "probabilities": bool(self.probabilities), "aoi": file_fingerprint(aoi),
                         "calibration": self.calibration is not None,
                         "input_rescale": None if src.rescale is None else list(src.rescale)},
            "input": src.fingerprint if src.fingerprint is not None else input_fingerprint(
                src.path, native.width, native.height, list(native.transform), native.crs.to_string()),
        }

    def record_settings(self, src: OrthoInput, aoi: str | Path | None) -> dict[str, Any]:
        """The model's and the settings' fields of ``src``'s ``prediction.json``
        (:class:`~aerialmtl.formats.prediction.PredictionRecord`; the job adds the input's and the run's).
        """
        return {
            "checkpoint": self.checkpoint_name,
            "model": model_summary(self.meta),
            "mc_samples": self.mc,
            "tta": self.tta,
            "seed": self.seed,
            "tile": self.tile,
            "overlap": self.overlap,
            "batch_size": self.resolved_batch_size(src.plan),
            "precision": self.precision,
            "engine": self.runner.engine.name,  # torch if ``auto`` fell back from OpenVINO
            "threads": self.threads.as_dict() if self.device.type == "cpu" else None,
            "device": str(self.device),
            "compile": self.compile,
            "calibration": self.calibration_info(),
            PROVENANCE_KEY: self.provenance(src, aoi),
        }

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


# ---- the tool ----------------------------------------------------------------------------------
def predict_raster(
    ortho: str | Path,
    checkpoint: str | Path | tuple[torch.nn.Module, ModelMeta],
    out_dir: str | Path,
    *,
    mc: int | None = None,
    tile: int = 1024,
    overlap: int = 64,
    batch_size: BatchSize = 2,
    precision: runtime.Precision = "auto",
    device: str = "auto",
    aoi: str | Path | None = None,
    probabilities: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    checkpoint_name: str | None = None,
    max_decode_pixels: int | None = None,
    compile: bool = False,
    seed: int = 0,
    calibration: bool = True,
    rescale_input: bool = False,
    engine: str = "auto",
    tta: bool = False,
    threads: int | str | None = None,
) -> PredictResult:
    """Predict height and land cover (with MC-dropout uncertainty) over a whole orthophoto.

    Builds a :class:`Predictor` and runs it once; the arguments are those of :class:`Predictor` and
    :meth:`Predictor.run` (22 parameters: the one-call form takes every setting of both by name).

    Returns:
        A :class:`PredictResult`.

    Raises:
        OutputExistsError: outputs exist and ``overwrite`` is false.
        InputError / AlignmentError / CheckpointError: unusable inputs (messages name the fix).
    """
    predictor = Predictor(checkpoint, mc=mc, tile=tile, overlap=overlap, batch_size=batch_size, precision=precision,
                          device=device, probabilities=probabilities, max_decode_pixels=max_decode_pixels,
                          compile=compile, seed=seed, checkpoint_name=checkpoint_name, calibration=calibration,
                          rescale_input=rescale_input, engine=engine, tta=tta, threads=threads)
    return predictor.run(ortho, out_dir, aoi=aoi, overwrite=overwrite, progress=progress)


__all__ = ["DEFAULT_MC_SAMPLES", "Predictor", "predict_raster"]
