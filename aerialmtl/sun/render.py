"""Heights chosen by rendering shadows: each object's height is the one whose cast shadow matches the image's.

For every object of a height map (e.g. the network's pixels ≥ 2 m), try a range of heights ``H`` for it (0.3–5 ×
the object's median, :class:`RenderSettings`), shaped as a flat top over its footprint (``"flat"``) or as its own
shape capped at its 90th percentile (``"shape"``); render the cast shadows of the **whole** map with the object
at that height (other objects cast and receive shadows too, so a shadow falling on a street, a lower roof or
behind a taller neighbour is rendered as the sun would cast it: one sweep of the others' shadow surface,
:func:`aerialmtl.sun.cast.shadow_surface_sweep`, and one compiled walk that gives each pixel the least ``H`` that
shades it, :func:`aerialmtl.sun.kernels.shade_thresholds`); and compare the rendering with the observed shadow
probability ``P`` on the pixels whose rendered state depends on ``H``:

    LL(H) = Σ_zone  r_H · (logit P − logit π)        (within ±MAX_LLR; π the map's mean probability)

The match curve ``LL(H)`` gives the object's height (its maximum) **and** its spread: the curve, tempered by the
pixels' correlation (:data:`CORRELATED_PX` pixels per independent observation), is a likelihood over heights
whose standard deviation is the measurement's, widened by the grid step and the sun elevation's uncertainty. A
flat curve, or one that peaks at an end of the range (the object's shadow is hidden, clipped or falls outside the
map), measures nothing: no vote.

The network's objects spill into their own shadows (a blurred edge reads as object). Pixels at an object's
down-sun edge that ``P`` calls shadow are tried both ways — as part of the object and as ground — and the
comparison keeps the better: where it keeps them as ground, they are the object's *spill*
(:attr:`RenderedHeights.spill`).

Before the objects, one multiplier of all of them is chosen the same way (a network that reads every object low is
corrected as a whole). Objects are then measured one after another with the others at their current heights;
with ``passes`` > 1, those whose surroundings another object's new height changed are measured again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from aerialmtl.errors import InputError
from aerialmtl.sun.cast import TOL_M, shadow_surface_sweep, sun_steps, sweep_plan
from aerialmtl.sun.heights import ShadowHeights, ShadowObject, walk_offsets
from aerialmtl.sun.position import Sun

#: Probabilities are clipped to [EPS, 1 − EPS] before their logit is taken.
EPS = 0.03
#: The most one pixel's evidence can weigh either way (a likelihood ratio of e² ≈ 7.4): a mask of 0s and 1s, or a
#: confident classifier's few wrong pixels, then weigh a shadow and a lit pixel alike.
MAX_LLR = 2.0
#: Pixels per independent observation of the shadow probability (its spatial correlation): the match curve's
#: log-likelihood is divided by it before it is read as a likelihood over heights.
CORRELATED_PX = 12.0


@dataclass(frozen=True)
class RenderSettings:
    """How :func:`rendered_heights` searches.

    Attributes:
        threshold: probability from which an object's pixel is a spill candidate (tried as ground).
        min_zone_px: an object whose height changes fewer pixels' rendered state is not measured.
        max_rel_std: an object whose spread exceeds this share of its height is not measured (flat curve).
        range_scale: the heights tried, as multiples of the object's median height (lowest, highest).
        n_heights: heights tried (geometric steps over the range).
        max_height_m: no object is rendered higher, metres.
        elevation_sd_deg: uncertainty of the sun's elevation, degrees (it scales every height of the area).
        correlated_px: pixels per independent observation (the match curve's temperature).
        passes: passes over the objects in all: after the first, an object is measured again where another
            object's new height changed its surroundings (rows of buildings shade each other).
        tol_m: metres an occluder must rise above a pixel's sun ray (as :func:`~aerialmtl.sun.cast_shadow_mask`).
        families: the object shapes tried: ``"flat"`` (a flat top over the footprint) and ``"shape"`` (the
            network's own shape, capped at its 90th percentile: ``min(1, h / h90)``), each scaled to ``H``.
        spill_m: object pixels called shadow within this distance of the object's down-sun edge, metres, are
            tried as ground (a blurred object's spill into its own shadow).
        prior: the share of shadow the probability was calibrated to (a classifier's base rate), against which a
            pixel's probability is evidence for or against a rendered shadow; None: the map's mean probability.
        min_object_m2: objects smaller than this (square metres) are not measured: too small for their shadow to
            tell their height.
        top_share: the measured height is painted where the network's heights reach this share of the object's
            90th percentile (its top, not the blurred rim around it).
        global_range, global_steps: the common multiplier of every object's heights searched first (geometric
            steps); ``(1, 1)``: none.
    """

    threshold: float = 0.5
    min_zone_px: int = 12
    max_rel_std: float = 0.35
    range_scale: tuple[float, float] = (0.3, 5.0)
    n_heights: int = 160
    max_height_m: float = 150.0
    elevation_sd_deg: float = 3.0
    correlated_px: float = CORRELATED_PX
    passes: int = 1
    tol_m: float = TOL_M
    families: tuple[str, ...] = ("flat", "shape")
    spill_m: float = 3.0
    prior: float | None = None
    top_share: float = 0.5
    min_object_m2: float = 20.0
    global_range: tuple[float, float] = (0.5, 4.0)
    global_steps: int = 25


@dataclass(frozen=True)
class RenderedObject(ShadowObject):
    """One object's rendered-shadow measurement (a :class:`~aerialmtl.sun.ShadowObject`).

    Attributes:
        family: the shape family that matched best (``"scaled"`` or ``"flat"``), ``""`` when not measured.
        scale: the best multiplier of the object's median height (NaN when not measured).
        trimmed_px: the object's pixels the match took as ground (its spill into its own shadow).
    """

    family: str = ""
    scale: float = math.nan
    trimmed_px: int = 0

    @property
    def zone_px(self) -> int:
        """Pixels whose rendered state depends on the object's height (what the match sees): ``n_runs``."""
        return self.n_runs


@dataclass
class RenderedHeights(ShadowHeights):
    """Heights chosen by rendering (a :class:`~aerialmtl.sun.ShadowHeights`).

    Attributes:
        height: float32 (H, W) metres: each measured object's rendered height per pixel (its shape scaled, or its
            flat top), NaN elsewhere, on unmeasured objects and on spill.
        std: float32 (H, W) metres, the spread of ``height`` (NaN where it is).
        spill: bool (H, W): pixels of measured objects that the match took as ground in the object's shadow.
        global_scale: the multiplier of every object's heights chosen first (:attr:`RenderSettings.global_range`).
        objects: one :class:`RenderedObject` per object label (ascending).
    """

    spill: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), bool))
    global_scale: float = 1.0


