"""Clean a raster footprint (a pixel staircase polygon) into a building outline.

:func:`clean_footprint` fills small holes, simplifies the staircase (Douglas–Peucker, topology kept)
and, optionally, regularises the outline orthogonally with :func:`regularize`:

1. the building's dominant direction θ is the length-weighted circular mean of its edge directions
   modulo 90° (the mean of ``exp(4iα)``), refined with the principal directions of the pixel-staircase
   vertices behind the edges close to it;
2. every edge within ``angle_tolerance`` of θ or θ + 90° (a wider tolerance for short edges, whose
   direction is uncertain) is turned onto that direction, through the mean of the staircase vertices it
   replaced; consecutive edges that become parallel are merged into one line;
3. short edges that point elsewhere (corner chamfers left by the staircase) are dropped; edges far from
   both directions (round or oblique walls) keep their own direction;
4. the vertices are the intersections of consecutive lines.

When the result is invalid or moves the outline too much (IoU with the simplified outline below
:data:`MIN_REGULARIZE_IOU`) the simplified outline is kept instead.

All lengths are in CRS units; the caller converts metres.
"""

from __future__ import annotations

import math

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon
from shapely.geometry.polygon import orient

#: Edges within this angle of the dominant direction (or its normal) are snapped onto it.
DEFAULT_ANGLE_TOLERANCE_DEG = 15.0
#: Edges shorter than this many simplification tolerances that point away from both dominant directions
#: are dropped by the regularisation (the corner chamfers a pixel staircase leaves).
SHORT_EDGE = 3.0
#: A regularised outline must keep this IoU with the simplified one, or the simplified one is kept.
MIN_REGULARIZE_IOU = 0.9


def largest_polygon(geom: shapely.Geometry) -> Polygon | None:
    """``geom`` itself if it is a polygon, its largest polygon if it is a collection, else ``None``."""
    if isinstance(geom, Polygon):
        return None if geom.is_empty else geom
    if isinstance(geom, MultiPolygon) or hasattr(geom, "geoms"):
        polys = [g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon) and not g.is_empty]
        return max(polys, key=lambda g: g.area) if polys else None
    return None


def fill_small_holes(poly: Polygon, max_area: float) -> Polygon:
    """``poly`` without the holes smaller than ``max_area`` (CRS units²)."""
    keep = [ring for ring in poly.interiors if Polygon(ring).area >= max_area]
    return poly if len(keep) == len(poly.interiors) else Polygon(poly.exterior, keep)


def dominant_direction(poly: Polygon) -> float:
    """Length-weighted mean direction of the edges of ``poly`` modulo 90°, in radians in [0, π/2)."""
    total = 0j
    for ring in (poly.exterior, *poly.interiors):
        xy = np.asarray(ring.coords)
        d = np.diff(xy, axis=0)
        length = np.hypot(d[:, 0], d[:, 1])
        total += complex(np.sum(length * np.exp(4j * np.arctan2(d[:, 1], d[:, 0]))))
    return (math.atan2(total.imag, total.real) / 4.0) % (math.pi / 2)


def _intersect(p: np.ndarray, u: np.ndarray, q: np.ndarray, v: np.ndarray) -> np.ndarray | None:
    """Intersection of the lines p + s·u and q + t·v (``None`` when nearly parallel)."""
    cross = u[0] * v[1] - u[1] * v[0]
    if abs(cross) < 1e-6:
        return None
    s = ((q[0] - p[0]) * v[1] - (q[1] - p[1]) * v[0]) / cross
    result: np.ndarray | None = p + s * u
    return result


def _supports(pts: np.ndarray, original: np.ndarray | None) -> list[np.ndarray] | None:
    """For each edge of the simplified ring ``pts``, the vertices of the ``original`` ring it replaced.

    Douglas–Peucker keeps a subset of the original vertices in order, so edge i of ``pts`` spans the
    original vertices from ``pts[i]`` to ``pts[i + 1]``. ``None`` when they cannot be found.
    """
    if original is None or not len(pts):
        return None
    keys = original[:, 0] + 1j * original[:, 1]  # complex numbers sort by x, then y
    order = np.argsort(keys)
    wanted = pts[:, 0] + 1j * pts[:, 1]
    pos = np.minimum(np.searchsorted(keys[order], wanted), len(keys) - 1)
    if not np.array_equal(keys[order][pos], wanted):
        return None
    idx = order[pos].tolist()
    n = len(original)
    spans = []
    for a, b in zip(idx, idx[1:] + idx[:1]):
        stop = b if b > a else b + n
        spans.append(original[np.arange(a, stop + 1) % n])
    if sum(len(s) - 1 for s in spans) != n:  # not one turn around the ring in order
        return None
    return spans


