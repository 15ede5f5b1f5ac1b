"""Every distance in metres: feet orthophotos, feet heights, geographic CRSs (issue: feet read as metres)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
import yaml
from affine import Affine
from helpers.rasters import write_raster
from rasterio.crs import CRS
from rasterio.warp import transform_bounds

from aerialmtl.classes import ClassScheme
from aerialmtl.errors import AlignmentError, InputError
from aerialmtl.evaluation.evaluate import EvaluateOptions, evaluate_prediction
from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.inference.predict import predict_raster
from aerialmtl.io.align import AlignedRaster, HeightSource, reference_grid
from aerialmtl.io.units import Z_UNITS, metres_per_unit, utm_epsg, vertical_unit
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net
from aerialmtl.tiling.splits import SplitSpec
from aerialmtl.tiling.tile import TileOptions, read_manifest, tile_dataset

FT = 0.3048
US_FT = 1200 / 3937
# Oregon GIC Lambert (international feet), as the Autzen orthophoto; a UTM 10N grid for metre layers
FEET_CRS = "EPSG:2994"
X0_FT, Y0_FT = 4_245_000.0, 880_000.0  # near Eugene, Oregon (feet)


def _feet_ortho(tmp_path: Path, rng: np.random.Generator, n: int = 128, res_ft: float = 1.0) -> Path:
    img = rng.integers(1, 255, (3, n, n), dtype=np.uint8)
    return write_raster(tmp_path / "ortho_ft.tif", img, FEET_CRS, Affine(res_ft, 0, X0_FT, 0, -res_ft, Y0_FT))


def _utm_height(tmp_path: Path, ortho: Path, name: str, value_m: float, res_m: float = 1.0,
                crs: str = "EPSG:32610", scale: float = 1.0, **extra: object) -> Path:
    """A constant height raster in ``crs`` covering the ortho plus a margin; values ``value_m / scale``."""
    with rasterio.open(ortho) as src:
        left, bottom, right, top = transform_bounds(src.crs, crs, *src.bounds)
    m = 5 * res_m
    w, h = int(np.ceil((right - left + 2 * m) / res_m)), int(np.ceil((top - bottom + 2 * m) / res_m))
    data = np.full((h, w), value_m / scale, np.float32)
    return write_raster(tmp_path / name, data, crs, Affine(res_m, 0, left - m, 0, -res_m, top + m), nodata=-9999.0,
                        **extra)


# ---- horizontal ------------------------------------------------------------------------------
def test_linear_unit_factors_come_from_the_crs() -> None:
    assert metres_per_unit(CRS.from_epsg(32610)) == 1.0
    assert metres_per_unit(CRS.from_epsg(2994)) == pytest.approx(FT)  # international foot
    assert metres_per_unit(CRS.from_epsg(2227)) == pytest.approx(US_FT)  # California zone 3, US survey foot
    assert utm_epsg(-123.1, 44.05) == 32610 and utm_epsg(151.2, -33.9) == 32756


def test_feet_orthophoto_grid_is_in_metres(tmp_path: Path, rng: np.random.Generator) -> None:
    ortho = _feet_ortho(tmp_path, rng)
    grid = reference_grid(ortho)
    assert grid.res == (1.0, 1.0) and grid.unit_m == pytest.approx(FT)
    assert grid.gsd == pytest.approx(FT)  # 1 ft pixels are 0.3048 m, not 1 m
    half = reference_grid(ortho, gsd=0.6096)  # 2 ft in metres
    assert half.res == pytest.approx((2.0, 2.0)) and (half.width, half.height) == (64, 64)
    assert half.gsd == pytest.approx(0.6096)


def test_geographic_orthophoto_is_refused_with_the_gdalwarp_fix(tmp_path: Path, rng: np.random.Generator) -> None:
    ortho = write_raster(tmp_path / "ll.tif", rng.integers(1, 255, (3, 16, 16), dtype=np.uint8), "EPSG:4326",
                         Affine(1e-5, 0, -123.1, 0, -1e-5, 44.05))
    with pytest.raises(AlignmentError, match=r"geographic CRS.*gdalwarp -t_srs EPSG:32610"):
        reference_grid(ortho)


def test_tile_feet_ortho_with_metre_utm_dsm_dtm(tmp_path: Path, rng: np.random.Generator) -> None:
    """The Autzen case: splits, gsd and heights in metres although the ortho's CRS is in feet."""
    ortho = _feet_ortho(tmp_path, rng, n=200)
    dsm = _utm_height(tmp_path, ortho, "dsm.tif", 112.5)
    dtm = _utm_height(tmp_path, ortho, "dtm.tif", 100.0)
    # 100 m blocks vs 32-px (9.75 m) patches: blocks snap to 10 strides (97.5 m), patches never straddle
    res = tile_dataset(
        ortho, tmp_path / "tiles", dsm=dsm, dtm=dtm, progress=False,
        options=TileOptions(size=32, min_valid=0.5,
                            splits=SplitSpec(block_size=30.0, ratios=(0.5, 0.25, 0.25), seed=1)),
    )
    meta = yaml.safe_load((tmp_path / "tiles" / "dataset.yaml").read_text())
    assert meta["gsd"] == pytest.approx(FT)
    assert meta["splits"]["block_size_used_m"] == pytest.approx(3 * 32 * FT)  # 30 m → 3 patch strides
    assert res.block_patches == 3
    assert meta["height"]["units"]["DSM"]["unit"] == "m"
    rows = read_manifest(res.manifest)
    assert {r["split"] for r in rows} == {"train", "val", "test"}
    interior = [r for r in rows if int(r["col_off"]) % 32 == 0 and int(r["row_off"]) % 32 == 0]
    assert len(interior) == 36  # every patch of the 6×6 stride grid is kept: none straddles two blocks
    for r in rows:
        assert float(r["height_mean"]) == pytest.approx(12.5, abs=1e-3)  # metres above ground


