"""Sun and sky light of synthetic scenes: hillshade, cast shadows along the sun direction, the sky's share.

Both styles light their surfaces the same way: each pixel receives
``albedo × ((1 − ambient)·direct + ambient·tint)`` (:class:`Sky`), with ``direct`` the sun on the surface
relative to flat ground, 0 in cast shadows (:func:`direct_sun`; :func:`wall_sun` for the walls a leaning
camera sees). Angles follow the photogrammetry convention: the sun ``azimuth`` is measured in degrees clockwise
from grid north (90 = east, 180 = south) and the ``elevation`` in degrees above the horizon. Arrays
are north-up rasters: row 0 is the northern edge, column 0 the western edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from aerialmtl.sun.cast import shadow_surface_sweep

#: Most direct sun a surface receives, relative to flat ground (steep slopes facing a low sun are capped).
MAX_DIRECT = 1.6


def sun_vector(azimuth: float, elevation: float) -> tuple[float, float, float]:
    """Unit vector pointing *towards* the sun as (east, north, up)."""
    az, el = math.radians(azimuth), math.radians(elevation)
    return (math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el))


def hillshade(surface: np.ndarray, gsd: float, azimuth: float, elevation: float,
              max_slope: float = 3.0) -> np.ndarray:
    """Direct-illumination factor of a surface model, relative to flat ground.

    Args:
        surface: float (H, W) heights in metres (a DSM).
        gsd: pixel size in metres.
        azimuth: sun azimuth in degrees clockwise from north.
        elevation: sun elevation in degrees.
        max_slope: gradients steeper than this (rise/run) are height steps between objects (walls,
            crown rims), not surfaces; they are shaded as flat so that edges do not get halos.

    Returns:
        float32 (H, W): ``max(0, n·s) / sin(elevation)``, i.e. 1 on flat ground, > 1 on slopes facing
        the sun, 0 on slopes facing away from it.
    """
    z = np.asarray(surface, dtype=np.float32)
    d_row, d_col = np.gradient(z, gsd)
    dz_east = np.asarray(d_col)
    dz_north = -np.asarray(d_row)  # rows grow southwards
    steep = np.hypot(dz_east, dz_north) > max_slope
    dz_east[steep] = 0.0
    dz_north[steep] = 0.0
    se, sn, su = sun_vector(azimuth, elevation)
    # normal = (-dz/dx, -dz/dy, 1) / norm
    dot = (-dz_east * se - dz_north * sn + su) / np.sqrt(dz_east * dz_east + dz_north * dz_north + 1.0)
    result: np.ndarray = (np.maximum(dot, 0.0) / su).astype(np.float32)
    return result


def cast_shadows(surface: np.ndarray, gsd: float, azimuth: float, elevation: float,
                 tolerance: float = 0.05) -> np.ndarray:
    """Pixels that the sun cannot see because something between them and the sun is tall enough.

    A pixel ``p`` is in shadow when ``max_d (Z(p + d·u) − Z(p) − d·gsd·tan(elevation)) > tolerance``
    over the pixels ``p + d·u`` on the digital line from ``p`` towards the sun (``u`` the horizontal
    sun direction). The maximum is not taken over every ``d`` explicitly: the "shadow surface"
    ``S(p) = max(Z(p), S(p + u) − |u|·gsd·tan(elevation))`` is swept once across the raster from the
    sun-side edge, which is equivalent and costs O(H·W) whatever the object heights
    (:func:`aerialmtl.sun.cast.shadow_surface_sweep`, shared with the heights-from-shadows code).

    Args:
        surface: float (H, W) heights in metres (DSM).
        gsd: pixel size in metres.
        azimuth: sun azimuth in degrees clockwise from north.
        elevation: sun elevation in degrees (0 < elevation ≤ 90).
        tolerance: metres by which the occluder must exceed the sun ray (ignores rounding noise).

    Returns:
        bool (H, W), True where the pixel is in a cast shadow (including self-shadow of surfaces
        steeper than the sun elevation). A shadow is only cast by objects inside the raster.
    """
    z = np.asarray(surface, dtype=np.float32)
    if not 0.0 < elevation <= 90.0:
        raise ValueError(f"sun elevation must be in (0, 90] degrees, got {elevation}")
    if elevation >= 89.999:
        return np.zeros(z.shape, dtype=bool)
    shadow: np.ndarray = (shadow_surface_sweep(z, gsd, azimuth, elevation) - z) > tolerance
    return shadow


def direct_sun(surface: np.ndarray, gsd: float, azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray]:
    """Direct sunlight on a surface model: :func:`hillshade`, 0 in :func:`cast_shadows`, at most :data:`MAX_DIRECT`.

    The arguments are those of :func:`hillshade` (a DSM in metres, its pixel size in metres, the sun's azimuth
    and elevation in degrees).

    Returns:
        ``direct`` float32 (H, W), relative to flat ground (1), and ``shadow`` bool (H, W), the cast shadows.
    """
    direct = hillshade(surface, gsd, azimuth, elevation)
    shadow = cast_shadows(surface, gsd, azimuth, elevation)
    direct[shadow] = 0.0
    np.minimum(direct, MAX_DIRECT, out=direct)
    return direct, shadow


def wall_sun(sun_azimuth: float, sun_elevation: float, lean_azimuth: float) -> float:
    """Direct sunlight on the walls a leaning camera sees, relative to flat ground, at most :data:`MAX_DIRECT`.

    A camera whose tall things lean towards ``lean_azimuth`` (degrees clockwise from north; see
    :mod:`aerialmtl.data.synth.relief`) sees the vertical walls that face the opposite way; the sun at
    (``sun_azimuth``, ``sun_elevation``) (degrees) lights them by ``max(0, cos(facing)) / tan(elevation)``.
    """
    facing = math.cos(math.radians(sun_azimuth - lean_azimuth - 180.0))
    el = math.radians(sun_elevation)
    return min(MAX_DIRECT, max(0.0, facing) * math.cos(el) / math.sin(el))


@dataclass(frozen=True)
class Sky:
    """The sky's part of the light: the share of flat-ground brightness left in shadow, and its colour.

    Attributes:
        ambient: fraction of flat-ground brightness that remains in shadow (sky light only), 0–1.
        tint: per-channel (R, G, B) factor on the ambient part (sky light is bluer than sunlight).
    """

    ambient: float
    tint: tuple[float, float, float]

    def band(self, direct: np.ndarray, channel: int) -> np.ndarray:
        """float32 (H, W) light of one channel for a ``direct`` float32 (H, W) sun factor (:func:`direct_sun`)."""
        tint = np.float32(self.tint[channel])
        light: np.ndarray = np.float32(1 - self.ambient) * direct + np.float32(self.ambient) * tint
        return light

    def light(self, direct: np.ndarray | float) -> np.ndarray:
        """float32 (3, ...) light of the three channels for a ``direct`` sun factor (an array or one value)."""
        d = np.asarray(direct, np.float32)
        tint = np.asarray(self.tint, np.float32).reshape(3, *(1,) * d.ndim)
        light: np.ndarray = np.float32(1 - self.ambient) * d[None] + np.float32(self.ambient) * tint
        return light
