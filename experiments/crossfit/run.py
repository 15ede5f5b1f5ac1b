"""Issue 28, fifth stage: an error model trained on out-of-fold errors (a cross-fit over the training block).

Every earlier arm learnt its spread from the training block's own errors, where the model fits its buildings, so
the spread followed the predicted height and ranked the tall misses backwards. Here the spread
is learnt from errors the model makes on areas it did **not** train on:

1. ``experiments/real_data/run.py --split cv3-a|cv3-b|cv3-c`` trains the recipe three times, each on two of the training
   block's three bands (same validation band, same budget); each fold model predicts its held-out band (raw,
   T = 16: ``OUT/runs/<fold run>/cf_oof``). Together they give out-of-fold maps of the whole training block.
2. The recipe's own models (``al_b0_s<seed>``, trained on the whole training block) predict the validation band
   (``cf_val``) and the test block (``cf_test``) the same way.
3. Per pixel of every map, features of the prediction and the orthophoto (:func:`features`); on the out-of-fold
   pixels of one seed's three fold models, gradient-boosted trees (scikit-learn's ``HistGradientBoostingRegressor``)
   learn the 68.27 % quantile of |error| (a one-σ half-width), the number of rounds chosen by leave-one-band-out
   cross-validation. (A height correction learnt the same way, the median of the signed error, was tried first: it
   learnt the held-out bands' own buildings from their colours and doubled the validation MAE, 2.28 → 4.63 m.)
4. The recipe's maps, with the error model's spread, are scored on the validation band (what may
   choose) and the test block (reported only), with ``aerialmtl evaluate``'s per-bin numbers
   (``experiments/uncertainty/run.py``'s ``evaluate``): ``OUT/runs/<base run>/crossfit.json``; ``--table`` prints them.

Nothing here ships unless it is measured better on validation. Usage::

    python -m experiments.crossfit.run --out /work/study --seeds 0 1 2 --table
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import rasterio
from rasterio.enums import Resampling
from rasterio.vrt import WarpedVRT
from scipy import ndimage

from aerialmtl.formats.checkpoint import load_model  # noqa: E402
from aerialmtl.formats.prediction import FLOAT_NODATA  # noqa: E402
from aerialmtl.inference.predict import predict_raster  # noqa: E402
from experiments.common.autzen import DATA, ORTHO, cpu_model
from experiments.common.maps import load, neighbourhood, write_like
from experiments.common.reports import evaluate_spread

FOLDS = ("cv3a", "cv3b", "cv3c")
FOLD_SPLIT = {"cv3a": "cv3-a", "cv3b": "cv3-b", "cv3c": "cv3-c"}
ONE_SIGMA = 0.6827
MC = 16


def predict(out: Path, run: str, block_geojson: Path, name: str) -> Path:
    """``run``'s ``best.pt`` on the AOI ``block_geojson`` (raw, T = 16, seed 0) into ``OUT/runs/<run>/<name>``."""
    rdir = out / "runs" / run
    pdir = rdir / name
    if not (pdir / "height_std.tif").is_file():
        model, meta = load_model(rdir / "best.pt")
        predict_raster(DATA / ORTHO, (model, meta), pdir, mc=MC, aoi=block_geojson, overwrite=True, progress=False,
                       checkpoint_name=str(rdir / "best.pt"), calibration=False, seed=0)
    return pdir


def ortho_on(grid_file: Path) -> np.ndarray:
    """The orthophoto's RGB averaged onto ``grid_file``'s grid: (3, H, W) float32 in 0-1."""
    with rasterio.open(grid_file) as g:
        crs, transform, width, height = g.crs, g.transform, g.width, g.height
    with rasterio.open(DATA / ORTHO) as src, WarpedVRT(src, crs=crs, transform=transform, width=width,
                                                         height=height, resampling=Resampling.average) as vrt:
        return vrt.read(indexes=[1, 2, 3]).astype(np.float32) / 255.0


def _local_std(a: np.ndarray, size: int) -> np.ndarray:
    m = ndimage.uniform_filter(a, size)
    return np.sqrt(np.maximum(ndimage.uniform_filter(a * a, size) - m * m, 0.0))


class Pixels(NamedTuple):
    """A prediction folder's pixels: ``x`` (N, F) float32 features named ``names``, ``height``, ``std`` and
    ``reference`` (metres) of the N valid pixels, and the full maps (``height_map``, ``std_map``: NaN where nodata)
    with the ``valid`` mask that picked them."""

    x: np.ndarray
    names: list[str]
    height: np.ndarray
    std: np.ndarray
    reference: np.ndarray
    height_map: np.ndarray
    std_map: np.ndarray
    valid: np.ndarray