def _snap(pts: np.ndarray, theta: float, angle_tol: float, tolerance: float) -> tuple[np.ndarray, ...]:
    """Per edge of the closed ring ``pts``: start, end, length, axis k (angle θ + k·90°), snapped?"""
    start, end = pts, np.roll(pts, -1, axis=0)
    d = end - start
    length = np.hypot(d[:, 0], d[:, 1])
    alpha = np.arctan2(d[:, 1], d[:, 0])
    k = np.round((alpha - theta) / (math.pi / 2))
    allowed = np.maximum(angle_tol, np.arctan2(2.0 * tolerance, length))
    snapped = np.abs(alpha - theta - k * math.pi / 2) <= allowed
    return start, end, length, alpha, k, snapped


def _refined_direction(rings: list[np.ndarray], supports: list[list[np.ndarray] | None], theta: float,
                       angle_tol: float, tolerance: float) -> float:
    """θ re-estimated from the principal direction of the staircase vertices behind each snapped edge.

    The simplified edges run between staircase corners, so their directions are off by up to
    atan(tolerance / length); the staircase vertices of a whole wall pin its direction much better.
    """
    total = 0j
    for pts, support in zip(rings, supports):
        if support is None or len(pts) < 3:
            continue
        _, _, length, _, _, snapped = _snap(pts, theta, angle_tol, tolerance)
        for i in np.flatnonzero(snapped):
            sp = support[i]
            if len(sp) < 3:
                continue
            c = sp - sp.mean(axis=0)
            # principal axis of the points: angle ½·atan2(2·Sxy, Sxx − Syy)
            axis = 0.5 * math.atan2(2.0 * float(c[:, 0] @ c[:, 1]), float(c[:, 0] @ c[:, 0] - c[:, 1] @ c[:, 1]))
            total += length[i] * np.exp(4j * axis)
    if total == 0:
        return theta
    return (math.atan2(total.imag, total.real) / 4.0) % (math.pi / 2)


def _regularize_ring(pts: np.ndarray, theta: float, angle_tol: float, tolerance: float,
                     support: list[np.ndarray] | None = None) -> np.ndarray | None:
    """Regularised vertices of the closed ring ``pts`` (n × 2, last vertex not repeated), or ``None``.

    An edge is snapped when its direction is within ``angle_tol`` of an axis, or within the direction
    uncertainty of a simplified edge, atan(2 · ``tolerance`` / length), whichever is larger: both ends of
    a short edge may be off by the simplification tolerance.

    ``support``: per edge, the vertices of the unsimplified ring (pixel staircase) it replaced (see
    :func:`_supports`); a snapped line then passes through their mean (outer and inner corners alternate
    around the true wall) instead of the mean of the simplified edges' midpoints, which lie on corners.
    """
    n = len(pts)
    if n < 3:
        return None
    start, end, length, alpha, k, snapped = _snap(pts, theta, angle_tol, tolerance)
    angle = np.where(snapped, theta + k * math.pi / 2, alpha)
    keep = snapped | (length >= SHORT_EDGE * tolerance)
    if keep.sum() < 3:
        return None
    idx = np.flatnonzero(keep)
    axis = np.where(snapped, np.mod(k, 2), -1).astype(int)  # 0 / 1: which axis; -1: free edge

    def mergeable(i: int, j: int) -> bool:
        return bool(axis[i] >= 0 and axis[i] == axis[j])

    # rotate so that the kept edges start at a group boundary
    m = len(idx)
    first = next((s for s in range(m) if not mergeable(int(idx[s - 1]), int(idx[s]))), None)
    if first is None:  # every edge parallel: a degenerate sliver
        return None
    idx = np.roll(idx, -first)
    groups: list[list[int]] = []
    for i in idx:
        if groups and mergeable(groups[-1][-1], int(i)):
            groups[-1].append(int(i))
        else:
            groups.append([int(i)])
    if len(groups) < 3:
        return None
    lines = []
    for g in groups:
        w = length[g]
        if support is not None and axis[g[0]] >= 0:
            point = np.concatenate([support[i] for i in g]).mean(axis=0)
        else:
            mid = 0.5 * (start[g] + end[g])
            point = (mid * w[:, None]).sum(axis=0) / max(w.sum(), 1e-12)
        a = angle[g[int(np.argmax(w))]]
        lines.append((point, np.array([math.cos(a), math.sin(a)]), g[-1]))
    out = []
    for j, (p, u, last_edge) in enumerate(lines):
        q, v, _ = lines[(j + 1) % len(lines)]
        x = _intersect(p, u, q, v)
        out.append(x if x is not None else end[last_edge])
    return np.asarray(out)


