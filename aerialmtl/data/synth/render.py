"""Turn a synthetic scene into an RGB orthophoto: sun illumination, cast shadows, optics and noise."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from aerialmtl.data.synth.scene_parts import Scene
from aerialmtl.data.synth.shading import Sky, direct_sun

#: Fraction of flat-ground brightness that remains in shadow (sky light only), in the town.
AMBIENT = 0.45
#: Sky light is bluer than sunlight: per-channel (R, G, B) factor on the ambient part, in the town.
SKY_TINT = (0.93, 0.98, 1.08)


def render_ortho(scene: Scene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Illuminate the scene's albedo with the sun and sky, blur slightly and add sensor noise.

    Each pixel receives ``albedo × (AMBIENT·tint + (1 − AMBIENT)·direct)`` (:class:`~.shading.Sky`) with
    ``direct`` the sun on the DSM (:func:`~.shading.direct_sun`: 1 on flat ground, 0 in cast shadows), so
    shadowed ground is about 0.45× as bright as sunlit ground and roof sides facing away from the sun are darker.

    Args:
        scene: the rasterised scene.
        rng: generator for the exposure and sensor noise.

    Returns:
        (ortho, shadow): uint8 (3, H, W) RGB image and bool (H, W) cast-shadow mask.
    """
    direct, shadow = direct_sun(scene.dtm + scene.ndsm, scene.gsd, scene.sun_azimuth, scene.sun_elevation)
    sky = Sky(AMBIENT, SKY_TINT)
    exposure = np.float32(rng.uniform(0.92, 1.08))
    haze = np.array([6, 8, 12], np.float32) * np.float32(rng.uniform(0.5, 1.5))
    out = np.empty(scene.albedo.shape, np.uint8)
    for ch in range(3):
        band = scene.albedo[ch] * sky.band(direct, ch)
        band = ndimage.gaussian_filter(band, sigma=0.5, truncate=3.0)  # lens / resampling blur
        band *= exposure
        band += haze[ch]
        band += rng.standard_normal(band.shape, dtype=np.float32) * np.float32(2.0)
        np.clip(np.rint(band), 0, 255, out=band)
        out[ch] = band
    return out, shadow
