"""Issue 36 part 4: does a feature-density ``unfamiliarity`` rank the height errors inside each height bin?

For runs of ``experiments/real_data/run.py`` on ``autzen_west``'s fixed split (``--out`` the same folder), with the
checkpoint validation chose (``best.pt``):

1. ``--dump``: predicts the validation and test blocks raw (T = 16, seed 0, calibration off:
   ``study_val_raw``, ``study_raw_best``), and saves the encoder's outputs at every level for the training
   patches (the package's :func:`aerialmtl.training.familiarity.feature_pixels`) and over the whole
   orthophoto on the prediction grid (one encoder pass, reflect-padded to a multiple of 32) to
   ``OUT/runs/<run>/unfam_features.npz``.
2. ``--variants``: fits each density variant (:data:`VARIANTS`: encoder level(s), PCA dims, GDA over
   height bins or an EM mixture) on the training features with the package's
   :func:`aerialmtl.models.familiarity.fit_density`, scores both blocks with
   :meth:`~aerialmtl.models.familiarity.FeatureDensity.unfamiliarity` (the predict-time code), and per
   reference-height bin reports Spearman(unfamiliarity, |error|) and Spearman(unfamiliarity, predicted
   height); also σ' = √(σ² + (a·u/(1−u+ε))² ...) folds (see :func:`fold_spread`) fitted on validation
   (``OUT/runs/<run>/unfam_variants.json``).
3. ``--final VARIANT``: stores the chosen density in a copy of ``best.pt`` (``best_unfam_<variant>.pt``, the package's
   :func:`~aerialmtl.training.familiarity.familiarize_checkpoint`), predicts the test block with the default
   engine and with ``--engine torch`` through ``predict_raster`` and scores the ``unfamiliarity.tif`` layers
   the package wrote (``unfam_final_<variant>.json``), with the predict time of the same model without a density
   (``best_plain.pt``).

``--table`` prints the mean over runs as Markdown. Validation chooses; the test block is reported.
Usage::

    python -m experiments.unfamiliarity.run --out /work/study_h36u --runs al_b0_s0 --dump --variants --table
    python -m experiments.unfamiliarity.run --out /work/study_h36u --runs al_b0_s0 --final l3_d32_gda
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import torch
from scipy import optimize, stats

from aerialmtl.evaluation.uncertainty import crps_gaussian, gaussian_nll_terms  # noqa: E402
from aerialmtl.formats.checkpoint import load_model, save_checkpoint  # noqa: E402
from aerialmtl.inference.predict import predict_raster  # noqa: E402
from aerialmtl.io.align import AlignedRaster, grid_of  # noqa: E402
from aerialmtl.models.d3net import pad_to_multiple  # noqa: E402
from aerialmtl.models.familiarity import fit_density  # noqa: E402
from aerialmtl.training.familiarity import HEIGHT_BINS_M, familiarize_checkpoint, feature_pixels  # noqa: E402
from experiments.common.autzen import DATA, ORTHO, cpu_model
from experiments.common.maps import load
from experiments.common.study import BINS

LEVELS = (1, 2, 3, 4)
#: Validation pixels the fold into the spread is fitted on (a seeded subsample).
FOLD_PIXELS = 20_000
#: name → (levels, dims, method, components)
VARIANTS: dict[str, tuple[tuple[int, ...], int, str, int]] = {
    "l1_d16_gda": ((1,), 16, "gda", 0),
    "l2_d16_gda": ((2,), 16, "gda", 0),
    "l2_d32_gda": ((2,), 32, "gda", 0),
    "l3_d16_gda": ((3,), 16, "gda", 0),
    "l3_d32_gda": ((3,), 32, "gda", 0),
    "l3_d32_em8": ((3,), 32, "em", 8),
    "l3_d8_gda": ((3,), 8, "gda", 0),
    "l4_d16_gda": ((4,), 16, "gda", 0),
    "l4_d32_gda": ((4,), 32, "gda", 0),
    "l34_d32_gda": ((3, 4), 32, "gda", 0),
    "l234_d32_gda": ((2, 3, 4), 32, "gda", 0),
    "l2_d32_em8": ((2,), 32, "em", 8),
    "l4_d32_em8": ((4,), 32, "em", 8),
}


def block_features(model: torch.nn.Module, meta: Any, grid_file: Path) -> list[np.ndarray]:
    """The encoder outputs (1×C×h×w per level) of the orthophoto read on ``grid_file``'s grid (whole raster)."""
    with rasterio.open(grid_file) as src:
        grid = grid_of(src)
    with AlignedRaster(DATA / ORTHO, grid, "image", bands=meta.bands, role="orthophoto") as r:
        data, valid = r.read(grid.full_window())
    x = (torch.from_numpy(data.astype(np.float32)) - torch.tensor(meta.mean)[:, None, None]) \
        / torch.tensor(meta.std)[:, None, None]
    x = torch.where(torch.from_numpy(valid)[None], x, torch.zeros(()))[None]
    xp, _ = pad_to_multiple(x)
    with torch.no_grad():
        feats = model.eval().encode(xp)
    return [f.numpy() for f in feats]


