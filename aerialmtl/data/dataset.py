"""Torch dataset over a tile folder written by ``aerialmtl tile`` (format: :mod:`aerialmtl.formats.tiles`).

A tile folder holds ``dataset.yaml`` (normalisation, class scheme, tasks, ...), ``manifest.csv`` (one row
per patch) and one GeoTIFF per patch and layer. :func:`read_raw_patch` decodes one patch's layers as
stored (the one place that turns GeoTIFF masks and nodata into validity); :class:`PatchDataset` reads one
split of it and returns normalised :class:`~aerialmtl.data.types.Sample` dicts; patches are opened with
rasterio inside ``__getitem__`` so the dataset can be used with DataLoader worker processes (nothing holds
an open file handle). Training reads the same values from the decoded cache (:mod:`aerialmtl.data.cache`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
import torch
from rasterio.errors import RasterioError

from aerialmtl.classes import IGNORE_INDEX
from aerialmtl.data.types import Sample, as_sample
from aerialmtl.errors import InputError, cause
from aerialmtl.formats.tiles import (
    MANIFEST_CSV,
    SPLITS,
    TASKS,
    TileFolderInfo,
    read_manifest,
    read_tile_info,
)

Transform = Callable[[Sample], Sample]


def class_pixel_counts(data_dir: str | Path, split: str, num_classes: int) -> np.ndarray:
    """Labelled pixels per class index in ``split``, summed from the manifest's ``class_hist`` (int64 (K,))."""
    counts = np.zeros(num_classes, np.int64)
    for row in read_manifest(data_dir, split):
        hist = (row.get("class_hist") or "").strip()
        if hist:
            values = [int(float(v)) for v in hist.split(";")]
            counts[: min(num_classes, len(values))] += values[:num_classes]
    return counts


@dataclass
class RawPatch:
    """One patch's layers as stored (before normalisation).

    Attributes:
        image: (C, H, W) in the image patches' dtype.
        image_valid: bool (H, W), True where the image is valid.
        height: float32 (H, W) metres, NaN where invalid (nodata, non-finite, or the image invalid);
            ``None`` when not requested.
        classes: uint8 (H, W) class indices, ``IGNORE_INDEX`` where unlabelled or the image is invalid;
            ``None`` when not requested.
    """

    image: np.ndarray
    image_valid: np.ndarray
    height: np.ndarray | None = None
    classes: np.ndarray | None = None


def _layer_path(root: Path, row: dict[str, str], key: str) -> Path:
    rel = (row.get(key) or "").strip()
    if not rel:
        raise InputError(
            f"manifest row '{row.get('patch_id')}' of '{root / MANIFEST_CSV}' has no {key}; "
            "re-run `aerialmtl tile`"
        )
    return root / rel


@contextlib.contextmanager
def _reading(path: Path, root: Path) -> Iterator[None]:
    """Turn a failed read of patch ``path`` (truncated, not a TIFF, unreadable) into one line naming it."""
    try:
        yield
    except (RasterioError, OSError) as exc:
        why = " ".join(str(exc).split())
        if "See previous exception" in why and exc.__cause__ is not None:
            why = " ".join(str(exc.__cause__).split())
        raise InputError(
            f"patch '{path}' of the tile folder '{root}' cannot be read ({cause(why)}): the file is truncated or "
            "damaged; re-run `aerialmtl tile ... --overwrite` to write the tile folder again"
        ) from exc


