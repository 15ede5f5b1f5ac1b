"""Cloud-Optimized GeoTIFFs: write a tiled GeoTIFF band by band, then copy it to a COG.

Large outputs are never held in memory: the caller writes a temporary tiled GeoTIFF window by window
(:func:`staging_profile`: fast light compression, or none), then :func:`to_cog` lets GDAL's COG driver
(GDAL ≥ 3.1) read it block-wise, build internal overviews and write the final layout: 512-pixel tiles,
DEFLATE with predictor 2 (integers) or 3 (floats), overviews resampled with ``average`` (continuous)
or ``mode`` (classes), the main image IFD first and the smallest overview's data first. Nodata, colour
table, band descriptions, units and tags of the staging file are carried over. ``to_cog(...,
num_threads=N)`` lets GDAL compress tiles on N threads; ``level`` trades compression for speed.

:func:`cog_problems` re-checks a file (tiling, overviews, IFD order, GDAL's ``LAYOUT=COG`` marker) by
reading the TIFF structure itself.
"""

from __future__ import annotations

import struct
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import rasterio.shutil
from affine import Affine
from rasterio.crs import CRS

from aerialmtl.errors import OutputError
from aerialmtl.io.profiles import light_compression, raster_profile, zstd_available

#: Internal tile size of every COG aerialmtl writes.
COG_BLOCKSIZE = 512


@cache
def _gdal_version() -> tuple[int, ...]:
    return tuple(int(p) for p in rasterio.__gdal_version__.split(".")[:2])


def staging_profile(
    crs: CRS, transform: Affine, width: int, height: int, count: int, dtype: str, nodata: float | None,
    compress: bool = True,
) -> dict[str, Any]:
    """Profile of the temporary tiled GeoTIFF that :func:`to_cog` converts.

    Args:
        compress: light compression (ZSTD level 1, else DEFLATE level 1); ``False`` writes raw tiles
            (fastest, and the only layout in which tiles can be rewritten in place when they are
            written in parts), at the cost of disk space while the file exists.
    """
    profile = raster_profile(crs, transform, width, height, count, dtype, nodata)
    profile.update(tiled=True, blockxsize=COG_BLOCKSIZE, blockysize=COG_BLOCKSIZE, bigtiff="IF_SAFER",
                   interleave="band")
    if not compress:
        profile["bigtiff"] = "IF_NEEDED"  # the size is known exactly without compression
        return profile
    profile.update(light_compression())
    return profile


def cog_options(
    dtype: str | np.dtype, categorical: bool = False, compress: str = "deflate", level: int | None = None,
    num_threads: int | str | None = None,
) -> dict[str, Any]:
    """GDAL COG-driver creation options for rasters of ``dtype``.

    Args:
        dtype: band dtype.
        categorical: class rasters (overviews by ``mode``) instead of continuous values (``average``).
        compress: ``"deflate"`` (readable everywhere) or ``"zstd"`` (falls back to deflate without it).
        level: compression level (GDAL's default when ``None``: 6 for DEFLATE).
        num_threads: threads GDAL compresses tiles with (an integer or ``"ALL_CPUS"``).
    """
    compress = "zstd" if compress.lower() == "zstd" and zstd_available() else "deflate"
    options: dict[str, Any] = {
        "blocksize": COG_BLOCKSIZE,
        "compress": compress,
        "predictor": "floating_point" if np.dtype(dtype).kind == "f" else "standard",
        "overview_resampling": "mode" if categorical else "average",
        "bigtiff": "if_safer",
    }
    if level is not None:
        options["level"] = int(level)
    if num_threads is not None:
        options["num_threads"] = str(num_threads)
    return options


def to_cog(
    src: str | Path, dst: str | Path, categorical: bool = False, compress: str = "deflate", level: int | None = None,
    num_threads: int | str | None = None,
) -> None:
    """Copy a GeoTIFF (or VRT) ``src`` to a Cloud-Optimized GeoTIFF ``dst`` (block-wise; flat memory).

    ``level`` and ``num_threads``: see :func:`cog_options`.

    Raises:
        OutputError: GDAL older than 3.1 (no COG driver) or the copy failed.
    """
    if _gdal_version() < (3, 1):  # pragma: no cover - the pinned environment has GDAL ≥ 3.1
        raise OutputError(
            f"writing Cloud-Optimized GeoTIFFs needs GDAL ≥ 3.1, this rasterio has GDAL {rasterio.__gdal_version__}; "
            "upgrade rasterio (pip install -U rasterio)"
        )
    with rasterio.open(src) as s:
        dtype = s.dtypes[0]
    try:
        rasterio.shutil.copy(str(src), str(dst), driver="COG",
                             **cog_options(dtype, categorical, compress, level, num_threads))
    except rasterio.errors.RasterioError as exc:
        raise OutputError(f"could not write COG '{dst}' from '{src}': {exc}; check free disk space") from exc


