"""Fit the sun on an area with reference heights: the (azimuth, elevation) whose cast shadows best match the image.

Objective: Pearson correlation, over ground pixels (reference height < ``ground_m``), between the image's
:func:`~aerialmtl.sun.colour.shadow_score` and the cast-shadow mask of the heights at a candidate sun
(a point-biserial correlation). Rank (AUC) and best-threshold-overlap objectives were dropped: they prefer
very small or very large masks (design note ``heights-from-shadows``). Search: a coarse grid (10° azimuth ×
5° elevation), then 2° × 1° and 0.5° × 0.25° grids around the best point; the suns of a grid are scored on up to
:data:`GRID_THREADS` threads (the shadow sweep releases the GIL; each sun's score is computed as alone, so the
fit is the same on any number of threads).

**Sharpness** = ``(r* − r30) / r*``, where ``r*`` is the correlation at the optimum and ``r30`` the best
correlation of the coarse grid at azimuths 30° or more from the optimum (any elevation): 0 = another
direction explains the shadows as well, 1 = nothing else explains them at all. A fit is **clear** when
``r* ≥ min_score``, sharpness ≥ ``min_sharpness`` and the elevation is not at the edge of the searched range.

Limits: any city's heights correlate a little with any city's image. On 128–256 px synthetic patches, the heights
of another patch reached r = 0.13–0.35, and 4 of 9 such mismatched pairs still gave a "clear" (wrong) sun; a
null from the same heights flipped was tried and dropped (grid-like layouts are nearly symmetric: flipped heights
scored 0.55 against 0.57 for the right ones). Larger areas lower the chance correlation; the fit is meant for
an orthophoto and the heights of the same area.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from aerialmtl.cpuinfo import usable_cpus
from aerialmtl.errors import InputError
from aerialmtl.sun._patches import ArrayOrList, as_patches
from aerialmtl.sun.cast import TOL_M, sweep_stack
from aerialmtl.sun.colour import shadow_score
from aerialmtl.sun.position import Sun, as_float

#: Most threads scoring the suns of a grid (each holds a float32 shadow surface of the training area; on 2 cores of
#: an AMD EPYC, 1024² area: 2.5 ms per sun on one thread, 1.2-1.7 on four).
GRID_THREADS = 4
#: Reference heights below this (metres) are ground where the correlation is taken.
GROUND_M = 0.5
#: Defaults of a clear fit: the least correlation and the least sharpness.
MIN_SCORE = 0.1
MIN_SHARPNESS = 0.08
#: Azimuth distance (degrees) of the alternative the sharpness compares with.
SHARPNESS_AWAY_DEG = 30.0


@dataclass(frozen=True)
class SunFit:
    """The outcome of :func:`fit_sun`.

    Attributes:
        sun: the fitted sun, or ``None`` when there is no clear optimum (the feature must switch off).
        score: correlation at the optimum (−1…1; NaN when no sun casts any shadow on ground).
        sharpness: ``(r* − r30) / r*`` (see the module docstring), 0…1 (NaN when undefined).
        clear: whether the optimum is clear (``sun`` is then set).
        reason: one line for the user: the sun and how sharp, or why none.
        best: the optimum even when it is not clear (diagnostics), ``None`` when nothing cast a shadow.
    """

    sun: Sun | None
    score: float
    sharpness: float
    clear: bool
    reason: str
    best: Sun | None = None

    def to_dict(self) -> dict[str, object]:
        """Plain JSON/YAML types (suns as dicts or ``None``, NaN as ``None``)."""
        return {"sun": None if self.sun is None else self.sun.to_dict(), "score": _num(self.score),
                "sharpness": _num(self.sharpness), "clear": bool(self.clear), "reason": str(self.reason),
                "best": None if self.best is None else self.best.to_dict()}

    @classmethod
    def from_dict(cls, d: Mapping[str, object]) -> SunFit:
        """Inverse of :meth:`to_dict`."""
        def sun(v: object) -> Sun | None:
            if v is None:
                return None
            if not isinstance(v, Mapping):
                raise TypeError(f"a sun record must be a mapping, got {v!r}")
            return Sun.from_dict(v)

        def num(v: object) -> float:
            return math.nan if v is None else as_float(v)

        try:
            return cls(sun=sun(d["sun"]), score=num(d["score"]), sharpness=num(d["sharpness"]),
                       clear=bool(d["clear"]), reason=str(d["reason"]), best=sun(d.get("best")))
        except KeyError as exc:
            raise InputError(f"not a sun-fit record: missing {exc}; keys {sorted(d)}") from exc


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


class _Objective:
    """Correlation of the shadow score with the cast-shadow mask over ground pixels, for any sun; patches of one
    shape are stacked so that one sweep casts the shadows of all of them.
    """

    def __init__(self, rgb: ArrayOrList, height: ArrayOrList, gsd_m: float, valid: ArrayOrList | None,
                 ground_m: float) -> None:
        self.gsd = float(gsd_m)
        groups: dict[tuple[int, int], list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
        n = s1 = s2 = 0.0
        for im, h, ok in as_patches(rgb, height, valid):
            s = shadow_score(im).astype(np.float64)
            ground = ok & (h < ground_m)
            groups.setdefault(h.shape, []).append((h, s, ground))
            n += float(ground.sum())
            s1 += float(s[ground].sum())
            s2 += float((s[ground] ** 2).sum())
        # per patch shape: heights float32 with NaN as -inf (what casting a shadow reads), scores, ground
        self.stacks = [(np.ascontiguousarray(np.nan_to_num(np.stack([h for h, _, _ in g]).astype(np.float32),
                                                           nan=-np.inf, posinf=np.inf, neginf=-np.inf)),
                        np.stack([np.where(gr, s, 0.0) for _, s, gr in g]),
                        np.stack([gr for _, _, gr in g])) for g in groups.values()]
        self.n, self.s1 = n, s1
        self.var = s2 - s1 * s1 / n if n > 0 else 0.0
        self.cache: dict[tuple[float, float], float] = {}

    @staticmethod
    def key(az: float, el: float) -> tuple[float, float]:
        """The cache's key of a sun: azimuth modulo 360°, both to 1e-4 degree."""
        return round(az % 360.0, 4), round(el, 4)

    def __call__(self, az: float, el: float) -> float:
        key = self.key(az, el)
        if key not in self.cache:
            self.cache[key] = self._corr(Sun(*key))
        return self.cache[key]

    def score(self, suns: Sequence[tuple[float, float]]) -> None:
        """Score the ``(azimuth, elevation)`` pairs not scored yet, on up to :data:`GRID_THREADS` threads."""
        keys = list(dict.fromkeys(self.key(az, el) for az, el in suns))
        todo = [k for k in keys if k not in self.cache]
        threads = min(GRID_THREADS, usable_cpus(), len(todo))
        if threads <= 1:
            scores = [self._corr(Sun(*k)) for k in todo]
        else:
            with ThreadPoolExecutor(threads, thread_name_prefix="sun-grid") as pool:
                scores = list(pool.map(lambda k: self._corr(Sun(*k)), todo))
        self.cache.update(zip(todo, scores))

    def _corr(self, sun: Sun) -> float:
        """The correlation at ``sun``: each stack's shadow surface swept, then its shaded ground pixels counted and
        their scores summed in one compiled pass (:func:`aerialmtl.sun.kernels.shadow_sums`; the pixels of
        :func:`~aerialmtl.sun.cast.cast_shadow_mask` and ground, their sum within ~1e-15 relative of numpy's).
        """
        from aerialmtl.sun.kernels import shadow_sums  # numba: imported when a sun is first scored

        m1 = sm = 0.0
        for z, s, ground in self.stacks:
            count, total = shadow_sums(z, sweep_stack(z, self.gsd, sun.azimuth_deg, sun.elevation_deg), ground, s,
                                       np.float32(TOL_M))
            m1 += float(count)
            sm += float(total)
        var_m = m1 - m1 * m1 / self.n if self.n > 0 else 0.0
        if var_m <= 0 or self.var <= 1e-12 * max(self.n, 1.0):  # no shadow cast, or an image without contrast
            return math.nan
        return (sm - self.s1 * m1 / self.n) / math.sqrt(self.var * var_m)


