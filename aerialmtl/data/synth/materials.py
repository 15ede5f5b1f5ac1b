"""What the surfaces of a synthetic scene are made of: class codes, colours, colour jitter and texture.

Both styles of the generator (the town of :mod:`~aerialmtl.data.synth.scene`, the city of
:mod:`~aerialmtl.data.synth.city`) colour a surface the same way: a base colour in DN (0–255), varied per
object by :func:`jitter`, times a texture gain and plus a per-pixel grain (:func:`texture_terms`) whose
amplitudes depend on the material. The colours and amplitudes both styles use are named here once; a style's
own palette (which materials it has, and the ones only it uses) stays beside its layout.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

#: Raw label codes of the built-in ``synthetic`` class scheme (``aerialmtl/resources/classes/synthetic.yaml``).
BARE_SOIL, ROAD, BUILDING, TREE, LOW_VEGETATION, WATER = 1, 2, 3, 4, 5, 6

#: An RGB colour in DN (0–255), as floats.
Rgb = tuple[float, float, float]


class Texture(NamedTuple):
    """Texture amplitudes of a material (see :func:`texture_terms`).

    Attributes:
        large: gain per unit of the large-scale noise (features of ~25 m), a factor.
        mid: gain per unit of the mid-scale noise (features of ~3–4 m), a factor.
        fine: per-pixel grain per unit of white noise, DN.
    """

    large: float
    mid: float
    fine: float


# Base colours (DN) and textures that both styles use for the same surface.
GRASS_RGB: Rgb = (96, 128, 62)
SOIL_RGB: Rgb = (150, 122, 88)
ASPHALT_RGB: Rgb = (92, 92, 94)
GRAVEL_RGB: Rgb = (172, 160, 140)
MARKING_RGB: Rgb = (215, 215, 205)
GRASS_TEXTURE = Texture(0.10, 0.10, 9.0)
SOIL_TEXTURE = Texture(0.08, 0.08, 7.0)
WATER_TEXTURE = Texture(0.04, 0.03, 1.5)
#: Crown colours of trees (before jitter and darkening).
TREE_GREENS: tuple[Rgb, ...] = ((46, 82, 36), (58, 96, 42), (38, 70, 40), (70, 100, 46), (50, 76, 30))
#: Red and brown roof tiles (before jitter); each style adds its own other roof colours.
TILE_REDS: tuple[Rgb, ...] = ((150, 68, 48), (172, 92, 62), (122, 58, 44), (140, 100, 80))


def jitter(rng: np.random.Generator, rgb: tuple[float, ...], amount: float) -> Rgb:
    """``rgb`` with N(0, ``amount``) DN added to each channel (three draws from ``rng``), clipped to 0–255."""
    r, g, b = (float(np.clip(c + rng.normal(0, amount), 0, 255)) for c in rgb)
    return r, g, b


def tree_green(rng: np.random.Generator) -> Rgb:
    """A tree's crown colour: one of :data:`TREE_GREENS` jittered by 8 DN (one integer and three normal draws)."""
    return jitter(rng, TREE_GREENS[int(rng.integers(len(TREE_GREENS)))], 8.0)


def texture_table(textures: tuple[Texture, ...]) -> np.ndarray:
    """float32 (M, 3) amplitudes (large, mid, fine) of a palette's materials, indexed by material number."""
    return np.array(textures, np.float32)


def texture_terms(amplitudes: np.ndarray, large: np.ndarray, mid: np.ndarray,
                  fine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The texture of every pixel: a surface of base colour ``c`` (DN) is drawn ``c × gain + grain``.

    Args:
        amplitudes: float32 (H, W, 3) each pixel's material amplitudes (a :func:`texture_table` indexed by
            the material raster).
        large, mid: float32 (H, W) smooth noise of about unit deviation with large and mid-sized features.
        fine: float32 (H, W) white noise of unit deviation.

    Returns:
        ``gain`` float32 (H, W), ``1 + large·a_large + mid·a_mid`` (a factor), and ``grain`` float32 (H, W),
        ``fine·a_fine`` (DN).
    """
    gain: np.ndarray = 1.0 + amplitudes[..., 0] * large + amplitudes[..., 1] * mid
    grain: np.ndarray = amplitudes[..., 2] * fine
    return gain, grain


__all__ = ["ASPHALT_RGB", "BARE_SOIL", "BUILDING", "GRASS_RGB", "GRASS_TEXTURE", "GRAVEL_RGB", "LOW_VEGETATION",
           "MARKING_RGB", "ROAD", "Rgb", "SOIL_RGB", "SOIL_TEXTURE", "TILE_REDS", "TREE", "TREE_GREENS", "Texture",
           "WATER", "WATER_TEXTURE", "jitter", "texture_table", "texture_terms", "tree_green"]
