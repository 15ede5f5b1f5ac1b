"""Benchmarks of streaming prediction (`aerialmtl predict`): speed, baseline comparison, peak memory.

Parts (select with flags; each can run alone):

* ``--speed``: full D3-Net (3 bands, 20 classes, untrained weights), T = 1, end-to-end on a
  synthetic ``--size``² raster (default 2048) for each of ``--precisions`` (default ``fp32``): output
  Mpx/s, model-only Mpx/s, the overlap factor; plus the model's FLOP per pixel (torch's flop counter)
  and this machine's fp32/bf16 GEMM ceilings (GFLOP/s), to say how far from the hardware it runs.
* ``--components``: time per megapixel of the full D3-Net's encoder and of one decoder sample
  (fp32, channels_last, 512² batch), from which the speed-up over the baseline on a large raster
  (baseline overlap 4×) is predicted.
* ``--baseline``: the authors' strategy (1024-pixel windows, stride 512, Gaussian blending, whole raster in
  RAM, fp32, every MC sample re-running the whole network) vs ``predict_raster`` (defaults: tile 1024,
  overlap 64, precision auto) at T = 30 on a ``--baseline-size``² raster with the ``--baseline-model``
  config (``small`` by default): speed ratio and mean |Δ height| (different dropout masks, so
  the difference is MC sampling noise plus blending).
* ``--rss``: peak RSS (``ru_maxrss``) of ``predict_raster`` (``--rss-model``: small by default, or the
  near-null model of ``--pipeline``; T = 1) on each of ``--rss-sizes`` (WxH), each in its own subprocess.
* ``--pipeline``: the pipeline around the model, through the CLI as a user runs it: a near-null D3-Net
  (growth 1, blocks 1-1-1-1, 2 stem features, bn_size 1, 20 classes, untrained; its forward costs almost
  nothing) saved as a checkpoint, then ``python -m aerialmtl predict`` in a subprocess on a synthetic
  raster for each of ``--pipeline-cases`` (``SIZE:T``), wall time including process start, plus the
  child's peak RSS and the stage timings of ``prediction.json``. ``--pipeline-args`` adds CLI flags.
  ``--pipeline-head-bias drawn`` gives the heads' convolutions the non-zero biases any trained head has
  (normal, std 0.5, seed 1); ``zero`` (the default, as in the earlier sessions) keeps their initial zeros,
  with which OpenVINO (2026.4, bf16) reorders the decoder's class planes with a slow reference kernel that a
  trained model does not meet (bench/RESULTS.md, issue 27, third session). ``--pipeline-against ROOT`` runs
  each case ``--pipeline-pairs`` times here and in another checkout (``git worktree add /tmp/base main``), in
  turn, with CPU seconds, and compares the layers of the last pair (bytes and decoded pixels): before/after.

* ``--engines``: the full D3-Net (DenseNet-121, 20 classes, untrained weights) saved as a checkpoint,
  then ``python -m aerialmtl predict`` in a subprocess on a synthetic ``--size``² raster for each T of
  ``--engine-mc`` (default 1,8), back to back: ``--engine torch --precision fp32`` (the former CPU path)
  against the default (``--engine auto --precision auto``), the latter twice: with an empty OpenVINO
  cache (conversion and compilation paid) and with the cache of the first run. Also, in this process:
  the model alone on one 1024² window on each engine/precision (best of 2, GFLOP/s from torch's flop
  counter), the CPU's name, its native-bf16 flags and its fp32/bf16 GEMM ceilings measured in the same run.

* ``--startup``: warm start-up of ``aerialmtl predict`` with the full D3-Net: the wall time of whole
  processes on a 256² raster (one small window, so almost all of it is imports, the checkpoint, the engine
  from its warm cache and the outputs), ``--startup-runs`` times after one warm-up run with ``--engine openvino``
  (which fills the cache); min / median / max, and the engine the timed runs took.
* ``--alone``: the full D3-Net alone in this process, run as ``predict`` runs it (the same ``Predictor``: default
  engine, precision, threads and streams, the OpenVINO cache of ``--startup``/``--shared-cpu`` under ``--tmp``) on
  ``--alone-windows`` windows of the shape ``predict`` uses on a ``--size``² raster, one batch per stream kept in
  flight, T = 1: Mpx/s of window pixels, the yardstick of the CLI's model stage (issue 27: ≥ 80 %).
* ``--class-map``: the ``classes`` layer of one finished ``--size``² block (K = 20 blended class sums, a strided
  view of wider accumulators as the stitcher has them): torch's quotients, argmax and nodata (the GPU's path, and
  the CPU's before :mod:`aerialmtl.inference.stitch_kernel`) against the compiled kernel, median of 9, with
  ``--threads`` torch threads; the two maps are checked equal.
* ``--shared-cpu``: the default ``predict`` (OpenVINO, auto threads and streams) against ``--engine torch
  --precision fp32`` on the full D3-Net, ``--size``² raster, T = 1, run in turn (default, torch, default,
  ...) while ``--busy`` (default ``0,1,3``) extra busy-loop processes hold cores: the issue's "load 1, 2
  and 4 on 2 cores" on a machine quiet otherwise. Each row has the load average before and after.

Usage::

    python bench/predict.py --engines --size 2048 --engine-mc 1,8
    python bench/predict.py --speed --components --baseline --rss
    python bench/predict.py --pipeline --pipeline-cases 8192:1,4096:30
    python bench/predict.py --pipeline --pipeline-cases 8192:1 --pipeline-head-bias drawn --pipeline-against /tmp/base
    python bench/predict.py --startup --tmp DIR
    python bench/predict.py --shared-cpu --size 2048 --busy 0,1,3 --tmp DIR
    python bench/predict.py --alone --size 2048 --tmp DIR
    python bench/predict.py --class-map --size 1024 --threads 1
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
from typing import cast

# As the CLI does (aerialmtl/cli): OpenMP threads sleep instead of spinning, or in-process timings of torch on
# a shared CPU come out several times too slow (bench/RESULTS.md, CPU engines).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import rasterio  # noqa: E402
import torch  # noqa: E402
from affine import Affine  # noqa: E402
from rasterio.windows import Window  # noqa: E402

from aerialmtl.classes import ClassDef, ClassScheme  # noqa: E402
from aerialmtl.formats.checkpoint import ModelMeta  # noqa: E402
from aerialmtl.inference.predict import predict_raster  # noqa: E402
from aerialmtl.models.config import ModelConfig  # noqa: E402
from aerialmtl.models.d3net import D3Net  # noqa: E402
from aerialmtl.models.mc_dropout import mc_dropout_mode  # noqa: E402

SMALL = dict(growth_rate=12, block_config=(2, 4, 8, 6), num_init_features=32)


def make_model(kind: str, k: int = 20) -> tuple[D3Net, ModelMeta]:
    torch.manual_seed(0)
    arch = {"small": SMALL, "null": NULL}.get(kind, {})
    cfg = ModelConfig(num_classes=k, **arch)  # type: ignore[arg-type]
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
def gemm_ceiling(dtype: torch.dtype, n: int = 2048, reps: int = 5) -> float:
    """GFLOP/s of an n×n×n matrix product in ``dtype`` on this CPU (best of ``reps``)."""
    a, b = torch.randn(n, n).to(dtype), torch.randn(n, n).to(dtype)
    a @ b
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t0)
    return 2 * n**3 / best / 1e9


def model_flops_per_px(model: torch.nn.Module, size: int = 512) -> float:
    from torch.utils.flop_counter import FlopCounterMode

    with torch.no_grad(), FlopCounterMode(display=False) as fc:
        model(torch.randn(1, 3, size, size))
    return fc.get_total_flops() / size**2


def bench_speed(size: int, precisions: list[str], tmp: Path) -> dict:
    model, meta = make_model("full")
    src = synthetic_raster(tmp / "speed.tif", size, size)
    runs = []
    for prec in precisions:
        res = predict_raster(src, (model, meta), tmp / "speed_out", mc=1, precision=prec,  # type: ignore[arg-type]
                             progress=False, overwrite=True)
        model_mpx = res.overlap_factor * size * size / 1e6 / res.timings["model"]
        runs.append({"precision": prec, "mpx_per_s": res.megapixels_per_s, "model_mpx_per_s_computed": model_mpx,
                     "timings_s": res.timings, "load_avg": load_avg()})
        print(json.dumps(runs[-1]), flush=True)
    flops = model_flops_per_px(model)
    return {"part": "speed", "model": "full D3-Net (DenseNet-121, 20 classes)", "size": size, "T": 1,
            "tile": 1024, "overlap_factor": res.overlap_factor, "mflop_per_px": flops / 1e6,
            "gemm_gflops": {"fp32": gemm_ceiling(torch.float32), "bf16": gemm_ceiling(torch.bfloat16)},
            "runs": runs}


def bench_components(reps: int = 3) -> dict:
    """Seconds per megapixel of the full model's encoder and of one decoder sample (fp32, channels_last)."""
    model, _ = make_model("full")
    model = model.to(memory_format=torch.channels_last)
    x = torch.randn(1, 3, 512, 512).contiguous(memory_format=torch.channels_last)
    px = 512 * 512 / 1e6
    with torch.inference_mode(), mc_dropout_mode(model):
        feats = model.encode(x)
        model.decode(feats)
        t0 = time.perf_counter()
        for _ in range(reps):
            feats = model.encode(x)
        enc = (time.perf_counter() - t0) / reps / px
        t0 = time.perf_counter()
        for _ in range(reps):
            model.decode(feats)
        dec = (time.perf_counter() - t0) / reps / px
    t = 30

    def ratio(base_overlap: float, ours_overlap: float) -> float:
        return base_overlap * t * (enc + dec) / (ours_overlap * (enc + t * dec))

    return {"part": "components", "model": "full", "encoder_s_per_mpx": enc, "decoder_sample_s_per_mpx": dec,
            "predicted_speedup_T30": {"large raster (baseline 4x, ours 1.14x)": ratio(4.0, 1.14),
                                      "2048² (baseline 2.25x, ours 1.30x)": ratio(2.25, 1.30)},
            "load_avg": load_avg()}


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
    res = predict_raster(src, (model, meta), tmp / "base_out", mc=samples, progress=False, overwrite=True)
    t_ours = time.perf_counter() - t0
    with rasterio.open(res.files["height"]) as s:
        ours = s.read(1)
    return {"part": "baseline", "model": kind, "size": size, "T": samples, "baseline_s": t_base, "ours_s": t_ours,
            "speedup": t_base / t_ours, "mean_abs_height_diff_m": float(np.abs(ours - base).mean()),
            "mean_abs_height_m": float(np.abs(base).mean()), "overlap_factor": res.overlap_factor,
            "load_avg": load_avg()}


