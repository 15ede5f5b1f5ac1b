"""City blocks: what stands between the streets of a synthetic city (halls, towers, stadiums, houses, ...).

Each ``*_block`` function fills one block [u0, u1] × [v0, v1] (city-frame metres) of a
:class:`~aerialmtl.data.synth.city_canvas.CityCanvas` with its ground cover and its objects. Large flat roofs
often take the material and colour of the ground around them (asphalt, gravel, concrete, planted roofs): in
real orthophotos that is what makes a 20 m hall look like a car park.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aerialmtl.data.synth.city_canvas import (
    BUILDING_MAX,
    CAR,
    CAR_COLOURS,
    CONCRETE,
    CROWN,
    DARK,
    FACADES,
    GRASS,
    GRAVEL,
    GREEN_ROOF,
    GROUND_LIKE,
    GROUND_ROOFS,
    MARKING,
    METAL,
    ROOF_OTHER,
    ROOF_TILES,
    SEATS,
    SOIL,
    TILE,
    TREE_MAX,
    WATER_M,
    YARD_ROOFS,
    CityCanvas,
)
from aerialmtl.data.synth.materials import (
    BARE_SOIL,
    BUILDING,
    GRASS_RGB,
    GRAVEL_RGB,
    LOW_VEGETATION,
    MARKING_RGB,
    ROAD,
    SOIL_RGB,
    TREE,
    WATER,
    Rgb,
    jitter,
    tree_green,
)
from aerialmtl.data.synth.shapes import crown, crown_size, forest_trees, gable, tile_rows


def span(rng: np.random.Generator, lo: float, hi: float) -> float:
    """Uniform in [lo, hi], or ``lo`` when the interval is empty (one draw either way)."""
    x = rng.random()
    return lo + (hi - lo) * x if hi > lo else lo


@dataclass(frozen=True)
class Ground:
    """A ground cover: material, label and colour (DN)."""

    material: int
    label: int
    rgb: Rgb


class Blocks:
    """Draws block contents on ``canvas`` with the layout generator ``rng`` (textures from ``tex_rng``)."""

    def __init__(self, canvas: CityCanvas, rng: np.random.Generator, tex_rng: np.random.Generator,
                 bumps: np.ndarray, ground_roofs: float = GROUND_ROOFS) -> None:
        self.cv, self.rng, self.tex_rng, self.bumps = canvas, rng, tex_rng, bumps
        self.ground_roofs = ground_roofs

    # ---- primitives ------------------------------------------------------------------------------
    def ground(self, u0: float, u1: float, v0: float, v1: float, g: Ground) -> None:
        """Lay ground cover ``g`` over the rectangle (a user texture instead, when the source gives one)."""
        hit = self.cv.rect(u0, u1, v0, v1)
        if hit is not None:
            win, inside = hit
            rgb, mat = self.cv.colour(self.tex_rng, win, g.rgb, g.material)
            self.cv.paint(win, inside, g.label, mat, rgb)

    def paved(self) -> Ground:
        """A random paved or bare ground cover (no grass)."""
        mat, label, rgb = GROUND_LIKE[int(self.rng.integers(0, 7))]
        return Ground(mat, label, jitter(self.rng, rgb, 8.0))

    def flat_roof(self, yard: Ground) -> tuple[int, Rgb, bool]:
        """(material, colour, textured) of a flat roof; often the yard's own look or another ground's."""
        roll = self.rng.random()
        if roll < self.ground_roofs * (YARD_ROOFS / GROUND_ROOFS):
            return yard.material, jitter(self.rng, yard.rgb, 5.0), True
        if roll < self.ground_roofs:
            mat, _, rgb = GROUND_LIKE[int(self.rng.integers(len(GROUND_LIKE)))]
            return (GREEN_ROOF if mat == GRASS else mat), jitter(self.rng, rgb, 8.0), True
        mat, rgb = ROOF_OTHER[int(self.rng.integers(len(ROOF_OTHER)))]
        return mat, jitter(self.rng, rgb, 8.0), False

    def box(self, u0: float, u1: float, v0: float, v1: float, height: float, mat: int, rgb: Rgb,
            facade: Rgb, textured: bool = False) -> None:
        """A flat-roofed building (height clipped to the stated maximum)."""
        hit = self.cv.rect(u0, u1, v0, v1)
        if hit is None:
            return
        win, inside = hit
        albedo, m = self.cv.colour(self.tex_rng, win, rgb, mat, textured)
        self.cv.put(win, inside, min(height, BUILDING_MAX), BUILDING, m, albedo, facade)

    def rooftop_plant(self, u0: float, u1: float, v0: float, v1: float, height: float) -> None:
        """0–4 small boxes 1–3 m above a flat roof (air handlers, lift rooms)."""
        rng = self.rng
        for _ in range(int(rng.integers(0, 5))):
            bw, bd = rng.uniform(2, 6), rng.uniform(2, 6)
            if u1 - u0 < bw + 3 or v1 - v0 < bd + 3:
                continue
            bu, bv = span(rng, u0 + 1, u1 - bw - 1), span(rng, v0 + 1, v1 - bd - 1)
            grey = jitter(rng, (165, 165, 160), 15.0)
            self.box(bu, bu + bw, bv, bv + bd, min(BUILDING_MAX, height + rng.uniform(1, 3)), METAL, grey, grey)

    def gable(self, u0: float, u1: float, v0: float, v1: float, eave: float, rise: float, rgb: Rgb,
              facade: Rgb) -> None:
        """A house with a ridge along the rectangle's longer side and roof-tile stripes parallel to it."""
        hit = self.cv.rect(u0, u1, v0, v1)
        if hit is None:
            return
        win, inside = hit
        h, across = gable(win.u, win.v, u0, u1, v0, v1, eave, rise)
        stripes = 1.0 + tile_rows(across)
        albedo = np.asarray(rgb, np.float32)[:, None, None] * stripes[None].astype(np.float32)
        self.cv.put(win, inside, h.astype(np.float32), BUILDING, TILE, albedo, facade)

    def tree(self, u: float, v: float, radius: float, top: float, dark: float = 0.0) -> None:
        """A tree crown (dome between its rim ``base`` and ``top``, metres) centred on (u, v)."""
        top, base = crown_size(self.rng, top, TREE_MAX, 0.6)
        rgb = np.asarray(tree_green(self.rng), np.float32) * (1 - dark)
        win = self.cv.window(u - radius, u + radius, v - radius, v + radius)
        if win is None:
            return
        d2 = ((win.u - u) ** 2 + (win.v - v) ** 2) / np.float32(radius * radius)
        inside = d2 < 1.0
        bumps = self.bumps[win.rows, win.cols]
        h = crown(d2, base, top, bumps, TREE_MAX)
        albedo = rgb[:, None, None] * (1.0 + 0.15 * bumps)[None]
        self.cv.put(win, inside, h.astype(np.float32), TREE, CROWN, albedo, tuple(rgb * 0.75))

    def car(self, u: float, v: float, along_u: bool) -> None:
        """A parked car (1.8 × 4.5 m, 1.4–1.8 m high); the map keeps the road's label under it."""
        rng = self.rng
        hu, hv = (2.25, 0.9) if along_u else (0.9, 2.25)
        hit = self.cv.rect(u - hu, u + hu, v - hv, v + hv)
        if hit is None:
            return
        win, inside = hit
        rgb = np.asarray(jitter(rng, CAR_COLOURS[int(rng.integers(len(CAR_COLOURS)))], 6.0), np.float32)
        along = np.abs(win.u - u) / hu if along_u else np.abs(win.v - v) / hv
        glass = (along > 0.25) & (along < 0.55)  # windscreens: darker bands across the car
        albedo = rgb[:, None, None] * np.where(glass, np.float32(0.35), np.float32(1.0))[None]
        self.cv.put(win, inside, float(rng.uniform(1.4, 1.8)), None, CAR, albedo, tuple(rgb * 0.6))

    def car_rows(self, u0: float, u1: float, v0: float, v1: float, fill: float) -> None:
        """Rows of parking stalls (white lines) across [u0, u1] × [v0, v1], a share ``fill`` occupied."""
        rng = self.rng
        v = v0 + 1.0
        while v + 5.0 <= v1:
            hit = self.cv.rect(u0, u1, v, v + 5.0)
            if hit is not None:
                win, inside = hit
                lines = inside & (np.mod(win.u - u0, 2.6) < 0.12 + 0.5 * self.cv.gsd)
                self.cv.paint(win, lines, ROAD, MARKING, np.asarray(MARKING_RGB, np.float32)[:, None, None])
            for s in np.arange(u0 + 1.3, u1 - 1.3, 2.6):
                if rng.random() < fill:
                    self.car(float(s), v + 2.5, along_u=False)
            v += 5.0 if (v - v0) % 13.0 < 5.0 else 8.0  # two rows back to back, then an aisle



