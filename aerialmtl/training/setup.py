"""What a training run is made of, assembled once: :class:`TrainSetup`, which the trainer receives.

:func:`prepare_training` builds it from the configuration by small functions, each of which takes what it
needs and returns a value (nothing is half-built and filled in later):

1. the process context, device and precision (:mod:`aerialmtl.runtime`);
2. the tile folder and the model config it implies (:func:`read_data_folder`), then :func:`open_data` →
   :class:`TrainData`: the patch caches of the train and val splits (:func:`prepare_caches`) and the checkpoint
   metadata (:func:`model_meta`, with the train split's height range, :func:`train_height_range`);
3. the objective (:class:`~aerialmtl.training.objective.Objective`);
4. :func:`build_model` → :class:`ModelParts`: the seeded D3-Net, the task weighting and the optimiser
   (:func:`build_optimizer`);
5. the starting point: :func:`~aerialmtl.training.resume.restore` (``resume``: weights, optimiser, weighting,
   counters and the RNG state of ``last.pt``), or the ``init`` weights, then this process's RNG stream
   (:func:`~aerialmtl.training.resume.seed_rank_stream`);
6. the step module (:class:`StepModule`, compiled through the runtime's
   fallback) and its ``DistributedDataParallel`` wrapper;
7. :func:`build_loaders` → :class:`Loaders`: the epoch order from the starting position and the train and
   val loaders over the caches.

The order is the one training always had: the RNG draws (the model's initial weights, the rank streams)
happen at the same points, so a run is the same run as before the setup was split out.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import nn

from aerialmtl import runtime
from aerialmtl.data.batches import CachedBatches, EpochOrder, RankBatchSampler, eval_batches
from aerialmtl.data.cache import PatchCache, ensure_patch_cache
from aerialmtl.data.copy_paste import CopyPaster, build_object_bank
from aerialmtl.data.prefetch import AssembledBatches
from aerialmtl.data.shadow_labels import SHADOW_IGNORE, split_labels
from aerialmtl.data.transforms import Compose, build_eval_transform, build_train_transform
from aerialmtl.errors import ConfigError, OutputError
from aerialmtl.formats.checkpoint import (
    ModelMeta,
    value_envelope,
)
from aerialmtl.formats.tiles import (
    HEIGHT_NODATA,
    MANIFEST_CSV,
    PatchCacheIndex,
    TileFolderInfo,
    cache_dir,
    cache_file,
    read_manifest,
)
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net, to_channels_last
from aerialmtl.models.encoders import encoder_spec
from aerialmtl.sun.position import Sun
from aerialmtl.sun.record import TrainingSun
from aerialmtl.training import distributed
from aerialmtl.training.config import OptimSection, TrainConfig
from aerialmtl.training.finetune import load_init_weights
from aerialmtl.training.objective import Objective, class_weights
from aerialmtl.training.resume import restore, seed_rank_stream
from aerialmtl.training.state import TrainState, seed_everything
from aerialmtl.training.sun import fit_training_sun
from aerialmtl.training.weighting import build_weighting

#: The trainer's logger (the messages of training, whichever module writes them).
log = logging.getLogger("aerialmtl.training.trainer")

#: Whether ``precision: auto`` trains in bf16 autocast on a CPU with native bf16 (measured: bench/RESULTS.md,
#: "CPU training precision"; fp32 until bf16 is both faster and as good there).
CPU_BF16_TRAINING = False


# ---- the data ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrainData:
    """The tile folder as training reads it.

    Attributes:
        info: the tile folder's ``dataset.yaml``.
        model_cfg: the model config, completed from the data (bands, tasks, classes).
        meta: the checkpoint metadata every checkpoint of the run carries (with the train split's height range).
        cache_folder: where the decoded patch caches are.
        train_index, val_index: the caches of the train and val splits (``None``: no val split).
    """

    info: TileFolderInfo
    model_cfg: ModelConfig
    meta: ModelMeta
    cache_folder: Path
    train_index: PatchCacheIndex
    val_index: PatchCacheIndex | None

    @property
    def tasks(self) -> tuple[str, ...]:
        """The tasks trained (``"height"``, ``"classes"``)."""
        return tuple(self.model_cfg.tasks)

    @property
    def k(self) -> int | None:
        """The number of classes of the tile folder (``None`` without classes)."""
        return self.info.classes.num_classes if self.info.classes is not None else None


def user_cache_dir(root: Path) -> Path:
    """Where the patch cache of a read-only tile folder goes: ``$XDG_CACHE_HOME/aerialmtl/<hash of its path>``."""
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "aerialmtl" / hashlib.sha256(str(root.resolve()).encode()).hexdigest()[:16]


def read_data_folder(cfg: TrainConfig, data_dir: str | Path | None) -> tuple[TileFolderInfo, ModelConfig]:
    """The tile folder and the model config it implies; checks ``data.crop_size`` against its patches."""
    data = data_dir if data_dir is not None else cfg.data.dir
    if data is None:
        raise ConfigError("data.dir: no tile folder given; set data.dir in the config or pass ‹data_dir›",
                          param="data_dir")
    info = TileFolderInfo.read(data)
    k = info.classes.num_classes if info.classes is not None else None
    model_cfg = cfg.model.resolve(info.num_bands, info.tasks, k)
    side = cfg.data.crop_size or info.patch_size
    if side % 32 or side > info.patch_size:
        raise ConfigError(
            f"data.crop_size: the network needs sides that are multiples of 32 and at most the {info.patch_size} "
            f"px patches of '{info.root}', got {side}; set data.crop_size to a multiple of 32 ≤ "
            f"{info.patch_size} or re-tile with --size a multiple of 32"
        )
    return info, model_cfg


def input_normalization(model_cfg: ModelConfig,
                        info: TileFolderInfo) -> tuple[tuple[float, ...], tuple[float, ...], str]:
    """The per-band ``(mean, std)`` the model's inputs are normalised with, and where it comes from.

    An encoder with pretrained weights that were trained on a fixed input scaling (its registry entry's
    ``input_scaling``, :mod:`aerialmtl.models.encoders`; EfficientNet-Lite: ``(x − 127) / 128`` on 8-bit
    bands) gets that scaling (``"encoder"``); anything else the tile folder's train statistics
    (``"dataset"``). Pretrained weights on other than 8-bit data fall back to the statistics, with a warning.
    """
    n = len(info.bands)
    scaling = encoder_spec(model_cfg.encoder).input_scaling
    if scaling is not None and model_cfg.encoder_weights:
        if str(info.dtype) == "uint8":
            return (scaling[0],) * n, (scaling[1],) * n, "encoder"
        warnings.warn(f"model.encoder_weights: the pretrained {model_cfg.encoder} weights expect 8-bit images scaled "
                      f"(x - 127) / 128, but the tile folder holds {info.dtype} bands; normalising with the tile "
                      "folder's statistics instead", UserWarning, stacklevel=2)
    return tuple(info.mean), tuple(info.std), "dataset"


def model_meta(info: TileFolderInfo, model_cfg: ModelConfig) -> ModelMeta:
    """The checkpoint metadata of a model trained on ``info`` (bands, normalisation, GSD, CRS, value range)."""
    norm_mean, norm_std, normalization = input_normalization(model_cfg, info)
    return ModelMeta(model=model_cfg, classes=info.classes if "classes" in model_cfg.tasks else None,
                     bands=info.bands, mean=norm_mean, std=norm_std, gsd=info.gsd,
                     band_names=info.band_names, crs=info.crs, normalization=normalization,
                     input_dtype=info.dtype,
                     input_range=value_envelope(info.mean, info.std, info.dtype) if info.mean and info.dtype else None)


def prepare_caches(cfg: TrainConfig, info: TileFolderInfo,
                   progress: bool) -> tuple[Path, PatchCacheIndex, PatchCacheIndex | None]:
    """Make sure the train (and val) split's patch caches are up to date (built on first use).

    Every process calls it; a lock file lets one build while the others wait.

    Returns:
        ``(cache folder, train index, val index or None)``.
    """
    data = cfg.data
    folder = Path(data.cache_dir) if data.cache_dir else cache_dir(info.root)
    try:
        train_index = ensure_patch_cache(info, "train", folder, workers=data.num_workers, progress=progress)
    except OutputError:
        if data.cache_dir:
            raise
        folder = user_cache_dir(info.root)  # a read-only tile folder still trains
        warnings.warn(f"data.cache_dir: the tile folder '{info.root}' is not writable; caching its decoded "
                      f"patches in '{folder}' instead (set data.cache_dir to choose)", UserWarning, stacklevel=2)
        train_index = ensure_patch_cache(info, "train", folder, workers=data.num_workers, progress=progress)
    val_index = None
    if read_manifest(info.root, "val"):
        val_index = ensure_patch_cache(info, "val", folder, workers=data.num_workers, progress=progress)
    return folder, train_index, val_index


def train_height_range(cache_folder: Path) -> tuple[float, float] | None:
    """``(min, max)`` metres of the train split's valid reference heights, or ``None`` without a valid height.

    Read from the patch cache in chunks; recorded in the checkpoint (:attr:`ModelMeta.height_range`).
    """
    path = cache_file(cache_folder, "train", "height")
    try:
        heights = np.load(path, mmap_mode="r")
    except (OSError, ValueError):
        return None
    lo, hi = math.inf, -math.inf
    for start in range(0, len(heights), 64):
        chunk = np.asarray(heights[start:start + 64])
        ok = chunk[np.isfinite(chunk) & (chunk != HEIGHT_NODATA)]
        if ok.size:
            lo, hi = min(lo, float(ok.min())), max(hi, float(ok.max()))
    return (lo, hi) if lo <= hi else None


# ---- the model ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ModelParts:
    """What the optimiser steps: the model, the task weighting and the optimiser over both."""

    model: nn.Module
    weighting: nn.Module
    optimizer: torch.optim.Optimizer


def build_optimizer(optim: OptimSection, model: nn.Module, weighting: nn.Module) -> torch.optim.Optimizer:
    """Adam or AdamW over the model and the weighting module.

    With ``weight_decay > 0`` only the model's convolution weights (tensors of ≥ 2 dimensions) decay;
    biases, BatchNorm parameters and the learned task weighting do not. With 0, one parameter group.
    """
    cls = torch.optim.AdamW if optim.name == "adamw" else torch.optim.Adam
    params = list(model.parameters()) + list(weighting.parameters())
    groups: list[dict[str, Any]]
    if optim.weight_decay > 0:
        decay = [p for p in model.parameters() if p.dim() >= 2]
        rest = [p for p in params if p.dim() < 2 or not any(p is q for q in model.parameters())]
        groups = [{"params": decay}, {"params": rest, "weight_decay": 0.0}]
    else:
        groups = [{"params": params}]
    return cls(groups, lr=optim.lr, betas=optim.betas, weight_decay=optim.weight_decay)


def build_model(cfg: TrainConfig, model_cfg: ModelConfig, device: torch.device, ctx: runtime.Torchrun) -> ModelParts:
    """Seeded D3-Net (channels_last, SyncBatchNorm if asked with several processes), weighting, optimiser."""
    seed_everything(cfg.seed)
    model: nn.Module = to_channels_last(D3Net(model_cfg).to(device))
    if cfg.model.sync_bn and ctx.distributed:
        model = distributed.convert_sync_batchnorm(model, device)
    weighting = build_weighting(cfg.weighting.method, list(model_cfg.tasks)).to(device)
    return ModelParts(model, weighting, build_optimizer(cfg.optim, model, weighting))


# ---- the data loaders ---------------------------------------------------------------------------------
#: A run's batches: assembled by a thread on a CPU (:class:`~aerialmtl.data.prefetch.AssembledBatches`), loaded by
#: DataLoader workers and finished on the device otherwise.
Batches = AssembledBatches | torch.utils.data.DataLoader[dict[str, Any]]


@dataclass(frozen=True)
class Loaders:
    """The batches of a run, from its starting position.

    Attributes:
        order: which patches each step uses (:class:`~aerialmtl.data.batches.EpochOrder`).
        train_transform, eval_transform: the augmentations of training / the crop of validation.
        mean, std: (C,) per-band normalisation on the device.
        train_loader: this process's training batches from the state's epoch and position (:data:`Batches`).
        val_loader: its share of the val split (``None``: no val split).
    """

    order: EpochOrder
    train_transform: Compose
    eval_transform: Compose
    mean: torch.Tensor
    std: torch.Tensor
    train_loader: Batches
    val_loader: Batches | None


def shadow_head_labels(cfg: TrainConfig, data: TrainData) -> tuple[TrainingSun | None, np.ndarray | None]:
    """The training sun and the shadow head's labels of the train split (``model.shadow_head``), else ``(None, None)``.

    The sun is fitted here, before the steps (:func:`~aerialmtl.training.sun.fit_training_sun`), and the trainer
    stores this same record after them; the labels are the cast shadows of the cached train heights at it
    (:func:`~aerialmtl.data.shadow_labels.split_labels`).

    Raises:
        ConfigError: copy-paste is on (pasted objects would cast no labelled shadow), or the fit found no sun.
    """
    if not data.model_cfg.shadow_head:
        return None, None
    if cfg.data.copy_paste.enabled:
        raise ConfigError("model.shadow_head: its labels are the cast shadows of the stored heights, and pasted "
                          "objects would cast none; set data.copy_paste.prob: 0 or model.shadow_head: false")
    sun = fit_training_sun(data.info.root)
    if not sun.clear or sun.grid_azimuth_deg is None or sun.elevation_deg is None:
        raise ConfigError(f"model.shadow_head: learns the cast shadows at the training area's sun, and none was "
                          f"found ({sun.reason}); set model.shadow_head: false")
    heights = PatchCache(data.cache_folder, data.train_index).arrays()["height"]
    labels = split_labels(heights, read_manifest(data.info.root, "train"), float(data.info.gsd),
                          Sun(sun.grid_azimuth_deg, sun.elevation_deg))
    known = labels != SHADOW_IGNORE
    log.info("shadow head: %s; labels: %.1f %% cast shadow, %.1f %% unknown", sun.reason,
             100.0 * float((labels == 1).sum()) / max(1, int(known.sum())), 100.0 * float((~known).mean()))
    return sun, labels


def build_loaders(cfg: TrainConfig, data: TrainData, device: torch.device, ctx: runtime.Torchrun,
                  state: TrainState, shadow: np.ndarray | None = None) -> Loaders:
    """The batch plan from ``state``'s position, and the train and val loaders over the caches (the train batches
    with the shadow head's labels ``shadow``, :func:`shadow_head_labels`, where given).
    """
    dcfg, nw = cfg.data, cfg.data.num_workers
    pin = device.type == "cuda"
    order = EpochOrder(data.train_index.count, dcfg.batch_size, cfg.seed, ctx.world)
    train_transform = build_train_transform(dcfg.flips, dcfg.rot90, dcfg.jitter, dcfg.crop_size)
    mean = torch.tensor(data.meta.mean, dtype=torch.float32, device=device)
    std = torch.tensor(data.meta.std, dtype=torch.float32, device=device)
    train_cache = PatchCache(data.cache_folder, data.train_index)
    sampler = RankBatchSampler(order, ctx.rank, state.epoch, state.position)
    paster = copy_paster(cfg, data, train_cache)
    eval_transform = build_eval_transform(dcfg.crop_size)
    val_loader: Batches | None = None
    train_loader: Batches
    if device.type == "cpu":  # one thread of this process assembles them (no worker processes: see the module)
        train_loader = AssembledBatches(train_cache, train_transform, data.tasks, sampler, mean, std, paster,
                                        shadow=shadow)
        if data.val_index is not None:
            val_loader = AssembledBatches(PatchCache(data.cache_folder, data.val_index), eval_transform, data.tasks,
                                          eval_batches(data.val_index.count, dcfg.batch_size, ctx.rank, ctx.world),
                                          mean, std)
    else:
        train_loader = torch.utils.data.DataLoader(
            CachedBatches(train_cache, train_transform, data.tasks, paster, shadow), sampler=sampler,
            batch_size=None, num_workers=nw, pin_memory=pin, generator=torch.Generator().manual_seed(cfg.seed),
        )
        if data.val_index is not None:
            val_loader = torch.utils.data.DataLoader(
                CachedBatches(PatchCache(data.cache_folder, data.val_index), eval_transform, data.tasks),
                sampler=eval_batches(data.val_index.count, dcfg.batch_size, ctx.rank, ctx.world),
                batch_size=None, num_workers=min(nw, 1), persistent_workers=nw > 0, pin_memory=pin,
                generator=torch.Generator().manual_seed(cfg.seed))
    if data.val_index is None and ctx.is_main:
        log.warning("no 'val' patches in %s: best.pt is chosen by the training loss", data.info.root / MANIFEST_CSV)
    return Loaders(order, train_transform, eval_transform, mean, std, train_loader, val_loader)


def copy_paster(cfg: TrainConfig, data: TrainData, cache: PatchCache) -> CopyPaster | None:
    """The copy-paste of ``data.copy_paste`` over the train split's object bank, or ``None`` when it is off.

    Raises:
        ConfigError: copy-paste is on but the tile folder has no heights.
    """
    spec = cfg.data.copy_paste
    if not spec.enabled:
        return None
    if "height" not in data.tasks:
        raise ConfigError("data.copy_paste: finds tall objects by their reference heights, and this run trains no "
                          "height task; set data.copy_paste.prob: 0 or tile with --dsm/--dtm (or --ndsm)")
    rows = read_manifest(data.info.root, "train")
    try:  # the tile grid: an object seen in several overlapping patches is banked once
        offsets: list[tuple[int, int]] | None = [(int(r["row_off"]), int(r["col_off"])) for r in rows]
    except (KeyError, TypeError, ValueError):
        offsets = None
    if offsets is not None and len(offsets) != len(cache):
        offsets = None
    bank = build_object_bank(cache.arrays(), spec, data.info.gsd, cfg.seed, offsets)
    log.info("copy-paste: %s", bank.summary())
    if not len(bank):
        warnings.warn(f"data.copy_paste: no object of ≥ {spec.min_height_m:g} m with its margin inside a training "
                      f"patch of '{data.info.root}'; nothing is pasted (lower min_height_m or margin_m)",
                      UserWarning, stacklevel=2)
    return CopyPaster(bank, spec)


class StepModule(nn.Module):
    """Forward + losses + task weighting of a batch: ``(total, {task: loss})``.

    This is what DistributedDataParallel wraps, so the gradients of the learned task weighting are
    averaged over processes like the network's. With ``compile`` the model's ``forward`` runs through
    ``torch.compile`` with the package's one fallback (:class:`aerialmtl.runtime.CompileFallback`: eager
    from the first failure on, with one warning).
    """

    def __init__(self, model: nn.Module, weighting: nn.Module, objective: Objective, device: torch.device,
                 precision: str, compile: bool = False) -> None:
        super().__init__()
        self.model, self.weighting = model, weighting
        self.objective, self.device, self.precision = objective, device, precision
        self.compiled = runtime.CompileFallback(model, "training") if compile else None

    def forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The weighted total and the per-task losses of ``batch``."""
        with runtime.autocast(self.device, self.precision):
            out = self.model(batch["image"]) if self.compiled is None else self.compiled("forward", batch["image"])
        losses = self.objective(out, batch)
        return self.objective.total(self.weighting(self.objective.weighted(losses)), losses), losses




