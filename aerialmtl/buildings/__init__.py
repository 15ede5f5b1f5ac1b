"""LoD1 building models from a prediction folder: footprints, heights and their uncertainty.

* :mod:`aerialmtl.buildings.layers` — the layers read (which class is a building, CRS units);
* :mod:`aerialmtl.buildings.extract` — building pixels → one footprint per building, streamed in blocks;
* :mod:`aerialmtl.buildings.clean` — hole filling, simplification, orthogonal regularisation;
* :mod:`aerialmtl.buildings.attributes` — height, spread, area, volume, confidence per building;
* :mod:`aerialmtl.buildings.export` — GeoPackage / GeoJSON / CityJSON outputs (``aerialmtl buildings``).
"""

from aerialmtl.buildings.export import BuildingsResult, output_format, write_buildings
from aerialmtl.buildings.extract import (
    Building,
    BuildingOptions,
    ExtractionStats,
    extract_buildings,
    iter_buildings,
)
from aerialmtl.buildings.layers import BuildingLayers, building_class_indices

__all__ = [
    "Building",
    "BuildingLayers",
    "BuildingOptions",
    "BuildingsResult",
    "ExtractionStats",
    "building_class_indices",
    "extract_buildings",
    "iter_buildings",
    "output_format",
    "write_buildings",
]
