"""The input layers of a tile run, opened on the reference grid and read window by window.

:class:`TileSources` opens the orthophoto, the height layers (nDSM, or DSM − DTM) and the labels (raster
codes or vector polygons) through :mod:`aerialmtl.io.align` / :mod:`aerialmtl.io.vector`, and says what
``dataset.yaml`` records of them (band names, dtype, height units).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.windows import Window

from aerialmtl.classes import ClassScheme, OnUnknown
from aerialmtl.io.align import AlignedRaster, Grid, HeightSource, NdsmOptions
from aerialmtl.io.vector import VectorLabels


def _band_names(src: rasterio.io.DatasetReader, bands: Sequence[int]) -> list[str]:
    names = []
    for b in bands:
        desc = src.descriptions[b - 1]
        names.append(desc if desc else src.colorinterp[b - 1].name if src.colorinterp else f"band{b}")
    return names


class TileSources:
    """Every input layer of a tile run, opened on the reference grid (a context manager).

    Attributes:
        image: the orthophoto bands (:class:`~aerialmtl.io.align.AlignedRaster`).
        heights: heights above ground in metres, or ``None`` without a height layer.
        labels: label codes (raster) or polygons (vector), or ``None`` without labels.
        scheme: the class scheme of the labels.
        tasks: ``("height", "classes")`` or the subset the layers allow.
        paths: the input paths by role (for the provenance in ``dataset.yaml``).
        band_names, dtype, height_units: what ``dataset.yaml`` records of the layers (kept after closing).

    The constructor takes each layer :func:`tile_dataset` was given as a keyword of its own (12 parameters).
    """

    def __init__(
        self, ortho: str | Path, grid: Grid, *, bands: Sequence[int] | None, dsm: str | Path | None,
        dtm: str | Path | None, ndsm: str | Path | None, ndsm_options: NdsmOptions, labels: str | Path | None,
        labels_vector: str | Path | None, class_field: str | None, scheme: ClassScheme | None,
        ignore_unknown_codes: bool,
    ) -> None:
        self.scheme = scheme
        self.on_unknown: OnUnknown = "ignore" if ignore_unknown_codes else "error"
        self.paths = {"ortho": ortho, "ndsm": ndsm, "dsm": dsm, "dtm": dtm, "labels": labels,
                      "labels_vector": labels_vector}
        self.class_field = class_field
        self._opened: list[Any] = []
        try:
            self.image = self._open(AlignedRaster(ortho, grid, "image", bands=bands, role="orthophoto",
                                                  bands_from="‹bands›"))
            has_height = any(p is not None for p in (dsm, dtm, ndsm))
            self.heights = (self._open(HeightSource(grid, ndsm=ndsm, dsm=dsm, dtm=dtm, options=ndsm_options))
                            if has_height else None)
            self.labels: AlignedRaster | VectorLabels | None = None
            if labels is not None:
                self.labels = self._open(AlignedRaster(labels, grid, "labels", bands=[1], role="labels"))
            elif labels_vector is not None and scheme is not None:
                self.labels = self._open(VectorLabels(labels_vector, grid, class_field or "", scheme,
                                                      self.on_unknown))
        except BaseException:
            self.close()
            raise
        self.tasks = (("height",) if self.heights is not None else ()) + (
            ("classes",) if self.labels is not None else ())
        #: one name per kept orthophoto band (its description, colour interpretation or ``bandN``)
        self.band_names = _band_names(self.image.src, self.image.bands)
        #: the orthophoto's band dtype (the image patches keep it)
        self.dtype = str(self.image.src.dtypes[self.image.bands[0] - 1])
        #: the unit each height layer was read in
        self.height_units = self.heights.units() if self.heights is not None else {}

    def read_classes(self, win: Window) -> np.ndarray:
        """(h, w) uint8 class indices of ``win`` (``IGNORE_INDEX`` where unlabelled)."""
        assert self.labels is not None and self.scheme is not None
        if isinstance(self.labels, VectorLabels):
            return self.labels.read(win)[0]
        codes, valid = self.labels.read(win)
        return self.scheme.remap(codes[0], valid=valid, on_unknown=self.on_unknown,
                                 source=f"labels '{self.labels.path}'")

    def _open(self, layer: Any) -> Any:
        self._opened.append(layer)
        return layer

    def close(self) -> None:
        """Close every layer opened so far (last opened first)."""
        for layer in reversed(self._opened):
            layer.close()
        self._opened.clear()

    def __enter__(self) -> TileSources:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["TileSources"]
