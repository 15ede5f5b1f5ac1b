"""The prediction folder: what ``aerialmtl predict`` writes and ``evaluate``, the maps notebook and
``buildings`` read.

One folder per orthophoto, all layers Cloud-Optimized GeoTIFFs on one grid (the orthophoto's, at the
model's GSD)::

    height.tif               float32, metres above ground (MC mean), nodata FLOAT_NODATA
    height_std.tif           float32, metres, predictive standard deviation: MC dropout (T > 1),
                             plus the aleatoric Laplace scale of a model with model.aleatoric (any T)
    classes.tif              uint8 class index, nodata CLASS_NODATA, colour table,
                             tag CLASS_SCHEME_TAG = the class scheme as JSON
    class_entropy.tif        float32, predictive entropy (nats)                       (T > 1)
    class_mutual_info.tif    float32, mutual information (nats), the epistemic part   (T > 1)
    class_probabilities.tif  K × float32, MC mean class probabilities                 (optional)
    <layer>.qml              QGIS style of each layer (:func:`style_filename`; QGIS applies a .qml
                             named like the raster when it opens it; :mod:`aerialmtl.formats.qgis_style`)
    item.json                STAC 1.1 Item describing the folder (:mod:`aerialmtl.formats.stac`)
    prediction.json          run information (checkpoint, T, tile, overlap, grid, timings)

Layers exist only for the tasks the model has. This module owns the names, tags and nodata values
and the output schema (:func:`prediction_layers`: one :class:`LayerSpec` per layer, which the
stitcher fills and the writer writes); every reader and writer imports them from here.

A run over several orthophotos writes one such folder per input (named after the file stem) and one
GDAL VRT mosaic per layer beside them, ``<layer>.mosaic.vrt`` (:func:`mosaic_filename`) with its QGIS
style ``<layer>.mosaic.qml``, so that a GIS opens one layer over all inputs, and a STAC Collection
``collection.json`` (:data:`COLLECTION_FILE`) linking the items of the inputs and the mosaics.

A folder is complete for a run (:meth:`PredictionFolder.check`, :meth:`PredictionFolder.is_complete`) when
``prediction.json`` exists (the writer renames it into place last, so a run that stopped earlier leaves
no complete-looking folder), every file it lists exists, each layer with the size it records
(``file_sizes``; the styles and ``item.json`` may be edited) and as a raster of the recorded grid, and its
``provenance`` matches the run at hand:

    provenance.checkpoint   :func:`checkpoint_fingerprint`: SHA-256 of the checkpoint file (of the weights
                            and metadata for a model given in memory)
    provenance.settings     what changes the maps: MC samples T, seed, precision, engine, the class
                            probabilities layer, the AOI (:func:`file_fingerprint` of the GeoJSON),
                            whether the checkpoint's calibration was applied, the linear map of
                            ``rescale_input`` (``input_rescale``, :mod:`aerialmtl.inference.sanity`)
    provenance.input        :func:`input_fingerprint` of the orthophoto: resolved path, size and mtime
                            (ns) of a local file; the GDAL path, size, transform and CRS of a remote or
                            virtual one (no ``stat`` there)

Window size, overlap, batch size and device are not part of it: they change speed and memory, and the
maps only within the blending of window seams. ``prediction.json`` is also the proof of what a run owns:
``overwrite`` removes a stale layer of an earlier run only when that run's ``prediction.json`` lists it
(:meth:`PredictionFolder.owned_files`).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.errors import InputError

#: Layer names, in the order a prediction folder lists them (file ``<name>.tif``).
HEIGHT = "height"
HEIGHT_STD = "height_std"
CLASSES = "classes"
CLASS_ENTROPY = "class_entropy"
CLASS_MUTUAL_INFO = "class_mutual_info"
CLASS_PROBABILITIES = "class_probabilities"
LAYERS = (HEIGHT, HEIGHT_STD, CLASSES, CLASS_ENTROPY, CLASS_MUTUAL_INFO, CLASS_PROBABILITIES)

#: Unit of each float layer (``class_probabilities``: none).
LAYER_UNITS = {HEIGHT: "m", HEIGHT_STD: "m", CLASS_ENTROPY: "nats", CLASS_MUTUAL_INFO: "nats"}

#: The run-information file.
INFO_FILE = "prediction.json"
#: The STAC Item of a prediction folder.
ITEM_FILE = "item.json"
#: The STAC Collection a run over several inputs writes beside their folders and the mosaics.
COLLECTION_FILE = "collection.json"

#: nodata of every float layer.
FLOAT_NODATA = -9999.0
#: nodata of ``classes.tif`` (the ignore index of the class scheme).
CLASS_NODATA = IGNORE_INDEX
#: Dataset tag of ``classes.tif`` holding the class scheme as JSON.
CLASS_SCHEME_TAG = "AERIALMTL_CLASS_SCHEME"


def layer_filename(name: str) -> str:
    """File name of layer ``name`` (``"height"`` → ``"height.tif"``)."""
    return f"{name}.tif"


def style_filename(name: str) -> str:
    """File name of the QGIS style of layer ``name`` (``"height"`` → ``"height.qml"``).

    QGIS applies ``<raster name without its extension>.qml`` when it opens a raster.
    """
    return f"{name}.qml"


#: Every file name a prediction folder can hold (``prediction.json`` last).
ALL_FILES = (tuple(layer_filename(n) for n in LAYERS) + tuple(style_filename(n) for n in LAYERS)
             + (ITEM_FILE, INFO_FILE))


def folder_files(names: Iterable[str]) -> list[str]:
    """Every file a prediction folder with layers ``names`` holds: the layers, their QGIS styles, the STAC
    item and ``prediction.json`` (last). A run claims all of them before writing, so that a user's own
    ``height.qml`` or ``item.json`` in ``--out`` is never replaced without ``--overwrite``."""
    names = list(names)
    return ([layer_filename(n) for n in names] + [style_filename(n) for n in names] + [ITEM_FILE, INFO_FILE])


def mosaic_filename(name: str) -> str:
    """File name of the VRT mosaic of layer ``name`` over all inputs of a run (``"height.mosaic.vrt"``)."""
    return f"{name}.mosaic.vrt"


def mosaic_style_filename(name: str) -> str:
    """File name of the QGIS style of the mosaic of layer ``name`` (``"height.mosaic.qml"``)."""
    return f"{name}.mosaic.qml"


def mosaic_files(names: Iterable[str]) -> list[str]:
    """Every file a run over several inputs writes beside their folders for layers ``names``: each layer's VRT
    mosaic and its QGIS style, and the STAC ``collection.json``."""
    names = list(names)
    return [mosaic_filename(n) for n in names] + [mosaic_style_filename(n) for n in names] + [COLLECTION_FILE]


# ---- the output schema -------------------------------------------------------------------------
@dataclass(frozen=True)
class LayerSpec:
    """One output raster of a prediction folder.

    Attributes:
        name: layer name (file :func:`layer_filename`).
        count, dtype, nodata: bands, numpy dtype name, nodata value.
        descriptions: one description per band.
        units: unit per band (``"m"``, ``"nats"``, ...; empty for none).
        categorical: class indices (``mode`` overviews) rather than continuous values.
        colormap: optional GDAL colour table of band 1.
        tags: dataset tags; ``band_tags``: tags per band (1-based index → mapping).
    """

    name: str
    count: int
    dtype: str
    nodata: float | int
    descriptions: tuple[str, ...]
    units: tuple[str, ...] = ()
    categorical: bool = False
    colormap: dict[int, tuple[int, int, int, int]] | None = None
    tags: dict[str, str] = field(default_factory=dict)
    band_tags: dict[int, dict[str, str]] = field(default_factory=dict)

    @property
    def filename(self) -> str:
        return layer_filename(self.name)


def prediction_layers(
    tasks: Sequence[str], classes: ClassScheme | None, mc: int, probabilities: bool = False, aleatoric: bool = False,
    tta: bool = False,
) -> tuple[LayerSpec, ...]:
    """The layers a prediction writes, in :data:`LAYERS` order.

    Args:
        tasks: the model's tasks (``"height"``, ``"classes"``).
        classes: the class scheme (required with the ``classes`` task).
        mc: MC-dropout samples T; uncertainty layers only for T > 1 (``height_std`` at T = 1 too with
            ``aleatoric``).
        probabilities: also the K-band ``class_probabilities`` layer.
        aleatoric: the model's height head predicts a Laplace scale: ``height_std`` is the predictive
            spread (MC dropout and the aleatoric scale).
        tta: test-time augmentation (8 views): uncertainty layers at any T.
    """
    specs: list[LayerSpec] = []
    unc = mc > 1 or tta
    if HEIGHT in tasks:
        specs.append(LayerSpec(HEIGHT, 1, "float32", FLOAT_NODATA, ("height above ground (MC mean)",),
                               (LAYER_UNITS[HEIGHT],)))
        if unc or aleatoric:
            parts = (["MC dropout"] if mc > 1 else []) + (["test-time augmentation"] if tta else []) + (
                ["aleatoric scale"] if aleatoric else [])
            what = ", ".join(parts)
            specs.append(LayerSpec(HEIGHT_STD, 1, "float32", FLOAT_NODATA,
                                   (f"height standard deviation ({what})",), (LAYER_UNITS[HEIGHT_STD],)))
    if CLASSES in tasks:
        if classes is None:
            raise InputError("the classes task needs a class scheme; pass the checkpoint's ModelMeta.classes")
        names = {str(i): n for i, n in enumerate(classes.names)}
        specs.append(LayerSpec(
            CLASSES, 1, "uint8", CLASS_NODATA, ("land-cover class index",), ("",), categorical=True,
            colormap=classes.colormap(), tags={CLASS_SCHEME_TAG: json.dumps(classes.to_dict())},
            band_tags={1: {"class_names": json.dumps(names), **{f"CLASS_{i}": n for i, n in names.items()}}},
        ))
        if unc:
            specs.append(LayerSpec(CLASS_ENTROPY, 1, "float32", FLOAT_NODATA,
                                   ("predictive entropy of the class probabilities",),
                                   (LAYER_UNITS[CLASS_ENTROPY],)))
            specs.append(LayerSpec(CLASS_MUTUAL_INFO, 1, "float32", FLOAT_NODATA,
                                   ("mutual information (epistemic part of the entropy)",),
                                   (LAYER_UNITS[CLASS_MUTUAL_INFO],)))
        if probabilities:
            specs.append(LayerSpec(CLASS_PROBABILITIES, classes.num_classes, "float32", FLOAT_NODATA,
                                   tuple(f"P({n})" for n in classes.names), ("",) * classes.num_classes))
    return tuple(specs)


def read_class_scheme_tag(path: str | Path) -> ClassScheme | None:
    """The :class:`ClassScheme` stored in the :data:`CLASS_SCHEME_TAG` tag of ``path``, or ``None``."""
    from aerialmtl.io.align import open_raster

    with open_raster(path, "predicted classes") as src:
        text = src.tags().get(CLASS_SCHEME_TAG) or src.tags(1).get(CLASS_SCHEME_TAG)
    if not text:
        return None
    try:
        return ClassScheme.from_dict(json.loads(text))
    except (ValueError, TypeError) as exc:
        raise InputError(
            f"'{path}': tag {CLASS_SCHEME_TAG} is not a valid class scheme ({exc}); pass ‹classes› with "
            "the scheme the model was trained with"
        ) from exc


@dataclass(frozen=True)
class PredictionFolder:
    """A prediction folder on disk (reading side).

    Attributes:
        path: the folder.
    """

    path: Path

    def __init__(self, path: str | Path) -> None:
        object.__setattr__(self, "path", Path(path))

    def layer_path(self, name: str) -> Path:
        """Path of layer ``name`` (whether or not it exists)."""
        return self.path / layer_filename(name)

    def layers(self) -> dict[str, Path]:
        """Layer name → path, for the layers present, in :data:`LAYERS` order."""
        return {n: self.layer_path(n) for n in LAYERS if self.layer_path(n).is_file()}

    @property
    def info_path(self) -> Path:
        return self.path / INFO_FILE

    def info(self) -> dict[str, Any]:
        """The parsed ``prediction.json`` (empty when the folder has none)."""
        if not self.info_path.is_file():
            return {}
        return dict(json.loads(self.info_path.read_text(encoding="utf-8")))

    def class_scheme(self) -> ClassScheme | None:
        """The class scheme tagged on ``classes.tif`` (``None`` without classes or tag)."""
        path = self.layer_path(CLASSES)
        return read_class_scheme_tag(path) if path.is_file() else None

    def owned_files(self) -> list[str]:
        """Files an earlier run here wrote, as its ``prediction.json`` lists them (with itself); [] without one."""
        try:
            files = self.info().get("files")
        except (OSError, ValueError, AttributeError):
            return []
        if not isinstance(files, dict):
            return []
        names = [str(n) for n in files.values() if str(n) in ALL_FILES]
        return [*names, INFO_FILE] if names else []

    def check(self, expected: Mapping[str, Any] | None = None) -> str | None:
        """Why this folder is not a finished prediction of the run ``expected`` describes (``None``: it is).

        Args:
            expected: the ``provenance`` of the run at hand (:meth:`Predictor.provenance
                <aerialmtl.inference.predict.Predictor.provenance>`); ``None`` checks only that a run finished
                here and its files are whole.

        Returns:
            ``None`` when complete, else a short reason for a summary (``"height.tif is truncated ..."``,
            ``"made with another model"``, ...).
        """
        try:
            info = self.info()
        except (OSError, ValueError):
            return f"its {INFO_FILE} is unreadable"
        files = info.get("files")
        if not info:
            return f"it has no {INFO_FILE} (no run finished there)"
        if not isinstance(files, dict) or not files:
            return f"its {INFO_FILE} lists no layer"
        sizes = info.get("file_sizes") or {}
        grid = info.get("grid") or {}
        for key, name in files.items():
            path = self.path / str(name)
            if not path.is_file():
                return f"{name} is missing"
            size = sizes.get(str(name))
            if size is not None and path.stat().st_size != size:
                return f"{name} is truncated or was changed ({path.stat().st_size} bytes, {INFO_FILE} says {size})"
            problem = _layer_problem(path, grid) if key in LAYERS else None  # layers, not styles or STAC
            if problem:
                return problem
        if expected is None:
            return None
        recorded = info.get(PROVENANCE_KEY)
        if not isinstance(recorded, dict):
            return f"its {INFO_FILE} records no provenance (made by an older version)"
        for key, what in (("checkpoint", "another model"), ("input", "another or a changed orthophoto")):
            if recorded.get(key) != expected.get(key):
                return f"it was made with {what}"
        old, new = recorded.get("settings") or {}, expected.get("settings") or {}
        changed = [f"{k} {old.get(k)!r} → {new.get(k)!r}" for k in sorted(set(old) | set(new))
                   if old.get(k) != new.get(k)]
        if changed:
            return f"it was made with other settings ({', '.join(changed)})"
        return None

    def is_complete(self, expected: Mapping[str, Any] | None = None) -> bool:
        """Whether a finished prediction of the run ``expected`` describes is here (see :meth:`check`)."""
        return self.check(expected) is None


def _layer_problem(path: Path, grid: Mapping[str, Any]) -> str | None:
    """Why layer ``path`` does not open as a raster of ``grid`` (``None`` when it does)."""
    import rasterio
    from rasterio.errors import RasterioError

    try:
        with rasterio.open(path) as src:
            shape = (src.width, src.height)
    except (RasterioError, OSError) as exc:
        return f"{path.name} does not open ({' '.join(str(exc).split())[:120]})"
    want = (grid.get("width"), grid.get("height"))
    if None not in want and shape != want:
        return f"{path.name} is {shape[0]}×{shape[1]} px, {INFO_FILE} says {want[0]}×{want[1]}"
    return None


# ---- provenance ---------------------------------------------------------------------------------
#: The ``prediction.json`` key of a run's provenance (see the module docstring).
PROVENANCE_KEY = "provenance"


def checkpoint_fingerprint(path: str | Path) -> str:
    """``sha256:<hex>`` of a checkpoint file's bytes (streamed)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return f"sha256:{digest.hexdigest()}"


