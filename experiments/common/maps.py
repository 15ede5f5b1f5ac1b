"""Prediction folders on the survey: its reference heights on a map's grid, maps read and written like a
prediction's layers, the constant maps that are the studies' baselines.

Shared by the studies that read what :mod:`experiments.real_data.run` left in ``OUT/runs/<run>/`` (no study
imports another study's ``run.py``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
from scipy import ndimage

from aerialmtl.formats.prediction import FLOAT_NODATA, HEIGHT, layer_filename
from aerialmtl.io.align import HeightSource, grid_of, reference_grid
from aerialmtl.io.vector import load_geometries
from experiments.common.autzen import DATA, DSM, DTM

Arrays = tuple[np.ndarray, np.ndarray, np.ndarray]


def reference_on(grid_file: Path) -> np.ndarray:
    """The reference nDSM (metres) on ``grid_file``'s grid as ``aerialmtl evaluate`` reads it
    (:class:`~aerialmtl.io.align.HeightSource`: DSM − DTM, bilinear, negatives clipped to 0); NaN where invalid."""
    with rasterio.open(grid_file) as src:
        grid = grid_of(src)
    with HeightSource(grid, dsm=DATA / DSM, dtm=DATA / DTM) as ref:
        height, _ = ref.read(grid.full_window())
    return height.astype(np.float64)


def load(folder: Path) -> Arrays:
    """``(height, height_std, reference)`` of a prediction folder, float64, NaN where nodata."""
    out = []
    for name in ("height.tif", "height_std.tif"):
        with rasterio.open(folder / name) as s:
            a = s.read(1).astype(np.float64)
            a[a == s.nodata] = np.nan
            out.append(a)
    return out[0], out[1], reference_on(folder / "height.tif")


def neighbourhood(h: np.ndarray, r: int) -> np.ndarray:
    """Highest predicted height within ``r`` pixels (a (2r+1)² square) minus the pixel's own, ≥ 0."""
    hh = np.where(np.isfinite(h), h, -1e9)
    return np.maximum(ndimage.maximum_filter(hh, size=2 * r + 1) - hh, 0.0)


def write_like(src_path: Path, data: np.ndarray, dst_path: Path) -> None:
    """``data`` (one band, float32) as a deflated, tiled GeoTIFF ``dst_path`` with ``src_path``'s grid and nodata."""
    with rasterio.open(src_path) as src:
        profile = src.profile.copy()
    profile.update(driver="GTiff", compress="deflate", predictor=3, tiled=True, blockxsize=512, blockysize=512)
    with rasterio.open(dst_path, "w", **profile) as dst:
        dst.write(data.astype(np.float32), 1)


def train_mean(pred_height: Path, data: Path, train_aoi: Path) -> float:
    """Mean reference nDSM (DSM − DTM, negatives → 0, metres) over the train block, on the prediction grid."""
    from rasterio.features import geometry_mask

    grid = reference_grid(pred_height)
    geoms = [g for g, _ in load_geometries(train_aoi, grid.crs, "train AOI")]
    total, n = 0.0, 0
    with HeightSource(grid, dsm=data / DSM, dtm=data / DTM) as hs:
        rows = max(1, (1 << 20) // grid.width)
        for r in range(0, grid.height, rows):
            win = rasterio.windows.Window(0, r, grid.width, min(rows, grid.height - r))
            h, valid = hs.read(win)
            inside = geometry_mask(geoms, out_shape=h.shape, transform=grid.window_transform(win), invert=True)
            sel = valid & inside
            total += float(h[sel].sum(dtype=np.float64))
            n += int(sel.sum())
    return total / n


def constant_prediction(pred_dir: Path, value: float, out_dir: Path) -> Path:
    """A prediction folder holding only ``height.tif`` = ``value`` wherever ``pred_dir``'s height is valid."""
    out_dir.mkdir(parents=True, exist_ok=True)
    src_path = pred_dir / layer_filename(HEIGHT)
    with rasterio.open(src_path) as src:
        profile = src.profile.copy()
        data = src.read(1)
    profile.update(driver="GTiff", compress="deflate", predictor=3, tiled=True, blockxsize=512, blockysize=512)
    for key in ("copy_src_overviews",):
        profile.pop(key, None)
    out = np.where(data == FLOAT_NODATA, FLOAT_NODATA, np.float32(value)).astype(np.float32)
    with rasterio.open(out_dir / layer_filename(HEIGHT), "w", **profile) as dst:
        dst.write(out, 1)
    return out_dir
