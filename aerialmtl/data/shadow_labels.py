"""Labels of the shadow head (``model.shadow_head``): the cast shadows of the training heights at the training sun.

A pixel's label is 1 where the reference heights cast a shadow on it at the sun the training area was fitted with
(:func:`aerialmtl.sun.cast.cast_shadow_mask`), 0 where they do not, and :data:`SHADOW_IGNORE` where it is not known:

* its own height is unknown (nodata, or the image is invalid there);
* an occluder it cannot see might stand towards the sun: beyond the raster's edge, or on pixels of unknown height,
  within the longest shadow the known heights allow. Such a pixel is labelled only when the answer is the same
  with every unknown height at the ground (nothing there) and at the tallest known height (capped at
  :data:`CAP_M`): the border facing the sun is ignored, as deep as the tallest object's shadow, except where a
  known occluder already shades the pixel or the pixel is itself too high to be shaded.

By construction the labels are *cast* shadow only: a roof's slope facing away from the sun, water and dark roofs are
0. Patches of a tile folder overlap on one grid, so :func:`patch_labels` pieces them together into one mosaic
(the tile grid, ``row_off``/``col_off`` of the manifest) and casts the shadows there: a patch then sees the
occluders of its neighbours, and only the mosaic's own edges (and the pixels next to other splits, whose heights
training must not see) are unknown. The labels are made once per run, before the augmentations, which move them
with the image (:mod:`aerialmtl.data.batches`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from aerialmtl.sun.cast import cast_shadow_mask
from aerialmtl.sun.position import Sun

#: The label of a pixel whose shadow is not known (the shadow head's loss skips it).
SHADOW_IGNORE = 255

#: Metres: the tallest unknown occluder assumed beyond the known heights (the known maximum, at most this).
CAP_M = 50.0

#: The largest mosaic (pixels) :func:`patch_labels` pieces together; a larger area is labelled patch by patch.
MAX_MOSAIC_PIXELS = 64_000_000


def shadow_labels(height: np.ndarray, gsd_m: float, sun: Sun, cap_m: float | None = None) -> np.ndarray:
    """uint8 labels (H, W) of float32 heights (H, W) in metres (NaN unknown): 1 cast shadow, 0 lit,
    :data:`SHADOW_IGNORE` unknown (see the module docstring).

    Args:
        height: the reference heights (an nDSM), NaN where unknown.
        gsd_m: pixel size, metres.
        sun: the sun on the raster's grid.
        cap_m: the tallest unknown occluder assumed (metres); default the largest known height, at most
            :data:`CAP_M`.
    """
    z = np.asarray(height, dtype=np.float32)
    known = np.isfinite(z)
    if not known.any():
        return np.full(z.shape, SHADOW_IGNORE, np.uint8)
    top = float(np.max(z[known]))
    cap = min(top, CAP_M) if cap_m is None else float(cap_m)
    cap = max(cap, 0.0)
    # the deepest shadow an unknown occluder of the cap could throw inside, in pixels (the border of unknowns)
    reach = int(math.ceil(cap / (sun.tan_elevation * gsd_m))) + 1 if cap > 0 else 1
    pad = np.full((z.shape[0] + 2 * reach, z.shape[1] + 2 * reach), np.nan, np.float32)
    pad[reach:-reach, reach:-reach] = z
    none = cast_shadow_mask(pad, gsd_m, sun)  # unknown heights occlude nothing
    walls = cast_shadow_mask(np.where(np.isnan(pad), np.float32(cap), pad), gsd_m, sun)  # ... or up to the cap
    inner = np.s_[reach:-reach, reach:-reach]
    lab = none[inner].astype(np.uint8)
    lab[(none[inner] != walls[inner]) | ~known] = SHADOW_IGNORE
    return lab


def patch_labels(heights: np.ndarray, gsd_m: float, sun: Sun,
                 offsets: Sequence[tuple[int, int]] | None = None) -> np.ndarray:
    """uint8 (N, H, W) labels of N patches' heights (N, H, W) or (N, 1, H, W), metres, NaN unknown.

    With ``offsets`` (each patch's (row, column) on the tile grid) the patches are pieced into one mosaic and
    labelled there (:func:`shadow_labels` of the mosaic, then cut back), so that a patch sees its neighbours'
    occluders; without (or for a mosaic over :data:`MAX_MOSAIC_PIXELS`) each patch is labelled alone. The cap
    is the largest known height of all the patches (at most :data:`CAP_M`).
    """
    z = np.asarray(heights, dtype=np.float32)
    if z.ndim == 4:
        z = z[:, 0]
    n, h, w = z.shape
    out = np.empty((n, h, w), np.uint8)
    if n == 0:
        return out
    finite = z[np.isfinite(z)]
    cap = min(float(finite.max()), CAP_M) if finite.size else 0.0
    if offsets is not None and len(offsets) == n:
        rows = np.array([o[0] for o in offsets], np.int64)
        cols = np.array([o[1] for o in offsets], np.int64)
        r0, c0 = int(rows.min()), int(cols.min())
        mh, mw = int(rows.max()) - r0 + h, int(cols.max()) - c0 + w
        if mh * mw <= MAX_MOSAIC_PIXELS:
            mosaic = np.full((mh, mw), np.nan, np.float32)
            for i in range(n):
                r, c = rows[i] - r0, cols[i] - c0
                tile = z[i]
                view = mosaic[r:r + h, c:c + w]
                np.copyto(view, tile, where=np.isfinite(tile))
            lab = shadow_labels(mosaic, gsd_m, sun, cap)
            for i in range(n):
                r, c = rows[i] - r0, cols[i] - c0
                out[i] = lab[r:r + h, c:c + w]
                out[i][~np.isfinite(z[i])] = SHADOW_IGNORE
            return out
    for i in range(n):
        out[i] = shadow_labels(z[i], gsd_m, sun, cap)
    return out


def split_labels(heights: np.ndarray, rows: Sequence[dict[str, str]], gsd_m: float, sun: Sun) -> np.ndarray:
    """uint8 (N, H, W) labels of a split's cached heights (N, 1, H, W) (:class:`~aerialmtl.data.cache.PatchCache`),
    pieced together on the tile grid of its manifest ``rows`` (``row_off``/``col_off``; patch by patch where the
    manifest lacks them), by :func:`patch_labels`.
    """
    try:
        offsets: list[tuple[int, int]] | None = [(int(r["row_off"]), int(r["col_off"])) for r in rows]
    except (KeyError, TypeError, ValueError):
        offsets = None
    if offsets is not None and len(offsets) != len(heights):
        offsets = None
    return patch_labels(np.asarray(heights), gsd_m, sun, offsets)


__all__ = ["CAP_M", "MAX_MOSAIC_PIXELS", "SHADOW_IGNORE", "patch_labels", "shadow_labels", "split_labels"]
