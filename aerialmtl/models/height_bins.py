"""The height-bin spread: a categorical distribution over height bins beside the regressed height.

An option of the aleatoric height head (``model.aleatoric: true`` with ``model.height_bins: K``), beside
the Laplace scale. Instead of one scale channel the height head outputs K logits over fixed height bins,
trained with cross-entropy on the reference height's bin (as DORN's ordinal regression discretises depth,
Fu et al., CVPR 2018, which the D3-Net authors' thesis cites). The height itself stays the regressed
channel, trained as in the aleatoric head (Laplace NLL with a scale channel used in training only); the
bins give its spread:

    std² = Σ_k p_k · ((c_k − μ)² + w_k² / 12)

the second moment of the bin distribution around the regressed height μ (bin k: centre c_k, width w_k,
probability p_k; the ``w²/12`` term spreads each bin's mass uniformly over its width). A categorical can be
bimodal, so a pixel the network finds ambiguous ("ground, or a 20 m roof") gets a large spread even where μ
is near the ground: what a Laplace scale predicted from the same features does not express. The spread is
returned as the head's ``height_scale`` b = std / √2, so that every consumer (MC statistics ``2·b²``, export,
calibration) reads it as it reads a Laplace scale.

Bins: spacing-increasing in ``log(1 + h)`` from 0 to ``model.height_bin_max`` metres (narrow bins near the
ground, wide ones for tall objects); heights above the top edge fall in the last bin, heights below 0 in the
first.
"""

from __future__ import annotations

import math

import torch


def bin_edges(bins: int, top: float) -> torch.Tensor:
    """The ``bins + 1`` bin edges in metres (float32), from 0 to ``top``, equally spaced in ``log(1 + h)``."""
    return torch.expm1(torch.linspace(0.0, math.log1p(top), bins + 1, dtype=torch.float64)).float()


def bin_index(height: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """The bin of each height (int64, same shape; 0 … K−1): below 0 → 0, at or above the top edge → K−1."""
    inner = edges[1:-1].to(height.device, height.dtype)
    return torch.bucketize(height.contiguous(), inner, right=True)


def second_moment(logits: torch.Tensor, mu: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """``Σ_k p_k ((c_k − μ)² + w_k²/12)`` in m², B×1×H×W, float32.

    Args:
        logits: B×K×H×W bin logits.
        mu: B×1×H×W regressed height (metres).
        edges: the K + 1 bin edges (metres), from :func:`bin_edges`.
    """
    e = edges.to(logits.device)
    centre = (0.5 * (e[1:] + e[:-1])).view(1, -1, 1, 1)
    width2 = ((e[1:] - e[:-1]) ** 2 / 12.0).view(1, -1, 1, 1)
    p = torch.softmax(logits.float(), dim=1)
    d = centre - mu.float()
    return (p * (d * d + width2)).sum(1, keepdim=True)


def bins_scale(logits: torch.Tensor, mu: torch.Tensor, edges: torch.Tensor, floor: float) -> torch.Tensor:
    """The head's ``height_scale``: ``b = sqrt(second_moment / 2)``, at least ``floor`` (metres), B×1×H×W."""
    return (second_moment(logits, mu, edges) * 0.5).sqrt().clamp_min(floor)


__all__ = ["bin_edges", "bin_index", "bins_scale", "second_moment"]
