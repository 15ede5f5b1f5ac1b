"""COG writer: tiled 512, internal overviews, IFD order, metadata carried over; the validator catches non-COGs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from helpers.rasters import write_raster

from aerialmtl.io.cog import cog_problems, staging_profile, to_cog


def _staging(path: Path, data: np.ndarray, nodata: float) -> Path:
    prof = staging_profile("EPSG:32619", Affine(0.5, 0, 320000.0, 0, -0.5, 4881600.0), data.shape[2],
                           data.shape[1], data.shape[0], data.dtype.name, nodata)
    with rasterio.open(path, "w", **prof) as dst:
        dst.write(data)
        if data.dtype == np.uint8:
            dst.write_colormap(1, {0: (255, 0, 0, 255), 1: (0, 255, 0, 255), 255: (0, 0, 0, 0)})
        dst.set_band_description(1, "layer")
        dst.units = ("m",)
        dst.update_tags(AERIALMTL_CLASS_SCHEME='{"name": "x"}')
    return path


def test_float_cog_is_valid_with_overviews_and_metadata(tmp_path: Path, rng: np.random.Generator) -> None:
    data = rng.normal(10, 3, size=(1, 1100, 1030)).astype(np.float32)
    data[0, :40, :40] = -9999.0
    src = _staging(tmp_path / "stage.tif", data, -9999.0)
    to_cog(src, tmp_path / "out.tif")
    assert cog_problems(tmp_path / "out.tif") == []
    with rasterio.open(tmp_path / "out.tif") as cog:
        assert cog.block_shapes == [(512, 512)]
        assert cog.overviews(1) == [2, 4]
        assert cog.nodata == -9999.0 and cog.descriptions == ("layer",) and cog.units == ("m",)
        assert cog.tags()["AERIALMTL_CLASS_SCHEME"] == '{"name": "x"}'
        assert cog.tags(ns="IMAGE_STRUCTURE")["PREDICTOR"] == "3"
        assert cog.transform == Affine(0.5, 0, 320000.0, 0, -0.5, 4881600.0) and cog.crs.to_epsg() == 32619
        np.testing.assert_array_equal(cog.read(), data)


def test_class_cog_keeps_colour_table_and_uses_mode_overviews(tmp_path: Path) -> None:
    data = np.zeros((1, 1200, 1200), np.uint8)
    data[0, :, 600:] = 1
    data[0, ::4, ::4] = 255  # sparse nodata must not turn whole overview pixels into averages
    src = _staging(tmp_path / "stage.tif", data, 255)
    to_cog(src, tmp_path / "classes.tif", categorical=True)
    assert cog_problems(tmp_path / "classes.tif") == []
    with rasterio.open(tmp_path / "classes.tif") as cog:
        assert cog.colormap(1)[1] == (0, 255, 0, 255)
        assert cog.tags(ns="IMAGE_STRUCTURE")["PREDICTOR"] == "2"
        ovr = cog.read(1, out_shape=(300, 300))
        assert set(np.unique(ovr)) <= {0, 1, 255}  # mode/nearest keeps valid class indices


def test_validator_flags_plain_geotiffs(tmp_path: Path, rng: np.random.Generator) -> None:
    plain = write_raster(tmp_path / "plain.tif", rng.random((1, 1100, 1100)).astype(np.float32))
    problems = cog_problems(plain)
    assert any("LAYOUT=COG" in p for p in problems)
    assert any("tiled" in p for p in problems)
    assert any("overviews" in p for p in problems)