def dump(out: Path, run: str, threads: int) -> None:
    rdir = out / "runs" / run
    import yaml

    tdir = Path(yaml.safe_load((rdir / "config.yaml").read_text())["data"]["dir"])
    split_dir = out / "split_middle-val"
    model, meta = load_model(rdir / "best.pt")
    for name, block in (("study_val_raw", "val"), ("study_raw_best", "test")):
        if not (rdir / name / "height_std.tif").is_file():
            t0 = time.perf_counter()
            predict_raster(DATA / ORTHO, (model, meta), rdir / name, mc=16, aoi=split_dir / f"{block}.geojson",
                           overwrite=True, progress=False, checkpoint_name=str(rdir / "best.pt"),
                           calibration=False, seed=0)
            print(f"{run}: predicted {block} in {time.perf_counter() - t0:.0f} s", flush=True)
    npz = rdir / "unfam_features.npz"
    if npz.is_file():
        return
    arrays: dict[str, np.ndarray] = {}
    for lv in LEVELS:
        x, h, p, stride = feature_pixels(model, meta, tdir, (lv,))
        arrays[f"train_x{lv}"], arrays[f"train_h{lv}"], arrays[f"train_p{lv}"] = x, h, p
        arrays[f"stride{lv}"] = np.array(stride)
    feats = block_features(model, meta, rdir / "study_raw_best" / "height.tif")
    for lv in LEVELS:
        arrays[f"block{lv}"] = feats[lv]
    np.savez(npz, **arrays)


def fold_spread(sd: np.ndarray, u: np.ndarray, a: float, c: float) -> np.ndarray:
    """σ' = √(σ² + (a·g(u))²) with g(u) = u^c (a in metres): the unfamiliarity folded into the height spread."""
    return np.sqrt(sd**2 + (a * np.power(u, c)) ** 2)


def fit_fold(err: np.ndarray, sd: np.ndarray, u: np.ndarray) -> tuple[float, float]:
    """(a, c) minimising the mean CRPS of |err| under :func:`fold_spread` (Nelder-Mead on log a, log c)."""
    def obj(p: np.ndarray) -> float:
        return float(crps_gaussian(err, fold_spread(sd, u, math.exp(p[0]), math.exp(p[1])), np.zeros_like(err)).mean())

    best = min((optimize.minimize(obj, np.array(p0), method="Nelder-Mead", options={"maxiter": 400})
                for p0 in ([0.0, 0.0], [1.5, 1.0], [2.5, 2.0])), key=lambda r: r.fun)
    return math.exp(best.x[0]), math.exp(best.x[1])


def scores(h: np.ndarray, s: np.ndarray, r: np.ndarray, u: np.ndarray) -> dict[str, Any]:
    """Per bin: Spearman(u, |err|), Spearman(u, predicted height), Spearman(σ, |err|), share, median u."""
    ok = np.isfinite(h) & np.isfinite(r) & np.isfinite(s) & np.isfinite(u)
    e = np.abs(h - r)
    out: dict[str, Any] = {"bins": [], "spearman_u_err_all": float(stats.spearmanr(u[ok], e[ok]).statistic)}
    for lo, hi in BINS:
        b = ok & (r >= lo) & (r < hi)
        out["bins"].append({
            "range_m": [lo, hi], "n": int(b.sum()), "share": float(b.sum() / ok.sum()),
            "rho_u_err": float(stats.spearmanr(u[b], e[b]).statistic),
            "rho_u_height": float(stats.spearmanr(u[b], h[b]).statistic),
            "rho_sd_err": float(stats.spearmanr(s[b], e[b]).statistic),
            "median_u": float(np.median(u[b])), "mae": float(e[b].mean())})
    return out