def features(folder: Path) -> Pixels:
    """The :class:`Pixels` of a prediction folder (its maps and reference read once).

    Features: the predicted height μ and spread s; for r = 2, 5, 10, 20 px the highest μ within r minus μ, the
    local mean and standard deviation of μ, the lowest μ; the local standard deviation of s (r = 5); the
    orthophoto's R, G, B (averaged onto the 1 m grid), brightness texture (local std at 3 and 9 px), excess green
    2G - R - B and its local mean (9 px).
    """
    h, s, ref = load(folder)
    valid = np.isfinite(h) & np.isfinite(s) & np.isfinite(ref)
    hh = np.where(np.isfinite(h), h, 0.0)
    cols: dict[str, np.ndarray] = {"mu": hh, "s": np.where(np.isfinite(s), s, 0.0)}
    for r in (2, 5, 10, 20):
        size = 2 * r + 1
        cols[f"dmax{r}"] = neighbourhood(h, r)
        cols[f"mean{r}"] = ndimage.uniform_filter(hh, size)
        cols[f"std{r}"] = _local_std(hh, size)
        cols[f"min{r}"] = ndimage.minimum_filter(np.where(np.isfinite(h), h, 1e9), size=size)
    cols["s_std5"] = _local_std(cols["s"], 11)
    rgb = ortho_on(folder / "height.tif").astype(np.float64)
    bright = rgb.mean(axis=0)
    cols.update(r=rgb[0], g=rgb[1], b=rgb[2], tex3=_local_std(bright, 3), tex9=_local_std(bright, 9))
    exg = 2 * rgb[1] - rgb[0] - rgb[2]
    cols.update(exg=exg, exg9=ndimage.uniform_filter(exg, 9))
    x = np.stack([c[valid] for c in cols.values()], axis=1).astype(np.float32)
    return Pixels(x, list(cols), h[valid], s[valid], ref[valid], h, s, valid)


def write_maps(folder: Path, px: Pixels, dst: Path, height: np.ndarray, std: np.ndarray) -> Path:
    """A prediction folder like ``folder`` (whose :class:`Pixels` are ``px``) with ``height`` and ``std`` on its
    valid pixels (in ``px``'s order); the other pixels keep the folder's values or nodata."""
    dst.mkdir(parents=True, exist_ok=True)
    for name, values, fallback in (("height.tif", height, px.height_map), ("height_std.tif", std, px.std_map)):
        out = np.where(np.isfinite(fallback), fallback, FLOAT_NODATA)
        out[px.valid] = values
        write_like(folder / name, out, dst / name)
    return dst


ITERATIONS = (50, 100, 200, 400, 800)


def _quantile_model(max_iter: int, seed: int) -> Any:
    from sklearn.ensemble import HistGradientBoostingRegressor

    return HistGradientBoostingRegressor(loss="quantile", quantile=ONE_SIGMA, max_iter=max_iter, learning_rate=0.05,
                                         max_leaf_nodes=31, min_samples_leaf=500, early_stopping=False,
                                         warm_start=True, random_state=seed)


def _pinball(y: np.ndarray, q: np.ndarray) -> float:
    d = y - q
    return float(np.mean(np.maximum(ONE_SIGMA * d, (ONE_SIGMA - 1) * d)))


def fit_models(x: np.ndarray, err: np.ndarray, group: np.ndarray, seed: int) -> dict[str, Any]:
    """The error model on out-of-fold pixels: the 68.27 % quantile of |err| (a one-σ half-width), by gradient-boosted
    trees whose number of rounds is chosen by leave-one-band-out cross-validation over the three folds (the pixels of
    one band are spatially correlated: a random hold-out would pick a model that memorises the band's buildings).
    Returns the model and the cross-validated pinball loss per number of rounds."""
    ay = np.abs(err)
    loss: dict[int, list[float]] = {it: [] for it in ITERATIONS}
    for g in np.unique(group):
        tr = group != g
        m = _quantile_model(ITERATIONS[0], seed)
        for it in ITERATIONS:
            m.set_params(max_iter=it)
            m.fit(x[tr], ay[tr])
            loss[it].append(_pinball(ay[~tr], m.predict(x[~tr])))
    mean = {it: float(np.mean(v)) for it, v in loss.items()}
    best = min(mean, key=lambda k: mean[k])
    return {"sigma": _quantile_model(best, seed).fit(x, ay), "rounds": best, "cv_pinball": mean}


def variants(models: dict[str, Any], x: np.ndarray, h: np.ndarray, s: np.ndarray) -> dict[str, tuple[np.ndarray,
                                                                                                      np.ndarray]]:
    """The maps scored per seed, all with the raw heights: ``raw`` (the model's spread s); ``cf_q68`` (the error
    model's one-σ half-width q, floored at 0.1 m); ``cf_mix`` (√(q² + (s/2)²): the error model with half the model's
    spread under it, against q's small values on ground)."""
    q = np.maximum(models["sigma"].predict(x), 0.01)
    return {"raw": (h, s), "cf_q68": (h, np.maximum(q, 0.1)), "cf_mix": (h, np.hypot(q, 0.5 * s))}


