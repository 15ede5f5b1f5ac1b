"""The ``classes`` layer of finished pixels on a CPU in one compiled pass: :func:`finished_classes`.

:class:`~aerialmtl.inference.stitch.Stitcher` finishes the class map as ``argmax_k(p_k / w)`` over the blended
class sums ``p`` (h, w, K) and weight sums ``w``, with the layer's nodata where ``w ≤ 0``. In torch that is a
division of every class sum into a new (h, w, K) tensor, an argmax over its last dimension (a reduction over K =
20 contiguous floats per pixel, which torch's CPU kernel does a pixel at a time), a widening and a ``where``: on
a 1024² block with K = 20, ~100 ms on one core, 80 ms on two, the stitch stage's largest part at T = 1.

:func:`kernel` gives the same class to the bit without dividing every sum: the division by a positive ``w`` is
monotone, so the largest quotient is that of the largest sum, ``top = max_k p_k / w``; the class is the first k
whose quotient equals ``top`` (torch's rule: the first of equal maxima), and only sums within 1e-6 of the largest
can round to the same quotient, so only they are divided. Everything torch would do otherwise is kept: the
first NaN wins where a sum is NaN, a NaN weight gives class 0 (every quotient NaN), and where the largest
quotient is not a normal float (overflow to ∞, zero, subnormal) every sum is divided and compared. 27 ms per 1024²
block with K = 20 on one core (tests/test_stitch.py checks it against torch on ties, NaN, ∞ and rounding ties).

The kernel is compiled by numba the first time after an install (~1 s for each of its two array layouts: blocks
as wide as the accumulators, and narrower ones) and kept in the package's ``numba``
store (:mod:`aerialmtl.jit`); importing this module imports numba (the predict command imports it anyway).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from aerialmtl.jit import jit

#: The smallest normal float32: below it (or at ∞) the quotients' rounding is not relative, so every sum is
#: divided.
_NORMAL = np.float32(np.finfo(np.float32).tiny)
#: Sums closer than this (relative) to the largest are divided and compared; farther ones cannot round to the
#: same quotient (the quotients' relative spacing is 2⁻²³ ≈ 1.2e-7).
_CLOSE = np.float32(1e-6)


@jit
def kernel(sums: Any, weight: Any, nodata: Any, out: Any) -> None:  # pragma: no cover - compiled
    """``out[r, c] = argmax_k(sums[r, c, k] / weight[r, c])`` (first maximum; NaN as torch), ``nodata`` where
    ``weight[r, c] ≤ 0``.

    Args:
        sums: (h, w, K) float32 class sums (any strides).
        weight: (h, w) float32 weight sums.
        nodata: the value of pixels without weight (``out``'s dtype).
        out: (h, w) integer array, written.
    """
    h, w, k = sums.shape
    for r in range(h):
        for c in range(w):
            s = weight[r, c]
            if s <= 0:
                out[r, c] = nodata
                continue
            # the largest sum, as four partial maxima (four short dependency chains instead of one of K), and
            # whether any sum is NaN
            m0 = m1 = m2 = m3 = sums[r, c, 0]
            nan = False
            q = 0
            while q + 4 <= k:
                v0, v1, v2, v3 = sums[r, c, q], sums[r, c, q + 1], sums[r, c, q + 2], sums[r, c, q + 3]
                nan |= (v0 != v0) | (v1 != v1) | (v2 != v2) | (v3 != v3)
                m0 = v0 if v0 > m0 else m0
                m1 = v1 if v1 > m1 else m1
                m2 = v2 if v2 > m2 else m2
                m3 = v3 if v3 > m3 else m3
                q += 4
            while q < k:
                v0 = sums[r, c, q]
                nan |= v0 != v0
                m0 = v0 if v0 > m0 else m0
                q += 1
            if nan:  # torch's argmax: the first NaN
                for q in range(k):
                    if sums[r, c, q] != sums[r, c, q]:
                        out[r, c] = q
                        break
                continue
            m01 = m0 if m0 > m1 else m1
            m23 = m2 if m2 > m3 else m3
            m = m01 if m01 > m23 else m23
            top = m / s
            if top != top:  # a NaN weight: every quotient is NaN, the first one wins
                out[r, c] = 0
                continue
            normal = abs(top) >= _NORMAL and abs(top) < np.inf
            bound = m - abs(m) * _CLOSE if normal else -np.inf
            for q in range(k):
                v = sums[r, c, q]
                if v >= bound and v / s == top:
                    out[r, c] = q
                    break


def finished_classes(sums: torch.Tensor, weight: torch.Tensor, nodata: int, out: torch.Tensor) -> None:
    """Write the class map of finished pixels into ``out`` (:func:`kernel`).

    Args:
        sums: (h, w, K) float32 blended class sums, on the CPU (a view of the stitcher's accumulator).
        weight: (h, w) float32 weight sums.
        nodata: the classes layer's nodata value.
        out: (h, w) uint8 CPU tensor (a view of the finished block's band), written.
    """
    kernel(sums.numpy(), weight.numpy(), out.numpy().dtype.type(nodata), out.numpy())


def prepare() -> None:
    """Load the kernel (from the numba store, or compile it) now: ``predict`` calls it before it makes any output,
    as for the MC class kernel (:func:`aerialmtl.models.class_kernel.prepare`).
    """
    out = torch.empty((2, 1), dtype=torch.uint8)
    whole = torch.ones((2, 1, 2))
    finished_classes(whole, whole[..., 0].contiguous(), 255, out)  # a block as wide as the accumulators
    part = torch.ones((2, 2, 2))[:, :1]
    finished_classes(part, part[..., 0], 255, out)  # the usual block: some of their columns


__all__ = ["finished_classes", "kernel", "prepare"]
