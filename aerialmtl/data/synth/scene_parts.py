"""What a synthetic town is made of: roof parts, buildings, trees, and the rasterised :class:`Scene` with the
true footprint and heights of its buildings (:class:`BuildingTruth`), as :func:`aerialmtl.data.synth.scene.build_scene`
plans and draws them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from shapely.geometry import Polygon


@dataclass(frozen=True)
class RoofPart:
    """One rectangle of a building footprint in the town frame (metres) and its roof.

    ``kind`` is ``"flat"`` (height ``eave``) or ``"gable"`` (ridge along the rectangle's longer side,
    rising ``rise`` metres above ``eave`` at the ridge line).
    """

    u0: float
    u1: float
    v0: float
    v1: float
    kind: str
    eave: float
    rise: float = 0.0


@dataclass(frozen=True)
class Building:
    """A building of the synthetic scene: its roof parts and its colour."""
    parts: tuple[RoofPart, ...]
    color: tuple[float, float, float]
    textured: bool  # roof tiles: stripes parallel to the ridge


@dataclass(frozen=True)
class TreeSpec:
    """A tree of the synthetic scene (position in scene units, crown size and height)."""
    u: float
    v: float
    radius: float  # crown radius, metres
    top: float  # crown top above ground, metres
    base: float  # crown rim above ground, metres
    color: tuple[float, float, float]


@dataclass(frozen=True)
class BuildingTruth:
    """The true footprint and roof heights of one building of a scene.

    Attributes:
        footprint: union of its roof parts, clipped to the scene, in scene metres: x east and y **south**
            of the scene's upper-left corner.
        height_m: median height above ground of its roof over the pixels it covers (the statistic
            ``aerialmtl buildings`` reports by default; eave + half the rise for a gable roof).
        height_max_m: its highest roof point above ground (metres).
        n_pixels: pixels covered by its roof parts (some may be hidden under trees in the rasters).
    """

    footprint: Polygon
    height_m: float
    height_max_m: float
    n_pixels: int


@dataclass
class Scene:
    """Rasterised scene on an (H, W) grid of ``gsd`` metres.

    Attributes:
        dtm: float32 (H, W) terrain elevation in metres.
        ndsm: float32 (H, W) height of the visible surface above the terrain, metres (≥ 0).
        labels: uint8 (H, W) raw codes of the "synthetic" scheme (1..6).
        albedo: float32 (3, H, W) surface colour in DN (0–255) before illumination.
        sun_azimuth, sun_elevation: degrees (azimuth clockwise from north).
        buildings: true footprint and heights of every building at least partly in the scene.
    """

    dtm: np.ndarray
    ndsm: np.ndarray
    labels: np.ndarray
    albedo: np.ndarray
    sun_azimuth: float
    sun_elevation: float
    gsd: float
    stats: dict[str, int] = field(default_factory=dict)
    buildings: list[BuildingTruth] = field(default_factory=list)


__all__ = ["Building", "BuildingTruth", "RoofPart", "Scene", "TreeSpec"]
