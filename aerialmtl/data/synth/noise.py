"""Seeded smooth noise for the textures, grass heights and crown bumps of synthetic scenes.

:func:`smooth_noise` is value noise: a coarse grid of N(0, 1) values, one every ``cell_px`` pixels,
interpolated to the pixels in one of two ways. The town uses Catmull-Rom (``"cubic"``); the city uses
smoothstep (``"smoothstep"``: about as smooth to the eye, and two gathers instead of a matrix product, which
cost most of a small scene's time). Each style keeps its own: swapping one for the other changes every scene
of that style.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

Interpolation = Literal["cubic", "smoothstep"]


def smooth_noise(shape: tuple[int, int], cell_px: float, rng: np.random.Generator,
                 interpolation: Interpolation = "cubic") -> np.ndarray:
    """Value noise with features of ``cell_px`` pixels.

    Args:
        shape: (H, W) of the output.
        cell_px: feature size in pixels (≤ 1 gives white noise).
        rng: random generator (consumed deterministically: the coarse grid, in one draw).
        interpolation: ``"cubic"`` (Catmull-Rom) or ``"smoothstep"`` (see the module).

    Returns:
        float32 (H, W), roughly zero-mean with standard deviation ~0.6–1.
    """
    h, w = shape
    if cell_px <= 1.0:
        return rng.standard_normal(shape, dtype=np.float32)
    if interpolation == "smoothstep":
        return _smoothstep(shape, cell_px, rng)
    cell = float(cell_px)
    gh, gw = int(math.ceil(h / cell)) + 4, int(math.ceil(w / cell)) + 4
    coarse = rng.standard_normal((gh, gw), dtype=np.float32)
    rows = (np.arange(h, dtype=np.float32) + 0.5) / cell + 1.5
    cols = (np.arange(w, dtype=np.float32) + 0.5) / cell + 1.5
    # Separable Catmull-Rom interpolation as two small matrix products (the coarse grid is tiny).
    result: np.ndarray = (_interp_matrix(rows, gh) @ coarse @ _interp_matrix(cols, gw).T).astype(np.float32)
    return result


def _interp_matrix(pos: np.ndarray, n: int) -> np.ndarray:
    """(len(pos), n) matrix of Catmull-Rom weights sampling a length-``n`` signal at ``pos``."""
    i = np.floor(pos).astype(np.int64)
    t = (pos - i).astype(np.float32)
    t2, t3 = t * t, t * t * t
    weights = (
        0.5 * (-t3 + 2 * t2 - t),
        0.5 * (3 * t3 - 5 * t2 + 2),
        0.5 * (-3 * t3 + 4 * t2 + t),
        0.5 * (t3 - t2),
    )
    m = np.zeros((pos.size, n), dtype=np.float32)
    idx = np.arange(pos.size)
    for k, wk in enumerate(weights):
        np.add.at(m, (idx, np.clip(i - 1 + k, 0, n - 1)), wk)
    return m


def _smoothstep(shape: tuple[int, int], cell_px: float, rng: np.random.Generator) -> np.ndarray:
    """:func:`smooth_noise` interpolated separably with smoothstep weights (two gathers; no BLAS, no spline)."""
    h, w = shape
    coarse = rng.standard_normal((int(h / cell_px) + 2, int(w / cell_px) + 2), dtype=np.float32)

    def axis(n: int) -> tuple[np.ndarray, np.ndarray]:
        pos = (np.arange(n, dtype=np.float32) + 0.5) / np.float32(cell_px)
        i = pos.astype(np.int64)
        f = pos - i
        return i, f * f * (3 - 2 * f)

    ri, rf = axis(h)
    ci, cf = axis(w)
    rows = coarse[ri] * (1 - rf)[:, None] + coarse[ri + 1] * rf[:, None]  # (H, gw)
    noise: np.ndarray = (rows[:, ci] * (1 - cf) + rows[:, ci + 1] * cf).astype(np.float32)
    return noise
