"""Training throughput: the model's own step, and the data path that feeds it.

``--model`` (default): samples/s of forward + backward + Adam step (channels_last), fp32 and bf16
autocast, on random inputs/targets already on the device (losses as in training: L1 on valid heights +
cross-entropy). Warm-up steps are excluded from the timing.

``--data``: samples/s of the training data path alone (no model): batches of the train split exactly as
``aerialmtl train`` builds them (order, augmentation: flips, rot90, jitter), moved to the device, over a
tile folder of 320² patches cut from a synthetic town (made once under ``--workdir``). ``geotiff`` is the
per-sample path (every sample opens its GeoTIFFs, augments in numpy/torch in a DataLoader worker);
``cache`` is the training path since issue 11 (the decoded patch cache, batches augmented on the device);
the cache's first-use build is timed separately.

    python bench/train.py                       # model step: small (128², batch 8) and full (320², batch 2)
    python bench/train.py --configs small --steps 20 --threads 2
    python bench/train.py --data --workers 0 2 --batch 16 --batches 30
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from _training import town_tiles  # bench/ is the script's folder: on sys.path when run as `python bench/train.py`

from aerialmtl.training import losses
from aerialmtl.training.config import load_train_config

ROOT = Path(__file__).resolve().parents[1]
SETUPS = {  # name: (config file, patch size, batch size, classes)
    "small": ("configs/d3net_small_synth.yaml", 128, 8, 6),
    "full": ("configs/d3net_dfc2018.yaml", 320, 2, 20),
}


def bench(name: str, precision: str, steps: int, warmup: int, device: torch.device,
          compile_model: bool = False) -> dict[str, float]:
    from aerialmtl.models.d3net import D3Net

    path, size, batch, k = SETUPS[name]
    cfg = load_train_config(ROOT / path)
    model = D3Net(cfg.model.resolve(3, ("height", "classes"), k)).to(device).to(memory_format=torch.channels_last)
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=cfg.optim.lr, betas=cfg.optim.betas)
    net = torch.compile(model) if compile_model else model
    g = torch.Generator().manual_seed(0)
    x = torch.randn(batch, 3, size, size, generator=g).to(device).contiguous(memory_format=torch.channels_last)
    h = (torch.rand(batch, 1, size, size, generator=g) * 20).to(device)
    valid = torch.ones_like(h, dtype=torch.bool)
    c = torch.randint(0, k, (batch, size, size), generator=g).to(device)
    times = []
    for i in range(warmup + steps):
        t = time.perf_counter()
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16"):
            out = net(x)
        loss = losses.l1(out["height"].float(), h, valid) + losses.cross_entropy(out["classes"].float(), c)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        if i >= warmup:
            times.append(time.perf_counter() - t)
    per_step = sum(times) / len(times)
    params = sum(p.numel() for p in model.parameters())
    return {"params_M": params / 1e6, "patch": size, "batch": batch, "s_per_step": per_step,
            "samples_per_s": batch / per_step, "s_per_sample": per_step / batch}


# ---- data path ----------------------------------------------------------------------------------
class _Batches:
    """Batches of ``(index, seed)``: an epoch permutation seeded by (seed, epoch), as training orders them."""

    def __init__(self, n: int, batch: int, seed: int = 0) -> None:
        self.n, self.bs, self.seed = n, min(batch, n), seed

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        epoch = 0
        while True:
            perm = torch.randperm(self.n, generator=torch.Generator().manual_seed(self.seed * 7919 + epoch))
            for b in range(self.n // self.bs):
                yield [(int(perm[p]), epoch * 100003 + p) for p in range(b * self.bs, (b + 1) * self.bs)]
            epoch += 1


class _Seeded(torch.utils.data.Dataset):
    def __init__(self, base: torch.utils.data.Dataset, transform: object) -> None:
        self.base, self.transform = base, transform

    def __getitem__(self, item: tuple[int, int]) -> dict:
        index, seed = item
        return self.transform(self.base.load(index), torch.Generator().manual_seed(seed))  # type: ignore[operator]


def geotiff_loader(tiles: Path, batch: int, workers: int, device: torch.device) -> Iterator[dict]:
    """The per-sample GeoTIFF path (``aerialmtl train`` up to this change): PatchDataset + per-sample transforms."""
    from aerialmtl.data.dataset import PatchDataset
    from aerialmtl.data.transforms import build_train_transform

    ds = PatchDataset(tiles, "train")
    loader = torch.utils.data.DataLoader(
        _Seeded(ds, build_train_transform(True, True, True, None)), batch_sampler=_Batches(len(ds), batch),
        num_workers=workers, pin_memory=device.type == "cuda", persistent_workers=workers > 0)
    for b in loader:
        out = {}
        for k, v in b.items():
            if isinstance(v, torch.Tensor):
                v = v.to(device, non_blocking=True)
                if k == "image":
                    v = v.contiguous(memory_format=torch.channels_last)
            out[k] = v
        yield out


def cache_loader(tiles: Path, batch: int, workers: int, device: torch.device) -> Iterator[dict]:
    """The training data path as the trainer builds it: on a CPU one thread assembles finished batches from the
    patch cache; on a GPU compact batches from workers → device → normalise + augment there.
    """
    from aerialmtl.data.batches import CachedBatches, EpochOrder, RankBatchSampler, prepare_batch
    from aerialmtl.data.cache import PatchCache, ensure_patch_cache
    from aerialmtl.data.prefetch import AssembledBatches
    from aerialmtl.data.transforms import build_train_transform
    from aerialmtl.formats.tiles import TileFolderInfo, cache_dir

    info = TileFolderInfo.read(tiles)
    index = ensure_patch_cache(info, "train")
    transform = build_train_transform(True, True, True, None)
    mean = torch.tensor(info.mean, device=device)
    std = torch.tensor(info.std, device=device)
    cache = PatchCache(cache_dir(tiles), index)
    sampler = RankBatchSampler(EpochOrder(index.count, batch, 0), 0, 0, 0)
    loader: Any
    if device.type == "cpu":  # as the trainer does
        loader = AssembledBatches(cache, transform, info.tasks, sampler, mean, std)
    else:
        loader = torch.utils.data.DataLoader(
            CachedBatches(cache, transform, info.tasks), sampler=sampler, batch_size=None, num_workers=workers,
            pin_memory=True, generator=torch.Generator().manual_seed(0))
    for raw in loader:
        yield prepare_batch(raw, transform, mean, std, device)


def bench_cache_build(tiles: Path) -> None:
    """Time building the train split's cache from scratch (first use)."""
    import shutil

    from aerialmtl.data.cache import ensure_patch_cache
    from aerialmtl.formats.tiles import TileFolderInfo, cache_dir

    shutil.rmtree(cache_dir(tiles), ignore_errors=True)
    info = TileFolderInfo.read(tiles)
    t = time.perf_counter()
    index = ensure_patch_cache(info, "train")
    dt = time.perf_counter() - t
    size = sum(f.stat().st_size for f in cache_dir(tiles).glob("train.*.npy")) / 2**20
    print(f"cache build (train, {index.count} patches, 0 workers): {dt:.2f} s = {index.count / dt:.1f} patches/s, "
          f"{size:.1f} MiB on disk")


