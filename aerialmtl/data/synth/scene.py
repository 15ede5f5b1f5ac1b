"""Procedural town layout: terrain, roads, blocks of houses, commercial lots, parks, forests, fields.

The town is one style of the synthetic generator, the city (:mod:`~aerialmtl.data.synth.city`) the other:
both plan in metres in a frame rotated by a seeded angle from the image axes and draw on a
:class:`~aerialmtl.data.synth.canvas.Canvas` (its frame, pixel conventions and "highest surface wins" rule),
lay a street grid (:mod:`~aerialmtl.data.synth.streets`), colour with the shared materials
(:mod:`~aerialmtl.data.synth.materials`) and are lit by the same sun (:mod:`~aerialmtl.data.synth.shading`).
The town's own parts: gentle terrain, ground covers as a material raster, objects rasterised one by one with
:func:`skimage.draw.polygon` / :func:`skimage.draw.disk`, so that the label of every pixel is the class of
the surface a camera looking straight down would see, and its nDSM is that surface's height above ground.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from shapely.geometry import Point, Polygon, box
from shapely.ops import unary_union
from skimage.draw import disk

from aerialmtl.data.synth import streets
from aerialmtl.data.synth.canvas import Canvas
from aerialmtl.data.synth.materials import (
    ASPHALT_RGB,
    BARE_SOIL,
    BUILDING,
    GRASS_RGB,
    GRASS_TEXTURE,
    GRAVEL_RGB,
    LOW_VEGETATION,
    MARKING_RGB,
    ROAD,
    SOIL_RGB,
    SOIL_TEXTURE,
    TILE_REDS,
    TREE,
    WATER,
    WATER_TEXTURE,
    Rgb,
    Texture,
    jitter,
    texture_table,
    texture_terms,
    tree_green,
)
from aerialmtl.data.synth.noise import smooth_noise
from aerialmtl.data.synth.scene_parts import Building, BuildingTruth, RoofPart, Scene, TreeSpec
from aerialmtl.data.synth.shapes import crown, crown_size, forest_trees, gable, tile_rows

# The town's ground materials (index into the tables below).
GRASS, SOIL, FIELD, ASPHALT, MARKING, POND, GRAVEL = range(7)
_COVER_LABEL = np.array([LOW_VEGETATION, BARE_SOIL, BARE_SOIL, ROAD, ROAD, WATER, BARE_SOIL], np.uint8)
# base colour (R, G, B) in DN and texture amplitudes; the town's asphalt, markings and gravel are its own
_COVER_RGB = np.array([GRASS_RGB, SOIL_RGB, (128, 100, 72), ASPHALT_RGB, MARKING_RGB, (32, 56, 78), GRAVEL_RGB],
                      np.float32)
_COVER_TEX = texture_table((GRASS_TEXTURE, SOIL_TEXTURE, Texture(0.06, 0.05, 6.0), Texture(0.05, 0.07, 6.0),
                            Texture(0.0, 0.03, 5.0), WATER_TEXTURE, Texture(0.05, 0.06, 8.0)))
_DRY_GRASS = np.array([150, 150, 88], np.float32)

_ROOF_TILES: tuple[Rgb, ...] = (*TILE_REDS, (160, 82, 70))
_ROOF_GREY: tuple[Rgb, ...] = ((118, 118, 124), (150, 148, 146), (104, 110, 118))
_ROOF_DARK: tuple[Rgb, ...] = ((60, 60, 68), (74, 70, 70), (52, 56, 62))
_ROOF_FLAT: tuple[Rgb, ...] = ((176, 174, 168), (196, 190, 178), (88, 88, 94), (142, 142, 136), (160, 150, 140))
#: The town's tallest tree, metres.
TREE_MAX = 25.0
#: The town's streets: 6–12 m wide, 45–110 m apart.
TOWN_STREETS = streets.StreetSpacing(spacing=(45, 110), width=(6, 12), lead=40, tail=60)


class _Canvas(Canvas):
    """The town's canvas: the shared arrays plus the surface colour (``albedo``, float32 (3, N, N) DN)."""

    def __init__(self, size: int, gsd: float, theta: float) -> None:
        super().__init__(size, gsd, theta)
        self.albedo = np.zeros((3, *self.shape), np.float32)

    def put(self, rr: np.ndarray, cc: np.ndarray, h: np.ndarray, code: int, rgb: np.ndarray) -> None:
        """Draw an object: where ``h`` is above the current surface it becomes the visible surface."""
        top, rt, ct = self.raise_top(rr, cc, h, code)
        self.albedo[:, rt, ct] = rgb[:, top]