def _crop(bbox: tuple[slice, slice], shape: tuple[int, int], sun: Sun, down_px: int, up_px: int,
          side_px: int) -> tuple[slice, slice]:
    """The box around an object's bounding box that holds its longest shadow (``down_px`` pixels away from the
    sun) and the occluders that can shade that shadow (``up_px`` pixels towards the sun), ``side_px`` across.
    """
    d_row, d_col = -math.cos(math.radians(sun.azimuth_deg)), math.sin(math.radians(sun.azimuth_deg))
    (r0, r1), (c0, c1) = (bbox[0].start, bbox[0].stop), (bbox[1].start, bbox[1].stop)

    def extend(lo: int, hi: int, toward_sun: float, n: int) -> tuple[int, int]:
        # a component of the direction towards the sun: + means the sun lies towards larger indices
        up = int(math.ceil(abs(toward_sun) * up_px)) + side_px
        down = int(math.ceil(abs(toward_sun) * down_px)) + side_px
        if toward_sun >= 0:
            return max(0, lo - down), min(n, hi + up)
        return max(0, lo - up), min(n, hi + down)

    rr = extend(r0, r1, d_row, shape[0])
    cc = extend(c0, c1, d_col, shape[1])
    return slice(*rr), slice(*cc)


def pixel_evidence(prob: np.ndarray, known: np.ndarray, prior: float | None) -> np.ndarray:
    """The evidence of each pixel, float32 (H, W): what a rendered shadow there adds to the match (the
    log-likelihood ratio of shadow to lit, ``logit P − logit prior``: the classifier's posterior odds over its
    prior odds, within ±:data:`MAX_LLR`; 0 where unknown); a lit pixel adds 0. ``prior`` None: the mean
    probability over the ``known`` pixels (a calibrated classifier's base rate of shadow there).
    """
    p = np.clip(np.where(known, prob, 0.5), EPS, 1.0 - EPS)
    if prior is None:
        prior = float(p[known].mean()) if known.any() else 0.5
    pi = min(max(float(prior), EPS), 1.0 - EPS)
    ratio = np.clip(np.log(p) - np.log1p(-p) - (math.log(pi) - math.log1p(-pi)), -MAX_LLR, MAX_LLR)
    evidence: np.ndarray = np.where(known, ratio, 0.0).astype(np.float32)
    return evidence


