"""The spread of the study's maps (issue 58's targets on ``height_std``): the calibration that was off, what the
within-bin targets measure, and two arms that did not help.

- ``--recalibrate``: the study's checkpoints calibrated again with the NLL-bounded spread fit
  (:func:`aerialmtl.training.calibrate.calibrate_checkpoint` into ``OUT/runs_cal``), both blocks predicted as the
  recipe arm (``--sun none --mc 16``: arm ``spreadfit``), then the study's table and CRPS / NLL per seed.
- ``--conditioning ARM``: bias and Spearman(std, |error|), Spearman(std, h) per bin of the *reference* height (the
  issue's targets) and per bin of the *predicted* height (what a user can select), from ARM's predictions.
- ``--quantile``: blends of the isotonic heights with a quantile map (validation block fitted, per seed),
  estimated from the recipe's predictions.
- ``--placement``: a third term in the spread, ``σ² = (a·std)² + f² + (p·rise)²`` with ``rise`` how much higher
  the predicted heights reach within 2 px (2 m): (a, f, p) per range of predicted height fitted on the validation
  patches (the product's calibration pixels), cross-fitted on two folds of patches, then applied to the held-out
  block's raw predictions.

Usage::

    python -m experiments.heights_from_the_sun.spread --out study58 --recalibrate
    python -m experiments.heights_from_the_sun.spread --out study58 --conditioning spreadfit --quantile --placement
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import rasterio

from experiments.heights_from_the_sun.run import DATA, MC, _reference_on, _report, _val_block, table

BLOCKS = ("val", "test")
#: Half-width (pixels) of the square in which the placement term's rise is taken.
RISE_PX = 2


def _read(path: Path) -> np.ndarray:
    with rasterio.open(path) as src:
        a = src.read(1).astype(np.float64)
        return np.where(a == src.nodata, np.nan, a)


def _block(out: Path, arm: str, block: str, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(height, height_std, reference) of one prediction, 2-D, NaN where any is missing."""
    pred = out / "pred" / f"{arm}_{block}_s{seed}"
    h, sd, ref = _read(pred / "height.tif"), _read(pred / "height_std.tif"), _reference_on(pred / "height.tif")
    bad = ~(np.isfinite(h) & np.isfinite(sd) & np.isfinite(ref))
    return np.where(bad, np.nan, h), np.where(bad, np.nan, sd), np.where(bad, np.nan, ref)


def recalibrate(out: Path, seeds: list[int], threads: int) -> None:
    """Calibrate each seed's best.pt again (a copy) and predict both blocks with it (each step kept once done)."""
    from aerialmtl.training.calibrate import calibrate_checkpoint

    blocks = {"val": _val_block(out), "test": DATA / "test_block.geojson"}
    for seed in seeds:
        ckpt = out / "runs_cal" / f"s{seed}" / "best.pt"
        if not ckpt.is_file():
            ckpt.parent.mkdir(parents=True, exist_ok=True)
            cal = calibrate_checkpoint(out / "runs" / f"s{seed}" / "best.pt", out / "tiles", out=ckpt)
            print(f"seed {seed}: {cal.summary()}", flush=True)
        for block, aoi in blocks.items():
            pred = out / "pred" / f"spreadfit_{block}_s{seed}"
            if not (pred / "prediction.json").is_file():
                subprocess.run([sys.executable, "-m", "aerialmtl", "predict", str(DATA / "ortho_1ft.tif"), "--model",
                                str(ckpt), "--aoi", str(aoi), "--mc", str(MC), "--out", str(pred), "--overwrite",
                                "--quiet", "--sun", "none"], check=True,
                               env={**os.environ, "OMP_NUM_THREADS": str(threads)})
    print(table(out, seeds, arms=("recipe", "spreadfit"), shadow_arms=()))
    for block in BLOCKS:
        for arm in ("recipe", "spreadfit"):
            cells = []
            for seed in seeds:
                u = _report(out / "pred" / f"{arm}_{block}_s{seed}")["uncertainty"]["height_std"]
                cells.append(f"CRPS {u['strata']['crps_gaussian_m']:.3f} NLL {u['strata']['nll_gaussian']:.2f} "
                             f"±1σ {u['coverage_1sigma']:.2f} ±2σ {u['coverage_2sigma']:.2f}")
            print(f"{block} {arm}: " + " | ".join(cells))


