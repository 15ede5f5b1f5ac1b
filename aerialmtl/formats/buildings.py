"""Building footprint layers: what ``aerialmtl buildings`` writes, ``aerialmtl synth`` writes as reference
and ``aerialmtl evaluate --buildings`` reads.

One polygon layer named :data:`LAYER` in a GeoPackage (``.gpkg``) or GeoJSON (``.geojson``) file, in the
CRS of the prediction (or of the synthetic town). Written and read through **pyogrio** (GDAL's OGR with
numpy arrays: no per-feature Python objects, and the same GDAL build as its wheels on every platform).
GeoJSON in a projected CRS carries the (legacy) ``crs`` member GDAL writes, which
:func:`aerialmtl.io.vector.read_geojson` and every GIS understand.

Fields of a predicted building (:data:`PREDICTED_FIELDS`; metres and square/cubic metres whatever the
CRS unit)::

    building_id       int     1, 2, ... in the order the buildings were completed (raster order)
    class_name        str     the building class most of its pixels have
    height_m          float   roof height above ground: a percentile (default the median) of height.tif
    height_std_m      float   median MC-dropout standard deviation (height_std.tif) over the same pixels
    ground_area_m2    float   area of the cleaned footprint polygon
    volume_m3         float   mean predicted height above ground × ground_area_m2
    class_confidence  float   mean of 1 − entropy / ln K (class_entropy.tif) over the pixels, in [0, 1]
    n_pixels          int     pixels of the building in classes.tif
    ground_z_m        float   median terrain elevation under the footprint (only with a DTM)

Fields of a reference building (:data:`REFERENCE_FIELDS`): ``building_id``, ``height_m`` (the same statistic of
the true roof surface), ``height_max_m`` (highest roof point).

Undefined values (no ``height_std.tif``, ...) are written as null.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from rasterio.crs import CRS

from aerialmtl.errors import InputError, cause

#: Layer name inside the files.
LAYER = "buildings"
#: The reference footprints ``aerialmtl synth`` writes beside its rasters.
REFERENCE_FILE = "buildings.geojson"

#: The building number field. Not "id": GDAL's GeoJSON driver takes an integer "id" property for the
#: feature id and then reorders the features it appends.
ID_FIELD = "building_id"
#: Field name → numpy dtype of the predicted buildings, in file order.
PREDICTED_FIELDS: dict[str, str] = {
    ID_FIELD: "int64",
    "class_name": "object",
    "height_m": "float64",
    "height_std_m": "float64",
    "ground_area_m2": "float64",
    "volume_m3": "float64",
    "class_confidence": "float64",
    "n_pixels": "int64",
}
#: Extra field written when a DTM gives the ground elevation.
GROUND_Z_FIELD = "ground_z_m"
#: Field name → numpy dtype of the reference buildings.
REFERENCE_FIELDS: dict[str, str] = {ID_FIELD: "int64", "height_m": "float64", "height_max_m": "float64"}

#: OGR driver per file suffix.
DRIVERS = {".gpkg": "GPKG", ".geojson": "GeoJSON", ".json": "GeoJSON"}
#: GeoPackage version written (GDAL creation option ``VERSION``): GDAL ≥ 3.7.1 writes 1.4 by default, which
#: the GDAL 3.6 of QGIS long-term releases opens with a warning; 1.2 opens without one in every GDAL ≥ 2.2
#: and needs nothing 1.3/1.4 added.
GPKG_VERSION = "1.2"
#: Dataset creation options per driver.
DATASET_OPTIONS: dict[str, dict[str, str]] = {"GPKG": {"VERSION": GPKG_VERSION}}


def driver_for(path: str | Path) -> str:
    """OGR driver of a footprint file from its suffix (``.gpkg`` → GPKG, ``.geojson`` → GeoJSON).

    Raises:
        InputError: any other suffix.
    """
    suffix = Path(path).suffix.lower()
    if suffix not in DRIVERS:
        raise InputError(f"'{path}': footprint files end in .gpkg or .geojson, got '{suffix or '(no suffix)'}'")
    return DRIVERS[suffix]


class FootprintWriter:
    """Append polygons with attributes to a new GeoPackage / GeoJSON file, batch by batch.

    Args:
        path: the file (must not exist; the caller writes to a temporary name and renames).
        crs: CRS of the coordinates.
        fields: field name → numpy dtype (e.g. :data:`PREDICTED_FIELDS`).
        driver: ``"GPKG"`` or ``"GeoJSON"`` (default: from the suffix of ``path``).

    The layer is created on the first :meth:`write` (or by :meth:`close` when nothing was written, so an
    empty result is still a valid, empty layer).
    """

    def __init__(self, path: str | Path, crs: CRS, fields: dict[str, str], driver: str | None = None) -> None:
        self.path = Path(path)
        self.crs_wkt = crs.to_wkt()
        self.fields = dict(fields)
        self.driver = driver or driver_for(self.path)
        self.count = 0
        self._created = False

    def write(self, geometries: Sequence[shapely.Geometry], records: Mapping[str, Sequence[Any]]) -> None:
        """Append ``geometries`` (polygons in the writer's CRS) with ``records[field][i]`` as attributes."""
        import pyogrio.raw

        if not self._created or len(geometries):
            wkb = np.asarray(shapely.to_wkb(np.asarray(geometries, dtype=object)), dtype=object) if len(geometries) \
                else np.array([], dtype=object)
            data = [np.asarray(records[name], dtype=dtype) if len(geometries) else np.array([], dtype=dtype)
                    for name, dtype in self.fields.items()]
            options = {} if self._created else DATASET_OPTIONS.get(self.driver, {})
            pyogrio.raw.write(self.path, wkb, data, list(self.fields), layer=LAYER, driver=self.driver,
                              geometry_type="Polygon", crs=self.crs_wkt, append=self._created,
                              dataset_options=options or None)
            self._created = True
            self.count += len(geometries)

    def close(self) -> None:
        """Create the (empty) layer if nothing was written."""
        if not self._created:
            self.write([], {})


def read_footprints(path: str | Path, role: str = "building footprints") -> tuple[list[shapely.Geometry],
                                                                                  dict[str, np.ndarray], CRS | None]:
    """Read a polygon layer (GeoPackage, GeoJSON or any file OGR reads).

    Returns:
        ``(geometries, fields, crs)``: shapely geometries (``None`` for features without one), field name →
        array, and the layer's CRS (``None`` when the file has none).

    Raises:
        InputError: the file is missing or not a vector file OGR can read.
    """
    import pyogrio
    import pyogrio.raw

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{role} '{p}' does not exist; check the path")
    try:
        meta, _, wkb, values = pyogrio.raw.read(p)
    except Exception as exc:  # pyogrio raises its own DataSourceError / DataLayerError
        raise InputError(
            f"{role} '{p}' cannot be read as a vector file ({cause(exc)}); pass a "
            "GeoPackage or GeoJSON of polygons"
        ) from exc
    geoms = list(shapely.from_wkb(wkb)) if wkb is not None else []
    fields = {str(name): np.asarray(v) for name, v in zip(meta["fields"], values)}
    crs = CRS.from_user_input(meta["crs"]) if meta.get("crs") else None
    return geoms, fields, crs


__all__ = [
    "DATASET_OPTIONS", "DRIVERS", "GPKG_VERSION",
    "GROUND_Z_FIELD", "ID_FIELD", "LAYER", "PREDICTED_FIELDS", "REFERENCE_FIELDS", "REFERENCE_FILE",
    "FootprintWriter", "driver_for", "read_footprints",
]