class _Curve(NamedTuple):
    """One variant's match curve: log-likelihood (G,) over the heights tried, and its zone's pixel count."""

    ll: np.ndarray
    zone_px: int


class _Variant(NamedTuple):
    """What one variant (a footprint and the receiving heights around it) shares between its shape families."""

    footprint: np.ndarray
    receive: np.ndarray
    reach: np.ndarray
    free: np.ndarray
    tops: np.ndarray
    base: float


def _variant(footprint: np.ndarray, receive: np.ndarray, others_surface: np.ndarray, use: np.ndarray,
             lp: np.ndarray, gsd_m: float, sun: Sun, tol_m: float) -> _Variant:
    """The parts of the match that do not depend on the object's shape: ``reach`` (−(steps to the footprint
    up-sun) × drop, one sweep), the pixels the rest of the map shades whatever the height (their evidence summed in
    ``base``), the ``free`` pixels the object alone may shade, and its ``tops``.
    """
    reach = shadow_surface_sweep(np.where(footprint, np.float32(0.0), np.float32(-np.inf)), gsd_m, sun.azimuth_deg,
                                 sun.elevation_deg)
    with np.errstate(invalid="ignore"):
        others = (others_surface - receive) > np.float32(tol_m)
    fixed = use & ~footprint
    return _Variant(footprint, receive, reach, fixed & ~others, footprint & use, float(lp[fixed & others].sum()))


def _curve(shape: np.ndarray, v: _Variant, others_surface: np.ndarray, lp: np.ndarray, heights: np.ndarray,
           gsd_m: float, sun: Sun, tol_m: float) -> _Curve:
    """The log-likelihood of the shadow probability for the object ``H · shape`` over ``v.footprint``, at each
    height ``H`` of ``heights`` (a lit pixel adds 0, a shaded one its evidence ``lp``).

    A pixel ``p`` off the footprint is in the object's shadow at ``H`` when ``H`` exceeds its threshold ``H*(p)``
    (:func:`aerialmtl.sun.kernels.shade_thresholds`), and whatever ``H`` when the rest of the map shades it (its
    shadow surface ``others_surface`` rises ``tol_m`` above the receiving height). A footprint pixel is the
    object's top at ``H · shape``: in the others' shadow while ``H`` stays below ``(others_surface − tol_m) / shape``.
    """
    from aerialmtl.sun.kernels import shade_thresholds

    _, _, slope = sun_steps(sun.azimuth_deg)
    drop = gsd_m * math.hypot(1.0, slope) * sun.tan_elevation
    top = float(heights[-1])
    off_r, off_c = walk_offsets(sun, int(math.ceil(top / drop)), away=False)  # steps 0 … n + 1 towards the sun
    with np.errstate(invalid="ignore"):
        start = np.where(np.isfinite(v.reach) & (v.receive - v.reach <= top), np.floor(-v.reach / drop) - 2, -1)
    thresh = np.empty(v.footprint.shape, np.float32)
    shade_thresholds(np.ascontiguousarray(shape, dtype=np.float32), np.ascontiguousarray(v.footprint),
                     np.ascontiguousarray(v.receive, dtype=np.float32), start.astype(np.int32), off_r, off_c, drop,
                     float(tol_m), top, thresh)
    reachable = v.free & (thresh <= top)  # the rest of ``free`` stays lit at every height tried
    t = thresh[reachable]
    order = np.argsort(t, kind="stable")
    t, cum = t[order], np.concatenate([[0.0], np.cumsum(lp[reachable][order].astype(np.float64))])
    ll = v.base + cum[np.searchsorted(t, heights, side="left")]  # thresholds strictly below H: shaded at H
    g = shape[v.tops]
    with np.errstate(invalid="ignore", divide="ignore"):
        # a top pixel stays in the others' shadow below this height of the object
        under = np.where(g > 0, (others_surface[v.tops] - np.float32(tol_m)) / g, -np.inf)
    hidden = under > heights[0]  # tops shaded by the others at the lowest heights tried
    if hidden.any():
        u = under[hidden]
        o2 = np.argsort(u, kind="stable")
        u, cum2 = u[o2], np.concatenate([[0.0], np.cumsum(lp[v.tops][hidden][o2].astype(np.float64))])
        ll = ll + (cum2[-1] - cum2[np.searchsorted(u, heights, side="right")])  # shaded while H < under
    zone = int(((t > heights[0]) & (t <= heights[-1])).sum()) + int(hidden.sum())
    return _Curve(ll, zone)


