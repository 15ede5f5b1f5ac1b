"""The resumable state of a run: counters, best score, early stopping, and every RNG.

``last.pt``'s ``train_state`` holds :meth:`TrainState.to_dict` plus the optimizer, the weighting module,
the config and the RNG states (:func:`rng_state`, one per process). Resuming restores them so the run
continues with exactly the batches, augmentations and dropout masks an uninterrupted run would have used.

``position`` counts the train patches of the current epoch already used, so a run can be resumed with
another number of processes (another global batch): it continues at the same place of the same epoch.
Checkpoints written before ``position`` existed store ``batch_in_epoch`` only; it is converted with the
batch size of the run.
"""

from __future__ import annotations

import math
import random
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, NonNegativeInt, PositiveInt, ValidationError


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (all devices)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def rng_state() -> dict[str, Any]:
    """This process's torch (CPU and CUDA), numpy and python RNG states (weights_only-loadable)."""
    np_state: Any = np.random.get_state()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {"keys": torch.from_numpy(np.asarray(np_state[1], dtype=np.int64)), "pos": int(np_state[2]),
                  "has_gauss": int(np_state[3]), "cached_gaussian": float(np_state[4])},
        "python": random.getstate(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` captured."""
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state(("MT19937", n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in state and torch.cuda.is_available():  # as many GPUs as both runs see
        for index, gpu_state in enumerate(state["cuda"][: torch.cuda.device_count()]):
            torch.cuda.set_rng_state(gpu_state, index)


def rank_seed(seed: int, rank: int) -> int:
    """Seed of process ``rank``'s own RNG stream (dropout masks) in a multi-process run."""
    return (seed * 1_000_003 + rank * 7_919) % 2**63


@dataclass
class TrainState:
    """Counters of a run.

    Attributes:
        step: optimisation steps done.
        epoch: completed epochs.
        position: train patches of the current epoch already used (over all processes).
        best_score: best validation score so far (lower is better).
        ref_losses: validation losses of the first validation (the score's reference).
        since_best: validations in a row without a better score (early stopping).
    """

    step: int = 0
    epoch: int = 0
    position: int = 0
    best_score: float = math.inf
    ref_losses: dict[str, float] | None = None
    since_best: int = 0

    def to_dict(self, global_batch: int) -> dict[str, Any]:
        """Plain values for the checkpoint (``batch_in_epoch`` kept for older readers)."""
        out = asdict(self)
        out["batch_in_epoch"] = self.position // max(1, global_batch)
        return out

    @classmethod
    def from_dict(cls, ts: dict[str, Any], global_batch: int) -> TrainState:
        """Read a checkpoint's ``train_state`` (validated by :class:`TrainStateFile`; also one written before
        ``position`` existed, whose ``batch_in_epoch`` counted batches of ``global_batch``). A non-finite
        ``best_score`` (older versions let a diverged NaN validation become the best) reads as ``inf``: the next
        finite score is better.

        Raises:
            ValueError: not of the form ``aerialmtl train`` writes (a :class:`pydantic.ValidationError`).
        """
        rec = TrainStateFile.model_validate(ts)
        position = rec.position if rec.position is not None else rec.batch_in_epoch * global_batch
        best = rec.best_score if math.isfinite(rec.best_score) else math.inf
        return cls(step=rec.step, epoch=rec.epoch, position=position, best_score=best, ref_losses=rec.ref_losses,
                   since_best=rec.since_best)


class TrainStateFile(BaseModel):
    """The schema of a checkpoint's ``train_state`` counters (the rest: optimizer, weighting and RNG states, are
    checked by loading them): a count is an integer ≥ 0 (not "abc", not -1); any other shape is refused as not
    written by ``aerialmtl train``.
    """

    model_config = ConfigDict(extra="allow", arbitrary_types_allowed=True)
    step: NonNegativeInt
    epoch: NonNegativeInt
    position: NonNegativeInt | None = None
    batch_in_epoch: NonNegativeInt = 0
    best_score: float
    ref_losses: dict[str, float] | None = None
    since_best: NonNegativeInt = 0
    global_batch: NonNegativeInt | None = None
    world_size: PositiveInt = 1
    rng_ranks: list[Any] | None = None


def read_train_state(ts: Any) -> TrainStateFile:
    """``ts`` validated as a checkpoint's ``train_state`` (:class:`TrainStateFile`).

    Raises:
        ValueError: not a mapping of that form; the message names the first bad key, its value and what it must be.
    """
    try:
        return TrainStateFile.model_validate(ts)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err.get("loc", ())) or "train_state"
        raise ValueError(f"train_state.{where}: {err.get('msg', 'invalid')}, got {err.get('input')!r}") from None


__all__ = ["TrainState", "TrainStateFile", "rank_seed", "read_train_state", "rng_state", "seed_everything",
           "set_rng_state"]
