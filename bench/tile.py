"""Benchmark `tile_dataset`: wall time and peak RSS at two raster sizes (peak RSS should not grow with size).

Usage::

    python bench/tile.py [--sizes 4096,8192] [--cache-mb 32] [--workdir /tmp/aerialmtl-bench-tile] [--keep]

For each size N it writes (block by block, never a whole raster in memory) an N×N 3-band uint8 ortho at
0.25 m, an nDSM at 1 m (N/4 × N/4 float32) and an N×N uint8 label raster, then tiles them (320 px, stride 320,
block splits) in a fresh subprocess and reports that subprocess's wall time and peak RSS
(``resource.getrusage(RUSAGE_SELF).ru_maxrss``). Prints a Markdown table.

The tiler's own arrays are a few patches; what can grow is GDAL's block cache, which ``tile_dataset``
caps at 128 MiB (``GDAL_CACHEMAX`` overrides it). ``--cache-mb`` sets it for the run, to separate the two.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

BLOCK = 512


def make_inputs(folder: Path, n: int) -> dict[str, str]:
    import rasterio
    from affine import Affine
    from rasterio.windows import Window

    folder.mkdir(parents=True, exist_ok=True)
    crs = "EPSG:32631"
    t = Affine(0.25, 0, 500000.0, 0, -0.25, 5000000.0)
    rng = np.random.default_rng(0)
    common = dict(driver="GTiff", crs=crs, tiled=True, blockxsize=BLOCK, blockysize=BLOCK, compress="deflate")
    paths = {k: str(folder / f"{k}.tif") for k in ("ortho", "ndsm", "labels")}
    with rasterio.open(paths["ortho"], "w", width=n, height=n, count=3, dtype="uint8", transform=t, **common) as o, \
            rasterio.open(paths["labels"], "w", width=n, height=n, count=1, dtype="uint8", transform=t,
                          **common) as lab:
        for r in range(0, n, BLOCK):
            for c in range(0, n, BLOCK):
                win = Window(c, r, min(BLOCK, n - c), min(BLOCK, n - r))
                h, w = int(win.height), int(win.width)
                yy, xx = np.mgrid[r:r + h, c:c + w]
                base = ((xx // 64 + yy // 64) % 6).astype(np.uint8)  # 16 m checkerboard of 6 "classes"
                img = np.stack([base * 40 + 10, base * 20 + 30, 200 - base * 30]).astype(np.uint8)
                img = img + rng.integers(0, 8, img.shape, dtype=np.uint8)
                o.write(img, window=win)
                lab.write((base + 1)[None], window=win)
    m = n // 4
    with rasterio.open(paths["ndsm"], "w", width=m, height=m, count=1, dtype="float32", nodata=-9999.0,
                       transform=Affine(1.0, 0, 500000.0, 0, -1.0, 5000000.0), **common) as d:
        for r in range(0, m, BLOCK):
            for c in range(0, m, BLOCK):
                win = Window(c, r, min(BLOCK, m - c), min(BLOCK, m - r))
                d.write(rng.uniform(0, 25, (1, int(win.height), int(win.width))).astype(np.float32), window=win)
    return paths


CHILD = r"""
import json, resource, sys, time
from aerialmtl.tiling.tile import TileOptions, tile_dataset
from aerialmtl.tiling.splits import SplitSpec
p = json.loads(sys.argv[1])
t0 = time.perf_counter()
res = tile_dataset(p["ortho"], p["out"], ndsm=p["ndsm"], labels=p["labels"], classes="synthetic", overwrite=True,
                   progress=False, options=TileOptions(size=320, stride=320, splits=SplitSpec(block_size=200.0)))
wall = time.perf_counter() - t0
print(json.dumps({"wall_s": wall, "maxrss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "patches": sum(res.counts.values()), "windows": res.windows}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="4096,8192")
    ap.add_argument("--workdir", default="/tmp/aerialmtl-bench-tile")
    ap.add_argument("--keep", action="store_true", help="keep the generated rasters and tiles")
    ap.add_argument("--cache-mb", type=int, default=None,
                    help="GDAL_CACHEMAX for the tiling subprocess (default: tile_dataset's own 128 MiB cap)")
    args = ap.parse_args()
    work = Path(args.workdir)
    rows = []
    for n in (int(s) for s in args.sizes.split(",")):
        t0 = time.perf_counter()
        paths = make_inputs(work / f"in_{n}", n)
        gen = time.perf_counter() - t0
        paths["out"] = str(work / f"tiles_{n}")
        env = dict(os.environ)
        env.pop("GDAL_CACHEMAX", None)
        if args.cache_mb is not None:
            env["GDAL_CACHEMAX"] = str(args.cache_mb * 1024 * 1024)
        out = subprocess.run([sys.executable, "-c", CHILD, json.dumps(paths)], capture_output=True, text=True,
                             env=env, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        r.update(n=n, gen_s=gen, mpix=n * n / 1e6)
        rows.append(r)
        print(f"# {n}: {r}", file=sys.stderr)
        if not args.keep:
            shutil.rmtree(work / f"in_{n}", ignore_errors=True)
            shutil.rmtree(work / f"tiles_{n}", ignore_errors=True)
    cache = f"{args.cache_mb} MiB" if args.cache_mb is not None else "default (128 MiB)"
    print(f"GDAL block cache: {cache}\n")
    print("| raster (px) | Mpx | windows | patches | tile wall (s) | Mpx/s | peak RSS (MiB) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['n']}×{r['n']} | {r['mpix']:.1f} | {r['windows']} | {r['patches']} | {r['wall_s']:.1f} | "
              f"{r['mpix'] / r['wall_s']:.2f} | {r['maxrss_mib']:.0f} |")


if __name__ == "__main__":
    main()
