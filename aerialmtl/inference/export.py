"""The inference model as ONNX (with the metadata QGIS model plugins read) or as an OpenVINO IR.

``aerialmtl export CKPT --format onnx --out model.onnx`` (:func:`export_model`) writes the model of a
checkpoint as one self-contained file that runs without aerialmtl or torch: in QGIS through the Deepness
plugin, in onnxruntime, OpenVINO or any ONNX runtime.

**The graph.** One input ``image``: float32 ``N×C×S×S`` (``N`` free, ``S`` = the tile size, a multiple of
32; ``C`` = the checkpoint's bands in its order) *standardised* as in training, ``(raw − mean) / std``
per band, raw being the band values of the orthophoto (0-255 for 8-bit imagery). The normalisation is
not in the graph but in the metadata, in the two forms readers use: Deepness's
``standardization_mean``/``standardization_std`` (applied after it scales 8-bit values to 0-1, so they
are ``mean/255`` and ``std/255``) and ``aerialmtl``'s ``mean``/``std`` in raw units. Outputs, by task:

* ``height``: ``N×1×S×S`` float32, height above ground in metres;
* ``classes``: ``N×K×S×S`` float32, class probabilities (softmax; the class of a pixel is the argmax).

The model is the deterministic one (dropout off): MC-dropout uncertainty stays with ``aerialmtl predict``.

**One model, two tasks.** ``task="all"`` (default) keeps both outputs in one file, for code and runtimes.
QGIS's Deepness plugin takes one kind of model per file, so ``task="height"`` writes a *Regressor* (the
height output alone) and ``task="classes"`` a *Segmentor* (the class probabilities alone), each with the
metadata Deepness reads; both are cut from the same exported graph.

The file's inputs, outputs and metadata are owned by :mod:`aerialmtl.formats.exported_model`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import torch
from torch import nn

from aerialmtl._version import __version__
from aerialmtl.errors import InputError, OutputError, OutputExistsError
from aerialmtl.filesafety import staging_path
from aerialmtl.formats.checkpoint import ModelMeta, load_model
from aerialmtl.formats.exported_model import (
    HEIGHT_STD_OUTPUT,
    INPUT,
    OPENVINO_SECTION,
    OPSET,
    deepness_input_problem,
    export_metadata,
    model_tasks,
)
from aerialmtl.inference.sanity import check_calibration
from aerialmtl.io.outputs import OutputFolder, check_files_not_input
from aerialmtl.models.calibration import Calibration
from aerialmtl.models.config import HEIGHT_SCALE
from aerialmtl.models.mc_dropout import laplace_variance
from aerialmtl.quiet import ignoring_warnings
from aerialmtl.runtime import import_openvino

Format = Literal["onnx", "openvino"]
Task = Literal["all", "height", "height_std", "classes"]
FORMATS: tuple[str, ...] = get_args(Format)
TASKS: tuple[str, ...] = ("all", "height", "height_std", "classes")
class ExportHead(nn.Module):
    """The exported computation: the model's deterministic forward.

    Class logits turned into probabilities, heights through the checkpoint's calibration (when given) as
    ``aerialmtl predict`` applies it.

    ``forward(image)``: ``N×C×S×S`` standardised image → a tuple in the order of ``tasks``:
    height ``N×1×S×S`` (metres) and/or class probabilities ``N×K×S×S``.
    """

    lo: torch.Tensor
    hi: torch.Tensor
    slope: torch.Tensor
    start: torch.Tensor

    def __init__(self, model: nn.Module, tasks: tuple[str, ...], calibration: Calibration | None = None) -> None:
        super().__init__()
        self.model = model
        self.tasks = tasks
        if calibration is not None and not calibration.height_applied:  # validation said: heights unchanged
            calibration = None
        self.calibrated = calibration is not None
        if calibration is not None:  # the piecewise-linear map as segments, 1×(K−1)×1×1 each
            x = torch.tensor(calibration.height_x, dtype=torch.float32)
            y = torch.tensor(calibration.height_y, dtype=torch.float32)
            self.register_buffer("lo", x[:-1].reshape(1, -1, 1, 1))
            self.register_buffer("hi", x[1:].reshape(1, -1, 1, 1))
            self.register_buffer("slope", ((y[1:] - y[:-1]) / (x[1:] - x[:-1])).reshape(1, -1, 1, 1))
            self.register_buffer("start", y[:1].reshape(1, 1, 1, 1))

    def calibrate(self, h: torch.Tensor) -> torch.Tensor:
        """:meth:`~aerialmtl.models.calibration.Calibration.height` with ops every ONNX runtime has.

        A sum of clamped segments instead of a search): ``y_0`` below the first knot, slope 1 beyond the last, ≥ 0.
        """
        segments = (torch.minimum(torch.maximum(h, self.lo), self.hi) - self.lo) * self.slope
        beyond = torch.relu(h - self.hi[:, -1:])
        return torch.relu(self.start + segments.sum(dim=1, keepdim=True) + beyond)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """(N, C, H, W) normalised image → one output per task (height in metres, class probabilities)."""
        out = self.model(image)
        results = []
        for t in self.tasks:
            if t == "classes":
                results.append(torch.softmax(out[t], dim=1))
            elif t == HEIGHT_STD_OUTPUT:  # the aleatoric spread of one pass: sqrt(2)·b
                results.append(laplace_variance(out[HEIGHT_SCALE]).sqrt())
            else:
                results.append(self.calibrate(out[t]) if self.calibrated else out[t])
        return tuple(results)


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_model` wrote.

    ``files`` (the model file first; an IR's weights ``.bin`` after it), the ``outputs`` in graph order, the tile
    size and the metadata.
    """

    files: tuple[Path, ...]
    format: str
    task: str
    outputs: tuple[str, ...]
    tile: int
    metadata: dict[str, str]


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """The exporter's notes (missing optional packages, deprecations) are for torch developers."""
    loggers = [logging.getLogger(n) for n in ("torch.onnx", "torch.export", "torch._dynamo", "onnxscript")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        with ignoring_warnings(), open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
            yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def _onnx_graph(model: nn.Module, meta: ModelMeta, tile: int, path: Path, calibration: bool) -> tuple[str, ...]:
    """Export the deterministic model of every task to ``path`` (one file, weights inside); returns the outputs."""
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError as exc:
        raise InputError(f"exporting to ONNX needs the onnx and onnxscript packages ({exc.name} is missing): "
                         "pip install 'aerialmtl[onnx]'") from None
    tasks = model_tasks(meta)
    head = ExportHead(model.eval(), tasks, meta.calibration if calibration else None).eval()
    example = torch.zeros(2, len(meta.bands), tile, tile)
    with _quiet_exporter(), torch.no_grad():
        torch.onnx.export(head, (example,), str(path), input_names=[INPUT], output_names=list(tasks),
                          dynamic_shapes=({0: torch.export.Dim("batch")},), dynamo=True, opset_version=OPSET,
                          external_data=False, verbose=False)
    return tasks


def _keep_output(src: Path, dst: Path, output: str) -> None:
    """``src`` cut down to the nodes and weights ``output`` needs."""
    import onnx.utils

    onnx.utils.extract_model(str(src), str(dst), [INPUT], [output])


def _write_onnx(graph: Path, out: Path, metadata: dict[str, str], task: str) -> None:
    import onnx

    proto = onnx.load(str(graph))
    del proto.metadata_props[:]
    for key, value in metadata.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    proto.producer_name = "aerialmtl"
    proto.producer_version = __version__
    proto.doc_string = (f"aerialmtl D3-Net, task {task}: input '{INPUT}' standardised per band ((raw - mean) / std, "
                        "see the 'aerialmtl' metadata); outputs height in metres and/or class probabilities")
    onnx.save(proto, str(out))


def _write_openvino(graph: Path, out: Path, metadata: dict[str, str]) -> tuple[Path, ...]:
    ov = import_openvino()
    model = ov.convert_model(str(graph))
    for key, value in metadata.items():
        model.set_rt_info(value, [OPENVINO_SECTION, key])
    ov.save_model(model, str(out), compress_to_fp16=False)  # fp32 weights: the same numbers as the checkpoint
    return out, out.with_suffix(".bin")


def export_model(
    checkpoint: str | Path | tuple[nn.Module, ModelMeta],
    out: str | Path,
    *,
    format: Format = "onnx",
    task: Task = "all",
    tile: int = 512,
    overlap: int = 64,
    calibration: bool = True,
    overwrite: bool = False,
) -> ExportResult:
    """Write the inference model of ``checkpoint`` as ONNX or OpenVINO IR (see the module docstring).

    Args:
        checkpoint: a checkpoint path, or ``(model, meta)``.
        out: the file: ``.onnx`` for ONNX, ``.xml`` for OpenVINO (its weights go to the ``.bin`` beside it).
        format: ``onnx`` or ``openvino``.
        task: ``all`` (every output of the model), ``height`` (a Deepness Regressor) or ``classes`` (a Segmentor).
        tile: input side ``S`` in pixels (a multiple of 32): the tile size QGIS plugins cut the map into.
        overlap: overlap between tiles in pixels, recorded as Deepness's ``tiles_overlap`` percentage.
        calibration: apply the checkpoint's height calibration (:mod:`aerialmtl.models.calibration`) in the
            graph, as ``aerialmtl predict`` does, when it has one.
        overwrite: replace existing files.

    Raises:
        InputError: a bad ``format``/``task``/``tile``/``overlap``, a task the model does not have, or
            ``out`` without the format's extension.
        OutputExistsError: ``out`` exists and ``overwrite`` is false.
    """
    out = Path(out)
    _check_arguments(out, format, task, tile, overlap)
    if isinstance(checkpoint, tuple):
        model, meta = checkpoint
    else:
        model, meta = load_model(checkpoint)
    if calibration and "height" in model_tasks(meta):
        check_calibration(meta, "<in-memory model>" if isinstance(checkpoint, tuple) else str(checkpoint))
    if task != "all" and task not in model_tasks(meta):
        raise InputError(f"the model has no {task} task (its tasks: {', '.join(model_tasks(meta))}); pass "
                         f"‹task=all› or one of its tasks", param="task")
    problem = deepness_input_problem(meta) if task in ("height", "classes") else None
    if problem is not None:
        warnings.warn(problem, stacklevel=2)
    files = (out,) if format == "onnx" else (out, out.with_suffix(".bin"))
    existing = [f for f in files if f.exists()]
    if existing and not overwrite:
        raise OutputExistsError(f"'{existing[0]}' exists; pass ‹overwrite=True› to replace it, or another ‹out›")
    if not isinstance(checkpoint, tuple):
        check_files_not_input(files, {"checkpoint": checkpoint}, option="out")

    metadata = export_metadata(meta, task, tile, overlap, calibrated=calibration and meta.calibration is not None)
    outputs = _write_files(model, meta, files, format, task, tile, calibration, metadata)
    return ExportResult(files, format, task, outputs, tile, metadata)


def _check_arguments(out: Path, format: str, task: str, tile: int, overlap: int) -> None:
    """Refuse a bad ``format``/``task``/``tile``/``overlap`` or an ``out`` without the format's extension.

    An :class:`~aerialmtl.errors.InputError` naming the argument, before the checkpoint is read.
    """
    if format not in FORMATS:
        raise InputError(f"‹format› must be one of {', '.join(FORMATS)}, got {format!r}", param="format")
    if task not in TASKS:
        raise InputError(f"‹task› must be one of {', '.join(TASKS)}, got {task!r}", param="task")
    if tile < 32 or tile % 32:
        raise InputError(f"‹tile› must be a positive multiple of 32 pixels, got {tile}; pass e.g. ‹tile=512›",
                         param="tile")
    if not 0 <= overlap < tile:
        raise InputError(f"‹overlap› must be within 0..{tile - 1} pixels (less than ‹tile›), got {overlap}",
                         param="overlap")
    suffix = ".onnx" if format == "onnx" else ".xml"
    if out.suffix.lower() != suffix:
        raise InputError(f"‹out› of a {format} export must end in {suffix}, got '{out}'; pass e.g. "
                         f"‹out={out.with_suffix(suffix).name}›", param="out")


def _write_files(model: nn.Module, meta: ModelMeta, files: tuple[Path, ...], format: str, task: str, tile: int,
                 calibration: bool, metadata: dict[str, str]) -> tuple[str, ...]:
    """Export the graph, cut it to ``task`` and write it as ``format`` with ``metadata``; returns its outputs.

    To ``files`` (the ``.onnx``, or the ``.xml`` and its ``.bin``), staged beside them and renamed whole.

    Raises:
        OutputError: the folder is in use or cannot be written.
    """
    out = files[0]
    try:
        # the folder held for the run (aerialmtl.io.outputs); the files staged in .NAME.partial/ beside them
        with OutputFolder(out.parent, "export", option="out") as folder, _staging_dir(folder, out) as tmp:
            graph = Path(tmp) / "all.onnx"
            outputs = _onnx_graph(model, meta, tile, graph, calibration)
            if task != "all" and len(outputs) > 1:
                _keep_output(graph, Path(tmp) / "task.onnx", task)
                graph, outputs = Path(tmp) / "task.onnx", (task,)
            staged = Path(tmp) / out.name
            if format == "onnx":
                _write_onnx(graph, staged, metadata, task)
                written: tuple[Path, ...] = (staged,)
            else:
                written = _write_openvino(graph, staged, metadata)
            for src, dst in zip(written, files):  # whole files only at the final paths
                os.replace(src, dst)
    except OSError as exc:
        if isinstance(exc, OutputError):  # the folder in use by another process, or not creatable
            raise
        raise OutputError(f"cannot write '{out}': {exc.strerror or exc}; choose a writable ‹out›") from exc
    return outputs


@contextlib.contextmanager
def _staging_dir(folder: OutputFolder, out: Path) -> Iterator[Path]:
    """``.NAME.partial/`` beside ``out``, removed afterwards (one a killed export left is removed first)."""
    folder.remove_leftovers([out.name])
    stage = staging_path(out)
    stage.mkdir()
    try:
        yield stage
    finally:
        shutil.rmtree(stage, ignore_errors=True)


__all__ = ["FORMATS", "TASKS", "ExportHead", "ExportResult", "export_model"]