# ---- the setup ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrainSetup:
    """Everything a :class:`~aerialmtl.training.trainer.Trainer` trains with, assembled by :func:`prepare_training`.

    Attributes:
        cfg: the training configuration.
        ctx: the process context; ``owns_ctx``: it was started here (the trainer closes it).
        device, precision: where and how it trains.
        run: the run folder; ``data_dir``: the tile folder as given (recorded in ``config.yaml``).
        data: the tile folder, its caches and the checkpoint metadata.
        parts: model, task weighting, optimiser.
        objective: the losses.
        step_module, ddp: one training step's forward and losses, and its DDP wrapper (the module itself
            with one process).
        loaders: the batches.
        state: the counters (epoch, position, step, best score; the trainer advances them).
        saved_step: the step of ``last.pt`` when resumed from it, else ``None``.
        resume: the run continues ``last.pt`` (the log is appended to).
        averaged: the weight average ``last.pt`` holds (``optim.ema``), ``None`` for a new run or without it.
        sun: the training sun fitted before the steps for the shadow head (``model.shadow_head``), which the
            trainer stores after them; ``None``: fitted after the steps, if at all.
    """

    cfg: TrainConfig
    ctx: runtime.Torchrun
    owns_ctx: bool
    device: torch.device
    precision: Literal["bf16", "fp32"]
    run: Path
    data_dir: str | Path | None
    data: TrainData
    parts: ModelParts
    objective: Objective
    step_module: nn.Module
    ddp: nn.Module
    loaders: Loaders
    state: TrainState
    saved_step: int | None
    resume: bool
    averaged: dict[str, torch.Tensor] | None = None
    sun: TrainingSun | None = None