def conditioning(out: Path, seeds: list[int], arm: str) -> None:
    """Per bin of reference and of predicted height, mean over seeds: bias, Spearman(std, |err|), Spearman(std, h)."""
    from scipy.stats import spearmanr

    bins = ((0.0, 1.0), (1.0, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, 20.0))
    for block in BLOCKS:
        rows: dict[str, list[list[float]]] = {"reference": [], "predicted": []}
        for seed in seeds:
            h, sd, ref = _block(out, arm, block, seed)
            ok = np.isfinite(h)
            h, sd, ref = h[ok], sd[ok], ref[ok]
            err = np.abs(h - ref)
            for by, key in (("reference", ref), ("predicted", h)):
                row = []
                for lo, hi in bins:
                    q = (key >= lo) & (key < hi)
                    row += [float(np.mean(h[q] - ref[q])), float(spearmanr(sd[q], err[q])[0]),
                            float(spearmanr(sd[q], h[q])[0])]
                rows[by].append(row)
        for by, vals in rows.items():
            v = np.mean(vals, axis=0).reshape(len(bins), 3)
            print(f"{block}, bins of {by} height " + " | ".join(
                f"{lo:g}–{hi:g} m: bias {b:+.2f}, ρ(std,|e|) {r:+.2f}, ρ(std,h) {rh:+.2f}"
                for (lo, hi), (b, r, rh) in zip(bins, v, strict=True)))


def quantile_arm(out: Path, seeds: list[int]) -> None:
    """(1 − λ)·h + λ·Q(h), Q the validation block's quantile map of the recipe's heights onto the reference."""
    def qmap(h: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = np.linspace(0.0, 1.0, 65)
        x, idx = np.unique(np.quantile(h, q), return_index=True)
        return x, np.maximum.accumulate(np.quantile(ref, q)[idx])

    data = {(b, s): tuple(a[np.isfinite(a)] for a in _block(out, "recipe", b, s)[::2]) for b in BLOCKS for s in seeds}
    for lam in (0.0, 0.25, 0.5, 0.75, 1.0):
        for block in BLOCKS:
            rows = []
            for seed in seeds:
                x, y = qmap(*data[("val", seed)])
                h, ref = data[(block, seed)]
                mapped = np.where(h > x[-1], y[-1] + h - x[-1], np.interp(h, x, y))
                hq = (1.0 - lam) * h + lam * mapped
                e, tall, b10 = hq - ref, ref >= 2.0, (ref >= 10.0) & (ref < 20.0)
                rows.append([np.abs(e).mean(), np.abs(e[tall]).mean(), e[tall].mean(), e[b10].mean()])
            v = np.mean(rows, axis=0)
            print(f"λ {lam:.2f} {block}: MAE {v[0]:.2f}, MAE ≥ 2 m {v[1]:.2f}, bias ≥ 2 m {v[2]:+.2f}, "
                  f"bias 10–20 m {v[3]:+.2f}")


def _rise(h: np.ndarray) -> np.ndarray:
    """How much higher the heights reach within :data:`RISE_PX` pixels (same shape, metres, ≥ 0; NaN as 0 m)."""
    import torch
    import torch.nn.functional as F

    t = torch.from_numpy(np.nan_to_num(h, nan=0.0)).double().reshape(-1, 1, *h.shape[-2:])
    r = F.max_pool2d(t, 2 * RISE_PX + 1, stride=1, padding=RISE_PX) - t
    return r.reshape(h.shape).numpy()


def _validation(out: Path, seed: int) -> dict[str, np.ndarray]:
    """The calibration's validation pixels of seed's best.pt with each pixel's rise (cached next to the runs)."""
    import torch

    from aerialmtl.data.batches import CachedBatches, eval_batches, prepare_batch
    from aerialmtl.data.cache import PatchCache, ensure_patch_cache
    from aerialmtl.data.transforms import build_eval_transform
    from aerialmtl.formats.checkpoint import load_model
    from aerialmtl.formats.tiles import TileFolderInfo, cache_dir
    from aerialmtl.models.mc_dropout import mc_predict

    cache = out / "runs" / f"s{seed}" / "val_pixels_rise.npz"
    if cache.is_file():
        return dict(np.load(cache))
    model, meta = load_model(out / "runs" / f"s{seed}" / "best.pt")
    info = TileFolderInfo.read(out / "tiles")
    index = ensure_patch_cache(info, "val", cache_dir(info.root))
    transform = build_eval_transform(None)
    data = CachedBatches(PatchCache(cache_dir(info.root), index), transform, ("height",))
    mean, std = torch.tensor(meta.mean), torch.tensor(meta.std)
    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("pred", "ref", "std", "rise", "patch")}
    model.eval()
    first = 0
    for k, spec in enumerate(eval_batches(index.count, 4)):  # as calibrate.validation_pixels: seed k per batch
        batch = prepare_batch(data[spec], transform, mean, std, torch.device("cpu"))
        with torch.no_grad():
            o = mc_predict(model, batch["image"], MC, seed=k, tasks=("height",))["height"]
        v = batch["height_valid"].numpy()
        m = o["mean"].numpy()
        for name, a in (("pred", m), ("ref", batch["height"].numpy()), ("std", o["std"].numpy()), ("rise", _rise(m)),
                        ("patch", np.broadcast_to(np.arange(first, first + v.shape[0]).reshape(-1, 1, 1, 1), v.shape))):
            rows[name].append(a[v])
        first += v.shape[0]
    result = {k: np.concatenate(v) for k, v in rows.items()}
    np.savez_compressed(cache, **result)
    return result


