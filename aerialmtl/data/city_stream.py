"""Training samples drawn from synthetic cities in memory (no disk), for pretraining.

:func:`city_raw` gives patch ``index`` of a stream as stored values (a :class:`~aerialmtl.data.dataset.RawPatch`:
uint8 image, heights, class indices), :func:`city_sample` as a normalised
:class:`~aerialmtl.data.types.Sample` exactly like :class:`~aerialmtl.data.dataset.PatchDataset` returns
(``image`` float32 (3, H, W) = ``(raw − mean) / std``, ``height`` float32 (1, H, W) metres with
``height_valid``, ``classes`` int64 (H, W) indices of the ``synthetic`` scheme, ``patch_id``), and
:class:`CityStream` is an endless (or ``length``-long) torch ``IterableDataset`` of them that splits the
indices between DataLoader workers. Patch ``index`` is the same whatever the number of workers.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from aerialmtl.classes import ClassScheme
from aerialmtl.data.dataset import RawPatch, normalise_batch
from aerialmtl.data.synth.city import GSD_RANGE, MIN_CITY_SIZE, CityPatch, sample_city
from aerialmtl.data.synth.style import CityStyle
from aerialmtl.data.synth.textures import TexturePool
from aerialmtl.data.types import Sample
from aerialmtl.errors import InputError

#: The class scheme of the cities' labels (``classes`` indices 0..5 of a sample follow it).
CITY_CLASSES = "synthetic"
#: ImageNet-style scaling of 8-bit bands, ``(x − 127) / 128``, as the small-area recipe's encoder expects.
LITE_MEAN, LITE_STD = (127.0, 127.0, 127.0), (128.0, 128.0, 128.0)


@dataclass(frozen=True)
class CityStreamOptions:
    """What a stream of synthetic city patches draws.

    Attributes:
        seed: stream seed; patch ``i`` is the city of :func:`city_seed` ``(seed, i)``.
        size: patch side in pixels.
        gsd: (min, max) pixel size in metres, drawn log-uniformly per patch (equal values: a fixed GSD).
        style: imaging ranges (default :class:`CityStyle`).
        textures: optional pool of the user's ground textures.
        mean, std: per-band normalisation of the 8-bit image (must match what the checkpoint records).
    """

    seed: int = 0
    size: int = 128
    gsd: tuple[float, float] = (0.25, 1.0)
    style: CityStyle | None = None
    textures: TexturePool | None = None
    mean: tuple[float, ...] = LITE_MEAN
    std: tuple[float, ...] = LITE_STD

    def __post_init__(self) -> None:
        if int(self.size) != self.size or self.size < MIN_CITY_SIZE:
            raise InputError(f"CityStreamOptions.size must be an integer ≥ {MIN_CITY_SIZE}, got {self.size}",
                             param="size")
        lo, hi = self.gsd
        if not GSD_RANGE[0] <= lo <= hi <= GSD_RANGE[1]:
            raise InputError(f"CityStreamOptions.gsd must be (min, max) metres within {GSD_RANGE}, got {self.gsd}",
                             param="gsd")
        if len(self.mean) != 3 or len(self.std) != 3 or min(self.std) <= 0:
            raise InputError(f"CityStreamOptions.mean/std need 3 values (std > 0), got {self.mean} / {self.std}",
                             param="mean")


def city_seed(seed: int, index: int) -> int:
    """The city seed of patch ``index`` of the stream ``seed`` (a 63-bit int, well mixed)."""
    return int(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(index)]).generate_state(2, np.uint64)[0] >> 1)


def city_patch(index: int, options: CityStreamOptions) -> CityPatch:
    """Patch ``index`` of the stream as a :class:`~aerialmtl.data.synth.city.CityPatch` (GSD drawn in the range)."""
    s = city_seed(options.seed, index)
    lo, hi = options.gsd
    u = float(np.random.default_rng([s & 0xFFFFFFFF, 7]).random())
    gsd = lo if hi <= lo else math.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * u)
    return sample_city(s, options.size, gsd, options.style, options.textures)


def city_raw(index: int, options: CityStreamOptions) -> RawPatch:
    """Patch ``index`` as stored values: uint8 (3, H, W) image, all valid, heights (metres), class indices."""
    patch = city_patch(index, options)
    classes = ClassScheme.load(CITY_CLASSES).remap(patch.classes, source="synthetic city")
    return RawPatch(image=patch.image, image_valid=np.ones(patch.height.shape, bool), height=patch.height,
                    classes=classes)


def city_sample(index: int, options: CityStreamOptions) -> Sample:
    """Patch ``index`` as a normalised :class:`~aerialmtl.data.types.Sample` (the format of ``PatchDataset``)."""
    raw = city_raw(index, options)
    assert raw.height is not None and raw.classes is not None
    batch = normalise_batch(
        torch.from_numpy(raw.image[None]), torch.from_numpy(raw.image_valid[None]),
        torch.tensor(options.mean, dtype=torch.float32), torch.tensor(options.std, dtype=torch.float32),
        torch.from_numpy(raw.height[None, None]), torch.from_numpy(raw.classes[None]),
    )
    sample: Sample = {k: v[0] for k, v in batch.items()}  # type: ignore[assignment]
    sample["patch_id"] = f"city-{options.seed}-{index}"
    return sample


class CityStream(torch.utils.data.IterableDataset[Sample]):
    """Synthetic city samples ``start, start + 1, ...`` (``length`` of them, or endless when None).

    With DataLoader workers, worker ``w`` of ``n`` yields the indices ``≡ w (mod n)``: each patch is the same
    whatever the number of workers (what :func:`city_sample` gives for its index), though with ``batch_size``
    > 1 a DataLoader groups each worker's patches into its own batches. For batches fixed by index, use
    :func:`city_sample` from a map-style dataset or a sampler instead.
    """

    def __init__(self, options: CityStreamOptions | None = None, length: int | None = None, start: int = 0) -> None:
        self.options = options or CityStreamOptions()
        self.length, self.start = length, start

    def __iter__(self) -> Iterator[Sample]:
        info = torch.utils.data.get_worker_info()
        worker, workers = (0, 1) if info is None else (info.id, info.num_workers)
        i = self.start + worker
        while self.length is None or i < self.start + self.length:
            yield city_sample(i, self.options)
            i += workers


__all__ = ["CITY_CLASSES", "CityStream", "CityStreamOptions", "LITE_MEAN", "LITE_STD", "city_patch", "city_raw",
           "city_sample", "city_seed"]
