"""Real-data benchmark: how well does a model trained on part of ``autzen_west`` predict a held-out block?

Fixed protocol (issue 12, part 3):

* **Split** — bands across the survey's long (north–south) axis, written as GeoJSON polygons in the
  orthophoto's CRS (EPSG:2994, feet) by :func:`write_split` from the fractions in :data:`SPLITS`:
  held-out **test** block = the northern 25 % (buildings, car parks, tree rows); ``--split middle-val``
  (default) validates on a 20 % band inside the rest and trains on both sides of it, ``--split south-val``
  (the first protocol) validates on the southern 20 % (river, forest) and trains on the middle; with
  :data:`GAP_M` metres left unused between blocks so that
  no tree crown or roof is cut between train and test. Only train and val are tiled (patches lie wholly
  inside their AOI); the test block is predicted as a whole with ``predict_raster(aoi=test)``, so every
  window sees its real context and the prediction is nodata outside the block.
* **Tiling** through the library (``tile_dataset`` with the DSM/DTM pair, heights in metres, the
  working GSD given in metres), cached per (GSD, patch size, stride).
* **Training** with :func:`aerialmtl.training.loop.train` under a step and/or wall-clock budget.
* **Evaluation** of ``best.pt`` (and optionally ``last.pt``) with ``evaluate_prediction(dsm_ref=...,
  dtm_ref=...)`` on the held-out block: MAE, RMSE, MAE on pixels whose reference height is ≥ 2 m,
  Spearman(height std, |error|) with T MC-dropout samples; the same evaluation of two constant
  predictions on the same pixels: the **train-mean** baseline (mean reference nDSM over the train block on
  the working grid) and the all-ground baseline (0 m).

Usage::

    python -m experiments.real_data.run --list                        # the recipes
    nice -n 10 python -m experiments.real_data.run --recipe scratch    # one recipe; prints a Markdown row
    python -m experiments.real_data.run --table                       # every result so far as a Markdown table

Every run writes ``OUT/runs/<name>/result.json`` (settings, counts, training time, metrics, the CPU
model and the load average at start and end). The training budget is **megapixels of patches processed**
(steps × batch × patch side², ``--budget-mpx``), so that recipes at different GSDs and patch sizes get
the same arithmetic work whatever else shares the machine (wall time on a shared CPU is recorded but is
not a fair budget); ``--max-time`` is only a safety cap. Validation (which picks ``best.pt``) runs about
every ``--val-steps`` steps.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import torch

from aerialmtl.formats.prediction import FLOAT_NODATA, HEIGHT, layer_filename
from aerialmtl.formats.tiles import ManifestWriter, read_manifest
from aerialmtl.inference.predict import predict_raster
from aerialmtl.io.units import metres_per_unit
from aerialmtl.tiling.splits import SplitSpec
from aerialmtl.tiling.tile import TileOptions, tile_dataset
from aerialmtl.training.config import TrainConfig, load_train_config
from aerialmtl.training.loop import train
from experiments.common.autzen import (
    DATA,
    DEFAULT_SPLIT,
    DSM,
    DTM,
    GAP_M,
    ORTHO,
    ROOT,
    SPLITS,
    TALL_M,
    cpu_model,
)
from experiments.common.maps import constant_prediction, train_mean
from experiments.common.reports import evaluate_dir
from experiments.real_data.recipes import (
    PretrainSettings,
    pretrain_synthetic,
    repeat_counts,
    stratified_weights,
    tall_shares,
)


# ---- split ---------------------------------------------------------------------------------------
def write_split(ortho: Path, out_dir: Path, bands: dict[str, list[tuple[float, float]]]) -> dict[str, Path]:
    """Write ``train/val/test.geojson`` (one rectangle per band, in the orthophoto's CRS); return their paths.

    ``bands`` is one of :data:`SPLITS`; every inner band edge is pulled back by :data:`GAP_M` metres.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    with rasterio.open(ortho) as src:
        left, bottom, right, top = src.bounds
        crs = src.crs
    gap = GAP_M / metres_per_unit(crs, "orthophoto", ortho)
    extent = top - bottom
    paths = {}
    for name, spans in bands.items():
        features = []
        for f0, f1 in spans:
            y_top = top - f0 * extent - (gap if f0 > 0 else 0.0)
            y_bottom = top - f1 * extent + (gap if f1 < 1 else 0.0)
            ring = [[left, y_bottom], [right, y_bottom], [right, y_top], [left, y_top], [left, y_bottom]]
            features.append({"type": "Feature", "properties": {"split": name},
                             "geometry": {"type": "Polygon", "coordinates": [ring]}})
        fc = {"type": "FeatureCollection",
              "crs": {"type": "name", "properties": {"name": f"EPSG:{crs.to_epsg()}"}}, "features": features}
        paths[name] = out_dir / f"{name}.geojson"
        paths[name].write_text(json.dumps(fc))
    return paths


# ---- recipes -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Recipe:
    """One way of training on the real area.

    Attributes:
        gsd: working GSD in metres (``None`` = the orthophoto's, 1 ft).
        size, stride: patch size and stride in pixels of the working grid.
        config: training YAML (relative to the repository root).
        overrides: ``TrainConfig.with_overrides`` sections.
        pretrain: synthetic pretraining first (``PretrainSettings`` fields plus ``budget_mpx`` and
            ``config``), at the recipe's GSD; the real-area training starts from its exported start.
        zero_shot: evaluate the pretrained model as it is, without training on the real area.
        stratify: height-stratified sampling: the share of tall (≥ 2 m) pixels per drawn patch to reach
            (:func:`experiments.real_data.recipes.stratified_weights`), applied as whole repeats of train patches in a
            manifest view.
        mix: train on the synthetic pretraining tiles and the real ones together, real patches repeated so
            that they make about this share of every epoch (validation: real patches only).
        note: one line saying what the recipe tries.
    """

    gsd: float | None = None
    size: int = 320
    stride: int | None = None
    config: str = "configs/d3net_small_synth.yaml"
    overrides: dict[str, Any] = field(default_factory=dict)
    pretrain: dict[str, Any] | None = None
    zero_shot: bool = False
    stratify: float | None = None
    mix: float | None = None
    note: str = ""


#: Synthetic pretraining at 1 m: 16 towns of 768 m, 128-px patches, the same budget as a real run.
SYNTH_G10: dict[str, Any] = {"towns": 16, "town_size": 768, "patch": 128, "stride": 64,
                             "budget_mpx": 600 * 8 * 128 * 128 / 1e6}

RECIPES: dict[str, Recipe] = {
    "scratch": Recipe(note="what a user gets today: small config, native 1 ft GSD, 320-px patches (97 m)"),
    "gsd06": Recipe(gsd=0.6, size=256, stride=128, note="0.6 m working GSD: 3.9x fewer pixels, 256-px patches (154 m)"),
    "gsd10": Recipe(gsd=1.0, size=128, stride=32, note="1 m working GSD (the reference's): 128-px patches (128 m)"),
    "berhu_g10": Recipe(gsd=1.0, size=128, stride=32, overrides={"loss": {"height": "berhu"}},
                        note="gsd10 + reverse Huber height loss (L2 on large errors: tall objects)"),
    "strat_g10": Recipe(gsd=1.0, size=128, stride=32, stratify=0.5,
                        note="gsd10 + height-stratified sampling (half the pixels drawn are >= 2 m)"),
    "synth_zero_g10": Recipe(gsd=1.0, size=128, stride=32, pretrain=SYNTH_G10, zero_shot=True,
                             note="pretrained on 16 synthetic towns at 1 m only, no real training (zero-shot)"),
    "synth_ft_g10": Recipe(gsd=1.0, size=128, stride=32, pretrain=SYNTH_G10,
                           note="pretrained on 16 synthetic towns at 1 m, then fine-tuned on the real area"),
    "synth_mix_g10": Recipe(gsd=1.0, size=128, stride=32, pretrain=SYNTH_G10, mix=0.5,
                            note="pretrained on the synthetic towns, then trained on synthetic + real patches "
                                 "together (half real)"),
}


def _parse_set(items: list[str]) -> dict[str, Any]:
    """``["optim.lr=5e-4", "loss.height=berhu"]`` → nested overrides (values parsed as YAML)."""
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        key, _, value = item.partition("=")
        section, _, sub = key.partition(".")
        parsed = yaml.safe_load(value)
        if isinstance(parsed, str):  # YAML 1.1 reads 1e-4 as a string
            try:
                parsed = float(parsed)
            except ValueError:
                pass
        if sub:
            out.setdefault(section, {})[sub] = parsed
        else:
            out[section] = parsed
    return out


# ---- helpers -------------------------------------------------------------------------------------
def tiles_for(recipe: Recipe, data: Path, split: dict[str, Path], out: Path,
              split_name: str) -> tuple[Path, dict[str, Any]]:
    """Tile folder of the split and the recipe's (GSD, size, stride), made once and reused."""
    stride = recipe.stride or recipe.size
    prefix = "" if split_name == "south-val" else f"{split_name}_"
    tdir = out / f"tiles_{prefix}g{recipe.gsd or 'native'}_s{recipe.size}_st{stride}"
    info_file = tdir / "tile_info.json"
    if info_file.is_file():
        return tdir, json.loads(info_file.read_text())
    if tdir.exists():
        shutil.rmtree(tdir)
    t0 = time.perf_counter()
    res = tile_dataset(
        data / ORTHO, tdir, dsm=data / DSM, dtm=data / DTM, progress=False,
        options=TileOptions(size=recipe.size, stride=stride, gsd=recipe.gsd,
                            splits=SplitSpec(method="aoi", aoi={k: str(split[k]) for k in ("train", "val")})),
    )
    info = {"counts": res.counts, "windows": res.windows, "dropped_invalid": res.dropped_invalid,
            "dropped_split": res.dropped_split, "seconds": time.perf_counter() - t0}
    info_file.write_text(json.dumps(info, indent=1))
    return tdir, info


def manifest_view(tdir: Path, vdir: Path, rows: list[dict[str, str]], links: dict[str, Path] | None = None) -> None:
    """Write tile folder ``vdir``: ``tdir``'s ``dataset.yaml``, symlinks to its split folders (and ``links``:
    name → folder) and a manifest of ``rows`` (through the package's own manifest writer)."""
    vdir.mkdir(parents=True, exist_ok=True)
    targets = {name: tdir / name for name in ("train", "val", "test") if (tdir / name).exists()}
    for name, target in {**targets, **(links or {})}.items():
        if not (vdir / name).exists():
            (vdir / name).symlink_to(target.resolve())
    shutil.copyfile(tdir / "dataset.yaml", vdir / "dataset.yaml")
    with ManifestWriter(vdir) as manifest:
        for row in rows:
            manifest.writerow(row)


def oversampled_view(tdir: Path, target: float) -> tuple[Path, dict[str, Any]]:
    """A tile folder that repeats train patches by :func:`experiments.real_data.recipes.repeat_counts` of their
    stratified weights (symlinks to ``tdir``'s patches; val and test rows unchanged)."""

    vdir = tdir.with_name(f"{tdir.name}_strat{target:g}")
    shares = tall_shares(tdir, "train", TALL_M)
    reps = repeat_counts(stratified_weights(shares, target))
    info = {"target": target, "mean_share": float(shares.mean()),
            "share_after": float((reps * shares).sum() / reps.sum()), "patches": int(reps.sum())}
    if (vdir / "manifest.csv").is_file():
        return vdir, info
    out_rows, k = [], 0
    for row in read_manifest(tdir):
        if row["split"] != "train":
            out_rows.append(row)
            continue
        for j in range(int(reps[k])):
            out_rows.append({**row, "patch_id": f"{row['patch_id']}#{j}"})
        k += 1
    manifest_view(tdir, vdir, out_rows)
    return vdir, info


def mixed_view(tdir: Path, synth_tiles: Path, real_share: float) -> tuple[Path, dict[str, Any]]:
    """A tile folder whose train split is the synthetic train patches plus the real ones repeated to make
    ``real_share`` of the patches; val/test rows and ``dataset.yaml`` (normalisation, tasks) are the real
    folder's. Synthetic patches are reached through a ``synthetic`` symlink."""
    vdir = tdir.with_name(f"{tdir.name}_mix{real_share:g}_{synth_tiles.parent.name}")
    rows = read_manifest(tdir)
    synth = read_manifest(synth_tiles, "train")
    real = [r for r in rows if r["split"] == "train"]
    reps = max(1, round(real_share * len(synth) / ((1 - real_share) * len(real))))
    info = {"real_share": real_share, "real_patches": len(real), "real_repeats": reps, "synthetic_patches": len(synth),
            "patches": len(real) * reps + len(synth)}
    if (vdir / "manifest.csv").is_file():
        return vdir, info
    out_rows = [r for r in rows if r["split"] != "train"]
    out_rows += [{**r, "patch_id": f"{r['patch_id']}#{j}"} for r in real for j in range(reps)]
    for r in synth:
        out_rows.append({k: (f"synthetic/{v}" if k.endswith("_path") and k != "classes_path" and v else
                             ("" if k == "classes_path" else v)) for k, v in r.items()}
                        | {"patch_id": f"synthetic_{r['patch_id']}", "class_hist": ""})
    manifest_view(tdir, vdir, out_rows, {"synthetic": synth_tiles})
    return vdir, info


def pretrained_checkpoint(recipe: Recipe, args: argparse.Namespace) -> tuple[Path, dict[str, Any]]:
    """Run (once, cached by its settings) the recipe's synthetic pretraining; returns its start and a record."""

    p = dict(recipe.pretrain or {})
    budget = float(p.pop("budget_mpx"))
    config = p.pop("config", recipe.config)
    cfg = load_train_config(ROOT / config).with_overrides(**p.pop("overrides", {}))
    settings = PretrainSettings(gsd=recipe.gsd or 0.3048, patch=p.pop("patch", recipe.size), **p)
    key = f"pretrain_g{settings.gsd}_n{settings.towns}_t{settings.town_size}_p{settings.patch}_b{budget:g}"
    pdir = args.out / key
    record_file = pdir / "pretrain.json"
    if record_file.is_file():
        return pdir / "run" / "synthetic-start.pt", json.loads(record_file.read_text())
    side = cfg.data.crop_size or settings.patch
    steps = max(1, round(budget * 1e6 / (cfg.data.batch_size * side * side)))
    cfg = cfg.with_overrides(data={"num_workers": args.workers}, schedule={"val_every": 1})
    t0, load0 = time.perf_counter(), os.getloadavg()
    res = pretrain_synthetic(pdir, settings, cfg, max_steps=steps, max_time_s=args.max_time * 2, overwrite=True,
                             progress=not args.quiet, log=print)
    record = {"settings": asdict(settings), "config": config, "budget_mpx": budget, "steps": res.train.step,
              "train_s": res.train.elapsed_s, "total_s": time.perf_counter() - t0, "patches": res.patches,
              "last_loss": res.train.loss, "load_start": load0, "load_end": os.getloadavg()}
    record_file.write_text(json.dumps(record, indent=1, default=float))
    return res.checkpoint, record


# ---- one run -------------------------------------------------------------------------------------
def run(name: str, recipe: Recipe, args: argparse.Namespace) -> dict[str, Any]:
    out: Path = args.out
    split_dir = out / ("split" if args.split == "south-val" else f"split_{args.split}")
    split = write_split(args.data / ORTHO, split_dir, SPLITS[args.split])
    load0 = os.getloadavg()
    tdir, tinfo = tiles_for(recipe, args.data, split, out, args.split)
    n_train = tinfo["counts"]["train"]
    if recipe.stratify:
        tdir, sinfo = oversampled_view(tdir, recipe.stratify)
        tinfo, n_train = {**tinfo, "stratify": sinfo}, sinfo["patches"]
    cfg: TrainConfig = load_train_config(ROOT / recipe.config)
    overrides = {**recipe.overrides}
    for key, value in _parse_set(args.set).items():
        overrides[key] = {**overrides.get(key, {}), **value} if isinstance(value, dict) else value
    overrides.setdefault("data", {})
    overrides["data"] = {**overrides["data"], "num_workers": args.workers}
    cfg = cfg.with_overrides(**overrides)
    side = cfg.data.crop_size or recipe.size
    steps = args.max_steps or max(1, round(args.budget_mpx * 1e6 / (cfg.data.batch_size * side * side)))
    per_epoch = max(1, n_train // cfg.data.batch_size)
    val_every = max(1, round(args.val_steps / per_epoch))
    cfg = cfg.with_overrides(schedule={"val_every": val_every})
    rdir = out / "runs" / name
    if rdir.exists():
        shutil.rmtree(rdir)
    rdir.mkdir(parents=True)
    torch.set_num_threads(args.threads)
    init, pre_record = (None, None)
    if recipe.pretrain:
        init, pre_record = pretrained_checkpoint(recipe, args)
    elif args.init is not None:  # a start made elsewhere (`aerialmtl pretrain`, or a shipped start's name)
        init, pre_record = args.init, {"init": str(args.init)}
    if recipe.mix:
        assert init is not None, "mix needs a pretrain section (its tiles)"
        tdir, minfo = mixed_view(tdir, init.parent.parent / "tiles", recipe.mix)
        tinfo = {**tinfo, "mix": minfo}
        per_epoch = max(1, minfo["patches"] // cfg.data.batch_size)
        cfg = cfg.with_overrides(schedule={"val_every": max(1, round(args.val_steps / per_epoch))})
    if recipe.zero_shot:
        assert init is not None, "zero_shot needs a pretrain section"
        shutil.copyfile(init, rdir / "best.pt")
        train_record: dict[str, Any] = {"steps": 0, "epochs": 0, "stopped_by": "zero-shot", "seconds": 0.0, "val": {}}
    else:
        kwargs: dict[str, Any] = {}
        if init is not None:
            if "init" not in inspect.signature(train).parameters:
                raise SystemExit("this recipe fine-tunes a pretrained model: it needs `train(init=...)` (train --init)")
            kwargs["init"] = init
        snaps = sorted({int(v) for v in args.snapshots.split(",")} | {steps}) if args.snapshots else [steps]
        snaps = [v for v in snaps if v <= steps]
        segments: list[dict[str, Any]] = []
        seconds = 0.0
        for i, until in enumerate(snaps):
            # one train() call per snapshot, resuming from last.pt (constant lr: same as one call)
            seg_load0 = os.getloadavg()
            result = train(cfg, data_dir=tdir, out_dir=rdir, max_steps=until, max_time_s=args.max_time,
                           progress=not args.quiet, resume=i > 0, **(kwargs if i == 0 else {}))
            seconds += result.elapsed_s
            if len(snaps) > 1:
                shutil.copyfile(rdir / "last.pt", rdir / f"snap_{until}.pt")
                shutil.copyfile(rdir / "best.pt", rdir / f"best_{until}.pt")
            segments.append({"step": result.step, "seconds": result.elapsed_s, "load_start": seg_load0,
                             "load_end": os.getloadavg(), "val": result.metrics})
            (rdir / "segments.json").write_text(json.dumps(segments, indent=1, default=float))
        train_record = {"steps": result.step, "epochs": result.epoch, "stopped_by": result.stopped_by,
                        "seconds": seconds, "val": result.metrics, "segments": segments}
    load1 = os.getloadavg()
    record: dict[str, Any] = {
        "name": name, "split": args.split, "recipe": asdict(recipe), "set": args.set, "tiles": str(tdir),
        "tile_info": tinfo,
        "budget": {"mpx": args.budget_mpx, "max_steps": steps, "val_every_epochs": val_every},
        "pretrain": pre_record, "train": train_record,
        "machine": {"cpu": cpu_model(), "torch": torch.__version__, "threads": torch.get_num_threads(),
                    "load_start": load0, "load_after_train": load1},
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "mc": args.mc, "checkpoints": {},
    }
    (rdir / "result.json").write_text(json.dumps(record, indent=1, default=float))
    if args.no_eval:
        return record
    for ckpt in ["best.pt"] + (["last.pt"] if args.also_last and not recipe.zero_shot else []):
        pdir = rdir / f"pred_{Path(ckpt).stem}"
        t0 = time.perf_counter()
        pr = predict_raster(args.data / ORTHO, rdir / ckpt, pdir, mc=args.mc, aoi=split["test"], overwrite=True,
                            progress=False)
        metrics = evaluate_dir(pdir, args.data, rdir / f"report_{Path(ckpt).stem}.json")
        metrics["predict_s"] = time.perf_counter() - t0
        metrics["predict_gsd_m"] = pr.grid.gsd
        record["checkpoints"][ckpt] = metrics
        if "baselines" not in record:
            mean = train_mean(pdir / layer_filename(HEIGHT), args.data, split["train"])
            record["baselines"] = {"train_mean_value_m": mean}
            for label, value in (("train_mean", mean), ("zero", 0.0)):
                bdir = constant_prediction(pdir, value, rdir / f"baseline_{label}")
                record["baselines"][label] = evaluate_dir(bdir, args.data, rdir / f"report_baseline_{label}.json")
    record["machine"]["load_end"] = os.getloadavg()
    (rdir / "result.json").write_text(json.dumps(record, indent=1, default=float))
    return record


# ---- learning curves and calibration --------------------------------------------------------------
CAL_METHODS = ("isotonic", "median", "quantile")


def _val_cv(pred: np.ndarray, ref: np.ndarray, sd: np.ndarray) -> dict[str, dict[str, float]]:
    """Two-fold check of each calibration method on validation pixels only (first/second half of the val
    patches in manifest order): fit on one half, score on the other; ``none`` = uncalibrated."""
    from aerialmtl.models.calibration import fit_calibration
    from aerialmtl.models.spread_fit import interval_coverage

    half = pred.size // 2
    folds = [(slice(0, half), slice(half, None)), (slice(half, None), slice(0, half))]
    out: dict[str, dict[str, float]] = {}
    for method in ("none", *CAL_METHODS):
        rows = []
        for fit, test in folds:
            if method == "none":
                h, s = pred[test], sd[test]
            else:
                cal = fit_calibration(pred[fit], ref[fit], sd[fit], method)  # type: ignore[arg-type]
                h, s = cal.height(pred[test]), cal.std(sd[test])
            r = ref[test]
            tall = r >= TALL_M
            err = h - r
            rows.append({"mae": float(np.abs(err).mean()), "mae_tall": float(np.abs(err[tall]).mean()),
                         "bias_tall": float(err[tall].mean()),
                         **interval_coverage(np.abs(err), s)})
        out[method] = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    return out


def _calibrated_copy(pred_dir: Path, cal: Any, out_dir: Path) -> Path:
    """``pred_dir``'s height (and height_std) with ``cal`` applied, as predict applies it (same functions)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for layer, fn in ((HEIGHT, cal.height), ("height_std", cal.std)):
        src_path = pred_dir / layer_filename(layer)
        if not src_path.is_file():
            continue
        with rasterio.open(src_path) as src:
            profile = src.profile.copy()
            data = src.read(1)
        profile.update(driver="GTiff", compress="deflate", predictor=3, tiled=True, blockxsize=512, blockysize=512)
        out = np.where(data == FLOAT_NODATA, FLOAT_NODATA, fn(data)).astype(np.float32)
        with rasterio.open(out_dir / layer_filename(layer), "w", **profile) as dst:
            dst.write(out, 1)
    return out_dir


def evaluate_run(name: str, args: argparse.Namespace) -> dict[str, Any]:
    """Evaluate every ``snap_<step>.pt``/``best_<step>.pt`` (or best.pt/last.pt) of run ``name`` on the test
    block, uncalibrated and with each calibration fitted on the val split; writes ``curve.json``."""
    from aerialmtl.formats.checkpoint import load_model
    from aerialmtl.models.calibration import fit_calibration
    from aerialmtl.training.calibrate import validation_pixels

    rdir = args.out / "runs" / name
    import yaml

    # while the run trains there is no result.json yet: its config.yaml names the tile folder
    rec = json.loads((rdir / "result.json").read_text()) if (rdir / "result.json").is_file() else {
        "split": args.split, "tiles": yaml.safe_load((rdir / "config.yaml").read_text())["data"]["dir"]}
    split_dir = args.out / ("split" if rec["split"] == "south-val" else f"split_{rec['split']}")
    split = {k: split_dir / f"{k}.geojson" for k in ("train", "val", "test")}
    tdir = Path(rec["tiles"])
    torch.set_num_threads(args.threads)
    ckpts = sorted(rdir.glob("snap_*.pt"), key=lambda p: int(p.stem.split("_")[1]))
    ckpts += sorted(rdir.glob("best_*.pt"), key=lambda p: int(p.stem.split("_")[1]))
    if args.only:
        ckpts = [p for p in ckpts if p.stem.startswith(args.only)]
    if not ckpts:
        ckpts = [p for p in (rdir / "best.pt", rdir / "last.pt") if p.is_file()]
    curve_file = rdir / "curve.json"
    curve: dict[str, Any] = json.loads(curve_file.read_text()) if curve_file.is_file() else {}
    for ckpt in ckpts:
        old = curve.get(ckpt.stem) if not args.force else None
        if old is not None and all(m in old["test"] for m in CAL_METHODS):
            continue
        t0, load0 = time.perf_counter(), os.getloadavg()
        model, meta = load_model(ckpt)
        pred, ref, sd, _ = validation_pixels(model, meta, tdir, mc=args.mc)
        cals = {m: fit_calibration(pred, ref, sd, m) for m in CAL_METHODS}  # type: ignore[arg-type]
        entry: dict[str, Any] = {"step": torch.load(ckpt, weights_only=True)["train_state"]["step"],
                                 "val_cv": _val_cv(pred, ref, sd), "val_pixels": int(pred.size),
                                 "calibration": {m: {"std_scale": c.std_scale, "knots": [c.height_x, c.height_y]}
                                                 for m, c in cals.items()}}
        pdir = rdir / f"pred_{ckpt.stem}"
        if old is not None:  # the raw test prediction is there: only the calibrations it lacks
            entry["test"] = old["test"]
        else:
            predict_raster(args.data / ORTHO, (model, meta), pdir, mc=args.mc, aoi=split["test"], overwrite=True,
                           progress=False, checkpoint_name=str(ckpt), calibration=False)
            entry["test"] = {"none": evaluate_dir(pdir, args.data, rdir / f"report_{ckpt.stem}.json")}
        for m, c in cals.items():
            if m in entry["test"]:
                continue
            cdir = _calibrated_copy(pdir, c, rdir / f"pred_{ckpt.stem}_{m}")
            entry["test"][m] = evaluate_dir(cdir, args.data, rdir / f"report_{ckpt.stem}_{m}.json")
        for m in ("none", *CAL_METHODS):
            rep = json.loads((rdir / f"report_{ckpt.stem}{'' if m == 'none' else '_' + m}.json").read_text())
            hs = rep.get("uncertainty", {}).get("height_std") or {}
            entry["test"][m].update({"coverage_1sigma": hs.get("coverage_1sigma"),
                                     "coverage_2sigma": hs.get("coverage_2sigma"),
                                     "per_bin": [{k: b[k] for k in ("range_m", "n_pixels", "mae", "bias")}
                                                 for b in rep["height"]["per_bin"]]})
        if "baselines" not in curve:
            mean = train_mean(pdir / layer_filename(HEIGHT), args.data, split["train"])
            bdir = constant_prediction(pdir, mean, rdir / "baseline_train_mean")
            curve["baselines"] = {"train_mean_value_m": mean,
                                  "train_mean": evaluate_dir(bdir, args.data, rdir / "report_baseline_train_mean.json")}
        entry["eval_s"], entry["load"] = time.perf_counter() - t0, [load0, os.getloadavg()]
        curve[ckpt.stem] = entry
        curve_file.write_text(json.dumps(curve, indent=1, default=float))
        t = entry["test"]
        print(f"{name} {ckpt.stem} step {entry['step']}: " + "; ".join(
            f"{m}: MAE {t[m]['mae']:.2f} MAE>=2 {t[m]['mae_tall']:.2f} bias>=2 {t[m]['bias_tall']:+.2f} "
            f"cov1 {t[m]['coverage_1sigma'] or math.nan:.2f}" for m in t), flush=True)
    return curve


def curve_table(out: Path, runs: list[str] | None = None) -> str:
    """Markdown: one row per evaluated checkpoint of each run's ``curve.json`` (test block), uncalibrated and
    calibrated, with the seconds per step and load of the training segment that reached it."""
    lines = ["| run | checkpoint | step | s/step (load) | calibration | MAE (m) | RMSE (m) | MAE ≥ 2 m (m) | "
             "bias ≥ 2 m (m) | ±1σ / ±2σ coverage | val-CV MAE / MAE ≥ 2 m |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    base = None
    for cfile in sorted((out / "runs").glob("*/curve.json")):
        name = cfile.parent.name
        if runs and name not in runs:
            continue
        curve = json.loads(cfile.read_text())
        base = base or curve.get("baselines")
        seg_file = cfile.parent / "segments.json"
        segs = json.loads(seg_file.read_text()) if seg_file.is_file() else []
        prev, rate = 0, {}
        for sgm in segs:
            rate[sgm["step"]] = (sgm["seconds"] / max(1, sgm["step"] - prev), sgm["load_start"][0], sgm["load_end"][0])
            prev = sgm["step"]
        keys = sorted((k for k in curve if k != "baselines"), key=lambda k: (k.split("_")[0], int(k.split("_")[1])))
        for k in keys:
            e = curve[k]
            snap = int(k.split("_")[1])
            r = rate.get(snap)
            rs = f"{r[0]:.1f} ({r[1]:.0f}→{r[2]:.0f})" if r else "?"
            for m, t in e["test"].items():
                cv = e["val_cv"][m]
                c1, c2 = (math.nan if t.get(c) is None else t[c] for c in ("coverage_1sigma", "coverage_2sigma"))
                lines.append(f"| {name} | {k} | {e['step']} | {rs} | {m} | {t['mae']:.2f} | {t['rmse']:.2f} | "
                             f"{t['mae_tall']:.2f} | {t['bias_tall']:+.2f} | "
                             f"{c1:.2f} / {c2:.2f} | "
                             f"{cv['mae']:.2f} / {cv['mae_tall']:.2f} |")
    if base:
        b = base["train_mean"]
        lines.append(f"\nTrain-mean baseline ({base['train_mean_value_m']:.2f} m): MAE {b['mae']:.2f}, RMSE "
                     f"{b['rmse']:.2f}, MAE ≥ 2 m {b['mae_tall']:.2f}, bias ≥ 2 m {b['bias_tall']:+.2f}.")
    return "\n".join(lines)


# ---- tables --------------------------------------------------------------------------------------
HEADER = ("| run | GSD (m) | patch | steps | train s | height MAE (m) | RMSE (m) | MAE ≥ 2 m (m) | "
          "Spearman(std, \\|err\\|) | train-mean MAE / RMSE / MAE ≥ 2 m | MAE / train-mean | "
          "load (start → end) |\n|---|---|---|---|---|---|---|---|---|---|---|---|")


def row(rec: dict[str, Any], ckpt: str = "best.pt") -> str:
    m = rec["checkpoints"][ckpt]
    b = rec["baselines"]["train_mean"]
    r = rec["recipe"]
    ld = rec["machine"]
    return (f"| {rec['name']}{'' if ckpt == 'best.pt' else ' (' + ckpt + ')'} | {m['gsd_m']:.3g} | {r['size']}/"
            f"{r['stride'] or r['size']} | {rec['train']['steps']} | {rec['train']['seconds']:.0f} | "
            f"{m['mae']:.2f} | {m['rmse']:.2f} | {m['mae_tall']:.2f} | {m['spearman_std_abs_err']:.2f} | "
            f"{b['mae']:.2f} / {b['rmse']:.2f} / {b['mae_tall']:.2f} | {m['mae'] / b['mae']:.2f} | "
            f"{ld['load_start'][0]:.1f} → {ld['load_end'][0]:.1f} |")


def table(out: Path) -> str:
    recs = [json.loads(p.read_text()) for p in sorted((out / "runs").glob("*/result.json"), key=os.path.getmtime)]
    lines = [HEADER]
    for rec in recs:
        for ckpt in rec["checkpoints"]:
            lines.append(row(rec, ckpt))
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recipe", default="scratch", help="a name from --list")
    ap.add_argument("--name", help="run name (default: the recipe's)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="config override, e.g. --set optim.name=adamw --set optim.weight_decay=1e-4")
    ap.add_argument("--gsd", type=float, help="override the recipe's working GSD (m)")
    ap.add_argument("--size", type=int, help="override the recipe's patch size (px)")
    ap.add_argument("--stride", type=int, help="override the recipe's patch stride (px)")
    ap.add_argument("--budget-mpx", type=float, default=600 * 8 * 128 * 128 / 1e6,
                    help="training budget in megapixels of patches processed (steps x batch x side^2); the default "
                         "is 600 steps of 8 patches of 128^2, about 10 min on 2 quiet cores")
    ap.add_argument("--max-steps", type=int, help="a step budget instead of --budget-mpx")
    ap.add_argument("--val-steps", type=int, default=20, help="validate about every this many steps")
    ap.add_argument("--max-time", type=float, default=3600.0, help="wall-clock cap of the training (s)")
    ap.add_argument("--mc", type=int, default=16, help="MC-dropout samples at prediction")
    ap.add_argument("--also-last", action="store_true", help="evaluate last.pt too")
    ap.add_argument("--init", help="fine-tune from this checkpoint or shipped start name (train --init)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--split", choices=sorted(SPLITS), default=DEFAULT_SPLIT,
                    help="where validation is (the test block is the same): see SPLITS")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--out", type=Path, default=ROOT / "experiments" / "out" / "real_data")
    ap.add_argument("--snapshots", help="comma-separated steps at which to keep snap_<step>.pt (last) and "
                    "best_<step>.pt (best so far) for learning curves")
    ap.add_argument("--no-eval", action="store_true", help="train only (evaluate later with --evaluate)")
    ap.add_argument("--evaluate", metavar="RUN", help="evaluate the snapshots of run RUN (test block, with and "
                    "without calibration fitted on val) into OUT/runs/RUN/curve.json")
    ap.add_argument("--only", help="with --evaluate: only checkpoints whose name starts with this (e.g. best_)")
    ap.add_argument("--curves", action="store_true", help="print the learning curves (every curve.json) as Markdown")
    ap.add_argument("--force", action="store_true", help="with --evaluate: redo checkpoints already in curve.json")
    ap.add_argument("--quiet", action="store_true")
    ap.add_argument("--list", action="store_true", help="list the recipes")
    ap.add_argument("--table", action="store_true", help="print every result in OUT as a Markdown table")
    args = ap.parse_args()
    if args.list:
        for k, r in RECIPES.items():
            print(f"{k}: {r.note}\n    {r}")
        return
    if args.table:
        print(table(args.out))
        return
    if args.evaluate:
        evaluate_run(args.evaluate, args)
        return
    if args.curves:
        print(curve_table(args.out))
        return
    recipe = RECIPES[args.recipe]
    changes = {k: getattr(args, k) for k in ("gsd", "size", "stride") if getattr(args, k) is not None}
    if changes:
        recipe = Recipe(**{**asdict(recipe), **changes})
    rec = run(args.name or args.recipe, recipe, args)
    if args.no_eval:
        print(json.dumps(rec["train"], default=float)[:2000])
        return
    print(HEADER)
    for ckpt in rec["checkpoints"]:
        print(row(rec, ckpt))
    print(f"CPU: {rec['machine']['cpu']}; train-mean value {rec['baselines']['train_mean_value_m']:.2f} m; "
          f"all-ground MAE {rec['baselines']['zero']['mae']:.2f} m")


if __name__ == "__main__":
    main()
