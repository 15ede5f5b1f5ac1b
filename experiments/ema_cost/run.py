"""What the demo's weight average (``optim.ema``) adds to its training: one update per step and one swap
in and out per validation, timed on the demo's small D3-Net (``d3net_small_synth``, 6 classes, 3 bands).

    python -m experiments.ema_cost.run            # prints seconds per update/swap and their total over the demo
"""

from __future__ import annotations

import argparse
import os
import time

import torch

from aerialmtl.demo import DEMO_CONFIG, DemoSettings, builtin_config
from aerialmtl.models.d3net import D3Net
from aerialmtl.training.averaging import WeightAverage
from aerialmtl.training.config import load_train_config


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    torch.set_num_threads(2)
    cfg = load_train_config(builtin_config(DEMO_CONFIG))
    model = D3Net(cfg.model.resolve(3, ("height", "classes"), 6))
    avg = WeightAverage(model, 0.99)
    n = sum(p.numel() for p in model.parameters())
    reps = 200
    t = time.perf_counter()
    for _ in range(reps):
        avg.update(model)
    update = (time.perf_counter() - t) / reps
    t = time.perf_counter()
    for _ in range(20):
        with avg.applied(model):
            pass
    swap = (time.perf_counter() - t) / 20
    steps, validations = DemoSettings().train_steps, 53
    print(f"{n / 1e6:.2f} M parameters; update {update * 1e3:.2f} ms, swap {swap * 1e3:.2f} ms; "
          f"over the demo ({steps} steps, {validations} validations): {steps * update + validations * swap:.1f} s; "
          f"load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
