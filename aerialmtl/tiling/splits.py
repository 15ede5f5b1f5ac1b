"""Spatial train/val/test splits that never let a patch straddle two splits.

Two methods:

* ``blocks`` — the grid is cut into disjoint square blocks of ``block_size`` metres (converted through
  the CRS's linear unit, so feet CRSs work), anchored at the grid's upper-left corner. When the patch
  stride is known (``tile``), the block side is snapped to the whole number of strides nearest to
  ``block_size`` (at least enough to hold one patch, and two patch sides when patches overlap, so that a
  val or test block keeps several patches), so blocks follow the patch grid and, with
  ``stride == size``, no patch straddles two blocks; the side actually used is recorded
  (:attr:`SplitAssigner.block_size_m`). Blocks are visited in a seeded random order and dealt to the
  split furthest below its share of the area (``ratios``); every split with a ratio > 0 gets at least one
  block when there are enough blocks. A patch is kept only if every block it touches belongs to the same
  split, so patches of different splits never share a pixel, whatever the stride.
* ``aoi`` — polygons per split: one GeoJSON whose features carry a ``split`` property (``train``, ``val``
  or ``test``), or one GeoJSON per split. A patch belongs to a split when its footprint lies inside that
  split's polygons (and no other split's); others are dropped. AOIs that overlap each other make the
  overlap unusable rather than leaky.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import shapely
from rasterio.windows import Window
from shapely.geometry import box

from aerialmtl.errors import InputError
from aerialmtl.io.vector import check_aoi_overlaps, load_geometries

SPLITS = ("train", "val", "test")
#: With overlapping patches (stride < size), a split block is at least this many patch sides wide.
MIN_PATCHES_PER_BLOCK_SIDE = 2


@dataclass(frozen=True)
class SplitSpec:
    """How patches are assigned to train/val/test.

    Attributes:
        method: ``"blocks"`` (random square blocks) or ``"aoi"`` (polygons).
        block_size: block side in metres, for ``blocks`` (snapped to the patch stride, see the module
            docstring).
        ratios: fractions of the area for (train, val, test), for ``blocks``; normalised to sum to 1.
        seed: RNG seed of the block shuffle.
        aoi: for ``aoi``: one GeoJSON path whose features have a ``split`` property, or a mapping
            ``{"train": path, "val": path, "test": path}`` (any subset).
        aoi_field: name of the property holding the split in a single AOI file.
    """

    method: Literal["blocks", "aoi"] = "blocks"
    block_size: float = 100.0
    ratios: tuple[float, float, float] = (0.7, 0.15, 0.15)
    seed: int = 0
    aoi: str | dict[str, str] | None = None
    aoi_field: str = "split"

    def __post_init__(self) -> None:
        if self.method not in ("blocks", "aoi"):
            raise InputError(f"split method must be 'blocks' or 'aoi', got {self.method!r}")
        if self.method == "blocks":
            if not 0 < self.block_size < math.inf:
                raise InputError(f"‹block_size› must be a positive size in metres, got {self.block_size}",
                                 param="block_size")
            if not 0 <= self.seed < 2**32:
                raise InputError(f"‹seed› must be an integer in 0..2**32-1, got {self.seed}", param="seed")
            r = tuple(float(x) for x in self.ratios)
            if len(r) != 3 or any(x < 0 or not math.isfinite(x) for x in r) or sum(r) <= 0:
                raise InputError(
                    f"‹ratios› must be three non-negative numbers for train,val,test with a positive sum, "
                    f"got {self.ratios}; e.g. ‹ratios=0.7,0.15,0.15›", param="ratios"
                )
        elif self.aoi is None:
            raise InputError("split method 'aoi' needs AOI polygons: pass ‹aoi=FILE›")

    def to_dict(self) -> dict[str, Any]:
        """Plain mapping for ``dataset.yaml``."""
        if self.method == "blocks":
            total = sum(self.ratios)
            return {"method": "blocks", "block_size": float(self.block_size),
                    "ratios": [float(x) / total for x in self.ratios], "seed": int(self.seed)}
        if isinstance(self.aoi, (str, Path)):
            aoi: str | dict[str, str] = str(Path(self.aoi).resolve())
        else:
            aoi = {k: str(Path(v).resolve()) for k, v in dict(self.aoi or {}).items()}
        return {"method": "aoi", "aoi": aoi, "aoi_field": self.aoi_field}


def assign_blocks(areas: np.ndarray, ratios: tuple[float, ...], rng: np.random.Generator) -> np.ndarray:
    """Deal blocks to splits so that each split's share of the *area* follows ``ratios``.

    Blocks are visited in a random order (``rng``) and each goes to the split furthest below its target
    area. Edge blocks are often slivers, so counting blocks instead of area could hand the one big block
    to ``val``. Afterwards every split with a positive ratio gets at least one block when there are enough
    blocks (the smallest block of the split holding the most blocks is moved to it).

    Args:
        areas: (n,) area of each block inside the grid (any unit).
        ratios: target fractions per split (normalised to sum to 1).
        rng: seeded generator.

    Returns:
        (n,) int array: split index of each block.
    """
    areas = np.asarray(areas, dtype=float)
    r = np.asarray(ratios, dtype=float)
    r = r / r.sum()
    target = r * areas.sum()
    assigned = np.zeros(len(r))
    out = np.zeros(len(areas), dtype=int)
    for b in rng.permutation(len(areas)):
        deficit = np.where(r > 0, target - assigned, -np.inf)
        k = int(np.argmax(deficit))
        out[b] = k
        assigned[k] += areas[b]
    wanted = [k for k in range(len(r)) if r[k] > 0]
    if len(areas) >= len(wanted):
        for k in wanted:
            if not np.any(out == k):
                counts = np.bincount(out, minlength=len(r))
                donor = int(np.argmax(counts))
                members = np.nonzero(out == donor)[0]
                out[members[np.argmin(areas[members])]] = k
    return out


class SplitAssigner:
    """Assigns windows of a grid to a split (or to none) following a :class:`SplitSpec`.

    Args:
        spec: the split specification.
        grid: the reference :class:`~aerialmtl.io.align.Grid` (north-up).
        stride: the patch stride in pixels; with it, blocks are snapped to whole strides.
        size: the patch size in pixels; with ``stride``, a block holds at least one whole patch.
    """

    def __init__(self, spec: SplitSpec, grid: Any, stride: int | None = None, size: int | None = None) -> None:
        self.spec = spec
        self.grid = grid
        self.stride = stride
        self.size = size
        self.block_size_m: float | None = None
        if spec.method == "blocks":
            self._setup_blocks()
        else:
            self._setup_aoi()

    # ---- blocks -------------------------------------------------------------------------------
    def _setup_blocks(self) -> None:
        res_x, res_y = self.grid.res
        unit = self.grid.unit_m
        # block side in pixels of the grid along x and y (square on the ground)
        bx = float(self.spec.block_size) / (res_x * unit)
        by = float(self.spec.block_size) / (res_y * unit)
        if self.stride is not None:  # follow the patch grid: a whole number of strides, holding a whole patch
            least = max(1, math.ceil(self.size / self.stride)) if self.size else 1
            if self.size and self.stride < self.size:
                # overlapping patches: a patch is kept only inside one split, so a block holding a single
                # patch keeps one patch of an isolated val/test block and drops its neighbours (the README's
                # small-area recipe gave validation 5 of 143 patches); blocks of two patch sides keep
                # (size/stride + 1)² patches each (26 val patches of 273 there)
                least = math.ceil(MIN_PATCHES_PER_BLOCK_SIDE * self.size / self.stride)
            bx = float(max(least, round(bx / self.stride)) * self.stride)
            by = float(max(least, round(by / self.stride)) * self.stride)
        self.block_px = (bx, by)
        #: block side actually used, in metres (mean of x and y)
        self.block_size_m = 0.5 * (bx * res_x + by * res_y) * unit
        self.nbx = max(1, math.ceil(self.grid.width / bx - 1e-9))
        self.nby = max(1, math.ceil(self.grid.height / by - 1e-9))
        # area of each block inside the grid (edge blocks are clipped), in pixels
        wx = np.minimum(bx, self.grid.width - bx * np.arange(self.nbx))
        wy = np.minimum(by, self.grid.height - by * np.arange(self.nby))
        areas = np.outer(np.clip(wy, 0, None), np.clip(wx, 0, None))
        rng = np.random.default_rng(self.spec.seed)
        #: (nby, nbx) split index (0 train, 1 val, 2 test) of each block, top row first.
        self.block_split = assign_blocks(areas.ravel(), self.spec.ratios, rng).reshape(self.nby, self.nbx)

    def block_range(self, window: Window) -> tuple[int, int, int, int]:
        """Blocks touched by ``window``: ``(bx0, bx1, by0, by1)`` inclusive, clipped to the block grid."""
        bx, by = self.block_px
        c0, r0 = float(window.col_off), float(window.row_off)
        c1, r1 = c0 + float(window.width), r0 + float(window.height)

        def idx(pix: float, size: float) -> int:
            return math.floor(pix / size + 1e-9)

        def idx_end(pix: float, size: float) -> int:  # block of the last pixel (exclusive edge)
            return math.ceil(pix / size - 1e-9) - 1

        bx0, bx1 = idx(c0, bx), idx_end(c1, bx)
        by0, by1 = idx(r0, by), idx_end(r1, by)

        def clip(v: int, n: int) -> int:
            return min(max(v, 0), n - 1)

        return clip(bx0, self.nbx), clip(bx1, self.nbx), clip(by0, self.nby), clip(by1, self.nby)

    # ---- AOI ----------------------------------------------------------------------------------
    def _setup_aoi(self) -> None:
        aoi = self.spec.aoi
        per_split: dict[str, list[shapely.Geometry]] = {s: [] for s in SPLITS}
        if isinstance(aoi, (str, Path)):
            for g, props in load_geometries(aoi, self.grid.crs, "split AOI"):
                value = props.get(self.spec.aoi_field)
                name = str(value).strip().lower() if value is not None else None
                if name == "validation":
                    name = "val"
                if name not in per_split:
                    raise InputError(
                        f"split AOI '{aoi}': a feature has {self.spec.aoi_field}={value!r}; every feature needs "
                        f"a '{self.spec.aoi_field}' property of train, val or test"
                    )
                per_split[name].append(g)
        else:
            assert aoi is not None, "SplitSpec checks that method 'aoi' has its polygons"
            for name, path in dict(aoi).items():
                if name not in per_split:
                    raise InputError(f"split AOI for unknown split {name!r}; use train, val or test")
                per_split[name].extend(g for g, _ in load_geometries(path, self.grid.crs, f"{name} AOI"))
        self.aoi = {s: shapely.union_all(gs) for s, gs in per_split.items() if gs}
        for g in self.aoi.values():
            shapely.prepare(g)
        check_aoi_overlaps(aoi, list(self.aoi.values()), self.grid, role="split AOI (‹aoi›)", param="aoi")

    # ---- common -------------------------------------------------------------------------------
    def split_of(self, window: Window) -> str | None:
        """The split of the patch covering ``window``, or ``None`` when it would straddle splits / lie
        outside every AOI.
        """
        if self.spec.method == "blocks":
            bx0, bx1, by0, by1 = self.block_range(window)
            ids = np.unique(self.block_split[by0:by1 + 1, bx0:bx1 + 1])
            return SPLITS[int(ids[0])] if ids.size == 1 else None
        t = self.grid.window_transform(window)
        left, top = t @ (0, 0)
        right, bottom = t @ (window.width, window.height)
        eps = 1e-6 * self.grid.res[0]
        foot = box(min(left, right) + eps, min(top, bottom) + eps, max(left, right) - eps, max(top, bottom) - eps)
        inside = [s for s, g in self.aoi.items() if g.covers(foot)]
        return inside[0] if len(inside) == 1 else None


__all__ = ["SPLITS", "SplitAssigner", "SplitSpec", "assign_blocks"]