class _Planner:
    """Draws random town content block by block (all sizes in metres)."""

    def __init__(self, canvas: _Canvas, rng: np.random.Generator, scene_poly: Polygon) -> None:
        self.cv = canvas
        self.rng = rng
        self.scene_poly = scene_poly
        self.cover = np.full(canvas.shape, GRASS, np.uint8)
        self.buildings: list[Building] = []
        self.trees: list[TreeSpec] = []
        self.ponds: list[tuple[np.ndarray, np.ndarray]] = []

    # ---- helpers --------------------------------------------------------------------------------
    def cover_rect(self, u0: float, u1: float, v0: float, v1: float, material: int) -> None:
        rr, cc = self.cv.fill_rect(u0, u1, v0, v1)
        self.cover[rr, cc] = material

    def tree(self, u: float, v: float, radius: float, top: float, dark: float = 0.0) -> None:
        top, base = crown_size(self.rng, top, TREE_MAX, 0.55)
        rgb = tree_green(self.rng)
        rgb = (rgb[0] * (1.0 - dark), rgb[1] * (1.0 - dark), rgb[2] * (1.0 - dark))
        self.trees.append(TreeSpec(u, v, radius, top, base, rgb))

    def visible(self, u0: float, u1: float, v0: float, v1: float) -> Polygon:
        return box(u0, v0, u1, v1).intersection(self.scene_poly)

    def random_point(self, region: Polygon, tries: int = 30) -> tuple[float, float] | None:
        if region.is_empty:
            return None
        a0, b0, a1, b1 = region.bounds
        for _ in range(tries):
            u, v = self.rng.uniform(a0, a1), self.rng.uniform(b0, b1)
            if region.contains(Point(u, v)):
                return u, v
        pt = region.representative_point()
        return pt.x, pt.y

    # ---- block types ----------------------------------------------------------------------------
    def residential(self, u0: float, u1: float, v0: float, v1: float) -> None:
        rng = self.rng
        swap = (u1 - u0) < (v1 - v0)  # lots run along the longer side; work in (a, b) = long, short
        a0, a1, b0, b1 = (v0, v1, u0, u1) if swap else (u0, u1, v0, v1)

        def uv(a: float, b: float) -> tuple[float, float]:
            return (b, a) if swap else (a, b)

        def rect(pa0: float, pa1: float, pb0: float, pb1: float) -> tuple[float, float, float, float]:
            (x0, y0), (x1, y1) = uv(pa0, min(pb0, pb1)), uv(pa1, max(pb0, pb1))
            return (min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1))

        depth = b1 - b0
        rows = [(b0, 1.0, depth / 2), (b1, -1.0, depth / 2)] if depth >= 34 else [(b0, 1.0, depth)]
        for street, sign, lot_depth in rows:
            a = a0
            while a < a1 - 6:
                lot_w = min(rng.uniform(12, 22), a1 - a)
                self._house_lot(a, a + lot_w, street, sign, lot_depth, rect, uv)
                a += lot_w

    def _house_lot(self, la0: float, la1: float, street: float, sign: float, depth: float,
                   rect: Callable[[float, float, float, float], tuple[float, float, float, float]],
                   uv: Callable[[float, float], tuple[float, float]]) -> None:
        rng = self.rng
        lot_w = la1 - la0
        setback = rng.uniform(3, 6)
        wh = min(lot_w - 2 * rng.uniform(1.5, 3.0), rng.uniform(8, 16))
        dh = min(rng.uniform(8, 13), depth - setback - 3)
        if wh >= 8 and dh >= 8:
            ca = rng.uniform(la0 + (lot_w - wh) / 2 - 1, la0 + (lot_w - wh) / 2 + 1)
            ca = float(np.clip(ca, la0 + 1, la1 - wh - 1))
            s0, s1 = setback, setback + dh
            parts_ab = [(ca, ca + wh, s0, s1)]
            back_room = depth - s1 - 2
            if rng.random() < 0.35 and back_room > 3 and wh >= 12:
                ww = rng.uniform(8, max(8.0, 0.6 * wh))
                ext = min(rng.uniform(4, 9), back_room)
                wa0 = ca if rng.random() < 0.5 else ca + wh - ww
                parts_ab.append((wa0, wa0 + ww, s0 + dh * 0.5, s1 + ext))
            flat = rng.random() < 0.2
            eave = rng.uniform(3.0, 7.0)
            pitch = math.radians(rng.uniform(25, 45))
            parts = []
            for pa0, pa1, ps0, ps1 in parts_ab:
                x0, x1, y0, y1 = rect(pa0, pa1, street + sign * ps0, street + sign * ps1)
                half = min(x1 - x0, y1 - y0) / 2
                kind = "flat" if flat else "gable"
                parts.append(RoofPart(x0, x1, y0, y1, kind, eave, 0.0 if flat else half * math.tan(pitch)))
            roll = rng.random()
            if flat:
                color, textured = _ROOF_FLAT[rng.integers(len(_ROOF_FLAT))], False
            elif roll < 0.6:
                color, textured = _ROOF_TILES[rng.integers(len(_ROOF_TILES))], True
            elif roll < 0.85:
                color, textured = _ROOF_GREY[rng.integers(len(_ROOF_GREY))], True
            else:
                color, textured = _ROOF_DARK[rng.integers(len(_ROOF_DARK))], False
            self.buildings.append(Building(tuple(parts), jitter(rng, color, 8.0), textured))
            if rng.random() < 0.5:  # gravel driveway from the street to the house
                side = ca - 3.5 if ca - 3.5 > la0 + 0.3 else ca + wh + 0.5
                if side + 3 < la1:
                    g0, g1, g2, g3 = rect(side, side + 3, street, street + sign * setback)
                    self.cover_rect(g0, g1, g2, g3, GRAVEL)
            yard0 = s1 + 1
        else:
            yard0 = 2.0
        if rng.random() < 0.3 and depth - yard0 > 5:  # vegetable patch / bare garden
            pa = rng.uniform(la0 + 1, max(la0 + 1, la1 - 7))
            ps = rng.uniform(yard0, depth - 4)
            s0, s1_, s2, s3 = rect(pa, min(la1 - 0.5, pa + rng.uniform(4, 8)), street + sign * ps,
                                   street + sign * min(depth - 0.5, ps + rng.uniform(3, 6)))
            self.cover_rect(s0, s1_, s2, s3, SOIL)
        for _ in range(rng.poisson(1.3)):
            radius = rng.uniform(2.0, 4.5)
            if depth - yard0 < 1.0:
                break
            ps = rng.uniform(yard0 + 0.5 * radius, max(yard0 + 0.5 * radius, depth - 0.5 * radius))
            pa = rng.uniform(la0 + 0.5, la1 - 0.5)
            tu, tv = uv(pa, street + sign * ps)
            self.tree(tu, tv, radius, rng.uniform(4, 14))

    def commercial(self, u0: float, u1: float, v0: float, v1: float, paved: bool) -> None:
        rng = self.rng
        if paved:
            self.cover_rect(u0, u1, v0, v1, GRAVEL if rng.random() < 0.3 else SOIL)
        placed: list[Polygon] = []
        for _ in range(14):
            if len(placed) >= 3:
                break
            w = min(rng.uniform(15, 40), u1 - u0 - 6)
            d = min(rng.uniform(15, 40), v1 - v0 - 6)
            if w < 10 or d < 10:
                break
            cu = rng.uniform(u0 + 3, max(u0 + 3, u1 - 3 - w))
            cvv = rng.uniform(v0 + 3, max(v0 + 3, v1 - 3 - d))
            fp = box(cu, cvv, cu + w, cvv + d)
            if any(fp.buffer(4).intersects(p) for p in placed):
                continue
            placed.append(fp)
            height = rng.uniform(18, 40) if rng.random() < 0.3 else rng.uniform(5, 14)
            parts = [RoofPart(cu, cu + w, cvv, cvv + d, "flat", height)]
            for _ in range(rng.integers(0, 5)):  # rooftop plant rooms / air handlers
                bw, bd = rng.uniform(2, 5), rng.uniform(2, 5)
                if w < bw + 3 or d < bd + 3:
                    continue
                bu, bv = rng.uniform(cu + 1, cu + w - bw - 1), rng.uniform(cvv + 1, cvv + d - bd - 1)
                parts.append(RoofPart(bu, bu + bw, bv, bv + bd, "flat", min(40.0, height + rng.uniform(1, 3))))
            roof = jitter(rng, _ROOF_FLAT[rng.integers(len(_ROOF_FLAT))], 12.0)
            self.buildings.append(Building(tuple(parts), roof, False))
        if rng.random() < 0.5:
            self._tree_row(u0, u1, v0 + 2.5, along_u=True)

    def park(self, u0: float, u1: float, v0: float, v1: float, pond: bool) -> None:
        rng = self.rng
        pond_poly = None
        if pond:
            c = self.random_point(self.visible(u0 + 6, u1 - 6, v0 + 6, v1 - 6))
            if c is not None:
                rx = min(rng.uniform(6, 20), 0.4 * (u1 - u0))
                ry = min(rng.uniform(6, 20), 0.4 * (v1 - v0))
                ang = np.linspace(0, 2 * np.pi, 32, endpoint=False)
                wob = 1 + 0.12 * np.sin(ang * rng.integers(2, 5) + rng.uniform(0, 6)) + rng.normal(0, 0.03, 32)
                pu, pv = c[0] + rx * wob * np.cos(ang), c[1] + ry * wob * np.sin(ang)
                rr, cc = self.cv.fill(pu, pv)
                self.cover[rr, cc] = POND
                self.ponds.append((rr, cc))
                pond_poly = Polygon(np.c_[pu, pv]).buffer(1.5)
        if rng.random() < 0.5 and v1 - v0 > 12:  # a footpath across the park
            vm = rng.uniform(v0 + 5, v1 - 5)
            self.cover_rect(u0, u1, vm - 1.2, vm + 1.2, GRAVEL)
        area = (u1 - u0) * (v1 - v0)
        for _ in range(int(area * rng.uniform(0.003, 0.008))):
            cu, cvv = rng.uniform(u0, u1), rng.uniform(v0, v1)
            radius = rng.uniform(2.5, 6.5)
            if pond_poly is not None and pond_poly.distance(Point(cu, cvv)) < radius:
                continue
            self.tree(cu, cvv, radius, radius * rng.uniform(2.0, 3.2) + rng.uniform(0, 3))

    def forest(self, u0: float, u1: float, v0: float, v1: float) -> None:
        for u, v, radius, top, dark in forest_trees(self.rng, u0, u1, v0, v1, 3.4, 0.2):
            self.tree(u, v, radius, top, dark)

    def field(self, u0: float, u1: float, v0: float, v1: float, ploughed: bool) -> None:
        if ploughed:
            self.cover_rect(u0 + 1, u1 - 1, v0 + 1, v1 - 1, FIELD)

    def _tree_row(self, u0: float, u1: float, fixed: float, along_u: bool) -> None:
        rng = self.rng
        spacing = rng.uniform(8, 14)
        for pos in streets.positions_along(rng, u0, u1, spacing, 2.0):
            radius = rng.uniform(2.0, 4.0)
            u, v = (pos, fixed) if along_u else (fixed, pos)
            self.tree(u, v, radius, rng.uniform(5, 13))

    def street_trees(self, u0: float, u1: float, v0: float, v1: float, verge: float) -> None:
        if (u1 - u0) >= (v1 - v0):
            self._tree_row(u0, u1, v0 + verge / 2, along_u=True)
            self._tree_row(u0, u1, v1 - verge / 2, along_u=True)
        else:
            self._tree_row(v0, v1, u0 + verge / 2, along_u=False)
            self._tree_row(v0, v1, u1 - verge / 2, along_u=False)