def rendered_heights(shadow_prob: np.ndarray, gsd_m: float, sun: Sun, objects: np.ndarray, height: np.ndarray,
                     settings: RenderSettings | None = None) -> RenderedHeights:
    """Per-object heights whose rendered cast shadows best match the shadow probability; see the module docstring.

    Args:
        shadow_prob: float (H, W) probability of cast shadow 0–1 (NaN = unknown, e.g. nodata).
        gsd_m: pixel size in metres.
        sun: the sun the image was taken under.
        objects: int (H, W) object labels, 0 = none (e.g. connected components of the network's heights ≥ 2 m).
        height: float (H, W) heights in metres (the network's; NaN = unknown): the objects' footprints and
            shapes, and the occluders and receiving surfaces around them.
        settings: the search (:class:`RenderSettings`; its defaults when None).

    Returns:
        :class:`RenderedHeights`: per-pixel heights (the object's flat top ``H``, tapered where the network's own
        heights fall below its 90th percentile: ``H · min(1, h(p) / h90)``) and spreads over measured objects, the
        spill, and one :class:`RenderedObject` per object (``n_edges`` holds its pixel count, ``n_runs`` its zone).
    """
    prob = np.asarray(shadow_prob, dtype=np.float32)
    labels = np.asarray(objects)
    hmap = np.asarray(height, dtype=np.float32)
    if not prob.shape == labels.shape == hmap.shape or prob.ndim != 2:
        raise InputError(f"'shadow_prob', 'objects' and 'height' must be (H, W) rasters of one shape, got "
                         f"{prob.shape}, {labels.shape} and {hmap.shape}")
    if not np.issubdtype(labels.dtype, np.integer):
        raise InputError(f"'objects' must hold integer labels (0 = no object), got dtype {labels.dtype}")
    settings = settings or RenderSettings()
    known = np.isfinite(prob)
    lp = pixel_evidence(prob, known, settings.prior)
    z = np.where(np.isfinite(hmap), hmap, np.float32(-np.inf)).astype(np.float32)
    # spill candidates: object pixels called shadow at the object's down-sun edge (where a blurred object runs
    # into its own shadow), not those deeper in (a lower roof shaded by a taller neighbour up-sun)
    called = known & (prob >= settings.threshold) & (labels > 0)
    called &= _down_sun_edge(labels > 0, gsd_m, sun, settings.spill_m)
    global_scale = _global_scale(z, labels > 0, known, lp, gsd_m, sun, settings)
    z = np.where(labels > 0, z * np.float32(global_scale), z)
    finite_max = float(np.max(hmap[np.isfinite(hmap)], initial=0.0))
    tan_e = sun.tan_elevation
    e = math.tan(math.radians(min(sun.elevation_deg + settings.elevation_sd_deg, 89.9))) / tan_e - 1.0
    boxes = ndimage.find_objects(labels)
    sizes = np.bincount(labels.ravel(), minlength=len(boxes) + 1)
    min_px = settings.min_object_m2 / (gsd_m * gsd_m)
    results: dict[int, _Result] = {}
    todo = [i + 1 for i, box in enumerate(boxes) if box is not None]
    for _ in range(max(1, int(settings.passes))):
        moved = np.zeros(labels.shape, bool)  # pixels whose height a measured object changed in this pass
        for label in todo:
            box = boxes[label - 1]
            assert box is not None
            if sizes[label] < min_px:  # too small for its shadow to tell its height
                empty = np.zeros((box[0].stop - box[0].start, box[1].stop - box[1].start), bool)
                results[label] = _Result(RenderedObject(label, int(sizes[label]), 0, math.nan, math.nan), box,
                                         empty, empty, empty, np.zeros(empty.shape, np.float32))
                continue
            res = _measure(label, box, labels, hmap, z, known, called, lp, finite_max, gsd_m, sun, e, settings)
            results[label] = res
            if res.record.measured:  # the next objects see this one at its measured height, its spill as ground
                new = z[res.crop].copy()
                new[res.top] = res.per_px[res.top]
                new[res.spill] = np.minimum(new[res.spill], np.float32(0.0))
                moved[res.crop] |= new != z[res.crop]
                z[res.crop] = new
        # measured again: the objects whose surroundings another object's new height changed
        todo = [label for label in todo if results[label].record.measured or results[label].record.n_runs > 0]
        todo = [label for label in todo
                if (moved[results[label].crop] & (labels[results[label].crop] != label)).any()]
        if not todo:
            break
    return _painted(labels.shape, results, global_scale)


