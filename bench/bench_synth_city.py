"""Synthetic cities per second (`aerialmtl.data.synth.city.sample_city`, in memory), one process, one thread.

Usage: python bench/bench_synth_city.py [--cases 128:0.3 256:0.3 256:0.5 512:0.3 512:0.5] [--n 40] [--samples]
Prints, per (size, GSD): patches per second of wall time and of this process's CPU time (the CPU figure is
what one DataLoader worker would give on a quiet core), and the load average. ``--scenes`` times
:func:`aerialmtl.data.synthetic_batches.synthetic_scene` (the scene as ``aerialmtl pretrain`` draws it, classes in
the training scheme) instead.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as in a DataLoader worker
os.environ.setdefault("OMP_NUM_THREADS", "1")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=["128:0.3", "128:0.5", "256:0.3", "256:0.5", "512:0.3",
                                                        "512:0.5"])
    parser.add_argument("--n", type=int, default=40, help="patches per case (seeds 0..n-1)")
    parser.add_argument("--scenes", action="store_true", help="time synthetic_scene (the pretraining stream's scenes)")
    args = parser.parse_args()
    import torch

    from aerialmtl.data.synth.city import sample_city
    from aerialmtl.data.synthetic_batches import synthetic_scene

    torch.set_num_threads(1)
    print(f"load average (1, 5, 15 min) before: {os.getloadavg()}")
    for case in args.cases:
        size, gsd = int(case.split(":")[0]), float(case.split(":")[1])
        sample_city(10_000, size, gsd)  # warm-up
        wall, cpu = time.perf_counter(), time.process_time()
        for seed in range(args.n):
            if args.scenes:
                synthetic_scene(0, seed, size, gsd)
            else:
                sample_city(seed, size, gsd)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        print(f"{size:4d}² px at {gsd:.2f} m: {args.n / wall:6.1f} patches/s wall, {args.n / cpu:6.1f} patches/s "
              f"per CPU-second ({1000 * cpu / args.n:6.1f} ms CPU each); load {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
