"""Fit a checkpoint's feature density on the training patches and store it in the checkpoint.

After training (beside the calibration, :mod:`aerialmtl.training.calibrate`), :func:`familiarize_checkpoint`
runs the encoder over every training patch of the tile folder (no augmentation, the model's own input
normalisation), keeps the encoder outputs at the configured levels for every feature pixel whose patch
pixels are at least half valid, fits :func:`aerialmtl.models.familiarity.fit_density` (class-conditional
Gaussians over the reference-height bins of :data:`HEIGHT_BINS_M`, DDU's GDA, or a mixture fitted by EM) and
rewrites the checkpoint with ``meta.familiarity`` set (weights and training state unchanged). ``predict``
then writes the ``unfamiliarity`` layer. Training patches only: the density describes what the model was
trained on.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F

from aerialmtl.data.batches import CachedBatches, eval_batches, prepare_batch
from aerialmtl.data.cache import PatchCache, ensure_patch_cache
from aerialmtl.data.transforms import build_eval_transform
from aerialmtl.errors import ConfigError
from aerialmtl.formats.checkpoint import ModelMeta, load_model, update_meta
from aerialmtl.formats.tiles import TileFolderInfo, cache_dir, read_manifest
from aerialmtl.models.d3net import encode_features
from aerialmtl.models.familiarity import FeatureDensity, fit_density
from aerialmtl.progress import tqdm_auto as tqdm

log = logging.getLogger(__name__)

#: Reference-height bins (metres, inner edges) whose Gaussians make the GDA density.
HEIGHT_BINS_M = (1.0, 2.0, 5.0, 10.0, 20.0)
#: Feature pixels kept for the fit (a seeded subsample beyond this).
MAX_FEATURE_PIXELS = 200_000
#: Share of a feature pixel's image pixels that must be valid for it to enter the fit.
MIN_VALID_SHARE = 0.5


def feature_pixels(model: torch.nn.Module, meta: ModelMeta, data_dir: str | Path, levels: tuple[int, ...],
                   split: str = "train", batch_size: int = 8, cache_folder: str | Path | None = None,
                   device: str | torch.device = "cpu",
                   progress: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The encoder features of ``split``'s patches, one row per valid feature pixel (``progress``: a
    ``feature density`` bar over the patches).

    Returns:
        ``(features N×C float32, mean reference height N (metres; NaN without heights), patch index N, stride)``
        where ``stride`` is the finest level's stride in pixels.

    Raises:
        ConfigError: the tile folder has no patches in ``split``.
    """
    info = TileFolderInfo.read(data_dir)
    if not read_manifest(info.root, split):
        raise ConfigError(f"familiarity: the tile folder '{info.root}' has no {split} patches", param="data_dir")
    folder = Path(cache_folder) if cache_folder else cache_dir(info.root)
    index = ensure_patch_cache(info, split, folder)
    dev = torch.device(device)
    mean = torch.tensor(meta.mean, dtype=torch.float32, device=dev)
    std = torch.tensor(meta.std, dtype=torch.float32, device=dev)
    transform = build_eval_transform(None)
    tasks = tuple(t for t in ("height",) if t in info.tasks)
    data = CachedBatches(PatchCache(folder, index), transform, tasks)
    model = model.to(dev).eval()
    feats, heights, patches = [], [], []
    stride = 1
    first = 0
    bar = tqdm(total=index.count, desc="feature density", unit="patch", disable=not progress, dynamic_ncols=True)
    with bar:
        for spec in eval_batches(index.count, batch_size):
            batch = prepare_batch(data[spec], transform, mean, std, dev)
            x = batch["image"]
            with torch.no_grad():
                enc = encode_features(model, x)
            picked = [enc[i].float() for i in levels]
            size = picked[0].shape[-2:]
            stride = x.shape[-1] // size[-1]
            f = torch.cat([p if p.shape[-2:] == size else F.interpolate(p, size=size, mode="bilinear",
                                                                        align_corners=False) for p in picked], 1)
            valid = (x != 0).any(1, keepdim=True).float()
            if "height_valid" in batch:
                valid = valid * batch["height_valid"].float()
            share = F.avg_pool2d(valid, stride)[:, 0]
            ok = share >= MIN_VALID_SHARE
            if "height" in batch:
                hsum = F.avg_pool2d(batch["height"] * valid, stride)[:, 0]
                h = hsum / share.clamp_min(1e-6)
            else:
                h = torch.full_like(share, float("nan"))
            ids = torch.arange(first, first + x.shape[0], device=dev).reshape(-1, 1, 1).expand_as(ok)
            first += x.shape[0]
            feats.append(f.permute(0, 2, 3, 1)[ok].cpu().numpy())
            heights.append(h[ok].cpu().numpy())
            patches.append(ids[ok].cpu().numpy())
            bar.update(len(spec))
    return (np.concatenate(feats), np.concatenate(heights).astype(np.float32), np.concatenate(patches), int(stride))


