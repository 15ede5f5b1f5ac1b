"""One or several (rgb, height, valid) patches, as the fitting functions accept them."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from aerialmtl.errors import InputError

Patch = tuple[np.ndarray, np.ndarray, np.ndarray]
ArrayOrList = np.ndarray | Sequence[np.ndarray]


def as_patches(rgb: ArrayOrList, height: ArrayOrList, valid: ArrayOrList | None = None) -> list[Patch]:
    """Patches as ``(rgb (3, H, W), height float32 (H, W) with NaN where invalid, valid bool (H, W))``.

    ``rgb``/``height``/``valid`` are each one array or equally long sequences of arrays (one per patch).
    ``valid`` (default: all) is and-ed with the height being finite.
    """
    single = isinstance(rgb, np.ndarray) and rgb.ndim == 3
    rgbs = [rgb] if single else list(rgb)
    heights = [height] if single else list(height)
    valids: list[ArrayOrList | None] = ([None] * len(rgbs) if valid is None
                                        else [valid] if single else list(valid))
    if not len(rgbs) == len(heights) == len(valids):
        raise InputError(f"'rgb', 'height' and 'valid' must hold as many patches each, got {len(rgbs)}, "
                         f"{len(heights)} and {len(valids)}")
    out: list[Patch] = []
    for i, (im, h, v) in enumerate(zip(rgbs, heights, valids)):
        im = np.asarray(im)
        h = np.asarray(h, dtype=np.float32)
        if im.ndim != 3 or im.shape[0] != 3 or h.shape != im.shape[1:]:
            raise InputError(f"patch {i}: 'rgb' must be (3, H, W) and 'height' (H, W) on the same grid, got "
                             f"{im.shape} and {h.shape}")
        ok = np.isfinite(h)
        if v is not None:
            v = np.asarray(v, dtype=bool)
            if v.shape != h.shape:
                raise InputError(f"patch {i}: 'valid' must be (H, W) like 'height', got {v.shape} and {h.shape}")
            ok &= v
        out.append((im, np.where(ok, h, np.float32(np.nan)).astype(np.float32), ok))
    return out