def build_scene(size: int, gsd: float, rng: np.random.Generator) -> Scene:
    """Plan and rasterise a random town of ``size`` × ``size`` pixels of ``gsd`` metres.

    Args:
        size: raster width and height in pixels.
        gsd: pixel size in metres.
        rng: the scene's random generator (all randomness comes from it, in a fixed order).

    Returns:
        A :class:`Scene` (terrain, nDSM, labels, albedo, sun angles).

    The steps below draw from ``rng`` in this order, which a seed's town depends on (tests/test_synth.py
    pins a hash of one): frame and sun, street lines, blocks, terrain, ground textures. Roads and objects
    draw nothing.
    """
    extent = size * gsd
    theta = 0.0 if rng.random() < 0.3 else math.radians(rng.uniform(-25, 25))
    sun_azimuth = float(rng.uniform(110, 250))
    sun_elevation = float(rng.uniform(35, 55))
    cv = _Canvas(size, gsd, theta)
    corners_u, corners_v = cv.to_frame(np.array([0, extent, extent, 0]), np.array([0, 0, extent, extent]))
    scene_poly = Polygon(np.c_[corners_u, corners_v])
    lines_u = streets.street_lines(rng, corners_u.min(), corners_u.max(), TOWN_STREETS)
    lines_v = streets.street_lines(rng, corners_v.min(), corners_v.max(), TOWN_STREETS)
    plan = _Planner(cv, rng, scene_poly)
    stats = _plan_blocks(plan, lines_u, lines_v)
    _paint_roads(cv, plan.cover, lines_u, lines_v)
    dtm = _terrain(rng, cv.centres(), extent)
    for rr, cc in plan.ponds:
        if rr.size:
            dtm[rr, cc] = dtm[rr, cc].min()
    tex_small, tex_mid, fine = _ground_covers(cv, plan.cover, cv.u, rng)
    truths = []
    for bld in plan.buildings:
        drawn = _draw_building(cv, bld, tex_small, fine)
        truth = _building_truth(cv, bld, drawn, box(0.0, 0.0, extent, extent))
        if truth is not None:
            truths.append(truth)
    for tr in plan.trees:
        _draw_tree(cv, tr, tex_small, tex_mid, fine)
    stats.update(buildings=len(plan.buildings), trees=len(plan.trees), ponds=len(plan.ponds))
    np.clip(cv.albedo, 0, 255, out=cv.albedo)
    return Scene(dtm, cv.ndsm, cv.labels, cv.albedo, sun_azimuth, sun_elevation, gsd, stats, truths)


