"""Layer alignment onto the ortho grid: across CRS and GSD, nodata into the nDSM, non-overlapping layers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from helpers.rasters import write_raster
from rasterio.warp import transform as warp_transform

from aerialmtl.errors import AlignmentError
from aerialmtl.formats.tiles import HEIGHT_NODATA
from aerialmtl.io.align import AlignedRaster, HeightSource, NdsmOptions, reference_grid
from aerialmtl.tiling.splits import SplitSpec
from aerialmtl.tiling.tile import TileOptions, read_manifest, tile_dataset

# ortho near the UTM 31/32 boundary (≈ 5.9° E, 45° N) so a zone-32 DSM is a genuinely different projection
ORTHO_CRS = "EPSG:32631"
ORTHO_T = Affine(0.5, 0, 700000.0, 0, -0.5, 5000000.0)
N = 48  # ortho pixels per side (24 m)


def _ortho(tmp_path: Path, rng: np.random.Generator) -> Path:
    return write_raster(tmp_path / "ortho.tif", rng.integers(1, 255, (3, N, N), dtype=np.uint8), ORTHO_CRS, ORTHO_T)


def _centres(grid) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.mgrid[0:grid.height, 0:grid.width]
    xs, ys = grid.transform @ (cols.ravel() + 0.5, rows.ravel() + 0.5)
    return np.asarray(xs), np.asarray(ys)


def _linear_dsm(
    path: Path, crs: str, res: tuple[float, float], coef: tuple[float, float, float], margin: float
) -> tuple[Path, tuple[float, float]]:
    """A DSM whose value is ``c0 + c1·(x − x0) + c2·(y − y0)`` in its own CRS, covering the ortho plus a margin."""
    left, bottom, right, top = 700000.0, 5000000.0 - N * 0.5, 700000.0 + N * 0.5, 5000000.0
    xs, ys = warp_transform(ORTHO_CRS, crs, [left, right, left, right], [bottom, bottom, top, top])
    x0, x1 = min(xs) - margin, max(xs) + margin
    y0, y1 = min(ys) - margin, max(ys) + margin
    w, h = int(np.ceil((x1 - x0) / res[0])), int(np.ceil((y1 - y0) / res[1]))
    t = Affine(res[0], 0, x0, 0, -res[1], y1)
    rows, cols = np.mgrid[0:h, 0:w]
    cx, cy = t @ (cols + 0.5, rows + 0.5)
    val = coef[0] + coef[1] * (cx - x0) + coef[2] * (cy - y0)
    write_raster(path, val.astype(np.float64), crs, t, nodata=-9999.0)
    return path, (x0, y0)


@pytest.mark.parametrize(
    "crs,res,coef,margin,tol",
    [
        ("EPSG:32632", (1.3, 1.1), (100.0, 1.0, 0.7), 5.0, 0.01),  # other UTM zone, coarser, non-square
        ("EPSG:4326", (1.2e-5, 0.9e-5), (100.0, 1e5, 7e4), 5e-5, 0.01),  # degrees, ≈ 0.95 × 1.0 m
    ],
)
def test_height_aligned_across_crs_and_gsd(tmp_path: Path, rng, crs, res, coef, margin, tol) -> None:
    ortho = _ortho(tmp_path, rng)
    dsm, (x0, y0) = _linear_dsm(tmp_path / "dsm.tif", crs, res, coef, margin)
    grid = reference_grid(ortho)
    with AlignedRaster(dsm, grid, "height", role="DSM") as layer:
        data, valid = layer.read()
    assert valid.all()
    xs, ys = _centres(grid)
    sx, sy = warp_transform(ORTHO_CRS, crs, xs, ys)  # independent: where each ortho pixel centre is in the DSM CRS
    expected = coef[0] + coef[1] * (np.asarray(sx) - x0) + coef[2] * (np.asarray(sy) - y0)
    got = data[0].ravel().astype(np.float64)
    # bilinear is exact on a linear field; a 0.25 m (half-pixel) misplacement would err by > 0.15
    assert np.abs(got - expected).max() < tol
    # a window read equals the same pixels of the full read
    with AlignedRaster(dsm, grid, "height") as layer:
        part, _ = layer.read(rasterio.windows.Window(10, 7, 16, 12))
    assert np.allclose(part[0], data[0][7:19, 10:26])


def test_height_aligned_at_working_gsd(tmp_path: Path, rng) -> None:
    ortho = _ortho(tmp_path, rng)
    dsm, (x0, y0) = _linear_dsm(tmp_path / "dsm.tif", "EPSG:32632", (0.7, 0.7), (50.0, 1.0, -2.0), 5.0)
    grid = reference_grid(ortho, gsd=2.0)
    assert grid.shape == (12, 12) and grid.transform.c == 700000.0 and grid.transform.f == 5000000.0
    with AlignedRaster(dsm, grid, "height") as layer:
        data, valid = layer.read()
    sx, sy = warp_transform(ORTHO_CRS, "EPSG:32632", *_centres(grid))
    expected = 50.0 + 1.0 * (np.asarray(sx) - x0) - 2.0 * (np.asarray(sy) - y0)
    # GDAL widens the bilinear kernel when downsampling 0.7 m → 2 m: a few cm of error on a 2.2 m/m gradient,
    # while a half-pixel (1 m) misplacement would err by > 1
    assert valid.all() and np.abs(data[0].ravel() - expected).max() < 0.15


def test_nodata_and_options_propagate_into_ndsm_patches(tmp_path: Path, rng) -> None:
    ortho = _ortho(tmp_path, rng)
    dtm = np.full((N, N), 200.0, np.float32)
    dsm = dtm + rng.uniform(1, 30, (N, N)).astype(np.float32)
    dsm[5, 6] = -9999.0  # DSM nodata
    dtm[10:12, 20:23] = np.nan  # DTM hole (NaN, no nodata value)
    dsm[30, 30] = 195.0  # below the terrain → clipped to 0
    dsm[40, 8] = 200.0 + 80.0  # above --max-height
    write_raster(tmp_path / "dsm.tif", dsm, ORTHO_CRS, ORTHO_T, nodata=-9999.0)
    write_raster(tmp_path / "dtm.tif", dtm, ORTHO_CRS, ORTHO_T)
    res = tile_dataset(
        ortho, tmp_path / "out", dsm=tmp_path / "dsm.tif", dtm=tmp_path / "dtm.tif", progress=False,
        options=TileOptions(size=N, min_valid=0.0, splits=SplitSpec(ratios=(1, 0, 0)),
                            heights=NdsmOptions(max_height=50.0)),
    )
    (row,) = read_manifest(res.manifest)
    with rasterio.open(res.out_dir / row["height_path"]) as f:
        h = f.read(1)
        assert f.nodata == HEIGHT_NODATA
    invalid = np.zeros((N, N), bool)
    invalid[5, 6] = invalid[10:12, 20:23] = invalid[40, 8] = True
    assert np.array_equal(h == HEIGHT_NODATA, invalid)
    assert h[30, 30] == 0.0
    ok = ~invalid
    ok[30, 30] = False
    assert np.allclose(h[ok], (dsm - dtm)[ok])
    assert float(row["height_max"]) <= 50.0 and float(row["height_min"]) == 0.0

    # without clipping the negative height survives; a coarser DTM spreads its hole bilinearly
    res2 = tile_dataset(
        ortho, tmp_path / "out2", dsm=tmp_path / "dsm.tif", dtm=tmp_path / "dtm.tif", progress=False,
        options=TileOptions(size=N, min_valid=0.0, splits=SplitSpec(ratios=(1, 0, 0)),
                            heights=NdsmOptions(clip_negative=False)),
    )
    with rasterio.open(res2.out_dir / read_manifest(res2.manifest)[0]["height_path"]) as f:
        assert f.read(1)[30, 30] == pytest.approx(-5.0)


def test_coarse_dtm_nodata_cell_invalidates_the_pixels_it_covers(tmp_path: Path, rng) -> None:
    ortho = _ortho(tmp_path, rng)
    dtm = np.full((N // 4, N // 4), 10.0, np.float32)  # 2 m cells
    dtm[3, 5] = -32768.0
    write_raster(tmp_path / "dtm.tif", dtm, ORTHO_CRS, Affine(2.0, 0, 700000.0, 0, -2.0, 5000000.0), nodata=-32768.0)
    write_raster(tmp_path / "dsm.tif", np.full((N, N), 25.0, np.float32), ORTHO_CRS, ORTHO_T)
    grid = reference_grid(ortho)
    with HeightSource(grid, dsm=tmp_path / "dsm.tif", dtm=tmp_path / "dtm.tif") as hs:
        h, valid = hs.read(grid.full_window())
    assert not valid[12:16, 20:24].any()  # the 4×4 ortho pixels inside the nodata cell
    assert np.all(np.isnan(h[~valid]))
    assert np.allclose(h[valid], 15.0) and valid[:8].all()


def test_non_overlapping_layer_names_both_bounds(tmp_path: Path, rng) -> None:
    ortho = _ortho(tmp_path, rng)
    far = write_raster(tmp_path / "ndsm.tif", np.ones((10, 10), np.float32), ORTHO_CRS,
                       Affine(1.0, 0, 600000.0, 0, -1.0, 4000000.0))
    with pytest.raises(AlignmentError) as info:
        tile_dataset(ortho, tmp_path / "out", ndsm=far, progress=False, options=TileOptions(size=16))
    msg = str(info.value)
    assert "ndsm.tif" in msg and "(700000, 4.99998e+06, 700024, 5e+06)" in msg and "(600000, 3.99999e+06" in msg
    assert not (tmp_path / "out").exists()  # nothing written
