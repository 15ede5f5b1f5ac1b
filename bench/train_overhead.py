"""Host overhead of the training loop per step: ``aerialmtl train`` with a near-null model vs its bare step.

The D3-Net is replaced by a near-null network (one 1×1 convolution from the bands to the outputs: a few
dozen parameters), so what is left of a step's time is the loop around the model: the loader (on a CPU its
thread, assembling each batch from the patch cache; on a GPU the workers, the transfer and the augmentation
there), the losses,
the optimiser, the weight average (``--ema``), the learning-rate schedule, the loss window, logging and the
per-epoch checkpoints. The loop runs through :func:`aerialmtl.training.loop.train` (the library call behind
``aerialmtl train``), on a tile folder of 320² patches cut from a synthetic town (made once under
``--workdir``); its ms/step is timed between the starts of its steps (the first ``--skip`` excluded), as wall
time and as CPU time of the main process (its threads included) and of any DataLoader workers (CPU time depends
less on what else runs on a shared machine than wall time, but counts threads that spin while they wait).

The bare step is the same near-null network's forward + losses + weighting + backward + Adam
(:class:`~aerialmtl.training.setup.StepModule`) on the loop's first batch, already on the device: what no loop can
avoid. The two are measured in turn ``--rounds`` times (the machine's state drifts; the median is printed).

    python bench/train_overhead.py                       # batch 32, 320² patches, 60 steps
    python bench/train_overhead.py --rounds 4            # loop and bare step in turn, 4 times
    python bench/train_overhead.py --ema 0.99 --steps 40
    python bench/train_overhead.py --profile             # cProfile of the loop's main process (top 25)

It also prints the data path's CPU time per batch on one thread: on a CPU run, what the loader's thread spends
(:class:`~aerialmtl.data.prefetch.AssembledBatches`; it shares the cores with the step, so that time is host
overhead unless the step leaves a core idle), and, for comparison, a GPU run's worker gather and torch's
finishing of the same batch on the CPU.

Speed only: the run folder and its weights are thrown away.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
from torch import nn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
from _training import town_tiles  # noqa: E402


class NullNet(nn.Module):
    """A 1×1 convolution from the input bands to every output D3-Net has for ``cfg`` (same keys and shapes)."""

    #: instances made (the loop's check that it measured this network, not the D3-Net)
    built = 0

    def __init__(self, cfg: Any) -> None:
        super().__init__()
        NullNet.built += 1
        self.tasks = tuple(cfg.tasks)
        self.k = int(cfg.num_classes or 0) if "classes" in self.tasks else 0
        self.aleatoric = bool(getattr(cfg, "aleatoric", False))
        out = (2 if self.aleatoric else 1) * ("height" in self.tasks) + self.k
        self.conv = nn.Conv2d(int(cfg.in_channels), out, 1)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        y = self.conv(x)
        out: dict[str, torch.Tensor] = {}
        i = 0
        if "height" in self.tasks:
            out["height"] = y[:, :1]
            i = 1
            if self.aleatoric:
                out["height_scale"] = nn.functional.softplus(y[:, 1:2]) + 1e-3
                i = 2
        if self.k:
            out["classes"] = y[:, i:i + self.k]
        return out


def config(args: argparse.Namespace, tiles: Path) -> Any:
    from aerialmtl.training.config import load_train_config

    cfg = load_train_config(ROOT / args.config)
    return cfg.with_overrides(
        model={"num_classes": None},
        data={"batch_size": args.batch, "num_workers": args.workers, "dir": str(tiles)},
        optim={"ema": args.ema},
        schedule={"max_steps": args.steps, "epochs": 10_000, "log_every": args.log_every,
                  "lr_schedule": args.lr_schedule, "warmup_steps": args.warmup},
        calibration={"enabled": False}, familiarity={"enabled": False}, sun={"enabled": False},
        device=args.device, precision="fp32" if args.device == "cpu" else "auto", seed=0)


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of this process's live children (the DataLoader workers), from /proc."""
    import multiprocessing

    ticks = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for child in multiprocessing.active_children():
        try:
            fields = Path(f"/proc/{child.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / ticks
    return total


def loop_ms(args: argparse.Namespace, tiles: Path) -> tuple[float, float, int, int]:
    """Wall and CPU (main process + workers) ms per step of ``train`` with the near-null model, over the steps
    after the first ``--skip``; the steps timed; steps per epoch.
    """
    import aerialmtl.training.setup as setup
    from aerialmtl.formats.tiles import read_manifest
    from aerialmtl.training.loop import train

    try:
        from aerialmtl.training.steploop import StepLoop
    except ImportError:  # before the shared loop (to measure an older version)
        from aerialmtl.training.trainer import Trainer as StepLoop  # type: ignore[assignment]

    # the name train's model assembly calls (setup imports D3Net at module level; patching aerialmtl.models.d3net
    # alone left the real network in, and the "overhead" was the D3-Net's own step)
    real, real_step = setup.D3Net, StepLoop.train_step
    stamps: list[tuple[float, float]] = []

    def stamped(self: Any, batch: dict[str, torch.Tensor]) -> Any:
        stamps.append((time.perf_counter(), time.process_time() + _children_cpu_s()))
        return real_step(self, batch)

    setup.D3Net = NullNet  # type: ignore[misc,assignment]
    NullNet.built = 0
    StepLoop.train_step = stamped  # type: ignore[method-assign]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            cfg = config(args, tiles)
            if args.profile:
                import cProfile
                import pstats

                prof = cProfile.Profile()
                prof.enable()
            result = train(cfg, out_dir=Path(tmp) / "run", progress=False)
            if args.profile:
                prof.disable()
                pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    finally:
        setup.D3Net, StepLoop.train_step = real, real_step  # type: ignore[misc,method-assign]
    assert result.step == args.steps
    if NullNet.built == 0:
        raise SystemExit("the loop did not build the near-null model: train's model assembly no longer calls "
                         "aerialmtl.training.setup.D3Net; patch the name it calls now")
    w = min(args.skip, len(stamps) - 2)
    n = len(stamps) - 1 - w
    (t0, c0), (t1, c1) = stamps[w], stamps[-1]
    per_epoch = len(read_manifest(tiles, "train")) // args.batch
    return 1000 * (t1 - t0) / n, 1000 * (c1 - c0) / n, n, per_epoch


def first_batch(args: argparse.Namespace, tiles: Path, device: torch.device) -> dict[str, torch.Tensor]:
    """The loop's first batch, finished (the same pixels the loop's step sees: invalid heights, unlabelled classes)."""
    from aerialmtl.data.batches import CachedBatches, EpochOrder, prepare_batch
    from aerialmtl.data.cache import PatchCache, ensure_patch_cache
    from aerialmtl.data.transforms import build_train_transform
    from aerialmtl.formats.tiles import TileFolderInfo, cache_dir

    cfg = config(args, tiles)
    info = TileFolderInfo.read(tiles)
    index = ensure_patch_cache(info, "train")
    transform = build_train_transform(cfg.data.flips, cfg.data.rot90, cfg.data.jitter, cfg.data.crop_size)
    mean, std = torch.tensor(info.mean), torch.tensor(info.std)
    spec = next(EpochOrder(index.count, args.batch, cfg.seed).batches(0, 0, 0))
    batch = prepare_batch(CachedBatches(PatchCache(cache_dir(tiles), index), transform, info.tasks)[spec], transform,
                          mean, std, torch.device("cpu"))
    return {k: v.to(device) for k, v in batch.items()}


def bare_ms(args: argparse.Namespace, tiles: Path, steps: int) -> tuple[float, float]:
    """Wall and CPU ms/step of the near-null model's step alone on the loop's first batch, already on the device."""
    from aerialmtl.formats.tiles import TileFolderInfo
    from aerialmtl.training.objective import Objective
    from aerialmtl.training.setup import StepModule, build_optimizer
    from aerialmtl.training.weighting import build_weighting

    cfg = config(args, tiles)
    info = TileFolderInfo.read(tiles)
    k = info.classes.num_classes if info.classes is not None else None
    model_cfg = cfg.model.resolve(info.num_bands, info.tasks, k)
    device = torch.device("cuda" if args.device in ("cuda", "auto") and torch.cuda.is_available() else "cpu")
    model = NullNet(model_cfg).to(device).to(memory_format=torch.channels_last)
    weighting = build_weighting(cfg.weighting.method, list(model_cfg.tasks)).to(device)
    opt = build_optimizer(cfg.optim, model, weighting)
    step = StepModule(model, weighting, Objective(cfg, tuple(model_cfg.tasks), None), device, "fp32")
    batch = first_batch(args, tiles, device)
    times, cpu = [], []
    for i in range(steps + 3):
        t, c = time.perf_counter(), time.process_time()
        total, _ = step(batch)
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        if i >= 3:
            times.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c)
    return 1000 * sum(times) / len(times), 1000 * sum(cpu) / len(cpu)


