"""Tiling: grids of windows, spatial train/val/test splits, and the `tile` command's library function."""

from aerialmtl.tiling.grid import count_windows, tile_windows
from aerialmtl.tiling.splits import SplitAssigner, SplitSpec
from aerialmtl.tiling.tile import MANIFEST_COLUMNS, TileResult, read_manifest, tile_dataset

__all__ = ["MANIFEST_COLUMNS", "SplitAssigner", "SplitSpec", "TileResult", "count_windows", "read_manifest",
           "tile_dataset", "tile_windows"]
