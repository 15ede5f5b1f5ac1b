"""GDAL VRT mosaics: one virtual raster over many rasters with the same bands (no pixel is copied).

:func:`mosaic_vrt` writes the XML of a ``VRTDataset`` whose sources are the given rasters, the way
``gdalbuildvrt`` does:

* grid: the CRS of the first source; the union of the sources' bounds; the finest pixel size among
  the sources in that CRS (x and y separately);
* each source is placed by its bounds (a source at a coarser pixel size is resampled on the fly,
  ``nearest`` for categorical rasters, ``bilinear`` otherwise); nodata pixels are transparent
  (``ComplexSource`` with ``NODATA``), so where sources overlap the later one is shown where it has data;
* a source in another CRS is reprojected on the fly through a warped VRT written beside the mosaic
  (``<mosaic stem>.warped/<k>.vrt``);
* band metadata (descriptions, units, colour table, nodata) and dataset tags come from the first source;
* overviews: an ``OverviewList`` (GDAL ≥ 3.2) declares virtual overviews at factors 2, 4, 8, ...
  (:func:`overview_factors`), which GDAL reads from the sources' own overviews (a COG's internal
  ones), so a GIS zoomed out reads overview tiles instead of every full-resolution tile, and no pixel
  is copied into an ``.ovr`` file.

Source paths are written relative to the mosaic when they are below its folder, so the folder can be
moved as a whole.
"""

from __future__ import annotations

import math
import os
import shutil
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import rasterio
import rasterio.shutil
from affine import Affine
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.vrt import WarpedVRT

from aerialmtl.errors import InputError, OutputError
from aerialmtl.filesafety import atomic_write

#: The smallest overview of a mosaic has at least this many pixels on its long side (as a COG's).
MIN_OVERVIEW_SIZE = 256

_GDAL_TYPES = {"uint8": "Byte", "int8": "Int8", "uint16": "UInt16", "int16": "Int16", "uint32": "UInt32",
               "int32": "Int32", "float32": "Float32", "float64": "Float64"}


@dataclass(frozen=True)
class _Source:
    path: Path
    transform: Affine
    width: int
    height: int

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        left, top = self.transform.c, self.transform.f
        return (left, top + self.height * self.transform.e, left + self.width * self.transform.a, top)


def _snap(v: float) -> float:
    """Round offsets that are integers up to float noise (GDAL would resample a 1e-9-pixel shift)."""
    r = round(v)
    return float(r) if abs(v - r) < 1e-6 else v


def _source_ref(path: Path, folder: Path) -> tuple[str, str]:
    """(filename, relativeToVRT) for a source path as seen from the VRT's folder."""
    try:
        rel = os.path.relpath(path.resolve(), folder.resolve())
    except ValueError:  # pragma: no cover - another drive on Windows
        return str(path.resolve()), "0"
    if rel.startswith(".."):
        return str(path.resolve()), "0"
    return rel, "1"


def overview_factors(width: int, height: int, smallest: int = MIN_OVERVIEW_SIZE) -> list[int]:
    """Overview factors 2, 4, 8, ... of a ``width`` × ``height`` raster, down to ``smallest`` px on its long side."""
    factors: list[int] = []
    f = 2
    while math.ceil(max(width, height) / f) >= smallest:
        factors.append(f)
        f *= 2
    return factors


def _place_sources(dst: Path, sources: Sequence[str | Path], crs: CRS, count: int, dtype: str,
                   resampling: Resampling, warped_dir: Path) -> tuple[list[_Source], list[_Source]]:
    """Every source as the mosaic places it (warped to ``crs`` through a VRT in ``warped_dir`` if needed).

    Returns:
        ``(placed, native)``: all sources, and those already in ``crs`` (they set the pixel size).

    Raises:
        InputError: a source's band count or dtype differs from the first's.
    """
    placed: list[_Source] = []
    native: list[_Source] = []
    for k, path in enumerate(Path(p) for p in sources):
        with rasterio.open(path) as src:
            if src.count != count or src.dtypes[0] != dtype:
                raise InputError(
                    f"mosaic '{dst}': '{path}' has {src.count} band(s) of {src.dtypes[0]}, the first source "
                    f"'{sources[0]}' {count} of {dtype}; mosaic rasters of one layer only"
                )
            if src.crs == crs:
                placed.append(_Source(path, src.transform, src.width, src.height))
                native.append(placed[-1])
                continue
            warped_dir.mkdir(parents=True, exist_ok=True)
            wpath = warped_dir / f"{k}.vrt"
            with WarpedVRT(src, crs=crs, resampling=resampling) as vrt:
                rasterio.shutil.copy(vrt, str(wpath), driver="VRT")
                placed.append(_Source(wpath, vrt.transform, vrt.width, vrt.height))
    return placed, native