def read_raw_patch(root: Path, row: dict[str, str], num_bands: int, tasks: Sequence[str]) -> RawPatch:
    """Decode the patch of manifest ``row`` of tile folder ``root``: the image and the layers of ``tasks``.

    Raises:
        InputError: the row lacks a layer's path, a patch cannot be read (named), or the image patch has
            another number of bands than ``dataset.yaml`` lists.
    """
    image_path = _layer_path(root, row, "image_path")
    with _reading(image_path, root), rasterio.open(image_path) as src:
        image = src.read()
        img_valid = src.dataset_mask() > 0
    if image.shape[0] != num_bands:
        raise InputError(
            f"image patch '{image_path}' has {image.shape[0]} bands but dataset.yaml "
            f"lists {num_bands}; re-run `aerialmtl tile`"
        )
    patch = RawPatch(image=image, image_valid=img_valid)
    if "height" in tasks:
        path = _layer_path(root, row, "height_path")
        with _reading(path, root), rasterio.open(path) as src:
            h = src.read(1).astype(np.float32)
            valid = src.read_masks(1) > 0
        valid &= np.isfinite(h) & img_valid
        patch.height = np.where(valid, h, np.float32(np.nan)).astype(np.float32)
    if "classes" in tasks:
        path = _layer_path(root, row, "classes_path")
        with _reading(path, root), rasterio.open(path) as src:
            c = src.read(1).astype(np.uint8)
            valid = src.read_masks(1) > 0
        c[~(valid & img_valid)] = IGNORE_INDEX
        patch.classes = c
    return patch


def read_rgb_heights(root: str | Path, split: str, what: str, param: str,
                     min_side: int = 0) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], float]:
    """The ``split`` patches of a tile folder as 8-bit RGB with heights, for ``what`` (named in errors, as is the
    option ``param``).

    Returns:
        ``(images, heights, valid, gsd)``: uint8 (3, S, S) (the first three bands), float32 (S, S) metres with NaN
        where invalid, bool (S, S) where the image is valid, one per patch; the folder's pixel size in metres.

    Raises:
        InputError: not a tile folder, not 8-bit RGB with heights, patches smaller than ``min_side`` pixels, or no
            patch in ``split``.
    """
    root = Path(root)
    info = read_tile_info(root)
    if info.num_bands < 3 or info.dtype not in (None, "uint8") or "height" not in info.tasks:
        raise InputError(f"the tile folder '{root}' holds {info.num_bands}-band {info.dtype} patches with tasks "
                         f"{list(info.tasks)}; {what} need 8-bit RGB patches with heights (tile an 8-bit RGB "
                         "orthophoto with a DSM and DTM, or an nDSM)", param=param)
    if info.patch_size < min_side:
        raise InputError(f"the tile folder '{root}' has {info.patch_size} px patches, smaller than the "
                         f"{min_side} px {what} need; pass --patch-size ≤ {info.patch_size}", param=param)
    images, heights, valid = [], [], []
    for row in read_manifest(root, split):
        raw = read_raw_patch(root, row, info.num_bands, ("height",))
        images.append(np.ascontiguousarray(raw.image[:3], np.uint8))
        heights.append(raw.height if raw.height is not None else np.full(raw.image_valid.shape, np.nan, np.float32))
        valid.append(raw.image_valid)
    if not images:
        raise InputError(f"the tile folder '{root}' has no '{split}' patches for {what}", param=param)
    return images, heights, valid, float(info.gsd)