def proper(err: np.ndarray, sig: np.ndarray) -> dict[str, float]:
    z = np.zeros_like(err)
    return {"crps": float(crps_gaussian(err, sig, z).mean()), "nll": float(gaussian_nll_terms(err, sig, z).mean())}


def variants(out: Path, run: str, names: list[str]) -> dict[str, Any]:
    rdir = out / "runs" / run
    d = np.load(rdir / "unfam_features.npz")
    blocks = {"val": load(rdir / "study_val_raw"), "test": load(rdir / "study_raw_best")}
    shape = blocks["test"][0].shape
    res_file = rdir / "unfam_variants.json"
    res: dict[str, Any] = {}
    for name in names:
        cond, knn = name.endswith("_cond"), name.endswith("_knn")
        levels, dims, method, k = VARIANTS[name.removesuffix("_cond").removesuffix("_knn")]
        t0 = time.perf_counter()
        lv0 = levels[0]
        if len(levels) == 1:
            x, hh = d[f"train_x{lv0}"], d[f"train_h{lv0}"]
        else:  # several levels: the coarser ones on the finest one's grid, as FeatureDensity.stack does
            x, hh = multi_level_train(d, levels), d[f"train_h{lv0}"]
        labels = np.digitize(hh, HEIGHT_BINS_M) if method == "gda" else None
        dens = fit_density(x, levels, int(d[f"stride{lv0}"]), dims=dims, labels=labels, components=k or 8)
        fit_s = time.perf_counter() - t0
        feats = {lv: torch.from_numpy(d[f"block{lv}"]) for lv in LEVELS}
        feat_list = [feats.get(i, torch.zeros(1)) for i in range(max(LEVELS) + 1)]
        t1 = time.perf_counter()
        pad_h = feats[lv0].shape[-2] * int(d[f"stride{lv0}"])
        pad_w = feats[lv0].shape[-1] * int(d[f"stride{lv0}"])
        u = dens.unfamiliarity(feat_list, (pad_h, pad_w))[0, :shape[0], :shape[1]].numpy().astype(np.float64)
        if cond:  # per block: the block's own predicted heights choose the Gaussian
            u_blocks = {blk: conditional_u(dens, x, labels, d[f"block{lv0}"], blocks[blk][0],
                                           int(d[f"stride{lv0}"]), shape) for blk in blocks}
        elif knn:
            u_knn = knn_u(dens, x, d[f"block{lv0}"], int(d[f"stride{lv0}"]), shape)
            u_blocks = {blk: u_knn for blk in blocks}
        else:
            u_blocks = {blk: u for blk in blocks}
        score_s = time.perf_counter() - t1
        entry: dict[str, Any] = {"levels": list(levels), "dims": dims, "method": method, "components": dens.components,
                                 "fit_s": fit_s, "score_s": score_s, "density_floats": n_floats(dens)}
        for blk, (h, s, r) in blocks.items():
            entry[blk] = scores(h, s, r, u_blocks[blk])
            ok_u = np.isfinite(h) & np.isfinite(u_blocks[blk])
            entry[blk]["share_u_at_1"] = float(np.mean(u_blocks[blk][ok_u] >= 1.0))
        # fold into the spread: fitted on validation (CRPS), both proper scores compared on both blocks
        hv, sv, rv = blocks["val"]
        ok = np.isfinite(hv) & np.isfinite(rv) & np.isfinite(sv)
        sub = np.flatnonzero(ok)
        sub = np.random.default_rng(0).choice(sub, min(FOLD_PIXELS, sub.size), replace=False)
        a, c = fit_fold(np.abs(hv - rv).ravel()[sub], sv.ravel()[sub], u_blocks["val"].ravel()[sub])
        entry["fold"] = {"a_m": a, "c": c}
        for blk, (h, s, r) in blocks.items():
            ok = np.isfinite(h) & np.isfinite(r) & np.isfinite(s)
            err = np.abs(h - r)[ok]
            folded = fold_spread(s[ok], u_blocks[blk][ok], a, c)
            entry[blk]["raw_spread"] = proper(err, s[ok])
            entry[blk]["folded_spread"] = proper(err, folded)
            entry[blk]["folded_rho"] = [float(stats.spearmanr(folded[(r[ok] >= lo) & (r[ok] < hi)],
                                                              err[(r[ok] >= lo) & (r[ok] < hi)]).statistic)
                                        for lo, hi in BINS]
            entry[blk]["folded_cov"] = [float(np.mean(err[(r[ok] >= lo) & (r[ok] < hi)]
                                                      <= folded[(r[ok] >= lo) & (r[ok] < hi)])) for lo, hi in BINS]
        res[name] = entry
        saved = json.loads(res_file.read_text()) if res_file.is_file() else {}
        res_file.write_text(json.dumps({**saved, **res}, indent=1))  # after every variant (others may run beside)
        v, t = entry["val"], entry["test"]
        print(f"{run} {name}: val rho(u,err) " + " ".join(f"{b['rho_u_err']:+.2f}" for b in v["bins"])
              + " | test " + " ".join(f"{b['rho_u_err']:+.2f}" for b in t["bins"])
              + " | test rho(u,h) " + " ".join(f"{b['rho_u_height']:+.2f}" for b in t["bins"])
              + f" | fold a={a:.2f} c={c:.2f} val CRPS {v['raw_spread']['crps']:.3f}->{v['folded_spread']['crps']:.3f}"
              f" NLL {v['raw_spread']['nll']:.3f}->{v['folded_spread']['nll']:.3f}", flush=True)
    return res


