"""How a synthetic city is imaged: sun, camera lean and the look of the sensor and its processing.

:class:`CityStyle` holds the *ranges* a scene's imaging is drawn from; :meth:`CityStyle.draw` turns them
into one :class:`Imaging` (the concrete values of a scene), and :func:`finish_image` applies the
photometric part (white balance, haze, resampling, blur, noise, gamma, JPEG) to a rendered image. None
of it changes the scene's heights or labels.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from aerialmtl.data.synth.city_canvas import GROUND_ROOFS
from aerialmtl.errors import InputError


@dataclass(frozen=True)
class Imaging:
    """One scene's imaging conditions (drawn by :meth:`CityStyle.draw`).

    Attributes:
        sun_azimuth: degrees clockwise from north.
        sun_elevation: degrees above the horizon.
        lean_azimuth: direction in which tall things are displaced (away from nadir), degrees from north.
        lean_tan: tangent of the view angle from the vertical (0 = true orthophoto); a point ``h`` metres
            high is drawn ``h · lean_tan`` metres away from its footprint.
        gains: (R, G, B) white-balance / exposure factors.
        haze: fraction of the image replaced by the airlight ``haze_rgb`` (0 = clear).
        haze_rgb: airlight colour in DN.
        resample: native pixel size ÷ output pixel size (≥ 1: the image was upsampled by this factor).
        blur: Gaussian blur sigma in output pixels.
        noise: sensor noise standard deviation in DN.
        gamma: tone curve exponent on [0, 1] values (1 = linear).
        jpeg_quality: JPEG quality 1–95 of a final compression round trip, or 0 for none.
    """

    sun_azimuth: float
    sun_elevation: float
    lean_azimuth: float
    lean_tan: float
    gains: tuple[float, float, float] = (1.0, 1.0, 1.0)
    haze: float = 0.0
    haze_rgb: tuple[float, float, float] = (200.0, 205.0, 215.0)
    resample: float = 1.0
    blur: float = 0.0
    noise: float = 0.0
    gamma: float = 1.0
    jpeg_quality: int = 0


def _check_range(name: str, lo: float, hi: float, low: float, high: float) -> None:
    if not (low <= lo <= hi <= high):
        raise InputError(f"CityStyle.{name} must be (lo, hi) with {low} ≤ lo ≤ hi ≤ {high}, got ({lo}, {hi})",
                         param=name)


@dataclass(frozen=True)
class CityStyle:
    """Ranges a synthetic city's imaging is drawn from (uniform in each range unless said otherwise).

    Attributes:
        sun_elevation: degrees above the horizon.
        sun_azimuth: degrees clockwise from north.
        lean_tan: tangent of the view angle (relief displacement); 0.6 ≈ 31°, the edge of a wide-angle
            frame; ``(0, 0)`` gives true orthophotos.
        true_ortho: probability that a scene is a true orthophoto (no lean) whatever ``lean_tan`` says.
        gain: per-channel white balance / exposure factor.
        haze: fraction of airlight mixed in.
        resample: native-to-output pixel size factor (drawn log-uniformly).
        blur: Gaussian blur sigma in pixels.
        noise: sensor noise in DN.
        gamma: tone curve exponent.
        jpeg: probability of a JPEG round trip, and its quality range.
        ground_roofs: probability that a flat roof is drawn in a ground material (asphalt, gravel, concrete,
            soil; grass as a planted roof), 35/65 of those in its own yard's look: the roofs that look like the
            ground around them. A share of what is drawn, not of the imaging.
    """

    sun_elevation: tuple[float, float] = (20.0, 70.0)
    sun_azimuth: tuple[float, float] = (0.0, 360.0)
    lean_tan: tuple[float, float] = (0.0, 0.6)
    true_ortho: float = 0.15
    gain: tuple[float, float] = (0.8, 1.2)
    haze: tuple[float, float] = (0.0, 0.25)
    resample: tuple[float, float] = (1.0, 2.0)
    blur: tuple[float, float] = (0.0, 1.0)
    noise: tuple[float, float] = (0.5, 4.0)
    gamma: tuple[float, float] = (0.8, 1.25)
    jpeg: float = 0.5
    jpeg_quality: tuple[int, int] = (40, 95)
    ground_roofs: float = GROUND_ROOFS

    def __post_init__(self) -> None:
        _check_range("sun_elevation", *self.sun_elevation, 1.0, 90.0)
        _check_range("sun_azimuth", *self.sun_azimuth, -360.0, 720.0)
        _check_range("lean_tan", *self.lean_tan, 0.0, 2.0)
        _check_range("gain", *self.gain, 0.1, 10.0)
        _check_range("haze", *self.haze, 0.0, 0.9)
        _check_range("resample", *self.resample, 1.0, 8.0)
        _check_range("blur", *self.blur, 0.0, 10.0)
        _check_range("noise", *self.noise, 0.0, 50.0)
        _check_range("gamma", *self.gamma, 0.2, 5.0)
        _check_range("jpeg_quality", *self.jpeg_quality, 1, 95)
        for name in ("true_ortho", "jpeg", "ground_roofs"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InputError(f"CityStyle.{name} is a probability in [0, 1], got {getattr(self, name)}",
                                 param=name)

    @classmethod
    def plain(cls) -> CityStyle:
        """Clean imaging: neutral colour, no haze, resampling, blur, noise, gamma or JPEG (sun and lean still vary)."""
        return cls(gain=(1.0, 1.0), haze=(0.0, 0.0), resample=(1.0, 1.0), blur=(0.0, 0.0), noise=(0.0, 0.0),
                   gamma=(1.0, 1.0), jpeg=0.0)

    def with_lean(self, lo: float, hi: float | None = None) -> CityStyle:
        """A copy with ``lean_tan`` in ``[lo, hi]`` (``hi`` defaults to ``lo``) and no true orthophotos."""
        return replace(self, lean_tan=(lo, lo if hi is None else hi), true_ortho=0.0)

    def draw(self, rng: np.random.Generator) -> Imaging:
        """One scene's :class:`Imaging` (a fixed number of draws from ``rng``, whatever the ranges)."""
        u = rng.random(14)

        def lerp(rng_: tuple[float, float], x: float) -> float:
            return float(rng_[0] + (rng_[1] - rng_[0]) * x)

        lean = 0.0 if u[3] < self.true_ortho else lerp(self.lean_tan, u[4])
        lo, hi = self.resample
        haze_tint = 0.9 + 0.2 * u[11]
        return Imaging(
            sun_azimuth=lerp(self.sun_azimuth, u[0]) % 360.0,
            sun_elevation=lerp(self.sun_elevation, u[1]),
            lean_azimuth=360.0 * float(u[2]),
            lean_tan=lean,
            gains=(lerp(self.gain, u[5]), lerp(self.gain, u[6]), lerp(self.gain, u[7])),
            haze=lerp(self.haze, u[8]),
            haze_rgb=(190.0 * haze_tint, 200.0 * haze_tint, 215.0),
            resample=float(math.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * u[9])),
            blur=lerp(self.blur, u[10]),
            noise=lerp(self.noise, u[12]),
            gamma=lerp(self.gamma, u[13]),
            jpeg_quality=int(rng.integers(self.jpeg_quality[0], self.jpeg_quality[1] + 1))
            if rng.random() < self.jpeg else 0,
        )