def study_seed(out: Path, seed: int, base: str) -> dict[str, Any]:
    """One seed: out-of-fold maps, the error model, the recipe's maps scored with it (maps already predicted are
    reused); writes and returns ``crossfit.json``."""
    t0, load0 = time.perf_counter(), os.getloadavg()
    mid = out / "split_middle-val"
    xs, es, gs = [], [], []
    for i, f in enumerate(FOLDS):
        run = f"{f}_s{seed}"
        pdir = predict(out, run, out / f"split_{FOLD_SPLIT[f]}" / "test.geojson", "cf_oof")
        px = features(pdir)
        xs.append(px.x)
        es.append(px.reference - px.height)
        gs.append(np.full(len(px.x), i))
    x_oof, e_oof = np.concatenate(xs), np.concatenate(es)
    models = fit_models(x_oof, e_oof, np.concatenate(gs), seed)
    brun = f"{base}_s{seed}"
    rdir = out / "runs" / brun
    res: dict[str, Any] = {"seed": seed, "oof_pixels": int(len(x_oof)), "features": px.names,
                           "oof_mae": float(np.abs(e_oof).mean()),
                           "rounds": models["rounds"], "cv_pinball": models["cv_pinball"]}
    for block, aoi in (("val", mid / "val.geojson"), ("test", mid / "test.geojson")):
        pdir = predict(out, brun, aoi, f"cf_{block}")
        px = features(pdir)
        scored: dict[str, Any] = {}
        for key, (hv, sv) in variants(models, px.x, px.height, px.std).items():
            vdir = write_maps(pdir, px, rdir / f"cf_{block}_{key}", hv, sv)
            scored[key] = evaluate_spread(vdir, DATA, rdir / f"cf_report_{block}_{key}.json")
        res[block] = scored
    res["eval"] = {"seconds": time.perf_counter() - t0, "load": [load0, os.getloadavg()], "cpu": cpu_model()}
    (rdir / "crossfit.json").write_text(json.dumps(res, indent=1, default=float))
    return res


def _row(block: str, key: str, rs: list[dict[str, Any]]) -> str:
    def m(k: str) -> str:
        v = [r[block][key][k] for r in rs]
        return f"{np.mean(v):.2f} ({min(v):.2f}–{max(v):.2f})"

    def per(k: str, fmt: str = "{:.2f}") -> str:
        nb = len(rs[0][block][key]["bins"])
        vals = []
        for i in range(nb):
            v = [r[block][key]["bins"][i][k] for r in rs]
            v = [x for x in v if x is not None]
            vals.append(fmt.format(np.mean(v)) if v else "–")
        return " / ".join(vals)

    def ratio() -> str:
        nb = len(rs[0][block][key]["bins"])
        vals = []
        for i in range(nb):
            v = [r[block][key]["bins"][i]["median_std_m"] / max(r[block][key]["bins"][i]["mae"], 1e-9) for r in rs]
            vals.append(f"{np.mean(v):.2f}")
        return " / ".join(vals)

    return (f"| {block} | {key} | {len(rs)} | {m('mae')} | {m('mae_tall')} | {m('bias_tall')} | "
            f"{m('coverage_1sigma')} | {m('crps_gaussian_m')} | {m('nll_gaussian')} | {per('coverage_1sigma')} | "
            f"{per('spearman_std_vs_abs_error', '{:+.2f}')} | {ratio()} |")


def table(out: Path, base: str) -> str:
    rs = [json.loads(p.read_text()) for p in sorted(out.glob(f"runs/{base}_s*/crossfit.json"))]
    if not rs:
        return "(no results)"
    lines = ["| block | variant | seeds | MAE | MAE ≥ 2 m | bias ≥ 2 m | ±1σ | CRPS | NLL | ±1σ per bin | "
             "Spearman per bin | median std / MAE per bin |", "|" + "---|" * 12]
    for block in ("val", "test"):
        for key in rs[0][block]:
            lines.append(_row(block, key, rs))
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="the experiments/real_data/run.py --out folder")
    ap.add_argument("--seeds", type=int, nargs="*", default=[], help="seeds whose fold and base runs to study")
    ap.add_argument("--base", default="al_b0", help="the recipe's run name without _s<seed>")
    ap.add_argument("--table", action="store_true", help="print every studied seed as Markdown")
    ap.add_argument("--threads", type=int, default=2, help="torch threads for the predictions")
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    for seed in args.seeds:
        res = study_seed(args.out, seed, args.base)
        for block in ("val", "test"):
            for key, v in res[block].items():
                cov = " ".join(f"{b['coverage_1sigma'] or math.nan:.2f}" for b in v["bins"])
                rho = " ".join(f"{b['spearman_std_vs_abs_error'] or math.nan:+.2f}" for b in v["bins"])
                print(f"s{seed} {block} {key}: MAE {v['mae']:.3f} MAE>=2 {v['mae_tall']:.2f} "
                      f"bias>=2 {v['bias_tall']:+.2f} CRPS {v['crps_gaussian_m']:.3f} NLL {v['nll_gaussian']:.2f} "
                      f"cov1/bin {cov} rho/bin {rho}", flush=True)
    if args.table:
        print(table(args.out, args.base))


if __name__ == "__main__":
    main()