def hall_block(b: Blocks, u0: float, u1: float, v0: float, v1: float) -> None:
    """Industrial: one to three large halls (6–28 m) with flat roofs, often like the yard around them."""
    rng = b.rng
    yard = b.paved()
    b.ground(u0, u1, v0, v1, yard)
    placed: list[tuple[float, float, float, float]] = []
    for _ in range(int(rng.integers(1, 4))):
        w, d = min(rng.uniform(30, 150), u1 - u0 - 6), min(rng.uniform(20, 90), v1 - v0 - 6)
        if w < 12 or d < 12:
            break
        cu, cv = span(rng, u0 + 3, u1 - 3 - w), span(rng, v0 + 3, v1 - 3 - d)
        if any(cu < p[1] + 5 and cu + w > p[0] - 5 and cv < p[3] + 5 and cv + d > p[2] - 5 for p in placed):
            continue
        placed.append((cu, cu + w, cv, cv + d))
        height = rng.uniform(15, 28) if rng.random() < 0.35 else rng.uniform(6, 15)
        mat, rgb, textured = b.flat_roof(yard)
        b.box(cu, cu + w, cv, cv + d, height, mat, rgb, jitter(rng, FACADES[int(rng.integers(len(FACADES)))], 10.0),
              textured)
        if rng.random() < 0.3:  # skylight strips along the hall
            for s in np.arange(cu + 4, cu + w - 4, rng.uniform(6, 12)):
                glass = jitter(rng, (120, 140, 160), 10.0)
                b.box(float(s), float(s) + 1.5, cv + 3, cv + d - 3, height + 0.4, METAL, glass, glass)
        b.rooftop_plant(cu, cu + w, cv, cv + d, height)
    if rng.random() < 0.6:
        b.car_rows(u0 + 2, min(u1 - 2, u0 + rng.uniform(20, 60)), v0 + 2, min(v1 - 2, v0 + rng.uniform(12, 40)),
                   rng.uniform(0.3, 0.9))