def _plan_blocks(plan: _Planner, lines_u: streets.Family, lines_v: streets.Family) -> dict[str, int]:
    """Give every block between the streets a kind and plan its content; returns blocks per kind."""
    rng, scene_poly = plan.rng, plan.scene_poly
    blocks = []
    for low_u, high_u, low_v, high_v in streets.blocks_between(lines_u, lines_v):
        b = (low_u.high, high_u.low, low_v.high, high_v.low)
        area = box(b[0], b[2], b[1], b[3]).intersection(scene_poly).area
        if area > 1.0:
            blocks.append((area, b))
    blocks.sort(key=lambda t: -t[0])
    mandatory = ["residential", "park", "commercial"]
    rng.shuffle(mandatory)
    kinds = ["residential", "commercial", "park", "forest", "field"]
    probs = [0.45, 0.2, 0.12, 0.13, 0.10]
    stats: dict[str, int] = {k: 0 for k in kinds}
    for i, (_, (u0, u1, v0, v1)) in enumerate(blocks):
        kind = mandatory[i] if i < len(mandatory) else kinds[rng.choice(len(kinds), p=probs)]
        stats[kind] += 1
        verge = rng.uniform(1.5, 3.5)
        iu0, iu1, iv0, iv1 = u0 + verge, u1 - verge, v0 + verge, v1 - verge
        if iu1 - iu0 < 8 or iv1 - iv0 < 8:
            continue
        if kind == "residential":
            plan.residential(iu0, iu1, iv0, iv1)
        elif kind == "commercial":
            plan.commercial(iu0, iu1, iv0, iv1, paved=i < len(mandatory) or rng.random() < 0.8)
        elif kind == "park":
            plan.park(iu0, iu1, iv0, iv1, pond=i < len(mandatory) or rng.random() < 0.6)
        elif kind == "forest":
            plan.forest(iu0, iu1, iv0, iv1)
        else:
            plan.field(iu0, iu1, iv0, iv1, ploughed=rng.random() < 0.6)
        if kind in ("residential", "commercial", "park") and rng.random() < (0.6 if kind == "residential" else 0.35):
            plan.street_trees(u0, u1, v0, v1, verge)
    return stats


