"""The city's canvas and palette: per-pixel material, colour and wall colour over the shared canvas.

A :class:`CityCanvas` is the generator's :class:`~aerialmtl.data.synth.canvas.Canvas` (frame, pixel grid,
"highest surface wins") plus what the city needs to render a leaning camera's view: each pixel's material
(its texture amplitudes, :data:`TEXTURE`), surface colour and the colour of the walls under it. The city's
materials and colours are listed here; those it shares with the town come from
:mod:`~aerialmtl.data.synth.materials`.
"""

from __future__ import annotations

import numpy as np

from aerialmtl.data.synth.canvas import Canvas, Window
from aerialmtl.data.synth.materials import (
    ASPHALT_RGB,
    BARE_SOIL,
    GRASS_RGB,
    GRASS_TEXTURE,
    LOW_VEGETATION,
    ROAD,
    SOIL_RGB,
    SOIL_TEXTURE,
    TILE_REDS,
    WATER_TEXTURE,
    Rgb,
    Texture,
    texture_table,
)
from aerialmtl.data.synth.textures import Source

# Materials: they choose the texture amplitudes; the colour of each pixel is held in the canvas's tint.
(GRASS, SOIL, ASPHALT, CONCRETE, GRAVEL, MARKING, WATER_M, TILE, METAL, MEMBRANE, DARK, CROWN, USER, SEATS, CAR,
 GREEN_ROOF) = range(16)
#: texture amplitudes per material, float32 (16, 3): large-scale (×), mid-scale (×), fine (DN)
TEXTURE = texture_table((
    GRASS_TEXTURE, SOIL_TEXTURE, Texture(0.06, 0.07, 6.0), Texture(0.05, 0.05, 5.0), Texture(0.05, 0.06, 9.0),
    Texture(0.0, 0.03, 4.0), WATER_TEXTURE, Texture(0.03, 0.05, 6.0), Texture(0.02, 0.03, 3.0),
    Texture(0.03, 0.03, 4.0), Texture(0.04, 0.05, 4.0), Texture(0.10, 0.18, 10.0), Texture(0.0, 0.0, 0.0),
    Texture(0.0, 0.04, 6.0), Texture(0.0, 0.02, 2.0), GRASS_TEXTURE,
))
#: ground surfaces (material, label, base RGB); flat roofs draw from the same list to look like the ground
GROUND_LIKE = (
    (ASPHALT, ROAD, ASPHALT_RGB), (ASPHALT, ROAD, (70, 70, 74)), (ASPHALT, ROAD, (118, 116, 112)),
    (CONCRETE, ROAD, (172, 170, 162)), (CONCRETE, ROAD, (150, 148, 140)),
    (GRAVEL, BARE_SOIL, (160, 150, 135)), (GRAVEL, BARE_SOIL, (132, 124, 112)),
    (GRASS, LOW_VEGETATION, GRASS_RGB), (SOIL, BARE_SOIL, SOIL_RGB),
)
#: probability that a flat roof is drawn in a ground material (:attr:`CityStyle.ground_roofs`' default) and, of all
#: flat roofs at that default, the share drawn in their own yard's look (the rest of the ground-like ones in another
#: ground's); another ``ground_roofs`` scales both alike
GROUND_ROOFS, YARD_ROOFS = 0.65, 0.35
#: roofs that do not look like ground
ROOF_OTHER = ((MEMBRANE, (205, 205, 200)), (METAL, (150, 152, 156)), (DARK, (62, 62, 68)), (METAL, (110, 128, 140)),
              (MEMBRANE, (185, 180, 168)))
ROOF_TILES = (*TILE_REDS, (118, 118, 124), (74, 70, 70))
FACADES = ((190, 185, 175), (150, 146, 140), (90, 104, 120), (60, 74, 92), (170, 150, 125), (200, 200, 200))
CAR_COLOURS = ((220, 220, 220), (30, 30, 34), (130, 132, 136), (180, 182, 186), (150, 30, 30), (30, 50, 120),
               (60, 60, 64), (200, 200, 196))
TREE_MAX, BUILDING_MAX = 30.0, 60.0

class CityCanvas(Canvas):
    """The shared canvas (:class:`~aerialmtl.data.synth.canvas.Canvas`, labels ``LOW_VEGETATION`` at first) plus
    the arrays a city renders from.

    Attributes:
        material: uint8 (N, N) material index (texture amplitudes, see :data:`TEXTURE`).
        tint: float32 (3, N, N) base colour of the top surface, DN.
        facade: float32 (3, N, N) colour of the walls (or crown sides) of the object at each pixel, DN.
        texture: the source of user textures for surfaces, if any.
    """

    def __init__(self, size: int, gsd: float, theta: float, texture: Source | None = None) -> None:
        super().__init__(size, gsd, theta, LOW_VEGETATION)
        self.material = np.full(self.shape, GRASS, np.uint8)
        self.tint = np.empty((3, *self.shape), np.float32)
        self.tint[:] = np.array(GROUND_LIKE[7][2], np.float32)[:, None, None]
        self.facade = np.zeros((3, *self.shape), np.float32)
        self.texture = texture

    def colour(self, rng: np.random.Generator, win: Window, rgb: Rgb, material: int,
               textured: bool = True) -> tuple[np.ndarray, int]:
        """(3, h, w) or (3, 1, 1) albedo for a surface of colour ``rgb``, taken from the texture source if any."""
        if textured and self.texture is not None:
            tex = self.texture(rng, (win.u.shape[0], win.u.shape[1]), rgb)
            if tex is not None:
                return tex, USER
        return np.asarray(rgb, np.float32)[:, None, None], material

    def paint(self, win: Window, mask: np.ndarray, label: int, material: int, rgb: np.ndarray) -> None:
        """Lay a ground cover (height 0) where ``mask`` is True and nothing stands (nDSM < 0.5 m)."""
        mask = mask & (self.ndsm[win.rows, win.cols] < 0.5)
        self.ndsm[win.rows, win.cols][mask] = 0.0
        self.labels[win.rows, win.cols][mask] = label
        self.material[win.rows, win.cols][mask] = material
        self.tint[:, win.rows, win.cols][:, mask] = np.broadcast_to(rgb, (3, *mask.shape))[:, mask]

    def put(self, win: Window, mask: np.ndarray, height: np.ndarray | float, label: int | None, material: int,
            rgb: np.ndarray, facade: Rgb | None = None) -> None:
        """Draw an object's top surface where ``mask`` is True and it is higher than what is there.

        ``label`` None keeps the label underneath (cars: lidar sees their height, the map the road).
        """
        r, c = np.nonzero(mask)
        h = np.broadcast_to(np.asarray(height, np.float32), mask.shape)[r, c]
        top, rt, ct = self.raise_top(r + win.rows.start, c + win.cols.start, h, label)
        self.material[rt, ct] = material
        self.tint[:, rt, ct] = np.broadcast_to(rgb, (3, *mask.shape))[:, r[top], c[top]]
        wall = rgb.reshape(3, -1).mean(axis=1) * 0.8 if facade is None else np.asarray(facade, np.float32)
        self.facade[:, rt, ct] = np.asarray(wall, np.float32)[:, None]


__all__ = ["CityCanvas", "GROUND_LIKE", "GROUND_ROOFS", "TEXTURE", "Window"]