# ---- validation --------------------------------------------------------------------------------
_TYPE_SIZES = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 16: 8, 17: 8, 18: 8}
_TYPE_FMT = {3: "H", 4: "I", 16: "Q"}


def _read_ifds(path: Path) -> list[dict[int | str, Any]]:
    """Parse the IFD chain of a (Big)TIFF: tag → value(s) for the tags needed here, plus its offset."""
    wanted = {256, 257, 322, 323, 324, 325, 254}
    ifds: list[dict[int | str, Any]] = []
    with open(path, "rb") as fh:
        head = fh.read(16)
        bo = {b"II": "<", b"MM": ">"}.get(head[:2])
        if bo is None:
            raise OutputError(f"'{path}' is not a TIFF file")
        magic = struct.unpack(bo + "H", head[2:4])[0]
        big = magic == 43
        offset = struct.unpack(bo + ("Q" if big else "I"), head[8:16] if big else head[4:8])[0]
        while offset and len(ifds) < 64:
            fh.seek(offset)
            n = struct.unpack(bo + ("Q" if big else "H"), fh.read(8 if big else 2))[0]
            entry_size = 20 if big else 12
            raw = fh.read(n * entry_size)
            ifd: dict[int | str, Any] = {"offset": offset}
            for k in range(n):
                e = raw[k * entry_size:(k + 1) * entry_size]
                tag, typ = struct.unpack(bo + "HH", e[:4])
                count = struct.unpack(bo + ("Q" if big else "I"), e[4:12] if big else e[4:8])[0]
                if tag not in wanted or typ not in _TYPE_FMT:
                    continue
                size = _TYPE_SIZES[typ] * count
                inline = e[12:20] if big else e[8:12]
                if size <= len(inline):
                    data = inline[:size]
                else:
                    ptr = struct.unpack(bo + ("Q" if big else "I"), inline)[0]
                    here = fh.tell()
                    fh.seek(ptr)
                    data = fh.read(size)
                    fh.seek(here)
                ifd[tag] = struct.unpack(bo + _TYPE_FMT[typ] * count, data)
            ifds.append(ifd)
            nxt = fh.read(8 if big else 4)
            offset = struct.unpack(bo + ("Q" if big else "I"), nxt)[0] if len(nxt) == (8 if big else 4) else 0
    return ifds


def cog_problems(path: str | Path) -> list[str]:
    """Check that ``path`` is a Cloud-Optimized GeoTIFF; returns the problems found (empty when valid).

    Checks: GDAL reports ``LAYOUT=COG``; the image is tiled; it has internal overviews when it is larger
    than one tile; the first IFD is the full-resolution image and sits at the start of the file, followed
    by the overview IFDs in decreasing size; overview tile data come before the full-resolution data.
    """
    path = Path(path)
    problems: list[str] = []
    ifds = [d for d in _read_ifds(path) if not (d.get(254, (0,))[0] & 4)]  # skip mask IFDs
    # tiling from the TIFF tags (TileWidth/TileLength): rasterio's profile calls a COG exactly one tile
    # wide (e.g. 512 px) "not tiled"
    tile = max(ifds[0][322][0], ifds[0].get(323, (0,))[0]) if ifds and 322 in ifds[0] else COG_BLOCKSIZE
    with rasterio.open(path) as src:
        if src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") != "COG":
            problems.append("GDAL does not report LAYOUT=COG")
        if max(src.width, src.height) > tile and not src.overviews(1):
            problems.append("no internal overviews although the image is larger than one tile")
        width = src.width
    if not ifds:
        return problems + ["no IFD found"]
    main = ifds[0]
    if main.get(256, (None,))[0] != width:
        problems.append("the first IFD is not the full-resolution image")
    if main["offset"] > 65536:
        problems.append(f"the first IFD is at byte {main['offset']}, not at the start of the file")
    if 322 not in main:
        problems.append("the image is not tiled")
    widths = [d.get(256, (0,))[0] for d in ifds]
    if any(b >= a for a, b in zip(widths, widths[1:])):
        problems.append(f"overview IFDs are not in decreasing size order: widths {widths}")
    if len(ifds) > 1 and 324 in main and 324 in ifds[-1]:
        main_data = min(o for o in main[324] if o > 0) if any(main[324]) else 0
        ovr_data = max(ifds[-1][324])
        if main_data and ovr_data > main_data:
            problems.append("full-resolution tile data come before the smallest overview's data")
    return problems


__all__ = ["COG_BLOCKSIZE", "cog_options", "cog_problems", "staging_profile", "to_cog"]
