"""Benchmarks of streaming prediction (`aerialmtl predict`): speed, baseline comparison, peak memory.

Parts (select with flags; each can run alone):

* ``--speed``: full D3-Net (3 bands, 20 classes, untrained weights), T = 1, bf16, end-to-end on a
  synthetic ``--size``² raster (default 2048): output Mpx/s and the overlap factor.
* ``--baseline``: the authors' strategy (1024-pixel windows, stride 512, Gaussian blending, whole raster in
  RAM, fp32, every MC sample re-running the whole network) vs ``predict_raster`` at T = 30 on a
  ``--baseline-size``² raster with the ``--baseline-model`` config (``small`` by default): speed ratio and
  mean |Δ height|.
* ``--rss``: peak RSS (``ru_maxrss``) of ``predict_raster`` (small model, T = 1) on a 4 Mpx and a 64 Mpx
  raster, each in its own subprocess.

Usage::

    python bench/predict.py --speed --baseline --rss
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio
import torch
from affine import Affine
from rasterio.windows import Window

from aerialmtl.classes import ClassDef, ClassScheme
from aerialmtl.inference.predict import predict_raster
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net
from aerialmtl.models.mc_dropout import mc_dropout_mode
from aerialmtl.training.checkpoint import ModelMeta

SMALL = dict(growth_rate=12, block_config=(2, 4, 8, 6), num_init_features=32)


def make_model(kind: str, k: int = 20) -> tuple[D3Net, ModelMeta]:
    torch.manual_seed(0)
    cfg = ModelConfig(num_classes=k, **(SMALL if kind == "small" else {}))  # type: ignore[arg-type]
    scheme = ClassScheme("bench", tuple(ClassDef(i + 1, f"c{i}", (i * 12 % 256, 100, 200)) for i in range(k)))
    meta = ModelMeta(cfg, scheme, (1, 2, 3), (110.0, 110.0, 100.0), (45.0, 45.0, 45.0), 0.5)
    return D3Net(cfg).eval(), meta


def synthetic_raster(path: Path, width: int, height: int, block: int = 512) -> Path:
    """A 3-band uint8 tiled GeoTIFF written block by block (smooth blobs + noise); flat memory."""
    prof = dict(driver="GTiff", width=width, height=height, count=3, dtype="uint8", crs="EPSG:32631",
                transform=Affine(0.5, 0, 500000.0, 0, -0.5, 5000000.0), tiled=True, blockxsize=block,
                blockysize=block, bigtiff="IF_SAFER")
    rng = np.random.default_rng(0)
    with rasterio.open(path, "w", **prof) as dst:
        for r in range(0, height, block):
            for c in range(0, width, block):
                h, w = min(block, height - r), min(block, width - c)
                yy, xx = np.mgrid[r:r + h, c:c + w]
                base = 120 + 60 * np.sin(xx / 37.0) * np.cos(yy / 23.0)
                data = np.stack([base + rng.normal(0, 10, (h, w)) + 10 * i for i in range(3)])
                dst.write(np.clip(data, 0, 255).astype(np.uint8), window=Window(c, r, w, h))
    return path


def load_avg() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


# ---- (a) speed ---------------------------------------------------------------------------------
def bench_speed(size: int, tmp: Path) -> dict:
    model, meta = make_model("full")
    src = synthetic_raster(tmp / "speed.tif", size, size)
    res = predict_raster(src, (model, meta), tmp / "speed_out", mc=1, precision="bf16", batch_size=2,
                         progress=False, overwrite=True)
    return {"part": "speed", "model": "full D3-Net (DenseNet-121, 20 classes)", "size": size, "T": 1,
            "precision": "bf16", "mpx_per_s": res.megapixels_per_s, "overlap_factor": res.overlap_factor,
            "timings_s": res.timings, "load_avg": load_avg()}


# ---- (b) baseline ------------------------------------------------------------------------------
def _offsets(length: int, size: int, stride: int) -> list[int]:
    n = 1 + max(0, -(-(length - size) // stride))
    return [min(i * stride, length - size) for i in range(n)]


def baseline_predict(image: np.ndarray, model: D3Net, meta: ModelMeta, samples: int, win: int = 1024,
                     stride: int = 512) -> np.ndarray:
    """Authors' strategy: whole raster in RAM, 1024 windows every 512 px, Gaussian weights, fp32, T full passes."""
    c, h, w = image.shape
    x_all = (image.astype(np.float32) - np.asarray(meta.mean, np.float32)[:, None, None]) / np.asarray(
        meta.std, np.float32)[:, None, None]
    acc = np.zeros((h, w), np.float64)
    wsum = np.zeros((h, w), np.float64)
    g1 = np.exp(-0.5 * ((np.arange(win) - (win - 1) / 2) / (win / 4)) ** 2)
    g = np.outer(g1, g1)
    with torch.no_grad(), mc_dropout_mode(model):
        for r in _offsets(h, win, stride):
            for cc in _offsets(w, win, stride):
                x = torch.from_numpy(np.ascontiguousarray(x_all[None, :, r:r + win, cc:cc + win]))
                hs = [model(x)["height"][0, 0].numpy() for _ in range(samples)]  # whole network T times
                acc[r:r + win, cc:cc + win] += np.mean(hs, axis=0) * g
                wsum[r:r + win, cc:cc + win] += g
    return (acc / wsum).astype(np.float32)


