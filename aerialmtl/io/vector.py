"""Polygon layers (GeoJSON): land-cover labels burnt window by window onto the reference grid, and AOIs.

A GeoJSON file is in EPSG:4326 (longitude, latitude; RFC 7946) unless it carries a (legacy) ``crs`` member
such as ``{"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32631"}}``. A file without one whose
coordinates cannot be degrees (a common export in a projected CRS) is refused, naming the CRS to declare.
Geometries are reprojected to the grid CRS with :func:`rasterio.warp.transform_geom`, repaired with
shapely's ``make_valid`` and indexed once in an ``STRtree`` so that each window rasterizes only the polygons
that intersect it.

Label polygons carry a class attribute (``class_field``) holding either a raw code (integer, mapped through
the :class:`~aerialmtl.classes.ClassScheme` like raster codes) or a class name (string, matched to the
scheme's names, case-insensitive). Pixels whose centre lies in no polygon get ``IGNORE_INDEX``; where
polygons overlap, the one listed later in the file wins.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import numpy as np
import shapely
from rasterio.crs import CRS
from rasterio.features import rasterize
from rasterio.warp import transform_geom
from rasterio.windows import Window
from shapely.geometry import box, mapping, shape
from shapely.strtree import STRtree

from aerialmtl.classes import IGNORE_INDEX, ClassScheme, OnUnknown
from aerialmtl.errors import AlignmentError, InputError, LabelError, cause

#: CRS of GeoJSON without a ``crs`` member (RFC 7946).
GEOJSON_DEFAULT_CRS = CRS.from_epsg(4326)


def read_geojson(path: str | Path, role: str = "vector file") -> tuple[list[dict[str, Any]], CRS]:
    """Read a GeoJSON FeatureCollection (or a single Feature/geometry).

    Returns:
        ``(features, crs)``: the list of feature mappings (``geometry``, ``properties``) and their CRS.

    Raises:
        InputError: the file is missing, not JSON, or not GeoJSON; the message names the file and the fix.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{role} '{p}' does not exist; check the path")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(
            f"{role} '{p}' is not GeoJSON ({exc}); convert it first, e.g. `ogr2ogr -f GeoJSON out.geojson {p.name}`"
        ) from exc
    if not isinstance(data, dict) or "type" not in data:
        raise InputError(f"{role} '{p}' is not a GeoJSON object (no 'type' member)")
    crs = GEOJSON_DEFAULT_CRS
    crs_member = data.get("crs")
    if crs_member:
        try:
            name = crs_member["properties"]["name"] if isinstance(crs_member, dict) else crs_member
            crs = CRS.from_user_input(name)
        except Exception as exc:
            raise InputError(
                f"{role} '{p}': cannot understand its 'crs' member {crs_member!r}; remove it (GeoJSON is "
                "EPSG:4326 by default) or write it as {{\"type\": \"name\", \"properties\": {{\"name\": "
                "\"EPSG:XXXX\"}}}}"
            ) from exc
    kind = data["type"]
    if kind == "FeatureCollection":
        features = list(data.get("features") or [])
    elif kind == "Feature":
        features = [data]
    else:
        features = [{"type": "Feature", "geometry": data, "properties": {}}]
    return features, crs


def load_geometries(
    path: str | Path, dst_crs: CRS, role: str = "vector file"
) -> list[tuple[shapely.Geometry, dict[str, Any]]]:
    """Polygons of ``path`` reprojected to ``dst_crs`` and made valid, with their properties.

    Features without geometry, and non-areal geometries (points, lines), are skipped.
    """
    features, src_crs = read_geojson(path, role)
    parsed = []
    for n, feat in enumerate(features):
        geom = feat.get("geometry") if isinstance(feat, dict) else None
        if not geom:
            continue
        try:
            g = shape(geom)
        except Exception as exc:  # shapely's errors for wrong nesting, missing coordinates, unknown types
            raise InputError(
                f"{role} '{path}': feature {n} has an invalid geometry ({cause(exc)}); fix or "
                "drop it, e.g. `ogr2ogr -makevalid out.geojson in.geojson`"
            ) from exc
        parsed.append((g, geom, feat))
    if src_crs is GEOJSON_DEFAULT_CRS and parsed:  # no 'crs' member: RFC 7946 says WGS 84 lon/lat
        check_lonlat(path, role, [g for g, _, _ in parsed], dst_crs)
    out = []
    for g, geom, feat in parsed:
        if src_crs != dst_crs:
            try:
                g = shape(transform_geom(src_crs, dst_crs, geom))
            except Exception as exc:
                raise InputError(
                    f"{role} '{path}': its polygons cannot be reprojected from {_crs_name(src_crs)} to "
                    f"{_crs_name(dst_crs)} ({cause(exc)}); check its CRS"
                ) from exc
        if not g.is_valid:
            g = shapely.make_valid(g)
        if g.is_empty or g.area <= 0:
            continue
        props = feat.get("properties")
        out.append((g, dict(props) if isinstance(props, dict) else {}))  # RFC 7946: an object or null
    return out


