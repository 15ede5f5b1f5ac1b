"""Real data: NEON Bartlett 0.1 m RGB + 1 m CHM on different grids, tiled single-task (height only)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
import yaml
from click.testing import CliRunner
from helpers.data import NEON_DIR
from rasterio.windows import Window
from rasterio.windows import transform as window_transform

from aerialmtl.cli import cli
from aerialmtl.formats.tiles import HEIGHT_NODATA
from aerialmtl.tiling.splits import SplitSpec
from aerialmtl.tiling.tile import TileOptions, read_manifest, tile_dataset

RGB = NEON_DIR / "rgb_0p1m.tif"
CHM = NEON_DIR / "chm_1m.tif"
pytestmark = pytest.mark.skipif(
    not (RGB.is_file() and CHM.is_file()),
    reason=f"NEON sample not found in {NEON_DIR} (expects rgb_0p1m.tif and chm_1m.tif from samples/neon_bart)",
)


def _chm_bilinear(xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CHM sampled at map coordinates by hand: bilinear between the 4 surrounding cell centres.

    Returns (values, ok) where ok is False when a neighbour is nodata or outside the CHM.
    """
    with rasterio.open(CHM) as src:
        chm = src.read(1).astype(np.float64)
        nodata, inv = src.nodata, ~src.transform
    fc, fr = inv @ (xs, ys)
    fc, fr = np.asarray(fc) - 0.5, np.asarray(fr) - 0.5  # fractional index between cell centres
    c0, r0 = np.floor(fc).astype(int), np.floor(fr).astype(int)
    dc, dr = fc - c0, fr - r0
    ok = (c0 >= 0) & (r0 >= 0) & (c0 + 1 < chm.shape[1]) & (r0 + 1 < chm.shape[0])
    c0, r0 = np.clip(c0, 0, chm.shape[1] - 2), np.clip(r0, 0, chm.shape[0] - 2)
    q = [chm[r0, c0], chm[r0, c0 + 1], chm[r0 + 1, c0], chm[r0 + 1, c0 + 1]]
    for v in q:
        ok &= v != nodata
    val = (q[0] * (1 - dc) * (1 - dr) + q[1] * dc * (1 - dr) + q[2] * (1 - dc) * dr + q[3] * dc * dr)
    return val, ok


def _patch_heights(out: Path, row: dict[str, str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Valid heights of a patch with the map coordinates of their pixel centres."""
    with rasterio.open(out / row["height_path"]) as f:
        h, t = f.read(1), f.transform
    rr, cc = np.nonzero(h != HEIGHT_NODATA)
    xs, ys = t @ (cc + 0.5, rr + 0.5)
    return h[rr, cc].astype(np.float64), np.asarray(xs), np.asarray(ys)


@pytest.fixture(scope="module")
def neon_tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("neon") / "tiles"
    tile_dataset(
        RGB, out, ndsm=CHM, progress=False,
        options=TileOptions(size=320, stride=296, min_valid=0.9, splits=SplitSpec(ratios=(1, 0, 0))),
    )
    return out


def test_neon_chm_lands_on_the_right_ortho_pixels(neon_tiles: Path) -> None:
    rows = read_manifest(neon_tiles / "manifest.csv")
    meta = yaml.safe_load((neon_tiles / "dataset.yaml").read_text())
    assert meta["tasks"] == ["height"] and meta["classes"] is None and meta["crs"] == "EPSG:32619"
    assert len(rows) == 5 * 4 and all(r["classes_path"] == "" for r in rows)  # 1 + ceil((1213 - 320) / 296) × …(1106)
    with rasterio.open(RGB) as src:
        ref = src.transform
    got, xs, ys = [], [], []
    for r in rows:
        win = Window(int(r["col_off"]), int(r["row_off"]), 320, 320)
        with rasterio.open(neon_tiles / r["image_path"]) as im:
            assert im.transform == window_transform(win, ref) and im.count == 3
        h, x, y = _patch_heights(neon_tiles, r)
        got.append(h), xs.append(x), ys.append(y)
    h, x, y = np.concatenate(got), np.concatenate(xs), np.concatenate(ys)
    expected, ok = _chm_bilinear(x, y)
    assert ok.mean() > 0.95
    assert np.abs(h[ok] - expected[ok]).max() < 1e-3  # same numbers, independently interpolated

    # semantics: the forest is tall, and the CHM's own low area (the clearing) stays near the ground
    assert np.percentile(h, 90) > 10.0
    with rasterio.open(CHM) as src:
        chm, ct = src.read(1), src.transform
    k = 5  # 5 m × 5 m windows of the CHM whose every cell is < 1 m
    low = [(r, c) for r in range(1, chm.shape[0] - k - 1) for c in range(1, chm.shape[1] - k - 1)
           if (chm[r:r + k, c:c + k] >= 0).all() and chm[r - 1:r + k + 1, c - 1:c + k + 1].max() < 1.0]
    assert low, "the CHM has no low area?"
    r0, c0 = low[0]
    (x0, y1), (x1, y0) = ct @ (c0, r0), ct @ (c0 + k, r0 + k)
    inside = (x > x0) & (x < x1) & (y > y0) & (y < y1)
    assert inside.sum() > 1000 and h[inside].max() < 1.0


def test_neon_tile_at_working_gsd_via_cli(tmp_path: Path) -> None:
    out = tmp_path / "tiles"
    res = CliRunner().invoke(cli, ["tile", "--ortho", str(RGB), "--ndsm", str(CHM), "--gsd", "0.5", "--size", "64",
                                   "--stride", "64", "--split-ratios", "1,0,0", "--quiet", "--out", str(out)])
    assert res.exit_code == 0, res.output
    meta = yaml.safe_load((out / "dataset.yaml").read_text())
    assert meta["gsd"] == 0.5 and meta["tasks"] == ["height"] and meta["height"]["source"] == "ndsm"
    rows = read_manifest(out / "manifest.csv")
    assert len(rows) >= 9
    for r in rows:
        with rasterio.open(out / r["image_path"]) as im:
            assert im.res == (0.5, 0.5) and im.shape == (64, 64)
            assert im.transform.c == pytest.approx(320214.8 + 0.5 * int(r["col_off"]))
            assert im.transform.f == pytest.approx(4881614.5 - 0.5 * int(r["row_off"]))
    h, x, y = (np.concatenate(a) for a in zip(*(_patch_heights(out, r) for r in rows)))
    expected, ok = _chm_bilinear(x, y)
    assert ok.mean() > 0.9
    # bilinear 1 m → 0.5 m is still upsampling: same interpolant
    assert np.abs(h[ok] - expected[ok]).max() < 1e-3
