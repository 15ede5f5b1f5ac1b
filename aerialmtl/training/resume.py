"""Resuming a training command's run from its ``last.pt``: one way for ``train`` and ``pretrain``.

:func:`load_parts` puts a checkpoint's weights (the trained ones, with ``optim.ema`` the average beside them),
optimiser state and task weighting back into the model's parts; both commands resume through it and through
:func:`checked_rng` (the saved RNG state, tried before it is trusted), so a checkpoint either command wrote
(:meth:`~aerialmtl.training.steploop.StepLoop.save`) is read back the same way and refused with the same
messages. :func:`restore` adds ``train``'s own part: the tile folder and model config must be the run's, and
the counters (:class:`~aerialmtl.training.state.TrainState`) with each process's RNG stream
(:func:`seed_rank_stream`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import torch
from torch import nn

from aerialmtl import runtime
from aerialmtl.config import to_dict
from aerialmtl.errors import CheckpointError, cause
from aerialmtl.formats.checkpoint import ModelMeta, check_same_data, first_nonfinite, load_checkpoint
from aerialmtl.formats.run import RAW_WEIGHTS_KEY
from aerialmtl.formats.tiles import TileFolderInfo, read_manifest
from aerialmtl.models.config import ModelConfig
from aerialmtl.training.config import OptimSection, TrainConfig
from aerialmtl.training.state import (
    TrainState,
    rank_seed,
    read_train_state,
    rng_state,
    seed_everything,
    set_rng_state,
)


class ModelParts(Protocol):
    """What a checkpoint is loaded into (:class:`aerialmtl.training.setup.ModelParts`)."""

    @property
    def model(self) -> nn.Module: ...  # noqa: D102
    @property
    def weighting(self) -> nn.Module: ...  # noqa: D102
    @property
    def optimizer(self) -> torch.optim.Optimizer: ...  # noqa: D102


class TrainData(Protocol):
    """What ``train``'s resume checks a checkpoint against (:class:`aerialmtl.training.setup.TrainData`)."""

    @property
    def info(self) -> TileFolderInfo: ...  # noqa: D102
    @property
    def model_cfg(self) -> ModelConfig: ...  # noqa: D102
    @property
    def meta(self) -> ModelMeta: ...  # noqa: D102


@dataclass(frozen=True)
class Resumed:
    """Where a resumed run continues: its counters, RNG state and weight average.

    The RNG state is this process's saved one (``{}``: none). The weight average is, for a run with
    ``optim.ema``, the one the checkpoint holds (``None``: none; the model then holds the raw weights saved
    beside it).
    """

    state: TrainState
    rng: dict[str, Any]
    averaged: dict[str, torch.Tensor] | None = None


#: What to do with a checkpoint a command cannot resume, by command.
_FIX = {"train": "resume from an unedited last.pt, or start a new run (another --out, or --overwrite) with ‹init› "
                 "to reuse its weights",
        "pretrain": "resume from an unedited last.pt, or start again with ‹overwrite=True›"}


def _bad_state(path: Path, what: str, exc: BaseException | None, command: str = "train") -> CheckpointError:
    why = f" ({cause(exc)})" if exc is not None else ""
    return CheckpointError(
        f"checkpoint '{path}' cannot be resumed: {what}{why}; it was not written by `aerialmtl {command}` as it is "
        f"(edited or from another version): {_FIX[command]}"
    )


def checked_rng(path: Path, rng: Any, command: str = "train") -> dict[str, Any]:
    """``rng`` if it restores (tried on a copy of the current states), else a CheckpointError."""
    if not rng:
        raise _bad_state(path, "its RNG state is missing", None, command)
    current = rng_state()
    try:
        set_rng_state(rng)
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as exc:
        raise _bad_state(path, "its RNG state is invalid", exc, command) from exc
    finally:
        set_rng_state(current)
    return dict(rng)


def _load_optimizer(path: Path, optimizer: torch.optim.Optimizer, ts: dict[str, Any], optim: OptimSection,
                    command: str) -> None:
    """The optimiser state of ``ts``, with the config's ``lr`` and ``betas`` (its moments are kept)."""
    bad = first_nonfinite(ts.get("optimizer"))
    if bad is not None:
        raise CheckpointError(
            f"checkpoint '{path}': its optimizer state holds NaN or inf ('{bad}'); it cannot be resumed: start a "
            "new run (another --out, or --overwrite), with a lower optim.lr"
        )
    try:
        optimizer.load_state_dict(ts["optimizer"])
    except ValueError as exc:
        raise CheckpointError(
            f"checkpoint '{path}': its optimizer state does not fit this optimizer ({exc}); resume with the "
            "run's config.yaml (same optim section) or start a new run"
        ) from exc
    except (KeyError, TypeError, RuntimeError, IndexError) as exc:
        raise _bad_state(path, "its optimizer state is incomplete", exc, command) from exc
    for group in optimizer.param_groups:  # weight decay: the group structure already follows the config
        group.update(lr=optim.lr, betas=optim.betas)


