"""The prediction folder: what ``aerialmtl predict`` writes and ``evaluate``, the maps notebook and
``buildings`` read.

One folder per orthophoto, all layers Cloud-Optimized GeoTIFFs on one grid (the orthophoto's, at the
model's GSD)::

    height.tif               float32, metres above ground (MC mean), nodata FLOAT_NODATA
    height_std.tif           float32, metres, MC-dropout standard deviation          (T > 1)
    classes.tif              uint8 class index, nodata CLASS_NODATA, colour table,
                             tag CLASS_SCHEME_TAG = the class scheme as JSON
    class_entropy.tif        float32, predictive entropy (nats)                       (T > 1)
    class_mutual_info.tif    float32, mutual information (nats), the epistemic part   (T > 1)
    class_probabilities.tif  K × float32, MC mean class probabilities                 (optional)
    prediction.json          run information (checkpoint, T, tile, overlap, grid, timings)

Layers exist only for the tasks the model has. This module owns the names, tags and nodata values;
every reader and writer imports them from here.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
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

#: The run-information file.
INFO_FILE = "prediction.json"

#: nodata of every float layer.
FLOAT_NODATA = -9999.0
#: nodata of ``classes.tif`` (the ignore index of the class scheme).
CLASS_NODATA = IGNORE_INDEX
#: Dataset tag of ``classes.tif`` holding the class scheme as JSON.
CLASS_SCHEME_TAG = "AERIALMTL_CLASS_SCHEME"


def layer_filename(name: str) -> str:
    """File name of layer ``name`` (``"height"`` → ``"height.tif"``)."""
    return f"{name}.tif"


#: Every file name a prediction folder can hold.
ALL_FILES = tuple(layer_filename(n) for n in LAYERS) + (INFO_FILE,)


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


__all__ = [
    "ALL_FILES", "CLASSES", "CLASS_ENTROPY", "CLASS_MUTUAL_INFO", "CLASS_NODATA", "CLASS_PROBABILITIES",
    "CLASS_SCHEME_TAG", "FLOAT_NODATA", "HEIGHT", "HEIGHT_STD", "INFO_FILE", "LAYERS", "PredictionFolder",
    "layer_filename", "read_class_scheme_tag",
]
