"""The trainer behind ``aerialmtl train``: data → D3-Net → masked losses → task weighting → Adam.

:class:`Trainer` is built from small parts, each readable and testable alone:

* data — :meth:`Trainer.build_data`: the decoded patch cache (:mod:`aerialmtl.data.cache`), the run's batch
  order (:class:`~aerialmtl.data.batches.EpochPlan`) and the DataLoaders; batches are augmented on the
  training device (:func:`~aerialmtl.data.batches.prepare_batch`);
* model and optimizer — :meth:`Trainer.build_model`, :func:`build_optimizer`;
* the step — :class:`StepModule` (forward, losses, weighting; what DistributedDataParallel wraps) and
  :meth:`Trainer.train_step`;
* validation — :meth:`Trainer.validate` (all processes, sums reduced);
* checkpoints and resume — :meth:`Trainer.checkpoint`, :meth:`Trainer.restore`, :mod:`aerialmtl.training.state`;
  fine-tuning from a checkpoint — :mod:`aerialmtl.training.finetune`;
* logging — :class:`~aerialmtl.training.runlog.CsvLog` and :class:`LossWindow`.

Several processes (``torchrun``) are handled by :mod:`aerialmtl.training.distributed`; here they appear
only as ``self.ctx`` (rank, world size, collectives that are no-ops for one process).

Device, precision, autocast and the compile fallback come from :mod:`aerialmtl.runtime` (as for prediction).
``precision: auto`` is bf16 autocast on a CUDA GPU with bf16 and fp32 otherwise (CPUs without bf16 units run
it hundreds of times slower; on CPUs with them see :data:`CPU_BF16_TRAINING`). Losses are computed in float32
either way. The model runs in ``channels_last``; ``compile: true`` (``--compile``) wraps it in
``torch.compile`` and falls back to eager execution with a warning if compilation fails.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from aerialmtl import runtime
from aerialmtl.config import to_dict
from aerialmtl.data.batches import CachedBatches, EpochPlan, RankBatchSampler, eval_batches, prepare_batch
from aerialmtl.data.cache import PatchCache, ensure_patch_cache
from aerialmtl.data.transforms import build_eval_transform, build_train_transform
from aerialmtl.errors import AerialMTLError, CheckpointError, ConfigError, NonFiniteError, OutputError
from aerialmtl.formats.checkpoint import (
    SURFACE_HEIGHTS_M,
    ModelMeta,
    check_same_data,
    first_nonfinite,
    height_slack,
    load_checkpoint,
    save_checkpoint,
    value_envelope,
)
from aerialmtl.formats.run import LOG_COLUMNS, RUN_FILES, CsvLog, RunFolder
from aerialmtl.formats.tiles import HEIGHT_NODATA, MANIFEST_CSV, TileFolderInfo, cache_dir, cache_file, read_manifest
from aerialmtl.io.oserrors import writing
from aerialmtl.models.config import ModelConfig
from aerialmtl.progress import tqdm_auto as tqdm
from aerialmtl.training import distributed
from aerialmtl.training.config import OptimSection, TrainConfig
from aerialmtl.training.distributed import DistContext
from aerialmtl.training.metrics import ConfusionMeter, HeightMeter
from aerialmtl.training.objective import Objective, class_weights, validation_score
from aerialmtl.training.state import TrainState, rank_seed, rng_state, seed_everything, set_rng_state

log = logging.getLogger(__name__)


def user_cache_dir(root: Path) -> Path:
    """Where the patch cache of a read-only tile folder goes: ``$XDG_CACHE_HOME/aerialmtl/<hash of its path>``."""
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "aerialmtl" / hashlib.sha256(str(root.resolve()).encode()).hexdigest()[:16]


#: Whether ``precision: auto`` trains in bf16 autocast on a CPU with native bf16 (measured: bench/RESULTS.md,
#: "CPU training precision"; fp32 until bf16 is both faster and as good there).
CPU_BF16_TRAINING = False


def resolve_precision(precision: str, device: torch.device) -> str:
    """``auto`` → ``bf16`` where the device computes it natively and training gains from it (CUDA GPUs
    with bf16; CPUs only if :data:`CPU_BF16_TRAINING`), else ``fp32``; others unchanged
    (:func:`aerialmtl.runtime.resolve_precision`)."""
    if precision == "auto":
        return runtime.resolve_precision("auto", device, cpu_bf16=CPU_BF16_TRAINING)
    return precision


def autocast(device: torch.device, precision: str) -> Any:
    """bf16 autocast for ``precision == "bf16"`` (:func:`aerialmtl.runtime.autocast`)."""
    return runtime.autocast(device, precision)


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


class StepModule(nn.Module):
    """Forward + losses + task weighting of a batch: ``(total, {task: loss})``.

    This is what DistributedDataParallel wraps, so the gradients of the learned task weighting are
    averaged over processes like the network's. ``net`` is the callable run on the image (the model, or
    its ``torch.compile`` wrapper sharing the same parameters).
    """

    def __init__(self, model: nn.Module, weighting: nn.Module, objective: Objective, device: torch.device,
                 precision: str) -> None:
        super().__init__()
        self.model, self.weighting = model, weighting
        self.objective, self.device, self.precision = objective, device, precision
        self._net: list[Any] = [model]  # a list: not registered as a second copy of the model's parameters

    @property
    def net(self) -> Any:
        return self._net[0]

    def use(self, net: Any) -> None:
        """Run ``net`` (the model or its compiled wrapper) on the images from now on."""
        self._net[0] = net

    def forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        with autocast(self.device, self.precision):
            out = self.net(batch["image"])
        losses = self.objective(out, batch)
        return self.weighting(self.objective.weighted(losses)), losses


#: A task loss this many times its first logged value means the run diverged (finite or not).
LOSS_GROWTH = 1e4
#: A validation class loss above this many times ln K (an untrained model's) means the run diverged.
EXPLODED_CLASS_LOSS = 20.0


class LossWindow:
    """Per-step losses kept on the device, read (one synchronisation, reduced over processes) only when
    logged or before a validation — not after every step, which would stall a GPU.

    ``flush`` checks every pending step for a non-finite loss, or a task loss that grew by more than
    :data:`LOSS_GROWTH` times its first logged value (a diverged-but-finite run), and raises naming the first
    one (with ``hint()``, what to do, appended).
    """

    def __init__(self, tasks: tuple[str, ...], ctx: DistContext, hint: Callable[[], str] | None = None) -> None:
        self.tasks, self.ctx = tasks, ctx
        self.hint = hint if hint is not None else (lambda: "")
        self.pending: list[torch.Tensor] = []
        self.first_step = 0
        self.window: dict[str, list[float]] = {"loss": [], **{t: [] for t in tasks}}
        self.since_val: list[float] = []
        #: each task's first logged loss (the untrained model's, or the resumed one's): the growth reference
        self.first: dict[str, float] = {}

    def add(self, step: int, total: torch.Tensor, losses: dict[str, torch.Tensor]) -> None:
        if not self.pending:
            self.first_step = step
        self.pending.append(torch.stack([total.float()] + [losses[t].float() for t in self.tasks]))

    def flush(self) -> None:
        if not self.pending:
            return
        values = self.ctx.all_reduce_sum(torch.stack(self.pending)) / self.ctx.world_size
        rows = values.cpu().tolist()
        first = self.first_step
        self.pending = []
        for i, row in enumerate(rows):
            if not math.isfinite(row[0]):
                tasks = [t for t, v in zip(self.tasks, row[1:]) if not math.isfinite(v)]
                which = f" ({', '.join(tasks)})" if tasks else ""
                raise NonFiniteError(f"training diverged at step {first + i}: the loss is {row[0]}{which}; "
                                     f"{self.hint()}")
            for t, v in zip(self.tasks, row[1:]):
                ref = self.first.setdefault(t, v)
                if ref > 0 and v > LOSS_GROWTH * ref:
                    raise NonFiniteError(f"training diverged at step {first + i}: the {t} loss grew from {ref:.3g} "
                                         f"to {v:.3g} (more than {LOSS_GROWTH:.0e} times); {self.hint()}")
            self.window["loss"].append(row[0])
            self.since_val.append(row[0])
            for t, v in zip(self.tasks, row[1:]):
                self.window[t].append(v)

    def take(self) -> dict[str, float]:
        """Means since the last ``take`` (after a flush); resets the window."""
        means = {k: float(np.mean(v)) for k, v in self.window.items() if v}
        self.window = {k: [] for k in self.window}
        return means

    def take_since_validation(self) -> float:
        value = float(np.mean(self.since_val)) if self.since_val else math.inf
        self.since_val = []
        return value


@dataclass
class TrainResult:
    """What a call to :func:`~aerialmtl.training.loop.train` produced.

    Attributes:
        run_dir: the run folder.
        last_checkpoint, best_checkpoint, log_path, config_path: files in ``run_dir``.
        step: optimisation steps done in total (including resumed ones).
        epoch: completed epochs.
        stopped_by: ``"epochs"``, ``"max_steps"``, ``"max_time"`` or ``"patience"`` (early stopping).
        elapsed_s: wall-clock seconds of this call.
        metrics: the last validation (``val_loss_<task>``, ``height_mae``/``height_rmse`` in metres,
            ``oa``/``miou``, ``score``); only ``score`` without a validation split.
        best_score: best validation score of the run (lower is better).
        model: the trained model as it is in ``last.pt`` (in train mode, on the training device).
    """

    run_dir: Path
    last_checkpoint: Path
    best_checkpoint: Path
    log_path: Path
    config_path: Path
    step: int
    epoch: int
    stopped_by: str
    elapsed_s: float
    metrics: dict[str, float] = field(default_factory=dict)
    best_score: float = math.inf
    model: torch.nn.Module | None = None


def input_normalization(model_cfg: ModelConfig,
                        info: TileFolderInfo) -> tuple[tuple[float, ...], tuple[float, ...], str]:
    """The per-band ``(mean, std)`` the model's inputs are normalised with, and where it comes from.

    An EfficientNet-Lite encoder with pretrained weights gets the scaling those weights were trained with,
    ``(x − 127) / 128`` on 8-bit bands (``"encoder"``); anything else the tile folder's train statistics
    (``"dataset"``). Pretrained weights on other than 8-bit data fall back to the statistics, with a warning.
    """
    from aerialmtl.models.efficientnet import IMAGENET_LITE_MEAN, IMAGENET_LITE_STD

    n = len(info.bands)
    if model_cfg.encoder != "densenet121" and model_cfg.encoder_weights:
        if str(info.dtype) == "uint8":
            return (IMAGENET_LITE_MEAN,) * n, (IMAGENET_LITE_STD,) * n, "encoder"
        warnings.warn(f"model.encoder_weights: the pretrained {model_cfg.encoder} weights expect 8-bit images scaled "
                      f"(x - 127) / 128, but the tile folder holds {info.dtype} bands; normalising with the tile "
                      "folder's statistics instead", UserWarning, stacklevel=2)
    return tuple(info.mean), tuple(info.std), "dataset"


class Trainer:
    """Train a D3-Net on a tile folder; :meth:`fit` runs it (see :func:`aerialmtl.training.loop.train`).

    Args:
        cfg: the training configuration.
        data_dir: tile folder (overrides ``cfg.data.dir``).
        out_dir: run folder.
        max_steps, max_time_s: override ``schedule.max_steps`` / ``schedule.max_time_s``.
        resume: continue from ``out_dir/last.pt``.
        init: start from the weights of this checkpoint (fine-tuning).
        progress: show a progress bar (rank 0 only).
        ctx: the process context (default: from torchrun's environment, one process without it).
    """

    def __init__(self, cfg: TrainConfig, data_dir: str | Path | None = None, out_dir: str | Path = "runs/train", *,
                 max_steps: int | None = None, max_time_s: float | None = None, resume: bool = False,
                 init: str | Path | None = None, progress: bool = True, ctx: DistContext | None = None) -> None:
        self.t0 = time.perf_counter()
        if resume and init is not None:
            raise ConfigError("init: a resumed run continues its own weights; pass init only when starting a run")
        self.cfg = cfg
        self.owns_ctx = ctx is None
        self.ctx = ctx if ctx is not None else DistContext.from_env(cfg.device)
        self.device = self.ctx.device
        self.precision = resolve_precision(cfg.precision, self.device)
        self.steps_cap = max_steps if max_steps is not None else cfg.schedule.max_steps
        self.time_cap = max_time_s if max_time_s is not None else cfg.schedule.max_time_s
        self.progress = progress and self.ctx.is_main
        self.run = Path(out_dir)
        self.paths = {n: self.run / n for n in RUN_FILES}

        self.info, self.model_cfg = self.read_data_folder(data_dir)
        self.tasks: tuple[str, ...] = tuple(self.model_cfg.tasks)
        self.k = self.info.classes.num_classes if self.info.classes is not None else None
        norm_mean, norm_std, normalization = input_normalization(self.model_cfg, self.info)
        self.meta = ModelMeta(model=self.model_cfg, classes=self.info.classes if "classes" in self.tasks else None,
                              bands=self.info.bands, mean=norm_mean, std=norm_std, gsd=self.info.gsd,
                              band_names=self.info.band_names, crs=self.info.crs, normalization=normalization,
                              input_dtype=self.info.dtype,
                              input_range=value_envelope(self.info.mean, self.info.std, self.info.dtype)
                              if self.info.mean and self.info.dtype else None)
        if self.ctx.is_main:
            self.run.mkdir(parents=True, exist_ok=True)
        self.objective = Objective(cfg, self.tasks, class_weights(cfg, self.info, self.k or 2)
                                   if "classes" in self.tasks else None)
        self.state = TrainState()
        #: step of the last checkpoint written whole (``last.pt``), or of the one resumed from
        self.saved_step: int | None = None
        self.prepare_caches()
        if "height" in self.tasks:
            self.meta = dataclasses.replace(self.meta, height_range=self.train_height_range())
        self.build_model()
        saved_rng: dict[str, Any] | None = None
        if resume:
            saved_rng = self.restore(self.paths["last.pt"])
        elif init is not None:
            from aerialmtl.training.finetune import load_init_weights

            load_init_weights(self.model, init, self.meta)
        self.seed_rank_stream(saved_rng)
        self.step_module = StepModule(self.model, self.weighting, self.objective, self.device, self.precision)
        self.compiled_ok = False
        if cfg.compile:
            self.step_module.use(torch.compile(self.model))
        self.ddp = distributed.wrap(self.step_module, self.ctx)
        if self.ctx.is_main:
            self.write_config(data_dir if data_dir is not None else cfg.data.dir)
        self.build_data()
        self.csv_log = CsvLog(self.paths["log.csv"], append=resume) if self.ctx.is_main else None
        self.losses = LossWindow(self.tasks, self.ctx, self.recovery_hint)
        self.metrics: dict[str, float] = {}

    # ---- data ---------------------------------------------------------------------------------------
    def read_data_folder(self, data_dir: str | Path | None) -> tuple[TileFolderInfo, ModelConfig]:
        """The tile folder and the model config it implies; checks ``data.crop_size`` against its patches."""
        data = data_dir if data_dir is not None else self.cfg.data.dir
        if data is None:
            raise ConfigError("data.dir: no tile folder given; set data.dir in the config or pass ‹data_dir›",
                              param="data_dir")
        info = TileFolderInfo.read(data)
        k = info.classes.num_classes if info.classes is not None else None
        model_cfg = self.cfg.model.resolve(info.num_bands, info.tasks, k)
        side = self.cfg.data.crop_size or info.patch_size
        if side % 32 or side > info.patch_size:
            raise ConfigError(
                f"data.crop_size: the network needs sides that are multiples of 32 and at most the {info.patch_size} "
                f"px patches of '{info.root}', got {side}; set data.crop_size to a multiple of 32 ≤ "
                f"{info.patch_size} or re-tile with --size a multiple of 32"
            )
        return info, model_cfg

    def prepare_caches(self) -> None:
        """Make sure the train (and val) split's patch caches are up to date (built on first use).

        Every process calls it; a lock file lets one build while the others wait.
        """
        cfg = self.cfg.data
        self.cache_folder = Path(cfg.cache_dir) if cfg.cache_dir else cache_dir(self.info.root)
        try:
            self.train_index = ensure_patch_cache(self.info, "train", self.cache_folder, workers=cfg.num_workers,
                                                  progress=self.progress)
        except OutputError:
            if cfg.cache_dir:
                raise
            self.cache_folder = user_cache_dir(self.info.root)  # a read-only tile folder still trains
            warnings.warn(f"data.cache_dir: the tile folder '{self.info.root}' is not writable; caching its decoded "
                          f"patches in '{self.cache_folder}' instead (set data.cache_dir to choose)",
                          UserWarning, stacklevel=2)
            self.train_index = ensure_patch_cache(self.info, "train", self.cache_folder, workers=cfg.num_workers,
                                                  progress=self.progress)
        self.val_index = None
        if read_manifest(self.info.root, "val"):
            self.val_index = ensure_patch_cache(self.info, "val", self.cache_folder, workers=cfg.num_workers,
                                                progress=self.progress)

    def train_height_range(self) -> tuple[float, float] | None:
        """``(min, max)`` metres of the train split's valid reference heights (read from the patch cache in
        chunks; ``None`` without a valid height), recorded in the checkpoint (:attr:`ModelMeta.height_range`)."""
        path = cache_file(self.cache_folder, "train", "height")
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

    @property
    def height_slack(self) -> float:
        """The largest validation height MAE (m) a sane model of these heights reaches (:func:`height_slack`)."""
        return height_slack(self.meta.height_range)

    def build_data(self) -> None:
        """The batch plan from the current position, and the train and val loaders over the caches."""
        cfg, ctx, nw = self.cfg.data, self.ctx, self.cfg.data.num_workers
        folder, train_index, val_index = self.cache_folder, self.train_index, self.val_index
        pin = self.device.type == "cuda"
        self.plan = EpochPlan(train_index.count, cfg.batch_size, self.cfg.seed, ctx.world_size)
        self.train_transform = build_train_transform(cfg.flips, cfg.rot90, cfg.jitter, cfg.crop_size)
        self.mean = torch.tensor(self.meta.mean, dtype=torch.float32, device=self.device)
        self.std = torch.tensor(self.meta.std, dtype=torch.float32, device=self.device)
        # on a CPU with workers, the workers finish the batches (the main process computes the model)
        in_workers = (self.mean.cpu(), self.std.cpu()) if self.device.type == "cpu" and nw > 0 else None
        self.train_loader = torch.utils.data.DataLoader(
            CachedBatches(PatchCache(folder, train_index), self.train_transform, self.tasks, in_workers),
            sampler=RankBatchSampler(self.plan, ctx.rank, self.state.epoch, self.state.position),
            batch_size=None, num_workers=nw, pin_memory=pin, generator=torch.Generator().manual_seed(self.cfg.seed),
        )
        self.val_loader: torch.utils.data.DataLoader | None = None
        self.eval_transform = build_eval_transform(cfg.crop_size)
        if val_index is not None:
            self.val_loader = torch.utils.data.DataLoader(
                CachedBatches(PatchCache(folder, val_index), self.eval_transform, self.tasks, in_workers),
                sampler=eval_batches(val_index.count, cfg.batch_size, ctx.rank, ctx.world_size),
                batch_size=None, num_workers=min(nw, 1), persistent_workers=nw > 0, pin_memory=pin,
                generator=torch.Generator().manual_seed(self.cfg.seed))
        elif ctx.is_main:
            log.warning("no 'val' patches in %s: best.pt is chosen by the training loss", self.info.root / MANIFEST_CSV)

    # ---- model and optimizer ------------------------------------------------------------------------
    def build_model(self) -> None:
        """Seeded D3-Net (channels_last, SyncBatchNorm if asked with several processes), weighting, optimizer."""
        from aerialmtl.models.d3net import D3Net
        from aerialmtl.training.weighting import build_weighting

        seed_everything(self.cfg.seed)
        model: nn.Module = D3Net(self.model_cfg).to(self.device).to(memory_format=torch.channels_last)  # type: ignore[call-overload]
        if self.cfg.model.sync_bn and self.ctx.distributed:
            model = distributed.convert_sync_batchnorm(model, self.device)
        self.model = model
        self.weighting = build_weighting(self.cfg.weighting.method, list(self.tasks)).to(self.device)
        self.optimizer = build_optimizer(self.cfg.optim, self.model, self.weighting)

    def seed_rank_stream(self, saved: dict[str, Any] | None) -> None:
        """Give this process its RNG stream: the saved one when resuming, else rank 0 keeps the seeded
        stream (a single process is unchanged) and rank r > 0 gets its own (other dropout masks)."""
        if saved:
            set_rng_state(saved)
        elif self.ctx.rank > 0:
            seed_everything(rank_seed(self.cfg.seed + self.state.step, self.ctx.rank))

    # ---- the step -----------------------------------------------------------------------------------
    def train_step(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One optimisation step on a prepared batch; returns the detached total and task losses."""
        try:
            total, losses = self.ddp(batch)
        except Exception as exc:  # torch.compile failed at its first call: continue without it
            if self.step_module.net is self.model or self.compiled_ok or isinstance(exc, AerialMTLError):
                raise
            runtime.warn_compile_failed(exc, "training")
            self.step_module.use(self.model)
            total, losses = self.ddp(batch)
        self.compiled_ok = True
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        self.optimizer.step()
        return total.detach(), {t: v.detach() for t, v in losses.items()}

    # ---- validation ---------------------------------------------------------------------------------
    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Mean validation loss per task and height/classification metrics over the whole val split.

        Every process evaluates its share of the batches; sums are reduced, so the result is the same as
        one process evaluating all of them.

        Returns:
            ``val_loss_<task>``, and ``height_mae``/``height_rmse`` (metres) and/or ``oa``/``miou``. A task
            whose loss was NaN or inf on any batch has a non-finite ``val_loss_<task>`` (never a flattering 0).
        """
        assert self.val_loader is not None
        was_training = self.model.training
        self.model.eval()
        sums = torch.zeros(len(self.tasks) + 1, dtype=torch.float64)
        hm, cm = HeightMeter(), ConfusionMeter(self.k or 2)
        for raw in self.val_loader:
            batch = prepare_batch(raw, self.eval_transform, self.mean, self.std, self.device)
            with autocast(self.device, self.precision):
                out = self.model(batch["image"])
            losses = self.objective(out, batch, scoring=True)
            for i, t in enumerate(self.tasks):
                sums[i] += float(losses[t])  # NaN/inf stays: a diverged model can never score best
            sums[-1] += 1
            if "height" in self.tasks:
                hm.update(out["height"].float(), batch["height"], batch["height_valid"])
            if "classes" in self.tasks:
                cm.update(out["classes"].float(), batch["classes"])
        self.model.train(was_training)
        self.ctx.all_reduce_sum(sums)
        metrics = {f"val_loss_{t}": float(sums[i]) / max(1.0, float(sums[-1])) for i, t in enumerate(self.tasks)}
        if "height" in self.tasks:
            hm.sync(self.ctx.all_reduce_sum)
            metrics.update(hm.compute())
        if "classes" in self.tasks:
            cm.sync(self.ctx.all_reduce_sum)
            metrics.update(cm.compute())
        return metrics

    def after_epoch_validation(self) -> bool:
        """Validate (or score by the training loss without a val split), log, write best.pt/last.pt.

        Returns:
            True when early stopping says to stop (``schedule.patience`` validations without improvement).
        """
        self.losses.flush()
        st = self.state
        if self.val_loader is not None:
            self.metrics = self.validate()
            current = {t: self.metrics[f"val_loss_{t}"] for t in self.tasks}
            st.ref_losses = reference = st.ref_losses or current
            score = validation_score(current, reference, self.objective.task_weights)
            self.losses.take_since_validation()
            measured = True
        else:
            measured = bool(self.losses.since_val)  # False: no step since the last score (inf, as before)
            score = self.losses.take_since_validation()
        self.metrics["score"] = score
        if self.csv_log is not None:
            self.csv_log.write(kind="val", step=st.step, epoch=st.epoch, time_s=self.elapsed(), lr=self.lr,
                               **{m: self.metrics.get(m) for m in LOG_COLUMNS if m in self.metrics})
        if measured and not math.isfinite(score):  # every process sees the same reduced score, so all stop together
            bad = [t for t in self.tasks if not math.isfinite(self.metrics.get(f"val_loss_{t}", 0.0))]
            raise NonFiniteError(
                f"training diverged: the validation score at step {st.step} is {score}"
                f"{' (' + ', '.join(bad) + ' loss)' if bad else ''}; best.pt keeps the best finite score; "
                f"{self.recovery_hint()}"
            )
        if measured:
            self.check_exploded(st.step)
        improved = score < st.best_score
        if improved or not self.paths["best.pt"].exists():
            st.best_score = min(st.best_score, score)
            self.checkpoint(self.paths["best.pt"])
        st.since_best = 0 if improved else st.since_best + 1
        self.checkpoint(self.paths["last.pt"])
        patience = self.cfg.schedule.patience
        return patience is not None and st.since_best >= patience

    def check_exploded(self, step: int) -> None:
        """Stop like a non-finite run when the validation error is finite but can only be garbage: a height MAE
        beyond :attr:`height_slack` (10 × the trained height span + 100 m), or a class loss above
        :data:`EXPLODED_CLASS_LOSS` × ln K (an untrained model scores ln K). Every process sees the same
        reduced metrics, so all stop together; ``best.pt`` and ``last.pt`` are not replaced.

        Raises:
            NonFiniteError: naming the step, the value, the bound and what to do.
        """
        kept = ("best.pt keeps the best earlier score" if self.paths["best.pt"].exists()
                else "it was not saved as best.pt")
        mae = self.metrics.get("height_mae")
        if mae is not None and mae > self.height_slack:
            trained = (f"reference heights of {self.meta.height_range[0]:.4g}..{self.meta.height_range[1]:.4g} m"
                       if self.meta.height_range is not None else "reference heights")
            raise NonFiniteError(
                f"training diverged: the validation height MAE at step {step} is {mae:.3g} m, more than "
                f"{self.height_slack:.4g} m for {trained}, so {kept}; "
                f"{self.recovery_hint()}")
        ce = self.metrics.get("val_loss_classes")
        bound = EXPLODED_CLASS_LOSS * math.log(max(self.k or 2, 2))
        if ce is not None and ce > bound:
            raise NonFiniteError(
                f"training diverged: the validation class loss at step {step} is {ce:.3g}, more than {bound:.3g} "
                f"({EXPLODED_CLASS_LOSS:g} × ln {self.k}, what an untrained model scores), so {kept}; "
                f"{self.recovery_hint()}")

    # ---- checkpoints --------------------------------------------------------------------------------
    def recovery_hint(self) -> str:
        """What to do after a divergence: where the last whole checkpoint is, and how to continue (first, when
        the tile folder's reference heights are ones no surface has, that: no learning rate fixes them)."""
        hr = self.meta.height_range
        if hr is not None and (hr[0] < SURFACE_HEIGHTS_M[0] or hr[1] > SURFACE_HEIGHTS_M[1]):
            return (f"the tile folder's reference heights reach {hr[0]:.3g}..{hr[1]:.3g} m, which no surface has "
                    "(an undeclared nodata value or a wrong unit in the DSM/DTM/nDSM): fix the height files "
                    "(`gdal_edit.py -a_nodata VALUE FILE`, --z-unit) and run `aerialmtl tile ... --overwrite` again")
        last = self.paths["last.pt"]
        lower = f"lower optim.lr (now {self.cfg.optim.lr:g}; e.g. {self.cfg.optim.lr / 10:g})"
        if self.saved_step is not None and last.exists():
            return (f"'{last}' (step {self.saved_step}) is the last good state, unchanged: {lower} in "
                    f"'{self.paths['config.yaml']}' and continue with `aerialmtl train --out {self.run} --resume`, "
                    "use precision fp32, or check the tile folder's images and references")
        return (f"no checkpoint was written; {lower}, use precision fp32, or check the tile folder's images and "
                "references, then start again")

    def checkpoint(self, target: Path) -> None:
        """Write a checkpoint with the full training state (rank 0 writes; every process must call it).

        Raises:
            NonFiniteError: a weight is NaN or inf (checked on every process, so all stop together); the
                checkpoint files stay as they were.
        """
        bad = first_nonfinite(self.model.state_dict())
        if bad is not None:
            raise NonFiniteError(f"training diverged at step {self.state.step}: weight '{bad}' holds NaN or inf; "
                                 f"{self.recovery_hint()}")
        rngs = self.ctx.gather_objects(rng_state())
        if not self.ctx.is_main:
            if target == self.paths["last.pt"]:
                self.saved_step = self.state.step
            return
        state = {"optimizer": self.optimizer.state_dict(), "weighting": self.weighting.state_dict(),
                 **self.state.to_dict(self.plan.global_batch), "rng": rngs[0], "rng_ranks": rngs,
                 "world_size": self.ctx.world_size, "global_batch": self.plan.global_batch,
                 "config": self.cfg.to_dict()}
        save_checkpoint(target, self.model, self.meta, state)
        if target == self.paths["last.pt"]:
            self.saved_step = self.state.step

    def restore(self, path: Path) -> dict[str, Any]:
        """Load weights, optimizer, weighting and counters from ``path``; returns this process's RNG state.

        The config's ``optim.lr`` and ``optim.betas`` replace those stored with the optimizer
        state (its moments are kept), so a run that diverged can continue from its last good ``last.pt``
        with a lower ``optim.lr`` written into the run's ``config.yaml``.

        Raises:
            CheckpointError: no training state, other data, another model config, or a training state that
                does not have the form ``aerialmtl train`` writes (e.g. edited by hand); names the file.
        """
        payload, old_meta = load_checkpoint(path, map_location=self.device)
        ts = payload.get("train_state")
        if not ts:
            raise CheckpointError(f"checkpoint '{path}' has no training state; cannot ‹resume› from it")
        check_same_data(path, old_meta, self.meta)
        if to_dict(old_meta.model) != to_dict(self.model_cfg):
            raise CheckpointError(
                f"checkpoint '{path}' was trained with another model config; "
                "resume with the run's config.yaml or start a new run (--overwrite)"
            )
        try:
            self.model.load_state_dict(payload["state_dict"])
        except (RuntimeError, KeyError, TypeError) as exc:
            raise self._bad_state(path, "its weights do not fit the model", exc) from exc
        if not isinstance(ts, dict):
            raise self._bad_state(path, "its training state is not a mapping", None)
        bad = first_nonfinite(ts.get("optimizer"))
        if bad is not None:
            raise CheckpointError(
                f"checkpoint '{path}': its optimizer state holds NaN or inf ('{bad}'); it cannot be resumed: start a "
                "new run (another --out, or --overwrite), with a lower optim.lr"
            )
        try:
            self.optimizer.load_state_dict(ts["optimizer"])
        except ValueError as exc:
            raise CheckpointError(
                f"checkpoint '{path}': its optimizer state does not fit this optimizer ({exc}); resume with the "
                "run's config.yaml (same optim section) or start a new run"
            ) from exc
        except (KeyError, TypeError, RuntimeError, IndexError) as exc:
            raise self._bad_state(path, "its optimizer state is incomplete", exc) from exc
        optim = self.cfg.optim
        for group in self.optimizer.param_groups:  # weight decay: the group structure already follows the config
            group.update(lr=optim.lr, betas=optim.betas)
        try:
            self.weighting.load_state_dict(ts["weighting"])
            old_global = int(ts.get("global_batch") or 0)
            self.state = TrainState.from_dict(ts, old_global or self._global_batch_guess())
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise self._bad_state(path, "its counters or task weighting are incomplete", exc) from exc
        self.saved_step = self.state.step
        ranks = ts.get("rng_ranks")
        if ranks and int(ts.get("world_size", 1)) == self.ctx.world_size:
            rng = ranks[self.ctx.rank]
        elif self.ctx.rank == 0:
            rng = ts.get("rng")
        else:
            return {}
        return self._checked_rng(path, rng)

    def _checked_rng(self, path: Path, rng: Any) -> dict[str, Any]:
        """``rng`` if it restores (tried on a copy of the current states), else a CheckpointError."""
        if not rng:
            raise self._bad_state(path, "its RNG state is missing", None)
        current = rng_state()
        try:
            set_rng_state(rng)
        except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as exc:
            raise self._bad_state(path, "its RNG state is invalid", exc) from exc
        finally:
            set_rng_state(current)
        return dict(rng)

    @staticmethod
    def _bad_state(path: Path, what: str, exc: BaseException | None) -> CheckpointError:
        why = f" ({' '.join(str(exc).split())[:160] or exc.__class__.__name__})" if exc is not None else ""
        return CheckpointError(
            f"checkpoint '{path}' cannot be resumed: {what}{why}; it was not written by `aerialmtl train` as it is "
            "(edited or from another version): resume from an unedited last.pt, or start a new run (another "
            "--out, or --overwrite) with ‹init› to reuse its weights"
        )

    def _global_batch_guess(self) -> int:
        """The global batch of a checkpoint written before it was recorded (one process, this batch size)."""
        n = len(read_manifest(self.info.root, "train"))
        return min(self.cfg.data.batch_size, n)

    def write_config(self, data: str | Path | None) -> None:
        """``config.yaml``: the config with the model fields taken from the data and the absolute data dir."""
        resolved = self.cfg.to_dict()
        resolved["model"] = {**to_dict(self.model_cfg), "sync_bn": self.cfg.model.sync_bn}
        resolved["data"]["dir"] = str(Path(data).resolve()) if data is not None else None
        with writing(self.paths["config.yaml"], "the run's config"):
            RunFolder(self.run).write_config(resolved)

    # ---- the loop -----------------------------------------------------------------------------------
    @property
    def lr(self) -> float:
        return float(self.optimizer.param_groups[0]["lr"])

    def elapsed(self) -> float:
        return round(time.perf_counter() - self.t0, 3)

    def log_train_row(self) -> dict[str, float]:
        """Write the ``train`` row of the steps since the last one; returns its mean losses."""
        self.losses.flush()
        means = self.losses.take()
        if self.csv_log is not None and means:
            self.csv_log.write(kind="train", step=self.state.step, epoch=self.state.epoch, time_s=self.elapsed(),
                               lr=self.lr, loss=means["loss"], **{f"loss_{t}": means.get(t) for t in self.tasks})
        return means

    def done(self) -> str | None:
        """Why training must stop now (``max_steps``, ``epochs``, ``max_time``), or ``None``."""
        st = self.state
        if self.steps_cap is not None and st.step >= self.steps_cap:
            return "max_steps"
        if st.epoch >= self.cfg.schedule.epochs:
            return "epochs"
        if self.time_cap is not None and self.ctx.any(time.perf_counter() - self.t0 >= self.time_cap):
            return "max_time"
        return None

    def fit(self) -> TrainResult:
        """Train until a stop condition (each process returns the same counters and metrics)."""
        st, sched = self.state, self.cfg.schedule
        nb = self.plan.steps_per_epoch
        total = sched.epochs * nb if self.steps_cap is None else min(self.steps_cap, sched.epochs * nb)
        stopped_by = self.done_before_start()
        validated_at = -1
        self.model.train()
        bar = tqdm(total=total, initial=min(st.step, total), disable=not self.progress, desc="train", unit="step",
                   dynamic_ncols=True)
        it = iter(self.train_loader) if stopped_by is None else None
        try:
            while stopped_by is None:
                assert it is not None
                batch = prepare_batch(next(it), self.train_transform, self.mean, self.std, self.device)
                total_loss, losses = self.train_step(batch)
                st.step += 1
                self.losses.add(st.step, total_loss, losses)
                st.epoch, st.position = self.plan.advance(st.epoch, st.position)
                bar.update(1)
                if st.step % sched.log_every == 0:
                    means = self.log_train_row()
                    bar.set_postfix(loss=f"{means.get('loss', math.nan):.4f}", epoch=st.epoch)
                if st.position == 0 and st.epoch % sched.val_every == 0:
                    validated_at = st.step
                    if self.after_epoch_validation():
                        stopped_by = "patience"
                        break
                stopped_by = self.done()
        except RuntimeError as exc:  # DDP's gradient all-reduce: a peer process is gone
            if self.ctx.distributed and distributed.is_peer_error(exc):
                raise distributed.PeerFailure(distributed.peer_failure_message(exc)) from exc
            raise
        finally:
            bar.close()
            del it
        if validated_at != st.step or not self.paths["last.pt"].exists():
            self.after_epoch_validation()
        self.calibrate()
        return TrainResult(run_dir=self.run, last_checkpoint=self.paths["last.pt"],
                           best_checkpoint=self.paths["best.pt"], log_path=self.paths["log.csv"],
                           config_path=self.paths["config.yaml"], step=st.step, epoch=st.epoch, stopped_by=stopped_by,
                           elapsed_s=time.perf_counter() - self.t0, metrics=self.metrics, best_score=st.best_score,
                           model=self.model)

    def calibrate(self) -> None:
        """Fit the calibration on the val split and store it in best.pt and last.pt (rank 0; see
        :mod:`aerialmtl.training.calibrate`); skipped without a val split or a height task."""
        cal = self.cfg.calibration
        if not (cal.enabled and self.ctx.is_main and self.val_loader is not None and "height" in self.tasks):
            return
        from aerialmtl.training.calibrate import calibrate_checkpoint

        for name in ("best.pt", "last.pt"):
            if self.paths[name].exists():
                c = calibrate_checkpoint(self.paths[name], self.info.root, mc=cal.mc_samples, method=cal.method,
                                         cache_folder=self.cache_folder, device=self.device)
                log.info("%s: %s", name, c.summary())

    def done_before_start(self) -> str | None:
        """Stop reason of a resumed run that has nothing left to do (no time check: it has not started)."""
        st = self.state
        if self.steps_cap is not None and st.step >= self.steps_cap:
            return "max_steps"
        if st.epoch >= self.cfg.schedule.epochs:
            return "epochs"
        return None

    def close(self) -> None:
        """Release the process group if this trainer created it."""
        if self.owns_ctx:
            self.ctx.close()


__all__ = ["Trainer", "TrainResult", "StepModule", "LossWindow", "build_optimizer", "resolve_precision", "autocast",
           "RUN_FILES"]