# ---- (c) peak RSS ------------------------------------------------------------------------------
def rss_child(width: int, height: int, tmp: Path, kind: str = "small", batch: str = "2") -> None:
    """Predict one raster; print peak RSS overall and per phase (window loop vs COG conversion)."""
    import threading

    import aerialmtl.inference.writer as writer_mod

    torch.set_num_threads(2)
    phase = ["setup"]
    peaks: dict[str, float] = {}

    def sample() -> None:
        while True:
            with open("/proc/self/status") as f:
                rss = next(int(line.split()[1]) / 1024 for line in f if line.startswith("VmRSS"))
            peaks[phase[0]] = max(peaks.get(phase[0], 0.0), rss)
            time.sleep(0.1)

    threading.Thread(target=sample, daemon=True).start()
    convert = writer_mod.PredictionWriter.convert

    def convert_phase(self, strips=()):  # type: ignore[no-untyped-def]
        phase[0] = "commit (COG)"
        return convert(self, strips)

    writer_mod.PredictionWriter.convert = convert_phase  # type: ignore[method-assign]
    model, meta = make_model(kind)
    src = tmp / f"rss_{width}x{height}.tif"
    if not src.exists():
        synthetic_raster(src, width, height)
    phase[0] = "window loop"
    t0 = time.perf_counter()
    res = predict_raster(src, (model, meta), tmp / f"rss_out_{width}x{height}", mc=1, progress=False,
                         overwrite=True, batch_size=batch if batch == "auto" else int(batch))  # type: ignore[arg-type]
    print(json.dumps({"width": width, "height": height, "mpx": width * height / 1e6,
                      "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "phase_peak_rss_mb": {k: round(v) for k, v in peaks.items()},
                      "seconds": time.perf_counter() - t0, "mpx_per_s": res.megapixels_per_s}))


