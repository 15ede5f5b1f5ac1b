"""Where on Earth a raster lies: its outline in WGS 84, and the check that it has one.

A raster's CRS ties its map coordinates to places on Earth, within the CRS's domain: a UTM zone's formulas hold
some hundreds of kilometres around its central meridian, not at x = 3·10⁷ m; a local (engineering) CRS ties them to
no place at all. What depends on the place — the sun of an acquisition time, the STAC footprint, the grid
convergence, whether two rasters are of one flight — needs the outline in longitude and latitude.
:func:`check_place` refuses a raster without one when it is opened, naming the file and the fix, before any work.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from aerialmtl.errors import AlignmentError

#: Points per edge of an outline reprojected to WGS 84 (a reprojected straight edge is curved).
EDGE_POINTS = 21


class NoPlace(ValueError):
    """A rectangle of map coordinates with no place on Earth; ``str(exc)`` says why."""


def outline_points(bounds: tuple[float, float, float, float], points: int = EDGE_POINTS
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``(xs, ys)``: the outline of ``bounds`` (left, bottom, right, top), clockwise from the upper-left corner,
    ``points - 1`` points per edge (the first point not repeated).
    """
    left, bottom, right, top = bounds
    t = np.linspace(0.0, 1.0, points)[:-1]
    xs = np.concatenate([left + (right - left) * t, np.full_like(t, right), right - (right - left) * t,
                         np.full_like(t, left)])
    ys = np.concatenate([np.full_like(t, top), top - (top - bottom) * t, np.full_like(t, bottom),
                         bottom + (top - bottom) * t])
    return xs, ys


def wgs84_outline(crs: Any, bounds: tuple[float, float, float, float], points: int = EDGE_POINTS
                  ) -> tuple[list[float], list[float]]:
    """``(lon, lat)`` in WGS 84 degrees of the outline of ``bounds`` in ``crs`` (:func:`outline_points`).

    Raises:
        NoPlace: ``crs`` is a local (engineering) one, or the outline lies outside its domain (the reprojection
            fails or gives no finite longitude and latitude).
    """
    from rasterio.crs import CRS
    from rasterio.errors import CRSError
    from rasterio.warp import transform

    try:
        src = CRS.from_user_input(crs)
    except CRSError as exc:
        raise NoPlace(f"its CRS is not one PROJ reads ({exc})") from None
    if not (src.is_projected or src.is_geographic):
        wkt = src.to_wkt()
        name = wkt.split('"')[1] if '"' in wkt else wkt[:40]
        raise NoPlace(f"its CRS is a local (engineering) one ({name!r}), tied to no place on Earth")
    if not all(math.isfinite(float(v)) for v in bounds):
        raise NoPlace(f"its coordinates {tuple(bounds)} are not all finite numbers")
    xs, ys = outline_points(bounds, points)
    try:
        lon, lat = transform(src, "EPSG:4326", xs.tolist(), ys.tolist())
    except Exception:  # noqa: BLE001 - GDAL/PROJ's own errors (CPLE_*): the rectangle has no place, said below
        lon, lat = [math.nan], [math.nan]
    if not (all(math.isfinite(v) for v in lon) and all(math.isfinite(v) and abs(v) <= 90.0 + 1e-6 for v in lat)):
        left, bottom, right, top = bounds
        raise NoPlace(f"its coordinates (x {left:.6g} to {right:.6g}, y {bottom:.6g} to {top:.6g}) lie outside the "
                      f"domain of its CRS ({src.to_string() or 'as written'}), at no place on Earth")
    return [float(v) for v in lon], [float(v) for v in lat]


def check_place(crs: Any, bounds: tuple[float, float, float, float], role: str, path: object) -> None:
    """Refuse a raster whose ``bounds`` in ``crs`` have no place on Earth (see :func:`wgs84_outline`).

    A raster without a CRS passes (the georeferencing checks of :mod:`aerialmtl.io.align` name that).

    Raises:
        AlignmentError: names the ``role`` and file ``path``, why, and the fix.
    """
    if crs is None:
        return
    try:
        wgs84_outline(crs, bounds)
    except NoPlace as exc:
        raise AlignmentError(
            f"{role} '{path}': {exc}; give it the projected CRS and geotransform of the place it shows "
            f"(`gdalinfo {path}` shows them; `gdal_edit.py -a_srs EPSG:XXXX -a_ullr ULX ULY LRX LRY {path}` sets "
            "them), or warp it into one (`gdalwarp -t_srs EPSG:XXXX`)") from None


__all__ = ["EDGE_POINTS", "NoPlace", "check_place", "outline_points", "wgs84_outline"]
