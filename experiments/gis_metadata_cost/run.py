"""What the GIS metadata of a prediction costs, and what mosaic overviews save.

Usage: python -m experiments.gis_metadata_cost.run --size 8192 --tiles 2 [--workdir /tmp/bench_gis_meta]

Writes ``--tiles`` float32 height COGs of N×N pixels side by side (smooth synthetic heights, a nodata
corner), then times:

* ``band_stats`` (what a style's 0..p98 range and the STAC statistics are computed from: a ≤ 1 Mpx read
  served by the COG overviews) against the exact p98 of a full read, and the two p98 values;
* the whole metadata step of a prediction folder's commit for one tile (``PredictionWriter._write_metadata``
  equivalent: stats + style + item);
* a zoomed-out read (1/16 of the side, what QGIS asks for a whole-mosaic view) of the VRT mosaic with
  its ``OverviewList`` against the same mosaic without it.
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine

from aerialmtl.formats.prediction import FLOAT_NODATA, prediction_layers
from aerialmtl.formats.qgis_style import layer_style, write_style
from aerialmtl.formats.stac import build_item, write_json
from aerialmtl.io.align import Grid
from aerialmtl.io.cog import to_cog
from aerialmtl.io.stats import band_stats
from aerialmtl.io.vrt import mosaic_vrt


def make_tile(path: Path, n: int, x0: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    raw = path.with_suffix(".raw.tif")
    tf = Affine(0.5, 0, x0, 0, -0.5, 5000000.0)
    with rasterio.open(raw, "w", driver="GTiff", width=n, height=n, count=1, dtype="float32", crs="EPSG:32631",
                       transform=tf, nodata=FLOAT_NODATA, tiled=True, blockxsize=512, blockysize=512) as dst:
        for r in range(0, n, 1024):
            h = min(1024, n - r)
            y, x = np.mgrid[r:r + h, 0:n]
            block = (12 + 10 * np.sin(x / 97.0) * np.cos(y / 131.0) + rng.gamma(1.0, 2.0, (h, n))).astype(np.float32)
            if r == 0:
                block[:256, :256] = FLOAT_NODATA
            dst.write(block[None], window=rasterio.windows.Window(0, r, n, h))
    to_cog(raw, path)
    raw.unlink()


def timed(fn, repeat: int = 3):  # type: ignore[no-untyped-def]
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", type=int, default=8192)
    ap.add_argument("--tiles", type=int, default=2)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_gis_meta"))
    a = ap.parse_args()
    shutil.rmtree(a.workdir, ignore_errors=True)
    a.workdir.mkdir(parents=True)
    tiles = []
    for k in range(a.tiles):
        path = a.workdir / f"t{k}" / "height.tif"
        path.parent.mkdir()
        make_tile(path, a.size, 500000.0 + k * a.size * 0.5, k)
        tiles.append(path)

    t_stats, stats = timed(lambda: band_stats(tiles[0]))

    def full_p98() -> float:
        with rasterio.open(tiles[0]) as src:
            v = src.read(1, masked=True).compressed()
        return float(np.percentile(v, 98))

    t_full, p98 = timed(full_p98, repeat=1)
    print(f"stats from overviews: {t_stats:.3f} s, p98 {stats.p98:.3f} m (approximate={stats.approximate}); "
          f"full read + percentile: {t_full:.3f} s, p98 {p98:.3f} m")

    specs = prediction_layers(("height",), None, 1)
    with rasterio.open(tiles[0]) as src:
        grid = Grid(src.crs, src.transform, src.width, src.height)

    def metadata() -> None:
        s = band_stats(tiles[0])
        write_style(a.workdir / "t0" / "height.qml", layer_style(specs[0], s))
        write_json(a.workdir / "t0" / "item.json", build_item(a.workdir / "t0", grid, specs, {}, {"height": s}))

    t_meta, _ = timed(metadata)
    print(f"metadata of one {a.size}² height layer (stats + .qml + item.json): {t_meta:.3f} s")

    with_ov = mosaic_vrt(a.workdir / "height.mosaic.vrt", tiles)
    without = mosaic_vrt(a.workdir / "plain.vrt", tiles, overviews=False)
    for name, vrt in (("with OverviewList", with_ov), ("without", without)):
        with rasterio.open(vrt) as src:
            shape = (src.height // 16, src.width // 16)
            ovs = src.overviews(1)
        def read(v: Path = vrt, s: tuple[int, int] = shape) -> None:
            with rasterio.Env(GDAL_CACHEMAX=64), rasterio.open(v) as src:  # a small cache: no warm re-reads
                src.read(1, out_shape=s)

        t, _ = timed(read)
        print(f"mosaic {name} (overviews {ovs}): read at 1/16 {shape}: {t:.3f} s")


if __name__ == "__main__":
    main()