def _crs_name(crs: CRS) -> str:
    """``EPSG:32631`` when the CRS has an EPSG code, else its short name."""
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else crs.to_string()[:80]


def check_lonlat(path: str | Path, role: str, geoms: list[shapely.Geometry], dst_crs: CRS) -> None:
    """Refuse coordinates that cannot be WGS 84 degrees in a GeoJSON without a ``crs`` member.

    Raises:
        InputError: naming the file, the coordinates' extent and the CRS to declare (the orthophoto's,
            the usual case: a GIS export in the project's CRS without the legacy ``crs`` member).
    """
    x0, y0, x1, y1 = (float(v) for v in shapely.total_bounds(np.array(geoms, dtype=object)))
    if -180.0 <= x0 and x1 <= 180.0 and -90.0 <= y0 and y1 <= 90.0:
        return
    name = _crs_name(dst_crs)
    raise InputError(
        f"{role} '{path}' has no 'crs' member, so it is read as WGS 84 longitude/latitude (RFC 7946), but its "
        f"coordinates span x {x0:.6g}..{x1:.6g}, y {y0:.6g}..{y1:.6g}, which are not degrees; if they are in the "
        f"orthophoto's CRS ({name}), declare it in the file: \"crs\": {{\"type\": \"name\", \"properties\": "
        f"{{\"name\": \"{name}\"}}}}, or reproject the file to WGS 84: `ogr2ogr -t_srs EPSG:4326 out.geojson "
        f"{Path(path).name}`"
    )


def check_aoi_overlaps(path: str | Path | object, geoms: list[shapely.Geometry], grid: Any,
                       role: str = "AOI (‹aoi›)", param: str | None = "aoi") -> None:
    """Refuse AOI polygons ``geoms`` (in ``grid``'s CRS) that miss the orthophoto grid entirely.

    Raises:
        InputError: naming the file, the AOI's extent and the grid's extent (both in the grid's CRS).
    """
    gb = grid.bounds
    grid_box = box(*gb)
    if any(g.intersects(grid_box) for g in geoms):
        return
    ab = shapely.total_bounds(np.array(geoms, dtype=object)) if geoms else None
    shown = "(no polygons)" if ab is None else "(" + ", ".join(f"{v:.6g}" for v in ab) + ")"
    raise InputError(
        f"{role} {path if isinstance(path, dict) else repr(str(path))} does not overlap the orthophoto: its polygons "
        f"cover {shown}, the orthophoto covers ({', '.join(f'{v:.6g}' for v in gb)}), both in "
        f"{_crs_name(grid.crs)} (left, bottom, right, top); pass an AOI over the orthophoto, or check the AOI's "
        "CRS (WGS 84 unless the GeoJSON has a 'crs' member)",
        param=param,
    )


def _class_index(value: Any, scheme: ClassScheme) -> int | None | Literal["unknown"]:
    """Attribute value → class index, ``None`` for "no label" (ignore codes / null), or ``"unknown"``."""
    if value is None:
        return None
    if isinstance(value, bool):
        return "unknown"
    if isinstance(value, str):
        key = value.strip().casefold()
        for i, name in enumerate(scheme.names):
            if name.strip().casefold() == key:
                return i
        try:
            value = int(key)
        except ValueError:
            return "unknown"
    if isinstance(value, float):
        if not value.is_integer():
            return "unknown"
        value = int(value)
    if isinstance(value, int):
        if value in scheme.codes:
            return scheme.codes.index(value)
        if value in scheme.ignore_codes:
            return None
    return "unknown"