def bench_data(paths: list[str], tiles: Path, batch: int, workers: list[int], batches: int, warmup: int,
               device: torch.device) -> None:
    if "cache" in paths:
        bench_cache_build(tiles)
    print("| path | workers | batch | batches timed | s | samples/s |")
    print("|---|---|---|---|---|---|")
    for path in paths:
        for nw in workers:
            if path == "geotiff":
                it = geotiff_loader(tiles, batch, nw, device)
            elif path == "cache":
                it = cache_loader(tiles, batch, nw, device)
            else:
                raise SystemExit(f"unknown data path {path!r}")
            for _ in range(warmup):
                next(it)
            if device.type == "cuda":
                torch.cuda.synchronize()
            t = time.perf_counter()
            for _ in range(batches):
                b = next(it)
            if device.type == "cuda":
                torch.cuda.synchronize()
            dt = time.perf_counter() - t
            assert b["image"].shape[0] == batch
            print(f"| {path} | {nw} | {batch} | {batches} | {dt:.2f} | {batches * batch / dt:.1f} |", flush=True)
            del it


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", action="store_true", help="time the data path instead of the model step")
    ap.add_argument("--configs", nargs="+", default=["small", "full"], choices=list(SETUPS))
    ap.add_argument("--precisions", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16"])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--full-steps", type=int, default=3, help="timed steps for the full config (slow on CPU)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--compile", action="store_true", help="torch.compile the model (model step)")
    ap.add_argument("--paths", nargs="+", default=["geotiff", "cache"], choices=["geotiff", "cache"],
                    help="data paths to time (--data)")
    ap.add_argument("--workers", type=int, nargs="+", default=[0, 2], help="DataLoader workers (--data)")
    ap.add_argument("--batch", type=int, default=16, help="batch size (--data)")
    ap.add_argument("--batches", type=int, default=20, help="timed batches (--data)")
    ap.add_argument("--town", type=int, default=2560, help="synthetic town side in px (--data)")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/aerialmtl-bench-train"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    print(f"torch {torch.__version__}, device {device}, threads {torch.get_num_threads()}, "
          f"load average {os.getloadavg()}")
    if args.data:
        tiles = town_tiles(args.workdir, args.town, val=0.1)
        bench_data(args.paths, tiles, args.batch, args.workers, args.batches, args.warmup, device)
        print(f"load average at the end {os.getloadavg()}")
        return
    print("| config | params (M) | patch | batch | precision | s/step | samples/s | s/sample |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.configs:
        for prec in args.precisions:
            steps = args.full_steps if name == "full" and device.type == "cpu" else args.steps
            r = bench(name, prec, steps, args.warmup if name == "small" else 1, device, args.compile)
            print(f"| {name} | {r['params_M']:.2f} | {r['patch']}² | {r['batch']} | {prec} | {r['s_per_step']:.3f} | "
                  f"{r['samples_per_s']:.2f} | {r['s_per_sample']:.3f} |", flush=True)


if __name__ == "__main__":
    main()
