"""Tiling: window grids, spatial splits, the tile folder (manifest ↔ files), vector labels, the CLI."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
import yaml
from affine import Affine
from click.testing import CliRunner
from helpers.rasters import write_raster
from rasterio.warp import transform as warp_transform
from rasterio.windows import Window
from rasterio.windows import transform as window_transform

from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.cli import cli
from aerialmtl.errors import InputError, LabelError, OutputExistsError
from aerialmtl.formats.tiles import HEIGHT_NODATA
from aerialmtl.tiling.grid import axis_offsets, count_windows, num_offsets, tile_windows
from aerialmtl.tiling.splits import SplitAssigner, SplitSpec, assign_blocks
from aerialmtl.tiling.tile import TileOptions, read_manifest, tile_dataset

CRS = "EPSG:32631"
ORIGIN = (500000.0, 5000000.0)
T05 = Affine(0.5, 0, ORIGIN[0], 0, -0.5, ORIGIN[1])
T1 = Affine(1.0, 0, ORIGIN[0], 0, -1.0, ORIGIN[1])
SCHEME = ClassScheme.load("synthetic")


@pytest.fixture
def scene(tmp_path: Path, rng: np.random.Generator) -> dict[str, Path]:
    """128×128 px RGB ortho at 0.5 m (zeros = nodata in the top-left corner), 1 m nDSM, 0.5 m label codes."""
    img = rng.integers(1, 255, size=(3, 128, 128), dtype=np.uint8)
    img[:, :24, :24] = 0
    ndsm = rng.uniform(0, 20, size=(64, 64)).astype(np.float32)
    codes = rng.integers(0, 7, size=(128, 128), dtype=np.uint8)  # 0 = ignore, 1..6 classes
    return {
        "ortho": write_raster(tmp_path / "ortho.tif", img, CRS, T05, nodata=0),
        "ndsm": write_raster(tmp_path / "ndsm.tif", ndsm, CRS, T1, nodata=-9999.0),
        "labels": write_raster(tmp_path / "labels.tif", codes, CRS, T05),
    }


# ---- grid ------------------------------------------------------------------------------------
@pytest.mark.parametrize("length,size,stride", [(100, 32, 32), (100, 32, 16), (96, 32, 32), (33, 32, 7), (32, 32, 5)])
def test_axis_offsets_cover_the_axis_and_snap_to_the_edge(length: int, size: int, stride: int) -> None:
    offs = axis_offsets(length, size, stride)
    assert len(offs) == num_offsets(length, size, stride) == 1 + math.ceil((length - size) / stride)
    assert offs[0] == 0 and offs[-1] == length - size
    assert all(0 <= o <= length - size for o in offs)
    assert all(0 < b - a <= stride for a, b in zip(offs, offs[1:]))
    covered = np.zeros(length, bool)
    for o in offs:
        covered[o:o + size] = True
    assert covered.all()


def test_small_raster_policies() -> None:
    assert list(tile_windows(20, 50, 32, 32)) == [Window(0, 0, 32, 32), Window(0, 18, 32, 32)]
    assert [tuple(w.flatten()) for w in tile_windows(20, 50, 32, 32, small="clip")] == [(0, 0, 20, 32), (0, 18, 20, 32)]
    assert list(tile_windows(20, 50, 32, 32, small="skip")) == []
    assert count_windows(100, 50, 32, 16) == len(list(tile_windows(100, 50, 32, 16)))
    with pytest.raises(InputError, match="stride"):
        axis_offsets(100, 32, 40)


# ---- splits ----------------------------------------------------------------------------------
def test_assign_blocks_follows_area_ratios_and_gives_every_split_a_block() -> None:
    rng = np.random.default_rng(0)
    out = assign_blocks(np.ones(100), (0.7, 0.15, 0.15), rng)
    assert np.bincount(out, minlength=3).tolist() == [70, 15, 15]
    assert np.bincount(assign_blocks(np.ones(4), (0.7, 0.15, 0.15), rng), minlength=3).tolist() == [2, 1, 1]
    assert set(assign_blocks(np.ones(10), (1, 0, 0), rng).tolist()) == {0}
    # one big block and three slivers (a 121 m × 110 m raster in 100 m blocks): the big one is train
    for seed in range(20):
        out = assign_blocks(np.array([10000.0, 2130.0, 1060.0, 226.0]), (0.7, 0.15, 0.15), np.random.default_rng(seed))
        assert out[0] == 0 and sorted(set(out.tolist())) == [0, 1, 2]


def _footprints_overlap(a: dict[str, str], b: dict[str, str]) -> bool:
    ax0, ay0, aw, ah = (int(a[k]) for k in ("col_off", "row_off", "width", "height"))
    bx0, by0, bw, bh = (int(b[k]) for k in ("col_off", "row_off", "width", "height"))
    return ax0 < bx0 + bw and bx0 < ax0 + aw and ay0 < by0 + bh and by0 < ay0 + ah


def test_block_splits_are_leak_free_with_overlapping_strides(scene: dict[str, Path], tmp_path: Path) -> None:
    res = tile_dataset(
        scene["ortho"], tmp_path / "out", ndsm=scene["ndsm"], progress=False,
        options=TileOptions(size=16, stride=6, min_valid=0.0,
                            splits=SplitSpec(block_size=16.0, ratios=(0.5, 0.25, 0.25), seed=3)),
    )
    rows = read_manifest(res.manifest)
    assert {r["split"] for r in rows} == {"train", "val", "test"}
    assert res.dropped_split > 0  # windows straddling blocks of different splits were dropped
    for i, a in enumerate(rows):
        for b in rows[i + 1:]:
            if a["split"] != b["split"]:
                assert not _footprints_overlap(a, b), (a["patch_id"], b["patch_id"])


def test_block_assignment_is_seeded(scene: dict[str, Path]) -> None:
    from aerialmtl.io.align import reference_grid

    grid = reference_grid(scene["ortho"])
    a = SplitAssigner(SplitSpec(block_size=8.0, seed=1), grid).block_split
    b = SplitAssigner(SplitSpec(block_size=8.0, seed=1), grid).block_split
    c = SplitAssigner(SplitSpec(block_size=8.0, seed=2), grid).block_split
    assert a.shape == (8, 8) and np.array_equal(a, b) and not np.array_equal(a, c)


def _utm_polygon_to_lonlat(x0: float, y0: float, x1: float, y1: float, n: int = 8) -> list[list[float]]:
    """Ring of the UTM rectangle (densified) in lon/lat."""
    xs = list(np.linspace(x0, x1, n)) + [x1] * n + list(np.linspace(x1, x0, n)) + [x0] * n
    ys = [y0] * n + list(np.linspace(y0, y1, n)) + [y1] * n + list(np.linspace(y1, y0, n))
    lon, lat = warp_transform(CRS, "EPSG:4326", xs, ys)
    ring = [[a, b] for a, b in zip(lon, lat)]
    return ring + [ring[0]]


def _feature(ring: list[list[float]], **props: object) -> dict:
    return {"type": "Feature", "properties": props, "geometry": {"type": "Polygon", "coordinates": [ring]}}


def test_aoi_splits_keep_patches_inside_their_polygon(scene: dict[str, Path], tmp_path: Path) -> None:
    x0, y1 = ORIGIN
    xm, y0 = x0 + 32.0, y1 - 64.0  # left half train, right half test (64 m wide raster)
    fc = {"type": "FeatureCollection", "features": [
        _feature(_utm_polygon_to_lonlat(x0 - 5, y0 - 5, xm, y1 + 5), split="train"),
        _feature(_utm_polygon_to_lonlat(xm, y0 - 5, x0 + 69, y1 + 5), split="test"),
    ]}
    aoi = tmp_path / "aoi.geojson"
    aoi.write_text(json.dumps(fc))
    res = tile_dataset(
        scene["ortho"], tmp_path / "out", ndsm=scene["ndsm"], progress=False,
        options=TileOptions(size=16, stride=8, min_valid=0.0, splits=SplitSpec(method="aoi", aoi=str(aoi))),
    )
    rows = read_manifest(res.manifest)
    assert res.counts["val"] == 0 and res.counts["train"] > 0 and res.counts["test"] > 0
    for r in rows:
        left, right = float(r["left"]), float(r["right"])
        if r["split"] == "train":
            assert right <= xm + 1e-6
        else:
            assert left >= xm - 1e-6
    assert res.dropped_split > 0  # the windows across x = xm


def test_a_split_without_tall_pixels_is_warned_about_with_the_numbers_and_the_fix(scene: dict[str, Path],
                                                                                    tmp_path: Path) -> None:
    """Training holds buildings, validation (the right half, by AOI) only ground: the calibration fitted there could
    correct no tall height, so `tile` says so, naming the counts and the options that draw other splits."""
    x0, y1 = ORIGIN
    ndsm = np.random.default_rng(2).uniform(0, 20, size=(64, 64)).astype(np.float32)
    ndsm[:, 28:] = 0.2  # the right half (and a margin for resampling): bare ground
    flat = write_raster(tmp_path / "flat.tif", ndsm, CRS, T1, nodata=-9999.0)
    xm, y0 = x0 + 32.0, y1 - 64.0
    fc = {"type": "FeatureCollection", "features": [
        _feature(_utm_polygon_to_lonlat(x0 - 5, y0 - 5, xm, y1 + 5), split="train"),
        _feature(_utm_polygon_to_lonlat(xm, y0 - 5, x0 + 69, y1 + 5), split="val"),
    ]}
    aoi = tmp_path / "aoi.geojson"
    aoi.write_text(json.dumps(fc))
    args = ["tile", "--ortho", str(scene["ortho"]), "--ndsm", str(flat), "--size", "16", "--stride", "16",
            "--min-valid", "0", "--split-aoi", str(aoi), "--quiet", "--out", str(tmp_path / "out")]
    with pytest.warns(UserWarning) as caught:  # `aerialmtl tile` prints each as one `warning:` line (cli.main)
        result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    lines = [str(w.message) for w in caught if "holds no pixel ≥ 2 m" in str(w.message)]
    assert len(lines) == 1 and "the val split" in lines[0], [str(w.message) for w in caught]
    assert all(opt in lines[0] for opt in ("--split-block", "--split-ratios", "--split-aoi")), lines[0]
    assert " px, mean 0.20 m" in lines[0] and "while train holds " in lines[0]
    # a split that holds tall pixels everywhere is not warned about
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        tile_dataset(scene["ortho"], tmp_path / "ok", ndsm=scene["ndsm"], progress=False,
                     options=TileOptions(size=16, stride=16, min_valid=0.0,
                                         splits=SplitSpec(method="aoi", aoi=str(aoi))))


# ---- tile folder -----------------------------------------------------------------------------
def test_manifest_agrees_with_files(scene: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    res = tile_dataset(
        scene["ortho"], out, ndsm=scene["ndsm"], labels=scene["labels"], classes="synthetic", progress=False,
        options=TileOptions(size=32, stride=24, min_valid=0.5, splits=SplitSpec(block_size=16.0, seed=0)),
    )
    rows = read_manifest(res.manifest)
    meta = yaml.safe_load((out / "dataset.yaml").read_text())
    with rasterio.open(scene["ortho"]) as src:
        ref_t, ref_crs = src.transform, src.crs
    assert meta["format"] == "aerialmtl-tiles" and meta["tasks"] == ["height", "classes"]
    assert meta["counts"] == res.counts and sum(res.counts.values()) == len(rows) > 0
    assert meta["classes"]["name"] == "synthetic" and meta["gsd"] == 0.5 and meta["bands"] == [1, 2, 3]
    assert res.dropped_invalid > 0  # the window over the nodata corner
    train_px = []
    for r in rows:
        win = Window(int(r["col_off"]), int(r["row_off"]), int(r["width"]), int(r["height"]))
        expected_t = window_transform(win, ref_t)
        with rasterio.open(out / r["image_path"]) as im:
            assert im.transform == expected_t and im.crs == ref_crs and im.dtypes[0] == "uint8"
            assert im.bounds == pytest.approx(tuple(float(r[k]) for k in ("left", "bottom", "right", "top")))
            valid = im.read_masks(1) > 0
            data = im.read()
            assert float(r["valid_fraction"]) == pytest.approx(valid.mean(), abs=1e-6)
            assert np.all(valid == np.all(data > 0, axis=0))  # the ortho's nodata=0 became the mask
        if r["split"] == "train":
            train_px.append(data[:, valid].astype(np.float64))
        with rasterio.open(out / r["height_path"]) as hf:
            assert hf.transform == expected_t and hf.nodata == HEIGHT_NODATA and hf.dtypes[0] == "float32"
            h = hf.read(1)
            hv = h[h != HEIGHT_NODATA]
            assert np.all(h[~valid] == HEIGHT_NODATA)  # invalid image → invalid height
            assert float(r["height_min"]) == pytest.approx(hv.min())
            assert float(r["height_max"]) == pytest.approx(hv.max())
            assert float(r["height_mean"]) == pytest.approx(hv.mean(), rel=1e-5)
        with rasterio.open(out / r["classes_path"]) as cf:
            assert cf.transform == expected_t and cf.nodata == IGNORE_INDEX
            c = cf.read(1)
            assert np.all(c[~valid] == IGNORE_INDEX)
            hist = np.bincount(c[c != IGNORE_INDEX], minlength=SCHEME.num_classes)
            assert r["class_hist"] == ";".join(str(v) for v in hist)
        # labels are the remapped source codes on the same grid: code k → index k-1, 0 → ignore
        with rasterio.open(scene["labels"]) as lab:
            codes = lab.read(1, window=win)
        expect = np.where(codes == 0, IGNORE_INDEX, codes.astype(int) - 1)
        expect[~valid] = IGNORE_INDEX
        assert np.array_equal(c, expect)
    px = np.concatenate(train_px, axis=1)
    assert meta["mean"] == pytest.approx(px.mean(axis=1).tolist(), rel=1e-9)
    assert meta["std"] == pytest.approx(px.std(axis=1).tolist(), rel=1e-9)


def test_unknown_label_codes(scene: dict[str, Path], tmp_path: Path) -> None:
    with rasterio.open(scene["labels"]) as src:
        codes = src.read(1)
    codes[40:44, 40:44] = 9
    codes[60, 60] = 42
    bad = write_raster(tmp_path / "bad_labels.tif", codes, CRS, T05)
    with pytest.raises(LabelError, match=r"9, 42.*ignore_unknown_codes=True"):
        tile_dataset(
            scene["ortho"], tmp_path / "o1", labels=bad, classes=SCHEME, progress=False,
            options=TileOptions(size=64, min_valid=0.0, splits=SplitSpec(ratios=(1, 0, 0))),
        )
    res = tile_dataset(
        scene["ortho"], tmp_path / "o2", labels=bad, classes=SCHEME, progress=False,
        options=TileOptions(size=64, min_valid=0.0, splits=SplitSpec(ratios=(1, 0, 0)), ignore_unknown_codes=True),
    )
    row = next(r for r in read_manifest(res.manifest) if r["patch_id"] == "r000000_c000000")
    with rasterio.open(res.out_dir / row["classes_path"]) as cf:
        c = cf.read(1)
    assert np.all(c[40:44, 40:44] == IGNORE_INDEX) and c[60, 60] == IGNORE_INDEX
    assert res.tasks == ["classes"] and row["height_path"] == "" and not (res.out_dir / "train" / "height").exists()


def test_vector_labels_land_on_the_right_pixels(scene: dict[str, Path], tmp_path: Path) -> None:
    x0, y0 = ORIGIN
    # building: cols 10..29, rows 20..39 (pixel edges); road by code: cols 60..99, rows 64..79
    b = _utm_polygon_to_lonlat(x0 + 5.0, y0 - 20.0, x0 + 15.0, y0 - 10.0)
    r = _utm_polygon_to_lonlat(x0 + 30.0, y0 - 40.0, x0 + 50.0, y0 - 32.0)
    fc = {"type": "FeatureCollection", "features": [_feature(b, kind="Building"), _feature(r, kind=2)]}
    vec = tmp_path / "labels.geojson"
    vec.write_text(json.dumps(fc))
    res = tile_dataset(
        scene["ortho"], tmp_path / "out", labels_vector=vec, class_field="kind", classes=SCHEME, progress=False,
        options=TileOptions(size=128, min_valid=0.0, splits=SplitSpec(ratios=(1, 0, 0))),
    )
    row = read_manifest(res.manifest)[0]
    with rasterio.open(res.out_dir / row["classes_path"]) as cf:
        c = cf.read(1)
    building, road = SCHEME.names.index("building"), SCHEME.names.index("road")
    expect = np.full((128, 128), IGNORE_INDEX, np.uint8)
    expect[20:40, 10:30] = building
    expect[64:80, 60:100] = road
    expect[:24, :24] = IGNORE_INDEX  # ortho nodata corner
    assert np.array_equal(c, expect)

    fc["features"].append(_feature(b, kind="castle"))
    vec.write_text(json.dumps(fc))
    with pytest.raises(LabelError, match="castle"):
        tile_dataset(
            scene["ortho"], tmp_path / "o2", labels_vector=vec, class_field="kind", classes=SCHEME, progress=False,
            options=TileOptions(size=128, min_valid=0.0, splits=SplitSpec(ratios=(1, 0, 0))),
        )


def test_refuses_non_empty_out_without_overwrite(scene: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    kw = dict(ndsm=scene["ndsm"], options=TileOptions(size=64, min_valid=0.0, splits=SplitSpec(ratios=(1, 0, 0))),
              progress=False)
    tile_dataset(scene["ortho"], out, **kw)
    with pytest.raises(OutputExistsError, match=r"out.*overwrite=True"):
        tile_dataset(scene["ortho"], out, **kw)
    res = tile_dataset(
        scene["ortho"], out, overwrite=True, ndsm=scene["ndsm"], progress=False,
        options=TileOptions(size=32, min_valid=0.0, splits=SplitSpec(ratios=(1, 0, 0))),
    )
    assert len(list((out / "train" / "image").glob("*.tif"))) == res.counts["train"] == 16  # old patches gone
    assert not (out / "train" / "classes").exists()


def test_cli_tile(scene: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "out"
    args = ["tile", "--ortho", str(scene["ortho"]), "--ndsm", str(scene["ndsm"]), "--labels", str(scene["labels"]),
            "--classes", "synthetic", "--size", "32", "--stride", "32", "--split-block", "16",
            "--split-ratios", "0.5,0.25,0.25", "--min-valid", "0.5", "--max-height", "18", "--quiet", "--out", str(out)]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert "manifest.csv" in result.output and "train" in result.output
    assert "heights: train mean" in result.output and "% of pixels ≥ 2 m" in result.output
    meta = yaml.safe_load((out / "dataset.yaml").read_text())
    assert meta["height"]["max_height"] == 18.0 and meta["splits"]["block_size"] == 16.0
    assert sum(meta["counts"].values()) == len(read_manifest(out / "manifest.csv"))
    again = CliRunner().invoke(cli, args)
    assert again.exit_code != 0 and isinstance(again.exception, OutputExistsError)
    bad = CliRunner().invoke(cli, ["tile", "--ortho", str(scene["ortho"]), "--dsm", str(scene["ndsm"]),
                                   "--out", str(tmp_path / "x")])
    assert bad.exit_code == 2 and "--dtm" in bad.output
    bad = CliRunner().invoke(cli, args[:-1] + [str(tmp_path / "y"), "--split-ratios", "0.7,0.3"])
    assert bad.exit_code == 2 and "--split-ratios" in bad.output


def test_raster_smaller_than_a_patch_gives_one_padded_patch(tmp_path: Path, rng: np.random.Generator) -> None:
    ortho = write_raster(tmp_path / "o.tif", rng.integers(1, 255, (3, 48, 40), dtype=np.uint8), CRS, T05)
    ndsm = write_raster(tmp_path / "n.tif", rng.uniform(0, 9, (48, 40)).astype(np.float32), CRS, T05)
    res = tile_dataset(
        ortho, tmp_path / "out", ndsm=ndsm, progress=False,
        options=TileOptions(size=64, min_valid=0.4, splits=SplitSpec(ratios=(1, 0, 0))),
    )
    (row,) = read_manifest(res.manifest)
    assert float(row["valid_fraction"]) == pytest.approx(48 * 40 / 64**2)
    with rasterio.open(res.out_dir / row["image_path"]) as im, rasterio.open(res.out_dir / row["height_path"]) as hf:
        mask, h = im.read_masks(1) > 0, hf.read(1)
    assert im.shape == (64, 64) and mask[:48, :40].all() and not mask[48:].any() and not mask[:, 40:].any()
    assert np.all(h[~mask] == HEIGHT_NODATA) and np.all(h[mask] != HEIGHT_NODATA)
    with pytest.raises(InputError, match="min_valid must be a fraction in 0..1, got 1.5"):
        tile_dataset(ortho, tmp_path / "o2", ndsm=ndsm, progress=False, options=TileOptions(min_valid=1.5))
