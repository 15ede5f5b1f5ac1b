"""Tests of the synthetic city generator (`sample_city`), its relief displacement, styles, textures and stream."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from helpers import pins

from aerialmtl.data.synth import CityStyle, TexturePool, sample_city
from aerialmtl.data.synth.city import render_city
from aerialmtl.data.synth.city_canvas import CityCanvas
from aerialmtl.data.synth.materials import BUILDING
from aerialmtl.data.synth.relief import relief_displacement
from aerialmtl.data.synth.style import Imaging
from aerialmtl.data.synthetic_batches import city_seed, synthetic_scene
from aerialmtl.errors import InputError

BARE, ROAD, TREE, LOWVEG, WATER = 1, 2, 4, 5, 6


@pytest.fixture(scope="module")
def cities():
    return [sample_city(seed, 96, gsd) for seed, gsd in ((0, 0.5), (1, 1.0), (2, 0.3), (3, 0.8))]


def test_shapes_dtypes_units_and_height_ranges(cities) -> None:
    for p in cities:
        assert p.image.shape == (3, 96, 96) and p.image.dtype == np.uint8
        assert p.height.shape == (96, 96) and p.height.dtype == np.float32
        assert p.classes.shape == (96, 96) and p.classes.dtype == np.uint8
        assert set(np.unique(p.classes)) <= {1, 2, 3, 4, 5, 6}, "every pixel carries a class of the scheme"
        h, c = p.height, p.classes
        assert h.min() >= 0
        if (c == BUILDING).any():
            assert 2.0 <= h[c == BUILDING].min() and h[c == BUILDING].max() <= 60.0
        if (c == TREE).any():
            assert 3.0 <= h[c == TREE].min() and h[c == TREE].max() <= 30.0
        for ground in (BARE, ROAD, LOWVEG):
            assert h[c == ground].max(initial=0) <= 1.8  # cars are the tallest thing labelled ground
        assert np.all(h[c == WATER] == 0)


def test_cities_hold_tall_buildings_and_ground_like_roofs() -> None:
    """Over a few scenes: towers over 40 m, and flat roofs coloured like the ground around them."""
    tall, like = 0, 0
    for seed in range(6):
        p = sample_city(seed, 256, 1.0, style=CityStyle.plain().with_lean(0.0))
        bld = p.classes == BUILDING
        tall += int((p.height[bld] > 40).sum())
        if bld.sum() > 100 and (p.classes == ROAD).sum() > 100:
            img = p.image.astype(np.float32).mean(axis=0)
            road = np.median(img[p.classes == ROAD])
            like += int((np.abs(img[bld] - road) < 15).mean() > 0.1)
    assert tall > 0 and like > 0


def test_same_seed_same_patch_and_style_or_textures_leave_labels_alone() -> None:
    a, b = sample_city(11, 64, 0.5), sample_city(11, 64, 0.5)
    assert a.image.tobytes() == b.image.tobytes() and a.height.tobytes() == b.height.tobytes()
    plain = sample_city(11, 64, 0.5, style=CityStyle.plain().with_lean(0.5))
    pool = TexturePool(np.full((2, 3, 16, 16), 200, np.uint8), gsd=0.5, share=1.0)
    textured = sample_city(11, 64, 0.5, textures=pool)
    for other in (plain, textured):
        assert np.array_equal(a.height, other.height) and np.array_equal(a.classes, other.classes)
        assert not np.array_equal(a.image, other.image)
    assert not np.array_equal(a.height, sample_city(12, 64, 0.5).height)


def _tower_canvas(size: int, gsd: float, height: float) -> CityCanvas:
    cv = CityCanvas(size, gsd, 0.0)
    cv.tint[:] = 100.0
    cv.labels[:] = ROAD
    r0, r1 = size // 2 - 4, size // 2 + 4
    cv.ndsm[r0:r1, r0:r1] = height
    cv.labels[r0:r1, r0:r1] = BUILDING
    cv.tint[:, r0:r1, r0:r1] = np.array([250.0, 20.0, 20.0])[:, None, None]  # a red roof
    cv.facade[:, r0:r1, r0:r1] = 60.0
    return cv


@pytest.mark.parametrize("lean_azimuth", [0.0, 90.0, 200.0, 315.0])
@pytest.mark.parametrize("lean_tan", [0.2, 0.5])
def test_relief_moves_the_roof_away_from_nadir_by_height_times_tan(lean_azimuth: float, lean_tan: float) -> None:
    size, gsd, height = 160, 0.5, 40.0
    cv = _tower_canvas(size, gsd, height)
    relief = relief_displacement(cv.ndsm, gsd, lean_azimuth, lean_tan)
    roof = (cv.labels[relief.src_row, relief.src_col] == BUILDING) & ~relief.wall
    rows, cols = np.nonzero(roof)
    shift = np.array([rows.mean() - (size / 2 - 0.5), cols.mean() - (size / 2 - 0.5)]) * gsd  # metres
    az = math.radians(lean_azimuth)
    expected = height * lean_tan * np.array([-math.cos(az), math.sin(az)])
    assert np.allclose(shift, expected, atol=1.5 * gsd), (shift, expected)
    assert roof.sum() == 64, "the roof keeps its size"
    walls = relief.wall & (cv.labels[relief.src_row, relief.src_col] == BUILDING)
    assert walls.sum() > 0 and relief.z[walls].max() <= height
    assert np.all(cv.labels[relief.src_row, relief.src_col][~walls & ~roof] == ROAD)


def test_true_ortho_has_no_lean() -> None:
    cv = _tower_canvas(64, 0.5, 30.0)
    relief = relief_displacement(cv.ndsm, 0.5, 45.0, 0.0)
    assert not relief.wall.any()
    assert np.array_equal(relief.src_row, np.indices((64, 64))[0])


@pytest.mark.parametrize("sun_azimuth", [0.0, 135.0, 250.0])
def test_shadows_fall_on_the_side_away_from_the_sun(sun_azimuth: float) -> None:
    size, gsd = 160, 0.5
    cv = _tower_canvas(size, gsd, 20.0)
    img = render_city(cv, Imaging(sun_azimuth, 40.0, 0.0, 0.0), np.random.default_rng(0)).mean(axis=0)
    az = math.radians(sun_azimuth)
    towards_sun = np.array([-math.cos(az), math.sin(az)])  # (row, col)
    c = size // 2
    down = np.round(c - 0.5 - 12 * towards_sun).astype(int)  # 6 m from the tower's centre, away from the sun
    up = np.round(c - 0.5 + 12 * towards_sun).astype(int)  # and towards it
    assert img[down[0], down[1]] < 0.7 * img[up[0], up[1]]


def test_texture_pool_cuts_only_near_ground_patches() -> None:
    rng = np.random.default_rng(0)
    image = np.zeros((3, 128, 128), np.uint8)
    image[1] = rng.integers(100, 200, (128, 128))  # green ground
    ndsm = np.zeros((128, 128), np.float32)
    ndsm[30:70, 40:90] = 12.0  # a building, painted red
    image[0][ndsm > 0], image[1][ndsm > 0] = 255, 0
    ndsm[100:110, 5:15] = np.nan  # unknown heights are never used
    image[2][100:110, 5:15] = 255
    pool = TexturePool.from_arrays(image, ndsm, gsd=0.5, patch_px=16)
    assert pool.patches.shape[1:] == (3, 16, 16) and len(pool.patches) > 10
    assert pool.patches[:, 0].max() == 0 and pool.patches[:, 2].max() == 0, "a patch touched a roof or a hole"
    with pytest.raises(InputError, match="patch_px"):
        TexturePool.from_arrays(image, np.full((128, 128), 5.0, np.float32), gsd=0.5)


def test_a_stream_scene_is_the_city_of_its_seed_in_the_synthetic_scheme() -> None:
    """Scene ``index`` of stream ``seed`` is the city of ``city_seed(seed, index)``, its classes the synthetic
    scheme's indices (the city's codes 1..6 → 0..5), whatever else was drawn before it."""
    seeds = {city_seed(3, i) for i in range(50)} | {city_seed(4, i) for i in range(50)}
    assert len(seeds) == 100 and all(0 <= s < 2**63 for s in seeds)  # distinct, 63-bit
    scene = synthetic_scene(3, 2, 48, 0.5)
    raw = sample_city(city_seed(3, 2), 48, 0.5)
    assert scene.image.shape == (3, 48, 48) and scene.image.dtype == np.uint8 and scene.gsd == 0.5
    np.testing.assert_array_equal(scene.image, raw.image)
    np.testing.assert_array_equal(scene.height, raw.height.astype(np.float32))
    np.testing.assert_array_equal(scene.classes, raw.classes.astype(np.int64) - 1)
    np.testing.assert_array_equal(synthetic_scene(3, 2, 48, 0.5).image, scene.image)  # a pure function


def test_cli_writes_a_city(tmp_path) -> None:
    import rasterio
    from click.testing import CliRunner

    from aerialmtl.cli import cli

    out = tmp_path / "city"
    res = CliRunner().invoke(cli, ["synth", str(out), "--kind", "city", "--size", "64", "--gsd", "1", "--lean",
                                   "0.3", "0.3", "--plain"])
    assert res.exit_code == 0, res.output
    with rasterio.open(out / "ortho.tif") as src:
        assert src.count == 3 and src.res == (1.0, 1.0) and src.tags()["AERIALMTL_LEAN_TAN"] == "0.3000"
    with rasterio.open(out / "ndsm.tif") as src, rasterio.open(out / "labels.tif") as lab:
        patch = sample_city(0, 64, 1.0)
        assert np.allclose(src.read(1), patch.height, atol=1e-4) and np.array_equal(lab.read(1), patch.classes)
    res = CliRunner().invoke(cli, ["synth", str(tmp_path / "t"), "--plain", "--size", "64"])
    assert res.exit_code == 2 and "--kind" in res.output


def test_ground_roofs_sets_the_share_of_roofs_that_look_like_the_ground() -> None:
    from aerialmtl.data.synth.city import build_city
    from aerialmtl.data.synth.city_canvas import ASPHALT, CONCRETE, GRASS, GRAVEL, GREEN_ROOF, SOIL

    def share(ground_roofs: float) -> float:
        roof = ground = 0
        for seed in range(4):
            layout, textures = np.random.default_rng([seed, 1]), np.random.default_rng([seed, 2])
            cv, _ = build_city(192, 0.5, layout, textures, None, ground_roofs)
            building = cv.labels == BUILDING
            roof += int(building.sum())
            ground += int(np.isin(cv.material[building], [ASPHALT, CONCRETE, GRAVEL, SOIL, GRASS, GREEN_ROOF]).sum())
        return ground / roof

    assert share(0.0) == 0.0 < share(0.3) < share(0.65) < share(1.0)
    a, b = sample_city(5, 96, 0.5), sample_city(5, 96, 0.5, CityStyle(ground_roofs=0.65))
    assert np.array_equal(a.image, b.image) and np.array_equal(a.height, b.height)  # the default is today's generator
    with pytest.raises(InputError, match="ground_roofs"):
        CityStyle(ground_roofs=1.2)


def test_cli_city_takes_textures_from_an_orthophoto_and_ndsm(tmp_path) -> None:
    """``--textures ORTHO NDSM`` cuts the pool from those rasters (read through the aligner) and lays it on the
    city's surfaces: the image changes, the heights and labels do not."""
    import rasterio
    from click.testing import CliRunner

    from aerialmtl.cli import cli
    from aerialmtl.data.synth import synthesize

    town = synthesize(tmp_path / "town", size=96, seed=2, gsd=0.5)
    args = ["synth", "--kind", "city", "--size", "64", "--gsd", "0.5", "--plain"]
    res = CliRunner().invoke(cli, [*args, str(tmp_path / "plain")])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(cli, [*args, str(tmp_path / "tex"), "--textures", str(town.ortho), str(town.ndsm)])
    assert res.exit_code == 0, res.output
    for name, same in (("ortho.tif", False), ("ndsm.tif", True), ("labels.tif", True)):
        with rasterio.open(tmp_path / "plain" / name) as a, rasterio.open(tmp_path / "tex" / name) as b:
            assert np.array_equal(a.read(), b.read()) == same, name