def _add_source(band: ET.Element, s: _Source, b: int, folder: Path, resampling: Resampling,
                frame: tuple[float, float, float, float], nodata: float | None) -> None:
    """Band ``b`` of source ``s`` as a ``ComplexSource`` of ``band``, placed in the mosaic's pixels.

    ``frame`` is the mosaic's (left, top, x resolution, y resolution) in CRS units.
    """
    left, top, xres, yres = frame
    name, relative = _source_ref(s.path, folder)
    src_el = ET.SubElement(band, "ComplexSource", resampling=resampling.name)
    ET.SubElement(src_el, "SourceFilename", relativeToVRT=relative).text = name
    ET.SubElement(src_el, "SourceBand").text = str(b)
    ET.SubElement(src_el, "SrcRect", xOff="0", yOff="0", xSize=str(s.width), ySize=str(s.height))
    sl, _, sr, st = s.bounds
    ET.SubElement(src_el, "DstRect", xOff=repr(_snap((sl - left) / xres)),
                  yOff=repr(_snap((top - st) / yres)), xSize=repr(_snap((sr - sl) / xres)),
                  ySize=repr(_snap(s.height * abs(s.transform.e) / yres)))
    if nodata is not None:
        ET.SubElement(src_el, "NODATA").text = repr(float(nodata))


def mosaic_vrt(dst: str | Path, sources: Sequence[str | Path], categorical: bool = False,
               overviews: bool = True) -> Path:
    """Write a VRT mosaic of ``sources`` at ``dst`` (see the module docstring).

    Args:
        dst: the ``.vrt`` file to write (replaced if it exists).
        sources: rasters with the same band count and dtype; the first defines CRS and metadata.
        categorical: class rasters (``nearest`` resampling of coarser sources) rather than continuous.
        overviews: declare virtual overviews (off for a VRT that is only converted into a COG, which
            builds its own overviews from the full-resolution pixels).

    Returns:
        ``dst``.

    Raises:
        InputError: no source, or sources whose band count or dtype differ.
        OutputError: the file cannot be written.
    """
    dst = Path(dst)
    if not sources:
        raise InputError(f"mosaic '{dst}': no source raster given")
    folder = dst.parent
    warped_dir = folder / f"{dst.stem}.warped"
    if warped_dir.exists():
        shutil.rmtree(warped_dir)
    with rasterio.open(sources[0]) as first:
        crs: CRS = first.crs
        count, dtype, nodata = first.count, first.dtypes[0], first.nodata
        colormap = None
        try:
            colormap = first.colormap(1)
        except ValueError:
            pass
        descriptions, units, tags = first.descriptions, first.units, first.tags()
        band_tags = [first.tags(b) for b in range(1, count + 1)]
    resampling = Resampling.nearest if categorical else Resampling.bilinear
    placed, native = _place_sources(dst, sources, crs, count, dtype, resampling, warped_dir)
    xres = min(abs(s.transform.a) for s in native)
    yres = min(abs(s.transform.e) for s in native)
    left = min(s.bounds[0] for s in placed)
    bottom = min(s.bounds[1] for s in placed)
    right = max(s.bounds[2] for s in placed)
    top = max(s.bounds[3] for s in placed)
    width = max(1, math.ceil((right - left) / xres - 1e-6))
    height = max(1, math.ceil((top - bottom) / yres - 1e-6))

    root = ET.Element("VRTDataset", rasterXSize=str(width), rasterYSize=str(height))
    ET.SubElement(root, "SRS").text = crs.to_wkt()
    ET.SubElement(root, "GeoTransform").text = ", ".join(repr(float(v)) for v in (left, xres, 0.0, top, 0.0, -yres))
    factors = overview_factors(width, height) if overviews else []
    if factors:
        ET.SubElement(root, "OverviewList", resampling="nearest" if categorical else "average").text = " ".join(
            str(f) for f in factors)
    for b in range(1, count + 1):
        band = ET.SubElement(root, "VRTRasterBand", dataType=_GDAL_TYPES.get(dtype, "Float32"), band=str(b))
        if nodata is not None:
            ET.SubElement(band, "NoDataValue").text = repr(float(nodata))
        for s in placed:
            _add_source(band, s, b, folder, resampling, (left, top, xres, yres), nodata)
    try:
        with atomic_write(dst) as tmp:
            ET.ElementTree(root).write(tmp, encoding="unicode")
            with rasterio.open(tmp, "r+") as vrt:  # metadata through GDAL, as in the sources
                for b, desc in enumerate(descriptions, start=1):
                    if desc:
                        vrt.set_band_description(b, desc)
                if any(units):
                    vrt.units = units
                if colormap is not None:
                    vrt.write_colormap(1, colormap)
                if tags:
                    vrt.update_tags(**tags)
                for b, bt in enumerate(band_tags, start=1):
                    if bt:
                        vrt.update_tags(b, **bt)
    except OSError as exc:
        raise OutputError(f"cannot write mosaic '{dst}' ({exc}); choose a writable output folder") from exc
    return dst


__all__ = ["MIN_OVERVIEW_SIZE", "mosaic_vrt", "overview_factors"]
