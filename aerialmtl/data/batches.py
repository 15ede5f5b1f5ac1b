"""Training and validation batches from the patch cache, augmented on the training device.

The data path of ``aerialmtl train``:

1. :class:`EpochOrder` fixes the run's order: every epoch is a permutation of the train split seeded by
   ``(seed, epoch)``, cut into global batches of ``batch_size × world_size`` positions (the last incomplete
   one dropped); rank r takes the r-th ``batch_size`` slice of each global batch. Each patch's augmentation
   is seeded by its position in the run (:func:`item_seed`), so neither the number of DataLoader workers
   nor the number of processes nor a resume changes what a given position sees.
2. :class:`CachedBatches` (in DataLoader workers) draws every sample's augmentation parameters on the CPU,
   cuts crops while copying the patches out of the memory-mapped cache (:class:`~aerialmtl.data.cache.PatchCache`)
   and returns compact tensors: the raw image in its own dtype (uint8/uint16), uint8 validity and classes,
   float32 heights.
3. :func:`prepare_batch` (in the training process) copies them to the device (pinned memory,
   ``non_blocking``), flips/rotates the compact arrays there, normalises
   (:func:`~aerialmtl.data.dataset.normalise_batch`), jitters (:meth:`~aerialmtl.data.transforms.Compose.apply`)
   and returns a :class:`~aerialmtl.data.types.Sample` batch with the image in ``channels_last``.
   Training on a CPU with DataLoader workers runs this step in the workers instead (one thread each), so
   the main process only computes the model.

The result equals what :class:`~aerialmtl.data.dataset.PatchDataset` plus the per-sample transforms give
for the same patches and seeds (tests/test_batches.py compares them).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from aerialmtl.data.cache import PatchCache
from aerialmtl.data.copy_paste import CopyPaster
from aerialmtl.data.dataset import normalise_batch
from aerialmtl.data.transforms import Compose, stack_params
from aerialmtl.errors import InputError

#: One batch as the sampler describes it: ``(patch index, augmentation seed)`` per sample.
BatchSpec = list[tuple[int, int]]


def item_seed(seed: int, epoch: int, position: int) -> int:
    """A 63-bit seed for the augmentation of the patch at ``position`` of ``epoch``."""
    return (seed * 6364136223846793005 + epoch * 1442695040888963407 + position * 2862933555777941757) % 2**63


@dataclass(frozen=True)
class EpochOrder:
    """Which patches every optimisation step uses, for any number of processes.

    Attributes:
        n: patches in the train split.
        batch_size: patches per process and step (``data.batch_size``).
        seed: the run's seed.
        world_size: number of processes.

    With one process a split smaller than ``batch_size`` gives one batch of the whole split per epoch.
    With several, the per-process batch shrinks to ``n // world_size`` when the split is that small.
    """

    n: int
    batch_size: int
    seed: int
    world_size: int = 1

    def __post_init__(self) -> None:
        if self.n < self.world_size:
            raise InputError(
                f"the train split has {self.n} patches, fewer than the {self.world_size} processes of this run; "
                "start fewer processes or tile a larger area"
            )

    @property
    def rank_batch(self) -> int:
        """Patches per process and step."""
        return min(self.batch_size, self.n // self.world_size)

    @property
    def global_batch(self) -> int:
        """Patches per step over all processes."""
        return self.rank_batch * self.world_size

    @property
    def steps_per_epoch(self) -> int:
        """Full global batches per epoch (the incomplete last one is dropped)."""
        return self.n // self.global_batch

    def permutation(self, epoch: int) -> torch.Tensor:
        """The order of the patches in ``epoch`` (seeded by ``(seed, epoch)``: the same on every rank)."""
        return torch.randperm(self.n, generator=torch.Generator().manual_seed(self.seed * 7919 + epoch))

    def advance(self, epoch: int, position: int) -> tuple[int, int]:
        """(epoch, position) after one step from (epoch, position)."""
        position += self.global_batch
        if position + self.global_batch > self.n:
            return epoch + 1, 0
        return epoch, position

    def batches(self, rank: int, epoch: int, position: int) -> Iterator[BatchSpec]:
        """Rank ``rank``'s batches from ``position`` (patches already used) of ``epoch`` on, forever."""
        g, b = self.global_batch, self.rank_batch
        if position + g > self.n:  # resumed with a larger global batch at the end of an epoch
            epoch, position = epoch + 1, 0
        while True:
            perm = self.permutation(epoch)
            while position + g <= self.n:
                first = position + rank * b
                yield [(int(perm[p]), item_seed(self.seed, epoch, p)) for p in range(first, first + b)]
                position += g
            epoch, position = epoch + 1, 0


