"""Torch dataset over a tile folder written by ``aerialmtl tile`` (see docs/CONTRACTS.md).

A tile folder holds ``dataset.yaml`` (normalisation, class scheme, tasks, ...), ``manifest.csv`` (one row
per patch) and one GeoTIFF per patch and layer. :class:`PatchDataset` reads one split of it and returns
:class:`~aerialmtl.data.types.Sample` dicts; patches are opened with rasterio inside ``__getitem__`` so
the dataset can be used with DataLoader worker processes (nothing holds an open file handle).
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import torch

from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.config import read_yaml
from aerialmtl.data.types import Sample
from aerialmtl.errors import ConfigError, InputError

TASKS = ("height", "classes")
SPLITS = ("train", "val", "test")
TILE_FORMAT = "aerialmtl-tiles"

Transform = Callable[[Sample], Sample]


@dataclass(frozen=True)
class TileFolderInfo:
    """The parts of ``dataset.yaml`` that datasets, training and checkpoints use.

    Attributes:
        root: the tile folder.
        tasks: tasks whose layers are present (subset of ``("height", "classes")``).
        bands: 1-based orthophoto band indexes stored in the image patches.
        band_names: one name per band.
        mean, std: per-band normalisation in raw image units (train split, valid pixels).
        gsd: ground sampling distance in metres per pixel.
        crs: CRS string of the patches.
        patch_size: patch side in pixels.
        classes: the class scheme, ``None`` without the classes task.
        raw: the whole parsed ``dataset.yaml``.
    """

    root: Path
    tasks: tuple[str, ...]
    bands: tuple[int, ...]
    band_names: tuple[str, ...]
    mean: tuple[float, ...]
    std: tuple[float, ...]
    gsd: float
    crs: str | None
    patch_size: int
    classes: ClassScheme | None
    raw: dict[str, Any]

    @property
    def num_bands(self) -> int:
        return len(self.bands)


def _not_a_tile_folder(root: Path, what: str) -> InputError:
    return InputError(
        f"'{root}' is not a tile folder: {what}. Run `aerialmtl tile` to make one, "
        "and pass the folder it wrote (the one holding dataset.yaml and manifest.csv)"
    )


def read_tile_info(data_dir: str | Path) -> TileFolderInfo:
    """Parse and check ``data_dir/dataset.yaml``.

    Raises:
        InputError: the folder or ``dataset.yaml`` is missing, or the file is not a tile-folder description.
    """
    root = Path(data_dir)
    if not root.is_dir():
        raise InputError(f"data folder '{root}' does not exist; run `aerialmtl tile` first or pass --data")
    yml = root / "dataset.yaml"
    if not yml.is_file():
        raise _not_a_tile_folder(root, f"'{yml}' is missing")
    if not (root / "manifest.csv").is_file():
        raise _not_a_tile_folder(root, f"'{root / 'manifest.csv'}' is missing")
    try:
        raw = read_yaml(yml)
    except ConfigError as exc:
        raise _not_a_tile_folder(root, str(exc)) from exc
    if not isinstance(raw, dict) or raw.get("format") != TILE_FORMAT:
        raise _not_a_tile_folder(root, f"'{yml}' has no 'format: {TILE_FORMAT}' entry")
    try:
        bands = tuple(int(b) for b in raw["bands"])
        mean = tuple(float(v) for v in raw["mean"])
        std = tuple(float(v) for v in raw["std"])
        tasks = tuple(t for t in raw.get("tasks") or () if t in TASKS)
        classes = ClassScheme.from_dict(raw["classes"]) if raw.get("classes") else None
        info = TileFolderInfo(
            root=root,
            tasks=tasks,
            bands=bands,
            band_names=tuple(str(n) for n in (raw.get("band_names") or [f"band{b}" for b in bands])),
            mean=mean,
            std=std,
            gsd=float(raw["gsd"]),
            crs=None if raw.get("crs") is None else str(raw["crs"]),
            patch_size=int(raw["patch_size"]),
            classes=classes,
            raw=raw,
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"'{yml}' is incomplete or invalid ({exc!r}); re-run `aerialmtl tile`") from exc
    if not (len(info.bands) == len(info.mean) == len(info.std)):
        raise InputError(f"'{yml}': bands, mean and std have different lengths; re-run `aerialmtl tile`")
    if any(s <= 0 for s in info.std):
        raise InputError(f"'{yml}': std must be > 0 for every band, got {list(info.std)}")
    if "classes" in info.tasks and info.classes is None:
        raise InputError(f"'{yml}': tasks include 'classes' but 'classes' (the class scheme) is empty")
    return info


def read_manifest(data_dir: str | Path, split: str | None = None) -> list[dict[str, str]]:
    """Rows of ``manifest.csv`` (all, or those of ``split``) as dicts of strings."""
    path = Path(data_dir) / "manifest.csv"
    with path.open("r", newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    if rows and "split" not in rows[0]:
        raise _not_a_tile_folder(Path(data_dir), f"'{path}' has no 'split' column")
    return [r for r in rows if split is None or r["split"] == split]


def class_pixel_counts(data_dir: str | Path, split: str, num_classes: int) -> np.ndarray:
    """Labelled pixels per class index in ``split``, summed from the manifest's ``class_hist`` (int64 (K,))."""
    counts = np.zeros(num_classes, np.int64)
    for row in read_manifest(data_dir, split):
        hist = (row.get("class_hist") or "").strip()
        if hist:
            values = [int(float(v)) for v in hist.split(";")]
            counts[: min(num_classes, len(values))] += values[:num_classes]
    return counts