def conditional_u(dens: Any, x_train: np.ndarray, labels: np.ndarray, block: np.ndarray, height: np.ndarray,
                  stride: int, shape: tuple[int, int]) -> np.ndarray:
    """Unfamiliarity *given the prediction* (variants ``*_cond``): the NLL of a feature pixel under the Gaussian of
    the height bin the model **predicted** there (the predicted height averaged over the feature pixel), as a
    share of the training feature pixels of that bin (under their reference bin's Gaussian) with a lower NLL;
    upsampled bilinearly to the output pixels. A roof predicted as ground whose features are unlike the ground
    the model was trained on scores high even when they resemble something else it saw."""
    need = 2 * dens.dims
    values, counts = np.unique(labels, return_counts=True)
    kept = values[counts >= need]
    t = dens._tensors

    def comp_nll(x: np.ndarray) -> np.ndarray:  # N×C → N×K NLL under each component alone (nats)
        xt = torch.from_numpy(x.astype(np.float32))
        z = (xt - t["centre"]) @ t["basis"].T
        m = torch.einsum("nkd,kde->nke", z[:, None, :] - t["means"], t["chol"])
        const = t["const"] - torch.log(torch.tensor(dens.weights, dtype=torch.float32))
        return (-(const - 0.5 * m.square().sum(-1))).numpy().astype(np.float64)

    def comp_of(bins: np.ndarray) -> np.ndarray:  # label → nearest kept label's component (by label value)
        return np.abs(bins[:, None] - kept[None, :]).argmin(1)

    nll_train = comp_nll(x_train)
    ct = comp_of(labels)
    own = nll_train[np.arange(len(ct)), ct]
    tables = [np.sort(own[ct == k]) for k in range(len(kept))]
    c, fh, fw = block.shape[1:]
    feats = block[0].reshape(c, -1).T
    hp = np.full((fh * stride, fw * stride), np.nan)
    hp[:shape[0], :shape[1]] = height
    pooled = np.nanmean(hp.reshape(fh, stride, fw, stride), axis=(1, 3)).reshape(-1)
    ok = np.isfinite(pooled)
    u = np.full(fh * fw, np.nan)
    comp = comp_of(np.digitize(np.where(ok, pooled, 0.0), HEIGHT_BINS_M))
    nll = comp_nll(feats[ok])[np.arange(ok.sum()), comp[ok]]
    u[ok] = [np.searchsorted(tables[k], v) / len(tables[k]) for k, v in zip(comp[ok], nll)]
    grid = torch.from_numpy(np.nan_to_num(u, nan=0.5).reshape(1, 1, fh, fw).astype(np.float32))
    up = torch.nn.functional.interpolate(grid, size=(fh * stride, fw * stride), mode="bilinear", align_corners=False)
    return up[0, 0, :shape[0], :shape[1]].numpy().astype(np.float64)


