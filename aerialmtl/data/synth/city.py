"""Synthetic cities for pretraining: :func:`sample_city` draws one patch in memory (no disk) from a seed.

A city teaches what a small real area cannot show: sheds to 60 m towers, large halls and tiered stadium
stands, and above all **large flat roofs made of what the ground around them is made of** (asphalt, gravel,
concrete, planted roofs), which only their shadows, walls and lean tell apart from a car park. Each scene
has its own sun (cast shadows consistent with the heights), its own camera lean (relief displacement of a
non-true orthophoto: roofs and upper walls drawn away from the nadir by ``height × tan(view angle)``, the
walls facing the nadir visible; the nDSM and labels stay at the true footprint, as lidar gives them), tree
rows, forests, water and cars, and its own sensor look (:class:`~aerialmtl.data.synth.style.CityStyle`).
Surfaces can wear textures cut from the user's own orthophoto where their nDSM is near 0
(:class:`~aerialmtl.data.synth.textures.TexturePool`), so the city looks like the user's area.

Labels are raw codes of the built-in ``synthetic`` class scheme (the one :func:`synthesize` uses: 1 bare
soil, 2 road, 3 building, 4 tree, 5 low vegetation, 6 water). Cars carry their height (1.4–1.8 m) in the
nDSM and keep the label of the ground they stand on.

The city is one style of the synthetic generator, the town (:mod:`~aerialmtl.data.synth.scene`) the other:
it draws on the same canvas, street grid, materials and sun (:mod:`~aerialmtl.data.synth.canvas`,
:mod:`~aerialmtl.data.synth.streets`, :mod:`~aerialmtl.data.synth.materials`,
:mod:`~aerialmtl.data.synth.shading`) with its own blocks (:mod:`~aerialmtl.data.synth.city_blocks`),
palette and imaging (:mod:`~aerialmtl.data.synth.style`).

Random streams: the layout (heights, labels), the imaging (sun, lean, sensor look, image noise) and the
textures each draw from their own generator seeded by ``(seed, stream)``, so changing the style or the
textures never changes the heights or labels of a seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from aerialmtl.data.synth import streets
from aerialmtl.data.synth.city_blocks import KINDS, Blocks
from aerialmtl.data.synth.city_canvas import (
    ASPHALT,
    CONCRETE,
    GRASS,
    GROUND_ROOFS,
    MARKING,
    TEXTURE,
    WATER_M,
    CityCanvas,
)
from aerialmtl.data.synth.materials import BUILDING, LOW_VEGETATION, ROAD, WATER, jitter, texture_terms
from aerialmtl.data.synth.noise import smooth_noise
from aerialmtl.data.synth.relief import relief_displacement
from aerialmtl.data.synth.shading import Sky, direct_sun, wall_sun
from aerialmtl.data.synth.style import CityStyle, Imaging, finish_image
from aerialmtl.data.synth.textures import Source, TexturePool
from aerialmtl.errors import InputError

#: Fraction of flat-ground brightness left in shadow, and the bluer sky light (:class:`~.shading.Sky`) of a city.
AMBIENT = 0.42
SKY = Sky(AMBIENT, (0.92, 0.98, 1.10))
#: The city's streets: 7–22 m wide, blocks of 50–170 m.
CITY_STREETS = streets.StreetSpacing(spacing=(50, 170), width=(7, 22), lead=120, tail=170)
#: Storey height drawn on walls (window bands), metres.
STOREY_M = 3.3
#: Smallest patch side accepted, pixels; GSD range accepted, metres.
MIN_CITY_SIZE = 16
GSD_RANGE = (0.05, 2.0)
_LAYOUT, _IMAGING, _TEXTURES = 0, 1, 2


@dataclass(frozen=True)
class CityPatch:
    """One synthetic city patch, north-up, ``size`` × ``size`` pixels of ``gsd`` metres.

    Attributes:
        image: uint8 (3, H, W) RGB orthophoto (non-true: tall things lean by ``imaging.lean_tan``).
        height: float32 (H, W) height of the top surface above ground in metres (nDSM, ≥ 0) at the true
            footprint: buildings 2.5–60 m, trees 3–30 m, cars ≤ 1.8 m, grass ≤ 0.3 m, other ground and water 0.
        classes: uint8 (H, W) raw codes of the ``synthetic`` class scheme (1–6, every pixel labelled).
        gsd: pixel size in metres.
        seed: the seed the patch was drawn from.
        imaging: the sun, lean and sensor look the image was made with.
    """

    image: np.ndarray
    height: np.ndarray
    classes: np.ndarray
    gsd: float
    seed: int
    imaging: Imaging


def _streams(seed: int) -> tuple[np.random.Generator, np.random.Generator, np.random.Generator]:
    """The layout, imaging and texture generators of ``seed`` (independent streams)."""
    layout, imaging, textures = (np.random.default_rng([int(seed) & 0xFFFFFFFFFFFF, k])
                                 for k in (_LAYOUT, _IMAGING, _TEXTURES))
    return layout, imaging, textures


def _lines(rng: np.random.Generator, lo: float, hi: float) -> streets.Family:
    """Parallel streets covering [lo, hi] (:data:`CITY_STREETS`); in 15 % of families one is a river of 15–50 m."""
    lines = streets.street_lines(rng, lo, hi, CITY_STREETS)
    if len(lines) > 2 and rng.random() < 0.15:
        i = int(rng.integers(1, len(lines) - 1))
        lines[i] = replace(lines[i], width=rng.uniform(15, 50), river=True)
    return lines


def _streets(cv: CityCanvas, rng: np.random.Generator, lines_u: streets.Family, lines_v: streets.Family,
             kerb: float) -> None:
    """Asphalt streets with dashed centre lines, concrete pavements, and rivers with grass banks."""
    asphalt = np.asarray(jitter(rng, (88, 88, 92), 10.0), np.float32)
    pavement = np.asarray(jitter(rng, (170, 168, 160), 10.0), np.float32)
    water = np.asarray(jitter(rng, (38, 62, 76), 10.0), np.float32)
    st = streets.StreetField.measure(cv.u, cv.v, lines_u, lines_v)
    river_u = np.array([ln.river for ln in lines_u], bool)[st.index_u]
    river_v = np.array([ln.river for ln in lines_v], bool)[st.index_v]
    off_u, half_u, off_v, half_v, on_u, on_v = st.off_u, st.half_u, st.off_v, st.half_v, st.on_u, st.on_v
    walk = ~(on_u | on_v) & ((np.abs(off_u) <= half_u + kerb) | (np.abs(off_v) <= half_v + kerb))
    road_u, road_v = on_u & ~river_u, on_v & ~river_v
    layers = ((walk, ROAD, CONCRETE, pavement), (road_u | road_v, ROAD, ASPHALT, asphalt))
    for mask, label, mat, rgb in layers:
        cv.labels[mask], cv.material[mask] = label, mat
        cv.tint[:, mask] = rgb[:, None]
    if cv.gsd <= 0.6:
        dash = st.centre_dashes(cv.u, cv.v, cv.gsd, road_u, road_v)
        cv.material[dash] = MARKING
        cv.tint[:, dash] = np.float32(212.0)
    wet = (on_u & river_u) | (on_v & river_v)
    cv.labels[wet], cv.material[wet] = WATER, WATER_M
    cv.tint[:, wet] = water[:, None]
    bank = ~wet & (((np.abs(off_u) <= half_u + kerb + 4) & river_u) | ((np.abs(off_v) <= half_v + kerb + 4) & river_v))
    cv.labels[bank], cv.material[bank] = LOW_VEGETATION, GRASS
    cv.tint[:, bank] = np.array([90, 124, 60], np.float32)[:, None]


def build_city(size: int, gsd: float, layout: np.random.Generator, texture_rng: np.random.Generator,
               texture: Source | None = None,
               ground_roofs: float = GROUND_ROOFS) -> tuple[CityCanvas, dict[str, int]]:
    """Plan and draw a city on a ``size`` × ``size`` canvas of ``gsd`` metres.

    Args:
        size: canvas side in pixels.
        gsd: pixel size in metres.
        layout: generator of everything that sets heights and labels.
        texture_rng: generator of the user texture choices.
        texture: optional texture source for surfaces.
        ground_roofs: probability that a flat roof is drawn in a ground material (:attr:`CityStyle.ground_roofs`).

    Returns:
        (canvas, counts of blocks per kind).
    """
    theta = 0.0 if layout.random() < 0.3 else math.radians(layout.uniform(-45, 45))
    cv = CityCanvas(size, gsd, theta, texture)
    bumps = smooth_noise(cv.ndsm.shape, max(1.0, 0.8 / gsd), layout, "smoothstep")
    lines_u = _lines(layout, float(cv.u.min()), float(cv.u.max()))
    lines_v = _lines(layout, float(cv.v.min()), float(cv.v.max()))
    kerb = layout.uniform(1.5, 4.0)
    _streets(cv, layout, lines_u, lines_v, kerb)
    blocks = Blocks(cv, layout, texture_rng, bumps, ground_roofs)
    names = list(KINDS)
    probs = np.array([KINDS[k][1] for k in names])
    stats = dict.fromkeys(names, 0)
    for low_u, high_u, low_v, high_v in streets.blocks_between(lines_u, lines_v):
        # a block stops at the kerb, and 4 m more from a river (its grass bank)
        u0, u1 = low_u.high + kerb + (4 if low_u.river else 0), high_u.low - kerb - (4 if high_u.river else 0)
        v0, v1 = low_v.high + kerb + (4 if low_v.river else 0), high_v.low - kerb - (4 if high_v.river else 0)
        kind = names[int(layout.choice(len(names), p=probs))]
        street_trees = layout.random() < 0.35
        if u1 - u0 < 12 or v1 - v0 < 12 or cv.window(u0, u1, v0, v1) is None:
            continue
        stats[kind] += 1
        KINDS[kind][0](blocks, u0, u1, v0, v1)
        if street_trees:
            _street_trees(blocks, u0, u1, v0, v1, kerb)
    grass = (cv.material == GRASS) & (cv.labels == LOW_VEGETATION) & (cv.ndsm < 0.5)
    cv.ndsm[grass] = np.clip(0.1 + 0.08 * bumps[grass], 0.0, 0.3)
    return cv, stats


def _street_trees(b: Blocks, u0: float, u1: float, v0: float, v1: float, kerb: float) -> None:
    """Rows of trees along the block's four edges, over the pavement."""
    spacing = b.rng.uniform(7, 13)
    for along_u, lo, hi, fixed in ((True, u0, u1, v0 - kerb / 2), (True, u0, u1, v1 + kerb / 2),
                                   (False, v0, v1, u0 - kerb / 2), (False, v0, v1, u1 + kerb / 2)):
        for pos in streets.positions_along(b.rng, lo, hi, spacing, 1.0):
            u, v = (pos, fixed) if along_u else (fixed, pos)
            b.tree(u, v, b.rng.uniform(2.0, 4.0), b.rng.uniform(5, 14))


