"""Issue 28's study: is the height spread right per height range on ``autzen_west``'s held-out block?

For each training run of ``experiments/real_data/run.py`` (same fixed split, tiles, budget; ``--out`` the same folder),
this script takes the checkpoint validation chose (``best.pt``) and evaluates on the **test block** (never used
to choose anything):

* ``raw`` — ``predict`` with calibration off (T MC samples; the aleatoric spread too for a model with
  ``model.aleatoric``);
* ``cal`` — the calibration ``train`` now fits (:func:`aerialmtl.models.calibration.fit_calibration` with two
  folds of validation patches: each part applied only where it beat none on held-out val patches; the spread
  per range of predicted height);
* ``legacy`` — the previous calibration (isotonic height map always applied, one spread factor and floor for
  all heights), to compare with what users had;
* ``height_only`` — a spread that follows the predicted height alone, ``σ = a·h ⊕ b`` fitted on validation
  (lowest CRPS): what a spread must beat to carry information beyond the height;
* ``tta`` (``--tta``) — flips and 90° rotations averaged into the MC statistics (no training).
* ``--val-block`` — the validation block predicted raw and with ``--tta`` and evaluated as the test block is
  (``study.json`` ``val_block``): what the choice of ``--tta`` for a recipe may look at.

Per variant: MAE, MAE and bias on pixels ≥ 2 m, and per reference-height bin (0–1, 1–2, 2–5, 5–10, 10–20,
≥ 20 m): share, bias, MAE, ±1σ/±2σ coverage, median std / median |error|, Spearman(std, |error|) within the
bin, Gaussian NLL and CRPS, the largest std. Results go to ``OUT/runs/<run>/study.json``;
``--table`` prints every run as Markdown (mean and range over seeds, grouped by arm = run name without
``_s<seed>``).

Usage::

    python -m experiments.uncertainty.run --out /work/study --runs lite0_in_s0 al_b0_s0 --mc 16
    python -m experiments.uncertainty.run --out /work/study --table
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import torch

from aerialmtl.formats.checkpoint import load_model  # noqa: E402
from aerialmtl.formats.prediction import FLOAT_NODATA, HEIGHT, HEIGHT_STD, layer_filename  # noqa: E402
from aerialmtl.inference.predict import predict_raster  # noqa: E402
from aerialmtl.models.calibration import Calibration, fit_calibration, fit_height_map  # noqa: E402
from aerialmtl.models.spread_fit import fit_spread, fit_spread_crps  # noqa: E402
from aerialmtl.training.calibrate import patch_folds, validation_pixels  # noqa: E402
from experiments.common.autzen import DATA, ORTHO, TALL_M, cpu_model
from experiments.common.maps import constant_prediction, train_mean, write_like
from experiments.common.reports import evaluate_dir, evaluate_spread
from experiments.common.study import fmt_range as _fmt_range


def transformed_copy(pred_dir: Path, out_dir: Path, height_fn: Any, std_fn: Any) -> Path:
    """``pred_dir``'s height and height_std through ``height_fn(h)`` and ``std_fn(s, h)`` (raw h), nodata kept."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with rasterio.open(pred_dir / layer_filename(HEIGHT)) as src:
        h = src.read(1)
    with rasterio.open(pred_dir / layer_filename(HEIGHT_STD)) as src:
        s = src.read(1)
    nod = h == FLOAT_NODATA
    write_like(pred_dir / layer_filename(HEIGHT), np.where(nod, FLOAT_NODATA, height_fn(h)), out_dir / "height.tif")
    write_like(pred_dir / layer_filename(HEIGHT_STD), np.where(nod, FLOAT_NODATA, std_fn(s, h)),
               out_dir / "height_std.tif")
    return out_dir


def val_scores(pred: np.ndarray, ref: np.ndarray, sd: np.ndarray) -> dict[str, float]:
    """What the choice between arms may look at: the validation patches' MAE, MAE and bias ≥ 2 m, and the raw
    spread's ±1σ coverage, CRPS and Gaussian NLL (the test block is never used to choose)."""
    from aerialmtl.evaluation.uncertainty import crps_gaussian, gaussian_nll_terms

    err = pred - ref
    tall = ref >= TALL_M
    return {"mae": float(np.abs(err).mean()), "mae_tall": float(np.abs(err[tall]).mean()),
            "bias_tall": float(err[tall].mean()), "coverage_1sigma": float(np.mean(np.abs(err) <= sd)),
            "crps_gaussian_m": float(crps_gaussian(pred, sd, ref).mean()),
            "nll_gaussian": float(gaussian_nll_terms(pred, sd, ref).mean()), "n_pixels": int(pred.size)}


