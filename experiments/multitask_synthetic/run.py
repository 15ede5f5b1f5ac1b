"""Quality benchmark: does multi-task help, and is MC-dropout uncertainty informative? (CPU, synthetic)

Fixed protocol (generator version recorded): one synthetic training town (seed ``--train-seed``) is
tiled once; three models with the small D3-Net configuration — height-only, classes-only and
multi-task — are trained from the same initial seed for the same number of optimisation steps with the
same batch size (the equal CPU budget; wall time is reported too), and each last checkpoint is evaluated
on held-out test towns generated with other seeds (disjoint from the training seed). Trivial baselines:
the training-town mean height and the training-town majority class.

Usage::

    python -m experiments.multitask_synthetic.run   # full protocol (about 25-35 min on 2 quiet cores)
    python -m experiments.multitask_synthetic.run --steps 20 --train-size 512 --test-size 256 \
        --test-seeds 101                            # smoke run

Prints a Markdown table and writes ``OUT/quality.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import rasterio
import torch

from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.data.synth import SYNTH_VERSION, synthesize
from aerialmtl.demo import builtin_config
from aerialmtl.evaluation.evaluate import EvaluateOptions, evaluate_prediction
from aerialmtl.evaluation.metrics import classification_metrics, confusion_matrix
from aerialmtl.inference.predict import predict_raster
from aerialmtl.tiling.splits import SplitSpec
from aerialmtl.tiling.tile import TileOptions, tile_dataset
from aerialmtl.training.config import load_train_config
from aerialmtl.training.loop import train

VARIANTS = {"height-only": ("height",), "classes-only": ("classes",), "multi-task": ("height", "classes")}


def _read(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with rasterio.open(path) as src:
        arr = src.read(1, masked=True)
    return np.asarray(arr.data), ~np.ma.getmaskarray(arr)


def trivial_baselines(train_town: Path, test_towns: list[Path], scheme: ClassScheme) -> dict[str, dict[str, float]]:
    """Train-mean height and majority class, scored on the test towns (pixels pooled)."""
    h, hv = _read(train_town / "ndsm.tif")
    mean_h = float(h[hv].mean())
    lab, _ = _read(train_town / "labels.tif")
    idx = scheme.remap(lab, on_unknown="ignore")
    counts = np.bincount(idx[idx != IGNORE_INDEX], minlength=scheme.num_classes)
    major = int(np.argmax(counts))
    abs_err, sq_err = [], []
    cm = np.zeros((scheme.num_classes, scheme.num_classes), np.int64)
    for town in test_towns:
        t, tv = _read(town / "ndsm.tif")
        abs_err.append(np.abs(t[tv] - mean_h))
        sq_err.append((t[tv] - mean_h) ** 2)
        ref = scheme.remap(_read(town / "labels.tif")[0], on_unknown="ignore")
        cm += confusion_matrix(ref, np.full_like(ref, major), scheme.num_classes, valid=ref != IGNORE_INDEX)
    cls = classification_metrics(cm, scheme.names)
    return {
        "train-mean height": {"height_mae": float(np.concatenate(abs_err).mean()),
                              "height_rmse": float(np.sqrt(np.concatenate(sq_err).mean())), "value_m": mean_h},
        "majority class": {"oa": cls["overall_accuracy"], "miou": cls["miou"], "class": scheme.names[major]},
    }


def _mean(values: list[float]) -> float:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(vals)) if vals else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("experiments/out/multitask_synthetic"))
    ap.add_argument("--train-seed", type=int, default=11)
    ap.add_argument("--train-size", type=int, default=1024)
    ap.add_argument("--test-seeds", default="101,102")
    ap.add_argument("--test-size", type=int, default=512)
    ap.add_argument("--steps", type=int, default=600, help="optimisation steps per model (equal budget)")
    ap.add_argument("--patch", type=int, default=128)
    ap.add_argument("--mc", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    test_seeds = [int(s) for s in args.test_seeds.split(",")]
    if args.train_seed in test_seeds:
        raise SystemExit("--train-seed must differ from every test seed (held-out towns)")
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    train_town = synthesize(out / "towns" / f"train_{args.train_seed}", size=args.train_size,
                            seed=args.train_seed, overwrite=True)
    tests = [synthesize(out / "towns" / f"test_{s}", size=args.test_size, seed=s, overwrite=True) for s in test_seeds]
    scheme = ClassScheme.load(train_town.classes)
    tile_dataset(
        train_town.ortho, out / "tiles", dsm=train_town.dsm, dtm=train_town.dtm, labels=train_town.labels,
        classes=scheme, overwrite=True, progress=False,
        options=TileOptions(size=args.patch, stride=args.patch,
                            splits=SplitSpec(block_size=args.patch * 0.25 * 2, ratios=(0.85, 0.15, 0.0), seed=0)),
    )

    base_cfg = load_train_config(builtin_config("d3net_small_synth"))
    results: dict[str, dict[str, float]] = {}
    for name, tasks in VARIANTS.items():
        cfg = base_cfg.with_overrides(model={"tasks": list(tasks)},
                                      schedule={"max_steps": args.steps, "epochs": 10_000, "max_time_s": None},
                                      data={"num_workers": 1}, seed=0)
        ts = time.perf_counter()
        run = train(cfg, data_dir=out / "tiles", out_dir=out / "runs" / name, progress=False)
        train_s = time.perf_counter() - ts
        per_town = []
        for town in tests:
            pdir = out / "pred" / name / town.ortho.parent.name
            predict_raster(town.ortho, run.last_checkpoint, pdir, mc=args.mc, precision="fp32", overwrite=True,
                           progress=False)
            per_town.append(evaluate_prediction(
                pdir, height_ref=town.ndsm if "height" in tasks else None,
                labels_ref=town.labels if "classes" in tasks else None, classes=scheme, out=None,
                options=EvaluateOptions(plots=False),
            ))
        row: dict[str, float] = {"train_s": train_s, "steps": run.step}
        if "height" in tasks:
            row["height_mae"] = _mean([r["height"]["mae"] for r in per_town])
            row["height_rmse"] = _mean([r["height"]["rmse"] for r in per_town])
            hs = [r["uncertainty"]["height_std"] for r in per_town]
            row["spearman_std_abs_err"] = _mean([h["spearman_std_vs_abs_error"] for h in hs])
            row["height_ause"] = _mean([h["sparsification"]["ause"] for h in hs])
            row["height_aurg"] = _mean([h["sparsification"]["aurg"] for h in hs])
        if "classes" in tasks:
            row["oa"] = _mean([r["classes"]["overall_accuracy"] for r in per_town])
            row["miou"] = _mean([r["classes"]["miou"] for r in per_town])
            for key in ("class_entropy", "class_mutual_info"):
                us = [r["uncertainty"][key] for r in per_town]
                row[f"{key}_ause"] = _mean([u["sparsification"]["ause"] for u in us])
                row[f"{key}_aurg"] = _mean([u["sparsification"]["aurg"] for u in us])
        results[name] = row
        print(name, json.dumps(row), flush=True)

    baselines = trivial_baselines(train_town.ortho.parent, [t.ortho.parent for t in tests], scheme)
    record = {
        "protocol": {"synth_version": SYNTH_VERSION, "train_seed": args.train_seed, "train_size": args.train_size,
                     "test_seeds": test_seeds, "test_size": args.test_size, "steps": args.steps,
                     "patch": args.patch, "batch_size": base_cfg.data.batch_size, "mc": args.mc,
                     "config": "d3net_small_synth", "threads": args.threads,
                     "machine": f"{platform.processor() or platform.machine()}, torch {torch.__version__}"},
        "models": results, "baselines": baselines, "total_s": time.perf_counter() - t0,
    }
    (out / "quality.json").write_text(json.dumps(record, indent=2))

    def f(v: float | None, nd: int = 3) -> str:
        return "—" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"

    print("\n| model | height MAE (m) | height RMSE (m) | OA | mIoU | Spearman(std, abs err) | height AUSE / AURG "
          "| entropy AUSE / AURG | MI AUSE / AURG | train s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, r in results.items():
        print(f"| {name} | {f(r.get('height_mae'), 2)} | {f(r.get('height_rmse'), 2)} | {f(r.get('oa'))} | "
              f"{f(r.get('miou'))} | {f(r.get('spearman_std_abs_err'))} | {f(r.get('height_ause'))} / "
              f"{f(r.get('height_aurg'))} | {f(r.get('class_entropy_ause'))} / {f(r.get('class_entropy_aurg'))} | "
              f"{f(r.get('class_mutual_info_ause'))} / {f(r.get('class_mutual_info_aurg'))} | {r['train_s']:.0f} |")
    b = baselines
    tm = b["train-mean height"]
    print(f"| train-mean height ({tm['value_m']:.2f} m) | {f(tm['height_mae'], 2)}"
          f" | {f(b['train-mean height']['height_rmse'], 2)} | | | | | | | |")
    print(f"| majority class ({b['majority class']['class']}) | | | {f(b['majority class']['oa'])} | "
          f"{f(b['majority class']['miou'])} | | | | | |")
    print(f"\ntotal {record['total_s']:.0f} s")


if __name__ == "__main__":
    main()
