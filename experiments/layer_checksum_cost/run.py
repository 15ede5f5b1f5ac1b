"""What the content checksum of a prediction layer costs (issue 40): SHA-256 of a 10k × 10k px float32 height
layer written as the package writes layers (a COG, DEFLATE, predictor 3), once at commit and once per
``--skip-existing`` check (:meth:`aerialmtl.formats.prediction.PredictionFolder.check`).

Usage: ``nice -n 10 python -m experiments.layer_checksum_cost.run [--size 10000] [--out /tmp/layer-bench]``;
prints one JSON line (seconds, MB, MB/s, and the load average beside them).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import rasterio
from rasterio.transform import from_origin

from aerialmtl.io.cog import to_cog
from aerialmtl.io.fingerprint import content_sha256


def write_layer(path: Path, size: int) -> Path:
    """A ``size``² float32 height layer (smooth terrain with roofs and noise) as a COG at ``path``."""
    plain = path.with_suffix(".plain.tif")
    rng = np.random.default_rng(40)
    profile = {"driver": "GTiff", "width": size, "height": size, "count": 1, "dtype": "float32",
               "crs": "EPSG:32631", "transform": from_origin(500000, 5000000, 0.5, 0.5), "nodata": -9999.0,
               "tiled": True, "blockxsize": 512, "blockysize": 512, "compress": "deflate", "predictor": 3}
    with rasterio.open(plain, "w", **profile) as dst:
        for row in range(0, size, 512):
            h = min(512, size - row)
            y = np.arange(row, row + h, dtype=np.float32)[:, None]
            x = np.arange(size, dtype=np.float32)[None, :]
            block = 3 * np.sin(x / 700) * np.cos(y / 500) + 6 * ((x // 40 + y // 40) % 5 == 0)
            block += rng.normal(0, 0.2, block.shape)
            dst.write(block.astype(np.float32)[None], window=((row, row + h), (0, size)))
    to_cog(plain, path)
    plain.unlink()
    return path


def main() -> None:
    """Write the layer, hash it cold-ish and warm, print the numbers."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=10000)
    ap.add_argument("--out", type=Path, default=Path("/tmp/layer-bench"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    layer = args.out / "height.tif"
    if not layer.exists():
        write_layer(layer, args.size)
    mb = layer.stat().st_size / 1e6
    times, cpu = [], []
    for _ in range(3):
        t0, c0 = time.perf_counter(), time.process_time()
        content_sha256(layer)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    print(json.dumps({"size_px": args.size, "file_MB": round(mb, 1), "sha256_wall_s": [round(t, 3) for t in times],
                      "sha256_cpu_s": [round(t, 3) for t in cpu], "MB_per_cpu_s": round(mb / min(cpu)),
                      "loadavg": os.getloadavg()}))


if __name__ == "__main__":
    main()
