"""Masked task losses: height regression (metres) and land-cover cross-entropy.

Every function takes a validity mask; invalid pixels change neither the value nor the gradient (their
targets may hold anything, even NaN or the -9999 nodata), and a batch without a single valid pixel
gives a loss of exactly 0 that still has a ``grad_fn`` (never NaN), so the training loop needs no
special case.

Shapes: ``pred``, ``target`` B×1×H×W float (metres); ``mask`` B×1×H×W bool (True = valid);
``logits`` B×K×H×W; class ``target`` B×H×W int64 with ``ignore_index`` where unlabelled.
Regression losses average over the valid pixels of the whole batch (scale-invariant ones per image,
then over images that have valid pixels).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from aerialmtl.errors import ConfigError
from aerialmtl.models.calibration import SPREAD_EDGES
from aerialmtl.models.height_bins import bin_index

IGNORE_INDEX = 255


def _check(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if pred.shape != target.shape:
        raise ValueError(f"height loss: pred {tuple(pred.shape)} and target {tuple(target.shape)} differ; "
                         "both must be B×1×H×W")
    if mask is None:
        return torch.isfinite(target)
    if mask.shape != pred.shape:
        raise ValueError(f"height loss: mask {tuple(mask.shape)} must have the prediction's shape {tuple(pred.shape)}")
    return mask.bool() & torch.isfinite(target)


def _masked_error(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Pred − target at valid pixels, exactly 0 (with zero gradient) elsewhere; float32."""
    t = torch.where(mask, target.float(), torch.zeros((), device=target.device))
    return torch.where(mask, pred.float() - t, torch.zeros((), device=pred.device))


