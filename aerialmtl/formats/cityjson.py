"""CityJSON 2.0 files of LoD1 buildings (extruded footprints), written in a stream.

One ``"Building"`` city object per footprint, with one ``"Solid"`` geometry of ``"lod": "1"``: a floor at
the ground elevation, a flat roof at ground + height and one vertical wall per footprint edge (courtyards
included). Surfaces are oriented outwards (exterior rings counter-clockwise seen from outside), so every
edge of a solid is used once in each direction. Coordinates are integers with the file's ``transform``
(``scale`` :data:`SCALE` CRS units, ``translate`` = a corner given by the caller); x, y are in the
prediction's CRS and z is in the same linear unit (metres, or feet for a CRS in feet), so the solids
are not stretched. Attributes keep their metre units. ``metadata.referenceSystem`` is the OGC URL of the
CRS's EPSG code (left out when the CRS has none).

City objects and vertices go to two temporary files while buildings arrive; :meth:`CityJSONWriter.close`
assembles the final file from them, so memory does not grow with the number of buildings.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import IO, Any

import numpy as np
from rasterio.crs import CRS
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

#: CityJSON version written.
VERSION = "2.0"
#: Level of detail of the solids.
LOD = "1"
#: Size of one integer coordinate step, in CRS units (1 mm for a CRS in metres).
SCALE = 0.001


def _jsonable(value: Any) -> Any:
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


class CityJSONWriter:
    """Stream LoD1 buildings into a CityJSON 2.0 file.

    Args:
        path: output file (``.city.json``); written by :meth:`close`.
        crs: CRS of the footprints (projected).
        translate: ``(x, y, z)`` subtracted from every vertex before scaling (e.g. the raster's lower-left
            corner and 0).
        z_factor: CRS units per metre of height (1 / the CRS's linear unit in metres).
    """

    def __init__(self, path: str | Path, crs: CRS, translate: tuple[float, float, float],
                 z_factor: float = 1.0) -> None:
        self.path = Path(path)
        self.crs = crs
        self.translate = tuple(float(v) for v in translate)
        self.z_factor = float(z_factor)
        self._objects_path = self.path.with_name(self.path.name + ".objects")
        self._vertices_path = self.path.with_name(self.path.name + ".vertices")
        self._objects: IO[str] = self._objects_path.open("w", encoding="utf-8")
        self._vertices: IO[str] = self._vertices_path.open("w", encoding="utf-8")
        self.n_objects = 0
        self.n_vertices = 0
        self._lo = np.full(3, np.inf)
        self._hi = np.full(3, -np.inf)

    def _int_xy(self, coords: np.ndarray) -> np.ndarray:
        result: np.ndarray = np.rint((coords[:, :2] - np.array(self.translate[:2])) / SCALE).astype(np.int64)
        return result

    def add(self, object_id: str, footprint: Polygon | None, z_ground_m: float, height_m: float,
            attributes: dict[str, Any]) -> None:
        """Add one building.

        Args:
            object_id: unique id of the city object.
            footprint: polygon in the CRS (``None``, or a non-positive / undefined ``height_m``, writes the
                building with its attributes but without geometry).
            z_ground_m: ground elevation (metres).
            height_m: height of the flat roof above the ground (metres).
            attributes: written under ``"attributes"`` (NaN → null).
        """
        obj: dict[str, Any] = {"type": "Building", "attributes": {k: _jsonable(v) for k, v in attributes.items()}}
        if footprint is not None and not footprint.is_empty and math.isfinite(height_m) and height_m > 0:
            solid = self._solid(footprint, z_ground_m, height_m)
            if solid is not None:
                obj["geometry"] = [solid]
        text = json.dumps(object_id) + ":" + json.dumps(obj, separators=(",", ":"))
        self._objects.write(("," if self.n_objects else "") + text)
        self.n_objects += 1

    def _solid(self, footprint: Polygon, z_ground_m: float, height_m: float) -> dict[str, Any] | None:
        poly = orient(footprint, 1.0)  # exterior counter-clockwise, holes clockwise (seen from above)
        z0 = int(round((z_ground_m * self.z_factor - self.translate[2]) / SCALE))
        z1 = int(round(((z_ground_m + height_m) * self.z_factor - self.translate[2]) / SCALE))
        rings = []
        for ring in (poly.exterior, *poly.interiors):
            xy = self._int_xy(np.asarray(ring.coords)[:-1])
            keep = np.any(xy != np.roll(xy, 1, axis=0), axis=1)  # vertices that rounding made equal
            rings.append(xy[keep])
        if len(rings[0]) < 3:  # a footprint smaller than the coordinate step
            return None
        rings = [rings[0]] + [r for r in rings[1:] if len(r) >= 3]
        base = self.n_vertices
        rows: list[list[int]] = []
        bottom: list[list[int]] = []  # vertex indices per ring at z0; the top ring is bottom + len(ring)
        for xy in rings:
            start = base + len(rows)
            rows += [[int(x), int(y), z0] for x, y in xy]
            rows += [[int(x), int(y), z1] for x, y in xy]
            bottom.append(list(range(start, start + len(xy))))
        floor = [list(reversed(b)) for b in bottom]            # seen from below: clockwise from above
        roof = [[i + len(b) for i in b] for b in bottom]       # seen from above: counter-clockwise
        walls = []
        for b in bottom:
            n = len(b)
            for k in range(n):
                i, j = b[k], b[(k + 1) % n]
                walls.append([[i, j, j + n, i + n]])           # outward: the exterior is right of i → j
        self._vertices.write(("," if self.n_vertices else "")
                             + ",".join(json.dumps(r, separators=(",", ":")) for r in rows))
        self.n_vertices += len(rows)
        arr = np.asarray(rows, np.float64)
        self._lo = np.minimum(self._lo, arr.min(axis=0))
        self._hi = np.maximum(self._hi, arr.max(axis=0))
        return {"type": "Solid", "lod": LOD, "boundaries": [[floor, roof, *walls]]}

    def _metadata(self) -> dict[str, Any]:
        meta: dict[str, Any] = {}
        epsg = self.crs.to_epsg() if self.crs is not None else None
        if epsg:
            meta["referenceSystem"] = f"https://www.opengis.net/def/crs/EPSG/0/{epsg}"
        if self.n_vertices:
            t = np.array(self.translate)
            meta["geographicalExtent"] = [*(self._lo * SCALE + t).tolist(), *(self._hi * SCALE + t).tolist()]
        return meta

    def close(self) -> None:
        """Write the final file from the temporary parts and delete them."""
        self._objects.close()
        self._vertices.close()
        head = {"type": "CityJSON", "version": VERSION,
                "transform": {"scale": [SCALE, SCALE, SCALE], "translate": list(self.translate)},
                "metadata": self._metadata()}
        with self.path.open("w", encoding="utf-8") as out:
            out.write(json.dumps(head)[:-1] + ',"CityObjects":{')
            with self._objects_path.open(encoding="utf-8") as part:
                shutil.copyfileobj(part, out)
            out.write('},"vertices":[')
            with self._vertices_path.open(encoding="utf-8") as part:
                shutil.copyfileobj(part, out)
            out.write("]}\n")
        self.discard_parts()

    def discard_parts(self) -> None:
        """Close and delete the temporary parts (after :meth:`close`, or to abandon the file)."""
        for f in (self._objects, self._vertices):
            if not f.closed:
                f.close()
        self._objects_path.unlink(missing_ok=True)
        self._vertices_path.unlink(missing_ok=True)


__all__ = ["LOD", "SCALE", "VERSION", "CityJSONWriter"]