def knn_u(dens: Any, x_train: np.ndarray, block: np.ndarray, stride: int, shape: tuple[int, int],
          k: int = 10) -> np.ndarray:
    """Unfamiliarity by nearest neighbours (variants ``*_knn``; Sun et al. 2022): the distance of a feature pixel's
    reduced, L2-normalised features to its k-th nearest training feature pixel, as a share of the training pixels
    (leave-one-out) with a smaller one; upsampled bilinearly. Non-parametric: no Gaussian shape assumed."""
    t = dens._tensors

    def reduce(x: np.ndarray) -> torch.Tensor:
        z = (torch.from_numpy(x.astype(np.float32)) - t["centre"]) @ t["basis"].T
        return z / z.norm(dim=1, keepdim=True).clamp_min(1e-6)

    zt = reduce(x_train)
    d_train = torch.cdist(zt, zt).topk(k + 1, largest=False).values[:, k]  # itself excluded (distance 0)
    table = np.sort(d_train.numpy())
    c, fh, fw = block.shape[1:]
    zb = reduce(block[0].reshape(c, -1).T)
    d_block = torch.cat([torch.cdist(zb[i:i + 4096], zt).topk(k, largest=False).values[:, k - 1]
                         for i in range(0, zb.shape[0], 4096)]).numpy()
    u = np.searchsorted(table, d_block) / len(table)
    grid = torch.from_numpy(u.reshape(1, 1, fh, fw).astype(np.float32))
    up = torch.nn.functional.interpolate(grid, size=(fh * stride, fw * stride), mode="bilinear", align_corners=False)
    return up[0, 0, :shape[0], :shape[1]].numpy().astype(np.float64)


def multi_level_train(d: Any, levels: tuple[int, ...]) -> np.ndarray:
    """Training rows of several levels on the finest one's feature pixels (coarser levels upsampled per patch,
    as :meth:`FeatureDensity.stack` does at predict time): recomputed from the block-free train dump is not
    possible, so this is done by the package's fitter (:func:`feature_pixels` with the levels together)."""
    return np.asarray(d[f"train_multi_{'_'.join(map(str, levels))}"])


def n_floats(dens: Any) -> int:
    return (len(dens.centre) * 2 + len(dens.basis) * len(dens.centre) + len(dens.weights) * (1 + dens.dims
            + dens.dims**2) + len(dens.quantiles))


def add_multi(out: Path, run: str) -> None:
    """The training rows of the multi-level variants (the package's fitter over the levels together)."""
    rdir = out / "runs" / run
    npz = rdir / "unfam_features.npz"
    d = dict(np.load(npz))
    need = {v[0] for v in VARIANTS.values() if len(v[0]) > 1}
    if all(f"train_multi_{'_'.join(map(str, lv))}" in d for lv in need):
        return
    import yaml

    tdir = Path(yaml.safe_load((rdir / "config.yaml").read_text())["data"]["dir"])
    model, meta = load_model(rdir / "best.pt")
    for lv in need:
        x, _, _, _ = feature_pixels(model, meta, tdir, lv)
        d[f"train_multi_{'_'.join(map(str, lv))}"] = x
    np.savez(npz, **d)