def tower_block(b: Blocks, u0: float, u1: float, v0: float, v1: float) -> None:
    """Downtown: one to three towers of 25–60 m, some on a podium, on a paved plaza."""
    rng = b.rng
    plaza = Ground(CONCRETE, ROAD, jitter(rng, (176, 172, 164), 12.0)) if rng.random() < 0.6 else b.paved()
    b.ground(u0, u1, v0, v1, plaza)
    for _ in range(int(rng.integers(1, 4))):
        w, d = min(rng.uniform(15, 40), u1 - u0 - 4), min(rng.uniform(15, 40), v1 - v0 - 4)
        if w < 8 or d < 8:
            break
        cu, cv = span(rng, u0 + 2, u1 - 2 - w), span(rng, v0 + 2, v1 - 2 - d)
        height = float(rng.triangular(25, 30, BUILDING_MAX))
        facade = jitter(rng, FACADES[int(rng.integers(len(FACADES)))], 10.0)
        if rng.random() < 0.5:  # podium
            m = rng.uniform(3, 8)
            mat, rgb, textured = b.flat_roof(plaza)
            b.box(max(u0, cu - m), min(u1, cu + w + m), max(v0, cv - m), min(v1, cv + d + m),
                  rng.uniform(5, 12), mat, rgb, facade, textured)
        mat, rgb, textured = b.flat_roof(plaza)
        b.box(cu, cu + w, cv, cv + d, height, mat, rgb, facade, textured)
        b.rooftop_plant(cu, cu + w, cv, cv + d, height)
    for _ in range(int(rng.integers(0, 4))):
        b.tree(rng.uniform(u0, u1), rng.uniform(v0, v1), rng.uniform(2, 4), rng.uniform(6, 12))


def midrise_block(b: Blocks, u0: float, u1: float, v0: float, v1: float) -> None:
    """Perimeter block: flat-roofed buildings of 8–25 m along the edges around a courtyard."""
    rng = b.rng
    yard = b.paved() if rng.random() < 0.6 else Ground(GRASS, LOW_VEGETATION, jitter(rng, GRASS_RGB, 10.0))
    b.ground(u0, u1, v0, v1, yard)
    depth = rng.uniform(10, 18)
    height = rng.uniform(8, 25)
    facade = jitter(rng, FACADES[int(rng.integers(len(FACADES)))], 10.0)
    edges = [(u0, u1, v0, v0 + depth), (u0, u1, v1 - depth, v1), (u0, u0 + depth, v0, v1), (u1 - depth, u1, v0, v1)]
    for e in edges:
        if rng.random() < 0.8:
            mat, rgb, textured = b.flat_roof(yard)
            b.box(*e, height * rng.uniform(0.85, 1.15), mat, rgb, facade, textured)
    for _ in range(int(rng.integers(0, 4))):
        b.tree(span(rng, u0 + depth, u1 - depth), span(rng, v0 + depth, v1 - depth), rng.uniform(2, 5),
               rng.uniform(5, 14))


