"""`train`'s sun: fitted on the training split of a tile folder (orthophoto and reference heights), stored with the
area's shadow classifier and footprint in the checkpoint, or stored as unclear (and predict then writes no shadow
layers) where the area shows no sun."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio

from aerialmtl.data.synth import synthesize
from aerialmtl.sun.solar_position import grid_convergence_deg
from aerialmtl.tiling.tile import TileOptions, tile_dataset
from aerialmtl.training.sun import fit_training_sun, training_area


def _tiles(tmp_path: Path, flat: bool = False) -> tuple[Path, float, float]:
    res = synthesize(tmp_path / "town", size=384, seed=11, gsd=0.5)
    ndsm = res.ndsm
    if flat:  # an overcast day: no cast shadows in the image, and nothing the heights could explain
        with rasterio.open(res.ortho) as src:
            profile, rgb = src.profile, src.read()
        overcast = np.random.default_rng(0).integers(100, 160, size=rgb.shape).astype(np.uint8)
        with rasterio.open(res.ortho, "w", **profile) as dst:
            dst.write(overcast)
    out = tmp_path / "tiles"
    tile_dataset(res.ortho, out, ndsm=ndsm, options=TileOptions(size=64, stride=64), progress=False)
    return out, res.sun_azimuth % 360.0, res.sun_elevation


def test_the_training_sun_is_the_scene_s_within_3_degrees_and_is_stored_true_north(tmp_path: Path) -> None:
    tiles, azimuth, elevation = _tiles(tmp_path)
    area = training_area(tiles)
    assert len(area.rgb) == 1 and area.rgb[0].shape[0] == 3  # the train patches pieced into one mosaic
    sun = fit_training_sun(tiles)
    assert sun.clear and sun.shadow_model is not None and "sun fitted" in sun.reason
    assert sun.grid_azimuth_deg is not None and sun.azimuth_deg is not None and sun.elevation_deg is not None
    assert abs((sun.grid_azimuth_deg - azimuth + 180.0) % 360.0 - 180.0) <= 3.0
    assert abs(sun.elevation_deg - elevation) <= 3.0
    b = sun.bounds
    assert b is not None
    convergence = grid_convergence_deg(sun.crs, (b[0] + b[2]) / 2, (b[1] + b[3]) / 2)
    assert sun.azimuth_deg == pytest.approx((sun.grid_azimuth_deg - convergence) % 360.0, abs=1e-3)


def test_an_area_without_shadows_stores_no_sun_and_says_why(tmp_path: Path) -> None:
    tiles, _, _ = _tiles(tmp_path, flat=True)
    sun = fit_training_sun(tiles)
    assert not sun.clear and sun.azimuth_deg is None and sun.shadow_model is None
    assert sun.reason.startswith("no sun fitted")