def _resample(band: np.ndarray, factor: float) -> np.ndarray:
    """Down- then up-sample a (H, W) band by ``factor`` (bilinear), as an image made at a coarser GSD."""
    h, w = band.shape
    small = ndimage.zoom(band, 1.0 / factor, order=1, grid_mode=True, mode="nearest")
    zoomed: np.ndarray = ndimage.zoom(small, (h / small.shape[0], w / small.shape[1]), order=1, grid_mode=True,
                                      mode="nearest")
    return zoomed


def finish_image(rendered: np.ndarray, imaging: Imaging, rng: np.random.Generator) -> np.ndarray:
    """Apply the photometric part of ``imaging`` to a rendered image.

    Args:
        rendered: float32 (3, H, W) radiance in DN (0–255 scale, may exceed it).
        imaging: the scene's imaging conditions.
        rng: generator for the sensor noise.

    Returns:
        uint8 (3, H, W) image.
    """
    img = rendered * np.asarray(imaging.gains, np.float32)[:, None, None]
    if imaging.haze > 0:
        img = img * np.float32(1 - imaging.haze) + np.float32(imaging.haze) * np.asarray(
            imaging.haze_rgb, np.float32)[:, None, None]
    if imaging.resample > 1.05:
        img = np.stack([_resample(b, imaging.resample) for b in img])
    if imaging.blur > 0.05:
        img = ndimage.gaussian_filter(img, sigma=(0, imaging.blur, imaging.blur), truncate=3.0)
    if imaging.noise > 0:
        img = img + rng.standard_normal(img.shape, dtype=np.float32) * np.float32(imaging.noise)
    if imaging.gamma != 1.0:
        img = 255.0 * np.power(np.clip(img, 0, 255) / np.float32(255.0), np.float32(imaging.gamma))
    out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    if imaging.jpeg_quality > 0:
        out = _jpeg_round_trip(out, imaging.jpeg_quality)
    return out


def _jpeg_round_trip(image: np.ndarray, quality: int) -> np.ndarray:
    """Encode (3, H, W) uint8 as JPEG at ``quality`` and decode it again."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image.transpose(1, 2, 0))).save(buf, format="JPEG", quality=int(quality))
    buf.seek(0)
    with Image.open(buf) as im:
        rgb: np.ndarray = np.asarray(im.convert("RGB")).transpose(2, 0, 1).copy()
        return rgb
