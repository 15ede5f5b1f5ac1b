"""Training throughput: samples/s of forward + backward + Adam step (channels_last), fp32 and bf16 autocast.

Random inputs/targets of the stated patch size (no data loading, which the DataLoader workers overlap),
losses as in training (L1 on valid heights + cross-entropy). Warm-up steps are excluded from the timing.

    python bench/train.py                       # small (128², batch 8) and full (320², batch 2) configs
    python bench/train.py --configs small --steps 20 --threads 2
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import torch

from aerialmtl.training import losses
from aerialmtl.training.config import load_train_config

ROOT = Path(__file__).resolve().parents[1]
SETUPS = {  # name: (config file, patch size, batch size, classes)
    "small": ("configs/d3net_small_synth.yaml", 128, 8, 6),
    "full": ("configs/d3net_dfc2018.yaml", 320, 2, 20),
}


def bench(name: str, precision: str, steps: int, warmup: int, device: torch.device) -> dict[str, float]:
    from aerialmtl.models.d3net import D3Net

    path, size, batch, k = SETUPS[name]
    cfg = load_train_config(ROOT / path)
    model = D3Net(cfg.model.resolve(3, ("height", "classes"), k)).to(device).to(memory_format=torch.channels_last)
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=cfg.optim.lr, betas=cfg.optim.betas)
    g = torch.Generator().manual_seed(0)
    x = torch.randn(batch, 3, size, size, generator=g).to(device).contiguous(memory_format=torch.channels_last)
    h = (torch.rand(batch, 1, size, size, generator=g) * 20).to(device)
    valid = torch.ones_like(h, dtype=torch.bool)
    c = torch.randint(0, k, (batch, size, size), generator=g).to(device)
    times = []
    for i in range(warmup + steps):
        t = time.perf_counter()
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16"):
            out = model(x)
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="+", default=["small", "full"], choices=list(SETUPS))
    ap.add_argument("--precisions", nargs="+", default=["fp32", "bf16"], choices=["fp32", "bf16"])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--full-steps", type=int, default=3, help="timed steps for the full config (slow on CPU)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    print(f"torch {torch.__version__}, device {device}, threads {torch.get_num_threads()}, "
          f"load average {os.getloadavg()}")
    print("| config | params (M) | patch | batch | precision | s/step | samples/s | s/sample |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.configs:
        for prec in args.precisions:
            steps = args.full_steps if name == "full" and device.type == "cpu" else args.steps
            r = bench(name, prec, steps, args.warmup if name == "small" else 1, device)
            print(f"| {name} | {r['params_M']:.2f} | {r['patch']}² | {r['batch']} | {prec} | {r['s_per_step']:.3f} | "
                  f"{r['samples_per_s']:.2f} | {r['s_per_sample']:.3f} |", flush=True)


if __name__ == "__main__":
    main()
