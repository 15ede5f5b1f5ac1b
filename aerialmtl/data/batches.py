"""Training and validation batches from the patch cache, augmented on the training device.

The data path of ``aerialmtl train``:

1. :class:`EpochOrder` fixes the run's order: every epoch is a permutation of the train split seeded by
   ``(seed, epoch)``, cut into global batches of ``batch_size × world_size`` positions (the last incomplete
   one dropped); rank r takes the r-th ``batch_size`` slice of each global batch. Each patch's augmentation
   is seeded by its position in the run (:func:`item_seed`), so neither the number of DataLoader workers
   nor the number of processes nor a resume changes what a given position sees.
2. :class:`CachedBatches` (in DataLoader workers, on a GPU run) draws every sample's augmentation parameters on the CPU,
   cuts crops while copying the patches out of the memory-mapped cache (:class:`~aerialmtl.data.cache.PatchCache`)
   and returns compact tensors: the raw image in its own dtype (uint8/uint16), uint8 validity and classes,
   float32 heights.
3. :func:`prepare_batch` (in the training process) copies them to the device (pinned memory,
   ``non_blocking``), flips/rotates the compact arrays there, normalises
   (:func:`~aerialmtl.data.dataset.normalise_batch`), jitters (:meth:`~aerialmtl.data.transforms.Compose.apply`)
   and returns a :class:`~aerialmtl.data.types.Sample` batch with the image in ``channels_last``
   (:func:`finish_on_device`). On a CPU it does the same in one compiled pass (:func:`finish_on_cpu`); training
   on a CPU takes its batches from :class:`~aerialmtl.data.prefetch.AssembledBatches` instead, which reads the
   cache and finishes the batch in that one pass in a thread of the training process, with no worker processes.

The result equals what :class:`~aerialmtl.data.dataset.PatchDataset` plus the per-sample transforms give
for the same patches and seeds (tests/test_batches.py compares them).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from aerialmtl.data.assemble import assemble_batch, empty_batch
from aerialmtl.data.cache import PatchCache
from aerialmtl.data.copy_paste import CopyPaster
from aerialmtl.data.dataset import normalise_batch
from aerialmtl.data.transforms import Compose, Move, Params, move_op, stack_params
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
        paster: pastes banked objects into the gathered (cropped) patches before the other augmentations
            (:mod:`aerialmtl.data.copy_paste`); ``None``: no copy-paste.
        shadow: the shadow head's labels of the cache's patches, uint8 (N, H, W)
            (:func:`~aerialmtl.data.shadow_labels.patch_labels`): cut and moved with the patches (``shadow``);
            ``None``: none.
    """

    def __init__(self, cache: PatchCache, transform: Compose, tasks: Sequence[str],
                 paster: CopyPaster | None = None, shadow: np.ndarray | None = None) -> None:
        self.cache, self.transform, self.paster, self.shadow = cache, transform, paster, shadow
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
        data = {k: v for k, v in data.items() if k in self.layers}
        if self.shadow is not None:
            data["shadow"] = torch.from_numpy(cut_windows(self.shadow, indices, window))
        return {"data": data, "params": params}


def cut_windows(labels: np.ndarray, indices: Sequence[int],
                window: tuple[int, torch.Tensor, torch.Tensor] | None) -> np.ndarray:
    """The (B, h, w) windows of ``labels`` (N, H, W) for samples ``indices``: whole patches without ``window``, else
    its ``(size, rows, cols)`` crops.
    """
    if window is None:
        return np.ascontiguousarray(labels[np.asarray(indices, np.int64)])
    size, rows, cols = window
    return np.stack([labels[i, r:r + size, c:c + size] for i, r, c in zip(indices, rows.tolist(), cols.tolist())])


def prepare_batch(raw: dict[str, Any], transform: Compose, mean: torch.Tensor, std: torch.Tensor,
                  device: torch.device) -> dict[str, torch.Tensor]:
    """A batch from :class:`CachedBatches` → normalised, augmented Sample tensors on ``device``.

    On a CPU the batch is finished in one compiled pass (:func:`finish_on_cpu`), on another device by torch
    there (:func:`finish_on_device`): the same tensors to the bit.

    Args:
        raw: the loader's item: ``data`` and ``params`` from :class:`CachedBatches`, or ``ready``, a batch
            already finished (:class:`~aerialmtl.data.prefetch.AssembledBatches`), which is only moved.
        transform: the same pipeline the dataset drew the parameters for.
        mean, std: (C,) float32 normalisation (on ``device`` to avoid a copy per batch).
        device: the training device.

    Returns:
        ``image`` float32 (B, C, H, W) channels_last, ``height`` float32 (B, 1, H, W) metres with
        ``height_valid`` bool, ``classes`` int64 (B, H, W) — for the loaded tasks.
    """
    if "ready" in raw:
        return {k: v.to(device, non_blocking=True) for k, v in raw["ready"].items()}
    if device.type == "cpu":
        data = raw["data"]
        b, _, h, w = data["image"].shape
        return finish_on_cpu(data, range(b), ([0] * b, [0] * b), (h, w), raw["params"], transform, mean, std)
    data = {k: v.to(device, non_blocking=True) for k, v in raw["data"].items()}
    return finish_on_device(data, raw["params"], transform, mean, std)


