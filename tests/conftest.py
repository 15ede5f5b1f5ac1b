"""Shared test fixtures: tiny georeferenced rasters generated in ``tmp_path`` with a fixed seed."""

from __future__ import annotations

import os

# Before torch loads OpenMP: threads that sleep instead of spinning while they wait. On a CPU shared with
# other jobs, spinning threads steal the cores the work needs (bench/RESULTS.md, train: 6× slower model
# steps at load 6); results do not change, only their speed. Child processes (torchrun, notebooks) inherit it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import rasterio  # noqa: E402
import torch  # noqa: E402
from affine import Affine  # noqa: E402

#: Real sample data shipped beside the repository (see ../shared/data/README.md).
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
NEON_DIR = SHARED_DATA / "neon_bart"

torch.set_num_threads(max(1, min(2, torch.get_num_threads())))


def write_raster(
    path: Path,
    data: np.ndarray,
    crs: str = "EPSG:32631",
    transform: Affine | None = None,
    nodata: float | None = None,
    **extra: object,
) -> Path:
    """Write ``data`` (bands, H, W) or (H, W) as a GeoTIFF; default grid: 0.5 m pixels at (500000, 5000000)."""
    if data.ndim == 2:
        data = data[None]
    transform = transform or Affine(0.5, 0, 500000.0, 0, -0.5, 5000000.0)
    profile = dict(driver="GTiff", width=data.shape[2], height=data.shape[1], count=data.shape[0],
                   dtype=data.dtype, crs=crs, transform=transform, nodata=nodata, **extra)
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data)
    return path


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
