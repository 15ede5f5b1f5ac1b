"""Relief displacement of a non-true orthophoto: tall surfaces drawn where an oblique camera ray meets them.

A frame orthophoto is made from a central projection rectified onto the terrain only, so a point ``h``
metres above the ground is drawn ``h · tan(view angle)`` metres away from the image's nadir point: roofs
lean away from the nadir and the walls facing the nadir become visible between the footprint and the
roof. Over a patch that is small against the camera's footprint, the view angle and the lean direction
are nearly constant, so a patch is modelled as a parallel projection: every point of height ``h`` moves
by ``h · lean_tan`` metres towards ``lean_azimuth``. The reference (lidar) nDSM and labels stay at the
true footprint; only the image moves.

Angles follow :mod:`aerialmtl.data.synth.shading`: azimuth in degrees clockwise from grid north, arrays
north-up (row 0 north).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Relief:
    """Which surface point every image pixel shows (arrays (H, W) on the same grid as the heights).

    Attributes:
        src_row, src_col: int (H, W) pixel of the height grid whose surface the image pixel shows (the
            roof or ground point itself, or for a wall the footprint pixel behind it).
        wall: bool (H, W), True where the image pixel shows the side (wall, crown side) of the object at
            ``(src_row, src_col)`` rather than its top.
        z: float32 (H, W) height above ground in metres of the point seen (0 on visible ground).
    """

    src_row: np.ndarray
    src_col: np.ndarray
    wall: np.ndarray
    z: np.ndarray


def _step(lean_azimuth: float) -> tuple[float, float]:
    """One step along the lean in (row, col) pixels, the dominant axis moving by exactly one pixel."""
    az = math.radians(lean_azimuth)
    d_row, d_col = -math.cos(az), math.sin(az)
    scale = max(abs(d_row), abs(d_col))
    return d_row / scale, d_col / scale


def relief_displacement(height: np.ndarray, gsd: float, lean_azimuth: float, lean_tan: float) -> Relief:
    """Trace every image pixel's ray of a parallel oblique view onto the height field (first hit from above).

    A surface point at pixel ``p`` with height ``h`` is drawn at ``p + h · lean_tan / gsd`` pixels along
    ``lean_azimuth``. For each image pixel ``q`` the camera ray descends towards ``q`` from the opposite
    side; the first surface it meets is the highest ``k`` (steps back along the lean) with
    ``height(q − k·step) ≥ k·|step|·gsd / lean_tan``. The cost is one pass per step over the pixels tall
    enough for that step (pixels sorted by height once), not over the whole raster.

    Args:
        height: float (H, W) surface height above ground, metres (≥ 0).
        gsd: pixel size in metres.
        lean_azimuth: direction, degrees clockwise from north, in which tall things are displaced (away
            from the image's nadir point).
        lean_tan: tangent of the view angle from the vertical (0 = a true orthophoto).

    Returns:
        :class:`Relief`. Rays whose surface lies outside the raster show the ground under them.
    """
    h = np.asarray(height, np.float32)
    n_rows, n_cols = h.shape
    rows, cols = np.indices(h.shape)
    hit = np.zeros(h.shape, np.int32)
    d_row, d_col = _step(lean_azimuth)
    step_m = gsd * math.hypot(d_row, d_col)
    if lean_tan > 1e-6:
        dz = step_m / lean_tan  # ray height gained per step back
        flat = h.ravel()
        candidates = np.flatnonzero(flat >= dz)  # only these can be seen from another pixel
        order = candidates[np.argsort(-flat[candidates], kind="stable")]
        tall = flat[order]
        k_max = int(tall[0] / dz) if tall.size else 0
        src_r, src_c = order // n_cols, order % n_cols
        n_at = np.searchsorted(-tall, -np.arange(1, k_max + 1, dtype=np.float32) * np.float32(dz), side="right")
        for k in range(1, k_max + 1):
            n = int(n_at[k - 1])
            if n == 0:
                break
            tr = src_r[:n] + int(round(k * d_row))
            tc = src_c[:n] + int(round(k * d_col))
            ok = (tr >= 0) & (tr < n_rows) & (tc >= 0) & (tc < n_cols)
            hit[tr[ok], tc[ok]] = k  # k ascends: the highest hit (first from above) wins
    else:
        dz = math.inf
    back_r = np.round(np.arange(hit.max() + 1) * d_row).astype(np.int64)
    back_c = np.round(np.arange(hit.max() + 1) * d_col).astype(np.int64)
    sr, sc = rows - back_r[hit], cols - back_c[hit]
    z = (hit * np.float32(dz if math.isfinite(dz) else 0.0)).astype(np.float32)
    wall = (h[sr, sc] - z) >= (dz if math.isfinite(dz) else np.inf)
    z = np.where(wall, z, h[sr, sc]).astype(np.float32)
    return Relief(sr, sc, wall, z)
