"""The training loop of ``aerialmtl train``: data → D3-Net → masked losses → task weighting → Adam.

:func:`train` writes a run folder::

    RUN/config.yaml   the resolved config (model fields filled from dataset.yaml, absolute data dir)
    RUN/last.pt       checkpoint after every validation and when training stops (also on a time budget)
    RUN/best.pt       checkpoint with the best validation score so far (see below)
    RUN/log.csv       one ``train`` row every ``schedule.log_every`` steps, one ``val`` row per validation

Validation score (lower is better): ``Σ_t w_t · L_t / L_t⁰`` over the model's tasks, where ``L_t`` is the
validation loss of task t, ``L_t⁰`` its value at the first validation of the run and ``w_t`` the task
weight (``weighting.task_weights``, default 1). Normalising by the first value puts height (metres) and
classes (nats) on the same footing, so neither task dominates the choice of ``best.pt``. Without a
validation split the mean training loss since the last validation point is used instead.

Reproducibility and ``--resume``: the order of patches comes from a permutation seeded by
``(seed, epoch)`` and each patch's augmentation from a generator seeded by its position in the run,
so neither depends on the number of DataLoader workers. ``last.pt`` stores the optimizer, the weighting
module, step/epoch/position in the epoch and the torch/numpy/python RNG states; resuming continues with
exactly the batches, augmentations and dropout masks an uninterrupted run would have used.
``max_time_s`` is a wall-clock budget for one invocation of :func:`train`.
"""

from __future__ import annotations

import csv
import logging
import math
import random
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from tqdm.auto import tqdm

from aerialmtl.classes import IGNORE_INDEX
from aerialmtl.config import to_dict
from aerialmtl.data.dataset import PatchDataset, TileFolderInfo, class_pixel_counts, read_manifest, read_tile_info
from aerialmtl.data.transforms import build_eval_transform, build_train_transform
from aerialmtl.errors import AerialMTLError, CheckpointError, ConfigError, InputError
from aerialmtl.formats.checkpoint import ModelMeta, check_same_data, load_checkpoint, save_checkpoint
from aerialmtl.models.config import ModelConfig
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.metrics import ConfusionMeter, HeightMeter

log = logging.getLogger(__name__)

LOG_COLUMNS = (
    "kind", "step", "epoch", "time_s", "lr", "loss", "loss_height", "loss_classes",
    "val_loss_height", "val_loss_classes", "height_mae", "height_rmse", "oa", "miou", "score",
)