def _painted(shape: tuple[int, ...], results: dict[int, _Result], global_scale: float) -> RenderedHeights:
    """The per-object results as :class:`RenderedHeights` on a raster of ``shape``."""
    out_h = np.full(shape, np.nan, np.float32)
    out_s = np.full(shape, np.nan, np.float32)
    spill_all = np.zeros(shape, bool)
    records: list[ShadowObject] = []
    for label in sorted(results):
        res = results[label]
        records.append(res.record)
        if res.record.measured:
            dst_h, dst_s = out_h[res.crop], out_s[res.crop]
            dst_h[res.top] = res.per_px[res.top]
            dst_s[res.top] = np.float32(res.record.std_m) * res.per_px[res.top] / np.float32(res.record.height_m)
            spill_all[res.crop] |= res.spill
    return RenderedHeights(out_h, out_s, records, spill_all, global_scale)


def _down_sun_edge(inside: np.ndarray, gsd_m: float, sun: Sun, width_m: float) -> np.ndarray:
    """Bool (H, W): pixels of ``inside`` from which walking away from the sun leaves it within ``width_m``."""
    away = Sun((sun.azimuth_deg + 180.0) % 360.0, sun.elevation_deg)
    # one sweep with the sun reversed: −(steps down-sun to the nearest outside pixel) × drop
    reach = shadow_surface_sweep(np.where(inside, np.float32(-np.inf), np.float32(0.0)), gsd_m, away.azimuth_deg,
                                 away.elevation_deg)
    _, _, slope = sun_steps(away.azimuth_deg)
    drop = gsd_m * math.hypot(1.0, slope) * away.tan_elevation
    with np.errstate(invalid="ignore"):
        steps = -reach / np.float32(drop)
    edge: np.ndarray = inside & np.isfinite(steps) & (steps * gsd_m * math.hypot(1.0, slope) <= width_m)
    return edge


def _global_scale(z: np.ndarray, inside: np.ndarray, known: np.ndarray, lp: np.ndarray,
                  gsd_m: float, sun: Sun, settings: RenderSettings) -> float:
    """The one multiplier of every object's heights whose rendered shadows match best (1.0 when the match curve
    peaks at an end of :attr:`RenderSettings.global_range` or there are no objects): a network that reads every
    object low is corrected as a whole before each object is measured with its neighbours near their heights.
    """
    lo, hi = settings.global_range
    if not inside.any() or hi <= lo:
        return 1.0
    from aerialmtl.sun.kernels import scaled_shadow_sums  # numba: every multiplier rendered and counted in one call

    scales = np.geomspace(lo, hi, settings.global_steps)
    ll = np.empty(len(scales))
    z3 = np.ascontiguousarray(z[None])
    rows, step, deltas, drop = sweep_plan(z3.shape, gsd_m, sun.azimuth_deg, sun.elevation_deg)
    scaled_shadow_sums(z3, np.ascontiguousarray(inside[None]), scales.astype(np.float32), rows, step, deltas, drop,
                       np.ascontiguousarray(known[None]), lp.astype(np.float64)[None], np.float32(settings.tol_m),
                       np.empty_like(z3), np.empty_like(z3), ll)
    k = int(np.argmax(ll))
    return float(scales[k]) if 0 < k < len(scales) - 1 else 1.0


class _Result(NamedTuple):
    """One object's measurement: its record, crop, painted pixels, the footprint it was rendered over, its spill
    and per-pixel heights in the crop.
    """

    record: RenderedObject
    crop: tuple[slice, slice]
    top: np.ndarray
    footprint: np.ndarray
    spill: np.ndarray
    per_px: np.ndarray


