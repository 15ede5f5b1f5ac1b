"""The tile folder: what ``aerialmtl tile`` writes and training reads.

::

    OUT/dataset.yaml                              DATASET_YAML: TileFolderInfo (normalisation, classes, ...)
    OUT/manifest.csv                              MANIFEST_CSV: one row per patch (MANIFEST_COLUMNS)
    OUT/{train,val,test}/image/<patch_id>.tif     raw ortho bands (source dtype), internal mask where invalid
    OUT/{train,val,test}/height/<patch_id>.tif    float32 metres, nodata -9999
    OUT/{train,val,test}/classes/<patch_id>.tif   uint8 class indices 0..K-1, nodata 255
    OUT/cache/<split>.*                           CACHE_DIR: the decoded patch cache (PatchCacheIndex)

A tile run writes its patches and ``manifest.csv`` into a hidden staging folder ``OUT/.patches.partial``
(the staging folder of :data:`STAGING_NAME`), moves them into place when every patch is written and writes
``dataset.yaml`` last
(files go through ``.NAME.partial`` and a rename, :mod:`aerialmtl.io.outputs`), so ``dataset.yaml`` marks
a finished tile folder. Together with ``manifest.csv`` it is also the proof of what the tile run owns
(:func:`owned_files`): ``--overwrite`` removes exactly those files (and the patch cache), never another
file in the folder. The patch cache is derived data: training writes it on first
use (see :mod:`aerialmtl.data.cache`), its index records a fingerprint of the manifest rows, of
``dataset.yaml`` and of every patch file's size and modification time, and a cache whose fingerprint no
longer matches is rebuilt, never used.

This module owns the file names, the ``dataset.yaml`` keys and the manifest columns; the tiler, the
datasets, the cache and the test helpers read and write through it.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import yaml

from aerialmtl.classes import ClassScheme
from aerialmtl.config import read_yaml
from aerialmtl.errors import ConfigError, InputError
from aerialmtl.filesafety import staging_path
from aerialmtl.io.outputs import write_text_atomic

#: The ``format`` tag of ``dataset.yaml`` and its version.
FORMAT = "aerialmtl-tiles"
FORMAT_VERSION = 1

DATASET_YAML = "dataset.yaml"
#: nodata of the float32 height patches (and of the height rasters ``aerialmtl synth`` writes).
HEIGHT_NODATA = -9999.0
MANIFEST_CSV = "manifest.csv"
#: Folder (inside the tile folder) of the decoded patch cache.
CACHE_DIR = "cache"
#: A tile run writes its patches and manifest into the staging folder of this name before moving them into
#: place: ``.patches.partial`` (:func:`aerialmtl.filesafety.staging_path`, :func:`~aerialmtl.io.outputs.is_staging_of`).
STAGING_NAME = "patches"

SPLITS = ("train", "val", "test")
#: Tasks a tile folder can hold references for (its layers besides ``image``).
TASKS = ("height", "classes")
LAYERS = ("image", *TASKS)

#: ``manifest.csv`` columns: the patch id and split; each layer's patch path relative to the folder (empty
#: when absent); the window on the reference grid (pixels) and its bounds (map units) and CRS; the valid
#: image fraction; ``class_hist`` (pixels per class index joined by ``;``, empty without classes); the
#: patch's min / mean / max height in metres (empty without height).
MANIFEST_COLUMNS = (
    "patch_id", "split", "image_path", "height_path", "classes_path",
    "col_off", "row_off", "width", "height", "left", "bottom", "right", "top", "crs",
    "valid_fraction", "class_hist", "height_min", "height_mean", "height_max",
)

#: Manifest column holding the relative path of each layer's patch.
LAYER_COLUMNS = {"image": "image_path", "height": "height_path", "classes": "classes_path"}


def patch_path(split: str, layer: str, patch_id: str) -> str:
    """Path of a patch relative to the tile folder (``train/image/<id>.tif``)."""
    return f"{split}/{layer}/{patch_id}.tif"


def _not_a_tile_folder(root: Path, what: str) -> InputError:
    return InputError(
        f"'{root}' is not a tile folder: {what}. Run `aerialmtl tile` to make one, "
        "and pass the folder it wrote (the one holding dataset.yaml and manifest.csv)"
    )


def _write_atomic(path: Path, text: str) -> None:
    write_text_atomic(path, text)


@dataclass(frozen=True)
class TileFolderInfo:
    """``dataset.yaml`` of the tile folder ``root``.

    Attributes:
        root: the tile folder.
        crs: CRS string of the patches.
        gsd: ground sampling distance in metres per pixel.
        patch_size: patch side in pixels.
        bands: 1-based orthophoto band indexes stored in the image patches.
        mean, std: per-band normalisation in raw image units (train split, valid pixels); empty when the
            folder has no train patches (written as ``null``).
        tasks: tasks whose layers are present (subset of :data:`TASKS`).
        band_names: one name per band.
        stride: step between patches (pixels).
        dtype: numpy dtype name of the image patches.
        classes: the class scheme, ``None`` without the classes task.
        height: how heights were made (``nodata``, ``clip_negative``, ``max_height`` in metres, ``source``
            ``ndsm``/``dsm-dtm``, ``units``: the unit each height raster was read in and where that came
            from), or ``None``.
        splits: the spatial split specification (``method``, ``block_size`` asked and
            ``block_size_used_m`` after snapping to the patch stride, ``ratios``, ``seed``; or the AOIs).
        counts: patches per split.
        min_valid: minimum valid fraction of a kept patch.
        provenance: input paths, aerialmtl version, creation time.
        extra: keys this version does not know, kept as read and written after the known ones.
    """

    root: Path
    crs: str | None
    gsd: float
    patch_size: int
    bands: tuple[int, ...]
    mean: tuple[float, ...]
    std: tuple[float, ...]
    tasks: tuple[str, ...] = ()
    band_names: tuple[str, ...] = ()
    stride: int | None = None
    dtype: str | None = None
    classes: ClassScheme | None = None
    height: dict[str, Any] | None = None
    splits: dict[str, Any] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    min_valid: float | None = None
    provenance: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def num_bands(self) -> int:
        """Number of orthophoto bands of the patches."""
        return len(self.bands)

    @property
    def path(self) -> Path:
        """``root/dataset.yaml``."""
        return self.root / DATASET_YAML

    @property
    def manifest(self) -> Path:
        """``root/manifest.csv``."""
        return self.root / MANIFEST_CSV

    def to_dict(self) -> dict[str, Any]:
        """The ``dataset.yaml`` mapping, keys in the documented order."""
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "crs": self.crs,
            "gsd": float(self.gsd),
            "patch_size": int(self.patch_size),
            "stride": None if self.stride is None else int(self.stride),
            "bands": [int(b) for b in self.bands],
            "band_names": list(self.band_names),
            "dtype": self.dtype,
            "mean": [float(v) for v in self.mean] or None,
            "std": [float(v) for v in self.std] or None,
            "tasks": list(self.tasks),
            "classes": self.classes.to_dict() if self.classes is not None else None,
            "height": self.height,
            "splits": self.splits,
            "counts": dict(self.counts),
            "min_valid": self.min_valid,
            "provenance": self.provenance,
            **self.extra,
        }

    def write(self) -> Path:
        """Write ``root/dataset.yaml`` (atomically, through ``.dataset.yaml.partial``); returns its path."""
        _write_atomic(self.path, yaml.safe_dump(self.to_dict(), sort_keys=False, allow_unicode=True))
        return self.path

    @classmethod
    def read(cls, data_dir: str | Path) -> TileFolderInfo:
        """Parse and check ``data_dir/dataset.yaml`` (``manifest.csv`` must exist too).

        Raises:
            InputError: the folder or a file is missing, or ``dataset.yaml`` is not a tile-folder description.
        """
        root = Path(data_dir)
        if not root.is_dir():
            raise InputError(f"data folder '{root}' does not exist; run `aerialmtl tile` first or pass ‹data_dir›")
        yml = root / DATASET_YAML
        if not yml.is_file():
            raise _not_a_tile_folder(root, f"'{yml}' is missing")
        if not (root / MANIFEST_CSV).is_file():
            raise _not_a_tile_folder(root, f"'{root / MANIFEST_CSV}' is missing")
        try:
            raw = read_yaml(yml)
        except ConfigError as exc:
            raise _not_a_tile_folder(root, str(exc)) from exc
        if not isinstance(raw, dict) or raw.get("format") != FORMAT:
            raise _not_a_tile_folder(root, f"'{yml}' has no 'format: {FORMAT}' entry")
        known = {"format", "format_version", "crs", "gsd", "patch_size", "stride", "bands", "band_names", "dtype",
                 "mean", "std", "tasks", "classes", "height", "splits", "counts", "min_valid", "provenance"}
        try:
            bands = tuple(int(b) for b in raw["bands"])
            info = cls(
                root=root,
                crs=None if raw.get("crs") is None else str(raw["crs"]),
                gsd=float(raw["gsd"]),
                patch_size=int(raw["patch_size"]),
                bands=bands,
                mean=tuple(float(v) for v in raw["mean"]),
                std=tuple(float(v) for v in raw["std"]),
                tasks=tuple(t for t in raw.get("tasks") or () if t in TASKS),
                band_names=tuple(str(n) for n in (raw.get("band_names") or [f"band{b}" for b in bands])),
                stride=None if raw.get("stride") is None else int(raw["stride"]),
                dtype=None if raw.get("dtype") is None else str(raw["dtype"]),
                classes=ClassScheme.from_dict(raw["classes"]) if raw.get("classes") else None,
                height=raw.get("height"),
                splits=dict(raw.get("splits") or {}),
                counts=dict(raw.get("counts") or {}),
                min_valid=None if raw.get("min_valid") is None else float(raw["min_valid"]),
                provenance=dict(raw.get("provenance") or {}),
                extra={k: v for k, v in raw.items() if k not in known},
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


def read_tile_info(data_dir: str | Path) -> TileFolderInfo:
    """:meth:`TileFolderInfo.read` (parse and check ``data_dir/dataset.yaml``)."""
    return TileFolderInfo.read(data_dir)


def read_manifest(path: str | Path, split: str | None = None) -> list[dict[str, str]]:
    """Rows of a tile folder's ``manifest.csv`` (all, or those of ``split``) as dicts of strings.

    Args:
        path: the tile folder, or its ``manifest.csv``.
        split: keep only this split's rows.

    Raises:
        InputError: a manifest without a ``split`` column.
    """
    path = Path(path)
    csv_path = path / MANIFEST_CSV if path.is_dir() else path
    with csv_path.open("r", newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    if rows and "split" not in rows[0]:
        raise _not_a_tile_folder(csv_path.parent, f"'{csv_path}' has no 'split' column")
    return [r for r in rows if split is None or r["split"] == split]


class ManifestWriter:
    """Stream manifest rows into ``root/.manifest.csv.partial``; renamed to ``manifest.csv`` on a clean exit.

    Usage::

        with ManifestWriter(out_dir) as manifest:
            manifest.writerow({"patch_id": ..., "split": ..., ...})   # missing columns are written empty

    On an exception the part file is closed and left for the caller to remove.
    """

    def __init__(self, root: str | Path) -> None:
        self.path = Path(root) / MANIFEST_CSV
        self.part = staging_path(self.path)
        self._fh = self.part.open("w", newline="", encoding="utf-8")
        self._writer = csv.DictWriter(self._fh, fieldnames=list(MANIFEST_COLUMNS), restval="")
        self._writer.writeheader()

    def writerow(self, row: dict[str, Any]) -> None:
        """Append one manifest row (keys: :data:`MANIFEST_COLUMNS`)."""
        self._writer.writerow(row)

    def __enter__(self) -> ManifestWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._fh.close()
        if exc_type is None:
            self.part.replace(self.path)
        else:
            self.part.unlink(missing_ok=True)


def owned_files(root: str | Path) -> list[str] | None:
    """Files (relative to ``root``) that a finished tile run there wrote, as its own index files prove.

    Returns ``dataset.yaml``, ``manifest.csv``, every patch the manifest lists (inside the split folders
    only) and the patch cache's files (:func:`cache_file`, :func:`cache_index_file`, the ``<split>.lock``
    files of :mod:`aerialmtl.data.cache`); ``None`` when ``root`` holds no tile dataset (no readable
    ``dataset.yaml`` of this format, or no ``manifest.csv``).
    """
    root = Path(root)
    try:
        TileFolderInfo.read(root)
        rows = read_manifest(root)
    except (InputError, ConfigError, OSError, ValueError):
        return None
    files = [DATASET_YAML, MANIFEST_CSV]
    for row in rows:
        for key in ("image_path", "height_path", "classes_path"):
            rel = row.get(key) or ""
            parts = Path(rel).parts
            if len(parts) == 3 and parts[0] in SPLITS and ".." not in parts:
                files.append(rel)
    cache = Path(CACHE_DIR)
    for split in SPLITS:
        files += [str(cache_file(cache, split, a)) for a in CACHE_ARRAYS]
        files += [str(cache_index_file(cache, split)), str(cache / f"{split}.lock")]
    return files


# ---- the patch cache ----------------------------------------------------------------------------
#: The ``format`` tag of a cache index and its version (bump when the arrays' meaning changes).
CACHE_FORMAT = "aerialmtl-patch-cache"
CACHE_VERSION = 1
#: Arrays of a split's cache: name → (dtype, shape after N) as documented in :class:`PatchCacheIndex`.
CACHE_ARRAYS = ("image", "image_valid", "height", "classes")


def cache_dir(root: str | Path) -> Path:
    """The cache folder of tile folder ``root``."""
    return Path(root) / CACHE_DIR


def cache_file(folder: str | Path, split: str, array: str) -> Path:
    """``<folder>/<split>.<array>.npy`` (``array`` in :data:`CACHE_ARRAYS`)."""
    return Path(folder) / f"{split}.{array}.npy"


def cache_index_file(folder: str | Path, split: str) -> Path:
    """``<folder>/<split>.json``: the index, written last."""
    return Path(folder) / f"{split}.json"


def split_fingerprint(info: TileFolderInfo, rows: list[dict[str, str]]) -> str:
    """SHA-256 of what a split's cache is decoded from.

    Covers ``dataset.yaml`` (bands, tasks), the split's manifest rows in order, and each patch file's size
    and modification time (a re-tiled or edited patch changes it).
    """
    h = hashlib.sha256()
    h.update(f"{CACHE_FORMAT}:{CACHE_VERSION}\n".encode())
    h.update(info.path.read_bytes())
    for row in rows:
        h.update(json.dumps([row.get(c, "") for c in MANIFEST_COLUMNS]).encode())
        for layer, column in LAYER_COLUMNS.items():
            rel = (row.get(column) or "").strip()
            if rel:
                st = os.stat(info.root / rel)
                h.update(f"{layer}:{st.st_size}:{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


@dataclass(frozen=True)
class PatchCacheIndex:
    """``cache/<split>.json``: what the arrays of one split's cache hold.

    Arrays (``numpy.save`` files, memory-mapped when read), N patches in manifest order, H×W pixels:

    * ``image`` (N, C, H, W), the image patches' dtype (raw values, not normalised);
    * ``image_valid`` (N, H, W) uint8, 1 where the image is valid;
    * ``height`` (N, 1, H, W) float32 metres, NaN where the height is invalid (nodata, non-finite, or
      the image invalid) — only when the folder has heights;
    * ``classes`` (N, H, W) uint8 class indices, 255 where unlabelled or the image is invalid — only
      when the folder has classes.

    Attributes:
        split: the split.
        fingerprint: :func:`split_fingerprint` of the folder when the cache was written.
        count: N.
        layers: the arrays present (subset of :data:`CACHE_ARRAYS`).
        image_dtype: numpy dtype name of ``image``.
        shape: (C, H, W) of one image patch.
    """

    split: str
    fingerprint: str
    count: int
    layers: tuple[str, ...]
    image_dtype: str
    shape: tuple[int, int, int]

    def to_dict(self) -> dict[str, Any]:
        """The index as plain types (written as JSON)."""
        return {"format": CACHE_FORMAT, "version": CACHE_VERSION, "split": self.split,
                "fingerprint": self.fingerprint, "count": self.count, "layers": list(self.layers),
                "image_dtype": self.image_dtype, "shape": list(self.shape)}

    def write(self, folder: str | Path) -> Path:
        """Write the index (atomically); call it after every array is in place."""
        path = cache_index_file(folder, self.split)
        _write_atomic(path, json.dumps(self.to_dict(), indent=1))
        return path

    @classmethod
    def read(cls, folder: str | Path, split: str) -> PatchCacheIndex | None:
        """The index of ``split`` in ``folder``, or ``None`` when absent, unreadable or of another version."""
        path = cache_index_file(folder, split)
        try:
            raw = json.loads(path.read_text(encoding="utf-8"))
            if raw.get("format") != CACHE_FORMAT or raw.get("version") != CACHE_VERSION:
                return None
            c, h, w = (int(v) for v in raw["shape"])
            return cls(split=str(raw["split"]), fingerprint=str(raw["fingerprint"]), count=int(raw["count"]),
                       layers=tuple(str(v) for v in raw["layers"]), image_dtype=str(raw["image_dtype"]),
                       shape=(c, h, w))
        except (OSError, ValueError, KeyError, TypeError):
            return None


__all__ = ["FORMAT", "FORMAT_VERSION", "DATASET_YAML", "MANIFEST_CSV", "CACHE_DIR", "SPLITS",
           "STAGING_NAME", "owned_files",
           "TASKS", "LAYERS", "MANIFEST_COLUMNS", "LAYER_COLUMNS", "patch_path", "TileFolderInfo", "read_tile_info",
           "read_manifest", "ManifestWriter", "CACHE_FORMAT", "CACHE_VERSION", "CACHE_ARRAYS", "cache_dir",
           "cache_file", "cache_index_file", "split_fingerprint", "PatchCacheIndex"]
