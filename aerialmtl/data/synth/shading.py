"""Sun geometry for synthetic scenes: hillshade of a surface and cast shadows along the sun direction.

Angles follow the photogrammetry convention: the sun ``azimuth`` is measured in degrees clockwise
from grid north (90 = east, 180 = south) and the ``elevation`` in degrees above the horizon. Arrays
are north-up rasters: row 0 is the northern edge, column 0 the western edge.
"""

from __future__ import annotations

import math

import numpy as np

from aerialmtl.sun.cast import shadow_surface_sweep


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
