"""The decoded patch cache: each split's patches decoded once into memory-mapped arrays.

Reading a patch from the tile folder opens up to three GeoTIFFs and decodes them (10–20 ms per patch on
one core); training reads every patch once per epoch. The cache decodes each split once into compact
arrays in the patches' own dtypes (layout and fingerprint: :class:`~aerialmtl.formats.tiles.PatchCacheIndex`),
written on first use into the tile folder's ``cache/`` folder (or another folder), and checked against the
tile folder at every use: a cache whose fingerprint differs from the folder's (re-tiled, patch edited,
another manifest) is rebuilt, never used.

Values are exactly those of :func:`~aerialmtl.data.dataset.read_raw_patch`, so a batch gathered from
the cache and normalised by :func:`~aerialmtl.data.dataset.normalise_batch` equals the one
:class:`~aerialmtl.data.dataset.PatchDataset` gives.

Writers are serialised by an advisory lock file (``<split>.lock``), arrays are written under temporary
names and renamed, and the index is written last: processes of one training run (or two runs) can call
:func:`ensure_patch_cache` at once, and a build that is killed leaves no index, so the next use rebuilds.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from aerialmtl.data.dataset import RawPatch, read_raw_patch
from aerialmtl.errors import InputError, OutputError
from aerialmtl.filesafety import staging_path
from aerialmtl.formats.tiles import (
    MANIFEST_CSV,
    PatchCacheIndex,
    TileFolderInfo,
    cache_dir,
    cache_file,
    cache_index_file,
    read_manifest,
    split_fingerprint,
)
from aerialmtl.progress import tqdm_auto as tqdm

log = logging.getLogger(__name__)


@contextlib.contextmanager
def _locked(folder: Path, split: str) -> Iterator[None]:
    """Hold an exclusive advisory lock on ``folder/<split>.lock`` (no-op where ``fcntl`` is missing)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    with (folder / f"{split}.lock").open("a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _prepare_folder(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write-test-{os.getpid()}"
        probe.touch()
        probe.unlink()
    except OSError as exc:
        raise OutputError(
            f"data.cache_dir: cannot write the patch cache in '{folder}' ({exc.strerror or exc}); make the tile "
            "folder writable or set data.cache_dir to a writable folder"
        ) from exc


def _arrays_match(folder: Path, index: PatchCacheIndex) -> bool:
    """True when every array of ``index`` exists with the shape and dtype it records."""
    c, h, w = index.shape
    want = {"image": ((index.count, c, h, w), index.image_dtype), "image_valid": ((index.count, h, w), "uint8"),
            "height": ((index.count, 1, h, w), "float32"), "classes": ((index.count, h, w), "uint8")}
    for name in index.layers:
        try:
            arr = np.load(cache_file(folder, index.split, name), mmap_mode="r")
        except (OSError, ValueError):
            return False
        if tuple(arr.shape) != want[name][0] or arr.dtype != np.dtype(want[name][1]):
            return False
    return True


class _RawPatches(torch.utils.data.Dataset[RawPatch]):
    """Decoded patches of manifest rows, for decoding with DataLoader workers."""

    def __init__(self, info: TileFolderInfo, rows: list[dict[str, str]]) -> None:
        self.info, self.rows = info, rows

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i: int) -> RawPatch:
        return read_raw_patch(self.info.root, self.rows[i], self.info.num_bands, self.info.tasks)


def _build(info: TileFolderInfo, split: str, rows: list[dict[str, str]], folder: Path, fingerprint: str,
           workers: int, progress: bool) -> PatchCacheIndex:
    index_path = cache_index_file(folder, split)
    index_path.unlink(missing_ok=True)  # from here on the old cache is invalid
    first = read_raw_patch(info.root, rows[0], info.num_bands, info.tasks)
    c, h, w = first.image.shape
    n = len(rows)
    layers = ("image", "image_valid") + tuple(t for t in ("height", "classes") if t in info.tasks)
    specs: dict[str, tuple[tuple[int, ...], Any]] = {
        "image": ((n, c, h, w), first.image.dtype), "image_valid": ((n, h, w), np.uint8),
        "height": ((n, 1, h, w), np.float32), "classes": ((n, h, w), np.uint8)}
    tmp = {name: staging_path(cache_file(folder, split, name), f"partial-{os.getpid()}") for name in layers}
    arrays: dict[str, Any] = {}
    try:
        for name in layers:
            shape, dtype = specs[name]
            arrays[name] = np.lib.format.open_memmap(tmp[name], mode="w+", dtype=dtype, shape=shape)
        # an own generator: iterating a DataLoader without one draws from (and shifts) torch's global RNG
        loader = torch.utils.data.DataLoader(_RawPatches(info, rows), batch_size=None, num_workers=workers,
                                             generator=torch.Generator())
        for i, patch in enumerate(tqdm(loader, total=n, desc=f"caching {split} patches", unit="patch",
                                       disable=not progress)):
            if patch.image.shape != (c, h, w):
                raise InputError(
                    f"patch '{rows[i].get('patch_id')}' of '{info.root / MANIFEST_CSV}' is "
                    f"{patch.image.shape[2]}×{patch.image.shape[1]} px with {patch.image.shape[0]} bands but the "
                    f"first one is {w}×{h} px with {c}; re-run `aerialmtl tile`"
                )
            arrays["image"][i] = patch.image
            arrays["image_valid"][i] = patch.image_valid
            if "height" in arrays:
                arrays["height"][i, 0] = patch.height
            if "classes" in arrays:
                arrays["classes"][i] = patch.classes
        for name in layers:
            arrays[name].flush()
        arrays.clear()
        for name in layers:
            tmp[name].replace(cache_file(folder, split, name))
    finally:
        arrays.clear()
        for path in tmp.values():
            path.unlink(missing_ok=True)
    index = PatchCacheIndex(split=split, fingerprint=fingerprint, count=n, layers=layers,
                            image_dtype=np.dtype(first.image.dtype).name, shape=(int(c), int(h), int(w)))
    index.write(folder)
    return index


