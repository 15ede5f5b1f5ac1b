"""Turn a synthetic scene into an RGB orthophoto: sun illumination, cast shadows, optics and noise."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from aerialmtl.data.synth.scene_parts import Scene
from aerialmtl.data.synth.shading import cast_shadows, hillshade

#: Fraction of flat-ground brightness that remains in shadow (sky light only).
AMBIENT = 0.45
#: Sky light is bluer than sunlight: per-channel (R, G, B) factor on the ambient part.
_SKY_TINT = np.array([0.93, 0.98, 1.08], np.float32)


def render_ortho(scene: Scene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Illuminate the scene's albedo with the sun and sky, blur slightly and add sensor noise.

    Each pixel receives ``albedo × (AMBIENT·tint + (1 − AMBIENT)·direct)`` with ``direct`` the
    :func:`hillshade` of the DSM (1 on flat ground) set to 0 in cast shadows, so shadowed ground is
    about 0.45× as bright as sunlit ground and roof sides facing away from the sun are darker.

    Args:
        scene: the rasterised scene.
        rng: generator for the exposure and sensor noise.

    Returns:
        (ortho, shadow): uint8 (3, H, W) RGB image and bool (H, W) cast-shadow mask.
    """
    dsm = scene.dtm + scene.ndsm
    direct = hillshade(dsm, scene.gsd, scene.sun_azimuth, scene.sun_elevation)
    shadow = cast_shadows(dsm, scene.gsd, scene.sun_azimuth, scene.sun_elevation)
    direct[shadow] = 0.0
    np.minimum(direct, 1.6, out=direct)
    direct *= np.float32(1.0 - AMBIENT)
    exposure = np.float32(rng.uniform(0.92, 1.08))
    haze = np.array([6, 8, 12], np.float32) * np.float32(rng.uniform(0.5, 1.5))
    out = np.empty(scene.albedo.shape, np.uint8)
    for ch in range(3):
        band = scene.albedo[ch] * (direct + AMBIENT * _SKY_TINT[ch])
        band = ndimage.gaussian_filter(band, sigma=0.5, truncate=3.0)  # lens / resampling blur
        band *= exposure
        band += haze[ch]
        band += rng.standard_normal(band.shape, dtype=np.float32) * np.float32(2.0)
        np.clip(np.rint(band), 0, 255, out=band)
        out[ch] = band
    return out, shadow
