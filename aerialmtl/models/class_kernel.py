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

numba compiles the kernel the first time it is used after an install (about 1 s) and keeps the machine code
in the package's ``numba`` store (:mod:`aerialmtl.models.class_kernel_jit`, :mod:`aerialmtl.stores`), so
later runs load it (0.4 s with the numba import); a damaged store is healed with a warning, and where it cannot
be written the kernel is compiled in every process. The kernel runs in the calling thread (OpenVINO's streams
hold the other cores).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import cast

import numpy as np


@functools.cache
def _kernel() -> Callable[..., None] | None:
    """The compiled kernel, or ``None`` where numba cannot be imported (then torch's path runs)."""
    try:
        from aerialmtl.models import class_kernel_jit  # numba: imported (seconds) only where the kernel runs
    except ImportError:  # pragma: no cover - numba is a dependency; a broken install falls back
        return None
    return cast(Callable[..., None], class_kernel_jit.kernel)


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


__all__ = ["add_class_sums", "available", "prepare"]