def test_city_output_is_pinned() -> None:
    """The city patches are the synthetic pretraining's (the shipped start was made from them): the same seeds make
    the same patches, compared with the pin (``tests/data/city_pin.npz``) within the town pin's tolerances, which
    hold on every CPU kind. If this fails, the city changed: say so on the start's card (it was made by the
    former city) and remake the pin (``python -m tests.helpers.pins``), or undo the change."""
    assert pins.city_differences(pins.make_cities(), pins.load_city_pin()) == []


@pytest.mark.parametrize("change", ["sky light", "street width", "one label", "5 cm on ten pixels"])
def test_city_pin_catches_a_changed_generator(monkeypatch: pytest.MonkeyPatch, change: str) -> None:
    """A renderer default moved a little, the narrowest street a metre wider, one pixel relabelled or ten pixels 5 cm
    higher: each is caught by the city pin's tolerances."""
    from aerialmtl.data.synth import city

    pin = pins.load_city_pin()
    if change == "sky light":
        monkeypatch.setattr(city, "SKY", city.Sky(city.AMBIENT + 0.01, (0.92, 0.98, 1.10)))
    elif change == "street width":
        monkeypatch.setattr(city, "CITY_STREETS", dataclasses.replace(city.CITY_STREETS, width=(8, 22)))
    if change in ("sky light", "street width"):
        got = pins.make_cities()
    else:
        got = {name: arr.copy() for name, arr in pin.items()}
        seed = pins.CITY_SEEDS[0]
        if change == "one label":
            got[f"classes_{seed}"][5, 7] = got[f"classes_{seed}"][5, 7] % 6 + 1
        else:
            got[f"height_{seed}"][60, 60:70] += np.float32(0.05)
    assert pins.city_differences(got, pin) != []