def finish_on_device(data: dict[str, torch.Tensor], params: Params, transform: Compose, mean: torch.Tensor,
                     std: torch.Tensor) -> dict[str, torch.Tensor]:
    """Flip/rotate the compact arrays where they are, normalise, jitter, image to ``channels_last`` (torch ops).

    Args:
        data: the compact batch of :meth:`~aerialmtl.data.cache.PatchCache.gather` (crops already cut), on the
            device.
        params: the samples' stacked augmentation parameters.
        transform, mean, std: as :func:`prepare_batch`.
    """
    data = transform.apply(data, params, stages=("permute",))  # on the compact arrays
    batch = normalise_batch(data["image"], data["image_valid"], mean, std, data.get("height"), data.get("classes"))
    if "shadow" in data:  # the shadow head's labels, moved with the image
        batch["shadow"] = data["shadow"]
    batch = transform.apply(batch, params, stages=("value",))
    batch["image"] = batch["image"].contiguous(memory_format=torch.channels_last)
    return batch


def cpu_batch_shape(transform: Compose, moves: Sequence[Move], window: tuple[int, int]) -> tuple[int, int, bool]:
    """``(h, w, channels_last)`` of the buffers :func:`finish_on_cpu` fills for samples moved by ``moves``.

    ``(h, w)`` is ``window`` after the moves (a batch's samples are all turned or none: a quarter turn needs
    square windows otherwise); the image is written ``channels_last`` unless a jitter follows (it reduces over the
    contiguous layout, as on a device).
    """
    h, w = window[::-1] if moves and moves[0][0] else window
    return h, w, not transform.has_stage("value")


def finish_on_cpu(source: Mapping[str, Any], index: Sequence[int], corners: tuple[Any, Any],
                  window: tuple[int, int], params: Params, transform: Compose, mean: torch.Tensor, std: torch.Tensor,
                  out: dict[str, torch.Tensor] | None = None,
                  moves: Sequence[Move] | None = None) -> dict[str, torch.Tensor]:
    """:func:`finish_on_device`'s batch made on the CPU in one pass (:func:`~aerialmtl.data.assemble.assemble_batch`).

    Args:
        source: ``image``, ``image_valid`` and the reference layers, (N, …) arrays or tensors: a compact batch
            (crops cut) or the cache's memory maps (:meth:`~aerialmtl.data.cache.PatchCache.arrays`).
        index: (B,) the samples' patches in ``source``.
        corners: (rows, cols), each (B,) ints (sequences or arrays): the top-left of each sample's window in its
            patch.
        window: (h, w) of the windows (before the flips and rotations).
        params, transform, mean, std: as :func:`finish_on_device`.
        out: buffers of :func:`~aerialmtl.data.assemble.empty_batch` to fill, shaped by :func:`cpu_batch_shape`
            (a loader reuses them); ``None``: new ones.
        moves: ``transform.sample_moves(params, B)`` when the caller has them already.

    Returns:
        The tensors of :func:`prepare_batch`, equal to the bit to :func:`finish_on_device`'s for the same samples.
    """
    b = len(index)
    if moves is None:
        moves = transform.sample_moves(params, b)
    if out is None:
        h, w, channels_last = cpu_batch_shape(transform, moves, window)
        out = empty_batch(b, int(source["image"].shape[1]), (h, w),
                          [k for k in ("height", "classes") if k in source], channels_last=channels_last)
    arrays = {k: (v.numpy() if isinstance(v, torch.Tensor) else v) for k, v in source.items()}
    batch = assemble_batch(arrays, index, corners[0], corners[1], moves, mean.cpu().numpy(), std.cpu().numpy(), out)
    if "shadow" in arrays:  # the shadow head's labels: each window cut and moved as its image
        batch = dict(batch)
        batch["shadow"] = moved_windows(arrays["shadow"], index, corners, tuple(batch["image"].shape[-2:]), moves)
    if transform.has_stage("value"):  # the jitter, on the contiguous image, as on a device
        batch = transform.apply(dict(batch), params, stages=("value",))
        batch["image"] = batch["image"].contiguous(memory_format=torch.channels_last)
    return batch


def moved_windows(labels: np.ndarray, index: Sequence[int], corners: tuple[Any, Any], side: Any,
                  moves: Sequence[Move]) -> torch.Tensor:
    """(B, h, w) windows of ``labels`` (N, H, W) at ``corners``, each moved by its sample's :data:`Move` (the same
    flips and quarter turns as the image); ``side`` is (h, w) after the moves.
    """
    h, w = int(side[0]), int(side[1])
    out = []
    for b, (i, move) in enumerate(zip(index, moves)):
        r, c = int(corners[0][b]), int(corners[1][b])
        hh, ww = (w, h) if move[0] else (h, w)  # the window before a transposing move
        t = torch.from_numpy(np.ascontiguousarray(labels[int(i), r:r + hh, c:c + ww]))
        op = move_op(move)
        out.append(t if op is None else op(t))
    return torch.stack(out).contiguous() if out else torch.zeros((0, h, w), dtype=torch.uint8)


__all__ = ["item_seed", "cut_windows", "moved_windows", "EpochOrder", "RankBatchSampler", "eval_batches",
           "CachedBatches", "prepare_batch", "finish_on_device", "finish_on_cpu", "cpu_batch_shape", "BatchSpec"]