def legacy_calibration(pred: np.ndarray, ref: np.ndarray, sd: np.ndarray) -> Calibration:
    """The calibration of the previous release: the isotonic height map always applied, one spread factor and
    floor for all heights fitted to ±1σ / ±2σ coverage (:func:`fit_spread`)."""
    x, y = fit_height_map(pred, ref, "isotonic")
    cal = Calibration(tuple(float(v) for v in x), tuple(float(v) for v in y))
    scale, floor = fit_spread(np.abs(cal.height(pred) - ref), sd)
    return dataclasses.replace(cal, std_scale=scale, std_floor=floor)


def height_only(pred: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """``(a, b)`` of σ = a·max(h, 0) ⊕ b with the lowest validation CRPS (the spread calibration's own fit, on
    the predicted height instead of the model's spread: the strongest height-only spread of that form)."""
    return fit_spread_crps(np.abs(pred - ref), np.maximum(pred, 0.0))


def study_run(name: str, args: argparse.Namespace) -> dict[str, Any]:
    rdir = args.out / "runs" / name
    import yaml

    cfg = yaml.safe_load((rdir / "config.yaml").read_text())
    tdir = Path(cfg["data"]["dir"])
    split_dir = args.out / "split_middle-val"
    test_aoi = split_dir / "test.geojson"
    out_file = rdir / "study.json"
    res: dict[str, Any] = json.loads(out_file.read_text()) if out_file.is_file() and not args.force else {}
    t0, load0 = time.perf_counter(), os.getloadavg()
    ckpt = rdir / args.checkpoint
    model, meta = load_model(ckpt)
    res["step"] = int(torch.load(ckpt, weights_only=True)["train_state"]["step"])
    res["config"] = {"aleatoric": meta.model.aleatoric, "task_activation": meta.model.task_activation,
                     "nll_beta": cfg["loss"].get("nll_beta", 0.0), "encoder": meta.model.encoder, "seed": cfg["seed"]}
    pdir = rdir / f"study_raw_{args.checkpoint.removesuffix('.pt')}"
    variants = res.setdefault("test", {})
    if "raw" not in variants:
        predict_raster(args.data / ORTHO, (model, meta), pdir, mc=args.mc, aoi=test_aoi, overwrite=True,
                       progress=False, checkpoint_name=str(ckpt), calibration=False, seed=0)
        variants["raw"] = evaluate_spread(pdir, args.data, rdir / "study_report_raw.json")
    pred, ref, sd, patch = validation_pixels(model, meta, tdir, mc=args.mc)
    folds = patch_folds(patch)
    res["val"] = val_scores(pred, ref, sd)
    cals: dict[str, Calibration] = {
        "cal": fit_calibration(pred, ref, sd, "isotonic", folds=folds),
        "legacy": legacy_calibration(pred, ref, sd),
    }
    res["calibration"] = {k: c.summary() for k, c in cals.items()}
    for key, c in cals.items():
        if key not in variants or args.force or key in args.redo:
            cdir = transformed_copy(pdir, rdir / f"study_{key}", c.height, c.std)
            variants[key] = evaluate_spread(cdir, args.data, rdir / f"study_report_{key}.json")
    if "height_only" not in variants or args.force:
        a, b = height_only(pred, ref)
        res["height_only_fit"] = {"a": a, "b": b}
        cdir = transformed_copy(pdir, rdir / "study_height_only", lambda h: h,
                                lambda s, h: np.hypot(a * np.maximum(h, 0.0), b))
        variants["height_only"] = evaluate_spread(cdir, args.data, rdir / "study_report_height_only.json")
    if args.tta and ("tta" not in variants or args.force):
        tdir_out = rdir / "study_tta"
        predict_raster(args.data / ORTHO, (model, meta), tdir_out, mc=args.mc, aoi=test_aoi, overwrite=True,
                       progress=False, checkpoint_name=str(ckpt), calibration=False, seed=0, tta=True)
        variants["tta"] = evaluate_spread(tdir_out, args.data, rdir / "study_report_tta.json")
    if args.val_block:  # the validation block predicted as the test block is: what may choose `--tta`
        blocks = res.setdefault("val_block", {})
        for key, views in (("raw", False), ("tta", True)):
            if key not in args.val_views:
                continue
            if key not in blocks or args.force:
                vdir = rdir / f"study_valblock_{key}"
                predict_raster(args.data / ORTHO, (model, meta), vdir, mc=args.mc, aoi=split_dir / "val.geojson",
                               overwrite=True, progress=False, checkpoint_name=str(ckpt), calibration=False, seed=0,
                               tta=views)
                blocks[key] = evaluate_spread(vdir, args.data, rdir / f"study_report_valblock_{key}.json")
    if "baseline_train_mean" not in res:
        mean = train_mean(pdir / layer_filename(HEIGHT), args.data, split_dir / "train.geojson")
        bdir = constant_prediction(pdir, mean, rdir / "study_baseline_train_mean")
        res["baseline_train_mean"] = {"value_m": mean, **evaluate_dir(bdir, args.data,
                                                                      rdir / "study_report_baseline.json")}
    res["eval"] = {"seconds": time.perf_counter() - t0, "load": [load0, os.getloadavg()], "cpu": cpu_model(),
                   "mc": args.mc}
    out_file.write_text(json.dumps(res, indent=1, default=float))
    for k, v in variants.items():
        cov = " ".join(f"{b['coverage_1sigma'] or math.nan:.2f}" for b in v["bins"])
        rho = " ".join(f"{b['spearman_std_vs_abs_error'] or math.nan:+.2f}" for b in v["bins"])
        print(f"{name} {k}: MAE {v['mae']:.2f} MAE>=2 {v['mae_tall']:.2f} bias>=2 {v['bias_tall']:+.2f} "
              f"CRPS {v['crps_gaussian_m']:.2f} NLL {v['nll_gaussian']:.2f} cov1/bin {cov} rho/bin {rho}", flush=True)
    return res


def ensemble_run(name: str, members: list[str], args: argparse.Namespace) -> dict[str, Any]:
    """A deep ensemble of runs (seeds of one arm, each with its ``raw`` test prediction already made): the mean
    of the members' heights, spread ``sqrt(mean_m σ_m² + var_m μ_m)`` (each member's predictive variance, MC and
    aleatoric, plus the members' disagreement). Written as the pseudo-run ``OUT/runs/<name>`` (variant ``raw``
    on the test block, ``val`` on the validation patches), so ``--table`` lists it as an arm of one "seed"."""
    rdir = args.out / "runs" / name
    rdir.mkdir(parents=True, exist_ok=True)
    t0, load0 = time.perf_counter(), os.getloadavg()
    first = args.out / "runs" / members[0]
    import yaml

    cfg = yaml.safe_load((first / "config.yaml").read_text())
    tdir = Path(cfg["data"]["dir"])
    hs, vs = [], []
    for m in members:
        pdir = args.out / "runs" / m / f"study_raw_{args.checkpoint.removesuffix('.pt')}"
        with rasterio.open(pdir / layer_filename(HEIGHT)) as src:
            hs.append(src.read(1))
        with rasterio.open(pdir / layer_filename(HEIGHT_STD)) as src:
            vs.append(src.read(1).astype(np.float64) ** 2)
    h, v = np.stack(hs), np.stack(vs)
    nod = (h == FLOAT_NODATA).any(0)
    mean, std = h.mean(0), np.sqrt(v.mean(0) + h.var(0))
    out_dir = rdir / "study_ensemble"
    out_dir.mkdir(exist_ok=True)
    src_dir = first / f"study_raw_{args.checkpoint.removesuffix('.pt')}"
    write_like(src_dir / layer_filename(HEIGHT), np.where(nod, FLOAT_NODATA, mean), out_dir / "height.tif")
    write_like(src_dir / layer_filename(HEIGHT_STD), np.where(nod, FLOAT_NODATA, std), out_dir / "height_std.tif")
    import shutil

    shutil.copy(src_dir / "prediction.json", out_dir / "prediction.json")
    res: dict[str, Any] = {"members": members, "test": {"raw": evaluate_spread(out_dir, args.data,
                                                                               rdir / "study_report_raw.json")}}
    preds, sds = [], []
    for m in members:
        model, meta = load_model(args.out / "runs" / m / args.checkpoint)
        pred, ref, sd, _patch = validation_pixels(model, meta, tdir, mc=args.mc)
        preds.append(pred)
        sds.append(sd.astype(np.float64) ** 2)
    p, q = np.stack(preds), np.stack(sds)
    res["val"] = val_scores(p.mean(0), ref, np.sqrt(q.mean(0) + p.var(0)))
    res["config"] = {"ensemble_of": members}
    res["eval"] = {"seconds": time.perf_counter() - t0, "load": [load0, os.getloadavg()], "cpu": cpu_model(),
                   "mc": args.mc}
    (rdir / "study.json").write_text(json.dumps(res, indent=1, default=float))
    v0 = res["test"]["raw"]
    print(f"{name}: MAE {v0['mae']:.2f} MAE>=2 {v0['mae_tall']:.2f} bias>=2 {v0['bias_tall']:+.2f} CRPS "
          f"{v0['crps_gaussian_m']:.2f} cov1/bin " + " ".join(f"{b['coverage_1sigma'] or math.nan:.2f}"
                                                             for b in v0["bins"])
          + " rho/bin " + " ".join(f"{b['spearman_std_vs_abs_error'] or math.nan:+.2f}" for b in v0["bins"]),
          flush=True)
    return res


def table(out: Path) -> str:
    """Markdown: per arm (runs grouped without their ``_s<seed>``) and variant, mean (range) over seeds."""
    arms: dict[str, list[dict[str, Any]]] = {}
    for f in sorted((out / "runs").glob("*/study.json")):
        arm = f.parent.name.rsplit("_s", 1)[0]
        arms.setdefault(arm, []).append(json.loads(f.read_text()))
    lines = ["| arm | variant | seeds | MAE (m) | MAE ≥ 2 m (m) | bias ≥ 2 m (m) | ±1σ | CRPS (m) | NLL | "
             "±1σ per bin (0–1, 1–2, 2–5, 5–10, 10–20, ≥ 20 m) | Spearman per bin | median std / MAE per bin |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    detail = []
    for arm, recs in arms.items():
        for variant in ("raw", "cal", "legacy", "height_only", "tta"):
            vs = [r["test"][variant] for r in recs if variant in r.get("test", {})]
            if not vs:
                continue
            nb = len(vs[0]["bins"])

            def per(key: str, vs: list[dict[str, Any]] = vs, nb: int = nb) -> str:
                return " / ".join(
                    f"{np.nanmean([np.nan if v['bins'][k][key] is None else v['bins'][k][key] for v in vs]):.2f}"
                    for k in range(nb))
            ratio = " / ".join(f"{np.nanmean([(v['bins'][k]['median_std_m'] or np.nan) / max(v['bins'][k]['mae'], 1e-9) for v in vs]):.2f}"  # noqa: E501
                               for k in range(nb))
            lines.append(f"| {arm} | {variant} | {len(vs)} | {_fmt_range([v['mae'] for v in vs])} | "
                         f"{_fmt_range([v['mae_tall'] for v in vs])} | {_fmt_range([v['bias_tall'] for v in vs], sign=True)} | "  # noqa: E501
                         f"{_fmt_range([v['coverage_1sigma'] for v in vs])} | {_fmt_range([v['crps_gaussian_m'] for v in vs])} | "  # noqa: E501
                         f"{_fmt_range([v['nll_gaussian'] for v in vs])} | {per('coverage_1sigma')} | "
                         f"{per('spearman_std_vs_abs_error')} | {ratio} |")
        vals = [r["val"] for r in recs if "val" in r]
        if vals:
            detail.append(f"- {arm} on VALIDATION (raw): MAE {_fmt_range([v['mae'] for v in vals])}, MAE ≥ 2 m "
                          f"{_fmt_range([v['mae_tall'] for v in vals])}, bias ≥ 2 m "
                          f"{_fmt_range([v['bias_tall'] for v in vals], sign=True)}, ±1σ "
                          f"{_fmt_range([v['coverage_1sigma'] for v in vals])}, CRPS "
                          f"{_fmt_range([v['crps_gaussian_m'] for v in vals])} m, NLL "
                          f"{_fmt_range([v['nll_gaussian'] for v in vals], 1)}")
        steps = ", ".join(str(r.get("step", "ensemble")) for r in recs)
        base = recs[0].get("baseline_train_mean")
        detail.append(f"- {arm}: best.pt steps {steps}; calibration fitted: {recs[0].get('calibration', {}).get('cal')}"
                      + (f"; train-mean baseline {base['value_m']:.2f} m: MAE {base['mae']:.2f}, "
                         f"MAE ≥ 2 m {base['mae_tall']:.2f}" if base else ""))
    return "\n".join(lines + [""] + detail)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="the experiments/real_data/run.py --out folder")
    ap.add_argument("--runs", nargs="*", default=[])
    ap.add_argument("--checkpoint", default="best.pt")
    ap.add_argument("--mc", type=int, default=16)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--force", action="store_true")
    ap.add_argument("--tta", action="store_true", help="also the tta variant (8 views × T samples)")
    ap.add_argument("--val-block", action="store_true",
                    help="also predict the validation block (raw and --tta) and evaluate it like the test block")
    ap.add_argument("--val-views", nargs="*", default=["raw", "tta"], choices=["raw", "tta"],
                    help="with --val-block: which predictions of the validation block (tta costs 8x raw)")
    ap.add_argument("--redo", nargs="*", default=[], help="variants to compute again (e.g. cal legacy)")
    ap.add_argument("--table", action="store_true")
    ap.add_argument("--ensemble", nargs="+", metavar=("NAME", "MEMBER"),
                    help="NAME MEMBER...: a deep ensemble of the member runs (their raw predictions must exist)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.table:
        print(table(args.out))
        return
    if args.ensemble:
        ensemble_run(args.ensemble[0], args.ensemble[1:], args)
    for name in args.runs:
        study_run(name, args)


if __name__ == "__main__":
    main()