def bench_baseline(size: int, kind: str, samples: int, tmp: Path) -> dict:
    model, meta = make_model(kind)
    src = synthetic_raster(tmp / "base.tif", size, size)
    with rasterio.open(src) as s:
        image = s.read()
    t0 = time.perf_counter()
    base = baseline_predict(image, model, meta, samples)
    t_base = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = predict_raster(src, (model, meta), tmp / "base_out", mc=samples, precision="bf16", batch_size=2,
                         progress=False, overwrite=True)
    t_ours = time.perf_counter() - t0
    with rasterio.open(res.files["height"]) as s:
        ours = s.read(1)
    return {"part": "baseline", "model": kind, "size": size, "T": samples, "baseline_s": t_base, "ours_s": t_ours,
            "speedup": t_base / t_ours, "mean_abs_height_diff_m": float(np.abs(ours - base).mean()),
            "mean_abs_height_m": float(np.abs(base).mean()), "overlap_factor": res.overlap_factor,
            "load_avg": load_avg()}


# ---- (c) peak RSS ------------------------------------------------------------------------------
def rss_child(width: int, height: int, tmp: Path) -> None:
    torch.set_num_threads(2)
    model, meta = make_model("small")
    src = synthetic_raster(tmp / f"rss_{width}x{height}.tif", width, height)
    t0 = time.perf_counter()
    res = predict_raster(src, (model, meta), tmp / f"rss_out_{width}x{height}", mc=1, precision="bf16",
                         batch_size=2, progress=False, overwrite=True)
    print(json.dumps({"width": width, "height": height, "mpx": width * height / 1e6,
                      "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "seconds": time.perf_counter() - t0, "mpx_per_s": res.megapixels_per_s}))


def bench_rss(sizes: list[tuple[int, int]], tmp: Path) -> dict:
    runs = []
    for w, h in sizes:
        out = subprocess.run([sys.executable, __file__, "--rss-child", f"{w}x{h}", "--tmp", str(tmp)],
                             check=True, capture_output=True, text=True)
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(json.dumps(runs[-1]), flush=True)
    return {"part": "rss", "model": "small", "runs": runs,
            "ratio_largest_to_smallest": runs[-1]["max_rss_mb"] / runs[0]["max_rss_mb"], "load_avg": load_avg()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--speed", action="store_true")
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--baseline", action="store_true")
    ap.add_argument("--baseline-size", type=int, default=1536)
    ap.add_argument("--baseline-model", choices=["small", "full"], default="small")
    ap.add_argument("--mc", type=int, default=30)
    ap.add_argument("--rss", action="store_true")
    ap.add_argument("--rss-sizes", default="2048x2048,8192x8192", help="WxH list, smallest first")
    ap.add_argument("--rss-child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--tmp", default=None)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory(dir=args.tmp) as t:
        tmp = Path(args.tmp) if args.rss_child else Path(t)
        if args.rss_child:
            w, h = (int(v) for v in args.rss_child.split("x"))
            rss_child(w, h, tmp)
            return
        if args.speed:
            print(json.dumps(bench_speed(args.size, tmp)), flush=True)
        if args.baseline:
            print(json.dumps(bench_baseline(args.baseline_size, args.baseline_model, args.mc, tmp)), flush=True)
        if args.rss:
            sizes = [tuple(int(v) for v in s.split("x")) for s in args.rss_sizes.split(",")]
            print(json.dumps(bench_rss(sizes, tmp)), flush=True)  # type: ignore[arg-type]


if __name__ == "__main__":
    main()
