"""Test helper: an independent whole-raster-in-memory prediction to compare the streaming path with.

It holds the whole orthophoto and whole-raster float32 accumulators in numpy, runs the model on every
window of the plan that has a valid pixel (in batches of ``batch_size`` windows of one window row, the
documented batching), blends ``acc += value * weight`` in plan order and finalises like the old numpy
stitcher did: weighted means, argmax, entropy of the mean probabilities, mutual information
``clip(entropy − mean per-sample entropy, 0, entropy)``. It uses the model as the pipeline prepares it
(:func:`aerialmtl.models.d3net.inference_model`) and, for T = 1, the same softmax, so with the same
batches the T = 1 maps must match bit for bit. For T > 1 the per-window statistics are written out here
in float64 (softmax, per-sample entropy ``−Σ p log p``, population std) with the dropout masks seeded
per window as the pipeline seeds them, one sample per decoder call: they match to float rounding.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from rasterio.features import geometry_mask

from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.inference.windows import plan_windows
from aerialmtl.io.align import AlignedRaster, Grid, reference_grid
from aerialmtl.io.vector import load_geometries
from aerialmtl.models.d3net import inference_model
from aerialmtl.models.mc_dropout import _SeededMasks, sample_seed

FLOAT_NODATA = -9999.0
CLASS_NODATA = 255


def _window_stats(model: torch.nn.Module, x: torch.Tensor, mc: int, keys: list[int],
                  seed: int) -> dict[str, np.ndarray]:
    """(B, C, h, w) → per-window statistics as numpy: height (B,h,w), height_std, probs (B,h,w,K), mean_entropy."""
    out: dict[str, np.ndarray] = {}
    with torch.inference_mode():
        if mc == 1:
            model.eval()
            raw = model(x)
            if "height" in raw:
                out["height_mean"] = raw["height"][:, 0].float().numpy()
            if "classes" in raw:
                out["probs"] = torch.softmax(raw["classes"].float().permute(0, 2, 3, 1).contiguous(), -1).numpy()
            return out
        masks = _SeededMasks(model)
        model.eval()
        heights, probs, ents = [], [], []
        with masks:
            feats = model.encode(x)
            for t in range(mc):  # one sample at a time, every window of the batch at once
                gens = []
                for key in keys:
                    g = torch.Generator()
                    g.manual_seed(sample_seed(seed, key, t))
                    gens.append(g)
                masks.generators = gens
                dec = model.decode(feats)
                if "height" in dec:
                    heights.append(dec["height"][:, 0].double())
                if "classes" in dec:
                    p = torch.softmax(dec["classes"].double().permute(0, 2, 3, 1), -1)
                    probs.append(p)
                    ents.append(-(p * torch.log(p.clamp_min(1e-300))).sum(-1))
    if heights:
        hs = torch.stack(heights)
        out["height_mean"] = hs.mean(0).float().numpy()
        out["height_std"] = hs.std(0, unbiased=False).float().numpy()
    if probs:
        out["probs"] = torch.stack(probs).mean(0).float().numpy()
        out["mean_entropy"] = torch.stack(ents).mean(0).float().numpy()
    return out


def reference_predict(
    ortho: str | Path,
    model: torch.nn.Module,
    meta: ModelMeta,
    *,
    mc: int,
    tile: int,
    overlap: int,
    batch_size: int = 2,
    aoi: str | Path | None = None,
    seed: int = 0,
    grid: Grid | None = None,
) -> dict[str, np.ndarray]:
    """Layer name → (bands, H, W) array, as a prediction folder holds them."""
    grid = grid or reference_grid(ortho)
    plan = plan_windows(grid.height, grid.width, tile, overlap)
    rows, cols = plan.rows, plan.cols
    with AlignedRaster(ortho, grid, "image", bands=list(meta.bands), role="orthophoto") as src:
        data, valid = src.read()
    if aoi is not None:
        geoms = [g for g, _ in load_geometries(aoi, grid.crs, role="AOI")]
        valid &= geometry_mask(geoms, out_shape=grid.shape, transform=grid.transform, invert=True)
    ext_h, ext_w = rows.extent, cols.extent
    img = np.zeros((data.shape[0], max(ext_h, grid.height), max(ext_w, grid.width)), np.float32)
    ok = np.zeros(img.shape[1:], bool)
    mean = np.asarray(meta.mean, np.float32)[:, None, None]
    std = np.asarray(meta.std, np.float32)[:, None, None]
    img[:, :grid.height, :grid.width] = (data.astype(np.float32) - mean) / std
    ok[:grid.height, :grid.width] = valid
    img[:, ~ok] = 0.0
    k = meta.classes.num_classes if meta.classes is not None and "classes" in meta.model.tasks else 0
    model = inference_model(model, torch.device("cpu"))
    acc: dict[str, np.ndarray] = {"weight": np.zeros(ok.shape, np.float32)}
    n_cols = len(cols.starts)
    for i, r in enumerate(rows.starts):
        todo = [j for j, c in enumerate(cols.starts) if ok[r:r + rows.size, c:c + cols.size].any()]
        for b0 in range(0, len(todo), batch_size):
            batch = todo[b0:b0 + batch_size]
            x = torch.from_numpy(np.stack([img[:, r:r + rows.size, cols.starts[j]:cols.starts[j] + cols.size]
                                           for j in batch])).contiguous(memory_format=torch.channels_last)
            stats = _window_stats(model, x, mc, [i * n_cols + j for j in batch], seed)
            for n, j in enumerate(batch):
                c = cols.starts[j]
                sl = (slice(r, r + rows.size), slice(c, c + cols.size))
                w = (rows.weights[i][:, None] * cols.weights[j][None, :]) * ok[sl]
                acc["weight"][sl] += w
                for name, v in stats.items():
                    if name not in acc:
                        acc[name] = np.zeros(ok.shape + v.shape[3:], np.float32)
                    acc[name][sl] += v[n] * (w[..., None] if v.ndim == 4 else w)
    h, w_ = grid.height, grid.width
    wsum = acc["weight"][:h, :w_]
    valid_out = wsum > 0
    safe = np.where(valid_out, wsum, np.float32(1.0)).astype(np.float32)

    def fl(x: np.ndarray) -> np.ndarray:
        x = x.astype(np.float32).copy()
        x[..., ~valid_out] = FLOAT_NODATA
        return x

    layers: dict[str, np.ndarray] = {}
    if "height_mean" in acc:
        layers["height"] = fl(acc["height_mean"][:h, :w_] / safe)[None]
    if "height_std" in acc:
        layers["height_std"] = fl(np.maximum(acc["height_std"][:h, :w_] / safe, 0.0))[None]
    if k:
        probs = acc["probs"][:h, :w_] / safe[..., None]
        cls = np.argmax(probs, axis=-1).astype(np.uint8)
        cls[~valid_out] = CLASS_NODATA
        layers["classes"] = cls[None]
        if mc > 1:
            ent = np.maximum(-(probs * np.log(np.clip(probs, 1e-12, 1.0))).sum(-1), 0.0)
            layers["class_entropy"] = fl(ent)[None]
            layers["class_mutual_info"] = fl(np.clip(ent - acc["mean_entropy"][:h, :w_] / safe, 0.0, ent))[None]
        layers["class_probabilities"] = fl(np.moveaxis(probs, -1, 0))
    return layers