def _grid(f: _Objective, azs: Sequence[float], els: Sequence[float]) -> tuple[float, float, float]:
    f.score([(az, el) for el in els for az in azs])
    best = (-math.inf, 0.0, 0.0)
    for el in els:
        for az in azs:
            r = f(az, el)
            if math.isfinite(r) and r > best[0]:
                best = (r, az % 360.0, el)
    return best


def _sharpness(f: _Objective, r: float, azimuth_deg: float) -> tuple[float, float]:
    """``(sharpness, r_far)`` of an optimum ``r`` at ``azimuth_deg`` (module docstring): ``r_far`` the best score
    ``f`` has computed :data:`SHARPNESS_AWAY_DEG` or more of azimuth away (−inf when none).
    """
    far = [v for (a, _), v in f.cache.items()
           if math.isfinite(v) and abs((a - azimuth_deg + 180.0) % 360.0 - 180.0) >= SHARPNESS_AWAY_DEG]
    r_far = max(far) if far else -math.inf
    return ((r - r_far) / r if r > 0 and math.isfinite(r_far) else (1.0 if r > 0 else 0.0)), r_far


def _span(centre: float, half: float, step: float, lo: float = -math.inf, hi: float = math.inf) -> list[float]:
    k = int(round(half / step))
    return [v for v in (centre + i * step for i in range(-k, k + 1)) if lo <= v <= hi]