def residential_block(b: Blocks, u0: float, u1: float, v0: float, v1: float) -> None:
    """Houses with gable roofs (3–12 m), sheds (2.5–4 m), lawns, driveways and garden trees."""
    rng = b.rng
    b.ground(u0, u1, v0, v1, Ground(GRASS, LOW_VEGETATION, jitter(rng, GRASS_RGB, 10.0)))
    for row_v0, row_v1 in ((v0, min(v1, v0 + 30)), (max(v0, v1 - 30), v1)) if v1 - v0 > 40 else ((v0, v1),):
        u = u0
        while u < u1 - 8:
            lot = min(rng.uniform(12, 22), u1 - u)
            w, d = min(lot - 3, rng.uniform(8, 14)), min(row_v1 - row_v0 - 6, rng.uniform(8, 12))
            if w >= 6 and d >= 6:
                hv = row_v0 + 3 if row_v0 == v0 else row_v1 - 3 - d
                facade = jitter(rng, FACADES[int(rng.integers(len(FACADES)))], 10.0)
                rgb = jitter(rng, ROOF_TILES[int(rng.integers(len(ROOF_TILES)))], 8.0)
                rise = 0.5 * min(w, d) * math.tan(math.radians(rng.uniform(25, 45)))
                b.gable(u + 1.5, u + 1.5 + w, hv, hv + d, rng.uniform(3, 7), rise, rgb, facade)
                drive = Ground(*GROUND_LIKE[int(rng.choice([3, 5, 0]))])
                b.ground(u + 1.5 + w, min(u + lot, u + 4.5 + w), row_v0, row_v1, drive)
                if rng.random() < 0.4:  # garden shed
                    su, sv = u + rng.uniform(1, max(1.5, lot - 5)), (row_v0 + row_v1) / 2
                    shed = jitter(rng, (120, 110, 100), 20.0)
                    b.box(su, su + rng.uniform(2.5, 4), sv, sv + rng.uniform(2, 3.5), rng.uniform(2.5, 4), DARK, shed,
                          shed)
            for _ in range(rng.poisson(1.2)):
                b.tree(u + rng.uniform(0, lot), rng.uniform(row_v0, row_v1), rng.uniform(2, 4.5), rng.uniform(4, 14))
            u += lot


def parking_block(b: Blocks, u0: float, u1: float, v0: float, v1: float) -> None:
    """An asphalt car park with rows of cars and tree islands."""
    rng = b.rng
    b.ground(u0, u1, v0, v1, Ground(*GROUND_LIKE[int(rng.integers(0, 3))]))
    b.car_rows(u0 + 1, u1 - 1, v0 + 1, v1 - 1, rng.uniform(0.2, 0.95))
    for _ in range(int(rng.integers(0, 5))):
        b.tree(rng.uniform(u0, u1), rng.uniform(v0, v1), rng.uniform(2, 4), rng.uniform(5, 12))


def stadium_block(b: Blocks, u0: float, u1: float, v0: float, v1: float) -> None:
    """A pitch ringed by tiered stands rising outwards to 15–40 m, sometimes with a roof over the top rows."""
    rng = b.rng
    b.ground(u0, u1, v0, v1, b.paved())
    uc, vc = (u0 + u1) / 2, (v0 + v1) / 2
    band = rng.uniform(15, 40)
    a = max(10.0, (u1 - u0) / 2 - band - 3) * rng.uniform(0.6, 1.0)
    c = max(8.0, (v1 - v0) / 2 - band - 3) * rng.uniform(0.6, 1.0)
    b.ground(uc - a, uc + a, vc - c, vc + c, Ground(GRASS, LOW_VEGETATION, jitter(rng, (70, 130, 60), 8.0)))
    win = b.cv.window(uc - a - band, uc + a + band, vc - c - band, vc + c + band)
    if win is None:
        return
    du, dv = np.maximum(np.abs(win.u - uc) - a, 0), np.maximum(np.abs(win.v - vc) - c, 0)
    dist = np.hypot(du, dv) if rng.random() < 0.5 else np.maximum(du, dv)
    inside = (dist > 0) & (dist < band)
    top, low = rng.uniform(15, 40), rng.uniform(1.5, 4)
    tier = rng.uniform(0.8, 1.2)
    steps = np.floor(dist / tier)
    h = low + (top - low) * np.minimum(steps * tier / band, 1.0)
    seat, concrete = np.asarray(jitter(rng, CAR_COLOURS[int(rng.integers(len(CAR_COLOURS)))], 20.0)), 175.0
    albedo = np.where((steps % 2 == 0)[None], seat[:, None, None], np.float32(concrete)).astype(np.float32)
    facade = jitter(rng, (170, 168, 160), 10.0)
    b.cv.put(win, inside, h.astype(np.float32), BUILDING, SEATS, albedo, facade)
    if rng.random() < 0.5:  # a roof canopy over the outer rows
        canopy = inside & (dist > band * rng.uniform(0.5, 0.8))
        mat, rgb = ROOF_OTHER[int(rng.integers(len(ROOF_OTHER)))]
        b.cv.put(win, canopy, float(min(BUILDING_MAX, top + rng.uniform(2, 6))), BUILDING, mat,
                 np.asarray(jitter(rng, rgb, 10.0), np.float32)[:, None, None], facade)


