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

**Metadata** (ONNX ``metadata_props``; in an OpenVINO IR, ``rt_info`` under ``model_info``), every value
JSON-encoded, the keys of Deepness's documentation plus one ``aerialmtl`` object:

=========================  ===================================================================
``model_type``             ``"Regressor"`` (height) / ``"Segmentor"`` (classes); absent for ``all``
``class_names``            ``{"0": name, ...}``: the classes, or ``{"0": "height (m)"}`` for height
``resolution``             the model's GSD in centimetres per pixel
``tile_size``              ``S``
``tiles_overlap``          overlap between tiles in percent of ``S`` (rounded up)
``standardization_mean``   per band, ``mean / 255`` (Deepness scales 8-bit input to 0-1 first)
``standardization_std``    per band, ``std / 255``
``reg_output_scaling``     ``1.0`` (height task: the output is already in metres)
``aerialmtl``              format version, package version, task, outputs (name, shape, unit), bands,
                           band names, ``mean``/``std`` in raw units, GSD (m), training CRS, the classes
                           (code, name, colour) and the input convention
=========================  ===================================================================
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import tempfile
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
from torch import nn

from aerialmtl import __version__
from aerialmtl.errors import InputError, OutputError, OutputExistsError
from aerialmtl.formats.checkpoint import ModelMeta

Format = Literal["onnx", "openvino"]
Task = Literal["all", "height", "classes"]
FORMATS: tuple[str, ...] = ("onnx", "openvino")
TASKS: tuple[str, ...] = ("all", "height", "classes")
#: Name of the graph's input.
INPUT = "image"
#: ONNX opset of the export (onnxruntime ≥ 1.14, OpenVINO ≥ 2023 read it).
OPSET = 18
#: Version of the ``aerialmtl`` metadata object.
METADATA_VERSION = 1
#: Metadata section of an OpenVINO IR's ``rt_info``.
OPENVINO_SECTION = "model_info"
#: Deepness's model type per task.
MODEL_TYPES = {"height": "Regressor", "classes": "Segmentor"}