def _masked_mean(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``values`` over ``mask`` (values are already 0 outside); 0 with grad when nothing is valid."""
    return values.sum() / mask.sum().clamp_min(1)


def l1(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
       weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute error (metres) over valid pixels (the paper's height loss); ``weight`` (B×1×H×W, mean 1
    over the valid pixels, e.g. :func:`height_balance_weights`) multiplies each pixel's error.
    """
    mask = _check(pred, target, mask)
    err = _masked_error(pred, target, mask).abs()
    return _masked_mean(err if weight is None else err * weight, mask)


def l2(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared error (m²) over valid pixels."""
    mask = _check(pred, target, mask)
    return _masked_mean(_masked_error(pred, target, mask) ** 2, mask)


def huber(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
          delta: float = 1.0) -> torch.Tensor:
    """Huber loss: ½e² for |e| ≤ δ, δ(|e| − ½δ) beyond (δ in metres), mean over valid pixels."""
    mask = _check(pred, target, mask)
    a = _masked_error(pred, target, mask).abs()
    per = torch.where(a <= delta, 0.5 * a**2, delta * (a - 0.5 * delta))
    return _masked_mean(per, mask)


def berhu(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
          ratio: float = 0.2) -> torch.Tensor:
    """Reverse Huber (Laina et al. 2016): |e| for |e| ≤ c, (e² + c²)/(2c) beyond.

    c = ``ratio`` · max |e| over the valid pixels of the batch (not back-propagated).
    """
    mask = _check(pred, target, mask)
    a = _masked_error(pred, target, mask).abs()
    c = (ratio * a.detach().max()).clamp_min(1e-6)
    per = torch.where(a <= c, a, (a**2 + c**2) / (2 * c))
    return _masked_mean(torch.where(mask, per, torch.zeros((), device=per.device)), mask)


def _log_heights(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, shift: float) -> torch.Tensor:
    """log(pred + shift) − log(max(target, 0) + shift) at valid pixels, 0 elsewhere (float32).

    nDSM heights are 0 on the ground (and slightly negative from noise), so heights are shifted by
    ``shift`` metres before the log (default 1 m: relative error for tall objects, ≈ absolute error near
    the ground). Targets are clamped at 0; predictions are clamped at 1 % of ``shift`` above −shift so
    the log stays finite (predictions below −0.99·shift get no gradient from this term).
    """
    valid_p = torch.where(mask, pred.float(), torch.zeros((), device=pred.device))
    valid_t = torch.where(mask, target.float(), torch.zeros((), device=target.device))
    lp = torch.log((valid_p + shift).clamp_min(0.01 * shift))
    lt = torch.log(valid_t.clamp_min(0) + shift)
    return torch.where(mask, lp - lt, torch.zeros((), device=pred.device))


def scale_invariant(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
                    lam: float = 0.5, shift: float = 1.0) -> torch.Tensor:
    """Scale-invariant log error (Eigen et al. 2014), per image, averaged over images with valid pixels.

    With d = log(pred + shift) − log(target + shift) over the n valid pixels of an image:
    L = (1/n) Σ d² − (λ/n²) (Σ d)². See :func:`_log_heights` for the ``shift`` (metres).
    """
    mask = _check(pred, target, mask)
    d = _log_heights(pred, target, mask, shift)
    return _per_image_si(d, mask, lam)


def _per_image_si(d: torch.Tensor, mask: torch.Tensor, lam: float) -> torch.Tensor:
    n = mask.flatten(1).sum(1).float()
    n_safe = n.clamp_min(1)
    s1 = d.flatten(1).sum(1)
    s2 = (d**2).flatten(1).sum(1)
    per = s2 / n_safe - lam * (s1 / n_safe) ** 2
    has = (n > 0).float()
    return (per * has).sum() / has.sum().clamp_min(1)


def _gradient_matching(d: torch.Tensor, mask: torch.Tensor, scales: int) -> torch.Tensor:
    """Σ_scales mean over valid neighbour pairs of |∂x d| + |∂y d| (Li & Snavely 2018), d subsampled by 2^k."""
    total = d.new_zeros(())
    for k in range(scales):
        step = 2**k
        ds, ms = d[..., ::step, ::step], mask[..., ::step, ::step]
        if ds.shape[-1] < 2 or ds.shape[-2] < 2:
            break
        mx = ms[..., :, 1:] & ms[..., :, :-1]
        my = ms[..., 1:, :] & ms[..., :-1, :]
        gx = torch.where(mx, (ds[..., :, 1:] - ds[..., :, :-1]).abs(), torch.zeros((), device=d.device))
        gy = torch.where(my, (ds[..., 1:, :] - ds[..., :-1, :]).abs(), torch.zeros((), device=d.device))
        total = total + (gx.sum() + gy.sum()) / (mx.sum() + my.sum()).clamp_min(1)
    return total


def scale_invariant_gradient(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
                             lam: float = 0.5, shift: float = 1.0, alpha: float = 0.5,
                             scales: int = 4) -> torch.Tensor:
    """Scale-invariant log loss + ``alpha`` · multi-scale gradient matching of the log-height error.

    The gradient term (Li & Snavely 2018, used in Carvalho's thesis ch. 2) is, at each of ``scales``
    scales (d subsampled by 1, 2, 4, 8), the mean of |d(x+1) − d(x)| + |d(y+1) − d(y)| over neighbour pairs
    where both pixels are valid; it penalises blurred or misplaced height edges.
    """
    mask = _check(pred, target, mask)
    d = _log_heights(pred, target, mask, shift)
    return _per_image_si(d, mask, lam) + alpha * _gradient_matching(d, mask, scales)


#: Upper edges (metres) of the reference-height bins that ``loss.height_balance`` counts pixels in (the last bin
#: is open): the height ranges of the spread calibration, which are the bins the evaluation reports.
BALANCE_EDGES = SPREAD_EDGES


def height_balance_weights(target: torch.Tensor, mask: torch.Tensor, power: float) -> torch.Tensor:
    """Per-pixel weights that balance the reference heights of one batch (``loss.height_balance``).

    Each valid pixel of ``target`` (B×1×H×W, metres) gets ``n_k^−power`` where ``n_k`` is the batch's number of
    valid pixels in its height bin (:data:`BALANCE_EDGES`), scaled so the weights' mean over the valid pixels is
    1 (the loss keeps its scale); 0 at invalid pixels. ``power`` 0.5 is the inverse square root of the bin's
    frequency (Yang et al., ICML 2021, "Delving into deep imbalanced regression"): a 20 m roof among 90 %
    ground pulls the heights harder than in the plain mean, where it is outvoted. No gradient flows through
    the weights.
    """
    valid = mask.bool() & torch.isfinite(target)
    t = torch.where(valid, target.float(), torch.zeros((), device=target.device))
    edges = torch.tensor(BALANCE_EDGES, dtype=torch.float32, device=target.device)
    idx = torch.bucketize(t, edges, right=True)
    counts = torch.bincount(idx[valid], minlength=len(BALANCE_EDGES) + 1).float()
    per_bin = torch.where(counts > 0, counts.clamp_min(1.0) ** (-float(power)), torch.zeros_like(counts))
    w = torch.where(valid, per_bin[idx], torch.zeros((), device=target.device))
    n = valid.sum()
    return (w * (n.clamp_min(1) / w.sum().clamp_min(1e-12))).detach()


def laplace_nll(pred: torch.Tensor, scale: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None,
                beta: float = 0.0, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Laplace negative log-likelihood of the heights, mean over valid pixels (nats, up to log 2).

    Per pixel ``|y − μ| / b + log b`` with μ = ``pred`` and b = ``scale`` (metres, > 0; both B×1×H×W). For a
    fixed b its minimum over μ is the paper's L1 (the median); its minimum over b is ``b = |y − μ|``, so b
    learns the expected absolute error of each pixel (the aleatoric uncertainty, Kendall & Gal 2017).

    ``beta`` (β-NLL, Seitzer et al., ICLR 2022) weights each pixel's term by ``b^β`` (not back-propagated):
    with β = 0 the plain NLL, whose gradient on μ is ``sign(μ − y) / b`` — hard pixels, given a large b, pull
    the heights less; with β = 1 the gradient on μ is L1's exactly, and b still learns ``|y − μ|``.

    ``weight`` (B×1×H×W, mean 1 over the valid pixels, e.g. :func:`height_balance_weights`) multiplies each
    pixel's term.
    """
    mask = _check(pred, target, mask)
    if scale.shape != pred.shape:
        raise ValueError(f"laplace_nll: scale {tuple(scale.shape)} must have the shape of pred, {tuple(pred.shape)}")
    if not 0.0 <= beta <= 1.0:
        raise ValueError(f"laplace_nll: beta must be in [0, 1], got {beta}")
    err = _masked_error(pred, target, mask).abs()
    b = torch.where(mask, scale.float(), torch.ones((), device=scale.device))
    per = err / b + torch.log(b)
    if beta > 0:
        per = per * b.detach() ** beta
    if weight is not None:
        per = per * weight
    return _masked_mean(torch.where(mask, per, torch.zeros((), device=per.device)), mask)


def height_bins_ce(logits: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None,
                   edges: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Cross-entropy (nats, mean over valid pixels) of B×K×H×W height-bin logits against the bin of the
    B×1×H×W reference height (metres); see :mod:`aerialmtl.models.height_bins`. 0 (with a gradient) when no
    pixel is valid. ``weight`` (B×1×H×W, mean 1 over the valid pixels) multiplies each pixel's term.
    """
    valid = _check(logits[:, :1], target, mask)
    idx = bin_index(torch.where(valid, target.float(), torch.zeros((), device=target.device))[:, 0], edges)
    ce = F.cross_entropy(logits.float(), idx, reduction="none")
    if weight is not None:
        ce = ce * weight[:, 0]
    return _masked_mean(torch.where(valid[:, 0], ce, torch.zeros((), device=ce.device)), valid)


def cross_entropy(logits: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None,
                  ignore_index: int = IGNORE_INDEX, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Class-weighted cross-entropy (nats) over labelled pixels.

    Args:
        logits: B×K×H×W.
        target: B×H×W int64 class indices, ``ignore_index`` where unlabelled.
        weight: optional K class weights; the mean is weighted like ``torch.nn.functional.cross_entropy``
            (divided by the sum of the weights of the counted pixels).
        ignore_index: label of unlabelled pixels.
        mask: optional B×1×H×W or B×H×W bool; False pixels are ignored as well.

    Returns:
        Scalar; 0 (with grad) when no pixel is labelled.
    """
    if logits.dim() != 4 or target.shape != (logits.shape[0], *logits.shape[2:]):
        raise ValueError(f"cross_entropy: expected logits B×K×H×W and target B×H×W, got {tuple(logits.shape)} "
                         f"and {tuple(target.shape)}")
    target = target.long()
    if mask is not None:
        m = mask.reshape(target.shape).bool()
        target = torch.where(m, target, torch.full_like(target, ignore_index))
    valid = target != ignore_index
    w = None if weight is None else weight.to(device=logits.device, dtype=torch.float32)
    total = F.cross_entropy(logits.float(), target, weight=w, ignore_index=ignore_index, reduction="sum")
    if w is None:
        denom = valid.sum().float()
    else:
        denom = w[torch.where(valid, target, torch.zeros_like(target))][valid].sum()
    # No labelled pixel: total is 0 (with grad), divide by 1.
    return total / torch.where(denom > 0, denom, torch.ones_like(denom))


def shadow_bce(logits: torch.Tensor, target: torch.Tensor, ignore: int = IGNORE_INDEX) -> torch.Tensor:
    """Binary cross-entropy (nats, mean over labelled pixels) of the shadow head's B×1×H×W logits against
    B×H×W uint8 labels (1 cast shadow, 0 lit, ``ignore`` unknown: :mod:`aerialmtl.data.shadow_labels`).

    Returns:
        Scalar float32; 0 (with a gradient) when no pixel is labelled.
    """
    if logits.dim() != 4 or logits.shape[1] != 1 or target.shape != (logits.shape[0], *logits.shape[2:]):
        raise ValueError(f"shadow_bce: expected logits B×1×H×W and labels B×H×W, got {tuple(logits.shape)} and "
                         f"{tuple(target.shape)}")
    z = logits[:, 0].float()
    valid = target != ignore
    y = torch.where(valid, target, torch.zeros((), dtype=target.dtype, device=target.device)).float()
    per = F.binary_cross_entropy_with_logits(z, y, reduction="none")
    return _masked_mean(torch.where(valid, per, torch.zeros((), device=per.device)), valid)


#: Height losses by ``loss.height`` name: ``fn(pred, target, mask) -> scalar``. To add one, add it here and
#: to ``HeightLoss`` in :mod:`aerialmtl.training.config` (a test keeps the two in step).
HEIGHT_LOSSES: dict[str, Callable[..., torch.Tensor]] = {
    "l1": l1,
    "l2": l2,
    "huber": huber,
    "berhu": berhu,
    "scale_invariant": scale_invariant,
    "scale_invariant_gradient": scale_invariant_gradient,
}


#: Classification losses by ``loss.classes`` name: ``fn(logits, target, weight=, ignore_index=) -> scalar``.
CLASS_LOSSES: dict[str, Callable[..., torch.Tensor]] = {
    "ce": cross_entropy,
}


class HeightLoss(nn.Module):
    """Module wrapper: ``HeightLoss("l1")(pred, target, mask)``; extra kwargs go to the function."""

    def __init__(self, name: str = "l1", **kwargs: Any) -> None:
        super().__init__()
        if name not in HEIGHT_LOSSES:
            raise ConfigError(f"height loss: got {name!r}; valid choices are {', '.join(HEIGHT_LOSSES)}")
        self.name = name
        self.fn = HEIGHT_LOSSES[name]
        self.kwargs = kwargs

    def forward(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """The masked regression loss of ``pred`` against ``target`` (both N × 1 × H × W, metres)."""
        return self.fn(pred, target, mask, **self.kwargs)


class CrossEntropyLoss(nn.Module):
    """Module wrapper of :func:`cross_entropy`; class weights are a buffer (move with ``.to``)."""

    weight: torch.Tensor | None

    def __init__(self, weight: torch.Tensor | None = None, ignore_index: int = IGNORE_INDEX) -> None:
        super().__init__()
        self.register_buffer("weight", None if weight is None else torch.as_tensor(weight, dtype=torch.float32))
        self.ignore_index = ignore_index

    def forward(self, logits: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """The masked cross-entropy of ``logits`` (N × K × H × W) against ``target`` class indices (N × H × W)."""
        return cross_entropy(logits, target, self.weight, self.ignore_index, mask)


__all__ = ["laplace_nll", "height_bins_ce", "shadow_bce",
           "l1", "l2", "huber", "berhu", "scale_invariant", "scale_invariant_gradient", "cross_entropy",
           "HEIGHT_LOSSES", "CLASS_LOSSES", "BALANCE_EDGES", "height_balance_weights",
           "HeightLoss", "CrossEntropyLoss", "IGNORE_INDEX"]