def _paint_roads(cv: _Canvas, cover: np.ndarray, lines_u: streets.Family, lines_v: streets.Family) -> None:
    """Mark asphalt (and, at 0.5 m or finer, dashed centre lines) in ``cover``, vectorised over the grid."""
    field = streets.StreetField.measure(cv.u, cv.v, lines_u, lines_v)
    cover[field.on_u | field.on_v] = ASPHALT
    if cv.gsd <= 0.5:
        cover[field.centre_dashes(cv.u, cv.v, cv.gsd, field.on_u, field.on_v)] = MARKING


def _ground_covers(cv: _Canvas, cover: np.ndarray, u: np.ndarray,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Labels, grass heights and textured colours of the ground covers; returns the small, mid and fine noise."""
    gsd = cv.gsd
    tex_large = smooth_noise(cv.shape, 25.0 / gsd, rng)
    tex_mid = smooth_noise(cv.shape, max(1.0, 4.0 / gsd), rng)
    tex_small = smooth_noise(cv.shape, max(1.0, 0.8 / gsd), rng)
    fine = rng.standard_normal(cv.shape, dtype=np.float32)
    cv.labels[:] = _COVER_LABEL[cover]
    gain, add = texture_terms(_COVER_TEX[cover], tex_large, tex_mid, fine)
    grass = cover == GRASS
    dry = np.clip(0.5 + 0.6 * tex_large, 0, 1)[grass]
    field_px = cover == FIELD
    furrows = 1.0 + 0.14 * np.sin(2 * np.pi * u[field_px] / 1.6)
    for ch in range(3):
        base = _COVER_RGB[:, ch][cover]
        base[grass] = (1 - dry) * _COVER_RGB[GRASS, ch] + dry * _DRY_GRASS[ch]
        base[field_px] *= furrows
        cv.albedo[ch] = base * gain + add
    cv.ndsm[grass] = np.clip(0.22 + 0.15 * tex_mid[grass] + 0.05 * tex_small[grass], 0.0, 0.5)
    return tex_small, tex_mid, fine


def _terrain(rng: np.random.Generator, xs: np.ndarray, extent: float) -> np.ndarray:
    """Gentle terrain: a base elevation, a tilt of ≤ 1.2 % and four long sinusoids (metres)."""
    base = rng.uniform(30, 250)
    tx, ty = rng.uniform(-0.012, 0.012, 2)
    col = (base + tx * xs).astype(np.float32)
    row = (ty * xs).astype(np.float32)
    dtm = row[:, None] + col[None, :]
    for _ in range(4):
        lam = rng.uniform(120, 600)
        amp = rng.uniform(0.4, 1.5)
        ang = rng.uniform(0, 2 * np.pi)
        phase = rng.uniform(0, 2 * np.pi)
        kx, ky = 2 * np.pi / lam * math.cos(ang), 2 * np.pi / lam * math.sin(ang)
        # sin(kx·x + ky·y + φ) as a sum of two outer products (separable, no full-size trig)
        sx, cx = np.sin(kx * xs + phase), np.cos(kx * xs + phase)
        sy, cy = np.sin(ky * xs), np.cos(ky * xs)
        dtm += (amp * (cy[:, None] * sx[None, :] + sy[:, None] * cx[None, :])).astype(np.float32)
    result: np.ndarray = dtm
    return result


def _building_truth(cv: _Canvas, bld: Building, drawn: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                    scene_box: Polygon) -> BuildingTruth | None:
    """Footprint (scene metres, x east, y south) and roof statistics of ``bld`` from its drawn parts."""
    if not drawn:
        return None
    rr = np.concatenate([d[0] for d in drawn]).astype(np.int64)
    cc = np.concatenate([d[1] for d in drawn]).astype(np.int64)
    h = np.concatenate([d[2] for d in drawn])
    if rr.size == 0:
        return None
    pixel = rr * cv.n + cc
    order = np.lexsort((-h, pixel))  # per pixel, the highest part first: the roof surface
    first = np.concatenate([[True], pixel[order][1:] != pixel[order][:-1]])
    roof = h[order][first]
    parts = []
    for p in bld.parts:
        x, y = cv.from_frame(np.array([p.u0, p.u1, p.u1, p.u0]), np.array([p.v0, p.v0, p.v1, p.v1]))
        parts.append(Polygon(np.c_[x, y]))
    footprint = unary_union(parts).intersection(scene_box)
    if footprint.is_empty or not isinstance(footprint, Polygon):
        polys = [g for g in getattr(footprint, "geoms", []) if isinstance(g, Polygon)]
        if not polys:
            return None
        footprint = max(polys, key=lambda g: g.area)
    return BuildingTruth(footprint, float(np.median(roof)), float(roof.max()), int(roof.size))


def _draw_building(cv: _Canvas, bld: Building, tex_small: np.ndarray,
                   fine: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Draw ``bld``; returns (rows, cols, roof heights) of each part's pixels."""
    color = np.array(bld.color, np.float32)[:, None]
    drawn = []
    for part in bld.parts:
        rr, cc = cv.fill_rect(part.u0, part.u1, part.v0, part.v1)
        if rr.size == 0:
            continue
        u, v = cv.uv_of(rr, cc)
        texture = 1.0 + 0.05 * tex_small[rr, cc] + 0.03 * fine[rr, cc]
        if part.kind == "gable":
            h, across = gable(u, v, part.u0, part.u1, part.v0, part.v1, part.eave, part.rise)
            if bld.textured:
                texture = texture + tile_rows(across)
        else:
            h = np.full(rr.shape, part.eave, np.float32)
        cv.put(rr, cc, h.astype(np.float32), BUILDING, color * texture[None, :])
        drawn.append((rr, cc, h.astype(np.float32)))
    return drawn


def _draw_tree(cv: _Canvas, tr: TreeSpec, tex_small: np.ndarray, tex_mid: np.ndarray, fine: np.ndarray) -> None:
    rows, cols = cv.to_px(np.array([tr.u]), np.array([tr.v]))
    r, c = float(rows[0]), float(cols[0])
    rad_px = tr.radius / cv.gsd
    if r < -rad_px or c < -rad_px or r > cv.n + rad_px or c > cv.n + rad_px:
        return
    rr, cc = disk((r, c), rad_px, shape=cv.shape)
    if rr.size == 0:
        return
    d2 = ((rr - r) ** 2 + (cc - c) ** 2) * (cv.gsd / tr.radius) ** 2
    bumps = tex_small[rr, cc]
    h = crown(d2, tr.base, tr.top, bumps, TREE_MAX).astype(np.float32)
    color = np.array(tr.color, np.float32)[:, None]
    texture = 1.0 + 0.18 * bumps + 0.08 * tex_mid[rr, cc] + 0.06 * fine[rr, cc]
    cv.put(rr, cc, h, TREE, color * texture[None, :])
