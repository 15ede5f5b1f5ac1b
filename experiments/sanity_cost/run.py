"""Cost of the sanity checks of issue 18 next to the work they guard.

Usage::

    python -m experiments.sanity_cost.run [--window 512] [--reps 5] [--workdir /tmp/aerialmtl-bench-sanity]

Measures, in this process, on the CPU:

* ``check_finite_outputs`` (runs after every model call of predict) against the model call it follows:
  the default D3-Net (DenseNet-121, 6 classes) on one ``window``² window, T = 1, fp32; the check on
  statistics of the same shapes (heights B×H×W, probabilities B×H×W×K). Medians of ``reps`` runs;
* ``sample_input`` (once per orthophoto): on the real Autzen orthophoto (1308 × 4385, no overviews) and on
  a generated 8192² tiled uint8 GeoTIFF (cold file cache not enforced: a second read is warm);
* ``HeightSource.check_dsm_above_dtm`` (once per tile/evaluate run with DSM + DTM): the Autzen DSM/DTM
  (EPSG:32610, 1 m) seen through the orthophoto's grid (EPSG:2994, 1 ft; warped).

Prints a Markdown table; the CPU model and load are printed too (``lscpu``, ``uptime``).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import time
from pathlib import Path

import numpy as np
import rasterio
import torch
from affine import Affine

from aerialmtl.inference.sanity import check_finite_outputs, sample_input
from aerialmtl.io.align import HeightSource, reference_grid
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net
from aerialmtl.models.mc_dropout import McStatistics
from experiments.common.autzen import DATA, DSM, DTM, ORTHO


def median_time(fn, reps: int) -> float:
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def big_ortho(path: Path, n: int = 8192, block: int = 512) -> Path:
    if path.exists():
        return path
    profile = dict(driver="GTiff", width=n, height=n, count=3, dtype="uint8", crs="EPSG:32631", tiled=True,
                   blockxsize=block, blockysize=block, compress="deflate",
                   transform=Affine(0.25, 0, 500000.0, 0, -0.25, 5000000.0))
    rng = np.random.default_rng(0)
    with rasterio.open(path, "w", **profile) as dst:
        for r in range(0, n, block):
            dst.write(rng.integers(0, 255, (3, block, n), dtype=np.uint8), window=((r, r + block), (0, n)))
    return path


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--window", type=int, default=512)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/aerialmtl-bench-sanity"))
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(0)
    rows = []

    n, k = args.window, 6
    model = D3Net(ModelConfig(num_classes=k)).eval()
    x = torch.randn(1, 3, n, n)
    with torch.no_grad():
        model_s = median_time(lambda: model(x), args.reps)
    stats = McStatistics(height_mean=torch.rand(1, n, n), probs=torch.rand(1, n, n, k))
    valid = torch.ones(1, n, n, dtype=torch.bool)
    check_s = median_time(lambda: check_finite_outputs(stats, valid, "x"), max(30, args.reps))
    big_stats = McStatistics(height_mean=torch.rand(1, 1024, 1024), probs=torch.rand(1, 1024, 1024, k))
    big_valid = torch.ones(1, 1024, 1024, dtype=torch.bool)
    big_s = median_time(lambda: check_finite_outputs(big_stats, big_valid, "x"), 30)
    rows.append((f"model call, D3-Net DenseNet-121 K={k}, 1×{n}², T=1 fp32", model_s, ""))
    rows.append((f"check_finite_outputs on its statistics (1×{n}², K={k})", check_s,
                 f"{100 * check_s / model_s:.2f} % of the model call"))
    rows.append((f"check_finite_outputs, 1×1024², K={k} (the default --tile)", big_s, "median of 30"))

    ortho = DATA / ORTHO
    if ortho.exists():
        rows.append(("sample_input, Autzen ortho 1308×4385 (no overviews)",
                     median_time(lambda: sample_input(ortho, [1, 2, 3]), args.reps), "16 windows of 128²"))
    big = big_ortho(args.workdir / "ortho_8192.tif")
    rows.append(("sample_input, 8192² tiled uint8 GeoTIFF",
                 median_time(lambda: sample_input(big, [1, 2, 3]), args.reps), "16 windows of 128²"))
    if ortho.exists():
        grid = reference_grid(ortho)
        with HeightSource(grid, dsm=DATA / DSM, dtm=DATA / DTM) as hs:
            rows.append(("check_dsm_above_dtm, Autzen DSM/DTM through the ortho grid (warped)",
                         median_time(hs.check_dsm_above_dtm, args.reps), "16 windows of 64²"))

    cpu = subprocess.run("lscpu | grep 'Model name'", shell=True, capture_output=True, text=True).stdout.strip()
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    print(f"CPU: {cpu.split(':', 1)[-1].strip()}; torch threads {torch.get_num_threads()}; uptime: {load}\n")
    print("| what | median s | note |\n|---|---|---|")
    for what, secs, note in rows:
        print(f"| {what} | {secs:.4f} | {note} |")


if __name__ == "__main__":
    main()