def final(out: Path, run: str, variant: str) -> dict[str, Any]:
    """The chosen variant through the package: stored in a checkpoint, predicted on both engines."""
    rdir = out / "runs" / run
    import yaml

    tdir = Path(yaml.safe_load((rdir / "config.yaml").read_text())["data"]["dir"])
    levels, dims, method, k = VARIANTS[variant]
    ckpt, plain = rdir / f"best_unfam_{variant}.pt", rdir / "best_plain.pt"
    model, meta = load_model(rdir / "best.pt")
    save_checkpoint(plain, model, dataclasses.replace(meta, familiarity=None))  # the same model without a density
    t0, load0 = time.perf_counter(), os.getloadavg()
    shutil.copyfile(plain, ckpt)
    dens = familiarize_checkpoint(ckpt, tdir, levels=levels, dims=dims, method=method,  # type: ignore[arg-type]
                                  components=k or 8)
    res: dict[str, Any] = {"variant": variant, "density": dens.summary(), "fit_s": time.perf_counter() - t0,
                           "checkpoint_bytes": {"best.pt": (rdir / "best.pt").stat().st_size,
                                                "best_unfam.pt": ckpt.stat().st_size},
                           "load": [load0], "cpu": cpu_model()}
    split_dir = out / "split_middle-val"
    for engine in ("auto", "torch"):
        for name, path in ((f"unfam_pred_{variant}_{engine}", ckpt), (f"unfam_plain_{engine}", plain)):
            t1 = time.perf_counter()
            load1 = os.getloadavg()
            predict_raster(DATA / ORTHO, path, rdir / name, mc=16, aoi=split_dir / "test.geojson",
                           overwrite=True, progress=False, calibration=False, seed=0, engine=engine)
            info = json.loads((rdir / name / "prediction.json").read_text())
            res[name] = {"seconds": time.perf_counter() - t1, "engine": info["engine"],
                         "model_s": info["timings_s"].get("model"), "total_s": info["timings_s"].get("total"),
                         "load": [load1, os.getloadavg()]}
        h, s, r = load(rdir / f"unfam_pred_{variant}_{engine}")
        with rasterio.open(rdir / f"unfam_pred_{variant}_{engine}" / "unfamiliarity.tif") as src:
            u = src.read(1).astype(np.float64)
            u[u == src.nodata] = np.nan
        ok = np.isfinite(u)
        res[f"test_{engine}"] = scores(h, s, r, u)
        res[f"test_{engine}"]["u_range"] = [float(np.nanmin(u)), float(np.nanmax(u))]
        res[f"test_{engine}"]["valid_pixels"] = int(ok.sum())
    res["load"].append(os.getloadavg())
    (rdir / f"unfam_final_{variant}.json").write_text(json.dumps(res, indent=1, default=str))
    for engine in ("auto", "torch"):
        t = res[f"test_{engine}"]
        print(f"{run} final {variant} {engine}: rho(u,err) " + " ".join(f"{b['rho_u_err']:+.2f}" for b in t["bins"])
              + " | rho(u,h) " + " ".join(f"{b['rho_u_height']:+.2f}" for b in t["bins"]), flush=True)
    return res


def table(out: Path, runs: list[str]) -> None:
    rows: dict[str, list[dict[str, Any]]] = {}
    for run in runs:
        for k, v in json.loads((out / "runs" / run / "unfam_variants.json").read_text()).items():
            rows.setdefault(k, []).append(v)

    def per(vs: list[dict[str, Any]], blk: str, key: str, bins: range = range(2, 6)) -> str:
        return " / ".join(f"{np.mean([v[blk]['bins'][i][key] for v in vs]):+.2f}" for i in bins)

    print("| variant | runs | val Spearman(u, \\|err\\|) 2–5 / 5–10 / 10–20 / ≥ 20 m | test Spearman(u, \\|err\\|) | "
          "test Spearman(u, predicted height) | test Spearman(σ, \\|err\\|) | fold: val CRPS raw → folded | "
          "val NLL raw → folded | test CRPS | test NLL |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for k, vs in rows.items():
        def m(f: Any, vs: list[dict[str, Any]] = vs) -> float:
            return float(np.mean([f(v) for v in vs]))
        def pair(blk: str, score: str, m: Any = m) -> str:
            return (f"{m(lambda v: v[blk]['raw_spread'][score]):.3f} → "
                    f"{m(lambda v: v[blk]['folded_spread'][score]):.3f}")
        print(f"| {k} | {len(vs)} | {per(vs, 'val', 'rho_u_err')} | {per(vs, 'test', 'rho_u_err')} | "
              f"{per(vs, 'test', 'rho_u_height')} | {per(vs, 'test', 'rho_sd_err')} | {pair('val', 'crps')} | "
              f"{pair('val', 'nll')} | {pair('test', 'crps')} | {pair('test', 'nll')} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--runs", nargs="+", required=True)
    ap.add_argument("--dump", action="store_true")
    ap.add_argument("--variants", nargs="*", help="variant names (none given: all of VARIANTS)")
    ap.add_argument("--final", metavar="VARIANT")
    ap.add_argument("--table", action="store_true")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    for run in args.runs:
        if args.dump:
            dump(args.out, run, args.threads)
        if args.variants is not None:
            names = args.variants or list(VARIANTS)
            if any(len(VARIANTS[n.removesuffix("_cond").removesuffix("_knn")][0]) > 1 for n in names):
                add_multi(args.out, run)
            variants(args.out, run, names)
        if args.final:
            final(args.out, run, args.final)
    if args.table:
        table(args.out, args.runs)


if __name__ == "__main__":
    main()
