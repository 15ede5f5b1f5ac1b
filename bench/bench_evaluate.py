"""Time and peak memory of `evaluate_prediction` on a synthetic prediction folder of N×N pixels.

Usage: python bench/bench_evaluate.py --size 3000 [--workdir /tmp/bench_eval]

Writes a full prediction folder (height, std, classes, entropy, mutual info, 4-band probabilities) on a
0.5 m UTM 31N grid, a height reference at 1 m in UTM 32N and labels at 1 m, then runs the evaluation
in a fresh child process and prints its wall time (imports and plots included) and peak RSS.
"""

from __future__ import annotations

import argparse
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from rasterio.warp import transform_bounds

from aerialmtl.evaluation.evaluate import evaluate_prediction


def _write(path: Path, data: np.ndarray, crs: str, tf: Affine, nodata: float | None, **kw: object) -> None:
    data = data if data.ndim == 3 else data[None]
    with rasterio.open(path, "w", driver="GTiff", width=data.shape[2], height=data.shape[1], count=data.shape[0],
                       dtype=data.dtype, crs=crs, transform=tf, nodata=nodata, tiled=True, compress="deflate",
                       **kw) as dst:
        dst.write(data)


def make_folder(root: Path, n: int) -> tuple[Path, Path, Path]:
    rng = np.random.default_rng(0)
    pred = root / "pred"
    pred.mkdir(parents=True)
    tf = Affine(0.5, 0, 736000.0, 0, -0.5, 4987000.0)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    height = (5 + 4 * np.sin(xx / 97) * np.cos(yy / 71)).astype(np.float32)
    err = rng.normal(0, 0.5, (n, n)).astype(np.float32)
    _write(pred / "height.tif", height + err, "EPSG:32631", tf, -9999.0)
    _write(pred / "height_std.tif", np.abs(err) + 0.1, "EPSG:32631", tf, -9999.0)
    cls = ((xx // 64 + yy // 64) % 4).astype(np.uint8)
    _write(pred / "classes.tif", cls, "EPSG:32631", tf, 255)
    ent = (0.2 + 0.1 * (xx % 7 == 0)).astype(np.float32)
    _write(pred / "class_entropy.tif", ent, "EPSG:32631", tf, -9999.0)
    _write(pred / "class_mutual_info.tif", ent / 2, "EPSG:32631", tf, -9999.0)
    probs = np.full((4, n, n), 0.1, np.float32)
    for k in range(4):
        probs[k][cls == k] = 0.7
    _write(pred / "class_probabilities.tif", probs, "EPSG:32631", tf, -9999.0)
    del probs
    # height reference: 1 m in UTM 32N over the same area (smooth field, bilinear-friendly)
    left, bottom, right, top = transform_bounds("EPSG:32631", "EPSG:32632", 736000.0, 4987000.0 - n / 2,
                                                736000.0 + n / 2, 4987000.0)
    m = int(max(right - left, top - bottom)) + 20
    ref = (5 + 0.001 * np.add.outer(np.arange(m), np.arange(m))).astype(np.float32)
    _write(root / "ndsm32.tif", ref, "EPSG:32632", Affine(1.0, 0, left - 10, 0, -1.0, top + 10), -9999.0)
    labels = (cls[::2, ::2] + 1).astype(np.uint8)
    _write(root / "labels.tif", labels, "EPSG:32631", Affine(1.0, 0, 736000.0, 0, -1.0, 4987000.0), 0)
    return pred, root / "ndsm32.tif", root / "labels.tif"


def run_eval(root: Path) -> None:
    """Child process: evaluate and print time, peak RSS and headline numbers."""
    t0 = time.perf_counter()
    rep = evaluate_prediction(root / "pred", height_ref=root / "ndsm32.tif", labels_ref=root / "labels.tif",
                              classes="synthetic", out=root / "ev" / "report.json", overwrite=True)
    dt = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    n = rep["grid"]["width"] * rep["grid"]["height"]
    print(f"size {rep['grid']['width']}x{rep['grid']['height']} ({n / 1e6:.1f} Mpx): evaluate {dt:.1f} s "
          f"({n / dt / 1e6:.2f} Mpx/s incl. imports/plots), peak RSS {rss:.0f} MiB; "
          f"MAE {rep['height']['mae']:.3f} m, OA {rep['classes']['overall_accuracy']:.3f}, "
          f"sampled {rep['sampling']['height_sampled']} of {rep['sampling']['height_pixels']} px")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=3000)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_eval"))
    ap.add_argument("--eval-only", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.eval_only is not None:
        run_eval(args.eval_only)
        return
    root = args.workdir / str(args.size)
    shutil.rmtree(root, ignore_errors=True)
    make_folder(root, args.size)
    # a fresh process so that peak RSS is the evaluation's own, not the input writing's
    subprocess.run([sys.executable, __file__, "--eval-only", str(root)], check=True)
    shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
