"""``write_buildings``: extract the buildings of a prediction folder into GeoPackage, GeoJSON and CityJSON
files in one streaming pass — the library behind ``aerialmtl buildings``.

The format of each output follows its name: ``.gpkg`` (GeoPackage) and ``.geojson`` (GeoJSON) hold the
footprints with their attributes (:mod:`aerialmtl.formats.buildings`), ``.city.json`` / ``.cityjson``
the LoD1 solids (:mod:`aerialmtl.formats.cityjson`). Footprints are appended in batches and solids
streamed, so memory does not grow with the number of buildings. Every output is written under a
hidden temporary name in its folder and renamed only when all of them are complete: a failed or
interrupted run leaves no file at a final path.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aerialmtl.buildings.extract import BuildingOptions, ExtractionStats, extract_buildings
from aerialmtl.buildings.layers import BuildingLayers
from aerialmtl.errors import AerialMTLError, InputError, OutputError, OutputExistsError
from aerialmtl.filesafety import staging_path
from aerialmtl.formats.buildings import GROUND_Z_FIELD, ID_FIELD, PREDICTED_FIELDS, FootprintWriter, driver_for
from aerialmtl.formats.cityjson import CityJSONWriter
from aerialmtl.formats.prediction import PredictionFolder
from aerialmtl.io.oserrors import kind_of, output_error, writing
from aerialmtl.io.outputs import OutputFolder, check_files_not_input, make_output_dir

#: Name endings of CityJSON outputs.
CITYJSON_SUFFIXES = (".city.json", ".cityjson")


def output_format(path: str | Path) -> str:
    """``"GPKG"``, ``"GeoJSON"`` or ``"CityJSON"`` from the name of ``path``.

    Raises:
        InputError: any other ending.
    """
    name = Path(path).name.lower()
    if name.endswith(CITYJSON_SUFFIXES):
        return "CityJSON"
    try:
        return driver_for(path)
    except InputError:
        raise InputError(
            f"output '{path}': the format follows the name: .gpkg (GeoPackage), .geojson (GeoJSON) or "
            ".city.json (CityJSON LoD1); rename it"
        ) from None


@dataclass(frozen=True)
class BuildingsResult:
    """What :func:`write_buildings` wrote.

    Attributes:
        outputs: final path → format.
        count: buildings written.
        stats: pixel and component counts (:class:`~aerialmtl.buildings.extract.ExtractionStats`).
        crs: the CRS of the outputs (the prediction's), as a string.
        seconds: wall time.
    """

    outputs: dict[Path, str]
    count: int
    stats: ExtractionStats
    crs: str
    seconds: float


def _hidden(path: Path) -> Path:
    return staging_path(path, keep_suffix=True)


def write_buildings(
    pred_dir: str | Path,
    outputs: Sequence[str | Path],
    options: BuildingOptions | None = None,
    dtm: str | Path | None = None,
    building_classes: Sequence[str | int] | None = None,
    overwrite: bool = False,
    batch_size: int = 2000,
    progress: bool = False,
) -> BuildingsResult:
    """Extract the buildings of ``pred_dir`` and write them to every file of ``outputs``.

    Args:
        pred_dir: folder written by ``aerialmtl predict``.
        outputs: output files; the format follows the name (see :func:`output_format`).
        options: extraction and cleaning settings.
        dtm: terrain model (metres, any CRS/GSD): each building gets ``ground_z_m`` and its CityJSON solid
            stands on it (without one, solids stand on z = 0).
        building_classes: names or indices of the building classes (default: recognised by name).
        overwrite: replace existing outputs.
        batch_size: footprints appended to the vector files at once.
        progress: show a tqdm bar.

    Returns:
        a :class:`BuildingsResult`.

    Raises:
        InputError: no output, an unknown output format, or what extraction raises.
        OutputExistsError: an output exists and ``overwrite`` is false.
        OutputError: an output folder cannot be created or written.
    """
    start = time.perf_counter()
    if not outputs:
        raise InputError("outputs: give at least one output file (.gpkg, .geojson or .city.json)")
    paths = [Path(p) for p in outputs]
    formats = {p: output_format(p) for p in paths}
    dup = sorted({str(p) for p in paths if paths.count(p) > 1})
    if dup:
        raise InputError(f"outputs: {', '.join(dup)} given more than once")
    existing = [str(p) for p in paths if os.path.lexists(p)]
    if existing and not overwrite:
        raise OutputExistsError(f"{', '.join(existing)} already exist(s); pass ‹overwrite=True› to "
                                "replace them or choose other output names")
    folders = [p for p in existing if Path(p).is_dir()]
    if folders:
        raise OutputError(f"'{folders[0]}' is a folder where a building file would be written; choose other "
                          "‹outputs›")
    pred = PredictionFolder(pred_dir)
    check_files_not_input(paths, [("dtm", dtm), *(("pred_dir", p) for p in pred.layers().values()),
                                  ("pred_dir", pred.info_path)], option="outputs")
    stats = ExtractionStats()
    with contextlib.ExitStack() as held:
        for parent in dict.fromkeys(p.parent for p in paths):  # each output folder is this run's until it ends
            held.enter_context(OutputFolder(parent, "buildings", option="outputs", what="output folder"))
        return _write(pred_dir, paths, formats, options, dtm, building_classes, batch_size, progress, stats, start)


def _write(pred_dir: str | Path, paths: list[Path], formats: dict[Path, str], options: BuildingOptions | None,
           dtm: str | Path | None, building_classes: Sequence[str | int] | None, batch_size: int, progress: bool,
           stats: ExtractionStats, start: float) -> BuildingsResult:
    """:func:`write_buildings` once the output folders are held."""
    with BuildingLayers(pred_dir, dtm=dtm) as layers:
        for p in paths:
            make_output_dir(p.parent)
        fields = dict(PREDICTED_FIELDS, **({GROUND_Z_FIELD: "float64"} if dtm is not None else {}))
        grid = layers.grid
        vectors: dict[Path, FootprintWriter] = {}
        solids: dict[Path, CityJSONWriter] = {}
        try:
            for p, fmt in formats.items():
                _hidden(p).unlink(missing_ok=True)
                if fmt == "CityJSON":
                    left, bottom, _, _ = grid.bounds
                    solids[p] = CityJSONWriter(_hidden(p), grid.crs, (left, bottom, 0.0), 1.0 / layers.metres_per_unit)
                else:
                    vectors[p] = FootprintWriter(_hidden(p), grid.crs, fields, fmt)
            geoms: list[Any] = []
            records: dict[str, list[Any]] = {name: [] for name in fields}

            def flush() -> None:
                for writer in vectors.values():
                    writer.write(geoms, records)
                geoms.clear()
                for values in records.values():
                    values.clear()

            count = 0
            for bld in extract_buildings(layers, options, building_classes, stats, progress):
                row = {ID_FIELD: bld.id, **bld.attributes}
                for name in fields:
                    records[name].append(row[name])
                geoms.append(bld.geometry)
                z0 = row.get(GROUND_Z_FIELD, 0.0)
                for cj in solids.values():
                    cj.add(f"building-{bld.id}", bld.geometry, z0, row["height_m"], row)
                count += 1
                if len(geoms) >= batch_size:
                    flush()
            flush()
            for writer in vectors.values():
                writer.close()
            for cj in solids.values():
                cj.close()
        except BaseException as exc:
            for cj in solids.values():
                cj.discard_parts()
            for p in paths:
                _hidden(p).unlink(missing_ok=True)
            if isinstance(exc, AerialMTLError):
                raise
            # pyogrio reports a full disk as its own error, sometimes without saying so
            kinds = [kind_of(exc, p) for p in paths]
            if isinstance(exc, OSError) or any(kinds):
                bad = [p for p, k in zip(paths, kinds) if k] or paths
                raise output_error(exc, ", ".join(str(p) for p in bad), "the building outputs", "‹outputs›") from exc
            raise
        crs = grid.crs.to_string()
    for p in paths:
        with writing(p, "the building outputs", "‹outputs›"):
            os.replace(_hidden(p), p)
    return BuildingsResult({p: formats[p] for p in paths}, count, stats, crs, time.perf_counter() - start)


__all__ = ["CITYJSON_SUFFIXES", "BuildingsResult", "output_format", "write_buildings"]