class VectorLabels:
    """Label polygons seen through the reference grid; :meth:`read` burns one window at a time.

    Args:
        path: GeoJSON file of polygons.
        grid: the reference :class:`~aerialmtl.io.align.Grid`.
        class_field: attribute holding the class code or name.
        scheme: the class scheme.
        on_unknown: ``"error"`` raises :class:`LabelError` listing the unknown values; ``"ignore"``
            drops those polygons (their pixels stay unlabelled).
        all_touched: burn every pixel a polygon touches instead of pixels whose centre is inside.

    Raises:
        InputError: the field is missing from every feature.
        LabelError: unknown class values (with ``on_unknown="error"``).
        AlignmentError: no polygon overlaps the grid.
    """

    def __init__(
        self,
        path: str | Path,
        grid: Any,
        class_field: str,
        scheme: ClassScheme,
        on_unknown: OnUnknown = "error",
        all_touched: bool = False,
    ) -> None:
        self.path = Path(path)
        self.grid = grid
        self.scheme = scheme
        self.all_touched = all_touched
        items = load_geometries(path, grid.crs, "labels vector")
        if items and not any(class_field in props for _, props in items):
            fields = sorted({k for _, props in items for k in props})
            raise InputError(
                f"labels vector '{self.path}': no feature has the attribute ‹class_field› '{class_field}'; "
                f"available attributes: {', '.join(fields) or '(none)'}"
            )
        geoms, values, unknown = [], [], set()
        for g, props in items:
            idx = _class_index(props.get(class_field), scheme)
            if idx == "unknown":
                unknown.add(repr(props.get(class_field)))
                continue
            if idx is None:
                continue
            geoms.append(g)
            values.append(idx)
        if unknown and on_unknown == "error":
            raise LabelError(
                f"labels vector '{self.path}': values {', '.join(sorted(unknown))} of attribute '{class_field}' "
                f"are neither codes ({scheme.codes}, ignored: {list(scheme.ignore_codes)}) nor names "
                f"({scheme.names}) of class scheme '{scheme.name}'; fix the attribute, add them to the scheme, "
                "or pass ‹ignore_unknown_codes=True› to leave those polygons unlabelled"
            )
        gb = grid.bounds
        grid_box = box(*gb)
        if not any(g.intersects(grid_box) for g in geoms):
            vb = shapely.total_bounds(np.array(geoms, dtype=object)) if geoms else None
            shown = "(no usable polygons)" if vb is None else "(" + ", ".join(f"{v:.6g}" for v in vb) + ")"
            raise AlignmentError(
                f"labels vector '{self.path}' does not overlap the orthophoto grid: its polygons cover {shown} "
                f"in {grid.crs.to_string()}, the grid covers ({', '.join(f'{v:.6g}' for v in gb)}); check that "
                "the files show the same area and that the GeoJSON's CRS is right (EPSG:4326 unless it has a "
                "'crs' member)"
            )
        self.geoms = np.array(geoms, dtype=object)
        self.values = np.array(values, dtype=np.int64)
        self.tree = STRtree(self.geoms)

    def read(self, window: Window) -> tuple[np.ndarray, np.ndarray]:
        """Burn ``window`` of the grid.

        Returns:
            ``(classes, labelled)``: (h, w) ``uint8`` class indices with ``IGNORE_INDEX`` where no polygon
            covers the pixel, and the (h, w) bool mask of labelled pixels.
        """
        h, w = int(window.height), int(window.width)
        transform = self.grid.window_transform(window)
        left, top = transform @ (0, 0)
        right, bottom = transform @ (w, h)
        win_box = box(min(left, right), min(top, bottom), max(left, right), max(top, bottom))
        hits = np.sort(self.tree.query(win_box, predicate="intersects"))  # keep file order: later wins
        out = np.full((h, w), IGNORE_INDEX, dtype=np.uint8)
        if hits.size:
            shapes = ((mapping(self.geoms[i]), int(self.values[i])) for i in hits)
            out = rasterize(shapes, out_shape=(h, w), transform=transform, fill=IGNORE_INDEX,
                            all_touched=self.all_touched, dtype="uint8")
        return out, out != IGNORE_INDEX

    def close(self) -> None:
        """Nothing to release (kept for symmetry with :class:`~aerialmtl.io.align.AlignedRaster`)."""

    def __enter__(self) -> VectorLabels:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["GEOJSON_DEFAULT_CRS", "VectorLabels", "check_aoi_overlaps", "check_lonlat", "load_geometries",
           "read_geojson"]