def fit_sun(rgb: ArrayOrList, height: ArrayOrList, gsd_m: float, valid: ArrayOrList | None = None, *,
            elevation_range: tuple[float, float] = (10.0, 80.0), min_score: float = MIN_SCORE,
            min_sharpness: float = MIN_SHARPNESS, ground_m: float = GROUND_M) -> SunFit:
    """Fit the sun on an area whose heights above ground are known.

    Args:
        rgb: (3, H, W) image (uint8 or float 0–1), or a sequence of such patches.
        height: float (H, W) reference heights above ground in metres (NaN = invalid), or a sequence (one per
            patch, same shapes as the images).
        gsd_m: pixel size in metres (every patch).
        valid: optional bool (H, W) mask(s) of usable pixels (and-ed with finite heights).
        elevation_range: elevations searched, degrees; an optimum at either end is not clear.
        min_score, min_sharpness: what makes a fit clear (module docstring).
        ground_m: heights below this are ground pixels, where the correlation is taken.

    Returns:
        :class:`SunFit`; ``sun`` is ``None`` unless the optimum is clear.
    """
    lo, hi = elevation_range
    if not 0.0 < lo < hi < 90.0:
        raise InputError(f"'elevation_range' must be (lo, hi) with 0 < lo < hi < 90 degrees, got {elevation_range}",
                         param="elevation_range")
    f = _Objective(rgb, height, gsd_m, valid, ground_m)
    if f.n > 0 and f.var <= 1e-12 * f.n:
        return SunFit(None, math.nan, math.nan, False, "no sun fitted: the image has no contrast on the ground pixels "
                      "(one colour everywhere): nothing to see shadows in")
    coarse_az = [10.0 * i for i in range(36)]
    coarse_el = _span((lo + hi) / 2, (hi - lo) / 2, 5.0, lo, hi) or [lo, hi]
    r0, az0, el0 = _grid(f, coarse_az, coarse_el)
    if not math.isfinite(r0):
        return SunFit(None, math.nan, math.nan, False, "no sun fitted: the heights cast no shadow on ground pixels "
                      "at any sun (a flat area, or no valid ground pixels)")
    r1, az1, el1 = _grid(f, _span(az0, 10.0, 2.0), _span(el0, 5.0, 1.0, lo, hi))
    r, az, el = _grid(f, _span(az1, 2.0, 0.5), _span(el1, 1.0, 0.25, lo, hi))
    best = Sun(round(az % 360.0, 4), el)
    sharp, r_far = _sharpness(f, r, best.azimuth_deg)
    at_edge = el <= lo + 0.5 or el >= hi - 0.5
    desc = (f"best azimuth {best.azimuth_deg:.0f}°, elevation {best.elevation_deg:.0f}° scores r = {r:.2f}, "
            f"the best sun {SHARPNESS_AWAY_DEG:.0f}° or more of azimuth away {r_far:.2f} (sharpness {sharp:.2f})")
    if r < min_score:
        reason = (f"no sun fitted: the image's shadows do not follow the heights ({desc}, under {min_score}): "
                  "overcast light, a mosaic of flights, or heights that do not match the image")
    elif sharp < min_sharpness:
        reason = (f"no sun fitted: no clear optimum ({desc}, under {min_sharpness}): a sun near the zenith, "
                  "too few shadows, or heights that do not match the image")
    elif at_edge and el <= lo + 0.5:
        reason = (f"no sun fitted: the optimum lies at the lowest elevation searched, {lo:g}° ({desc}): long masks "
                  "over dark ground (water, dark roofs) or shadows of objects outside the heights explain the image "
                  "better than the heights do")
    elif at_edge:
        reason = (f"no sun fitted: the optimum lies at the highest elevation searched, {hi:g}° ({desc}): a sun "
                  "near the zenith casts too little shadow to fit")
    else:
        return SunFit(best, r, sharp, True, f"sun fitted: azimuth {best.azimuth_deg:.0f}°, elevation "
                      f"{best.elevation_deg:.0f}° (r = {r:.2f}; sharp: the best sun {SHARPNESS_AWAY_DEG:.0f}° or "
                      f"more of azimuth away scores {r_far:.2f}, sharpness {sharp:.2f})", best)
    return SunFit(None, r, sharp, False, reason, best)