def _measure(label: int, box: tuple[slice, slice], labels: np.ndarray, hmap: np.ndarray, z: np.ndarray,
             known: np.ndarray, called: np.ndarray, lp: np.ndarray, finite_max: float,
             gsd_m: float, sun: Sun, e: float, settings: RenderSettings) -> _Result:
    """:func:`rendered_heights` for one object, the map ``z`` (−inf: unknown) holding the others' heights."""
    min_zone_px, max_rel_std, range_scale = settings.min_zone_px, settings.max_rel_std, settings.range_scale
    n_heights, max_height_m, correlated_px = settings.n_heights, settings.max_height_m, settings.correlated_px
    tol_m, families = settings.tol_m, settings.families
    own_box = labels[box] == label
    vals = hmap[box][own_box]
    vals = vals[np.isfinite(vals)]
    h_obj = float(np.median(vals)) if vals.size else math.nan
    n_px = int(own_box.sum())
    lo = max(0.5, range_scale[0] * h_obj) if math.isfinite(h_obj) else math.nan
    hi = min(max_height_m, range_scale[1] * h_obj) if math.isfinite(h_obj) else math.nan
    if not (math.isfinite(h_obj) and h_obj > 0 and hi > lo * 1.5):
        empty = np.zeros(own_box.shape, bool)
        return _Result(RenderedObject(label, n_px, 0, math.nan, math.nan), box, empty, empty, empty,
                       np.zeros(own_box.shape, np.float32))
    heights = np.geomspace(lo, hi, int(n_heights))
    tan_e = sun.tan_elevation
    down = int(math.ceil(hi / tan_e / gsd_m)) + 2
    up = int(math.ceil(max(finite_max, hi) / tan_e / gsd_m)) + 2
    crop = _crop(box, labels.shape, sun, down, up, 2)
    own = labels[crop] == label
    spill = own & called[crop]
    core = own & ~spill
    zc = z[crop]
    others_z = np.where(own, np.float32(-np.inf), zc)
    others_surface = shadow_surface_sweep(others_z, gsd_m, sun.azimuth_deg, sun.elevation_deg)
    kc, lpc = known[crop], lp[crop]
    # the variants: a flat top or the network's shape (capped at its 90th percentile), each with the whole
    # object as top or with its pixels called shadow as ground (the spill trimmed)
    base = np.where(np.isfinite(hmap[crop]), hmap[crop], 0.0).astype(np.float32)
    variants = [(own, zc, False)]
    if spill.any() and core.any():
        variants.append((core, np.where(spill, np.minimum(zc, np.float32(0.0)), zc), True))
    curves = []
    for fp, recv, trim in variants:
        v = _variant(fp, recv, others_surface, kc, lpc, gsd_m, sun, tol_m)
        vals = base[fp]
        h90 = max(float(np.partition(vals, int(0.9 * (len(vals) - 1)))[int(0.9 * (len(vals) - 1))]), 1e-3)
        shapes = {"flat": fp.astype(np.float32),
                  "shape": np.where(fp, np.clip(base / np.float32(h90), 0.0, 1.0), 0.0).astype(np.float32)}
        for family in families:
            curve = _curve(shapes[family], v, others_surface, lpc, heights, gsd_m, sun, tol_m)
            curves.append((curve, fp, trim, family, shapes[family]))
    best, footprint, trim, family, shape = max(curves, key=lambda c: float(c[0].ll.max()))
    ll = best.ll
    w = np.exp((ll - ll.max()) / max(correlated_px, 1e-6))
    w /= w.sum()
    k = int(np.argmax(ll))
    mean = float((w * heights).sum())
    sd_curve = math.sqrt(max(float((w * (heights - mean) ** 2).sum()), 0.0))
    step = float(heights[min(k + 1, len(heights) - 1)] - heights[max(k - 1, 0)]) / 2.0
    h_best = float(heights[k])
    sd = math.sqrt(sd_curve ** 2 + (step / 2.0) ** 2 + (h_best * e) ** 2)
    ok = (best.zone_px >= min_zone_px and 0 < k < len(heights) - 1 and sd <= max_rel_std * h_best)
    per_px = (h_best * shape).astype(np.float32)
    none = np.zeros(own.shape, bool)
    if not ok:  # no vote: neither its painted height nor its top is made
        return _Result(RenderedObject(label, n_px, best.zone_px, math.nan, math.nan, "", math.nan, 0), crop, none,
                       none, none, per_px)
    # the object's height as its painted median (a flat top: H; the network's shape: H times its median share)
    h_med = float(np.median(per_px[footprint])) if footprint.any() else h_best
    record = RenderedObject(label, n_px, best.zone_px, h_med, sd * h_med / h_best, family, h_best / h_obj,
                            int(spill.sum()) if trim else 0)
    # painted: the object's top, where the network's own shape reaches half its height (not its blurred rim)
    top = footprint & (np.where(footprint, base, 0.0) >= np.float32(settings.top_share) * np.float32(
        np.percentile(base[footprint], 90) if footprint.any() else 0.0))
    return _Result(record, crop, top, footprint, spill if trim else none, per_px)


__all__ = ["RenderSettings", "RenderedHeights", "RenderedObject", "pixel_evidence", "rendered_heights"]
