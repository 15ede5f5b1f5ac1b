"""What training minimises and how validation is scored.

* :class:`Objective` — the per-task losses of a batch (``loss.height`` from
  :data:`~aerialmtl.training.losses.HEIGHT_LOSSES`, ``loss.classes`` from
  :data:`~aerialmtl.training.losses.CLASS_LOSSES`), masked to valid pixels, times the fixed task weights;
* :func:`class_weights` — ``loss.class_weights`` resolved against the tile folder;
* :func:`validation_score` — the number ``best.pt`` and early stopping are chosen by.

With ``model.shadow_head`` the batch also holds the shadow labels (:mod:`aerialmtl.data.shadow_labels`) and the
objective adds ``shadow``, the head's binary cross-entropy, to the losses of a training batch; it enters the total
as ``loss.shadow_weight`` × that loss beside the task weighting (:meth:`Objective.total`), and validation scores
the tasks alone (so ``best.pt`` is chosen by the same measure with and without the head).

Validation score (lower is better): ``Σ_t w_t · L_t / L_t⁰`` over the model's tasks, where ``L_t`` is the
validation loss of task t, ``L_t⁰`` its value at the first validation of the run and ``w_t`` the task
weight (``weighting.task_weights``, default 1). Normalising by the first value puts height (metres) and
classes (nats) on the same footing, so neither task dominates the choice of ``best.pt``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from aerialmtl.classes import IGNORE_INDEX
from aerialmtl.data.dataset import class_pixel_counts
from aerialmtl.data.shadow_labels import SHADOW_IGNORE
from aerialmtl.errors import ConfigError, InputError
from aerialmtl.formats.tiles import MANIFEST_CSV, TileFolderInfo
from aerialmtl.models.config import HEIGHT_BINS, HEIGHT_LAPLACE, HEIGHT_SCALE, SHADOW
from aerialmtl.models.height_bins import bin_edges
from aerialmtl.training import losses
from aerialmtl.training.config import TrainConfig


def class_weights(cfg: TrainConfig, info: TileFolderInfo, k: int) -> torch.Tensor | None:
    """The K class weights of ``loss.class_weights`` (``None`` for ``none``).

    Raises:
        InputError: ``balanced`` without ``class_hist`` in the manifest.
        ConfigError: an explicit list of the wrong length.
    """
    spec = cfg.loss.class_weights
    if spec == "none":
        return None
    if spec == "balanced":
        counts = class_pixel_counts(info.root, "train", k).astype(np.float64)
        present = counts > 0
        if not present.any():
            raise InputError(f"loss.class_weights: 'balanced' needs class_hist in '{info.root / MANIFEST_CSV}'")
        w = np.ones(k)
        w[present] = counts[present].sum() / (present.sum() * counts[present])
        w[present] /= w[present].mean()
        return torch.tensor(w, dtype=torch.float32)
    if len(spec) != k:
        raise ConfigError(f"loss.class_weights: got {len(spec)} weights but the class scheme has {k} classes")
    return torch.tensor(spec, dtype=torch.float32)


class Objective:
    """Per-task losses of a batch (float32 scalars), masked to valid pixels.

    Args:
        cfg: the training config (``loss`` and ``weighting.task_weights``).
        tasks: the model's tasks.
        class_weights: optional K class weights for the classes loss.
    """

    def __init__(self, cfg: TrainConfig, tasks: tuple[str, ...], class_weights: torch.Tensor | None) -> None:
        self.tasks = tasks
        self.height_fn = losses.HEIGHT_LOSSES[cfg.loss.height]
        self.classes_fn = losses.CLASS_LOSSES[cfg.loss.classes]
        self.class_weights = class_weights
        self.task_weights = {t: float(cfg.weighting.task_weights.get(t, 1.0)) for t in tasks}
        self.nll_beta = float(cfg.loss.nll_beta)
        self.bins_weight = float(cfg.loss.bins_weight)
        self.height_balance = float(cfg.loss.height_balance)
        #: the shadow head's loss weight (``loss.shadow_weight``)
        self.shadow_weight = float(cfg.loss.shadow_weight)
        bins = cfg.model.height_bins
        self.bin_edges = bin_edges(bins, float(cfg.model.height_bin_max)) if bins else None

    def __call__(self, out: dict[str, torch.Tensor], batch: dict[str, Any], scoring: bool = False) -> dict[
            str, torch.Tensor]:
        """``{task: loss}`` for the model outputs ``out`` and the batch's references.

        With an aleatoric height head (``out`` holds ``height_scale``) the height loss is the Laplace NLL
        (:func:`~aerialmtl.training.losses.laplace_nll`); with ``scoring`` (validation, which picks
        ``best.pt``) it is ``loss.height`` of the mean alone, so every model is chosen by the same measure.
        With a height-bin head it is the Laplace NLL of the height and its training scale plus
        ``loss.bins_weight`` × the cross-entropy of the reference height's bin, where the model returns them
        (training mode); else (validation) ``loss.height`` of the height alone.
        """
        result: dict[str, torch.Tensor] = {}
        if "height" in self.tasks:
            w = (losses.height_balance_weights(batch["height"], batch["height_valid"], self.height_balance)
                 if self.height_balance and not scoring else None)
            if HEIGHT_BINS in out and not scoring:  # a height-bin head in training mode
                assert self.bin_edges is not None
                nll = losses.laplace_nll(out["height"].float(), out[HEIGHT_LAPLACE].float(), batch["height"],
                                         batch["height_valid"], beta=self.nll_beta, weight=w)
                result["height"] = nll + self.bins_weight * losses.height_bins_ce(
                    out[HEIGHT_BINS], batch["height"], batch["height_valid"], self.bin_edges, weight=w)
            elif HEIGHT_SCALE in out and self.bin_edges is None and not scoring:  # (a bin head's is no Laplace b)
                result["height"] = losses.laplace_nll(out["height"].float(), out[HEIGHT_SCALE].float(),
                                                      batch["height"], batch["height_valid"], beta=self.nll_beta,
                                                      weight=w)
            elif w is not None:  # loss.height is l1 (the config checks it)
                result["height"] = losses.l1(out["height"].float(), batch["height"], batch["height_valid"], weight=w)
            else:
                result["height"] = self.height_fn(out["height"].float(), batch["height"], batch["height_valid"])
        if "classes" in self.tasks:
            w = None if self.class_weights is None else self.class_weights.to(out["classes"].device)
            result["classes"] = self.classes_fn(out["classes"].float(), batch["classes"], weight=w,
                                                ignore_index=IGNORE_INDEX)
        if SHADOW in out and SHADOW in batch and not scoring:
            result[SHADOW] = losses.shadow_bce(out[SHADOW], batch[SHADOW], SHADOW_IGNORE)
        return result

    def weighted(self, task_losses: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Each task loss times its fixed task weight (the input of the weighting module); the tasks only."""
        return {t: self.task_weights[t] * v for t, v in task_losses.items() if t in self.task_weights}

    def total(self, weighted_sum: torch.Tensor, task_losses: dict[str, torch.Tensor]) -> torch.Tensor:
        """The training objective: the weighting module's sum of the tasks plus ``loss.shadow_weight`` × the
        shadow head's loss, where the batch has one.
        """
        if SHADOW in task_losses:
            return weighted_sum + self.shadow_weight * task_losses[SHADOW]
        return weighted_sum


def validation_score(task_losses: dict[str, float], reference: dict[str, float], weights: dict[str, float]) -> float:
    """``Σ_t w_t · L_t / L_t⁰`` (lower is better); see the module docstring."""
    return float(sum(weights[t] * v / max(reference[t], 1e-12) for t, v in task_losses.items()))


__all__ = ["Objective", "class_weights", "validation_score"]
