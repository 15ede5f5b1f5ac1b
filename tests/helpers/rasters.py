"""Tiny georeferenced rasters and prediction folders written into a test's ``tmp_path``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
from affine import Affine

from aerialmtl.classes import ClassScheme
from aerialmtl.io.align import Grid


def write_raster(
    path: Path,
    data: np.ndarray,
    crs: str = "EPSG:32631",
    transform: Affine | None = None,
    nodata: float | None = None,
    **extra: object,
) -> Path:
    """Write ``data`` (bands, H, W) or (H, W) as a GeoTIFF; default grid: 0.5 m pixels at (500000, 5000000)."""
    if data.ndim == 2:
        data = data[None]
    transform = transform or Affine(0.5, 0, 500000.0, 0, -0.5, 5000000.0)
    profile = dict(driver="GTiff", width=data.shape[2], height=data.shape[1], count=data.shape[0],
                   dtype=data.dtype, crs=crs, transform=transform, nodata=nodata, **extra)
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data)
    return path


def write_prediction_layers(
    folder: Path,
    classes: np.ndarray,
    height: np.ndarray,
    height_std: np.ndarray | None = None,
    entropy: np.ndarray | None = None,
    crs: str = "EPSG:32631",
    transform: Affine | None = None,
    scheme: str | None = "synthetic",
) -> Path:
    """A prediction folder (aerialmtl.formats.prediction) from (H, W) arrays: ``classes.tif`` (uint8, nodata 255,
    tagged with the built-in class ``scheme`` unless ``None``), ``height.tif`` and optional ``height_std.tif`` /
    ``class_entropy.tif`` (float32, nodata -9999); default grid as :func:`write_raster`."""
    import json

    from aerialmtl.classes import ClassScheme
    from aerialmtl.formats.prediction import (
        CLASS_ENTROPY,
        CLASS_NODATA,
        CLASS_SCHEME_TAG,
        CLASSES,
        FLOAT_NODATA,
        HEIGHT,
        HEIGHT_STD,
        layer_filename,
    )

    folder.mkdir(parents=True, exist_ok=True)
    path = write_raster(folder / layer_filename(CLASSES), classes.astype(np.uint8), crs, transform, CLASS_NODATA)
    if scheme is not None:
        with rasterio.open(path, "r+") as dst:
            dst.update_tags(**{CLASS_SCHEME_TAG: json.dumps(ClassScheme.load(scheme).to_dict())})
    for name, data in ((HEIGHT, height), (HEIGHT_STD, height_std), (CLASS_ENTROPY, entropy)):
        if data is not None:
            write_raster(folder / layer_filename(name), data.astype(np.float32), crs, transform, FLOAT_NODATA)
    return folder


def write_prediction_folder(folder: Path, rng: np.random.Generator, size: int = 64) -> Path:
    """A tiny prediction folder with every uncertainty layer on 0.5 m pixels (random values, nodata in the
    upper-left 4×4 corner), plus ``ortho.tif`` beside it at twice the resolution over the same footprint."""
    from aerialmtl.formats.prediction import CLASS_MUTUAL_INFO, CLASS_NODATA, FLOAT_NODATA, layer_filename

    scheme = ClassScheme.load("synthetic")
    height = rng.uniform(0, 20, (size, size)).astype(np.float32)
    std, entropy, mutual_info = (rng.uniform(0, hi, (size, size)).astype(np.float32) for hi in (2.0, 1.0, 1.0))
    cls = rng.integers(0, scheme.num_classes, (size, size)).astype(np.uint8)
    for layer in (height, std, entropy, mutual_info):
        layer[:4, :4] = FLOAT_NODATA
    cls[:4, :4] = CLASS_NODATA
    write_prediction_layers(folder, cls, height, std, entropy)
    write_raster(folder / layer_filename(CLASS_MUTUAL_INFO), mutual_info, nodata=FLOAT_NODATA)
    write_raster(folder.parent / "ortho.tif", rng.integers(0, 255, (3, 2 * size, 2 * size)).astype(np.uint8),
                 transform=Affine(0.25, 0, 500000.0, 0, -0.25, 5000000.0))
    return folder


def dated_mosaic(folder: Path, parts: list[tuple[str, str | None, Affine]], crs: str = "EPSG:32631"
                 ) -> tuple[Path, Grid]:
    """A VRT mosaic ``folder/mosaic.vrt`` of uniform 64 × 64 RGB orthophotos, one per ``(name, TIFF DateTime or
    None, transform)``; returns ``(vrt path, its Grid)``."""
    from aerialmtl.io.vrt import mosaic_vrt

    paths = []
    for name, stamp, transform in parts:
        path = write_raster(folder / name, np.full((3, 64, 64), 90, np.uint8), crs=crs, transform=transform)
        if stamp:
            with rasterio.open(path, "r+") as dst:
                dst.update_tags(TIFFTAG_DATETIME=stamp)
        paths.append(str(path))
    vrt = folder / "mosaic.vrt"
    mosaic_vrt(vrt, paths)
    with rasterio.open(vrt) as src:
        return vrt, Grid(src.crs, src.transform, src.width, src.height)
