"""GeoTIFF creation defaults: one place that decides tiling, compression, predictor and BigTIFF.

Every GeoTIFF aerialmtl writes (patches, predictions, COGs, synthetic scenes) starts from
:func:`raster_profile` (driver, georeferencing, size, dtype, nodata) and :func:`creation_options` (or
:func:`gtiff_profile` / :func:`patch_profile`, which join the two), rasterio-style; files written only
to be read again soon (a COG's staging file, synthetic scenes) take :func:`light_compression`. Whether
GDAL has ZSTD is probed once, here (:func:`zstd_available`)::

    profile = gtiff_profile(grid.crs, grid.transform, width, height, count=1, dtype="float32",
                            nodata=HEIGHT_NODATA)
    with rasterio.open(path, "w", **profile) as dst: ...

Defaults: DEFLATE (readable by every GIS; ``compress="zstd"`` is available when GDAL has it), horizontal
predictor 2 for integers and floating-point predictor 3 for floats, ``BIGTIFF=IF_SAFER``, internal tiles
of 512 (or 256) pixels when the raster spans at least two tiles in both directions, strips otherwise
(a 320-pixel patch in 512-pixel tiles would be mostly padding).
"""

from __future__ import annotations

from functools import cache
from typing import Any

import numpy as np
from affine import Affine
from rasterio.crs import CRS
from rasterio.windows import Window

from aerialmtl.errors import InputError
from aerialmtl.quiet import ignoring_warnings

#: Preferred internal tile sizes, largest first (multiples of 16 as GeoTIFF requires).
BLOCK_SIZES = (512, 256)


@cache
def zstd_available() -> bool:
    """Whether the linked GDAL can write ZSTD-compressed GeoTIFFs."""
    from rasterio.io import MemoryFile

    try:
        with ignoring_warnings(), MemoryFile() as mem:
            with mem.open(driver="GTiff", width=1, height=1, count=1, dtype="uint8", compress="zstd") as dst:
                dst.write(np.zeros((1, 1, 1), np.uint8))
            with mem.open() as src:
                return src.compression is not None and src.compression.name.lower() == "zstd"
    except Exception:  # pragma: no cover - depends on the GDAL build
        return False


def light_compression() -> dict[str, Any]:
    """Fast, light compression: ZSTD level 1 where GDAL has it (:func:`zstd_available`), else DEFLATE level 1."""
    if zstd_available():
        return {"compress": "zstd", "zstd_level": 1}
    return {"compress": "deflate", "zlevel": 1}  # pragma: no cover - depends on the GDAL build


def block_size_for(width: int, height: int) -> int | None:
    """Internal tile size for a ``width`` × ``height`` raster, or ``None`` for strips.

    512 (or 256) when the raster spans at least two such tiles in both directions; smaller rasters
    (e.g. 320-pixel training patches) are written in strips, which wastes no padding.
    """
    for size in BLOCK_SIZES:
        if width >= 2 * size and height >= 2 * size:
            return size
    return None


def creation_options(
    dtype: str | np.dtype, width: int | None = None, height: int | None = None, compress: str = "deflate"
) -> dict[str, Any]:
    """GDAL GeoTIFF creation options for rasters of ``dtype`` (and size, when known).

    Args:
        dtype: numpy/rasterio dtype of the bands.
        width, height: raster size in pixels; decides the internal tile size (see :func:`block_size_for`).
            Without them the raster is tiled at 512 pixels.
        compress: ``"deflate"`` (default), ``"zstd"`` (falls back to deflate if GDAL lacks it) or ``"lzw"``.

    Returns:
        ``{"compress", "predictor", "bigtiff", "tiled"[, "blockxsize", "blockysize"]}`` ready for
        ``rasterio.open(..., "w", **options)``.
    """
    kind = np.dtype(dtype).kind
    compress = compress.lower()
    if compress not in ("deflate", "zstd", "lzw"):
        raise InputError(f"compress={compress!r} is not supported; use 'deflate', 'zstd' or 'lzw'")
    if compress == "zstd" and not zstd_available():
        compress = "deflate"
    opts: dict[str, Any] = {
        "compress": compress,
        "predictor": 3 if kind == "f" else 2,
        "bigtiff": "IF_SAFER",
    }
    if kind == "b":  # booleans are written as uint8; predictor 2 still fits
        opts["predictor"] = 2
    block = BLOCK_SIZES[0] if width is None or height is None else block_size_for(width, height)
    if block is None:
        opts["tiled"] = False
    else:
        opts.update(tiled=True, blockxsize=block, blockysize=block)
    return opts


def gtiff_profile(
    crs: CRS | str,
    transform: Affine,
    width: int,
    height: int,
    count: int,
    dtype: str | np.dtype,
    nodata: float | None = None,
    compress: str = "deflate",
) -> dict[str, Any]:
    """A complete rasterio write profile (:func:`raster_profile` + :func:`creation_options`)."""
    profile = raster_profile(crs, transform, width, height, count, dtype, nodata)
    profile.update(creation_options(dtype, width, height, compress))
    return profile


def raster_profile(crs: CRS | str, transform: Affine, width: int, height: int, count: int, dtype: str | np.dtype,
                   nodata: float | None = None) -> dict[str, Any]:
    """The GeoTIFF driver, georeferencing, size (pixels), band count, dtype and nodata of a raster to write."""
    return {
        "driver": "GTiff",
        "crs": crs,
        "transform": transform,
        "width": int(width),
        "height": int(height),
        "count": int(count),
        "dtype": np.dtype(dtype).name,
        "nodata": nodata,
    }


def patch_profile(grid: Any, window: Window, count: int, dtype: str | np.dtype, nodata: float | None) -> dict[str, Any]:
    """Write profile of a patch covering ``window`` of ``grid`` (an :class:`aerialmtl.io.align.Grid`).

    The patch transform is ``rasterio.windows.transform(window, grid.transform)``, so patch pixels are
    exactly the grid's pixels.
    """
    return gtiff_profile(grid.crs, grid.window_transform(window), int(window.width), int(window.height),
                         count, dtype, nodata)


__all__ = ["BLOCK_SIZES", "block_size_for", "creation_options", "gtiff_profile", "light_compression", "patch_profile",
           "raster_profile", "zstd_available"]
