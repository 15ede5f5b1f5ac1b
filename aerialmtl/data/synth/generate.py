"""``synthesize``: write a georeferenced synthetic town (ortho, DSM, DTM, nDSM, labels) to a folder."""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from affine import Affine
from rasterio.crs import CRS
from rasterio.enums import ColorInterp
from rasterio.errors import CRSError
from shapely.affinity import affine_transform
from shapely.geometry.polygon import orient

from aerialmtl.classes import BUILTIN_DIR, ClassScheme
from aerialmtl.data.synth.city import sample_city
from aerialmtl.data.synth.render import render_ortho
from aerialmtl.data.synth.scene import build_scene
from aerialmtl.data.synth.scene_parts import Scene
from aerialmtl.data.synth.style import CityStyle, Imaging
from aerialmtl.data.synth.textures import TexturePool
from aerialmtl.errors import InputError, OutputExistsError
from aerialmtl.filesafety import atomic_write
from aerialmtl.formats.buildings import ID_FIELD, REFERENCE_FIELDS, REFERENCE_FILE, FootprintWriter
from aerialmtl.formats.tiles import HEIGHT_NODATA
from aerialmtl.io.outputs import OutputFolder
from aerialmtl.io.profiles import light_compression, raster_profile

#: Version of the generator; bump it whenever the same seed would produce different rasters.
SYNTH_VERSION = "1"

#: Smallest scene size accepted (pixels).
MIN_SIZE = 32

_OUTPUTS = ("ortho.tif", "dsm.tif", "dtm.tif", "ndsm.tif", "labels.tif", "classes.yaml", REFERENCE_FILE)


@dataclass(frozen=True)
class Written:
    """The folder and the files both :func:`synthesize` and :func:`synthesize_city` write."""

    out_dir: Path
    ortho: Path
    dsm: Path
    dtm: Path
    ndsm: Path
    labels: Path
    classes: Path


@dataclass(frozen=True)
class SynthResult(Written):
    """Paths written by :func:`synthesize` and the scene's sun angles (degrees; the azimuth from the grid's
    north).
    """

    sun_azimuth: float
    sun_elevation: float
    seconds: float
    buildings: Path

    def sun_option(self) -> str:
        """The town's own sun as ``predict --sun`` takes it, ``"AZ,EL"`` in degrees from true north: what a flight
        record gives a user. Towns made at one place under different suns are two flights of one town, and
        ``--sun auto`` rightly gives the second no sun of a model trained on the first
        (:mod:`aerialmtl.sun.flight`); the demo and the uncertainty notebook pass this instead.
        """
        from aerialmtl.sun.solar_position import grid_convergence_deg

        with rasterio.open(self.ortho) as src:
            crs, b = src.crs.to_string(), src.bounds
        convergence = grid_convergence_deg(crs, (b.left + b.right) / 2.0, (b.bottom + b.top) / 2.0)
        return f"{(self.sun_azimuth - convergence) % 360.0:.4f},{self.sun_elevation:.4f}"


def _profile(size: int, count: int, dtype: str, crs: CRS, transform: Affine, nodata: float | None) -> dict[str, Any]:
    block = 256 if size >= 256 else None
    profile = raster_profile(crs, transform, size, size, count, dtype, nodata)
    profile.update(light_compression(), predictor=3 if dtype == "float32" else 2, num_threads="ALL_CPUS",
                   bigtiff="IF_SAFER")
    if block:
        profile.update(tiled=True, blockxsize=block, blockysize=block)
    if count == 3:
        profile.update(interleave="pixel", photometric="RGB")
    return profile


