"""Read the windows of a plan ahead of the model, in background threads.

:class:`WindowReader` yields the windows of a range of window rows in plan order. Reading and decoding
happen in ``threads`` worker threads (GDAL releases Python's GIL while it reads), each with its own
dataset handle (:class:`~aerialmtl.io.align.AlignedRaster`), at most ``depth`` windows ahead of the
consumer: memory holds ``depth`` windows whatever the raster size. The AOI mask is applied in the
workers too. A window without any valid pixel comes back with ``data=None`` (the model skips it).

On CUDA the raw pixels go into pinned host memory so that the copy to the device can run
asynchronously (``non_blocking``); normalisation happens on the device.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from rasterio.features import geometry_mask
from rasterio.windows import Window
from shapely.geometry import box
from shapely.strtree import STRtree

from aerialmtl.errors import InputError
from aerialmtl.inference.ortho import OrthoInput
from aerialmtl.io.align import AlignedRaster, Grid
from aerialmtl.io.vector import check_aoi_overlaps, load_geometries

if TYPE_CHECKING:
    from shapely.geometry.base import BaseGeometry

#: Window dtypes torch takes as they are; others are widened to int32/float32 in the worker.
_TORCH_DTYPES = {np.dtype(t) for t in ("uint8", "int8", "int16", "int32", "float32", "float64")}


class Aoi:
    """AOI polygons on the grid; ``mask(window)`` → (h, w) bool inside (thread-safe: read-only)."""

    def __init__(self, path: str | Path, grid: Grid) -> None:
        self.geoms: list[BaseGeometry] = [g for g, _ in load_geometries(path, grid.crs, role="AOI (‹aoi›)")]
        if not self.geoms:
            raise InputError(f"AOI (‹aoi›) '{path}' holds no polygon; pass a GeoJSON with polygons", param="aoi")
        check_aoi_overlaps(path, self.geoms, grid)
        self.tree = STRtree(self.geoms)
        self.grid = grid

    def mask(self, window: Window) -> np.ndarray:
        """(h, w) bool mask of the pixels of ``window`` inside the AOI."""
        h, w = int(window.height), int(window.width)
        tr = self.grid.window_transform(window)
        x0, y0 = tr @ (0, 0)
        x1, y1 = tr @ (w, h)
        hits = [self.geoms[k] for k in self.tree.query(box(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)))]
        if not hits:
            return np.zeros((h, w), bool)
        result: np.ndarray = geometry_mask(hits, out_shape=(h, w), transform=tr, invert=True)
        return result


@dataclass
class ReadWindow:
    """One window of the plan as read.

    Attributes:
        i, j: window row and column.
        data: (C, h, w) raw pixels (pinned tensor on CUDA runs, else numpy), ``None`` without valid pixel.
        valid: (h, w) bool input validity (and inside the AOI).
    """

    i: int
    j: int
    data: np.ndarray | torch.Tensor | None
    valid: np.ndarray


class WindowReader:
    """Windows of window rows ``rows`` of ``plan``, read ahead in background threads.

    Args:
        src: the input (:class:`~aerialmtl.inference.ortho.OrthoInput`: the orthophoto, its prediction grid
            and the window plan over it); each thread opens its own handle on it.
        bands: 1-based bands to read.
        rows: window rows to read, in order.
        aoi: optional AOI mask.
        threads: reader threads (each with its own dataset handle).
        depth: windows read ahead at most.
        pin: put the pixels into pinned host memory (CUDA).
    """

    def __init__(self, src: OrthoInput, bands: Sequence[int], rows: Sequence[int], aoi: Aoi | None = None,
                 threads: int = 2, depth: int = 8, pin: bool = False) -> None:
        self.ortho = src.path
        self.grid = src.grid
        self.bands = list(bands)
        self.plan = src.plan
        self.rows = list(rows)
        self.aoi = aoi
        self.depth = max(1, depth)
        self.pin = pin
        self._local = threading.local()
        self._opened: list[AlignedRaster] = []
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(max_workers=max(1, threads), thread_name_prefix="aerialmtl-reader")
        self.seconds_reading = 0.0

    def _source(self) -> AlignedRaster:
        src = getattr(self._local, "src", None)
        if src is None:
            src = AlignedRaster(self.ortho, self.grid, "image", bands=self.bands, role="orthophoto")
            self._local.src = src
            with self._lock:
                self._opened.append(src)
        return src

    def _read(self, i: int, j: int) -> ReadWindow:
        import time

        t0 = time.perf_counter()
        win = self.plan.window_rows[i].windows[j]
        data, valid = self._source().read(win)
        if self.aoi is not None:
            valid &= self.aoi.mask(win)
        out: np.ndarray | torch.Tensor | None = None
        if valid.any():
            if data.dtype not in _TORCH_DTYPES:
                data = data.astype(np.float32 if data.dtype.kind == "f" else np.int32)
            out = data
            if self.pin:
                pinned = torch.empty(data.shape, dtype=torch.from_numpy(data[:1, :1, :1]).dtype, pin_memory=True)
                pinned.numpy()[...] = data
                out = pinned
        with self._lock:
            self.seconds_reading += time.perf_counter() - t0
        return ReadWindow(i, j, out, valid)

    def __iter__(self) -> Iterator[ReadWindow]:
        order = [(i, j) for i in self.rows for j in range(len(self.plan.cols.starts))]
        queue: deque[Future[ReadWindow]] = deque()
        nxt = 0
        try:
            while nxt < len(order) or queue:
                while nxt < len(order) and len(queue) < self.depth:
                    queue.append(self._pool.submit(self._read, *order[nxt]))
                    nxt += 1
                yield queue.popleft().result()
        finally:
            for fut in queue:
                fut.cancel()

    def close(self) -> None:
        """Close the reader threads' datasets."""
        self._pool.shutdown(wait=True, cancel_futures=True)
        with self._lock:
            for src in self._opened:
                src.close()
            self._opened.clear()

    def __enter__(self) -> WindowReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["Aoi", "ReadWindow", "WindowReader"]