def bench_rss(sizes: list[tuple[int, int]], tmp: Path, kind: str = "small", batch: str = "2") -> dict:
    runs = []
    for w, h in sizes:
        out = subprocess.run([sys.executable, __file__, "--rss-child", f"{w}x{h}", "--tmp", str(tmp),
                              "--rss-model", kind, "--rss-batch", batch], check=True, capture_output=True, text=True)
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(json.dumps(runs[-1]), flush=True)
    return {"part": "rss", "model": kind, "batch_size": batch, "runs": runs,
            "ratio_to_first": [r["max_rss_mb"] / runs[0]["max_rss_mb"] for r in runs], "load_avg": load_avg()}


# ---- (d) the pipeline around a near-null model, through the CLI ---------------------------------
NULL = dict(growth_rate=1, block_config=(1, 1, 1, 1), num_init_features=2, bn_size=1)


def cpu_name() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        return next(line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name"))
    except (OSError, subprocess.CalledProcessError, StopIteration):  # pragma: no cover - not Linux
        return "unknown CPU"


def bench_pipeline(cases: list[tuple[int, int]], extra: list[str], tmp: Path, cache: Path,
                   head_bias: str = "zero", against: Path | None = None, pairs: int = 1) -> dict:
    """Rasters are kept in ``cache`` (``--tmp``) between invocations; outputs go to ``tmp``. With ``against``
    (another checkout's root, e.g. main's), each case runs ``pairs`` times as this checkout then that one, back
    to back, and the layers of the last pair are compared (byte for byte, and their decoded pixels).
    """
    from aerialmtl.formats.checkpoint import save_checkpoint

    torch.manual_seed(0)
    k = 20
    cfg = ModelConfig(num_classes=k, **NULL)  # type: ignore[arg-type]
    scheme = ClassScheme("bench", tuple(ClassDef(i + 1, f"c{i}", (i * 12 % 256, 100, 200)) for i in range(k)))
    meta = ModelMeta(cfg, scheme, (1, 2, 3), (110.0, 110.0, 100.0), (45.0, 45.0, 45.0), 0.5)
    ckpt = tmp / "null.pt"
    model = D3Net(cfg).eval()
    if head_bias == "drawn":  # as a trained head has (the module docstring says why it matters)
        gen = torch.Generator().manual_seed(1)
        with torch.no_grad():
            for head in model.heads.values():
                bias = cast(torch.nn.Conv2d, getattr(head, "head")).bias  # noqa: B009
                assert bias is not None
                bias.copy_(torch.randn(tuple(bias.shape), generator=gen) * 0.5)
    save_checkpoint(ckpt, model, meta)
    here = Path(__file__).resolve().parents[1]
    sides = [("this", here)] + ([("against", against.resolve())] if against is not None else [])
    runs = []
    for size, samples in cases:
        src = cache / f"pipe_{size}.tif"
        if not src.exists():
            synthetic_raster(src, size, size)
        for rep in range(pairs if against is not None else 1):
            for label, root in sides:
                out = tmp / f"pipe_out_{size}_{samples}_{label}"
                runs.append({"code": label, "root": str(root), "rep": rep,
                             **_pipeline_run(root, src, ckpt, out, size, samples, extra)})
                print(json.dumps(runs[-1]), flush=True)
        if against is not None:
            same = _same_layers(tmp / f"pipe_out_{size}_{samples}_this", tmp / f"pipe_out_{size}_{samples}_against")
            runs.append({"size": size, "T": samples, "layers_this_vs_against": same})
            print(json.dumps(runs[-1]), flush=True)
    return {"part": "pipeline", "model": "near-null D3-Net (growth 1, blocks 1-1-1-1, 2 stem, bn_size 1, 20 classes)",
            "head_bias": head_bias,
            "cpu": cpu_name(), "runs": runs}


def _pipeline_run(root: Path, src: Path, ckpt: Path, out: Path, size: int, samples: int, extra: list[str]) -> dict:
    """One ``python -m aerialmtl predict`` of the code at ``root``: wall, CPU seconds, peak RSS, stage timings."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    cmd = [sys.executable, "-m", "aerialmtl", "predict", str(src), "--model", str(ckpt), "--out", str(out),
           "--mc", str(samples), "--quiet", "--overwrite", *extra]
    load_before = load_avg()
    t0 = time.perf_counter()
    # run from ``root``: ``python -m`` puts the working directory first on sys.path, before PYTHONPATH
    proc = subprocess.Popen(cmd, env=env, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    stdout, stderr = proc.stdout.read(), proc.stderr.read()  # type: ignore[union-attr]
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"predict failed ({proc.returncode}): {stderr.strip()[-2000:]}")
    info = json.loads((out / "prediction.json").read_text())
    return {"size": size, "T": samples, "wall_s": round(wall, 2), "mpx_per_s": size * size / 1e6 / wall,
            "cpu_s": round(usage.ru_utime + usage.ru_stime, 1), "peak_rss_mb": round(usage.ru_maxrss / 1024),
            "timings_s": info.get("timings_s"), "engine": info.get("engine"), "precision": info.get("precision"),
            "cli_extra": extra, "load_avg_before": load_before, "load_avg_after": load_avg(),
            "stdout": stdout.strip().splitlines()[-1:]}


def _same_layers(a: Path, b: Path) -> dict:
    """Per layer of two prediction folders: whether the files are byte-identical, and the largest difference of
    their decoded pixels (0 when equal).
    """
    import hashlib

    out = {}
    files = json.loads((a / "prediction.json").read_text())["files"]
    for name, fname in files.items():
        if not fname.endswith(".tif"):
            continue
        fa, fb = a / fname, b / fname
        same_bytes = hashlib.sha256(fa.read_bytes()).digest() == hashlib.sha256(fb.read_bytes()).digest()
        with rasterio.open(fa) as x, rasterio.open(fb) as y:
            da, db = x.read(), y.read()
        diff = float(np.nanmax(np.abs(da.astype(np.float64) - db.astype(np.float64)))) if da.size else 0.0
        out[name] = {"bytes_equal": same_bytes, "pixels_equal": bool(np.array_equal(da, db, equal_nan=True)),
                     "max_abs_diff": diff}
    return out


def bench_model_alone(size: int = 1024, reps: int = 2) -> list[dict]:
    """The full model alone on one ``size``² window per engine and precision: seconds, Mpx/s, GFLOP/s."""
    from aerialmtl import runtime
    from aerialmtl.inference.runner import ModelRunner
    from aerialmtl.inference.settings import PredictSettings, ResolvedSettings

    model, meta = make_model("full")
    flops = model_flops_per_px(model, 256)
    x = torch.randn(1, 3, size, size).contiguous(memory_format=torch.channels_last)
    cases = [("torch", "fp32"), ("openvino", "fp32")]
    if runtime.native_bf16(torch.device("cpu")):
        cases.append(("openvino", "bf16"))
    out = []
    for engine, precision in cases:
        settings = PredictSettings(mc=1, precision=precision, engine=engine)  # type: ignore[arg-type]
        resolved = ResolvedSettings(torch.device("cpu"), engine, precision, runtime.resolve_threads(), 1)  # type: ignore[arg-type]
        runner = ModelRunner(model, meta, settings, resolved)
        runner(x, [0])  # conversion, compilation, warm-up
        best = float("inf")
        for _ in range(reps):
            t0 = time.perf_counter()
            runner(x, [0])
            best = min(best, time.perf_counter() - t0)
        out.append({"engine": engine, "precision": precision, "window": size, "s": round(best, 3),
                    "mpx_per_s": size * size / 1e6 / best, "gflops": flops * size * size / best / 1e9,
                    "load_avg": load_avg()})
        print(json.dumps(out[-1]), flush=True)
    return out


def bench_engines(size: int, mcs: list[int], tmp: Path, cache: Path) -> dict:
    """See the module docstring (``--engines``)."""
    from aerialmtl import runtime
    from aerialmtl.formats.checkpoint import save_checkpoint

    model, meta = make_model("full")
    ckpt = tmp / "full.pt"
    save_checkpoint(ckpt, model, meta)
    src = cache / f"engines_{size}.tif"
    if not src.exists():
        synthetic_raster(src, size, size)
    ov_cache = tmp / "openvino-cache"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]),
           "AERIALMTL_OPENVINO_CACHE": str(ov_cache)}
    result: dict = {"part": "engines", "model": "full D3-Net (DenseNet-121, 20 classes, untrained)", "size": size,
                    "cpu": cpu_name(), "bf16_flags": list(runtime.cpu_bf16_flags()),
                    "mflop_per_px": model_flops_per_px(model, 256) / 1e6,
                    "gemm_gflops": {"fp32": gemm_ceiling(torch.float32), "bf16": gemm_ceiling(torch.bfloat16)}}
    print(json.dumps(result), flush=True)
    runs = []
    for samples in mcs:
        for label, extra in (("torch fp32", ["--engine", "torch", "--precision", "fp32"]),
                             ("auto, cold cache", []), ("auto, warm cache", [])):
            if label == "auto, cold cache" and ov_cache.exists():
                import shutil

                shutil.rmtree(ov_cache)
            out = tmp / "engines_out"
            cmd = [sys.executable, "-m", "aerialmtl", "predict", str(src), "--model", str(ckpt), "--out", str(out),
                   "--mc", str(samples), "--quiet", "--overwrite", *extra]
            load_before = load_avg()
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
            wall = time.perf_counter() - t0
            if proc.returncode != 0:
                raise RuntimeError(f"predict failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
            info = json.loads((out / "prediction.json").read_text())
            runs.append({"T": samples, "run": label, "engine": info.get("engine"), "precision": info["precision"],
                         "wall_s": round(wall, 1), "mpx_per_s": size * size / 1e6 / wall,
                         "timings_s": info.get("timings_s"), "overlap_factor": info["overlap_factor"],
                         "load_avg_before": load_before, "load_avg_after": load_avg()})
            print(json.dumps(runs[-1]), flush=True)
    result["runs"] = runs
    result["model_alone"] = bench_model_alone()
    return result


def _run_predict(args: list[str], env: dict[str, str]) -> float:
    """Wall seconds of ``python -m aerialmtl predict ARGS`` in a subprocess (raises on failure)."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "aerialmtl", "predict", *args], env=env, capture_output=True,
                          text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"predict failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
    return wall


def _full_checkpoint(cache: Path) -> tuple[Path, dict[str, str]]:
    """The full D3-Net's checkpoint in ``cache`` (kept, like its OpenVINO cache, between invocations: the
    same seed writes the same weights) and the environment of the predict subprocesses."""
    from aerialmtl.formats.checkpoint import save_checkpoint

    ckpt = cache / "full.pt"
    if not ckpt.exists():
        model, meta = make_model("full")
        save_checkpoint(ckpt, model, meta)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]),
           "AERIALMTL_OPENVINO_CACHE": str(cache / "openvino-cache")}
    return ckpt, env