def synthesize(
    out_dir: str | Path,
    size: int = 1024,
    seed: int = 0,
    gsd: float = 0.25,
    crs: str = "EPSG:32631",
    origin: tuple[float, float] = (500000.0, 5000000.0),
    overwrite: bool = False,
) -> SynthResult:
    """Generate a procedural town and write it as pixel-aligned GeoTIFFs in ``out_dir``.

    Files (all ``size`` × ``size`` pixels, north-up, ``gsd`` metres, upper-left corner at ``origin``):
    ``ortho.tif`` (uint8 RGB), ``dsm.tif``, ``dtm.tif``, ``ndsm.tif`` (float32 metres, nodata
    :data:`HEIGHT_NODATA`, nDSM = DSM − DTM), ``labels.tif`` (uint8 raw codes of the built-in
    ``synthetic`` class scheme, nodata 0), ``classes.yaml`` (that scheme) and ``buildings.geojson``
    (the true footprint of every building, clipped to the scene, with ``height_m`` = the median roof
    height above ground and ``height_max_m``; in ``crs``, see :mod:`aerialmtl.formats.buildings`).
    Every raster carries the tags ``AERIALMTL_SYNTH_VERSION``, ``AERIALMTL_SYNTH_SEED``, ``AERIALMTL_SYNTH_SIZE``,
    ``AERIALMTL_SYNTH_GSD``, ``AERIALMTL_SUN_AZIMUTH`` and ``AERIALMTL_SUN_ELEVATION``.
    The same (seed, size, gsd) always gives identical arrays.

    Args:
        out_dir: output folder (created if missing).
        size: width and height in pixels (≥ 32).
        seed: random seed.
        gsd: pixel size in metres (> 0).
        crs: a projected CRS (EPSG code or WKT), in metres or another linear unit (pixels are ``gsd``
            metres on the ground whatever the unit; heights are written in metres).
        origin: map coordinates (x, y) of the upper-left corner.
        overwrite: replace existing outputs.

    Raises:
        InputError: bad ``size``, ``gsd`` or ``crs``.
        OutputExistsError: an output exists and ``overwrite`` is False.
        OutputError: ``out_dir`` cannot be created.
    """
    start = time.perf_counter()
    crs_obj = _check_args(size, gsd, crs)
    out = Path(out_dir)
    with _claimed(out, _OUTPUTS, overwrite):
        return _write_scene(out, size, seed, gsd, crs_obj, origin, start)


def _check_args(size: int, gsd: float, crs: str) -> CRS:
    """Validate the options shared by the writers; returns the CRS."""
    if int(size) != size or size < MIN_SIZE:
        raise InputError(f"‹size› must be an integer ≥ {MIN_SIZE} pixels, got {size}; pass e.g. ‹size=1024›",
                         param="size")
    if not gsd > 0:
        raise InputError(f"‹gsd› must be a positive pixel size in metres, got {gsd}; pass e.g. ‹gsd=0.25›",
                         param="gsd")
    try:
        crs_obj = CRS.from_user_input(crs)
    except CRSError as exc:
        raise InputError(f"‹crs› {crs!r} is not a valid CRS ({exc}); pass an EPSG code such as 'EPSG:32631'",
                         param="crs") from exc
    if not crs_obj.is_projected:
        raise InputError(f"‹crs› {crs!r} is not projected; synthetic scenes need a projected CRS, e.g. a UTM zone "
                         "'EPSG:32631'", param="crs")
    return crs_obj


@contextlib.contextmanager
def _claimed(out: Path, outputs: tuple[str, ...], overwrite: bool) -> Iterator[None]:
    """Hold ``out`` for writing ``outputs`` (refusing existing ones unless ``overwrite``)."""
    existing = [name for name in outputs if os.path.lexists(out / name)]
    if existing and not overwrite:
        raise OutputExistsError(
            f"{out}: {', '.join(existing)} already exist; pass ‹overwrite=True› to replace them "
            "or choose another output folder"
        )
    with OutputFolder(out, "synth", what="output folder") as folder:
        folder.claim(outputs, overwrite)
        folder.remove_leftovers(outputs)
        yield


