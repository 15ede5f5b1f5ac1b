"""Running validation metrics used during training (height MAE/RMSE, OA/mIoU from a confusion matrix).

These accumulate over batches with exact sums, so the result equals the metric over all validation
pixels at once. Full evaluation reports live in :mod:`aerialmtl.evaluation`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from aerialmtl.classes import IGNORE_INDEX

#: Sums a tensor over the processes of a run, in place (``aerialmtl.runtime.Torchrun.all_reduce_sum``).
Reduce = Callable[[torch.Tensor], torch.Tensor]


class HeightMeter:
    """Sums of absolute and squared height errors (metres) over valid pixels."""

    def __init__(self) -> None:
        self.abs_sum = 0.0
        self.sq_sum = 0.0
        self.count = 0

    def update(self, pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> None:
        """Add a batch: ``pred``, ``target`` float (B, 1, H, W) metres, ``valid`` bool (B, 1, H, W)."""
        err = (pred.float() - target.float())[valid]
        self.abs_sum += float(err.abs().sum())
        self.sq_sum += float((err * err).sum())
        self.count += int(err.numel())

    def sync(self, reduce: Reduce) -> None:
        """Replace the sums by their totals over every process (call on every process)."""
        total = reduce(torch.tensor([self.abs_sum, self.sq_sum, float(self.count)], dtype=torch.float64))
        self.abs_sum, self.sq_sum, self.count = float(total[0]), float(total[1]), int(total[2])

    def compute(self) -> dict[str, float]:
        """``{"height_mae", "height_rmse"}`` in metres (NaN without valid pixels)."""
        if self.count == 0:
            return {"height_mae": math.nan, "height_rmse": math.nan}
        return {"height_mae": self.abs_sum / self.count, "height_rmse": math.sqrt(self.sq_sum / self.count)}


class ConfusionMeter:
    """K × K confusion matrix (rows = reference, columns = prediction), ignoring ``IGNORE_INDEX``."""

    def __init__(self, num_classes: int) -> None:
        self.k = num_classes
        self.matrix = torch.zeros(num_classes, num_classes, dtype=torch.int64)

    def update(self, logits: torch.Tensor, target: torch.Tensor) -> None:
        """Add a batch: ``logits`` (B, K, H, W), ``target`` int64 (B, H, W) with 255 = unlabelled."""
        pred = logits.argmax(dim=1)
        keep = (target != IGNORE_INDEX) & (target >= 0) & (target < self.k)
        idx = target[keep].to(torch.int64) * self.k + pred[keep].to(torch.int64)
        self.matrix += torch.bincount(idx.cpu(), minlength=self.k * self.k).reshape(self.k, self.k)

    def sync(self, reduce: Reduce) -> None:
        """Replace the matrix by its total over every process (call on every process)."""
        self.matrix = reduce(self.matrix.clone())

    def compute(self) -> dict[str, float]:
        """``{"oa", "miou"}``: overall accuracy and mean IoU over classes present in the reference or prediction."""
        m = self.matrix.double()
        total = m.sum()
        if total == 0:
            return {"oa": math.nan, "miou": math.nan}
        tp = m.diag()
        union = m.sum(0) + m.sum(1) - tp
        present = union > 0
        return {"oa": float(tp.sum() / total), "miou": float((tp[present] / union[present]).mean())}


__all__ = ["HeightMeter", "ConfusionMeter"]