def fit_from_patches(model: torch.nn.Module, meta: ModelMeta, data_dir: str | Path, *,
                     levels: tuple[int, ...] = (2,), dims: int = 32, method: Literal["gda", "em"] = "gda",
                     components: int = 8, cache_folder: str | Path | None = None,
                     device: str | torch.device = "cpu", seed: int = 0, progress: bool = False) -> FeatureDensity:
    """:func:`feature_pixels` of the train split → :func:`~aerialmtl.models.familiarity.fit_density`.

    ``gda`` labels each feature pixel by the bin (:data:`HEIGHT_BINS_M`) of its mean reference height; without
    heights in the tile folder it falls back to ``em``.
    """
    x, h, _, stride = feature_pixels(model, meta, data_dir, levels, cache_folder=cache_folder, device=device,
                                     progress=progress)
    if x.shape[0] < 2:
        raise ConfigError(f"familiarity: fewer than 2 valid feature pixels in the train split of '{data_dir}'",
                          param="data_dir")
    if x.shape[0] > MAX_FEATURE_PIXELS:
        keep = np.random.default_rng(seed).choice(x.shape[0], MAX_FEATURE_PIXELS, replace=False)
        x, h = x[keep], h[keep]
    labels = None
    if method == "gda" and np.isfinite(h).all():
        labels = np.digitize(h, HEIGHT_BINS_M)
    return fit_density(x, levels, stride, dims=dims, labels=labels, components=components, seed=seed,
                       source=f"train split of {Path(data_dir).name}")


def familiarize_checkpoint(path: str | Path, data_dir: str | Path, *, levels: tuple[int, ...] = (2,),
                           dims: int = 32, method: Literal["gda", "em"] = "gda", components: int = 8,
                           cache_folder: str | Path | None = None, out: str | Path | None = None,
                           device: str | torch.device = "cpu", progress: bool = False) -> FeatureDensity:
    """Fit the feature density of checkpoint ``path`` on ``data_dir``'s train split and store it.

    Args:
        path: the checkpoint (rewritten in place unless ``out`` is given).
        data_dir: the tile folder the model was trained on.
        levels, dims, method, components: see :func:`fit_from_patches`.
        out: write the checkpoint with its density here instead.
        progress: a ``feature density`` bar over the train patches.

    Returns:
        The fitted :class:`~aerialmtl.models.familiarity.FeatureDensity` (also logged).
    """
    model, meta = load_model(path)
    density = fit_from_patches(model, meta, data_dir, levels=levels, dims=dims, method=method,
                               components=components, cache_folder=cache_folder, device=device, progress=progress)
    update_meta(path, out, familiarity=density)
    log.info("feature density of '%s': %s", path, density.summary())
    return density


__all__ = ["HEIGHT_BINS_M", "MAX_FEATURE_PIXELS", "familiarize_checkpoint", "feature_pixels", "fit_from_patches"]
