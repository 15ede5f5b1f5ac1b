"""How much the demo's four numbers move with the CPU kind and thread count (issue 35).

Runs the demo (:func:`aerialmtl.demo.run_demo`) once per environment, each in its own process, and prints
the test town's height MAE, RMSE, class OA and mIoU per environment, their range, and the wall time:

    python -m experiments.demo_spread.run --out /tmp/spread --env native2 native1 avx2-2 avx2-1 [--ema 0.99 ...]

Environments (the CPU here is emulated downwards, never upwards):
  native2 / native1   this CPU, 2 / 1 threads (OMP_NUM_THREADS)
  avx2-2 / avx2-1     oneDNN and ATen limited to AVX2 (``ONEDNN_MAX_CPU_ISA=AVX2``,
                      ``ATEN_CPU_CAPABILITY=avx2``): the kernels an AVX2-only CPU (AMD Zen 3) runs
  avx512-2            oneDNN limited to AVX-512 without the bf16/VNNI extensions (``AVX512_CORE``)
Training settings other than the defaults (``--lr``, ``--ema``, ``--schedule``, ``--warmup``) make a
variant; each row of results is appended to ``OUT/results.jsonl``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ENVS: dict[str, dict[str, str]] = {
    "native2": {"OMP_NUM_THREADS": "2"},
    "native1": {"OMP_NUM_THREADS": "1"},
    "avx2-2": {"OMP_NUM_THREADS": "2", "ONEDNN_MAX_CPU_ISA": "AVX2", "ATEN_CPU_CAPABILITY": "avx2"},
    "avx2-1": {"OMP_NUM_THREADS": "1", "ONEDNN_MAX_CPU_ISA": "AVX2", "ATEN_CPU_CAPABILITY": "avx2"},
    "avx512-2": {"OMP_NUM_THREADS": "2", "ONEDNN_MAX_CPU_ISA": "AVX512_CORE"},
}

CHILD = """
import json, sys
from dataclasses import replace
from aerialmtl.demo import DemoSettings, run_demo
kw = json.loads(sys.argv[2])
res = run_demo(sys.argv[1], replace(DemoSettings(), **kw), overwrite=True, progress=False, log=lambda m: None)
h, c = res.report.get("height", {}), res.report.get("classes", {})
print(json.dumps({"mae": h.get("mae"), "rmse": h.get("rmse"), "oa": c.get("overall_accuracy"),
                  "miou": c.get("miou"), "timings": res.timings}))
"""


def run_one(out: Path, env_name: str, overrides: dict[str, object]) -> dict[str, object]:
    """One demo in a child process with the environment ``env_name``; returns its numbers."""
    env = {**os.environ, **ENVS[env_name]}
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", CHILD, str(out / env_name), json.dumps(overrides)], env=env,
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"{env_name}: the demo failed:\n{proc.stderr[-3000:]}")
    row = json.loads(proc.stdout.strip().splitlines()[-1])
    row.update(env=env_name, wall_s=round(time.perf_counter() - t, 1), load=os.getloadavg(), settings=overrides)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="folder for the demos and results.jsonl")
    ap.add_argument("--env", nargs="+", choices=sorted(ENVS), default=["native2", "native1", "avx2-2", "avx2-1"],
                    help="environments to run, one after the other")
    ap.add_argument("--lr", type=float, help="peak learning rate (default: the demo's)")
    ap.add_argument("--ema", type=float, help="weight-average decay; 0 for none (default: the demo's)")
    ap.add_argument("--schedule", choices=["constant", "cosine"], help="learning-rate schedule")
    ap.add_argument("--warmup", type=int, help="warm-up steps")
    ap.add_argument("--steps", type=int, help="training steps (default: the demo's)")
    a = ap.parse_args()
    overrides: dict[str, object] = {}
    for key, value in (("lr", a.lr), ("lr_schedule", a.schedule), ("warmup_steps", a.warmup),
                       ("train_steps", a.steps)):
        if value is not None:
            overrides[key] = value
    if a.ema is not None:
        overrides["ema"] = a.ema or None
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in a.env:
        row = run_one(a.out, name, overrides)
        rows.append(row)
        with open(a.out / "results.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)
    for key in ("mae", "rmse", "oa", "miou"):
        vals = [float(r[key]) for r in rows if r.get(key) is not None]  # type: ignore[arg-type]
        if vals:
            print(f"{key}: {min(vals):.3f} .. {max(vals):.3f} (range {max(vals) - min(vals):.3f})")


if __name__ == "__main__":
    main()
