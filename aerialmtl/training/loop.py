"""``aerialmtl train`` as a library call: :func:`train` runs a :class:`~aerialmtl.training.trainer.Trainer`.

:func:`train` writes a run folder::

    RUN/config.yaml   the resolved config (model fields filled from dataset.yaml, absolute data dir)
    RUN/last.pt       checkpoint after every validation and when training stops (also on a time budget)
    RUN/best.pt       checkpoint with the best validation score so far (what predict should use)
    RUN/log.csv       one ``train`` row every ``schedule.log_every`` steps, one ``val`` row per validation

Validation score (lower is better): ``Σ_t w_t · L_t / L_t⁰`` over the model's tasks (see
:mod:`aerialmtl.training.objective`). Without a validation split the mean training loss since the last
validation point is used instead. Early stopping (``schedule.patience``) stops after that many validations
in a row without a better score; ``best.pt`` holds the best model.

Reproducibility and ``--resume``: the order of patches comes from a permutation seeded by ``(seed, epoch)``
and each patch's augmentation from a generator seeded by its position in the run (see
:mod:`aerialmtl.data.batches`), so neither depends on the number of DataLoader workers. ``last.pt`` stores
the optimizer, the weighting module, step/epoch/position in the epoch and every process's RNG states;
resuming continues with exactly the batches, augmentations and dropout masks an uninterrupted run would
have used. A run may be resumed with another number of processes: it continues at the same patch position
of the same epoch (the global batch is then ``batch_size × processes`` of the new run).
``max_time_s`` is a wall-clock budget for one invocation of :func:`train`.

Several processes: started by ``torchrun``, :func:`train` runs data-parallel (one process per GPU with
nccl, or per CPU process with gloo); ``data.batch_size`` is per process. See
:mod:`aerialmtl.training.distributed`.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from aerialmtl.errors import ConfigError, InputError
from aerialmtl.formats.run import LOG_COLUMNS
from aerialmtl.io.outputs import OutputFolder
from aerialmtl.runtime import COLLECTIVE_TIMEOUT, Torchrun
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.run_folder import TRAIN_FOLDER
from aerialmtl.training.setup import prepare_training
from aerialmtl.training.state import seed_everything
from aerialmtl.training.trainer import Trainer, TrainResult


def check_budget(max_steps: int | None, max_time_s: float | None) -> None:
    """Validate the step and time budgets of :func:`train` (``None`` = the config's).

    Raises:
        InputError: ``max_steps`` < 1 or ``max_time_s`` ≤ 0 (``param`` names which).
    """
    if max_steps is not None and max_steps < 1:
        raise InputError(f"‹max_steps› must be ≥ 1, got {max_steps}", param="max_steps")
    if max_time_s is not None and not max_time_s > 0:
        raise InputError(f"‹max_time_s› must be > 0 seconds, got {max_time_s}", param="max_time_s")


def train(
    cfg: TrainConfig,
    data_dir: str | Path | None = None,
    out_dir: str | Path = "runs/train",
    max_steps: int | None = None,
    max_time_s: float | None = None,
    resume: bool = False,
    progress: bool = True,
    init: str | Path | None = None,
    ctx: Torchrun | None = None,
    overwrite: bool = False,
) -> TrainResult:
    """Train a D3-Net on a tile folder and write checkpoints, a CSV log and the resolved config.

    Args:
        cfg: the training configuration.
        data_dir: tile folder (overrides ``cfg.data.dir``).
        out_dir: run folder (created). A folder holding a run's files is refused unless ``resume`` or
            ``overwrite`` (:data:`~aerialmtl.training.run_folder.TRAIN_FOLDER`). The run holds its lock
            (:class:`~aerialmtl.io.outputs.OutputFolder`) until it ends.
        max_steps: total optimisation steps (overrides ``cfg.schedule.max_steps``).
        max_time_s: wall-clock budget of this call in seconds (overrides ``cfg.schedule.max_time_s``).
        resume: continue from ``out_dir/last.pt``.
        progress: show a tqdm bar with the running loss (rank 0 only).
        init: start from the weights of this aerialmtl checkpoint (fine-tuning; see
            :mod:`aerialmtl.training.finetune`).
        ctx: process context; default: from torchrun's environment variables (one process without them),
            left again when training ends.
        overwrite: replace the run in ``out_dir`` (its :data:`~aerialmtl.formats.run.RUN_FILES` only).

    Returns:
        A :class:`TrainResult` (on every process; files are written by rank 0 only).

    Raises:
        ConfigError: no data folder, cuda unavailable, config/data mismatch.
        InputError: the data folder is not a tile folder or the train split is empty; a run-folder
            option conflict (:meth:`~aerialmtl.training.run_folder.RunFolderPolicy.check`).
        OutputExistsError: ``out_dir`` holds a run and neither ``resume`` nor ``overwrite`` is given.
        CheckpointError: ``resume`` without a usable ``last.pt`` or with a different model config; ``init``
            with other bands or another architecture.
        OutputError: the patch cache cannot be written (set ``data.cache_dir``).
        OutputInUseError: another process is writing ``out_dir``.
    """
    check_budget(max_steps, max_time_s)
    TRAIN_FOLDER.check(out_dir, resume=resume, overwrite=overwrite, init=init)
    data = data_dir if data_dir is not None else cfg.data.dir
    folder = OutputFolder(out_dir, "train", inputs={"data_dir": data, "init": init}, what="run folder")
    own_ctx = ctx is None
    if ctx is None:
        ctx = Torchrun.start(cfg.device, COLLECTIVE_TIMEOUT, ConfigError)
    try:
        with contextlib.ExitStack() as stack:
            ctx.barrier()  # every process has checked the folder before rank 0 changes it
            ctx.main_first(lambda: TRAIN_FOLDER.take(folder, stack, resume=resume, overwrite=overwrite))
            setup = prepare_training(cfg, data_dir, out_dir, resume=resume, init=init, progress=progress, ctx=ctx)
            trainer = Trainer(setup, max_steps=max_steps, max_time_s=max_time_s, progress=progress)
            try:
                return trainer.fit()
            finally:
                trainer.close()
    finally:
        if own_ctx:
            ctx.leave()


__all__ = ["LOG_COLUMNS", "TrainResult", "check_budget", "seed_everything", "train"]
