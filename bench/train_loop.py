"""The real training loop's speed against its model step alone, with the GPU's busy share and memory.

Runs :func:`aerialmtl.training.loop.train` (what ``aerialmtl train`` runs) with a config (default the paper's,
``configs/d3net_dfc2018.yaml``: DenseNet-121 D3-Net, batch 8, 2 workers, precision auto) on a synthetic town
tiled 320/160 (made once under ``--workdir``), and reports:

* the loop's samples/s over its training steps (the first ``--warmup`` steps excluded; validations, checkpoints
  and epoch ends included, as a user sees them), and the seconds spent in validation, calibration, the
  feature density and the sun fit (timed around the trainer's methods);
* the model step alone at the same batch, precision and memory format (forward, losses, weighting, backward,
  optimiser on one batch already on the device), and the ratio loop / step;
* on a CUDA GPU: its utilisation sampled by ``nvidia-smi`` every 250 ms (mean over the training steps, and
  over the whole call), the peak memory torch allocated and the most ``nvidia-smi`` saw used.

    python bench/train_loop.py                               # on the GPU: 300 steps of the paper config
    python bench/train_loop.py --device cpu --town 1024 --steps 6 --batch 2 --config configs/d3net_small_synth.yaml

Speed only: the run folder is thrown away.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _training import random_batch, town_tiles  # noqa: E402


class GpuSampler:
    """``nvidia-smi`` utilisation (%) and memory used (MiB) every ``ms`` milliseconds, with their times."""

    def __init__(self, ms: int = 250) -> None:
        self.samples: list[tuple[float, float, float]] = []
        self.proc: subprocess.Popen[str] | None = None
        if shutil.which("nvidia-smi") is None:
            return
        self.proc = subprocess.Popen(["nvidia-smi", "--id=0", "--query-gpu=utilization.gpu,memory.used",
                                      "--format=csv,noheader,nounits", f"-lms={ms}"],
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                util, mem = (float(x) for x in line.strip().split(","))
            except ValueError:
                continue
            self.samples.append((time.perf_counter(), util, mem))

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait()

    def mean_util(self, start: float = -1.0, end: float = float("inf")) -> float | None:
        values = [u for t, u, _ in self.samples if start <= t <= end]
        return sum(values) / len(values) if values else None

    def max_mem(self) -> float | None:
        return max((m for _, _, m in self.samples), default=None)


def timed(cls: Any, name: str, into: dict[str, float]) -> None:
    """Wrap ``cls.name`` (if it has one) so that the seconds spent in it add up in ``into[name]``."""
    real = getattr(cls, name, None)
    if real is None:
        return

    def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        t = time.perf_counter()
        try:
            return real(self, *args, **kwargs)
        finally:
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            into[name] = into.get(name, 0.0) + time.perf_counter() - t

    setattr(cls, name, wrapper)


def loop(args: argparse.Namespace, cfg: Any, tiles: Path, sampler: GpuSampler) -> dict[str, Any]:
    """Train and time it (see the module docstring)."""
    from aerialmtl.training.loop import train
    from aerialmtl.training.steploop import StepLoop
    from aerialmtl.training.trainer import Trainer

    spent: dict[str, float] = {}
    for name in ("validate", "calibrate", "familiarize", "fit_sun"):
        timed(Trainer, name, spent)
    stamps: list[float] = []
    real_step = StepLoop.train_step

    def stamped(self: Any, batch: dict[str, torch.Tensor]) -> Any:
        stamps.append(time.perf_counter())
        return real_step(self, batch)

    StepLoop.train_step = stamped  # type: ignore[method-assign]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        result = train(cfg, out_dir=Path(tmp) / "run", progress=False)
    wall = time.perf_counter() - t0
    StepLoop.train_step = real_step  # type: ignore[method-assign]
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    w = min(args.warmup, len(stamps) - 2)
    steps = len(stamps) - 1 - w
    span = stamps[-1] - stamps[w]  # from the start of step w + 1 to the start of the last step
    return {"steps": result.step, "batch": cfg.data.batch_size, "wall_s": wall, "span_s": span,
            "samples_per_s": steps * cfg.data.batch_size / span, "spent": spent, "stopped_by": result.stopped_by,
            "gpu_util_steps": sampler.mean_util(stamps[w], stamps[-1]),
            "gpu_util_call": sampler.mean_util(t0, t0 + wall)}


def model_step(args: argparse.Namespace, cfg: Any, tiles: Path) -> float:
    """Samples/s of the model's step alone at the loop's batch, precision and memory format."""
    from aerialmtl import runtime
    from aerialmtl.formats.tiles import TileFolderInfo
    from aerialmtl.training.objective import Objective
    from aerialmtl.training.setup import CPU_BF16_TRAINING, StepModule, build_model

    info = TileFolderInfo.read(tiles)
    k = info.classes.num_classes if info.classes is not None else None
    model_cfg = cfg.model.resolve(info.num_bands, info.tasks, k)
    ctx = runtime.Torchrun.start(cfg.device, runtime.COLLECTIVE_TIMEOUT, RuntimeError)
    device = ctx.device
    precision = runtime.resolve_precision(cfg.precision, device, cpu_bf16=CPU_BF16_TRAINING)
    parts = build_model(cfg, model_cfg, device, ctx)
    step = StepModule(parts.model, parts.weighting, Objective(cfg, tuple(model_cfg.tasks), None), device, precision,
                      compile=cfg.compile)
    b, s = cfg.data.batch_size, info.patch_size
    batch = random_batch(b, info.num_bands, s, k, device)
    parts.model.train()
    times = []
    for i in range(args.step_warmup + args.model_steps):
        t = time.perf_counter()
        total, _ = step(batch)
        parts.optimizer.zero_grad(set_to_none=True)
        total.backward()
        parts.optimizer.step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        if i >= args.step_warmup:
            times.append(time.perf_counter() - t)
    return b * len(times) / sum(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="configs/d3net_dfc2018.yaml")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--warmup", type=int, default=20, help="loop steps left out of the samples/s")
    ap.add_argument("--batch", type=int, default=None, help="data.batch_size [default: the config's]")
    ap.add_argument("--workers", type=int, default=None, help="data.num_workers [default: the config's]")
    ap.add_argument("--model-steps", type=int, default=20)
    ap.add_argument("--step-warmup", type=int, default=5)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--town", type=int, default=3072, help="synthetic town side (px); tiled 320 at --stride")
    ap.add_argument("--stride", type=int, default=160)
    ap.add_argument("--val", type=float, default=0.1, help="share of the town kept for validation")
    ap.add_argument("--workdir", default=os.environ.get("AERIALMTL_BENCH_DIR", "/tmp/aerialmtl-bench"))
    args = ap.parse_args()
    from aerialmtl.training.config import load_train_config

    t = time.perf_counter()
    tiles = town_tiles(Path(args.workdir), args.town, args.stride, args.val)
    print(f"tile folder: {tiles} ({time.perf_counter() - t:.0f} s)", flush=True)
    data: dict[str, Any] = {"dir": str(tiles)}
    if args.batch:
        data["batch_size"] = args.batch
    if args.workers is not None:
        data["num_workers"] = args.workers
    cfg = load_train_config(ROOT / args.config).with_overrides(
        model={"num_classes": None}, data=data, schedule={"max_steps": args.steps, "max_time_s": None},
        device=args.device)
    sampler = GpuSampler()
    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()
    try:
        r = loop(args, cfg, tiles, sampler)
        peak_loop = torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else None
        print(f"train loop ({args.config}, batch {r['batch']}, {r['steps']} steps, stopped by {r['stopped_by']}): "
              f"{r['samples_per_s']:.1f} samples/s over the steps after the first {args.warmup} "
              f"({r['span_s']:.1f} s); whole call {r['wall_s']:.1f} s", flush=True)
        share = {k: f"{v:.1f} s ({100 * v / r['wall_s']:.0f} %)" for k, v in r["spent"].items()}
        from aerialmtl.runtime import resolve_device
        from aerialmtl.training.sun_beside import beside_steps

        sun = ("fitted beside the steps: fit_sun is the wait for its process"
               if beside_steps(resolve_device(cfg.device).type) else "fitted after the steps")
        print(f"  of the call: {share}; the sun {sun}", flush=True)
        alone = model_step(args, cfg, tiles)
        print(f"model step alone, batch {r['batch']}: {alone:.1f} samples/s; loop / step = "
              f"{r['samples_per_s'] / alone:.2f}", flush=True)
        util = r["gpu_util_steps"]
        if util is not None:
            print(f"GPU utilisation (nvidia-smi every 250 ms): {util:.0f} % over the training steps, "
                  f"{r['gpu_util_call']:.0f} % over the whole call", flush=True)
        if peak_loop is not None:
            print(f"memory: {peak_loop:.0f} MiB peak allocated by torch in the loop; {sampler.max_mem()} MiB most "
                  f"used on the GPU (nvidia-smi)", flush=True)
    finally:
        sampler.stop()


if __name__ == "__main__":
    main()