def regularize(poly: Polygon, tolerance: float, angle_tolerance_deg: float = DEFAULT_ANGLE_TOLERANCE_DEG,
               original: Polygon | None = None) -> Polygon | None:
    """Orthogonally regularised ``poly`` (see the module docstring), or ``None`` when it cannot be done.

    Args:
        poly: a simplified outline (CRS units).
        tolerance: the simplification tolerance; edges shorter than :data:`SHORT_EDGE` times it that point
            away from both dominant directions are dropped.
        angle_tolerance_deg: snapping tolerance, degrees.
        original: the outline before simplification (its vertices place the snapped walls).
    """
    tol = math.radians(angle_tolerance_deg)
    originals = [] if original is None else [np.asarray(r.coords)[:-1] for r in (original.exterior,
                                                                                 *original.interiors)]
    simplified = [np.asarray(ring.coords)[:-1] for ring in (poly.exterior, *poly.interiors)]

    def source(pts: np.ndarray) -> np.ndarray | None:  # the original ring holding the simplified one's vertices
        if not len(pts):
            return None
        return next((o for o in originals if np.any(np.all(o == pts[0], axis=1))), None)

    supports = [_supports(pts, source(pts)) for pts in simplified]
    theta = _refined_direction(simplified, supports, dominant_direction(poly), tol, tolerance)
    rings = []
    for i, (pts, support) in enumerate(zip(simplified, supports)):
        reg = _regularize_ring(pts, theta, tol, tolerance, support)
        if reg is None:
            if i == 0:
                return None
            reg = pts
        rings.append(reg)
    try:
        out = Polygon(rings[0], rings[1:])
    except (ValueError, shapely.errors.GEOSException):  # pragma: no cover - defensive
        return None
    if not out.is_valid or out.is_empty:
        return None
    union = out.union(poly).area
    if union <= 0 or out.intersection(poly).area / union < MIN_REGULARIZE_IOU:
        return None
    return out


def clean_footprint(
    poly: Polygon,
    max_hole_area: float,
    tolerance: float,
    orthogonal: bool = True,
    angle_tolerance_deg: float = DEFAULT_ANGLE_TOLERANCE_DEG,
    clip: Polygon | None = None,
) -> Polygon | None:
    """Fill holes smaller than ``max_hole_area``, simplify with ``tolerance``, optionally regularise, then clip.

    Args:
        poly: the raster footprint in map coordinates (CRS units).
        max_hole_area: holes smaller than this (CRS units²) are filled; larger ones (courtyards) are kept.
        tolerance: Douglas–Peucker tolerance (CRS units); 0 keeps the staircase.
        orthogonal: regularise orthogonally (see :func:`regularize`).
        angle_tolerance_deg: snapping tolerance of the regularisation, degrees.
        clip: the raster's footprint: the result is cut to it. Regularised walls meet at new corners,
            which for a building cut by the raster edge can lie beyond it (metres, for a slanted wall).

    Returns:
        the cleaned polygon, exterior counter-clockwise, or ``None`` when nothing valid is left.
    """
    out = filled = fill_small_holes(poly, max_hole_area)
    if tolerance > 0:
        simple = largest_polygon(shapely.make_valid(out.simplify(tolerance, preserve_topology=True)))
        out = simple if simple is not None else out
        if orthogonal:
            reg = regularize(out, tolerance, angle_tolerance_deg, original=filled)
            out = reg if reg is not None else out
    if not out.is_valid:
        fixed = largest_polygon(shapely.make_valid(out))
        if fixed is None:
            return None
        out = fixed
    if clip is not None and not clip.covers(out):
        inside = largest_polygon(out.intersection(clip))
        if inside is None:
            return None
        out = inside
    return orient(out, 1.0)


__all__ = [
    "DEFAULT_ANGLE_TOLERANCE_DEG", "MIN_REGULARIZE_IOU", "SHORT_EDGE", "clean_footprint", "dominant_direction",
    "fill_small_holes", "largest_polygon", "regularize",
]
