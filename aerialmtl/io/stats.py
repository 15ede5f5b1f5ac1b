"""Summary statistics of an output raster band, from its overviews rather than the full raster.

The display range of a QGIS style (0..p98 of the heights) and the ``raster:bands`` statistics of a
STAC item need a few numbers per layer. :func:`band_stats` gets them from a decimated read: GDAL serves
a read with a smaller ``out_shape`` from the COG's internal overviews (or a VRT mosaic's
``OverviewList``), so at most ``max_pixels`` pixels are read and decoded whatever the raster's size.
The numbers are then approximate (overview pixels are averages of 2^k × 2^k pixels), which is what a
colour ramp or a catalogue needs; ``approximate`` says so. Averaging pulls the upper percentiles in a
little: on the Autzen nDSM (1 m, 0.5 Mpx) the p98 of its 2×, 4× and 8× overviews is 27.1, 26.3 and
26.4 m against 27.9 m over every pixel, while 16 full-resolution windows of the same total size gave
22.7-23.2 m (they miss the tall blocks) - so the overviews it is (bench/RESULTS.md, gis-meta).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio

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
    """Statistics of band ``band`` of ``path`` from at most ``max_pixels`` pixels; ``None`` if no pixel is valid.

    Args:
        path: a raster (COG, VRT) with nodata set; overviews make the read cheap.
        band: 1-based band index.
        max_pixels: the decimated read's size limit (width × height).
    """
    with rasterio.open(path) as src:
        factor = max(1.0, math.sqrt(src.width * src.height / max_pixels))
        shape = (max(1, round(src.height / factor)), max(1, round(src.width / factor)))
        data = src.read(band, out_shape=shape, masked=True)
        approximate = shape != (src.height, src.width)
    values = np.asarray(data.compressed(), dtype=np.float64)
    values = values[np.isfinite(values)]
    if values.size == 0:
        return None
    return BandStats(
        minimum=float(values.min()), maximum=float(values.max()), mean=float(values.mean()),
        stddev=float(values.std()), p98=float(np.percentile(values, 98)),
        valid_percent=100.0 * values.size / data.size, approximate=approximate,
    )


__all__ = ["MAX_PIXELS", "BandStats", "band_stats"]