def _albedo(cv: CityCanvas, rng: np.random.Generator) -> np.ndarray:
    """Surface colour with material textures: float32 (3, N, N) DN."""
    large = smooth_noise(cv.ndsm.shape, 25.0 / cv.gsd, rng, "smoothstep")
    mid = smooth_noise(cv.ndsm.shape, max(1.0, 3.0 / cv.gsd), rng, "smoothstep")
    fine = rng.standard_normal(cv.ndsm.shape, dtype=np.float32)
    gain, grain = texture_terms(TEXTURE[cv.material], large, mid, fine)
    tinted: np.ndarray = cv.tint * gain[None] + grain[None]
    return tinted


def render_city(cv: CityCanvas, imaging: Imaging, rng: np.random.Generator) -> np.ndarray:
    """Light the canvas with the sun and sky, cast shadows, and view it with the imaging's lean.

    Returns:
        float32 (3, N, N) radiance in DN (before the sensor look of :func:`finish_image`).
    """
    albedo = _albedo(cv, rng)
    direct, _ = direct_sun(cv.ndsm, cv.gsd, imaging.sun_azimuth, imaging.sun_elevation)
    lit = albedo * SKY.light(direct)
    relief = relief_displacement(cv.ndsm, cv.gsd, imaging.lean_azimuth, imaging.lean_tan)
    out = lit[:, relief.src_row, relief.src_col]
    if relief.wall.any():
        rows, cols = relief.src_row[relief.wall], relief.src_col[relief.wall]
        wall_light = SKY.light(wall_sun(imaging.sun_azimuth, imaging.sun_elevation, imaging.lean_azimuth))
        z = relief.z[relief.wall]
        storeys = np.where(cv.labels[rows, cols] == BUILDING,
                           np.where(np.mod(z, STOREY_M) < 0.45 * STOREY_M, np.float32(0.7), np.float32(1.0)),
                           np.float32(0.9))
        out[:, relief.wall] = cv.facade[:, rows, cols] * wall_light[:, None] * storeys[None]
    result: np.ndarray = out
    return result


