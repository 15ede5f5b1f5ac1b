"""Shapes of the objects both styles draw: gable roofs, tree crowns (size and height profile), closed forests.

Coordinates are metres in the scene's frame (:mod:`~aerialmtl.data.synth.canvas`); heights are metres above
ground. The profiles take the pixels an object covers and return their heights; the style draws them.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

#: Lowest crown height (rim) of a tree and lowest crown top, metres.
CROWN_MIN_M, CROWN_TOP_MIN_M = 3.0, 4.0
#: Roof tiles: rows 0.9 m apart, ±7 % brightness.
TILE_ROW_M, TILE_CONTRAST = 0.9, 0.07


def gable(u: np.ndarray, v: np.ndarray, u0: float, u1: float, v0: float, v1: float, eave: float,
          rise: float) -> tuple[np.ndarray, np.ndarray]:
    """A gable roof over the rectangle [u0, u1] × [v0, v1], its ridge along the rectangle's longer side.

    Args:
        u, v: float32 (...) frame coordinates of the pixels, metres.
        u0, u1, v0, v1: the rectangle, metres.
        eave: height of the eaves, metres.
        rise: height of the ridge above the eaves, metres.

    Returns:
        ``height`` (...) metres (``eave`` at the long edges, ``eave + rise`` on the ridge line) and ``across``
        (...) the signed distance from the ridge line, metres.
    """
    along_u = (u1 - u0) >= (v1 - v0)
    across = (v - 0.5 * (v0 + v1)) if along_u else (u - 0.5 * (u0 + u1))
    half = 0.5 * ((v1 - v0) if along_u else (u1 - u0))
    height = eave + rise * np.clip(1.0 - np.abs(across) / half, 0.0, 1.0)
    return height, across


def tile_rows(across: np.ndarray) -> np.ndarray:
    """Brightness change (a factor − 1) of roof tiles laid in rows parallel to the ridge, ``across`` metres off it."""
    rows: np.ndarray = TILE_CONTRAST * np.sin(2 * np.pi * np.abs(across) / TILE_ROW_M)
    return rows


def crown_size(rng: np.random.Generator, top: float, top_max: float, rim_share: float) -> tuple[float, float]:
    """The top and rim heights of a tree crown, metres.

    Args:
        rng: draws the rim's share of the top (one uniform draw in [0.3, ``rim_share``]).
        top: the wanted top, clipped to [:data:`CROWN_TOP_MIN_M`, ``top_max``].
        top_max: the style's tallest tree, metres.
        rim_share: the highest rim as a share of the top.
    """
    top = float(np.clip(top, CROWN_TOP_MIN_M, top_max))
    return top, max(CROWN_MIN_M, top * rng.uniform(0.3, rim_share))


def crown(d2: np.ndarray, base: float, top: float, bumps: np.ndarray, top_max: float) -> np.ndarray:
    """A tree crown: a dome from its rim at ``base`` to ``top`` metres, roughened by ``bumps``.

    Args:
        d2: (...) squared distance from the trunk over the squared crown radius (< 1 inside the crown).
        base, top: heights of the crown's rim and top, metres.
        bumps: (...) smooth noise of about unit deviation (±0.35 m per unit).
        top_max: the style's tallest tree, metres.

    Returns:
        (...) heights, metres, within [:data:`CROWN_MIN_M`, ``top_max``].
    """
    height: np.ndarray = np.clip(base + (top - base) * np.sqrt(np.clip(1.0 - d2, 0.0, 1.0)) + 0.35 * bumps,
                                 CROWN_MIN_M, top_max)
    return height


def forest_trees(rng: np.random.Generator, u0: float, u1: float, v0: float, v1: float, slender_max: float,
                 dark_max: float) -> Iterator[tuple[float, float, float, float, float]]:
    """The trees of a closed forest over the frame rectangle [u0, u1] × [v0, v1] (metres).

    About 1–1.6 crowns of 4.5 m radius per their area, at random places; crowns of 2.5–7 m radius, their top
    ``radius × [2.2, slender_max] + [0, 4]`` metres, darkened by a share in [0, ``dark_max``]. Draws from ``rng``
    lazily, tree by tree (the caller may draw for each tree in between).

    Yields:
        (u, v, radius, top, dark) of each tree: metres, metres, metres, metres, a share.
    """
    for _ in range(int((u1 - u0) * (v1 - v0) / (math.pi * 4.5**2) * rng.uniform(1.0, 1.6))):
        radius = rng.uniform(2.5, 7.0)
        yield (rng.uniform(u0, u1), rng.uniform(v0, v1), radius, radius * rng.uniform(2.2, slender_max)
               + rng.uniform(0, 4), rng.uniform(0.0, dark_max))


__all__ = ["crown", "crown_size", "forest_trees", "gable", "tile_rows"]
