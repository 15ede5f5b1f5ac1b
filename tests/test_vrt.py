"""Mosaic VRTs (aerialmtl.io.vrt): sources placed by their geotransforms, nodata elsewhere."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from conftest import write_raster

from aerialmtl.errors import InputError
from aerialmtl.io.vrt import mosaic_vrt


def _tile(tmp_path: Path, name: str, col: int, row: int, rng: np.random.Generator, crs: str = "EPSG:2994",
          res: float = 2.0, dtype: str = "float32", nodata: float | None = -9999.0, bands: int = 1) -> Path:
    data = rng.uniform(1, 50, (bands, 8, 12)).astype(dtype)
    t = Affine(res, 0, 1000.0 + col * res, 0, -res, 9000.0 - row * res)
    return write_raster(tmp_path / f"{name}.tif", data, crs=crs, transform=t, nodata=nodata)


def test_sources_land_at_their_offsets_and_gaps_read_nodata(tmp_path: Path, rng: np.random.Generator) -> None:
    a = _tile(tmp_path, "a", 0, 0, rng)
    b = _tile(tmp_path, "b", 20, 5, rng)  # 8 empty columns right of a, 5 rows lower
    out = mosaic_vrt([a, b], tmp_path / "m.vrt")
    with rasterio.open(out) as m, rasterio.open(a) as sa, rasterio.open(b) as sb:
        assert (m.width, m.height) == (32, 13)
        assert m.crs == sa.crs and m.transform == sa.transform and m.nodata == -9999.0
        data = m.read(1)
        np.testing.assert_array_equal(data[0:8, 0:12], sa.read(1))
        np.testing.assert_array_equal(data[5:13, 20:32], sb.read(1))
        assert (data[0:5, 12:32] == -9999.0).all() and (data[8:13, 0:20] == -9999.0).all()
        mask = m.read_masks(1)
        assert mask[0, 0] == 255 and mask[0, 15] == 0


def test_unordered_sources_and_byte_images_with_a_declared_nodata(tmp_path: Path, rng: np.random.Generator) -> None:
    right = _tile(tmp_path, "r", 12, 0, rng, dtype="uint8", nodata=None, bands=3)
    left = _tile(tmp_path, "l", -12, 0, rng, dtype="uint8", nodata=None, bands=3)
    out = mosaic_vrt([right, left], tmp_path / "img.vrt", nodata=0)
    with rasterio.open(out) as m, rasterio.open(left) as sl, rasterio.open(right) as sr:
        assert m.count == 3 and m.dtypes[0] == "uint8" and m.width == 36
        assert m.transform.c == sl.transform.c  # the union starts at the left-most source
        data = m.read()
        np.testing.assert_array_equal(data[:, :, 0:12], sl.read())
        np.testing.assert_array_equal(data[:, :, 24:36], sr.read())
        assert (m.dataset_mask()[:, 12:24] == 0).all()


def test_refuses_sources_on_other_grids(tmp_path: Path, rng: np.random.Generator) -> None:
    a = _tile(tmp_path, "a", 0, 0, rng)
    with pytest.raises(InputError, match="CRS"):
        mosaic_vrt([a, _tile(tmp_path, "b", 20, 0, rng, crs="EPSG:32610")], tmp_path / "m.vrt")
    with pytest.raises(InputError, match="pixel size"):
        mosaic_vrt([a, _tile(tmp_path, "c", 20, 0, rng, res=1.0)], tmp_path / "m.vrt")
    with pytest.raises(InputError, match="bands"):
        mosaic_vrt([a, _tile(tmp_path, "d", 20, 0, rng, bands=2)], tmp_path / "m.vrt")
    shifted = write_raster(tmp_path / "e.tif", np.ones((4, 4), np.float32), crs="EPSG:2994",
                           transform=Affine(2.0, 0, 1001.0, 0, -2.0, 9000.0), nodata=-9999.0)
    with pytest.raises(InputError, match="whole pixels"):
        mosaic_vrt([a, shifted], tmp_path / "m.vrt")
    with pytest.raises(InputError, match="no raster"):
        mosaic_vrt([], tmp_path / "m.vrt")
