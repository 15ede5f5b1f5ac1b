"""Building pixels of a prediction folder → one footprint polygon per building, streamed block by block.

The grid is read in square blocks (``block_size`` pixels, raster order). In each block the building
pixels are grouped into 4-connected components (``scipy.ndimage.label``; with ``height_step_m`` two
neighbouring pixels are connected only when their predicted heights differ by less than the step, so
touching buildings of different heights come apart) and every component is polygonised with
:func:`rasterio.features.shapes` in **global pixel coordinates** (integers, so pieces of one building in
two blocks share exactly the same edge coordinates). Components that touch across a block edge — a pair
of building pixels facing each other on the two sides, under the same height-step rule — are joined in
a union–find that counts, per building, the block edges it reaches that have not been read across yet
(a piece in a block's last row or column). When that count falls to zero the building is complete: its
pieces are merged (:func:`shapely.union_all`), it is handed on and forgotten, right after the block
that completed it.

Memory therefore holds one block of every layer, one row of pixel ids and heights along the frontier
(a few bytes × the raster width), the pixels of the buildings that cross it and GDAL's block
cache (capped at ``GDAL_CACHE_BYTES["buildings"]`` of :mod:`aerialmtl.runtime` unless
``GDAL_CACHEMAX`` is set); it does not grow with the
raster's size, only with the size of the largest building.

:func:`iter_buildings` turns each merged component into a :class:`Building`: map coordinates, cleaned
outline (:mod:`aerialmtl.buildings.clean`) and attributes (:mod:`aerialmtl.buildings.attributes`).
"""

from __future__ import annotations

import warnings
from collections import defaultdict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from affine import Affine
from rasterio.features import shapes
from rasterio.windows import Window
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from shapely.affinity import affine_transform
from shapely.geometry import Polygon, shape

from aerialmtl.buildings.attributes import building_attributes
from aerialmtl.buildings.clean import DEFAULT_ANGLE_TOLERANCE_DEG, clean_footprint, largest_polygon
from aerialmtl.buildings.layers import BuildingLayers, building_class_indices
from aerialmtl.classes import IGNORE_INDEX
from aerialmtl.errors import InputError
from aerialmtl.formats.prediction import CLASSES
from aerialmtl.progress import tqdm_auto as tqdm
from aerialmtl.runtime import gdal_env

#: 4-connectivity (pixels sharing an edge), as rasterio.features.shapes uses by default.
FOUR_CONNECTED = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=bool)


@dataclass(frozen=True)
class BuildingOptions:
    """How footprints are extracted and cleaned (lengths in metres whatever the CRS unit).

    Attributes:
        min_area_m2: buildings whose cleaned footprint is smaller are dropped.
        max_hole_m2: holes smaller than this are filled; larger ones (courtyards) are kept.
        simplify_m: Douglas–Peucker tolerance; ``None`` = 1.5 pixels (removes the pixel staircase).
        orthogonal: regularise outlines onto their dominant direction and its normal.
        angle_tolerance_deg: edges within this angle of those directions are snapped.
        height_step_m: split touching buildings where neighbouring pixel heights differ by at least this
            much (``None`` = never split).
        height_percentile: percentile of the pixel heights that gives ``height_m`` (50 = median).
        block_size: side of the blocks read at once, pixels (memory ≈ 30 bytes × block_size²).
    """

    min_area_m2: float = 10.0
    max_hole_m2: float = 10.0
    simplify_m: float | None = None
    orthogonal: bool = True
    angle_tolerance_deg: float = DEFAULT_ANGLE_TOLERANCE_DEG
    height_step_m: float | None = None
    height_percentile: float = 50.0
    block_size: int = 1024

    def __post_init__(self) -> None:
        checks = [
            ("min_area_m2", self.min_area_m2 >= 0), ("max_hole_m2", self.max_hole_m2 >= 0),
            ("simplify_m", self.simplify_m is None or self.simplify_m >= 0),
            ("angle_tolerance_deg", 0 <= self.angle_tolerance_deg < 45),
            ("height_step_m", self.height_step_m is None or self.height_step_m > 0),
            ("height_percentile", 0 <= self.height_percentile <= 100),
            ("block_size", int(self.block_size) == self.block_size and self.block_size >= 2),
        ]
        for name, ok in checks:
            if not ok:
                raise InputError(f"building option {name} = {getattr(self, name)!r} is out of range; see "
                                 "BuildingOptions for the allowed values")