def _write_scene(out: Path, size: int, seed: int, gsd: float, crs_obj: CRS, origin: tuple[float, float],
                 start: float) -> SynthResult:
    """Render and write the town (see :func:`synthesize`) into the held folder ``out``."""
    rng = np.random.default_rng(seed)
    scene = build_scene(int(size), float(gsd), rng)
    ortho, _ = render_ortho(scene, rng)
    paths = _write_rasters(out, _Layers(ortho, scene.dtm, scene.ndsm, scene.labels), gsd, crs_obj, origin,
                           _tags(seed, size, gsd, scene.sun_azimuth, scene.sun_elevation))
    _write_reference_buildings(scene, out / REFERENCE_FILE, crs_obj, origin)
    return SynthResult(out, paths["ortho.tif"], paths["dsm.tif"], paths["dtm.tif"], paths["ndsm.tif"],
                       paths["labels.tif"], paths["classes.yaml"], scene.sun_azimuth, scene.sun_elevation,
                       time.perf_counter() - start, out / REFERENCE_FILE)


def _tags(seed: int, size: int, gsd: float, sun_azimuth: float, sun_elevation: float) -> dict[str, str]:
    return {
        "AERIALMTL_SYNTH_VERSION": SYNTH_VERSION,
        "AERIALMTL_SYNTH_SEED": str(seed),
        "AERIALMTL_SYNTH_SIZE": str(size),
        "AERIALMTL_SYNTH_GSD": repr(float(gsd)),
        "AERIALMTL_SUN_AZIMUTH": f"{sun_azimuth:.4f}",
        "AERIALMTL_SUN_ELEVATION": f"{sun_elevation:.4f}",
    }


@dataclass(frozen=True)
class _Layers:
    """What a scene writes: uint8 (3, H, W) ortho, float32 (H, W) DTM and nDSM (metres), uint8 labels."""

    ortho: np.ndarray
    dtm: np.ndarray
    ndsm: np.ndarray
    labels: np.ndarray


def _write_rasters(out: Path, layers: _Layers, gsd: float, crs_obj: CRS, origin: tuple[float, float],
                   tags: dict[str, str]) -> dict[str, Path]:
    """Write ortho, DSM (= DTM + nDSM), DTM, nDSM, labels and classes.yaml into ``out``; returns their paths."""
    size = layers.ndsm.shape[0]
    dsm = (layers.dtm + layers.ndsm).astype(np.float32)
    ndsm = dsm - layers.dtm  # exactly DSM − DTM in float32
    px = gsd / float(crs_obj.linear_units_factor[1])  # pixel size in CRS units (e.g. feet)
    transform = Affine(px, 0.0, origin[0], 0.0, -px, origin[1])
    scheme = ClassScheme.load("synthetic")
    paths = {name: out / name for name in _OUTPUTS}

    def write(name: str, data: np.ndarray, nodata: float | None, descriptions: tuple[str, ...],
              units: str | None = None, colormap: dict[int, tuple[int, int, int, int]] | None = None) -> None:
        count = data.shape[0] if data.ndim == 3 else 1
        profile = _profile(size, count, data.dtype.name, crs_obj, transform, nodata)
        with atomic_write(paths[name]) as tmp, rasterio.open(tmp, "w", **profile) as dst:
            dst.write(data if data.ndim == 3 else data[None])
            dst.update_tags(**tags)
            for i, desc in enumerate(descriptions, start=1):
                dst.set_band_description(i, desc)
            if units:
                dst.units = (units,) * count
            if count == 3:
                dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue]
            if colormap:
                dst.write_colormap(1, colormap)

    write("ortho.tif", layers.ortho, None, ("red", "green", "blue"))
    write("dsm.tif", dsm, HEIGHT_NODATA, ("DSM",), "metre")
    write("dtm.tif", layers.dtm, HEIGHT_NODATA, ("DTM",), "metre")
    write("ndsm.tif", ndsm, HEIGHT_NODATA, ("nDSM",), "metre")
    cmap = {c.code: (*c.color, 255) for c in scheme.classes}
    cmap.update({code: (0, 0, 0, 0) for code in scheme.ignore_codes})
    write("labels.tif", layers.labels, 0, ("land cover (raw code)",), colormap=cmap)
    with atomic_write(paths["classes.yaml"]) as tmp:
        shutil.copyfile(BUILTIN_DIR / "synthetic.yaml", tmp)
    return paths