def _fit_ranges(pred: np.ndarray, ref: np.ndarray, sd: np.ndarray, rise: np.ndarray, placement: bool,
                edges: tuple[float, ...]) -> list[tuple[float, float, float]]:
    """(a, f, p) per range of predicted height: the lowest CRPS among those within the raw spread's NLL."""
    from aerialmtl.models.spread_fit import mean_crps, mean_nll

    k = np.searchsorted(np.asarray(edges), pred, side="right")
    err = np.abs(pred - ref)
    pars = []
    rng = np.random.default_rng(0)
    for r in range(len(edges) + 1):
        idx = np.flatnonzero(k == r)
        idx = rng.choice(idx, min(idx.size, 20_000), replace=False)
        e, s, u = err[idx], sd[idx], rise[idx]
        bound, best = mean_nll(e, s), (mean_crps(e, s), 1.0, 0.0, 0.0)
        base = float(np.median(e)) / max(float(np.median(s)), 1e-6)
        for a in base * 10.0 ** np.linspace(-2, 2, 13):
            for f in (0.0, *np.quantile(e, (0.1, 0.3, 0.5)).tolist()):
                for p in ((0.0, 0.2, 0.5, 1.0, 1.5) if placement else (0.0,)):
                    sigma = np.sqrt((a * s) ** 2 + f * f + (p * u) ** 2)
                    c = mean_crps(e, sigma)
                    if c < best[0] and mean_nll(e, sigma) <= bound:
                        best = (c, float(a), float(f), float(p))
        pars.append(best[1:])
    return pars


def _apply(pars: list[tuple[float, float, float]], edges: tuple[float, ...], pred: np.ndarray, sd: np.ndarray,
           rise: np.ndarray) -> np.ndarray:
    k = np.searchsorted(np.asarray(edges), pred, side="right")
    a, f, p = (np.asarray([q[i] for q in pars])[k] for i in range(3))
    result: np.ndarray = np.sqrt((a * sd) ** 2 + f * f + (p * rise) ** 2)
    return result


def placement_arm(out: Path, seeds: list[int]) -> None:
    """The spread with and without the placement term: cross-fitted on validation patches, then held-out."""
    from aerialmtl.models.calibration import spread_ranges
    from aerialmtl.models.spread_fit import mean_crps, mean_nll
    from aerialmtl.training.calibrate import patch_folds

    for placement in (False, True):
        xval, held = [], []
        for seed in seeds:
            d = _validation(out, seed)
            pred, ref, sd, rise = (d[k].astype(np.float64) for k in ("pred", "ref", "std", "rise"))
            edges = spread_ranges(pred)
            folds = patch_folds(d["patch"])
            crps = nll = 0.0
            for f in (0, 1):
                fit, score = folds == f, folds != f
                pars = _fit_ranges(pred[fit], ref[fit], sd[fit], rise[fit], placement, edges)
                sigma = _apply(pars, edges, pred[score], sd[score], rise[score])
                w = score.mean()
                crps += w * mean_crps(np.abs(pred[score] - ref[score]), sigma)
                nll += w * mean_nll(np.abs(pred[score] - ref[score]), sigma)
            xval.append((crps, nll))
            pars = _fit_ranges(pred, ref, sd, rise, placement, edges)
            h, s, r = _block(out, "recipe", "test", seed)  # the recipe's raw spread (its calibration was off)
            rs = _rise(h)
            ok = np.isfinite(h)
            sigma = _apply(pars, edges, h[ok], s[ok], rs[ok])
            e = np.abs(h[ok] - r[ok])
            held.append((mean_crps(e, sigma), mean_nll(e, sigma), float(np.mean(e > 3 * sigma))))
        x, t = np.mean(xval, axis=0), np.mean(held, axis=0)
        print(f"{'with' if placement else 'without'} the placement term: validation (cross-fitted) CRPS {x[0]:.3f}, "
              f"NLL {x[1]:.3f}; held-out CRPS {t[0]:.3f}, NLL {t[1]:.3f}, beyond 3σ {t[2]:.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--recalibrate", action="store_true")
    ap.add_argument("--conditioning", metavar="ARM")
    ap.add_argument("--quantile", action="store_true")
    ap.add_argument("--placement", action="store_true")
    a = ap.parse_args()
    if a.recalibrate:
        recalibrate(a.out, a.seeds, a.threads)
    if a.conditioning:
        conditioning(a.out, a.seeds, a.conditioning)
    if a.quantile:
        quantile_arm(a.out, a.seeds)
    if a.placement:
        placement_arm(a.out, a.seeds)


if __name__ == "__main__":
    main()
