"""The compiled part of :mod:`aerialmtl.models.class_kernel` (numba; imported only when a run needs it).

The kernels are compiled with :func:`aerialmtl.jit.jit`: their machine code is kept in the package's ``numba``
store (see :mod:`aerialmtl.jit`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from aerialmtl.jit import jit

log2e = np.float32(1.4426950408889634)
ln2_hi = np.float32(0.693359375)  # exactly representable, so that n·ln2_hi is exact
ln2_lo = np.float32(-2.12194440054690583e-4)  # ln 2 − ln2_hi
c2, c3, c4 = np.float32(1 / 2), np.float32(1 / 6), np.float32(1 / 24)
c5, c6, c7 = np.float32(1 / 120), np.float32(1 / 720), np.float32(1 / 5040)
one, half, zero = np.float32(1.0), np.float32(0.5), np.float32(0.0)
#: exp(d) for d below this is taken as exp of it (float32's smallest normal number is 1.2e-38 = exp(−87.3)).
EXP_FLOOR = np.float32(-87.0)


@jit
def add_row(zk: Any, img: int, y: int, p_sum: Any, e_sum: Any, top: Any, s_exp: Any, s_ed: Any,
            poly: Any, bits: Any, e: Any) -> None:  # pragma: no cover - runs compiled
    """One row of one sample: ``zk`` (K, W) logits → added into ``p_sum[:, img, y]`` and ``e_sum[img, y]``."""
    k_cls, width = zk.shape
    pow2 = bits.view(np.float32)
    for x in range(width):
        top[x] = zk[0, x]
    for k in range(1, k_cls):
        for x in range(width):
            v = zk[k, x]
            top[x] = v if v > top[x] else top[x]
    for x in range(width):
        s_exp[x] = zero
        s_ed[x] = zero
    for k in range(k_cls):
        for x in range(width):
            d = zk[k, x] - top[x]
            if d < EXP_FLOOR:  # NaN stays NaN
                d = EXP_FLOOR
            m = np.floor(d * log2e + half)
            r = (d - m * ln2_hi) - m * ln2_lo
            p = c7 * r + c6
            p = p * r + c5
            p = p * r + c4
            p = p * r + c3
            p = p * r + c2
            p = p * r + one
            poly[x] = p * r + one
            bits[x] = (np.int32(m) + np.int32(127)) << np.int32(23)
        for x in range(width):
            ex = poly[x] * pow2[x]
            e[k, x] = ex
            s_exp[x] += ex
            s_ed[x] += ex * (zk[k, x] - top[x])
    for x in range(width):
        inv = one / s_exp[x]
        h = np.log(s_exp[x]) - s_ed[x] * inv
        e_sum[img, y, x] += zero if h < zero else h  # clamped ≥ 0; NaN stays NaN
        s_exp[x] = inv
    for k in range(k_cls):
        for x in range(width):
            p_sum[k, img, y, x] += e[k, x] * s_exp[x]


@jit
def kernel(z: Any, b: int, p_sum: Any, e_sum: Any, channels_last: bool) -> None:  # pragma: no cover
    """:func:`aerialmtl.models.class_kernel.add_class_sums` (its arguments), row by row of every sample."""
    if channels_last:  # (N, H, W, K): each row is copied into class planes first (K × W, in the cache)
        n_img, height, width, k_cls = z.shape
    else:  # (N, K, H, W)
        n_img, k_cls, height, width = z.shape
    top = np.empty(width, np.float32)
    s_exp = np.empty(width, np.float32)
    s_ed = np.empty(width, np.float32)
    poly = np.empty(width, np.float32)
    bits = np.empty(width, np.int32)
    e = np.empty((k_cls, width), np.float32)
    planes = np.empty((k_cls, width), np.float32)
    for n in range(n_img):
        img = n % b
        for y in range(height):
            if channels_last:
                for x in range(width):
                    for k in range(k_cls):
                        planes[k, x] = z[n, y, x, k]
                add_row(planes, img, y, p_sum, e_sum, top, s_exp, s_ed, poly, bits, e)
            else:
                add_row(z[n, :, y, :], img, y, p_sum, e_sum, top, s_exp, s_ed, poly, bits, e)


__all__ = ["EXP_FLOOR", "add_row", "kernel"]
