"""Mosaic VRTs: several rasters on one pixel grid presented as one dataset, without copying pixels.

:func:`mosaic_vrt` writes a GDAL VRT (XML) that places each source at the offset given by its own
geotransform on the union of their extents. Every source must share the CRS, pixel size, band count and
data type (they are *placed*, never resampled); pixels covered by no source read as ``nodata``. This is
what ``gdalbuildvrt`` does for same-grid inputs, written with the standard library so nothing beyond
rasterio is needed. Sources are referenced relative to the VRT when they lie below its folder.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from xml.sax.saxutils import escape

import rasterio
from rasterio.dtypes import dtype_rev, typename_fwd

from aerialmtl.errors import InputError

#: Tolerance on pixel offsets and sizes, in pixels.
_EPS = 1e-6


def mosaic_vrt(sources: Sequence[str | Path], out: str | Path, nodata: float | None = None) -> Path:
    """Write ``out`` (a ``.vrt``) that mosaics ``sources`` placed by their geotransforms.

    Args:
        sources: GeoTIFFs (or any GDAL rasters) on one grid: same CRS, same north-up pixel size, pixel
            offsets between them whole numbers of pixels, same band count and data type.
        out: VRT path to write (its folder must exist).
        nodata: value of pixels covered by no source, declared as every band's nodata; default the
            first source's nodata (``None``: undeclared; uncovered pixels then read as 0).

    Returns:
        ``out`` as a :class:`~pathlib.Path`.

    Raises:
        InputError: no sources, or sources that are not on one grid (the message names the file and
            what differs).
    """
    if not sources:
        raise InputError("‹sources›: no raster given to mosaic; pass at least one file", param="sources")
    out = Path(out)
    metas = []
    for path in sources:
        with rasterio.open(path) as src:
            metas.append({"path": Path(path), "crs": src.crs, "transform": src.transform, "width": src.width,
                          "height": src.height, "count": src.count, "dtype": src.dtypes[0],
                          "nodata": src.nodata, "colorinterp": [c.name for c in src.colorinterp]})
    first = metas[0]
    t0 = first["transform"]
    if t0.b != 0 or t0.d != 0 or t0.e >= 0:
        raise InputError(f"mosaic source '{first['path']}' is not north-up; warp it first (gdalwarp)")
    for m in metas[1:]:
        t = m["transform"]
        what = None
        if m["crs"] != first["crs"]:
            what = f"CRS {m['crs']} instead of {first['crs']}"
        elif not (math.isclose(t.a, t0.a, rel_tol=1e-9) and math.isclose(t.e, t0.e, rel_tol=1e-9)) or t.b or t.d:
            what = f"pixel size ({t.a}, {t.e}) instead of ({t0.a}, {t0.e})"
        elif (m["count"], m["dtype"]) != (first["count"], first["dtype"]):
            what = f"{m['count']} × {m['dtype']} bands instead of {first['count']} × {first['dtype']}"
        else:
            dx, dy = (t.c - t0.c) / t0.a, (t.f - t0.f) / t0.e
            if abs(dx - round(dx)) > _EPS or abs(dy - round(dy)) > _EPS:
                what = f"an origin {dx:.4f}, {dy:.4f} pixels away from the first one's (not whole pixels)"
        if what:
            raise InputError(f"mosaic source '{m['path']}' is not on the grid of '{first['path']}': it has {what}; "
                             "a mosaic only places rasters, so resample them onto one grid first")
    cols = [round((m["transform"].c - t0.c) / t0.a) for m in metas]
    rows = [round((m["transform"].f - t0.f) / t0.e) for m in metas]
    c0, r0 = min(cols), min(rows)
    width = max(c + m["width"] for c, m in zip(cols, metas)) - c0
    height = max(r + m["height"] for r, m in zip(rows, metas)) - r0
    x0, y0 = t0.c + c0 * t0.a, t0.f + r0 * t0.e
    if nodata is None:
        nodata = first["nodata"]

    def source_name(p: Path) -> tuple[str, int]:
        p = p.resolve()
        try:
            return os.path.relpath(p, out.parent.resolve()), 1 if p.is_relative_to(out.parent.resolve()) else 0
        except ValueError:
            return str(p), 0

    lines = [f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}">',
             f"  <SRS>{escape(first['crs'].to_wkt())}</SRS>",
             f"  <GeoTransform>{x0!r}, {t0.a!r}, 0.0, {y0!r}, 0.0, {t0.e!r}</GeoTransform>"]
    gdal_type = typename_fwd[dtype_rev[first["dtype"]]]
    for band in range(1, first["count"] + 1):
        lines.append(f'  <VRTRasterBand dataType="{gdal_type}" band="{band}">')
        if nodata is not None:
            lines.append(f"    <NoDataValue>{nodata!r}</NoDataValue>")
        interp = first["colorinterp"][band - 1]
        if interp not in ("undefined",):
            lines.append(f"    <ColorInterp>{interp.capitalize()}</ColorInterp>")
        for c, r, m in zip(cols, rows, metas):
            name, relative = source_name(m["path"])
            src_nodata = m["nodata"]
            tag = "ComplexSource" if src_nodata is not None else "SimpleSource"
            lines += [f"    <{tag}>",
                      f'      <SourceFilename relativeToVRT="{relative}">{escape(name)}</SourceFilename>',
                      f"      <SourceBand>{band}</SourceBand>",
                      f'      <SrcRect xOff="0" yOff="0" xSize="{m["width"]}" ySize="{m["height"]}"/>',
                      f'      <DstRect xOff="{c - c0}" yOff="{r - r0}" xSize="{m["width"]}" ySize="{m["height"]}"/>']
            if src_nodata is not None:  # source nodata pixels stay transparent (show the mosaic's nodata)
                lines.append(f"      <NODATA>{src_nodata!r}</NODATA>")
            lines.append(f"    </{tag}>")
        lines.append("  </VRTRasterBand>")
    lines.append("</VRTDataset>")
    out.write_text("\n".join(lines) + "\n")
    return out


__all__ = ["mosaic_vrt"]