def park_block(b: Blocks, u0: float, u1: float, v0: float, v1: float) -> None:
    """Grass, a gravel path, sometimes a pond, and scattered trees."""
    rng = b.rng
    b.ground(u0, u1, v0, v1, Ground(GRASS, LOW_VEGETATION, jitter(rng, GRASS_RGB, 10.0)))
    if rng.random() < 0.5:
        ru, rv = (u1 - u0) * rng.uniform(0.15, 0.35), (v1 - v0) * rng.uniform(0.15, 0.35)
        pu, pv = span(rng, u0 + ru, u1 - ru), span(rng, v0 + rv, v1 - rv)
        win = b.cv.window(pu - ru, pu + ru, pv - rv, pv + rv)
        if win is not None:
            pond = ((win.u - pu) / ru) ** 2 + ((win.v - pv) / rv) ** 2 < 1.0
            water = np.asarray(jitter(rng, (36, 60, 78), 10.0), np.float32)[:, None, None]
            b.cv.paint(win, pond, WATER, WATER_M, water)
    if rng.random() < 0.5:
        vm = rng.uniform(v0, v1)
        b.ground(u0, u1, vm - 1.2, vm + 1.2, Ground(GRAVEL, BARE_SOIL, jitter(rng, GRAVEL_RGB, 10.0)))
    for _ in range(int((u1 - u0) * (v1 - v0) * rng.uniform(0.002, 0.008))):
        r = rng.uniform(2.5, 6.5)
        b.tree(rng.uniform(u0, u1), rng.uniform(v0, v1), r, r * rng.uniform(2.0, 3.2) + rng.uniform(0, 4))


def forest_block(b: Blocks, u0: float, u1: float, v0: float, v1: float) -> None:
    """A closed forest of 4–30 m trees."""
    rng = b.rng
    b.ground(u0, u1, v0, v1, Ground(SOIL, BARE_SOIL, jitter(rng, (110, 100, 70), 10.0)))
    for u, v, radius, top, dark in forest_trees(rng, u0, u1, v0, v1, 4.2, 0.25):
        b.tree(u, v, radius, top, dark)


def bare_block(b: Blocks, u0: float, u1: float, v0: float, v1: float) -> None:
    """A construction site or fallow lot: soil and gravel, a few sheds."""
    rng = b.rng
    b.ground(u0, u1, v0, v1, Ground(SOIL if rng.random() < 0.5 else GRAVEL, BARE_SOIL,
                                    jitter(rng, SOIL_RGB, 15.0)))
    for _ in range(int(rng.integers(0, 4))):
        su, sv = span(rng, u0, u1 - 6), span(rng, v0, v1 - 3)
        shed = jitter(rng, (200, 200, 200), 30.0)
        b.box(su, su + rng.uniform(3, 6), sv, sv + rng.uniform(2.4, 3), rng.uniform(2.5, 3.2), METAL, shed, shed)


#: block kinds and their probabilities
KINDS = {
    "hall": (hall_block, 0.22), "tower": (tower_block, 0.12), "midrise": (midrise_block, 0.14),
    "residential": (residential_block, 0.14), "parking": (parking_block, 0.10), "stadium": (stadium_block, 0.06),
    "park": (park_block, 0.10), "forest": (forest_block, 0.07), "bare": (bare_block, 0.05),
}

__all__ = ["Blocks", "Ground", "KINDS", "ROAD", "SEATS"]