@dataclass(frozen=True)
class Building:
    """One extracted building.

    Attributes:
        id: 1, 2, ... in the order buildings were completed.
        geometry: cleaned footprint in the prediction's CRS (exterior counter-clockwise).
        attributes: the fields of :data:`aerialmtl.formats.buildings.PREDICTED_FIELDS` except ``building_id``
            (plus ``ground_z_m`` with a DTM).
    """

    id: int
    geometry: Polygon
    attributes: dict[str, Any]


@dataclass
class ExtractionStats:
    """Counts gathered while streaming (filled in by :func:`iter_buildings`)."""

    valid_pixels: int = 0
    building_pixels: int = 0
    components: int = 0
    too_small: int = 0
    buildings: int = 0
    blocks: int = 0
    building_classes: list[str] = field(default_factory=list)


@dataclass
class PixelBuilding:
    """A building as raster pixels: its footprint in global pixel coordinates and its pixel values.

    Attributes:
        polygon: union of its pixels (x = column, y = row, pixel corners at integers).
        values: layer name → 1-D array over its pixels (``class`` uint8, float32 layers with NaN = nodata).
    """

    polygon: Polygon
    values: dict[str, np.ndarray]

    @property
    def n_pixels(self) -> int:
        """Pixels of the piece."""
        return int(self.values["class"].size)


class _Groups:
    """Union–find over building pieces, with each group's pieces and open edges.

    Open edges: how many block edges a group may still continue through (an open edge of one of its pieces).
    """

    def __init__(self) -> None:
        self.parent: dict[int, int] = {}
        self.members: dict[int, list[int]] = {}
        self.open: dict[int, int] = {}

    def add(self, i: int, open_edges: int) -> None:
        self.parent[i] = i
        self.members[i] = [i]
        self.open[i] = open_edges

    def find(self, i: int) -> int:
        root = i
        while self.parent[root] != root:
            root = self.parent[root]
        while self.parent[i] != root:
            self.parent[i], i = root, self.parent[i]
        return root

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            keep, drop = min(ra, rb), max(ra, rb)
            self.parent[drop] = keep
            self.members[keep] += self.members.pop(drop)
            self.open[keep] += self.open.pop(drop)

    def close_edge(self, i: int) -> None:
        """The edge through which piece ``i`` could continue has been read: one open edge less."""
        self.open[self.find(i)] -= 1

    def pop_closed(self, ids: Sequence[int]) -> list[list[int]]:
        """Remove and return the members of every group of ``ids`` that has no open edge left."""
        roots = sorted({self.find(i) for i in ids})
        out = []
        for root in roots:
            if self.open[root] == 0:
                members = self.members.pop(root)
                del self.open[root]
                for m in members:
                    del self.parent[m]
                out.append(members)
        return out


def _components(mask: np.ndarray, height: np.ndarray, step: float | None) -> tuple[np.ndarray, int]:
    """Label the 4-connected building pixels of ``mask`` 1..n (0 elsewhere), cut at height steps."""
    if step is None:
        labels, n = ndimage.label(mask, structure=FOUR_CONNECTED)
        return labels.astype(np.int32, copy=False), int(n)
    h, w = mask.shape
    idx = np.arange(h * w, dtype=np.int64).reshape(h, w)
    with np.errstate(invalid="ignore"):  # NaN heights never cut
        right = mask[:, :-1] & mask[:, 1:] & ~(np.abs(height[:, 1:] - height[:, :-1]) >= step)
        down = mask[:-1] & mask[1:] & ~(np.abs(height[1:] - height[:-1]) >= step)
    src = np.concatenate([idx[:, :-1][right], idx[:-1][down]])
    dst = np.concatenate([idx[:, 1:][right], idx[1:][down]])
    graph = coo_matrix((np.ones(src.size, np.int8), (src, dst)), shape=(h * w, h * w)).tocsr()
    _, comp = connected_components(graph, directed=False)
    labels = np.zeros((h, w), np.int32)
    uniq, inverse = np.unique(comp.reshape(h, w)[mask], return_inverse=True)
    labels[mask] = inverse.astype(np.int32) + 1
    return labels, int(uniq.size)


