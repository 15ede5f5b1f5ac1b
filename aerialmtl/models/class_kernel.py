"""The per-sample class statistics of MC dropout in one pass over the logits, on CPUs (a numba kernel).

At T = 30 every window's K class planes are turned into probabilities and an entropy T times; with torch's
element-wise operations that is a dozen passes over K × H × W floats per sample (max, subtract, exp, sums,
products), each one memory-bound: 35–50 ms per 1024² sample with K = 20 on one Zen 5 core, as long as the
model itself on OpenVINO (bench/RESULTS.md, issue 27). :func:`add_class_sums` reads each pixel's K logits once
per sample, row by row (a row's K × W floats stay in the core's cache), and adds its probabilities and entropy
into the running sums: 15–19 ms per sample there.

The kernel computes what torch's path (:func:`aerialmtl.models.mc_dropout._class_sums_torch`) computes, with
``d = z − max_k z`` and ``S = Σ_k exp(d_k)``: ``p_k = exp(d_k) / S`` and ``H = log S − Σ_k exp(d_k)·d_k / S``
(clamped ≥ 0), and adds the samples one after the other into the sums (so the sums do not depend on how the
samples are chunked). Its ``exp`` is the textbook one that vectorises: ``exp(d) = 2^n · exp(r)`` with
``n = round(d / ln 2)`` and ``r = d − n·ln 2`` (ln 2 split in two so that ``r`` is exact), ``exp(r)`` by its
Taylor series to the 7th power (relative error below 9e-8 on ``|r| ≤ ln 2 / 2``) and ``2^n`` put together
from its exponent bits; ``d`` below −87 is taken as −87 (``exp`` ≈ 1.6e-38, where float32's normal numbers
end). Against torch's path: probabilities within 1e-6 and entropies within 2e-6 (tests); NaN logits give
NaN, as there.

numba compiles the kernel on its first call in a process (about 1 s) and keeps the machine code in its cache
(``__pycache__`` beside this file, or numba's user cache when that is read-only), so later runs load it. The
kernel runs in the calling thread (OpenVINO's streams hold the other cores).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np

#: exp(d) for d below this is taken as exp of it (float32's smallest normal number is 1.2e-38 = exp(−87.3)).
EXP_FLOOR = -87.0


@functools.cache
def _kernel() -> Callable[..., None] | None:
    """The compiled kernel, or ``None`` where numba cannot be imported (then torch's path runs)."""
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency; a broken install falls back
        return None

    log2e = np.float32(1.4426950408889634)
    ln2_hi = np.float32(0.693359375)  # exactly representable, so that n·ln2_hi is exact
    ln2_lo = np.float32(-2.12194440054690583e-4)  # ln 2 − ln2_hi
    c2, c3, c4 = np.float32(1 / 2), np.float32(1 / 6), np.float32(1 / 24)
    c5, c6, c7 = np.float32(1 / 120), np.float32(1 / 720), np.float32(1 / 5040)
    one, half, zero = np.float32(1.0), np.float32(0.5), np.float32(0.0)
    floor = np.float32(EXP_FLOOR)

    jit = numba.njit(cache=True, boundscheck=False, error_model="numpy", nogil=True)

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
                if d < floor:  # NaN stays NaN
                    d = floor
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

    return kernel


def available() -> bool:
    """Whether the kernel can run here (numba imports)."""
    return _kernel() is not None


@functools.cache
def prepare() -> bool:
    """Import numba and load the kernel (from numba's cache, or compile it) now, once per process; whether it
    can run.

    ``predict`` calls it before it makes any output. Loaded at the first MC window instead, a Ctrl-C that landed
    while numba was being loaded ended the process by the signal itself (exit status −2, no ``KeyboardInterrupt``,
    so no clean-up of the run's hidden staging files) in 4 of 8 tries; loaded first, 10 of 10 runs interrupted
    there ended as Ctrl-C should (exit 130, staging files removed).
    """
    if not available():
        return False
    one = np.zeros((1, 1, 1, 1), np.float32)
    add_class_sums(one, 1, np.zeros((1, 1, 1, 1), np.float32), np.zeros((1, 1, 1), np.float32))
    return True


def add_class_sums(logits: np.ndarray, b: int, p_sum: np.ndarray, e_sum: np.ndarray,
                   channels_last: bool = False) -> None:
    """Add the class probabilities and entropies of ``logits``' samples into the running sums, in place.

    Args:
        logits: (s·b, K, H, W) float32, C-contiguous, sample-major (sample ``t`` of image ``n`` at ``t·b + n``);
            with ``channels_last``, (s·b, H, W, K) (as OpenVINO's decoder graph returns them).
        b: images per sample.
        p_sum: (K, b, H, W) float32: ``p_sum[:, n] += Σ_t softmax(logits[t·b + n])`` (class planes).
        e_sum: (b, H, W) float32: ``e_sum[n] += Σ_t H(softmax(logits[t·b + n]))`` (nats).

    Raises:
        RuntimeError: numba is not importable (check :func:`available` first).
    """
    kernel = _kernel()
    if kernel is None:  # pragma: no cover - see available()
        raise RuntimeError("the class-statistics kernel needs numba; install it with `pip install numba`")
    kernel(logits, b, p_sum, e_sum, channels_last)


__all__ = ["EXP_FLOOR", "add_class_sums", "available", "prepare"]