def _check(size: int, gsd: float) -> None:
    if int(size) != size or size < MIN_CITY_SIZE:
        raise InputError(f"‹size› must be an integer ≥ {MIN_CITY_SIZE} pixels, got {size}; pass e.g. ‹size=256›",
                         param="size")
    if not GSD_RANGE[0] <= gsd <= GSD_RANGE[1]:
        raise InputError(f"‹gsd› must be a pixel size in metres within {GSD_RANGE}, got {gsd}; pass e.g. "
                         "‹gsd=0.5›", param="gsd")


def sample_city(seed: int, size: int = 256, gsd: float = 0.5, style: CityStyle | None = None,
                textures: TexturePool | None = None) -> CityPatch:
    """Draw one synthetic city patch in memory.

    The city is drawn on a canvas a margin wider than the patch (so that objects just outside cast their
    shadows and lean into it) and cut to ``size`` × ``size``. The same (seed, size, gsd, style, textures)
    always gives identical arrays; the heights and labels depend on (seed, size, gsd) only.

    Args:
        seed: random seed (any int).
        size: patch side in pixels (≥ 16).
        gsd: pixel size in metres (0.05–2; the generator is designed for 0.1–1 m).
        style: ranges the sun, lean and sensor look are drawn from (default :class:`CityStyle`).
        textures: optional pool of the user's ground textures laid on a share of roofs and ground.

    Returns:
        :class:`CityPatch`.

    Raises:
        InputError: bad ``size`` or ``gsd``.
    """
    _check(size, gsd)
    layout, imaging_rng, texture_rng = _streams(seed)
    pad = max(8, int(size) // 8)
    texture = None if textures is None else textures.source(gsd)
    style = style or CityStyle()
    cv, _ = build_city(int(size) + 2 * pad, float(gsd), layout, texture_rng, texture, style.ground_roofs)
    imaging = style.draw(imaging_rng)
    radiance = render_city(cv, imaging, imaging_rng)
    crop = (slice(pad, pad + size), slice(pad, pad + size))
    image = finish_image(np.ascontiguousarray(radiance[:, crop[0], crop[1]]), imaging, imaging_rng)
    return CityPatch(image=image, height=np.ascontiguousarray(cv.ndsm[crop]),
                     classes=np.ascontiguousarray(cv.labels[crop]), gsd=float(gsd), seed=int(seed), imaging=imaging)


__all__ = ["AMBIENT", "CityPatch", "CityStyle", "GSD_RANGE", "Imaging", "MIN_CITY_SIZE", "TexturePool",
           "build_city", "render_city", "sample_city"]