def _join(groups: _Groups, ids_a: np.ndarray, h_a: np.ndarray, ids_b: np.ndarray, h_b: np.ndarray,
          step: float | None) -> None:
    """Union the pieces of facing pixel pairs (``ids_a[i]`` next to ``ids_b[i]``; −1 = not a building)."""
    ok = (ids_a >= 0) & (ids_b >= 0)
    if step is not None:
        with np.errstate(invalid="ignore"):
            ok &= ~(np.abs(h_a - h_b) >= step)
    if not ok.any():
        return
    for a, b in np.unique(np.stack([ids_a[ok], ids_b[ok]], axis=1), axis=0):
        groups.union(int(a), int(b))


def _block_pieces(labels: np.ndarray, n: int, mask: np.ndarray, block: dict[str, np.ndarray], col_off: int,
                  row_off: int) -> list[PixelBuilding]:
    """One :class:`PixelBuilding` per component 1..n of ``labels`` (polygons in global pixel coordinates)."""
    ids = labels[mask]
    order = np.argsort(ids, kind="stable")
    cuts = np.cumsum(np.bincount(ids, minlength=n + 1)[1:])[:-1]
    values = {key: np.split(arr[mask][order], cuts) for key, arr in block.items()}
    polys: dict[int, list[Polygon]] = defaultdict(list)
    for geom, value in shapes(labels, mask=mask, connectivity=4, transform=Affine.translation(col_off, row_off)):
        polys[int(value)].append(shape(geom))
    pieces = []
    for i in range(n):
        parts = polys[i + 1]
        poly = parts[0] if len(parts) == 1 else shapely.union_all(parts)
        # copies: a view would keep the whole block's arrays alive while the building stays open
        pieces.append(PixelBuilding(poly, {key: v[i].copy() for key, v in values.items()}))
    return pieces


def _merge(pieces: list[PixelBuilding]) -> PixelBuilding:
    if len(pieces) == 1:
        return pieces[0]
    poly = shapely.union_all([p.polygon for p in pieces])
    values = {key: np.concatenate([p.values[key] for p in pieces]) for key in pieces[0].values}
    return PixelBuilding(poly, values)


