"""Training augmentations on :class:`~aerialmtl.data.types.Sample` dicts.

Geometric transforms (flips, 90° rotations, crops) move every spatial layer of a sample identically
(``image`` (C, H, W), ``height`` and ``height_valid`` (1, H, W), ``classes`` (H, W)), so the image
stays aligned with its references. Photometric jitter changes the image only, in normalised space
(after ``(raw - mean) / std``): contrast scales each band around its patch mean and brightness adds a
shift in units of the band's standard deviation, so one setting fits 8-bit, 16-bit and reflectance
imagery alike. Invalid image pixels are 0 in normalised space and are not jittered.

Randomness comes from torch: every transform takes an optional ``torch.Generator``; without one it
uses torch's global RNG, which DataLoader seeds per worker (``base_seed + worker_id``), so runs are
reproducible. The training loop passes a generator seeded per (seed, epoch, position) so that results
do not depend on the number of workers or on resuming.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from aerialmtl.data.types import Sample
from aerialmtl.errors import ConfigError

SPATIAL_KEYS = ("image", "height", "height_valid", "classes")


def _rand(generator: torch.Generator | None) -> float:
    return float(torch.rand((), generator=generator))


def _apply(sample: Sample, fn: Callable[[torch.Tensor], torch.Tensor]) -> Sample:
    out: Sample = dict(sample)  # type: ignore[assignment]
    for key in SPATIAL_KEYS:
        if key in out:
            out[key] = fn(out[key]).contiguous()  # type: ignore[literal-required]
    return out


class RandomFlip:
    """Flip left-right and/or up-down, each with probability ``p``."""

    def __init__(self, p: float = 0.5, horizontal: bool = True, vertical: bool = True) -> None:
        self.p, self.horizontal, self.vertical = p, horizontal, vertical

    def __call__(self, sample: Sample, generator: torch.Generator | None = None) -> Sample:
        if self.horizontal and _rand(generator) < self.p:
            sample = _apply(sample, lambda t: torch.flip(t, dims=(-1,)))
        if self.vertical and _rand(generator) < self.p:
            sample = _apply(sample, lambda t: torch.flip(t, dims=(-2,)))
        return sample


class RandomRot90:
    """Rotate by k·90° counter-clockwise, k uniform in {0, 1, 2, 3}.

    Non-square patches only get k in {0, 2} so that every sample of a batch keeps its shape.
    """

    def __call__(self, sample: Sample, generator: torch.Generator | None = None) -> Sample:
        h, w = sample["image"].shape[-2:]
        k = int(torch.randint(0, 4, (), generator=generator)) if h == w else 2 * int(
            torch.randint(0, 2, (), generator=generator))
        if k == 0:
            return sample
        return _apply(sample, lambda t: torch.rot90(t, k, dims=(-2, -1)))


class RandomCrop:
    """Cut a random ``size`` × ``size`` window (all layers); patches already that size are kept."""

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ConfigError(f"data.crop_size: must be ≥ 1, got {size}")
        self.size = size

    def __call__(self, sample: Sample, generator: torch.Generator | None = None) -> Sample:
        h, w = sample["image"].shape[-2:]
        if h < self.size or w < self.size:
            raise ConfigError(
                f"data.crop_size: {self.size} is larger than the {h}×{w} patches; use a crop ≤ the tile size"
            )
        if (h, w) == (self.size, self.size):
            return sample
        r = int(torch.randint(0, h - self.size + 1, (), generator=generator))
        c = int(torch.randint(0, w - self.size + 1, (), generator=generator))
        return _apply(sample, lambda t: t[..., r : r + self.size, c : c + self.size])


class CenterCrop:
    """Cut the central ``size`` × ``size`` window (validation counterpart of :class:`RandomCrop`)."""

    def __init__(self, size: int) -> None:
        self.size = size

    def __call__(self, sample: Sample, generator: torch.Generator | None = None) -> Sample:
        h, w = sample["image"].shape[-2:]
        if h < self.size or w < self.size:
            raise ConfigError(
                f"data.crop_size: {self.size} is larger than the {h}×{w} patches; use a crop ≤ the tile size"
            )
        r, c = (h - self.size) // 2, (w - self.size) // 2
        return _apply(sample, lambda t: t[..., r : r + self.size, c : c + self.size])


class PhotometricJitter:
    """Random contrast and brightness of the (normalised) image, per band.

    ``image' = (image - m) · c + m + b`` with ``m`` the band's mean over valid (non-zero) pixels,
    ``c ~ U(1 - contrast, 1 + contrast)`` and ``b ~ U(-brightness, brightness)`` (in std units).
    Applied with probability ``p``.
    """

    def __init__(self, brightness: float = 0.2, contrast: float = 0.2, p: float = 0.8) -> None:
        if brightness < 0 or not 0 <= contrast < 1:
            raise ConfigError(
                f"data.jitter: brightness must be ≥ 0 and contrast in [0, 1), got {brightness}, {contrast}"
            )
        self.brightness, self.contrast, self.p = brightness, contrast, p

    def __call__(self, sample: Sample, generator: torch.Generator | None = None) -> Sample:
        if _rand(generator) >= self.p:
            return sample
        img = sample["image"]
        n = img.shape[0]
        c = 1.0 + (torch.rand(n, 1, 1, generator=generator) * 2 - 1) * self.contrast
        b = (torch.rand(n, 1, 1, generator=generator) * 2 - 1) * self.brightness
        valid = (img != 0).any(dim=0, keepdim=True)
        count = valid.sum().clamp(min=1)
        m = (img * valid).sum(dim=(-2, -1), keepdim=True) / count
        out: Sample = dict(sample)  # type: ignore[assignment]
        out["image"] = torch.where(valid, (img - m) * c + m + b, img).to(img.dtype)
        return out


class Compose:
    """Apply transforms in order, passing the same generator to each."""

    def __init__(self, transforms: Sequence[Callable[..., Sample]]) -> None:
        self.transforms = list(transforms)

    def __call__(self, sample: Sample, generator: torch.Generator | None = None) -> Sample:
        for t in self.transforms:
            sample = t(sample, generator)
        return sample


def build_train_transform(
    flips: bool = True,
    rot90: bool = True,
    jitter: bool = False,
    crop_size: int | None = None,
    brightness: float = 0.2,
    contrast: float = 0.2,
) -> Compose:
    """The training augmentation pipeline: crop → flips → rot90 → jitter (each optional)."""
    ts: list[Callable[..., Sample]] = []
    if crop_size:
        ts.append(RandomCrop(crop_size))
    if flips:
        ts.append(RandomFlip())
    if rot90:
        ts.append(RandomRot90())
    if jitter:
        ts.append(PhotometricJitter(brightness, contrast))
    return Compose(ts)


def build_eval_transform(crop_size: int | None = None) -> Compose:
    """Validation transform: a centre crop when training crops, otherwise the identity."""
    return Compose([CenterCrop(crop_size)] if crop_size else [])


__all__ = ["RandomFlip", "RandomRot90", "RandomCrop", "CenterCrop", "PhotometricJitter", "Compose",
           "build_train_transform", "build_eval_transform", "SPATIAL_KEYS"]
