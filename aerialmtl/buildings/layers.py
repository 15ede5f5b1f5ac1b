"""The layers of a prediction folder that building extraction reads, one block at a time.

:class:`BuildingLayers` opens ``classes.tif`` (which class is a building), ``height.tif`` (roof heights),
and when present ``height_std.tif``, ``class_entropy.tif`` (or ``class_probabilities.tif``) and a DTM, all
on the grid of ``classes.tif``; :meth:`BuildingLayers.read` returns one window of each as arrays.

Which classes are buildings comes from the class scheme tagged on ``classes.tif``
(:data:`~aerialmtl.formats.prediction.CLASS_SCHEME_TAG`): every class whose name contains the word
"building" or "buildings" (any case) — ``building`` (synthetic), ``Building`` (ISPRS), ``Residential
buildings`` and ``Non-residential buildings`` (DFC 2018). :func:`building_class_indices` takes explicit
names or indices instead.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from rasterio.windows import Window

from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.errors import InputError
from aerialmtl.formats.prediction import (
    CLASS_ENTROPY,
    CLASS_PROBABILITIES,
    CLASS_SCHEME_TAG,
    CLASSES,
    HEIGHT,
    HEIGHT_STD,
    PredictionFolder,
)
from aerialmtl.io.align import AlignedRaster, Grid, LayerKind, grid_of, open_raster
from aerialmtl.io.units import metres_per_unit

#: Class names recognised as buildings when none are given.
BUILDING_NAME = re.compile(r"\bbuildings?\b", re.IGNORECASE)


def building_class_indices(scheme: ClassScheme | None,
                           building_classes: Sequence[str | int] | None = None) -> list[int]:
    """Indices (in ``classes.tif``) of the building class(es).

    Args:
        scheme: the class scheme of the prediction (``None`` when ``classes.tif`` has no scheme tag).
        building_classes: class names (case-insensitive) or indices; default: every class of ``scheme``
            whose name contains the word "building(s)".

    Raises:
        InputError: no class matches, a name is not in the scheme, an index is out of range, or names are
            needed but there is no scheme.
    """
    if not building_classes:
        if scheme is None:
            raise InputError(
                f"classes.tif has no {CLASS_SCHEME_TAG} tag, so the building class cannot be recognised by name; "
                "pass building_classes with the class index(es) of buildings, e.g. [2]"
            )
        found = [i for i, name in enumerate(scheme.names) if BUILDING_NAME.search(name)]
        if not found:
            raise InputError(
                f"class scheme '{scheme.name}' has no class named 'building(s)' (classes: "
                f"{', '.join(repr(n) for n in scheme.names)}); pass building_classes with the name(s) or index(es) "
                "of the building classes"
            )
        return found
    out: list[int] = []
    k = scheme.num_classes if scheme is not None else IGNORE_INDEX
    for item in building_classes:
        text = str(item).strip()
        if text.lstrip("-").isdigit():
            idx = int(text)
            if not 0 <= idx < k:
                raise InputError(f"building_classes: class index {idx} is not in 0..{k - 1}")
        elif scheme is None:
            raise InputError(
                f"building_classes: cannot look up the class name {text!r} because classes.tif has no "
                f"{CLASS_SCHEME_TAG} tag; give class indices instead"
            )
        else:
            matches = [i for i, n in enumerate(scheme.names) if n.strip().casefold() == text.casefold()]
            if not matches:
                raise InputError(
                    f"building_classes: {text!r} is not a class of scheme '{scheme.name}' (classes: "
                    f"{', '.join(repr(n) for n in scheme.names)})"
                )
            idx = matches[0]
        if idx not in out:
            out.append(idx)
    return out


class BuildingLayers:
    """The layers building extraction reads, opened on the grid of ``classes.tif``.

    Args:
        pred_dir: prediction folder (``classes.tif`` and ``height.tif`` required).
        dtm: optional terrain model (metres, any CRS/GSD; resampled bilinearly onto the grid).

    Attributes:
        grid: the grid of ``classes.tif``.
        scheme: its class scheme (``None`` without tag).
        num_classes: K, for the confidence 1 − entropy / ln K.
        metres_per_unit: metres per CRS unit.
        available: names of the optional layers found (``height_std``, ``confidence``, ``dtm``).

    Raises:
        InputError: missing folder or layer, layers on different grids, no or geographic CRS.
    """

    def __init__(self, pred_dir: str | Path, dtm: str | Path | None = None) -> None:
        folder = PredictionFolder(pred_dir)
        if not folder.path.is_dir():
            raise InputError(f"prediction folder '{folder.path}' does not exist; pass the --out folder of "
                             "`aerialmtl predict`")
        present = folder.layers()
        for name in (CLASSES, HEIGHT):
            if name not in present:
                raise InputError(
                    f"prediction folder '{folder.path}' has no {folder.layer_path(name).name}; buildings need the "
                    "classes and heights of a multi-task model: predict with a checkpoint that has both tasks"
                )
        self.folder = folder
        self.scheme = folder.class_scheme()
        self._open: list[AlignedRaster] = []
        try:
            with open_raster(present[CLASSES], "prediction classes.tif") as src:
                self.grid: Grid = grid_of(src)
            self.metres_per_unit = metres_per_unit(self.grid.crs, "prediction", present[CLASSES])
            self.classes = self._layer(present[CLASSES], "labels", "prediction classes.tif")
            self.height = self._layer(present[HEIGHT], "height", "prediction height.tif")
            self.height_std = (self._layer(present[HEIGHT_STD], "height", "prediction height_std.tif")
                               if HEIGHT_STD in present else None)
            self.entropy = self.probabilities = None
            if CLASS_ENTROPY in present:
                self.entropy = self._layer(present[CLASS_ENTROPY], "height", "prediction class_entropy.tif")
            elif CLASS_PROBABILITIES in present:
                self.probabilities = self._layer(present[CLASS_PROBABILITIES], "height",
                                                 "prediction class_probabilities.tif", all_bands=True)
            self.dtm = self._layer(dtm, "height", "DTM", same_grid=False) if dtm is not None else None
        except BaseException:
            self.close()
            raise
        if self.scheme is not None:
            self.num_classes = self.scheme.num_classes
        elif self.probabilities is not None:
            self.num_classes = len(self.probabilities.bands)
        else:
            self.num_classes = 0
        self.available = [name for name, layer in (("height_std", self.height_std), ("dtm", self.dtm))
                          if layer is not None]
        if (self.entropy is not None or self.probabilities is not None) and self.num_classes > 0:
            self.available.append("confidence")

    def _layer(self, path: str | Path, kind: LayerKind, role: str, same_grid: bool = True,
               all_bands: bool = False) -> AlignedRaster:
        """Open ``path`` on the grid; a prediction layer (``same_grid``) must already be on it."""
        layer = AlignedRaster(path, self.grid, kind, bands=None if all_bands else [1], role=role)
        self._open.append(layer)
        if same_grid and not layer.same_grid:
            raise InputError(
                f"'{path}' is not on the grid of '{self.folder.layer_path(CLASSES)}'; all files of a prediction "
                "folder must share one grid: predict again into an empty folder"
            )
        return layer

    @property
    def pixel_area_m2(self) -> float:
        """Area of one pixel in m²."""
        t = self.grid.transform
        return abs(t.a * t.e - t.b * t.d) * self.metres_per_unit**2

    def read(self, window: Window) -> dict[str, np.ndarray]:
        """One window of every layer.

        Returns:
            ``class`` (h, w) uint8 class indices (:data:`IGNORE_INDEX` = nodata); ``height`` (h, w) float32
            metres, NaN = nodata; and, when available, ``height_std`` (m), ``confidence`` (1 − entropy /
            ln K, in [0, 1]) and ``dtm`` (m), float32 with NaN = nodata.
        """
        cls, valid = self.classes.read(window)
        out = {"class": np.where(valid, cls[0], IGNORE_INDEX).astype(np.uint8)}
        out["height"] = self.height.read(window)[0][0]
        if self.height_std is not None:
            out["height_std"] = self.height_std.read(window)[0][0]
        if "confidence" in self.available:
            if self.entropy is not None:
                entropy = self.entropy.read(window)[0][0]
            else:
                assert self.probabilities is not None, "confidence is available with entropy or probabilities"
                probs = self.probabilities.read(window)[0]
                with np.errstate(divide="ignore", invalid="ignore"):
                    entropy = -np.sum(np.where(probs > 0, probs * np.log(probs), 0.0), axis=0).astype(np.float32)
            norm = math.log(self.num_classes) if self.num_classes > 1 else 1.0
            out["confidence"] = np.clip(1.0 - entropy / norm, 0.0, 1.0).astype(np.float32)
        if self.dtm is not None:
            out["dtm"] = self.dtm.read(window)[0][0]
        return out

    def close(self) -> None:
        """Close every raster this reader opened."""
        for layer in self._open:
            layer.close()
        self._open = []

    def __enter__(self) -> BuildingLayers:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["BUILDING_NAME", "BuildingLayers", "building_class_indices"]
