"""Training batches on a CPU: assembled by one thread of the training process, ahead of the step.

On a CPU the step and the data path share the same cores, so every pass over a batch outside the model is time
the step loses. DataLoader worker processes cost more than the work itself there: each batch is finished in the
worker and then copied into a new shared-memory segment for the main process (81 MB for 32 patches of 320², about
40 ms per batch on one core, plus the page faults of mapping it), on top of its gather and its torch passes.

:class:`AssembledBatches` does the same work in one compiled pass per pixel
(:func:`~aerialmtl.data.batches.finish_on_cpu`), straight from the memory-mapped patch cache into a few buffers
reused from batch to batch, in a thread of the training process that runs while the step computes (the kernel
releases the GIL). Its batches are those of :class:`~aerialmtl.data.batches.CachedBatches` +
:func:`~aerialmtl.data.batches.prepare_batch` for the same batch specs, to the bit (tests/test_batches.py): the
order, the augmentation seeds and a resume are the sampler's, as with a DataLoader.

A batch stays valid until the next one is taken from the iterator (its buffers are then reused): the loop
uses each batch for one step or one validation batch and keeps none.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import numpy as np
import torch

from aerialmtl.data.assemble import empty_batch
from aerialmtl.data.batches import BatchSpec, cpu_batch_shape, finish_on_cpu
from aerialmtl.data.cache import PatchCache
from aerialmtl.data.copy_paste import CopyPaster
from aerialmtl.data.transforms import Compose, stack_params

#: Batches assembled ahead of the one the step uses.
AHEAD = 2
_END = object()


class AssembledBatches:
    """An iterable of finished CPU batches (``{"ready": {...}}`` items, as :func:`~aerialmtl.data.batches.
    prepare_batch` takes them) over ``specs``, assembled by a background thread.

    Args:
        cache: the split's cache.
        transform: the augmentation pipeline (train) or the validation crop.
        tasks: reference layers to load (``height`` and/or ``classes``; absent ones are skipped).
        specs: the batches (a :class:`~aerialmtl.data.batches.RankBatchSampler`, endless, or a list); iterated
            anew by every ``iter()``.
        mean, std: (C,) float32 normalisation.
        paster: copy-paste of banked objects (:mod:`aerialmtl.data.copy_paste`): the patches are then gathered,
            pasted into, and finished from the gathered batch.
        ahead: batches assembled ahead of the step.
        shadow: the shadow head's labels of the cache's patches, uint8 (N, H, W)
            (:func:`~aerialmtl.data.shadow_labels.patch_labels`), cut and moved with the patches (``shadow``);
            ``None``: none. Not with ``paster`` (the labels are those of the stored heights).
    """

    def __init__(self, cache: PatchCache, transform: Compose, tasks: Sequence[str], specs: Iterable[BatchSpec],
                 mean: torch.Tensor, std: torch.Tensor, paster: CopyPaster | None = None, ahead: int = AHEAD,
                 shadow: np.ndarray | None = None) -> None:
        if shadow is not None and paster is not None:
            raise ValueError("AssembledBatches: shadow labels are those of the stored heights; not with copy-paste")
        self.cache, self.transform, self.specs, self.paster = cache, transform, specs, paster
        self.shadow = shadow
        self.mean, self.std = mean.cpu(), std.cpu()
        self.layers = ("image", "image_valid") + tuple(t for t in tasks if t in cache.layers)
        self.ahead = max(1, ahead)

    def __len__(self) -> int:
        return len(self.specs)  # type: ignore[arg-type]

    def __iter__(self) -> Iterator[dict[str, Any]]:
        q: queue.Queue[Any] = queue.Queue(maxsize=self.ahead)
        stop = threading.Event()
        worker = threading.Thread(target=self._produce, args=(q, stop), name="aerialmtl-batches", daemon=True)
        worker.start()
        try:
            while True:
                item = q.get()
                if item is _END:
                    return
                if isinstance(item, BaseException):
                    raise item
                yield {"ready": item}
        finally:
            stop.set()
            while worker.is_alive():  # unblock a put, then let the thread see the stop
                try:
                    q.get(timeout=0.05)
                except queue.Empty:
                    pass
            worker.join()

    def _produce(self, q: queue.Queue[Any], stop: threading.Event) -> None:
        """The thread: assemble each spec's batch into the ring of buffers and queue it."""
        # A buffer is reused once the batch after it was taken: the queue holds ≤ ahead batches, the consumer one,
        # the thread writes one (:data:`AHEAD` + 2 per shape; the last validation batch may be shorter).
        rings: dict[tuple[int, ...], list[dict[str, torch.Tensor]]] = {}
        turns: dict[tuple[int, ...], int] = {}

        def put(item: Any) -> bool:
            while not stop.is_set():
                try:
                    q.put(item, timeout=0.1)
                    return True
                except queue.Full:
                    continue
            return False

        try:
            for spec in self.specs:
                if stop.is_set():
                    return
                batch = self.assemble(spec, rings, turns)
                if not put(batch):
                    return
            put(_END)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            put(exc)

    def assemble(self, spec: BatchSpec, rings: dict[tuple[int, ...], list[dict[str, torch.Tensor]]] | None = None,
                 turns: dict[tuple[int, ...], int] | None = None) -> dict[str, torch.Tensor]:
        """One batch (into a ring buffer when ``rings`` is given, else into new tensors)."""
        shape = self.cache.index.shape
        b = len(spec)
        params = stack_params([self.transform.draw(torch.Generator().manual_seed(seed), shape) for _, seed in spec])
        indices = [i for i, _ in spec]
        window = self.transform.load_window(params)
        side = (shape[-2], shape[-1]) if window is None else (window[0], window[0])
        corners = ((np.zeros(b, np.int64), np.zeros(b, np.int64)) if window is None
                   else (window[1].numpy(), window[2].numpy()))
        arrays = {k: v for k, v in self.cache.arrays().items() if k in self.layers}
        if self.shadow is not None:
            arrays["shadow"] = self.shadow
        source: dict[str, Any] = arrays
        if self.paster is not None:
            pairs = None if window is None else list(zip(corners[0].tolist(), corners[1].tolist()))
            gathered = self.cache.gather(indices, pairs, None if window is None else side[0])
            source = {k: v for k, v in self.paster.paste(gathered, spec).items() if k in self.layers}
            indices = list(range(b))
            corners = (np.zeros(b, np.int64), np.zeros(b, np.int64))
        out = None
        moves = self.transform.sample_moves(params, b)
        if rings is not None and turns is not None:
            h, w, channels_last = cpu_batch_shape(self.transform, moves, side)
            key = (b, h, w)
            ring = rings.setdefault(key, [])
            turn = turns.get(key, 0)
            turns[key] = turn + 1
            if len(ring) < self.ahead + 2:
                ring.append(empty_batch(b, int(shape[0]), (h, w), [k for k in ("height", "classes")
                                                                   if k in self.layers], channels_last=channels_last))
            out = ring[turn % len(ring)] if len(ring) == self.ahead + 2 else ring[-1]
        return finish_on_cpu(source, indices, corners, side, params, self.transform, self.mean, self.std, out, moves)


__all__ = ["AHEAD", "AssembledBatches"]