class _BlockWalk:
    """The open buildings of a walk over the blocks in raster order, and the edges they may continue through.

    Per block row: :meth:`start_row`, one :meth:`add_block` per block left to right, :meth:`end_row`.

    Attributes:
        groups: union–find over the pieces of the buildings not yet complete.
        live: piece id → its :class:`PixelBuilding`, while its building is open.
        frontier_ids, frontier_h: (width,) piece id (−1: none) and height of the pixels just above the
            current block row.
        above: block column → pieces of the block above that reach its bottom row.
    """

    def __init__(self, width: int, step: float | None) -> None:
        self.width = width
        self.step = step
        self.groups = _Groups()
        self.live: dict[int, PixelBuilding] = {}
        self.next_id = 0
        self.frontier_ids = np.full(width, -1, np.int64)
        self.frontier_h = np.full(width, np.nan, np.float32)
        self.above: dict[int, list[int]] = {}
        self.start_row(0)

    def start_row(self, rows: int) -> None:
        """Begin a block row ``rows`` pixels high: nothing on its left yet, its bottom row still to fill."""
        self.new_ids = np.full(self.width, -1, np.int64)  # the bottom row of this block row: the next frontier
        self.new_h = np.full(self.width, np.nan, np.float32)
        self.below: dict[int, list[int]] = {}
        self.left_ids = np.full(rows, -1, np.int64)  # right column of the block on the left
        self.left_h = np.full(rows, np.nan, np.float32)
        self.left_open: list[int] = []  # pieces of the block on the left that reach its right column

    def end_row(self) -> None:
        """The block row is read: its bottom row becomes the frontier of the next one."""
        self.frontier_ids, self.frontier_h, self.above = self.new_ids, self.new_h, self.below

    def add_block(self, block: dict[str, np.ndarray], mask: np.ndarray, col_off: int, row_off: int, *,
                  last_row: bool, last_col: bool, stats: ExtractionStats) -> Iterator[PixelBuilding]:
        """Add the building pixels of one block; yields every building the block completes.

        ``mask`` (h, w) holds the block at ``col_off, row_off``.
        """
        n_mask = int(np.count_nonzero(mask))
        new: list[int] = []
        right_open: list[int] = []
        if n_mask:
            stats.building_pixels += n_mask
            new, right_open = self._add_pieces(block, mask, col_off, row_off, last_row, last_col, stats)
        else:
            self.left_ids = np.full(mask.shape[0], -1, np.int64)
        # the right column of the block on the left and the bottom row of the block above are read now
        resolved = self.left_open + self.above.get(col_off, [])
        for pid in resolved:
            self.groups.close_edge(pid)
        self.left_open = right_open
        for members in self.groups.pop_closed(new + resolved):
            yield _merge([self.live.pop(pid) for pid in members])

    def _add_pieces(self, block: dict[str, np.ndarray], mask: np.ndarray, col_off: int, row_off: int,
                    last_row: bool, last_col: bool, stats: ExtractionStats) -> tuple[list[int], list[int]]:
        """Open one piece per component of ``mask`` and join it to its neighbours on the left and above.

        Returns the new piece ids and those reaching the block's right column.
        """
        labels, n = _components(mask, block["height"], self.step)
        stats.components += n
        gid = np.where(labels > 0, labels.astype(np.int64) + (self.next_id - 1), -1)
        at_bottom = set() if last_row else set(np.unique(gid[-1][gid[-1] >= 0]).tolist())
        at_right = set() if last_col else set(np.unique(gid[:, -1][gid[:, -1] >= 0]).tolist())
        new = []
        for i, piece in enumerate(_block_pieces(labels, n, mask, block, col_off, row_off)):
            pid = self.next_id + i
            self.live[pid] = piece
            self.groups.add(pid, int(pid in at_bottom) + int(pid in at_right))
            new.append(pid)
        self.next_id += n
        self.below[col_off] = sorted(at_bottom)
        hgt = block["height"]
        bw = mask.shape[1]
        if col_off > 0:
            _join(self.groups, self.left_ids, self.left_h, gid[:, 0], hgt[:, 0], self.step)
        if row_off > 0:
            _join(self.groups, self.frontier_ids[col_off:col_off + bw], self.frontier_h[col_off:col_off + bw],
                  gid[0], hgt[0], self.step)
        self.left_ids, self.left_h = gid[:, -1].copy(), hgt[:, -1].copy()
        self.new_ids[col_off:col_off + bw] = gid[-1]
        self.new_h[col_off:col_off + bw] = hgt[-1]
        return new, sorted(at_right)


