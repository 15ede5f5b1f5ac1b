"""The pixel arrays a synthetic city is drawn on, its materials, and the drawing primitives.

Everything is planned in metres in a city frame (u, v) rotated by the scene's street angle; a pixel centre
(row, col) lies at x = (col + 0.5)·gsd east, y = (row + 0.5)·gsd south of the canvas's upper-left corner,
and u = x·cosθ + y·sinθ, v = −x·sinθ + y·cosθ. Objects are drawn with a "highest surface wins" rule, so
each pixel's label and nDSM are those of the surface a lidar sees from above at the true footprint.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from aerialmtl.data.synth.scene import BARE_SOIL, BUILDING, LOW_VEGETATION, ROAD, TREE, WATER

# Materials: they choose the texture amplitudes; the colour of each pixel is held in the canvas's tint.
(GRASS, SOIL, ASPHALT, CONCRETE, GRAVEL, MARKING, WATER_M, TILE, METAL, MEMBRANE, DARK, CROWN, USER, SEATS, CAR,
 GREEN_ROOF) = range(16)
#: texture amplitudes per material: large-scale (×), mid-scale (×), fine (DN)
TEXTURE = np.array(
    [[0.10, 0.10, 9.0], [0.08, 0.08, 7.0], [0.06, 0.07, 6.0], [0.05, 0.05, 5.0], [0.05, 0.06, 9.0],
     [0.0, 0.03, 4.0], [0.04, 0.03, 1.5], [0.03, 0.05, 6.0], [0.02, 0.03, 3.0], [0.03, 0.03, 4.0],
     [0.04, 0.05, 4.0], [0.10, 0.18, 10.0], [0.0, 0.0, 0.0], [0.0, 0.04, 6.0], [0.0, 0.02, 2.0],
     [0.10, 0.10, 9.0]],
    np.float32,
)
#: ground surfaces (material, label, base RGB); flat roofs draw from the same list to look like the ground
GROUND_LIKE = (
    (ASPHALT, ROAD, (92, 92, 94)), (ASPHALT, ROAD, (70, 70, 74)), (ASPHALT, ROAD, (118, 116, 112)),
    (CONCRETE, ROAD, (172, 170, 162)), (CONCRETE, ROAD, (150, 148, 140)),
    (GRAVEL, BARE_SOIL, (160, 150, 135)), (GRAVEL, BARE_SOIL, (132, 124, 112)),
    (GRASS, LOW_VEGETATION, (96, 128, 62)), (SOIL, BARE_SOIL, (150, 122, 88)),
)
#: probability that a flat roof is drawn in a ground material (:attr:`CityStyle.ground_roofs`' default) and, of all
#: flat roofs at that default, the share drawn in their own yard's look (the rest of the ground-like ones in another
#: ground's); another ``ground_roofs`` scales both alike
GROUND_ROOFS, YARD_ROOFS = 0.65, 0.35
#: roofs that do not look like ground
ROOF_OTHER = ((MEMBRANE, (205, 205, 200)), (METAL, (150, 152, 156)), (DARK, (62, 62, 68)), (METAL, (110, 128, 140)),
              (MEMBRANE, (185, 180, 168)))
ROOF_TILES = ((150, 68, 48), (172, 92, 62), (122, 58, 44), (140, 100, 80), (118, 118, 124), (74, 70, 70))
FACADES = ((190, 185, 175), (150, 146, 140), (90, 104, 120), (60, 74, 92), (170, 150, 125), (200, 200, 200))
TREE_GREENS = ((46, 82, 36), (58, 96, 42), (38, 70, 40), (70, 100, 46), (50, 76, 30))
CAR_COLOURS = ((220, 220, 220), (30, 30, 34), (130, 132, 136), (180, 182, 186), (150, 30, 30), (30, 50, 120),
               (60, 60, 64), (200, 200, 196))
TREE_MAX, BUILDING_MAX = 30.0, 60.0

Rgb = tuple[float, float, float]
#: a texture source: (rng, (h, w), base colour) → float32 (3, h, w) albedo in DN, or None to use the colour
TextureFn = Callable[[np.random.Generator, tuple[int, int], Rgb], "np.ndarray | None"]


def jitter(rng: np.random.Generator, rgb: tuple[float, ...], amount: float = 10.0) -> Rgb:
    """``rgb`` with N(0, amount) DN added to each channel, clipped to 0–255."""
    r, g, b = (float(np.clip(c + rng.normal(0, amount), 0, 255)) for c in rgb)
    return r, g, b


@dataclass
class Window:
    """A rectangle of canvas pixels with the city-frame coordinates of their centres."""

    rows: slice
    cols: slice
    u: np.ndarray  # float32 (h, w) metres
    v: np.ndarray


class CityCanvas:
    """Arrays of an (N, N) canvas of ``gsd`` metres and the city frame rotated by ``theta`` radians.

    Attributes:
        ndsm: float32 (N, N) height above ground of the top surface, metres.
        labels: uint8 (N, N) raw codes of the ``synthetic`` class scheme.
        material: uint8 (N, N) material index (texture amplitudes, see :data:`TEXTURE`).
        tint: float32 (3, N, N) base colour of the top surface, DN.
        facade: float32 (3, N, N) colour of the walls (or crown sides) of the object at each pixel, DN.
        u, v: float32 (N, N) city-frame coordinates of the pixel centres, metres.
    """

    def __init__(self, size: int, gsd: float, theta: float, texture: TextureFn | None = None) -> None:
        self.n, self.gsd = size, gsd
        self.cos, self.sin = math.cos(theta), math.sin(theta)
        shape = (size, size)
        self.ndsm = np.zeros(shape, np.float32)
        self.labels = np.full(shape, LOW_VEGETATION, np.uint8)
        self.material = np.full(shape, GRASS, np.uint8)
        self.tint = np.empty((3, *shape), np.float32)
        self.tint[:] = np.array(GROUND_LIKE[7][2], np.float32)[:, None, None]
        self.facade = np.zeros((3, *shape), np.float32)
        xs = (np.arange(size, dtype=np.float32) + 0.5) * np.float32(gsd)
        self.u = xs[None, :] * np.float32(self.cos) + xs[:, None] * np.float32(self.sin)
        self.v = -xs[None, :] * np.float32(self.sin) + xs[:, None] * np.float32(self.cos)
        self.texture = texture
        self.extent = size * gsd

    def window(self, u0: float, u1: float, v0: float, v1: float) -> Window | None:
        """Canvas pixels around the city-frame rectangle [u0, u1] × [v0, v1], or None if off the canvas."""
        us = np.array([u0, u1, u1, u0])
        vs = np.array([v0, v0, v1, v1])
        x = us * self.cos - vs * self.sin
        y = us * self.sin + vs * self.cos
        c0, c1 = int(math.floor(x.min() / self.gsd)), int(math.ceil(x.max() / self.gsd)) + 1
        r0, r1 = int(math.floor(y.min() / self.gsd)), int(math.ceil(y.max() / self.gsd)) + 1
        r0, c0, r1, c1 = max(r0, 0), max(c0, 0), min(r1, self.n), min(c1, self.n)
        if r0 >= r1 or c0 >= c1:
            return None
        rows, cols = slice(r0, r1), slice(c0, c1)
        return Window(rows, cols, self.u[rows, cols], self.v[rows, cols])

    def rect(self, u0: float, u1: float, v0: float, v1: float) -> tuple[Window, np.ndarray] | None:
        """The window of a rectangle and its (h, w) inside mask, or None if nothing of it is on the canvas."""
        win = self.window(u0, u1, v0, v1)
        if win is None:
            return None
        inside = (win.u >= u0) & (win.u < u1) & (win.v >= v0) & (win.v < v1)
        return (win, inside) if inside.any() else None

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
        h = np.broadcast_to(np.asarray(height, np.float32), mask.shape)
        top = mask & (h > self.ndsm[win.rows, win.cols])
        self.ndsm[win.rows, win.cols][top] = h[top]
        if label is not None:
            self.labels[win.rows, win.cols][top] = label
        self.material[win.rows, win.cols][top] = material
        self.tint[:, win.rows, win.cols][:, top] = np.broadcast_to(rgb, (3, *mask.shape))[:, top]
        wall = rgb.reshape(3, -1).mean(axis=1) * 0.8 if facade is None else np.asarray(facade, np.float32)
        self.facade[:, win.rows, win.cols][:, top] = np.asarray(wall, np.float32)[:, None]


__all__ = ["BUILDING", "CityCanvas", "ROAD", "TREE", "WATER", "Window", "jitter"]