@dataclass
class TrainResult:
    """What a call to :func:`train` produced.

    Attributes:
        run_dir: the run folder.
        last_checkpoint, best_checkpoint, log_path, config_path: files in ``run_dir``.
        step: optimisation steps done in total (including resumed ones).
        epoch: completed epochs.
        stopped_by: ``"epochs"``, ``"max_steps"`` or ``"max_time"``.
        elapsed_s: wall-clock seconds of this call.
        metrics: the last validation (``val_loss_<task>``, ``height_mae``/``height_rmse`` in metres,
            ``oa``/``miou``, ``score``); empty without a validation split.
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


# ---- helpers ------------------------------------------------------------------------------------
def resolve_device(name: str) -> torch.device:
    """``auto`` → CUDA when available, else CPU; ``cuda`` without a GPU is an error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device: 'cuda' was requested but no CUDA GPU is available; use --device cpu or auto")
    return torch.device(name)


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (all devices)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _rng_state() -> dict[str, Any]:
    np_state = np.random.get_state()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {"keys": torch.from_numpy(np.asarray(np_state[1], dtype=np.int64)), "pos": int(np_state[2]),
                  "has_gauss": int(np_state[3]), "cached_gaussian": float(np_state[4])},
        "python": random.getstate(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state(("MT19937", n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def _item_seed(seed: int, epoch: int, position: int) -> int:
    """A 63-bit seed for the augmentation of the patch at ``position`` of ``epoch``."""
    return (seed * 6364136223846793005 + epoch * 1442695040888963407 + position * 2862933555777941757) % 2**63


class _RunBatchSampler:
    """Batches of ``(index, augmentation seed)`` for the whole run, starting at (epoch, batch).

    Every epoch is a fresh permutation of the train split seeded by ``(seed, epoch)``; the last
    incomplete batch is dropped (BatchNorm dislikes tiny batches), unless the split is smaller than
    one batch, in which case the batch is the whole split.
    """

    def __init__(self, n: int, batch_size: int, seed: int, start_epoch: int, start_batch: int) -> None:
        self.n, self.bs, self.seed = n, min(batch_size, n), seed
        self.start_epoch, self.start_batch = start_epoch, start_batch

    @property
    def batches_per_epoch(self) -> int:
        return self.n // self.bs

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        epoch, first = self.start_epoch, self.start_batch
        while True:
            perm = torch.randperm(self.n, generator=torch.Generator().manual_seed(self.seed * 7919 + epoch))
            for b in range(first, self.batches_per_epoch):
                pos = range(b * self.bs, (b + 1) * self.bs)
                yield [(int(perm[p]), _item_seed(self.seed, epoch, p)) for p in pos]
            epoch, first = epoch + 1, 0


class _SeededDataset(torch.utils.data.Dataset):
    """Wraps a :class:`PatchDataset`: items are ``(index, seed)`` and the transform gets a seeded generator."""

    def __init__(self, base: PatchDataset, transform: Callable[..., Any]) -> None:
        self.base, self.transform = base, transform

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, item: tuple[int, int]) -> dict[str, Any]:
        index, seed = item
        return self.transform(self.base.load(index), torch.Generator().manual_seed(seed))


def _class_weights(cfg: TrainConfig, info: TileFolderInfo, k: int) -> torch.Tensor | None:
    spec = cfg.loss.class_weights
    if spec == "none":
        return None
    if spec == "balanced":
        counts = class_pixel_counts(info.root, "train", k).astype(np.float64)
        present = counts > 0
        if not present.any():
            raise InputError(f"loss.class_weights: 'balanced' needs class_hist in '{info.root / 'manifest.csv'}'")
        w = np.ones(k)
        w[present] = counts[present].sum() / (present.sum() * counts[present])
        w[present] /= w[present].mean()
        return torch.tensor(w, dtype=torch.float32)
    if len(spec) != k:
        raise ConfigError(f"loss.class_weights: got {len(spec)} weights but the class scheme has {k} classes")
    return torch.tensor(spec, dtype=torch.float32)


def _to_device(batch: dict[str, Any], device: torch.device) -> dict[str, Any]:
    out = {}
    for k, v in batch.items():
        if isinstance(v, torch.Tensor):
            v = v.to(device, non_blocking=True)
            if k == "image":
                v = v.contiguous(memory_format=torch.channels_last)
        out[k] = v
    return out


class _Objective:
    """Per-task losses of a batch (float32 scalars), masked to valid pixels."""

    def __init__(self, cfg: TrainConfig, tasks: tuple[str, ...], class_weights: torch.Tensor | None) -> None:
        from aerialmtl.training import losses

        self.tasks = tasks
        self.height_fn = losses.HEIGHT_LOSSES[cfg.loss.height]
        self.ce = losses.cross_entropy
        self.class_weights = class_weights
        self.task_weights = {t: float(cfg.weighting.task_weights.get(t, 1.0)) for t in tasks}

    def __call__(self, out: dict[str, torch.Tensor], batch: dict[str, Any]) -> dict[str, torch.Tensor]:
        losses: dict[str, torch.Tensor] = {}
        if "height" in self.tasks:
            losses["height"] = self.height_fn(out["height"].float(), batch["height"], batch["height_valid"])
        if "classes" in self.tasks:
            w = None if self.class_weights is None else self.class_weights.to(out["classes"].device)
            losses["classes"] = self.ce(out["classes"].float(), batch["classes"], weight=w,
                                        ignore_index=IGNORE_INDEX)
        return losses


def _autocast(device: torch.device, precision: str) -> Any:
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=precision == "bf16")


@torch.no_grad()
def validate(model: torch.nn.Module, loader: torch.utils.data.DataLoader, objective: _Objective,
             device: torch.device, precision: str, num_classes: int) -> dict[str, float]:
    """Mean validation loss per task and height/classification metrics over the whole split.

    Returns:
        ``val_loss_<task>``, and ``height_mae``/``height_rmse`` (metres) and/or ``oa``/``miou``.
    """
    was_training = model.training
    model.eval()
    sums = {t: 0.0 for t in objective.tasks}
    n_batches = 0
    hm, cm = HeightMeter(), ConfusionMeter(num_classes)
    for batch in loader:
        batch = _to_device(batch, device)
        with _autocast(device, precision):
            out = model(batch["image"])
        for t, v in objective(out, batch).items():
            if torch.isfinite(v):
                sums[t] += float(v)
        n_batches += 1
        if "height" in objective.tasks:
            hm.update(out["height"].float(), batch["height"], batch["height_valid"])
        if "classes" in objective.tasks:
            cm.update(out["classes"].float(), batch["classes"])
    model.train(was_training)
    metrics = {f"val_loss_{t}": s / max(1, n_batches) for t, s in sums.items()}
    if "height" in objective.tasks:
        metrics.update(hm.compute())
    if "classes" in objective.tasks:
        metrics.update(cm.compute())
    return metrics


def _score(losses: dict[str, float], ref: dict[str, float], weights: dict[str, float]) -> float:
    return float(sum(weights[t] * v / max(ref[t], 1e-12) for t, v in losses.items()))


class _CsvLog:
    def __init__(self, path: Path, append: bool) -> None:
        self.path = path
        if not (append and path.is_file()):
            with path.open("w", newline="") as fh:
                csv.writer(fh).writerow(LOG_COLUMNS)

    def write(self, **row: Any) -> None:
        with self.path.open("a", newline="") as fh:
            csv.writer(fh).writerow(["" if row.get(c) is None else row.get(c) for c in LOG_COLUMNS])


def _build_weighting(cfg: TrainConfig, tasks: tuple[str, ...]) -> torch.nn.Module:
    from aerialmtl.training.weighting import build_weighting

    return build_weighting(cfg.weighting.method, list(tasks))


# ---- the loop ------------------------------------------------------------------------------------
def train(
    cfg: TrainConfig,
    data_dir: str | Path | None = None,
    out_dir: str | Path = "runs/train",
    max_steps: int | None = None,
    max_time_s: float | None = None,
    resume: bool = False,
    progress: bool = True,
) -> TrainResult:
    """Train a D3-Net on a tile folder and write checkpoints, a CSV log and the resolved config.

    Args:
        cfg: the training configuration.
        data_dir: tile folder (overrides ``cfg.data.dir``).
        out_dir: run folder (created; the caller decides whether an existing one may be reused).
        max_steps: total optimisation steps (overrides ``cfg.schedule.max_steps``).
        max_time_s: wall-clock budget of this call in seconds (overrides ``cfg.schedule.max_time_s``).
        resume: continue from ``out_dir/last.pt``.
        progress: show a tqdm bar with the running loss.

    Returns:
        A :class:`TrainResult`.

    Raises:
        ConfigError: no data folder, cuda unavailable, config/data mismatch.
        InputError: the data folder is not a tile folder or the train split is empty.
        CheckpointError: ``resume`` without a usable ``last.pt`` or with a different model config.
    """
    t0 = time.perf_counter()
    data = data_dir if data_dir is not None else cfg.data.dir
    if data is None:
        raise ConfigError("data.dir: no tile folder given; set data.dir in the config or pass --data")
    info = read_tile_info(data)
    k = info.classes.num_classes if info.classes is not None else None
    model_cfg: ModelConfig = cfg.model.resolve(info.num_bands, info.tasks, k)
    tasks = tuple(model_cfg.tasks)
    side = cfg.data.crop_size or info.patch_size
    if side % 32 or side > info.patch_size:
        raise ConfigError(
            f"data.crop_size: the network needs sides that are multiples of 32 and at most the {info.patch_size} px "
            f"patches of '{info.root}', got {side}; set data.crop_size to a multiple of 32 ≤ {info.patch_size} "
            "or re-tile with --size a multiple of 32"
        )
    device = resolve_device(cfg.device)
    steps_cap = max_steps if max_steps is not None else cfg.schedule.max_steps
    time_cap = max_time_s if max_time_s is not None else cfg.schedule.max_time_s

    run = Path(out_dir)
    run.mkdir(parents=True, exist_ok=True)
    paths = {n: run / n for n in ("last.pt", "best.pt", "log.csv", "config.yaml")}

    seed_everything(cfg.seed)
    from aerialmtl.models.d3net import D3Net

    model = D3Net(model_cfg).to(device).to(memory_format=torch.channels_last)
    weighting = _build_weighting(cfg, tasks).to(device)
    params = list(model.parameters()) + list(weighting.parameters())
    opt_cls = torch.optim.AdamW if cfg.optim.name == "adamw" else torch.optim.Adam
    optimizer = opt_cls(params, lr=cfg.optim.lr, betas=cfg.optim.betas, weight_decay=cfg.optim.weight_decay)
    meta = ModelMeta(model=model_cfg, classes=info.classes if "classes" in tasks else None, bands=info.bands,
                     mean=info.mean, std=info.std, gsd=info.gsd, band_names=info.band_names, crs=info.crs)

    step, epoch, batch_in_epoch = 0, 0, 0
    best, ref_losses = math.inf, None
    if resume:
        payload, old_meta = load_checkpoint(paths["last.pt"], map_location=device)
        ts = payload.get("train_state")
        if not ts:
            raise CheckpointError(f"checkpoint '{paths['last.pt']}' has no training state; cannot --resume from it")
        check_same_data(paths["last.pt"], old_meta, meta)
        if to_dict(old_meta.model) != to_dict(model_cfg):
            raise CheckpointError(
                f"checkpoint '{paths['last.pt']}' was trained with another model config; "
                "resume with the run's config.yaml or start a new run (--overwrite)"
            )
        model.load_state_dict(payload["state_dict"])
        optimizer.load_state_dict(ts["optimizer"])
        weighting.load_state_dict(ts["weighting"])
        step, epoch, batch_in_epoch = ts["step"], ts["epoch"], ts["batch_in_epoch"]
        best, ref_losses = ts["best_score"], ts["ref_losses"]
        _set_rng_state(ts["rng"])

    resolved = cfg.to_dict()
    resolved["model"] = to_dict(model_cfg)
    resolved["data"]["dir"] = str(Path(data).resolve())
    with paths["config.yaml"].open("w") as fh:
        yaml.safe_dump(resolved, fh, sort_keys=False)

    train_ds = PatchDataset(data, "train", tasks=tasks)
    crop = cfg.data.crop_size
    sampler = _RunBatchSampler(len(train_ds), cfg.data.batch_size, cfg.seed, epoch, batch_in_epoch)
    nw = cfg.data.num_workers
    loader = torch.utils.data.DataLoader(
        _SeededDataset(train_ds, build_train_transform(cfg.data.flips, cfg.data.rot90, cfg.data.jitter, crop)),
        batch_sampler=sampler, num_workers=nw, pin_memory=device.type == "cuda",
        generator=torch.Generator().manual_seed(cfg.seed), persistent_workers=False,
    )
    val_loader = None
    if read_manifest(info.root, "val"):
        val_ds = PatchDataset(data, "val", transform=build_eval_transform(crop), tasks=tasks)
        val_loader = torch.utils.data.DataLoader(
            val_ds, batch_size=cfg.data.batch_size, shuffle=False, num_workers=min(nw, 1),
            persistent_workers=nw > 0, generator=torch.Generator().manual_seed(cfg.seed))
    else:
        log.warning("no 'val' patches in %s: best.pt is chosen by the training loss", info.root / "manifest.csv")

    objective = _Objective(cfg, tasks, _class_weights(cfg, info, k) if "classes" in tasks else None)
    csv_log = _CsvLog(paths["log.csv"], append=resume)
    nb = sampler.batches_per_epoch
    total = cfg.schedule.epochs * nb if steps_cap is None else min(steps_cap, cfg.schedule.epochs * nb)
    lr = optimizer.param_groups[0]["lr"]
    metrics: dict[str, float] = {}
    window: dict[str, list[float]] = {"loss": [], **{t: [] for t in tasks}}
    since_val: list[float] = []

    def checkpoint(target: Path) -> None:
        state = {"optimizer": optimizer.state_dict(), "weighting": weighting.state_dict(), "step": step,
                 "epoch": epoch, "batch_in_epoch": batch_in_epoch, "best_score": best, "ref_losses": ref_losses,
                 "rng": _rng_state(), "config": cfg.to_dict()}
        save_checkpoint(target, model, meta, state)

    def run_validation() -> None:
        nonlocal metrics, best, ref_losses
        if val_loader is not None:
            metrics = validate(model, val_loader, objective, device, cfg.precision, k or 2)
            losses = {t: metrics[f"val_loss_{t}"] for t in tasks}
            ref_losses = ref_losses or losses
            score = _score(losses, ref_losses, objective.task_weights)
        else:
            score = float(np.mean(since_val)) if since_val else math.inf
        since_val.clear()
        metrics["score"] = score
        csv_log.write(kind="val", step=step, epoch=epoch, time_s=round(time.perf_counter() - t0, 3), lr=lr,
                      **{m: metrics.get(m) for m in LOG_COLUMNS if m in metrics})
        if score < best or not paths["best.pt"].exists():
            best = min(best, score)
            checkpoint(paths["best.pt"])
        checkpoint(paths["last.pt"])

    stopped_by = "epochs"
    done = epoch >= cfg.schedule.epochs or (steps_cap is not None and step >= steps_cap)
    if done:
        stopped_by = "max_steps" if steps_cap is not None and step >= steps_cap else "epochs"
    model.train()
    bar = tqdm(total=total, initial=min(step, total), disable=not progress, desc="train", unit="step",
               dynamic_ncols=True)
    validated_at = -1
    it = iter(loader) if not done else None
    try:
        while not done:
            batch = _to_device(next(it), device)  # type: ignore[arg-type]
            with _autocast(device, cfg.precision):
                out = model(batch["image"])
            losses = objective(out, batch)
            weighted = {t: objective.task_weights[t] * v for t, v in losses.items()}
            total_loss = weighting(weighted)
            if not torch.isfinite(total_loss):
                raise AerialMTLError(
                    f"training diverged at step {step + 1} (loss {float(total_loss)}); lower optim.lr, "
                    "use precision fp32, or check the references in the tile folder"
                )
            optimizer.zero_grad(set_to_none=True)
            total_loss.backward()
            optimizer.step()
            step += 1
            batch_in_epoch += 1
            value = float(total_loss.detach())
            window["loss"].append(value)
            since_val.append(value)
            for t, v in losses.items():
                window[t].append(float(v.detach()))
            bar.update(1)
            bar.set_postfix(loss=f"{np.mean(window['loss']):.4f}", epoch=epoch)
            if step % cfg.schedule.log_every == 0:
                csv_log.write(kind="train", step=step, epoch=epoch, time_s=round(time.perf_counter() - t0, 3),
                              lr=lr, loss=np.mean(window["loss"]),
                              **{f"loss_{t}": np.mean(window[t]) for t in tasks})
                window = {key: [] for key in window}
            if batch_in_epoch >= nb:
                epoch += 1
                batch_in_epoch = 0
                if epoch % cfg.schedule.val_every == 0:
                    run_validation()
                    validated_at = step
            if steps_cap is not None and step >= steps_cap:
                stopped_by, done = "max_steps", True
            elif epoch >= cfg.schedule.epochs:
                stopped_by, done = "epochs", True
            elif time_cap is not None and time.perf_counter() - t0 >= time_cap:
                stopped_by, done = "max_time", True
    finally:
        bar.close()
        del it
    if validated_at != step or not paths["last.pt"].exists():
        run_validation()
    return TrainResult(run_dir=run, last_checkpoint=paths["last.pt"], best_checkpoint=paths["best.pt"],
                       log_path=paths["log.csv"], config_path=paths["config.yaml"], step=step, epoch=epoch,
                       stopped_by=stopped_by, elapsed_s=time.perf_counter() - t0, metrics=metrics,
                       best_score=best, model=model)


__all__ = ["train", "TrainResult", "validate", "resolve_device", "seed_everything", "LOG_COLUMNS"]
