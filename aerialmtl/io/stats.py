"""Summary statistics of an output raster band, from its overviews rather than the full raster.

The display range of a QGIS style (0..p98 of the heights) and the ``raster:bands`` statistics of a
STAC item need a few numbers per layer. :func:`band_stats` gets them without reading the raster again:
a decimated read (GDAL serves a smaller ``out_shape`` from the COG's internal overviews, or a VRT
mosaic's ``OverviewList``) and a sample of full-resolution windows, about ``max_pixels`` pixels each,
whatever the raster's size. The numbers are then approximate, which is what a colour ramp or a
catalogue needs; ``approximate`` says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
from rasterio.windows import Window

#: Pixels read at most per band (1 Mpx: about 4 MB of float32).
MAX_PIXELS = 1 << 20


@dataclass(frozen=True)
class BandStats:
    """Statistics of the valid (not nodata) pixels of one band.

    Attributes:
        minimum, maximum, mean, stddev: in the band's unit.
        p98: the 98th percentile (the top of a display range that a few outliers do not flatten).
        valid_percent: share of valid pixels, 0..100.
        approximate: computed from a decimated read (overviews) rather than every pixel.
    """

    minimum: float
    maximum: float
    mean: float
    stddev: float
    p98: float
    valid_percent: float
    approximate: bool


def band_stats(path: str | Path, band: int = 1, max_pixels: int = MAX_PIXELS) -> BandStats | None:
    """Statistics of band ``band`` of ``path`` from about ``max_pixels`` pixels; ``None`` if no pixel is valid.

    A raster of at most ``max_pixels`` pixels is read whole (exact statistics). A larger one is read
    twice, cheaply: decimated to ``max_pixels`` (served by its overviews) for the minimum, maximum,
    mean, standard deviation and valid share, and as :data:`SAMPLE_WINDOWS` full-resolution windows
    spread over a regular grid (about ``max_pixels`` pixels in all) for the 98th percentile, which the
    averaging of overviews would pull towards the mean.

    Args:
        path: a raster (COG, VRT) with nodata set; overviews make the read cheap.
        band: 1-based band index.
        max_pixels: the size of each read (pixels).
    """
    with rasterio.open(path) as src:
        factor = max(1.0, math.sqrt(src.width * src.height / max_pixels))
        shape = (max(1, round(src.height / factor)), max(1, round(src.width / factor)))
        approximate = shape != (src.height, src.width)
        data = src.read(band, out_shape=shape, masked=True)
        sample = _full_resolution_sample(src, band, max_pixels) if approximate else None
    values = _valid(data)
    if values.size == 0:
        return None
    top = sample if sample is not None and sample.size else values
    return BandStats(
        minimum=float(values.min()), maximum=float(values.max()), mean=float(values.mean()),
        stddev=float(values.std()), p98=float(np.percentile(top, 98)),
        valid_percent=100.0 * values.size / data.size, approximate=approximate,
    )


#: Full-resolution windows per side of the sampling grid of :func:`band_stats` (``SAMPLE_WINDOWS``² windows).
SAMPLE_WINDOWS = 4


def _valid(data: np.ma.MaskedArray) -> np.ndarray:
    values = np.asarray(data.compressed(), dtype=np.float64)
    return values[np.isfinite(values)]


def _full_resolution_sample(src: rasterio.DatasetReader, band: int, max_pixels: int) -> np.ndarray:
    """The valid pixels of ``SAMPLE_WINDOWS``² full-resolution windows centred on a regular grid."""
    side = max(1, int(math.sqrt(max_pixels)) // SAMPLE_WINDOWS)
    w, h = min(side, src.width), min(side, src.height)
    parts = []
    for i in range(SAMPLE_WINDOWS):
        for j in range(SAMPLE_WINDOWS):
            col = int((j + 0.5) * src.width / SAMPLE_WINDOWS - w / 2)
            row = int((i + 0.5) * src.height / SAMPLE_WINDOWS - h / 2)
            win = Window(min(max(col, 0), src.width - w), min(max(row, 0), src.height - h), w, h)
            parts.append(_valid(src.read(band, window=win, masked=True)))
    return np.concatenate(parts)


__all__ = ["MAX_PIXELS", "SAMPLE_WINDOWS", "BandStats", "band_stats"]