def file_fingerprint(path: str | Path | None) -> dict[str, Any] | None:
    """Resolved path, size and mtime (ns) of a local file (``None`` for ``None``); the path alone otherwise."""
    if path is None:
        return None
    from aerialmtl.io.paths import gdal_path, is_local

    if not is_local(path):
        return {"path": gdal_path(path)}
    st = os.stat(path)
    return {"path": str(Path(path).resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def input_fingerprint(path: str | Path, width: int, height: int, transform: Sequence[float],
                      crs: str) -> dict[str, Any]:
    """The fingerprint of an orthophoto: :func:`file_fingerprint` of a local file; for a remote or virtual
    path (no ``stat``) the GDAL path with the raster's size, geotransform and CRS."""
    from aerialmtl.io.paths import is_local

    fp = file_fingerprint(path)
    assert fp is not None
    if not is_local(path):
        fp.update(width=int(width), height=int(height), transform=[float(v) for v in transform][:6], crs=str(crs))
    return fp


__all__ = [
    "ALL_FILES", "CLASSES", "CLASS_ENTROPY", "CLASS_MUTUAL_INFO", "CLASS_NODATA", "CLASS_PROBABILITIES",
    "CLASS_SCHEME_TAG", "COLLECTION_FILE", "FLOAT_NODATA", "HEIGHT", "HEIGHT_STD", "INFO_FILE", "ITEM_FILE", "LAYERS",
    "LAYER_UNITS",
    "LayerSpec", "PredictionFolder", "folder_files", "layer_filename", "mosaic_files", "mosaic_filename",
    "mosaic_style_filename",
    "prediction_layers", "read_class_scheme_tag", "style_filename",
    "PROVENANCE_KEY", "checkpoint_fingerprint", "file_fingerprint", "input_fingerprint",
]