def normalise_batch(
    image: torch.Tensor,
    image_valid: torch.Tensor,
    mean: torch.Tensor,
    std: torch.Tensor,
    height: torch.Tensor | None = None,
    classes: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Stored values → the :class:`~aerialmtl.data.types.Sample` tensors of a batch, on their device.

    Args:
        image: (B, C, H, W) raw values (any numeric dtype).
        image_valid: (B, H, W) bool or uint8.
        mean, std: (C,) float32 per-band normalisation.
        height: (B, 1, H, W) float32 metres, NaN where invalid.
        classes: (B, H, W) uint8 or int64 class indices, ``IGNORE_INDEX`` where unlabelled.

    Returns:
        ``image`` float32 ``(raw - mean) / std``, 0 where invalid; ``height`` float32 (0 where invalid)
        with ``height_valid`` bool; ``classes`` int64 — the keys whose inputs were given.
    """
    m = mean.to(image.device).view(1, -1, 1, 1)
    s = std.to(image.device).view(1, -1, 1, 1)
    norm = image.to(torch.float32, copy=True).sub_(m).div_(s)  # one new tensor, updated in place
    out = {"image": norm.masked_fill_(~image_valid.bool()[:, None], 0.0)}
    if height is not None:
        hv = torch.isfinite(height)
        out["height"] = torch.where(hv, height, torch.zeros((), device=height.device))
        out["height_valid"] = hv
    if classes is not None:
        out["classes"] = classes.long()
    return out


class PatchDataset(torch.utils.data.Dataset[Sample]):
    """Patches of one split of a tile folder, as :class:`~aerialmtl.data.types.Sample` dicts.

    Each item holds ``image`` float32 (C, H, W) normalised as ``(raw - mean) / std`` (0 where the image
    is invalid), and, for the requested tasks present in the folder, ``height`` float32 (1, H, W) in
    metres (0 where invalid) with ``height_valid`` bool (1, H, W), and ``classes`` int64 (H, W) with
    255 (``IGNORE_INDEX``) where unlabelled. ``patch_id`` names the manifest row.

    Args:
        data_dir: the tile folder (holding ``dataset.yaml`` and ``manifest.csv``).
        split: ``"train"``, ``"val"`` or ``"test"``.
        transform: optional callable applied to every sample (e.g. :mod:`aerialmtl.data.transforms`).
        tasks: tasks to load (default: all tasks of the folder); tasks the folder lacks are absent.

    Raises:
        InputError: not a tile folder, unknown split/task, or no patches in ``split``.
    """

    def __init__(
        self,
        data_dir: str | Path,
        split: str,
        transform: Transform | None = None,
        tasks: Sequence[str] | None = None,
    ) -> None:
        if split not in SPLITS:
            raise InputError(f"split: got {split!r}; valid splits are {', '.join(SPLITS)}")
        self.info = read_tile_info(data_dir)
        self.root = self.info.root
        self.split = split
        self.transform = transform
        if tasks is None:
            tasks = self.info.tasks
        bad = [t for t in tasks if t not in TASKS]
        if bad:
            raise InputError(f"tasks: got {bad[0]!r}; valid tasks are {', '.join(TASKS)}")
        self.tasks = tuple(t for t in tasks if t in self.info.tasks)
        self.rows = read_manifest(self.root, split)
        if not self.rows:
            raise InputError(
                f"split '{split}' of '{self.root}' has no patches (see {self.root / MANIFEST_CSV}); "
                "re-run `aerialmtl tile` with a larger area or other split fractions"
            )
        self._mean = torch.tensor(self.info.mean, dtype=torch.float32)
        self._std = torch.tensor(self.info.std, dtype=torch.float32)

    def __len__(self) -> int:
        return len(self.rows)

    def load(self, index: int) -> Sample:
        """Read patch ``index`` without applying the transform."""
        row = self.rows[index]
        raw = read_raw_patch(self.root, row, self.info.num_bands, self.tasks)
        batch = normalise_batch(
            torch.from_numpy(raw.image[None]), torch.from_numpy(raw.image_valid[None]), self._mean, self._std,
            None if raw.height is None else torch.from_numpy(raw.height[None, None]),
            None if raw.classes is None else torch.from_numpy(raw.classes[None]),
        )
        sample = as_sample({k: v[0] for k, v in batch.items()})
        sample["patch_id"] = row["patch_id"]
        return sample

    def __getitem__(self, index: int) -> Sample:
        sample = self.load(index)
        return self.transform(sample) if self.transform is not None else sample


__all__ = ["PatchDataset", "RawPatch", "read_raw_patch", "read_rgb_heights", "normalise_batch", "TileFolderInfo",
           "read_tile_info", "read_manifest", "class_pixel_counts", "TASKS", "SPLITS"]
