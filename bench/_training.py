"""What the training benchmarks share (bench/train.py, train_loop.py, train_overhead.py): the synthetic town they
tile, and a random training batch already on the device for the model step alone."""

from __future__ import annotations

from pathlib import Path

import torch


def town_tiles(workdir: Path, town_px: int, stride: int = 320, val: float = 0.0) -> Path:
    """A synthetic town of ``town_px``² at 0.25 m (seed 3) tiled into 320² patches at ``stride``, a ``val`` share
    of 160 m blocks for validation and the rest for training; made once under ``workdir``, reused if present."""
    from aerialmtl.data.synth import synthesize
    from aerialmtl.tiling.splits import SplitSpec
    from aerialmtl.tiling.tile import TileOptions, tile_dataset

    tiles = workdir / f"tiles_{town_px}_{stride}_val{val:g}"
    if (tiles / "dataset.yaml").is_file():
        return tiles
    town = synthesize(workdir / f"town_{town_px}", size=town_px, seed=3, gsd=0.25, overwrite=True)
    tile_dataset(town.ortho, tiles, ndsm=town.ndsm, labels=town.labels, classes=town.classes, overwrite=True,
                 progress=False, options=TileOptions(size=320, stride=stride, splits=SplitSpec(
                     block_size=160.0, ratios=(1 - val, val, 0.0), seed=0)))
    return tiles


def random_batch(batch: int, bands: int, size: int, classes: int | None,
                 device: torch.device) -> dict[str, torch.Tensor]:
    """A seeded random batch as the training step takes it: image (B, bands, size, size) channels_last, heights
    0–20 m all valid, and class indices (B, size, size) when ``classes`` is given."""
    g = torch.Generator().manual_seed(0)
    out = {"image": torch.randn(batch, bands, size, size, generator=g).to(device)
           .contiguous(memory_format=torch.channels_last),
           "height": (torch.rand(batch, 1, size, size, generator=g) * 20).to(device),
           "height_valid": torch.ones(batch, 1, size, size, dtype=torch.bool, device=device)}
    if classes:
        out["classes"] = torch.randint(0, classes, (batch, size, size), generator=g).to(device)
    return out