def open_data(cfg: TrainConfig, info: TileFolderInfo, model_cfg: ModelConfig, progress: bool) -> TrainData:
    """The tile folder's metadata and up-to-date patch caches (see the module docstring)."""
    meta = model_meta(info, model_cfg)
    folder, train_index, val_index = prepare_caches(cfg, info, progress)
    if "height" in model_cfg.tasks:
        meta = dataclasses.replace(meta, height_range=train_height_range(folder))
    return TrainData(info, model_cfg, meta, folder, train_index, val_index)


def prepare_training(cfg: TrainConfig, data_dir: str | Path | None = None, out_dir: str | Path = "runs/train", *,
                     resume: bool = False, init: str | Path | None = None, progress: bool = True,
                     ctx: runtime.Torchrun | None = None) -> TrainSetup:
    """Assemble a run (see the module docstring for the order).

    Args:
        cfg: the training configuration.
        data_dir: tile folder (overrides ``cfg.data.dir``).
        out_dir: run folder (created on rank 0).
        resume: continue from ``out_dir/last.pt``.
        init: start from the weights of this checkpoint (fine-tuning); a new run only:
            :func:`~aerialmtl.training.run_folder.check_run_folder` refuses it with ``resume`` before the run
            folder is touched (:func:`~aerialmtl.training.loop.train` calls it first).
        progress: progress bars of the cache builds (rank 0 only).
        ctx: the process context (default: from torchrun's environment, one process without it).

    Raises:
        ConfigError: no tile folder, a crop size the patches cannot give.
        CheckpointError: a ``last.pt`` that cannot be resumed (names the file and the fix).
    """
    owns_ctx = ctx is None
    if ctx is None:
        ctx = runtime.Torchrun.start(cfg.device, runtime.COLLECTIVE_TIMEOUT, ConfigError)
    device = ctx.device
    precision = runtime.resolve_precision(cfg.precision, device, cpu_bf16=CPU_BF16_TRAINING)
    run = Path(out_dir)
    progress = progress and ctx.is_main
    info, model_cfg = read_data_folder(cfg, data_dir)  # checked before the run folder is made
    if ctx.is_main:
        run.mkdir(parents=True, exist_ok=True)
    tasks = tuple(model_cfg.tasks)
    k = info.classes.num_classes if info.classes is not None else None
    objective = Objective(cfg, tasks, class_weights(cfg, info, k or 2) if "classes" in tasks else None)
    data = open_data(cfg, info, model_cfg, progress)
    sun, shadow = shadow_head_labels(cfg, data)
    parts = build_model(cfg, data.model_cfg, device, ctx)
    state, saved_step, rng, averaged = TrainState(), None, None, None
    if resume:
        resumed = restore(run / "last.pt", parts, data, cfg, ctx, device)
        state, saved_step, rng, averaged = resumed.state, resumed.state.step, resumed.rng, resumed.averaged
    elif init is not None:
        load_init_weights(parts.model, init, data.meta)
    seed_rank_stream(cfg, ctx, state.step, rng)
    step_module = StepModule(parts.model, parts.weighting, objective, device, precision, compile=cfg.compile)
    ddp = distributed.wrap(step_module, ctx)
    loaders = build_loaders(cfg, data, device, ctx, state, shadow)
    return TrainSetup(cfg, ctx, owns_ctx, device, precision, run, data_dir, data, parts, objective, step_module, ddp,
                      loaders, state, saved_step, resume, averaged, sun)


__all__ = ["CPU_BF16_TRAINING", "Loaders", "ModelParts", "TrainData", "TrainSetup", "build_loaders",
           "build_model", "build_optimizer", "copy_paster", "input_normalization", "model_meta", "open_data",
           "prepare_caches", "prepare_training", "read_data_folder", "shadow_head_labels", "train_height_range",
           "user_cache_dir"]
