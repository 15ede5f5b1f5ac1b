"""Cast shadows from known heights: which pixels the sun cannot see.

A pixel ``p`` is in shadow when, marching towards the sun along the digital line ``p + d·u`` (``u`` the
horizontal step towards the sun, ``d = 1, 2, ...``), some height ``h(p + d·u) − d·|u|·gsd·tan(elevation)`` rises
above ``h(p) + tol``. Rasters are north-up (row 0 north); see :mod:`aerialmtl.sun.position` for the angles.
"""

from __future__ import annotations

import math

import numpy as np

from aerialmtl.sun.position import Sun


def line_offsets(n: int, slope: float) -> np.ndarray:
    """int64 (n,): integer cross-axis offset of a digital line with ``slope`` at positions ``0..n-1``."""
    result: np.ndarray = np.floor(np.arange(n) * slope + 0.5).astype(np.int64)
    return result


def sun_steps(azimuth_deg: float) -> tuple[bool, int, float]:
    """How to walk towards the sun one pixel at a time along the dominant axis.

    Returns:
        ``(rows_dominant, step, slope)``: whether the walk moves one row per step (else one column), the sign of
        that move (+1 / −1), and the move along the other axis per step (|slope| ≤ 1, signed).
    """
    az = math.radians(azimuth_deg)
    d_row, d_col = -math.cos(az), math.sin(az)
    if abs(d_row) > abs(d_col):
        return True, 1 if d_row > 0 else -1, d_col / abs(d_row)
    return False, 1 if d_col > 0 else -1, d_row / abs(d_col)


def shadow_surface_sweep(surface: np.ndarray, gsd: float, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """The "shadow surface" ``S(p) = max(Z(p), S(p + u) − |u|·gsd·tan(elevation))`` swept once from the sun-side edge.

    ``S(p) − Z(p)`` is how far the highest occluder towards the sun rises above ``p``'s sun ray; this is the
    O(pixels) form of the running maximum over every distance (no length limit).

    Args:
        surface: float (H, W) or a stack (N, H, W) of heights in metres (each (H, W) swept on its own).
        gsd: pixel size in metres.
        azimuth_deg: degrees clockwise from grid north (any value; taken modulo 360).
        elevation_deg: degrees above the horizon, 0 < elevation < 90.

    Returns:
        float32 array of the input's shape: the shadow surface in metres.
    """
    z = np.asarray(surface, dtype=np.float32)
    flat = z.ndim == 2
    surf = sweep_stack(np.ascontiguousarray(z[None] if flat else z), gsd, azimuth_deg, elevation_deg)
    return surf[0] if flat else surf


def sweep_plan(shape: tuple[int, ...], gsd: float, azimuth_deg: float, elevation_deg: float
               ) -> tuple[bool, int, np.ndarray, np.float32]:
    """The arguments of :func:`aerialmtl.sun.kernels.sweep_surface` for rasters of ``shape`` (..., H, W):
    ``(rows, step, deltas, drop)`` — whether the sweep moves one row per step, the way towards the sun (±1), the
    across-axis shift (int64) from each position to its upstream neighbour, and the drop per step (float32 metres).
    """
    rows, step, slope = sun_steps(azimuth_deg)  # along the dominant axis: one row (else one column) per step
    length = shape[-2] if rows else shape[-1]
    drop = np.float32(gsd * math.tan(math.radians(elevation_deg)) * math.hypot(1.0, slope))
    offsets = line_offsets(length, slope * step)  # across-axis offset of the line through 0 at each position
    deltas = np.zeros(length, np.int64)  # the shift from each position to its upstream neighbour p + step
    if step > 0:
        deltas[:-1] = offsets[1:] - offsets[:-1]
    else:
        deltas[1:] = offsets[:-1] - offsets[1:]
    return rows, step, deltas, drop


def sweep_stack(z3: np.ndarray, gsd: float, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """:func:`shadow_surface_sweep` of a C-contiguous float32 stack ``z3`` (N, H, W) as it is (no copy made)."""
    from aerialmtl.sun.kernels import sweep_surface  # numba: imported when a shadow is first cast

    rows, step, deltas, drop = sweep_plan(z3.shape, gsd, azimuth_deg, elevation_deg)
    surf = np.empty_like(z3)
    sweep_surface(z3, rows, step, deltas, drop, surf)
    return surf


def _limited_occluder(z: np.ndarray, gsd: float, sun: Sun, max_length_m: float) -> np.ndarray:
    """Highest ``Z(p + d·u) − d·|u|·gsd·tan(E)`` over ``d·|u|·gsd ≤ max_length_m`` (−inf where none); (..., H, W)."""
    rows_dom, step, slope = sun_steps(sun.azimuth_deg)
    per_step = gsd * math.hypot(1.0, slope)
    n = int(max_length_m // per_step)
    h, w = z.shape[-2:]
    best = np.full(z.shape, -np.inf, dtype=np.float32)
    cross = line_offsets(n + 1, slope)
    drop = per_step * sun.tan_elevation
    for d in range(1, n + 1):
        dr, dc = (step * d, int(cross[d])) if rows_dom else (int(cross[d]), step * d)
        if abs(dr) >= h or abs(dc) >= w:
            break
        src = z[..., max(dr, 0): h + min(dr, 0), max(dc, 0): w + min(dc, 0)]
        dst = best[..., max(-dr, 0): h + min(-dr, 0), max(-dc, 0): w + min(-dc, 0)]
        np.maximum(dst, src - np.float32(d * drop), out=dst)
    return best


#: Metres by which an occluder must rise above a pixel's sun ray for the pixel to be in cast shadow (surface noise).
TOL_M = 0.3


def cast_shadow_mask(height: np.ndarray, gsd_m: float, sun: Sun, tol_m: float = TOL_M,
                     max_length_m: float | None = None) -> np.ndarray:
    """Pixels in the cast shadow of the heights at ``sun``.

    Args:
        height: float (H, W) (or a stack (N, H, W)) heights in metres (an nDSM; a DSM works too). NaN counts as
            a height no occluder rises above and which occludes nothing.
        gsd_m: pixel size in metres.
        sun: the sun.
        tol_m: metres by which an occluder must rise above the pixel's sun ray (ignores surface noise).
        max_length_m: only occluders within this horizontal distance (metres) count; ``None``: any distance
            (one sweep, O(pixels)); a limit costs O(pixels × length / gsd).

    Returns:
        bool array of ``height``'s shape, True in shadow (also the self-shadow of surfaces steeper than the
        sun). Only objects inside the raster cast shadows.
    """
    z = np.asarray(height, dtype=np.float32)
    nan = np.isnan(z)
    if nan.any():
        z = np.where(nan, np.float32(-np.inf), z)
    if max_length_m is None:
        surf = shadow_surface_sweep(z, gsd_m, sun.azimuth_deg, sun.elevation_deg)
        with np.errstate(invalid="ignore"):
            shadow = (surf - z) > np.float32(tol_m)
    else:
        occ = _limited_occluder(z, gsd_m, sun, float(max_length_m))
        with np.errstate(invalid="ignore"):
            shadow = (occ - z) > np.float32(tol_m)
    shadow &= ~nan
    result: np.ndarray = shadow
    return result
