"""Heights from the sun: shadow geometry that needs no training data.

An object of height ``h`` casts a shadow ``h / tan(elevation)`` long away from the sun's azimuth, and the
sun is one pair of numbers for a whole flight. This package (numpy and scipy; its per-pixel loops compiled with
numba, :mod:`aerialmtl.sun.kernels`) casts shadows from known heights (:func:`cast_shadow_mask`), scores how
shadow-like pixels look (:func:`shadow_score`, :class:`ShadowModel`), fits the sun on an area with reference
heights (:func:`fit_sun`), measures heights from shadow runs next to objects (:func:`shadow_heights`), chooses
each object's height by rendering the whole map's cast shadows and comparing them with the image's
(:func:`rendered_heights`) and fuses them into a height map inside objects only (:func:`fuse_heights`,
:func:`fuse_rendered`). Angles: azimuth towards the sun, clockwise from grid north; rasters north-up.
A differentiable cast shadow for self-supervised steps is in :mod:`aerialmtl.sun.soft` (imports torch; not
imported here).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from aerialmtl.sun.cast import cast_shadow_mask
    from aerialmtl.sun.colour import ShadowModel, shadow_score
    from aerialmtl.sun.fit import SunFit, fit_sun, fit_sun_patches
    from aerialmtl.sun.fusion import fuse_heights, fuse_rendered
    from aerialmtl.sun.heights import ShadowHeights, ShadowObject, shadow_heights
    from aerialmtl.sun.position import Sun
    from aerialmtl.sun.render import RenderedHeights, RenderSettings, rendered_heights

#: Where each public name lives. The package imports a module when one of its names is first asked for
#: (PEP 562), so that reading a checkpoint (its sun record, :mod:`aerialmtl.sun.record`) or a sun's angles
#: does not import scipy and the numba kernels (~0.45 s) for a run that casts no shadow.
_OWNERS = {
    "cast_shadow_mask": "cast",
    "ShadowModel": "colour",
    "shadow_score": "colour",
    "SunFit": "fit",
    "fit_sun": "fit",
    "fit_sun_patches": "fit",
    "fuse_heights": "fusion",
    "fuse_rendered": "fusion",
    "RenderedHeights": "render",
    "RenderSettings": "render",
    "rendered_heights": "render",
    "ShadowHeights": "heights",
    "ShadowObject": "heights",
    "shadow_heights": "heights",
    "Sun": "position",
}


def __getattr__(name: str) -> Any:
    module = _OWNERS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


__all__ = [
    "RenderSettings",
    "RenderedHeights",
    "ShadowHeights",
    "ShadowModel",
    "ShadowObject",
    "Sun",
    "SunFit",
    "cast_shadow_mask",
    "fit_sun",
    "fit_sun_patches",
    "fuse_heights",
    "fuse_rendered",
    "rendered_heights",
    "shadow_heights",
    "shadow_score",
]