class RankBatchSampler:
    """The batch sampler of one process: :meth:`EpochOrder.batches` as an iterable for a DataLoader."""

    def __init__(self, order: EpochOrder, rank: int, epoch: int, position: int) -> None:
        self.order, self.rank, self.epoch, self.position = order, rank, epoch, position

    def __iter__(self) -> Iterator[BatchSpec]:
        return self.order.batches(self.rank, self.epoch, self.position)


def eval_batches(n: int, batch_size: int, rank: int = 0, world_size: int = 1) -> list[BatchSpec]:
    """Validation batches: consecutive patches in manifest order (the last one may be short), dealt
    round-robin to the processes, so the union over ranks is the single-process set of batches.
    """
    specs = [[(i, 0) for i in range(s, min(s + batch_size, n))] for s in range(0, n, batch_size)]
    return specs[rank::world_size]


class CachedBatches(torch.utils.data.Dataset[dict[str, Any]]):
    """Map-style dataset whose items are whole batches (use with ``batch_size=None``).

    ``dataset[spec]`` draws each sample's augmentation parameters from a generator seeded with its seed,
    copies the patches (cropped if the pipeline starts with a crop) out of the cache and returns
    ``{"data": {...}, "params": {...}}`` for :func:`prepare_batch`.

    Args:
        cache: the split's cache.
        transform: the augmentation pipeline (:func:`~aerialmtl.data.transforms.build_train_transform` or
            ``build_eval_transform``).
        tasks: reference layers to load (``height`` and/or ``classes``; absent ones are skipped).
        normalisation: ``(mean, std)`` to finish the batch here (:func:`prepare_batch` on the CPU, in the
            worker): what training on a CPU does, so that workers augment while the main process computes.
            ``None`` (training on a GPU): return the compact arrays for the device to finish.
        paster: pastes banked objects into the gathered (cropped) patches before the other augmentations
            (:mod:`aerialmtl.data.copy_paste`); ``None``: no copy-paste.
    """

    def __init__(self, cache: PatchCache, transform: Compose, tasks: Sequence[str],
                 normalisation: tuple[torch.Tensor, torch.Tensor] | None = None,
                 paster: CopyPaster | None = None) -> None:
        self.cache, self.transform, self.normalisation, self.paster = cache, transform, normalisation, paster
        self.layers = ("image", "image_valid") + tuple(t for t in tasks if t in cache.layers)

    def __len__(self) -> int:
        return len(self.cache)

    def __getitem__(self, spec: BatchSpec) -> dict[str, Any]:
        shape = self.cache.index.shape
        params = stack_params([self.transform.draw(torch.Generator().manual_seed(seed), shape)
                               for _, seed in spec])
        indices = [i for i, _ in spec]
        window = self.transform.load_window(params)
        if window is None:
            data = self.cache.gather(indices)
        else:
            size, rows, cols = window
            data = self.cache.gather(indices, list(zip(rows.tolist(), cols.tolist())), size)
        if self.paster is not None:
            data = self.paster.paste(data, spec)
        raw = {"data": {k: v for k, v in data.items() if k in self.layers}, "params": params}
        if self.normalisation is None:
            return raw
        return {"ready": prepare_batch(raw, self.transform, *self.normalisation, torch.device("cpu"))}


def prepare_batch(raw: dict[str, Any], transform: Compose, mean: torch.Tensor, std: torch.Tensor,
                  device: torch.device) -> dict[str, torch.Tensor]:
    """A batch from :class:`CachedBatches` → normalised, augmented Sample tensors on ``device``.

    Args:
        raw: the DataLoader's item (``data`` and ``params``; or ``ready``, a batch finished on the CPU,
            which is only moved).
        transform: the same pipeline the dataset drew the parameters for.
        mean, std: (C,) float32 normalisation (on ``device`` to avoid a copy per batch).
        device: the training device.

    Returns:
        ``image`` float32 (B, C, H, W) channels_last, ``height`` float32 (B, 1, H, W) metres with
        ``height_valid`` bool, ``classes`` int64 (B, H, W) — for the loaded tasks.
    """
    if "ready" in raw:
        return {k: v.to(device, non_blocking=True) for k, v in raw["ready"].items()}
    data = {k: v.to(device, non_blocking=True) for k, v in raw["data"].items()}
    data = transform.apply(data, raw["params"], stages=("permute",))  # on the compact arrays
    batch = normalise_batch(data["image"], data["image_valid"], mean, std, data.get("height"), data.get("classes"))
    batch = transform.apply(batch, raw["params"], stages=("value",))
    batch["image"] = batch["image"].contiguous(memory_format=torch.channels_last)
    return batch


__all__ = ["item_seed", "EpochOrder", "RankBatchSampler", "eval_batches", "CachedBatches", "prepare_batch",
           "BatchSpec"]