class AzimuthCheck(NamedTuple):
    """What :func:`check_azimuth` found: ``found`` the azimuth the image's shadows fall at (degrees, None when the
    fit is not clear), ``score`` the best sun's correlation, ``given_score`` the best correlation of the azimuth
    checked at any elevation (NaN when none casts a shadow on ground).
    """

    found: float | None
    score: float
    given_score: float


#: The elevations (degrees) :func:`check_azimuth` searches and scores the given azimuth at.
CHECK_ELEVATIONS = tuple(float(e) for e in range(10, 81, 10))


def check_azimuth(rgb: np.ndarray, height: np.ndarray, gsd_m: float, azimuth_deg: float,
                  valid: np.ndarray | None = None, *, min_score: float = MIN_SCORE,
                  min_sharpness: float = MIN_SHARPNESS, ground_m: float = GROUND_M) -> AzimuthCheck:
    """Where an image's shadows fall, to check a sun taken on trust: :func:`fit_sun`'s objective searched coarsely
    (every 10° of azimuth at :data:`CHECK_ELEVATIONS`, then 2° × 5° within 10° of the best, then 1° × 2.5°: about
    370 suns, where the full :func:`fit_sun` and a second score of the given azimuth took 760 on two objectives),
    and the given azimuth scored at the same elevations. Good to the few degrees a check needs: on a weak-contrast
    synthetic town whose objective is flat within 1 % over 149–156°, it finds 156° where :func:`fit_sun` finds 149°
    (true 150°).

    The fit is clear as in :func:`fit_sun`: correlation ≥ ``min_score``, sharpness ≥ ``min_sharpness`` against the
    best sun 30° or more of azimuth away, the elevation not at an end of the search. Arguments as :func:`fit_sun`
    (``rgb`` (3, H, W), ``height`` float (H, W) metres, ``valid`` bool (H, W)).
    """
    f = _Objective(rgb, height, gsd_m, valid, ground_m)
    els = list(CHECK_ELEVATIONS)
    f.score([(azimuth_deg, el) for el in els])
    given = [f(azimuth_deg, el) for el in els]
    given_score = max((r for r in given if math.isfinite(r)), default=math.nan)
    if f.n > 0 and f.var <= 1e-12 * f.n:
        return AzimuthCheck(None, math.nan, given_score)
    r0, az0, el0 = _grid(f, [10.0 * i for i in range(36)], els)
    if not math.isfinite(r0):
        return AzimuthCheck(None, math.nan, given_score)
    _, az1, el1 = _grid(f, _span(az0, 10.0, 2.0), _span(el0, 10.0, 5.0, els[0], els[-1]))
    r, az, el = _grid(f, _span(az1, 2.0, 1.0), _span(el1, 2.5, 2.5, els[0], els[-1]))
    sharp, _ = _sharpness(f, r, az)
    clear = r >= min_score and sharp >= min_sharpness and els[0] < el < els[-1]
    return AzimuthCheck(round(az % 360.0, 4) if clear else None, r, given_score)


def fit_sun_patches(patches: Sequence[tuple[np.ndarray, ...]], gsd_m: float, *,
                    elevation_range: tuple[float, float] = (10.0, 80.0), min_score: float = MIN_SCORE,
                    min_sharpness: float = MIN_SHARPNESS, ground_m: float = GROUND_M) -> SunFit:
    """:func:`fit_sun` (same keywords) on a sequence of ``(rgb, height)`` or ``(rgb, height, valid)`` tuples."""
    rgbs = [p[0] for p in patches]
    heights = [p[1] for p in patches]
    valids = [p[2] if len(p) > 2 else np.ones(np.shape(p[1]), bool) for p in patches]
    return fit_sun(rgbs, heights, gsd_m, valids, elevation_range=elevation_range, min_score=min_score,
                   min_sharpness=min_sharpness, ground_m=ground_m)