class ExportHead(nn.Module):
    """The exported computation: the model's deterministic forward, class logits turned into probabilities.

    ``forward(image)``: ``N×C×S×S`` standardised image → a tuple in the order of ``tasks``:
    height ``N×1×S×S`` (metres) and/or class probabilities ``N×K×S×S``.
    """

    def __init__(self, model: nn.Module, tasks: tuple[str, ...]) -> None:
        super().__init__()
        self.model = model
        self.tasks = tasks

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.model(image)
        return tuple(torch.softmax(out[t], dim=1) if t == "classes" else out[t] for t in self.tasks)


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_model` wrote: ``files`` (the model file first; an IR's weights ``.bin`` after it),
    the ``outputs`` in graph order, the tile size and the metadata."""

    files: tuple[Path, ...]
    format: str
    task: str
    outputs: tuple[str, ...]
    tile: int
    metadata: dict[str, str]


def model_tasks(meta: ModelMeta) -> tuple[str, ...]:
    """The checkpoint's tasks in output order (``height`` before ``classes``)."""
    return tuple(t for t in ("height", "classes") if t in meta.model.tasks)


def export_metadata(meta: ModelMeta, task: str, tile: int, overlap: int) -> dict[str, str]:
    """The metadata of an export (see the module table), every value JSON-encoded."""
    outputs = model_tasks(meta) if task == "all" else (task,)
    k = meta.classes.num_classes if meta.classes is not None else 0
    shapes = {"height": {"shape": ["N", 1, tile, tile], "unit": "m", "meaning": "height above ground"},
              "classes": {"shape": ["N", k, tile, tile], "unit": "1",
                          "meaning": "class probabilities (softmax over the class axis)"}}
    values: dict[str, Any] = {}
    if task in MODEL_TYPES:
        values["model_type"] = MODEL_TYPES[task]
        if task == "classes" and meta.classes is not None:
            values["class_names"] = {str(i): c.name for i, c in enumerate(meta.classes.classes)}
        elif task == "height":
            values["class_names"] = {"0": "height (m)"}
            values["reg_output_scaling"] = 1.0
    values.update({
        "resolution": round(meta.gsd * 100.0, 6),
        "tile_size": tile,
        "tiles_overlap": max(0, min(99, math.ceil(100.0 * overlap / tile - 1e-9))),  # at least overlap px
        "standardization_mean": [m / 255.0 for m in meta.mean],
        "standardization_std": [s / 255.0 for s in meta.std],
    })
    values["aerialmtl"] = {
        "metadata_version": METADATA_VERSION,
        "aerialmtl_version": __version__,
        "task": task,
        "input": {"name": INPUT, "shape": ["N", len(meta.bands), tile, tile],
                  "standardisation": "(raw - mean) / std per band, raw = the orthophoto's band values"},
        "outputs": {name: shapes[name] for name in outputs},
        "bands": list(meta.bands),
        "band_names": list(meta.band_names),
        "mean": list(meta.mean),
        "std": list(meta.std),
        "gsd_m": meta.gsd,
        "crs": meta.crs,
        "classes": ([{"index": i, "code": c.code, "name": c.name, "color": list(c.color)}
                     for i, c in enumerate(meta.classes.classes)] if meta.classes is not None else None),
        "mc_dropout": "not exported: the model is deterministic (dropout off); `aerialmtl predict` gives uncertainty",
    }
    return {key: json.dumps(value) for key, value in values.items()}


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The metadata of an exported ``.onnx`` or OpenVINO ``.xml`` file, JSON-decoded."""
    path = Path(path)
    if path.suffix == ".xml":
        import openvino as ov

        model = ov.Core().read_model(path)
        info = model.get_rt_info()[OPENVINO_SECTION]
        return {key: json.loads(value.astype(str)) for key, value in info.items()}
    import onnx

    proto = onnx.load(str(path), load_external_data=False)
    return {p.key: json.loads(p.value) for p in proto.metadata_props}


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """The exporter's notes (missing optional packages, deprecations) are for torch developers."""
    loggers = [logging.getLogger(n) for n in ("torch.onnx", "torch.export", "torch._dynamo", "onnxscript")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
            warnings.simplefilter("ignore")
            yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def _onnx_graph(model: nn.Module, meta: ModelMeta, tile: int, path: Path) -> tuple[str, ...]:
    """Export the deterministic model of every task to ``path`` (one file, weights inside); returns the outputs."""
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError as exc:
        raise InputError(f"exporting to ONNX needs the onnx and onnxscript packages ({exc.name} is missing): "
                         "pip install 'aerialmtl[onnx]'") from None
    tasks = model_tasks(meta)
    head = ExportHead(model.eval(), tasks).eval()
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
    import openvino as ov

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
        overwrite: replace existing files.

    Raises:
        InputError: a bad ``format``/``task``/``tile``/``overlap``, a task the model does not have, or
            ``out`` without the format's extension.
        OutputExistsError: ``out`` exists and ``overwrite`` is false.
    """
    out = Path(out)
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
    if isinstance(checkpoint, tuple):
        model, meta = checkpoint
    else:
        from aerialmtl.formats.checkpoint import load_model

        model, meta = load_model(checkpoint)
    if task != "all" and task not in model_tasks(meta):
        raise InputError(f"the model has no {task} task (its tasks: {', '.join(model_tasks(meta))}); pass "
                         f"‹task=all› or one of its tasks", param="task")
    files = (out,) if format == "onnx" else (out, out.with_suffix(".bin"))
    existing = [f for f in files if f.exists()]
    if existing and not overwrite:
        raise OutputExistsError(f"'{existing[0]}' exists; pass ‹overwrite=True› to replace it, or another ‹out›")
    if not out.parent.is_dir():
        out.parent.mkdir(parents=True, exist_ok=True)

    metadata = export_metadata(meta, task, tile, overlap)
    try:
        with tempfile.TemporaryDirectory(prefix=".aerialmtl-export-", dir=out.parent) as tmp:
            graph = Path(tmp) / "all.onnx"
            outputs = _onnx_graph(model, meta, tile, graph)
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
        raise OutputError(f"cannot write '{out}': {exc.strerror or exc}; choose a writable ‹out›") from exc
    return ExportResult(files, format, task, outputs, tile, metadata)


__all__ = ["FORMATS", "INPUT", "MODEL_TYPES", "OPSET", "TASKS", "ExportHead", "ExportResult", "export_metadata",
           "export_model", "model_tasks", "read_metadata"]
