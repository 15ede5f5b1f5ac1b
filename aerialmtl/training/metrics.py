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
    """Sums of absolute and squared height errors (metres) over valid pixels, kept on the model's device.

    Nothing is read back to the host until :meth:`sync`/:meth:`compute`: a validation pass on a GPU queues its
    batches without waiting on each one. The sums are float64, of the float32 errors and their float32 squares.

    Args:
        device: where the batches are (the sums live there).
    """

    def __init__(self, device: torch.device | str = "cpu") -> None:
        #: (3,) float64: Σ|e|, Σe², the count of valid pixels
        self.sums = torch.zeros(3, dtype=torch.float64, device=device)

    def update(self, pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> None:
        """Add a batch: ``pred``, ``target`` float (B, 1, H, W) metres, ``valid`` bool (B, 1, H, W)."""
        err = torch.where(valid, pred.float() - target.float(), 0.0)  # no boolean indexing: no wait on the device
        self.sums[0] += err.abs().sum(dtype=torch.float64)
        self.sums[1] += (err * err).sum(dtype=torch.float64)
        self.sums[2] += valid.sum(dtype=torch.float64)

    def sync(self, reduce: Reduce) -> None:
        """Replace the sums by their totals over every process (call on every process)."""
        self.sums = reduce(self.sums)

    def compute(self) -> dict[str, float]:
        """``{"height_mae", "height_rmse"}`` in metres (NaN without valid pixels)."""
        abs_sum, sq_sum, count = self.sums.tolist()
        if count == 0:
            return {"height_mae": math.nan, "height_rmse": math.nan}
        return {"height_mae": abs_sum / count, "height_rmse": math.sqrt(sq_sum / count)}


class ConfusionMeter:
    """K × K confusion matrix (rows = reference, columns = prediction), ignoring ``IGNORE_INDEX``, kept on the
    model's device (counted there, read back by :meth:`compute`).

    Args:
        num_classes: K.
        device: where the batches are.
    """

    def __init__(self, num_classes: int, device: torch.device | str = "cpu") -> None:
        self.k = num_classes
        self.matrix = torch.zeros(num_classes, num_classes, dtype=torch.int64, device=device)

    def update(self, logits: torch.Tensor, target: torch.Tensor) -> None:
        """Add a batch: ``logits`` (B, K, H, W), ``target`` int64 (B, H, W) with 255 = unlabelled."""
        k = self.k
        pred = logits.argmax(dim=1)
        keep = (target != IGNORE_INDEX) & (target >= 0) & (target < k)
        # pixels not kept go to one extra bin, dropped after counting (no boolean indexing: no wait on the device)
        idx = torch.where(keep, target.to(torch.int64) * k + pred.to(torch.int64), k * k)
        self.matrix += torch.bincount(idx.flatten(), minlength=k * k + 1)[: k * k].reshape(k, k)

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