class PatchDataset(torch.utils.data.Dataset):
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
                f"split '{split}' of '{self.root}' has no patches (see {self.root / 'manifest.csv'}); "
                "re-run `aerialmtl tile` with a larger area or other split fractions"
            )
        self._mean = np.asarray(self.info.mean, np.float32)[:, None, None]
        self._std = np.asarray(self.info.std, np.float32)[:, None, None]

    def __len__(self) -> int:
        return len(self.rows)

    def _path(self, row: dict[str, str], key: str) -> Path:
        rel = (row.get(key) or "").strip()
        if not rel:
            raise InputError(
                f"manifest row '{row.get('patch_id')}' of '{self.root / 'manifest.csv'}' has no {key}; "
                "re-run `aerialmtl tile`"
            )
        return self.root / rel

    def load(self, index: int) -> Sample:
        """Read patch ``index`` without applying the transform."""
        row = self.rows[index]
        with rasterio.open(self._path(row, "image_path")) as src:
            raw = src.read().astype(np.float32)
            img_valid = src.dataset_mask() > 0
        if raw.shape[0] != self._mean.shape[0]:
            raise InputError(
                f"image patch '{self._path(row, 'image_path')}' has {raw.shape[0]} bands but dataset.yaml "
                f"lists {self._mean.shape[0]}; re-run `aerialmtl tile`"
            )
        image = (raw - self._mean) / self._std
        image[:, ~img_valid] = 0.0
        sample: Sample = {"image": torch.from_numpy(np.ascontiguousarray(image)), "patch_id": row["patch_id"]}
        if "height" in self.tasks:
            with rasterio.open(self._path(row, "height_path")) as src:
                h = src.read(1).astype(np.float32)
                valid = src.read_masks(1) > 0
            valid &= np.isfinite(h) & img_valid
            h = np.where(valid, h, 0.0).astype(np.float32)
            sample["height"] = torch.from_numpy(h[None])
            sample["height_valid"] = torch.from_numpy(valid[None])
        if "classes" in self.tasks:
            with rasterio.open(self._path(row, "classes_path")) as src:
                c = src.read(1)
                valid = src.read_masks(1) > 0
            cls = c.astype(np.int64)
            cls[~(valid & img_valid)] = IGNORE_INDEX
            sample["classes"] = torch.from_numpy(cls)
        return sample

    def __getitem__(self, index: int) -> Sample:
        sample = self.load(index)
        return self.transform(sample) if self.transform is not None else sample


__all__ = ["PatchDataset", "TileFolderInfo", "read_tile_info", "read_manifest", "class_pixel_counts",
           "TASKS", "SPLITS"]
