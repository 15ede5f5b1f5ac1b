"""Fit a checkpoint's calibration on the validation split of its tile folder and store it in the checkpoint.

After training, :func:`calibrate_checkpoint` predicts every validation patch with MC dropout (T samples,
the model's own input normalisation), fits :func:`aerialmtl.models.calibration.fit_calibration` on the
valid pixels (predicted mean height, reference height, predictive spread) with two folds of whole
validation patches, so that each part (height map, spread map) is kept only where it beat no calibration
on patches it was not fitted on, and rewrites the checkpoint with ``meta.calibration`` set (weights and
training state unchanged). ``predict`` then applies what it holds. A validation split of fewer than
:data:`MIN_VAL_PATCHES` patches gives a warning. Validation patches only: the test data never enters the fit.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np
import torch

from aerialmtl.data.batches import CachedBatches, eval_batches, prepare_batch
from aerialmtl.data.cache import PatchCache, ensure_patch_cache
from aerialmtl.data.transforms import build_eval_transform
from aerialmtl.errors import ConfigError
from aerialmtl.formats.checkpoint import ModelMeta, load_model, update_meta
from aerialmtl.formats.tiles import TileFolderInfo, cache_dir, read_manifest
from aerialmtl.models.calibration import Calibration, CalibrationMethod, fit_calibration
from aerialmtl.models.mc_dropout import mc_predict
from aerialmtl.progress import tqdm_auto as tqdm

log = logging.getLogger(__name__)

#: MC-dropout samples per validation patch when fitting.
DEFAULT_CALIBRATION_SAMPLES = 16
#: Pixels kept for the fit (a seeded subsample beyond this).
MAX_PIXELS = 2_000_000
#: Validation patches whose MC predictions stay on the model's device before their valid pixels are read back
#: together (each boolean selection and copy to the host waits for the device: once per 64 patches, not 4 times
#: per batch; ~85 MB of 320² patches).
READ_BACK_PATCHES = 64
#: Fewest validation patches for which a calibration is fitted without a warning.
MIN_VAL_PATCHES = 20


def validation_pixels(model: torch.nn.Module, meta: ModelMeta, data_dir: str | Path,
                      mc: int = DEFAULT_CALIBRATION_SAMPLES, batch_size: int = 4,
                      cache_folder: str | Path | None = None, device: str | torch.device = "cpu",
                      progress: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """MC-dropout predictions of the validation patches: ``(pred, ref, std, patch)`` over valid pixels
    (metres, 1-D; ``patch``: the index of each pixel's validation patch). ``progress``: a ``calibration`` bar
    over the patches.

    Raises:
        ConfigError: the tile folder has no validation patches or no heights.
    """
    info = TileFolderInfo.read(data_dir)
    if "height" not in info.tasks or not read_manifest(info.root, "val"):
        raise ConfigError(f"calibration: the tile folder '{info.root}' has no validation patches with heights; "
                          "tile with a val split (the default split draws one) or skip calibration",
                          param="data_dir")
    folder = Path(cache_folder) if cache_folder else cache_dir(info.root)
    index = ensure_patch_cache(info, "val", folder)
    dev = torch.device(device)
    mean = torch.tensor(meta.mean, dtype=torch.float32, device=dev)
    std = torch.tensor(meta.std, dtype=torch.float32, device=dev)
    transform = build_eval_transform(None)
    data = CachedBatches(PatchCache(folder, index), transform, ("height",))
    preds: list[np.ndarray] = []
    refs: list[np.ndarray] = []
    stds: list[np.ndarray] = []
    patches: list[np.ndarray] = []
    pending: list[tuple[torch.Tensor, ...]] = []  # batches not yet read back: on the device, not waited for
    first = 0

    def read_back() -> None:
        """Select the valid pixels of the pending batches and bring them to the host, in one wait."""
        nonlocal first
        mean_h, std_h, ref_h, valid = (torch.cat(parts) for parts in zip(*pending))
        pending.clear()
        ids = torch.arange(first, first + valid.shape[0], device=valid.device).reshape(-1, 1, 1, 1)
        first += valid.shape[0]
        preds.append(mean_h[valid].cpu().numpy())
        stds.append(std_h[valid].cpu().numpy())
        refs.append(ref_h[valid].cpu().numpy())
        patches.append(ids.expand_as(valid)[valid].cpu().numpy())

    model = model.to(dev).eval()
    with tqdm(total=index.count, desc="calibration", unit="patch", disable=not progress, dynamic_ncols=True) as bar:
        for k, spec in enumerate(eval_batches(index.count, batch_size)):
            batch = prepare_batch(data[spec], transform, mean, std, dev)
            with torch.no_grad():
                out = mc_predict(model, batch["image"], mc, seed=k, tasks=("height",))["height"]
            pending.append((out["mean"], out["std"], batch["height"], batch["height_valid"]))
            if len(pending) * batch_size >= READ_BACK_PATCHES:
                read_back()
            bar.update(len(spec))
        if pending:
            read_back()
    pred, ref, sd = (np.concatenate(a) if a else np.zeros(0, np.float32) for a in (preds, refs, stds))
    patch = np.concatenate(patches) if patches else np.zeros(0, np.int64)
    if pred.size > MAX_PIXELS:
        keep = np.random.default_rng(0).choice(pred.size, MAX_PIXELS, replace=False)
        pred, ref, sd, patch = pred[keep], ref[keep], sd[keep], patch[keep]
    return pred, ref, sd, patch


def patch_folds(patch: np.ndarray, seed: int = 0) -> np.ndarray:
    """The fold (0 or 1) of each pixel for the calibration's cross-fitted check: whole validation patches,
    half of them in each fold, drawn with ``seed`` (``patch``: each pixel's patch index, 1-D).
    """
    if patch.size == 0:
        return np.zeros(0, np.int64)
    n = int(patch.max()) + 1
    result: np.ndarray = np.random.default_rng(seed).permutation(np.arange(n) % 2)[patch]
    return result


def calibrate_checkpoint(path: str | Path, data_dir: str | Path, *, mc: int = DEFAULT_CALIBRATION_SAMPLES,
                         method: CalibrationMethod = "isotonic", cache_folder: str | Path | None = None,
                         out: str | Path | None = None, device: str | torch.device = "cpu",
                         progress: bool = False) -> Calibration:
    """Fit the calibration of checkpoint ``path`` on ``data_dir``'s validation split and store it.

    Args:
        path: the checkpoint (rewritten in place unless ``out`` is given).
        data_dir: the tile folder the model was trained on.
        mc: MC-dropout samples (the spread factor is fitted for this T; predict with a similar T).
        method: ``isotonic`` or ``quantile`` (:mod:`aerialmtl.models.calibration`).
        out: write the calibrated checkpoint here instead.
        progress: a ``calibration`` bar over the validation patches.

    Returns:
        The fitted :class:`Calibration` (also logged).
    """
    model, meta = load_model(path)
    pred, ref, sd, patch = validation_pixels(model, meta, data_dir, mc, cache_folder=cache_folder, device=device,
                                             progress=progress)
    if pred.size == 0:
        raise ConfigError(f"calibration: no valid validation pixel in '{data_dir}'", param="data_dir")
    n_patches = int(np.unique(patch).size)
    if n_patches < MIN_VAL_PATCHES:
        warnings.warn(f"calibration: the validation split of '{data_dir}' holds {n_patches} patches, too few to "
                      f"fit and check a calibration per height range (≥ {MIN_VAL_PATCHES}); each part is applied "
                      "only where it beat no calibration on held-out validation patches. Give validation a larger "
                      "share (aerialmtl tile --split-ratios 0.7,0.2,0.1, or larger --split-block), or set "
                      "calibration.enabled: false", stacklevel=2)
    spread = sd if (mc > 1 or meta.model.aleatoric) else None
    cal = fit_calibration(pred, ref, spread, method, source=f"val split of {Path(data_dir).name}, T={mc}",
                          folds=patch_folds(patch))
    update_meta(path, out, calibration=cal)
    log.info("calibration of '%s': %s", path, cal.summary())
    return cal


__all__ = ["DEFAULT_CALIBRATION_SAMPLES", "calibrate_checkpoint", "patch_folds", "validation_pixels"]
