"""Fuse shadow heights into a height map, inside objects only, weighted by both spreads (never raising flat ground)."""

from __future__ import annotations

import numpy as np

from aerialmtl.errors import InputError
from aerialmtl.sun.heights import ShadowHeights
from aerialmtl.sun.render import RenderedHeights

#: Least shadow spread used as a weight, metres (a zero spread would override the network entirely).
MIN_SHADOW_STD_M = 0.1


def inverse_variance(h1: np.ndarray, s1: np.ndarray, h2: np.ndarray,
                     s2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float64 ``(height, spread)`` of two estimates ``h1 ± s1`` and ``h2 ± s2`` (metres, any one shape) combined
    with weights ``w = 1 / s²``: ``(w1·h1 + w2·h2) / (w1 + w2)``, and the spread of the two-part mixture,
    ``sqrt(1 / (w1 + w2) + w1·w2·(h1 − h2)² / (w1 + w2)²)``, which grows with their disagreement.
    """
    w1, w2 = 1.0 / s1 ** 2, 1.0 / s2 ** 2
    fused = (w1 * h1 + w2 * h2) / (w1 + w2)
    var = 1.0 / (w1 + w2) + w1 * w2 * (h1 - h2) ** 2 / (w1 + w2) ** 2
    return fused, np.sqrt(var)


def fuse_heights(height: np.ndarray, std: np.ndarray, shadow: ShadowHeights,
                 objects: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move each measured object's heights towards its shadow height, in proportion to the two spreads.

    Per object with a shadow height ``hs ± ss``: ``h_obj`` = median network height over the object; each pixel
    ``p`` gets the shadow's estimate of it under the object's own shape, ``hs_p = hs · h(p) / h_obj`` (spread
    ``ss_p = ss · h(p) / h_obj``), and the inverse-variance mean of ``h(p) ± s(p)`` and ``hs_p ± ss_p``, with
    weights ``w = 1 / s²``: ``h_f = (w1·h + w2·hs_p) / (w1 + w2)``. Its spread is the spread of that two-part
    mixture, ``s_f² = 1 / (w1 + w2) + w1·w2·(h − hs_p)² / (w1 + w2)²``: it grows with the disagreement.

    Args:
        height: float (H, W) network heights, metres (NaN = nodata).
        std: float (H, W) their spread, metres.
        shadow: :func:`~aerialmtl.sun.shadow_heights` of the same objects.
        objects: int (H, W) object labels (0 = none), those given to :func:`~aerialmtl.sun.shadow_heights`.

    Returns:
        ``(height, std)`` float32 (H, W). Pixels outside objects, in objects without a shadow height, and where
        the height or spread is NaN or the spread ≤ 0 keep the network's values exactly.
    """
    h = np.asarray(height, dtype=np.float32)
    s = np.asarray(std, dtype=np.float32)
    labels = np.asarray(objects)
    if not h.shape == s.shape == labels.shape == shadow.height.shape:
        raise InputError(f"'height', 'std', 'objects' and the shadow heights must share one (H, W) shape, got "
                         f"{h.shape}, {s.shape}, {labels.shape} and {shadow.height.shape}")
    out_h, out_s = h.copy(), s.copy()
    hs_all, ss_all = shadow.height, shadow.std
    use = (labels != 0) & np.isfinite(hs_all) & np.isfinite(ss_all) & np.isfinite(h) & np.isfinite(s) & (s > 0)
    if not use.any():
        return out_h, out_s
    lab = labels[use]
    hp, sp = h[use].astype(np.float64), s[use].astype(np.float64)
    hs, ss = hs_all[use].astype(np.float64), np.maximum(ss_all[use].astype(np.float64), MIN_SHADOW_STD_M)
    order = np.argsort(lab, kind="stable")
    uniq, first = np.unique(lab[order], return_index=True)
    bounds = np.append(first, len(order))
    h_obj = np.empty(len(lab))
    for i in range(len(uniq)):
        idx = order[bounds[i]: bounds[i + 1]]
        h_obj[idx] = np.median(hp[idx])
    ok = h_obj > 0
    ratio = np.where(ok, hp / np.where(ok, h_obj, 1.0), 1.0)
    hs_p, ss_p = hs * ratio, np.maximum(ss * ratio, MIN_SHADOW_STD_M)
    fused, sd = inverse_variance(hp, sp, hs_p, ss_p)
    out_h[use] = np.where(ok, fused, hp).astype(np.float32)
    out_s[use] = np.where(ok, sd, sp).astype(np.float32)
    return out_h, out_s


#: The spread given to "ground" where rendering took an object's pixels as its spill into its own shadow, metres.
SPILL_STD_M = 1.0


def fuse_rendered(height: np.ndarray, std: np.ndarray, rendered: RenderedHeights,
                  spill_std_m: float = SPILL_STD_M) -> tuple[np.ndarray, np.ndarray]:
    """Fuse heights chosen by rendering (:func:`aerialmtl.sun.render.rendered_heights`) into a height map.

    On each measured object's pixels the rendered height ``hs ± ss`` (per pixel) and the network's ``h ± s`` are
    combined by inverse variance, as :func:`fuse_heights` does: ``h_f = (h/s² + hs/ss²) / (1/s² + 1/ss²)``, with
    the spread of the two-part mixture, which grows with their disagreement. On the object's spill (its pixels
    the rendering took as ground in its own shadow) the second estimate is the ground, ``0 ± spill_std_m``, and it
    can only lower the pixel. Flat ground is never raised: every other pixel keeps the network's values exactly.

    Args:
        height: float (H, W) network heights, metres (NaN = nodata). std: float (H, W) their spread, metres.
        rendered: the rendered heights of the same map. spill_std_m: the ground's spread on spill pixels.

    Returns:
        ``(height, std)`` float32 (H, W).
    """
    h = np.asarray(height, dtype=np.float32)
    s = np.asarray(std, dtype=np.float32)
    if not h.shape == s.shape == rendered.height.shape:
        raise InputError(f"'height', 'std' and the rendered heights must share one (H, W) shape, got {h.shape}, "
                         f"{s.shape} and {rendered.height.shape}")
    out_h, out_s = h.copy(), s.copy()
    ok = np.isfinite(h) & np.isfinite(s) & (s > 0)
    top = ok & np.isfinite(rendered.height) & np.isfinite(rendered.std)
    spill = ok & rendered.spill & ~top
    for where, est, est_sd in ((top, rendered.height, rendered.std), (spill, None, None)):
        if not where.any():
            continue
        hp, sp = h[where].astype(np.float64), s[where].astype(np.float64)
        if est is None or est_sd is None:
            hs, ss = np.zeros_like(hp), np.full_like(hp, float(spill_std_m))
        else:
            hs = est[where].astype(np.float64)
            ss = np.maximum(est_sd[where].astype(np.float64), MIN_SHADOW_STD_M)
        fused, sd = inverse_variance(hp, sp, hs, ss)
        if est is None:
            fused = np.minimum(fused, hp)
        out_h[where] = fused.astype(np.float32)
        out_s[where] = sd.astype(np.float32)
    return out_h, out_s
