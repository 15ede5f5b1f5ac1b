"""The exported model file (``aerialmtl export``): its input, outputs and metadata keys.

Written by :func:`aerialmtl.inference.export.export_model`; read by QGIS's Deepness plugin, ONNX runtimes,
OpenVINO and :func:`read_metadata`. The graph has one input ``image`` (float32 ``N×C×S×S``, the
checkpoint's bands standardised ``(raw − mean) / std``) and, by task, the outputs ``height``
(``N×1×S×S``, metres, calibrated as ``predict`` does when the checkpoint has a calibration) and
``classes`` (``N×K×S×S``, softmax probabilities).

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

import json
import math
from pathlib import Path
from typing import Any

from aerialmtl._version import __version__
from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.runtime import openvino_core

#: Name of the graph's input.
INPUT = "image"
#: ONNX opset of the export (onnxruntime ≥ 1.14, OpenVINO ≥ 2023 read it).
OPSET = 18
#: Version of the ``aerialmtl`` metadata object.
METADATA_VERSION = 1
#: Metadata section of an OpenVINO IR's ``rt_info``.
OPENVINO_SECTION = "model_info"
#: The output of an aleatoric height head's spread (metres).
HEIGHT_STD_OUTPUT = "height_std"
#: Deepness's model type per task.
MODEL_TYPES = {"height": "Regressor", HEIGHT_STD_OUTPUT: "Regressor", "classes": "Segmentor"}


def model_tasks(meta: ModelMeta) -> tuple[str, ...]:
    """The checkpoint's exportable outputs in order.

    ``height``, ``height_std`` (a model with an aleatoric height head: its one-pass spread √2·b in metres),
    ``classes``.
    """
    out: list[str] = []
    for t in ("height", "classes"):
        if t in meta.model.tasks:
            out.append(t)
            if t == "height" and meta.model.aleatoric:
                out.append(HEIGHT_STD_OUTPUT)
    return tuple(out)


def export_metadata(meta: ModelMeta, task: str, tile: int, overlap: int, calibrated: bool = False) -> dict[str, str]:
    """The metadata of an export (see the module table), every value JSON-encoded.

    ``calibrated``: the graph applies the checkpoint's height calibration.
    """
    outputs = model_tasks(meta) if task == "all" else (task,)
    k = meta.classes.num_classes if meta.classes is not None else 0
    shapes = {"height": {"shape": ["N", 1, tile, tile], "unit": "m", "meaning": "height above ground"},
              HEIGHT_STD_OUTPUT: {"shape": ["N", 1, tile, tile], "unit": "m",
                                  "meaning": "height standard deviation of the aleatoric head (sqrt(2)·b, one "
                                             "deterministic pass: no MC dropout, no spread calibration)"},
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
        elif task == HEIGHT_STD_OUTPUT:
            values["class_names"] = {"0": "height standard deviation (m)"}
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
        "input_dtype": meta.input_dtype,
        "gsd_m": meta.gsd,
        "crs": meta.crs,
        "classes": ([{"index": i, "code": c.code, "name": c.name, "color": list(c.color)}
                     for i, c in enumerate(meta.classes.classes)] if meta.classes is not None else None),
        "height_calibration": (meta.calibration.summary() if calibrated and meta.calibration is not None
                               else "not applied"),
        "mc_dropout": "not exported: the model is deterministic (dropout off); `aerialmtl predict` gives uncertainty",
    }
    return {key: json.dumps(value) for key, value in values.items()}


def deepness_input_problem(meta: ModelMeta) -> str | None:
    """Why Deepness would feed this model wrong values, or ``None``.

    It reads 8-bit images only (0-255, scaled to 0-1 before its standardisation), so a model trained on other data
    types gets other values.
    """
    if meta.input_dtype is None or meta.input_dtype == "uint8":
        return None
    return (f"the model was trained on {meta.input_dtype} images but QGIS's Deepness plugin feeds 8-bit values "
            "(0-255): in QGIS use it only on 8-bit orthophotos of the same scaling, or predict with "
            "`aerialmtl predict`")


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The metadata of an exported ``.onnx`` or OpenVINO ``.xml`` file, JSON-decoded."""
    path = Path(path)
    if path.suffix == ".xml":
        model = openvino_core().read_model(path)
        info = model.get_rt_info()[OPENVINO_SECTION]
        return {key: json.loads(value.astype(str)) for key, value in info.items()}
    import onnx

    proto = onnx.load(str(path), load_external_data=False)
    return {p.key: json.loads(p.value) for p in proto.metadata_props}


__all__ = ["HEIGHT_STD_OUTPUT", "INPUT", "METADATA_VERSION", "MODEL_TYPES", "OPENVINO_SECTION", "OPSET",
           "deepness_input_problem", "export_metadata", "model_tasks", "read_metadata"]