@pytest.mark.parametrize("how", ["band_unit", "compound_crs", "z_unit"])
def test_feet_heights_are_converted_to_metres(tmp_path: Path, rng: np.random.Generator, how: str) -> None:
    ortho = _feet_ortho(tmp_path, rng, n=64)
    grid = reference_grid(ortho)
    if how == "band_unit":  # GDAL's unit type, e.g. from the GeoTIFF VerticalUnitsGeoKey
        dsm = _utm_height(tmp_path, ortho, "dsm.tif", 30.0, scale=FT)
        with rasterio.open(dsm, "r+") as dst:
            dst.units = ("ft",)
        expected_unit, z = "ft", None
    elif how == "compound_crs":  # Oregon Lambert (ft) + NAVD88 height (US survey feet)
        dsm = _feet_dsm_compound(tmp_path, ortho, 30.0)
        expected_unit, z = "us-ft", None
    else:  # nothing stated: the user says feet
        dsm = _utm_height(tmp_path, ortho, "dsm.tif", 30.0, scale=FT)
        expected_unit, z = "ft", "ft"
    with AlignedRaster(dsm, grid, "height", bands=[1], role="DSM", z_unit=z) as layer:
        data, valid = layer.read()
        assert layer.z is not None and layer.z.name == expected_unit
    assert valid.all() and np.allclose(data[0], 30.0, atol=1e-3)  # metres


def _feet_dsm_compound(tmp_path: Path, ortho: Path, value_m: float) -> Path:
    with rasterio.open(ortho) as src:
        profile = dict(driver="GTiff", width=src.width, height=src.height, count=1, dtype="float32",
                       crs=CRS.from_user_input("EPSG:2994+6360"), transform=src.transform, nodata=-9999.0)
    path = tmp_path / "dsm_compound.tif"
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(np.full((1, profile["height"], profile["width"]), value_m / US_FT, np.float32))
    return path