def data_parts_ms(args: argparse.Namespace, tiles: Path, batches: int = 5) -> dict[str, float]:
    """CPU ms per batch of the data path, one thread: on a CPU, what the loader's thread spends per batch
    (:meth:`~aerialmtl.data.prefetch.AssembledBatches.assemble`: parameters, and the one pass from the cache to the
    finished batch); the worker path a GPU run takes (gathering the compact patches, then finishing them with torch
    on the CPU), for comparison.
    """
    from aerialmtl.data.batches import CachedBatches, EpochOrder, finish_on_device
    from aerialmtl.data.cache import PatchCache, ensure_patch_cache
    from aerialmtl.data.prefetch import AssembledBatches
    from aerialmtl.data.transforms import build_train_transform
    from aerialmtl.formats.tiles import TileFolderInfo, cache_dir

    cfg = config(args, tiles)
    info = TileFolderInfo.read(tiles)
    index = ensure_patch_cache(info, "train")
    transform = build_train_transform(cfg.data.flips, cfg.data.rot90, cfg.data.jitter, cfg.data.crop_size)
    mean, std = torch.tensor(info.mean), torch.tensor(info.std)
    cache = PatchCache(cache_dir(tiles), index)
    ds = CachedBatches(cache, transform, info.tasks)
    assembled = AssembledBatches(cache, transform, info.tasks, [], mean, std)
    specs = EpochOrder(index.count, args.batch, 0).batches(0, 0, 0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    times: dict[str, list[float]] = {"assemble": [], "gather": [], "finish": []}
    rings: dict[Any, Any] = {}
    turns: dict[Any, int] = {}
    try:
        for i in range(batches + 1):
            spec = next(specs)
            t = time.process_time()
            assembled.assemble(spec, rings, turns)
            t1 = time.process_time()
            raw = ds[spec]
            t2 = time.process_time()
            finish_on_device(raw["data"], raw["params"], transform, mean, std)
            t3 = time.process_time()
            if i:  # the first compiles or loads the kernel
                times["assemble"].append(t1 - t)
                times["gather"].append(t2 - t1)
                times["finish"].append(t3 - t2)
    finally:
        torch.set_num_threads(threads)
    return {k: 1000 * sorted(v)[len(v) // 2] for k, v in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="configs/d3net_dfc2018.yaml")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--workers", type=int, default=2, help="data.num_workers (a GPU run's loader processes)")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--log-every", type=int, default=10)
    ap.add_argument("--skip", type=int, default=5, help="first loop steps left out of the timing")
    ap.add_argument("--ema", type=float, default=None)
    ap.add_argument("--lr-schedule", default="constant", choices=("constant", "cosine"))
    ap.add_argument("--warmup", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--town", type=int, default=3072, help="synthetic town side (px); tiled 320 at --stride")
    ap.add_argument("--stride", type=int, default=160)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--workdir", default=os.environ.get("AERIALMTL_BENCH_DIR", "/tmp/aerialmtl-bench"))
    ap.add_argument("--profile", action="store_true", help="cProfile the loop's main process")
    ap.add_argument("--rounds", type=int, default=1, help="loop and bare step measured in turn this many times")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    tiles = town_tiles(Path(args.workdir), args.town, args.stride)
    walls, cpus = [], []
    for r in range(args.rounds):  # loop and bare step in turn: the machine's state drifts between them
        ms, cpu, timed, per_epoch = loop_ms(args, tiles)
        bare, bare_cpu = bare_ms(args, tiles, min(timed, 20))
        walls.append(ms - bare)
        cpus.append(cpu - bare_cpu)
        load = " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else "?"
        print(f"round {r + 1}: train loop, near-null model: {ms:.1f} ms/step wall, {cpu:.1f} ms/step CPU (main + "
              f"workers) over {timed} steps ({per_epoch} steps/epoch; batch {args.batch} of 320², "
              f"{args.workers} workers, ema {args.ema}, {args.device}, torch threads {torch.get_num_threads()})")
        print(f"round {r + 1}: bare step, near-null model:  {bare:.1f} ms/step wall, {bare_cpu:.1f} ms/step CPU")
        print(f"round {r + 1}: loop overhead:               {ms - bare:.1f} ms/step wall, {cpu - bare_cpu:.1f} "
              f"ms/step CPU   (load {load})")
    if args.rounds > 1:
        print(f"loop overhead, median of {args.rounds} rounds: {statistics.median(walls):.1f} ms/step wall, "
              f"{statistics.median(cpus):.1f} ms/step CPU")
    parts = data_parts_ms(args, tiles)
    print(f"data path, CPU time per batch on one thread: the CPU loader's thread {parts['assemble']:.1f} ms "
          f"(cache → finished batch, one pass); a GPU run's workers would gather {parts['gather']:.1f} ms, and "
          f"torch finishing on a CPU {parts['finish']:.1f} ms")


if __name__ == "__main__":
    main()
