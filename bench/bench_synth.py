"""Time `aerialmtl.data.synth.synthesize` (generation + writing) per scene size, in fresh processes.

Usage: python bench/bench_synth.py [--sizes 1024 2048 4096] [--seed 0] [--out /tmp/synth_bench]
Prints one line per size: wall seconds (inside the call) and peak RSS of the child process.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

CHILD = """
import resource, sys, time
from aerialmtl.data.synth import synthesize
size, seed, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
t0 = time.perf_counter()
synthesize(out, size=size, seed=seed, overwrite=True)
dt = time.perf_counter() - t0
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(f"size {size:5d}: {dt:6.1f} s, peak RSS {rss:6.0f} MiB")
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="/tmp/synth_bench")
    args = parser.parse_args()
    print(f"load average (1, 5, 15 min): {os.getloadavg()}")
    for size in args.sizes:
        out = os.path.join(args.out, str(size))
        subprocess.run([sys.executable, "-c", CHILD, str(size), str(args.seed), out], check=True)


if __name__ == "__main__":
    main()