def bench_startup(runs: int, tmp: Path, cache: Path) -> dict:
    """See the module docstring (``--startup``)."""
    ckpt, env = _full_checkpoint(cache)
    src = synthetic_raster(tmp / "startup.tif", 256, 256)
    args = [str(src), "--model", str(ckpt), "--out", str(tmp / "startup_out"), "--mc", "1", "--quiet", "--overwrite"]
    # fills the engine cache: named, since auto takes torch for a job this small while OpenVINO's cache is cold
    # (engine_choice.auto_engine) and would then never fill it
    _run_predict([*args, "--engine", "openvino"], env)
    load_before = load_avg()
    walls = sorted(_run_predict(args, env) for _ in range(runs))
    engine = json.loads((tmp / "startup_out" / "prediction.json").read_text())["engine"]
    res = {"part": "startup", "cpu": cpu_name(), "engine": engine, "runs": runs, "wall_s_min": round(walls[0], 2),
           "wall_s_median": round(walls[len(walls) // 2], 2), "wall_s_max": round(walls[-1], 2),
           "load_avg_before": load_before, "load_avg_after": load_avg()}
    print(json.dumps(res), flush=True)
    return res


def bench_alone(size: int, windows: int, cache: Path) -> dict:
    """See the module docstring (``--alone``)."""
    from collections import deque

    from aerialmtl.inference.predict import Predictor
    from aerialmtl.inference.windows import plan_windows

    ckpt, env = _full_checkpoint(cache)
    os.environ["AERIALMTL_OPENVINO_CACHE"] = env["AERIALMTL_OPENVINO_CACHE"]
    predictor = Predictor(ckpt, mc=1)
    plan = plan_windows(size, size, predictor.settings.window, predictor.settings.overlap)
    h, w = plan.rows.size, plan.cols.size
    x = torch.randn(1, 3, h, w).contiguous(memory_format=torch.channels_last)
    runner = predictor.runner
    runner.submit(x, [0]).result()  # compilation (or import from the cache) and warm-up
    load_before = load_avg()
    t0 = time.perf_counter()
    pending: deque = deque()
    for n in range(windows):
        pending.append(runner.submit(x, [n]))
        while len(pending) > runner.in_flight:
            pending.popleft().result()
    while pending:
        pending.popleft().result()
    dt = time.perf_counter() - t0
    res = {"part": "alone", "cpu": cpu_name(), "engine": runner.engine.name, "precision": predictor.precision,
           "threads": predictor.threads.as_dict(), "window": [h, w], "windows": windows, "s": round(dt, 3),
           "mpx_per_s": windows * h * w / 1e6 / dt, "load_avg_before": load_before, "load_avg_after": load_avg()}
    print(json.dumps(res), flush=True)
    return res


def _busy() -> None:  # pragma: no cover - a child process spinning until killed
    while True:
        pass


def bench_shared_cpu(size: int, busy: list[int], reps: int, tmp: Path, cache: Path) -> dict:
    """See the module docstring (``--shared-cpu``)."""
    import multiprocessing as mp

    ckpt, env = _full_checkpoint(cache)
    src = cache / f"engines_{size}.tif"
    if not src.exists():
        synthetic_raster(src, size, size)
    base = [str(src), "--model", str(ckpt), "--mc", "1", "--quiet", "--overwrite"]
    cases = {"default": [*base, "--out", str(tmp / "shared_a")],
             "torch fp32": [*base, "--out", str(tmp / "shared_b"), "--engine", "torch", "--precision", "fp32"]}
    _run_predict(cases["default"], env)  # fills the engine cache
    rows = []
    for extra in busy:
        procs = [mp.Process(target=_busy, daemon=True) for _ in range(extra)]
        for proc in procs:
            proc.start()
        try:
            for rep in range(reps):
                for label, args in cases.items():
                    load_before = load_avg()
                    wall = _run_predict(args, env)
                    rows.append({"busy_processes": extra, "run": label, "rep": rep, "wall_s": round(wall, 2),
                                 "load_avg_before": load_before, "load_avg_after": load_avg()})
                    print(json.dumps(rows[-1]), flush=True)
        finally:
            for proc in procs:
                proc.kill()
    return {"part": "shared-cpu", "cpu": cpu_name(), "size": size, "runs": rows}


def bench_class_map(size: int, k: int = 20, reps: int = 9) -> dict:
    """See the module docstring (``--class-map``)."""
    from aerialmtl.inference import stitch_kernel

    gen = torch.Generator().manual_seed(0)
    sums = -torch.log(torch.rand((size, size + 64, k), generator=gen))  # Dirichlet(1) sums, times the weights
    weight = torch.rand((size, size + 64), generator=gen) + 0.5
    weight[::7, ::5] = 0.0
    sums *= weight.unsqueeze(-1) / sums.sum(-1, keepdim=True)
    block_sums, block_weight = sums[:, 32:32 + size], weight[:, 32:32 + size]

    def with_torch() -> torch.Tensor:
        invalid = block_weight <= 0
        safe = torch.where(invalid, torch.ones_like(block_weight), block_weight)
        return torch.where(invalid, torch.tensor(255, dtype=torch.uint8),
                           (block_sums / safe.unsqueeze(-1)).argmax(-1).to(torch.uint8))

    out = torch.empty((size, size), dtype=torch.uint8)

    def with_kernel() -> torch.Tensor:
        stitch_kernel.finished_classes(block_sums, block_weight, 255, out)
        return out

    row: dict = {"part": "class-map", "cpu": cpu_name(), "size": size, "classes": k,
                 "threads": torch.get_num_threads(), "load_avg_before": load_avg()}
    for name, fn in (("torch_ms", with_torch), ("kernel_ms", with_kernel)):
        fn()
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        row[name] = round(sorted(times)[reps // 2] * 1000, 1)
    row["equal"] = bool(torch.equal(with_torch(), with_kernel()))
    row["load_avg_after"] = load_avg()
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--speed", action="store_true")
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--precisions", default="fp32", help="comma list of fp32, bf16, auto (speed part)")
    ap.add_argument("--components", action="store_true")
    ap.add_argument("--baseline", action="store_true")
    ap.add_argument("--baseline-size", type=int, default=2048)
    ap.add_argument("--baseline-model", choices=["small", "full"], default="small")
    ap.add_argument("--mc", type=int, default=30)
    ap.add_argument("--rss", action="store_true")
    ap.add_argument("--rss-sizes", default="2048x2048,2048x32768,32768x2048", help="WxH list, smallest first")
    ap.add_argument("--rss-model", choices=["small", "null"], default="small")
    ap.add_argument("--rss-batch", default="2", help="batch_size of the RSS runs (a number, or auto)")
    ap.add_argument("--rss-child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--pipeline", action="store_true")
    ap.add_argument("--pipeline-cases", default="8192:1,4096:30", help="comma list of SIZE:T")
    ap.add_argument("--pipeline-args", default="", help="extra predict CLI flags, space separated")
    ap.add_argument("--pipeline-head-bias", choices=["zero", "drawn"], default="zero")
    ap.add_argument("--pipeline-against", default=None,
                    help="another checkout's root (e.g. main's): run each case there and here in turn")
    ap.add_argument("--pipeline-pairs", type=int, default=2, help="pairs with --pipeline-against")
    ap.add_argument("--engines", action="store_true")
    ap.add_argument("--engine-mc", default="1,8", help="comma list of T (engines part)")
    ap.add_argument("--startup", action="store_true")
    ap.add_argument("--startup-runs", type=int, default=5)
    ap.add_argument("--alone", action="store_true")
    ap.add_argument("--alone-windows", type=int, default=8)
    ap.add_argument("--class-map", action="store_true")
    ap.add_argument("--shared-cpu", action="store_true")
    ap.add_argument("--busy", default="0,1,3", help="comma list of busy-loop processes (shared-cpu part)")
    ap.add_argument("--shared-reps", type=int, default=2)
    ap.add_argument("--tmp", default=None)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory(dir=args.tmp) as t:
        tmp = Path(args.tmp) if args.rss_child else Path(t)
        if args.rss_child:
            w, h = (int(v) for v in args.rss_child.split("x"))
            rss_child(w, h, tmp, args.rss_model, args.rss_batch)
            return
        if args.engines:
            cache = Path(args.tmp) if args.tmp else tmp
            mcs = [int(v) for v in args.engine_mc.split(",")]
            print(json.dumps(bench_engines(args.size, mcs, tmp, cache)), flush=True)
        if args.speed:
            print(json.dumps(bench_speed(args.size, args.precisions.split(","), tmp)), flush=True)
        if args.components:
            print(json.dumps(bench_components()), flush=True)
        if args.baseline:
            print(json.dumps(bench_baseline(args.baseline_size, args.baseline_model, args.mc, tmp)), flush=True)
        if args.pipeline:
            cases = [(int(a), int(b)) for a, b in (c.split(":") for c in args.pipeline_cases.split(","))]
            cache = Path(args.tmp) if args.tmp else tmp
            against = Path(args.pipeline_against) if args.pipeline_against else None
            result = bench_pipeline(cases, args.pipeline_args.split(), tmp, cache, args.pipeline_head_bias, against,
                                    args.pipeline_pairs)
            print(json.dumps(result), flush=True)
        if args.startup:
            cache = Path(args.tmp) if args.tmp else tmp
            print(json.dumps(bench_startup(args.startup_runs, tmp, cache)), flush=True)
        if args.alone:
            cache = Path(args.tmp) if args.tmp else tmp
            bench_alone(args.size, args.alone_windows, cache)
        if args.class_map:
            print(json.dumps(bench_class_map(args.size)), flush=True)
        if args.shared_cpu:
            cache = Path(args.tmp) if args.tmp else tmp
            busy = [int(v) for v in args.busy.split(",")]
            print(json.dumps(bench_shared_cpu(args.size, busy, args.shared_reps, tmp, cache)), flush=True)
        if args.rss:
            sizes = [tuple(int(v) for v in s.split("x")) for s in args.rss_sizes.split(",")]
            cache = Path(args.tmp) if args.tmp else tmp  # rasters kept there between invocations
            print(json.dumps(bench_rss(sizes, cache, args.rss_model, args.rss_batch)), flush=True)  # type: ignore[arg-type]


if __name__ == "__main__":
    main()