_CITY_OUTPUTS = _OUTPUTS[:-1]  # no reference footprints for a city
#: Ground elevation of a synthetic city's (flat) DTM, metres.
CITY_GROUND_M = 100.0


@dataclass(frozen=True)
class CityResult(Written):
    """Paths written by :func:`synthesize_city`, the imaging the ortho was made with, and the time taken (s)."""

    imaging: Imaging
    seconds: float


def synthesize_city(out_dir: str | Path, size: int = 1024, seed: int = 0, gsd: float = 0.5,
                    crs: str = "EPSG:32631", origin: tuple[float, float] = (500000.0, 5000000.0),
                    style: CityStyle | None = None, textures: TexturePool | None = None,
                    overwrite: bool = False) -> CityResult:
    """Write a synthetic city (:func:`~aerialmtl.data.synth.city.sample_city`) as pixel-aligned GeoTIFFs.

    The files are those of :func:`synthesize` without ``buildings.geojson``; the DTM is flat at
    :data:`CITY_GROUND_M`; the orthophoto is a non-true one (tall things lean, see the ``AERIALMTL_LEAN_*`` tags)
    while the nDSM and labels sit at the true footprints. Arguments as :func:`synthesize`, plus ``style`` and
    ``textures`` as :func:`~aerialmtl.data.synth.city.sample_city`.

    Raises:
        InputError: bad ``size``, ``gsd`` or ``crs``.
        OutputExistsError: an output exists and ``overwrite`` is False.
    """
    start = time.perf_counter()
    crs_obj = _check_args(size, gsd, crs)
    out = Path(out_dir)
    with _claimed(out, _CITY_OUTPUTS, overwrite):
        patch = sample_city(seed, int(size), float(gsd), style, textures)
        im = patch.imaging
        tags = _tags(seed, size, gsd, im.sun_azimuth, im.sun_elevation)
        tags.update(AERIALMTL_SYNTH_KIND="city", AERIALMTL_LEAN_AZIMUTH=f"{im.lean_azimuth:.4f}",
                    AERIALMTL_LEAN_TAN=f"{im.lean_tan:.4f}")
        dtm = np.full(patch.height.shape, CITY_GROUND_M, np.float32)
        paths = _write_rasters(out, _Layers(patch.image, dtm, patch.height, patch.classes), gsd, crs_obj, origin,
                               tags)
    return CityResult(out, paths["ortho.tif"], paths["dsm.tif"], paths["dtm.tif"], paths["ndsm.tif"],
                      paths["labels.tif"], paths["classes.yaml"], im, time.perf_counter() - start)


def _write_reference_buildings(scene: Scene, path: Path, crs: CRS, origin: tuple[float, float]) -> None:
    """The scene's true building footprints (map coordinates) and heights as GeoJSON."""
    with atomic_write(path, keep_suffix=True) as tmp:
        _write_footprints(scene, tmp, crs, origin)


def _write_footprints(scene: Scene, tmp: Path, crs: CRS, origin: tuple[float, float]) -> None:
    writer = FootprintWriter(tmp, crs, REFERENCE_FIELDS, driver="GeoJSON")
    # scene metres (x east, y south of the upper-left corner) → map coordinates
    to_map = [1.0, 0.0, 0.0, -1.0, origin[0], origin[1]]
    geoms = [orient(affine_transform(b.footprint, to_map), 1.0) for b in scene.buildings]
    writer.write(geoms, {ID_FIELD: list(range(1, len(geoms) + 1)),
                         "height_m": [b.height_m for b in scene.buildings],
                         "height_max_m": [b.height_max_m for b in scene.buildings]})
    writer.close()
