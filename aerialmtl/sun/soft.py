"""A differentiable cast shadow (torch): the soft running maximum of :func:`aerialmtl.sun.cast_shadow_mask`.

For a self-supervised step: render the shadows of a *predicted* height map at the sun and compare them with the
observed shadow probability, with gradients flowing back into the heights. torch is imported here only, so
the rest of :mod:`aerialmtl.sun` stays numpy/scipy.
"""

from __future__ import annotations

import math

import torch

from aerialmtl.sun.cast import line_offsets, sun_steps
from aerialmtl.sun.position import Sun


def soft_cast_shadow(height: torch.Tensor, gsd_m: float, sun: Sun, max_length_m: float, tol_m: float = 0.3,
                     temperature_m: float = 0.5) -> torch.Tensor:
    """Soft cast shadows of heights: a probability that rises smoothly where an occluder rises above the sun ray.

    ``occ(p) = τ · logsumexp_d((h(p + d·u) − d·|u|·gsd·tan E) / τ)`` over ``d·|u|·gsd ≤ max_length_m`` (a soft
    maximum, ≥ the hard one by at most ``τ·log(n)``), and ``shadow = sigmoid((occ − h(p) − tol) / τ)``. As ``τ → 0``
    it tends to :func:`~aerialmtl.sun.cast_shadow_mask` with the same ``max_length_m``. Occluders beyond the raster
    count as absent.

    Args:
        height: float tensor (..., H, W) of heights in metres (e.g. a batch (N, 1, H, W)); may require grad.
        gsd_m: pixel size in metres. sun: the sun.
        max_length_m: the longest shadow considered, metres (cost grows with it: one shifted copy per step).
        tol_m: metres an occluder must rise above the ray (as the hard mask).
        temperature_m: softness τ in metres.

    Returns:
        tensor of ``height``'s shape and dtype, 0–1.
    """
    rows_dom, step, slope = sun_steps(sun.azimuth_deg)
    per_step = gsd_m * math.hypot(1.0, slope)
    n = max(1, int(max_length_m // per_step))
    cross = line_offsets(n + 1, slope)
    drop = per_step * sun.tan_elevation
    h_, w_ = height.shape[-2:]
    pad = n + 1
    neg = -1.0e4  # metres: below any occluder, finite so that the soft maximum stays finite with its gradient
    padded = torch.nn.functional.pad(height, (pad, pad, pad, pad), value=neg)
    terms = []
    for d in range(1, n + 1):
        dr, dc = (step * d, int(cross[d])) if rows_dom else (int(cross[d]), step * d)
        shifted = padded[..., pad + dr: pad + dr + h_, pad + dc: pad + dc + w_]
        terms.append((shifted - d * drop) / temperature_m)
    occ = temperature_m * torch.logsumexp(torch.stack(terms, dim=0), dim=0)
    return torch.sigmoid((occ - height - tol_m) / temperature_m)