def test_a_stated_unit_that_contradicts_z_unit_is_an_error(tmp_path: Path, rng: np.random.Generator) -> None:
    ortho = _feet_ortho(tmp_path, rng, n=32)
    dsm = _feet_dsm_compound(tmp_path, ortho, 10.0)
    with pytest.raises(InputError, match=r"DSM '.*' states its heights are in us-ft.*z_unit 'm'"):
        AlignedRaster(dsm, reference_grid(ortho), "height", bands=[1], role="DSM", z_unit="m")
    with pytest.raises(InputError, match="not a known height unit"):
        vertical_unit(None, None, "yards", "DSM", "x.tif")
    assert vertical_unit(None, None, None, "DSM", "x.tif").factor == 1.0  # nothing stated: metres
    assert Z_UNITS["us-ft"] == pytest.approx(0.3048006096)


def test_mixed_units_dsm_feet_dtm_metres(tmp_path: Path, rng: np.random.Generator) -> None:
    ortho = _feet_ortho(tmp_path, rng, n=64)
    dsm = _feet_dsm_compound(tmp_path, ortho, 57.0)
    dtm = _utm_height(tmp_path, ortho, "dtm.tif", 50.0)
    with HeightSource(reference_grid(ortho), dsm=dsm, dtm=dtm) as hs:
        h, valid = hs.read(reference_grid(ortho).full_window())
        units = hs.units()
    assert units["DSM"]["unit"] == "us-ft" and units["DTM"]["unit"] == "m"
    assert np.allclose(h[valid], 7.0, atol=1e-3) and valid.mean() > 0.9


# ---- predict / evaluate ------------------------------------------------------------------------
def _tiny_model(gsd: float) -> tuple[D3Net, ModelMeta]:
    torch.manual_seed(0)
    scheme = ClassScheme.load("synthetic")
    scheme = ClassScheme(scheme.name, scheme.classes[:3])
    cfg = ModelConfig(num_classes=3, growth_rate=4, block_config=(1, 1, 1, 1), num_init_features=8, bn_size=2)
    meta = ModelMeta(cfg, scheme, (1, 2, 3), (120.0, 110.0, 100.0), (40.0, 40.0, 40.0), gsd, ("r", "g", "b"))
    return D3Net(cfg).eval(), meta


def test_predict_on_feet_ortho_resamples_by_the_metre_ratio(tmp_path: Path, rng: np.random.Generator) -> None:
    ortho = _feet_ortho(tmp_path, rng, n=96)
    same = predict_raster(ortho, _tiny_model(FT), tmp_path / "same", mc=1, window=64, overlap=16, progress=False)
    assert (same.grid.width, same.grid.height) == (96, 96)  # trained at 0.3048 m: 1 ft pixels are the same GSD
    info = json.loads(same.files["prediction"].read_text())
    assert info["grid"]["gsd"] == pytest.approx(FT)
    with pytest.warns(UserWarning, match=r"GSD of 0\.3048 m but the model was trained at 0\.25 m"):
        res = predict_raster(ortho, _tiny_model(0.25), tmp_path / "p", mc=1, window=64, overlap=16, progress=False)
    assert res.grid.width == 118  # 96 ft = 29.26 m at 0.25 m: ×1.22, not ×4
    assert res.grid.gsd == pytest.approx(0.25)
    with rasterio.open(res.files["height"]) as out:
        assert out.res == pytest.approx((0.25 / FT, 0.25 / FT))  # written in the ortho's CRS units (feet)


def test_evaluate_with_feet_dsm_dtm_reference(tmp_path: Path, rng: np.random.Generator) -> None:
    ortho = _feet_ortho(tmp_path, rng, n=64)
    pred = predict_raster(ortho, _tiny_model(FT), tmp_path / "p", mc=1, window=64, overlap=16, progress=False)
    with rasterio.open(pred.files["height"]) as src:
        predicted = src.read(1, masked=True)
    dsm = _utm_height(tmp_path, ortho, "dsm.tif", 20.0 + 3.0, scale=FT)  # feet values, unit not stated
    dtm = _utm_height(tmp_path, ortho, "dtm.tif", 20.0, scale=FT)
    report = evaluate_prediction(
        pred.out_dir, dsm_ref=dsm, dtm_ref=dtm, out=None, options=EvaluateOptions(z_unit="ft", plots=False),
    )
    assert report["height"]["mae"] == pytest.approx(float(np.abs(predicted - 3.0).mean()), rel=1e-3)
    assert report["references"]["height_units"]["DSM"]["unit"] == "ft"