def ensure_patch_cache(info: TileFolderInfo, split: str, folder: str | Path | None = None, workers: int = 0,
                       progress: bool = False) -> PatchCacheIndex:
    """Make sure ``split``'s cache is in ``folder`` and matches the tile folder; build it if not.

    Args:
        info: the tile folder.
        split: ``train``, ``val`` or ``test`` (must have patches).
        folder: where the cache lives (default: ``cache/`` inside the tile folder).
        workers: DataLoader workers decoding the GeoTIFFs while building.
        progress: show a progress bar while building.

    Returns:
        The index of the up-to-date cache.

    Raises:
        InputError: the split has no patches, or the patches differ in size.
        OutputError: the cache folder cannot be written.
    """
    folder = Path(folder) if folder is not None else cache_dir(info.root)
    rows = read_manifest(info.root, split)
    if not rows:
        raise InputError(
            f"split '{split}' of '{info.root}' has no patches (see {info.root / MANIFEST_CSV}); "
            "re-run `aerialmtl tile` with a larger area or other split fractions"
        )
    fingerprint = split_fingerprint(info, rows)
    index = PatchCacheIndex.read(folder, split)
    if index is not None and index.fingerprint == fingerprint and _arrays_match(folder, index):
        return index
    _prepare_folder(folder)
    with _locked(folder, split):
        index = PatchCacheIndex.read(folder, split)  # another process may have built it meanwhile
        if index is not None and index.fingerprint == fingerprint and _arrays_match(folder, index):
            return index
        log.info("%s patch cache of split '%s' in %s", "rebuilding the stale" if index else "building the", split,
                 folder)
        return _build(info, split, rows, folder, fingerprint, workers, progress)


class PatchCache:
    """Read access to one split's cache (memory-mapped; opened lazily, so it can cross into worker processes).

    Args:
        folder: the cache folder.
        index: the split's index (from :func:`ensure_patch_cache`).
    """

    def __init__(self, folder: str | Path, index: PatchCacheIndex) -> None:
        self.folder, self.index = Path(folder), index
        self._arrays: dict[str, np.ndarray] | None = None

    def __len__(self) -> int:
        return self.index.count

    @property
    def layers(self) -> tuple[str, ...]:
        """The cached layers (``image`` and the references)."""
        return self.index.layers

    def __getstate__(self) -> dict[str, Any]:
        return {"folder": self.folder, "index": self.index, "_arrays": None}

    def arrays(self) -> dict[str, np.ndarray]:
        """Layer name → its memory-mapped array (N × ...), opened on first use in each process."""
        if self._arrays is None:
            self._arrays = {name: np.load(cache_file(self.folder, self.index.split, name), mmap_mode="r")
                            for name in self.index.layers}
        return self._arrays

    def gather(self, indices: Sequence[int], windows: Sequence[tuple[int, int]] | None = None,
               size: int | None = None) -> dict[str, torch.Tensor]:
        """Copy patches ``indices`` (in that order) out of the cache, optionally cropped.

        Args:
            indices: patch indexes in manifest order.
            windows: per patch, the (row, col) of the top-left corner of a ``size`` × ``size`` crop.
            size: crop side (with ``windows``).

        Returns:
            CPU tensors: ``image`` (B, C, h, w) in the stored dtype (uint16/uint32 widened to int32/int64,
            which torch handles on every device), ``image_valid`` uint8 (B, h, w), and ``height`` float32 (B, 1, h, w) /
            ``classes`` uint8 (B, h, w) when cached.
        """
        out: dict[str, torch.Tensor] = {}
        for name, arr in self.arrays().items():
            if windows is None:
                data = arr[np.asarray(indices, np.int64)]
            else:
                assert size is not None
                data = np.stack([arr[i, ..., r:r + size, c:c + size] for i, (r, c) in zip(indices, windows)])
            if data.dtype in (np.uint16, np.uint32):
                data = data.astype(np.int32 if data.dtype == np.uint16 else np.int64)
            out[name] = torch.from_numpy(np.ascontiguousarray(data))
        return out


__all__ = ["ensure_patch_cache", "PatchCache"]