def load_parts(path: Path, payload: dict[str, Any], parts: ModelParts, optim: OptimSection,
               command: str = "train") -> dict[str, torch.Tensor] | None:
    """Load a checkpoint's weights, optimiser and task weighting into ``parts``; returns its weight average.

    ``payload`` is checkpoint ``path`` as read (its ``train_state`` a mapping). With ``optim.ema`` the
    checkpoint's weights are the average and the trained ones ride beside them (``RAW_WEIGHTS_KEY``): the model
    gets the trained ones and the average is returned (``None`` without one). The config's ``optim.lr`` and
    ``optim.betas`` replace those stored with the optimiser state (its moments are kept).

    Raises:
        CheckpointError: weights that do not fit, an optimiser state that is not finite or does not fit, a
            missing task weighting; names the file, ``command`` and the fix.
    """
    ts = payload["train_state"]
    raw = ts.get(RAW_WEIGHTS_KEY)  # optim.ema: the checkpoint's weights are the average, these the trained ones
    try:
        parts.model.load_state_dict(payload["state_dict"])
        if raw is not None:
            parts.model.load_state_dict(raw)
    except (RuntimeError, KeyError, TypeError, AttributeError) as exc:
        raise _bad_state(path, "its weights do not fit the model", exc, command) from exc
    _load_optimizer(path, parts.optimizer, ts, optim, command)
    try:
        parts.weighting.load_state_dict(ts["weighting"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise _bad_state(path, "its counters or task weighting are incomplete", exc, command) from exc
    return payload["state_dict"] if raw is not None else None


def restore(path: Path, parts: ModelParts, data: TrainData, cfg: TrainConfig, ctx: runtime.Torchrun,
            device: torch.device) -> Resumed:
    """Load weights, optimiser, weighting and counters from ``path`` into ``parts``.

    The config's ``optim.lr`` and ``optim.betas`` replace those stored with the optimizer
    state (its moments are kept), so a run that diverged can continue from its last good ``last.pt``
    with a lower ``optim.lr`` written into the run's ``config.yaml``.

    Raises:
        CheckpointError: no training state, other data, another model config, or a training state that
            does not have the form ``aerialmtl train`` writes (e.g. edited by hand); names the file.
    """
    payload, old_meta = load_checkpoint(path, map_location=device)
    ts = payload.get("train_state")
    if not ts:
        raise CheckpointError(f"checkpoint '{path}' has no training state; cannot ‹resume› from it")
    check_same_data(path, old_meta, data.meta)
    if to_dict(old_meta.model) != to_dict(data.model_cfg):
        raise CheckpointError(
            f"checkpoint '{path}' was trained with another model config; "
            "resume with the run's config.yaml or start a new run (--overwrite)"
        )
    if not isinstance(ts, dict):
        raise _bad_state(path, "its training state is not a mapping", None)
    try:
        counters = read_train_state(ts)
    except ValueError as exc:
        raise _bad_state(path, "its counters are not of the form aerialmtl writes", exc) from exc
    averaged = load_parts(path, payload, parts, cfg.optim)
    try:
        old_global = counters.global_batch or 0
        # a checkpoint written before the global batch was recorded: one process, this batch size
        state = TrainState.from_dict(ts, old_global or min(cfg.data.batch_size,
                                                            len(read_manifest(data.info.root, "train"))))
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise _bad_state(path, "its counters or task weighting are incomplete", exc) from exc
    ranks = ts.get("rng_ranks")
    if ranks and counters.world_size == ctx.world:
        rng = ranks[ctx.rank]
    elif ctx.rank == 0:
        rng = ts.get("rng")
    else:
        return Resumed(state, {}, averaged)
    return Resumed(state, checked_rng(path, rng), averaged)


def seed_rank_stream(cfg: TrainConfig, ctx: runtime.Torchrun, step: int, saved: dict[str, Any] | None) -> None:
    """Give this process its RNG stream.

    The saved one when resuming; else rank 0 keeps the seeded stream (a single process is unchanged) and rank
    r > 0 gets its own (other dropout masks).
    """
    if saved:
        set_rng_state(saved)
    elif ctx.rank > 0:
        seed_everything(rank_seed(cfg.seed + step, ctx.rank))


__all__ = ["Resumed", "checked_rng", "load_parts", "restore", "seed_rank_stream"]