def iter_pixel_buildings(layers: BuildingLayers, class_indices: Sequence[int], block_size: int = 1024,
                         height_step_m: float | None = None, stats: ExtractionStats | None = None,
                         progress: bool = False) -> Iterator[PixelBuilding]:
    """Stream the buildings of ``layers`` as pixel footprints (see the module docstring).

    Args:
        layers: the opened prediction layers.
        class_indices: class indices that are buildings.
        block_size: block side, pixels.
        height_step_m: cut between neighbouring pixels whose heights differ by at least this (metres).
        stats: filled with pixel and component counts.
        progress: tqdm bar over the blocks.

    Yields:
        every 4-connected building component once, as soon as no block still to be read can touch it
        (after the block holding its last pixel in raster order, or the block below or right of it).
    """
    stats = stats if stats is not None else ExtractionStats()
    height, width = layers.grid.height, layers.grid.width
    b = int(block_size)
    classes = np.asarray(sorted(class_indices), dtype=np.uint8)
    walk = _BlockWalk(width, height_step_m)
    n_blocks = -(-height // b) * -(-width // b)
    with gdal_env("buildings"), tqdm(total=n_blocks, desc="buildings", unit="block", disable=not progress) as bar:
        for r0 in range(0, height, b):
            bh = min(b, height - r0)
            walk.start_row(bh)
            for c0 in range(0, width, b):
                bw = min(b, width - c0)
                block = layers.read(Window(c0, r0, bw, bh))
                stats.blocks += 1
                bar.update(1)
                cls = block["class"]
                stats.valid_pixels += int(np.count_nonzero(cls != IGNORE_INDEX))
                yield from walk.add_block(block, np.isin(cls, classes), c0, r0, last_row=r0 + bh >= height,
                                          last_col=c0 + bw >= width, stats=stats)
            walk.end_row()


def extract_buildings(
    layers: BuildingLayers,
    options: BuildingOptions | None = None,
    building_classes: Sequence[str | int] | None = None,
    stats: ExtractionStats | None = None,
    progress: bool = False,
) -> Iterator[Building]:
    """Extract the buildings of opened prediction layers, one at a time, in the prediction's CRS.

    Args:
        layers: the prediction folder's layers (and DTM), see :class:`BuildingLayers`.
        options: extraction and cleaning settings (default :class:`BuildingOptions`).
        building_classes: names or indices of the building classes; default: recognised by name
            (see :func:`aerialmtl.buildings.layers.building_class_indices`).
        stats: filled with counts while streaming.
        progress: show a tqdm bar.

    Yields:
        :class:`Building` objects.

    Raises:
        InputError: no building class, or a ``classes.tif`` that is nodata everywhere (raised once the
            whole raster has been read). A prediction without any building pixel yields nothing and warns.
    """
    options = options or BuildingOptions()
    stats = stats if stats is not None else ExtractionStats()
    indices = building_class_indices(layers.scheme, building_classes)
    names = layers.scheme.names if layers.scheme is not None else [str(i) for i in range(max(indices) + 1)]
    stats.building_classes = [names[i] for i in indices]
    unit = layers.metres_per_unit
    pixel_area_m2 = layers.pixel_area_m2
    t = layers.grid.transform
    matrix = [t.a, t.b, t.d, t.e, t.c, t.f]
    tolerance = options.simplify_m / unit if options.simplify_m is not None else 1.5 * layers.grid.gsd
    max_hole = options.max_hole_m2 / unit**2
    footprint = shapely.box(*layers.grid.bounds)  # outlines stay inside the raster
    next_id = 1
    for pix in iter_pixel_buildings(layers, indices, options.block_size, options.height_step_m, stats, progress):
        if pix.n_pixels * pixel_area_m2 < options.min_area_m2:
            stats.too_small += 1
            continue
        poly = largest_polygon(pix.polygon)
        if poly is None:  # pragma: no cover - a component is never empty
            continue
        # the same outline whatever the blocks: no seam vertices, canonical start vertex
        poly = shapely.normalize(poly.simplify(0))
        cleaned = clean_footprint(affine_transform(poly, matrix), max_hole, tolerance, options.orthogonal,
                                  options.angle_tolerance_deg, clip=footprint)
        area_m2 = cleaned.area * unit**2 if cleaned is not None else 0.0
        if cleaned is None or area_m2 < options.min_area_m2:
            stats.too_small += 1
            continue
        attrs = building_attributes(pix.values, area_m2, options.height_percentile, names)
        stats.buildings += 1
        yield Building(next_id, cleaned, attrs)
        next_id += 1
    classes_path = layers.folder.layer_path(CLASSES)
    if stats.valid_pixels == 0:
        raise InputError(
            f"'{classes_path}' is nodata everywhere: the prediction covers no valid pixel; check the "
            "orthophoto (nodata, alpha) and the AOI given to predict"
        )
    if stats.building_pixels == 0:
        warnings.warn(
            f"no building pixel in '{classes_path}' (building classes: {', '.join(stats.building_classes)}; "
            f"{stats.valid_pixels} valid pixels): the outputs hold no building",
            UserWarning, stacklevel=2,
        )


def iter_buildings(
    pred_dir: str | Path,
    options: BuildingOptions | None = None,
    dtm: str | Path | None = None,
    building_classes: Sequence[str | int] | None = None,
    stats: ExtractionStats | None = None,
    progress: bool = False,
) -> Iterator[Building]:
    """:func:`extract_buildings` on the prediction folder ``pred_dir`` (and terrain model ``dtm``, metres).

    Raises:
        InputError: as :class:`BuildingLayers` and :func:`extract_buildings`.
    """
    with BuildingLayers(pred_dir, dtm=dtm) as layers:
        yield from extract_buildings(layers, options, building_classes, stats, progress)


__all__ = [
    "Building", "BuildingOptions", "ExtractionStats", "PixelBuilding", "extract_buildings", "iter_buildings",
    "iter_pixel_buildings",
]
