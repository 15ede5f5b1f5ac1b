"""Test helper: write a tiny tile folder exactly as docs/CONTRACTS.md describes it.

The scene is learnable: the image's red band rises with height and its green band marks trees, so a
small network can fit both tasks in a few dozen steps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
from affine import Affine

from aerialmtl.classes import ClassScheme
from aerialmtl.formats.tiles import MANIFEST_COLUMNS, ManifestWriter, TileFolderInfo, patch_path

CRS = "EPSG:32631"
SCHEME = {
    "name": "toy",
    "ignore_codes": [0],
    "classes": [
        {"code": 1, "name": "ground", "color": [180, 150, 110]},
        {"code": 2, "name": "building", "color": [220, 40, 40]},
        {"code": 3, "name": "tree", "color": [20, 120, 30]},
    ],
}


def toy_patch(rng: np.random.Generator, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image uint8 3×H×W, height float32 H×W metres, classes uint8 H×W) with rectangles of buildings/trees."""
    cls = np.zeros((size, size), np.uint8)
    height = np.zeros((size, size), np.float32)
    for _ in range(4):
        r, c = rng.integers(0, size - 12, 2)
        h, w = rng.integers(8, 24, 2)
        k = int(rng.integers(1, 3))
        cls[r:r + h, c:c + w] = k
        height[r:r + h, c:c + w] = 8.0 if k == 1 else 4.0
    image = np.stack([60 + 15 * height, 80 + 100 * (cls == 2), np.full_like(height, 90)])
    image = image + rng.normal(0, 3, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8), height, cls


def write_tile_folder(
    root: Path,
    size: int = 64,
    counts: dict[str, int] | None = None,
    tasks: tuple[str, ...] = ("height", "classes"),
    seed: int = 0,
    invalid_corner: bool = True,
) -> Path:
    """Write ``root/dataset.yaml``, ``manifest.csv`` and patches; returns ``root``.

    With ``invalid_corner`` the first train patch has a 4×4 nodata corner in every layer (image masked,
    height -9999, classes 255) and one unlabelled pixel (255) at (10, 10).
    """
    counts = counts or {"train": 8, "val": 2, "test": 0}
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    rows, stats = [], []
    gsd = 0.5
    n = 0
    for split, count in counts.items():
        for layer in ("image", *tasks):
            (root / split / layer).mkdir(parents=True, exist_ok=True)
        for _ in range(count):
            pid = f"p{n:04d}"
            image, height, cls = toy_patch(rng, size)
            valid = np.ones((size, size), bool)
            if invalid_corner and n == 0:
                valid[:4, :4] = False
                cls[10, 10] = 255
            left, top = 500000.0 + n * size * gsd, 5000000.0
            tr = Affine(gsd, 0, left, 0, -gsd, top)
            base = dict(driver="GTiff", width=size, height=size, crs=CRS, transform=tr)
            row = {c: "" for c in MANIFEST_COLUMNS}
            row.update(patch_id=pid, split=split, col_off=n * size, row_off=0, width=size, height=size,
                       left=left, bottom=top - size * gsd, right=left + size * gsd, top=top, crs=CRS,
                       valid_fraction=float(valid.mean()))
            row["image_path"] = patch_path(split, "image", pid)
            with rasterio.open(root / row["image_path"], "w", count=3, dtype="uint8", **base) as dst:
                dst.write(image)
                dst.write_mask(valid.astype(np.uint8) * 255)
            if split == "train":
                stats.append(image[:, valid].astype(np.float64))
            if "height" in tasks:
                h = np.where(valid, height, -9999.0).astype(np.float32)
                row["height_path"] = patch_path(split, "height", pid)
                with rasterio.open(root / row["height_path"], "w", count=1, dtype="float32", nodata=-9999.0,
                                   **base) as dst:
                    dst.write(h[None])
                row.update(height_min=float(height[valid].min()), height_mean=float(height[valid].mean()),
                           height_max=float(height[valid].max()))
            if "classes" in tasks:
                c = np.where(valid, cls, 255).astype(np.uint8)
                row["classes_path"] = patch_path(split, "classes", pid)
                with rasterio.open(root / row["classes_path"], "w", count=1, dtype="uint8", nodata=255,
                                   **base) as dst:
                    dst.write(c[None])
                row["class_hist"] = ";".join(str(int((c == k).sum())) for k in range(3))
            rows.append(row)
            n += 1
    allpix = np.concatenate(stats, axis=1)
    TileFolderInfo(
        root=root, crs=CRS, gsd=gsd, patch_size=size, stride=size, bands=(1, 2, 3),
        band_names=("red", "green", "blue"), dtype="uint8",
        mean=tuple(float(v) for v in allpix.mean(axis=1)), std=tuple(float(v) for v in allpix.std(axis=1)),
        tasks=tasks, classes=ClassScheme.from_dict(SCHEME) if "classes" in tasks else None,
        height={"nodata": -9999.0, "clip_negative": True, "max_height": None, "source": "ndsm"}
        if "height" in tasks else None,
        splits={"method": "test"}, counts=counts, provenance={"inputs": "tests/helpers/tilefolder.py"},
    ).write()
    with ManifestWriter(root) as manifest:
        for row in rows:
            manifest.writerow(row)
    return root
