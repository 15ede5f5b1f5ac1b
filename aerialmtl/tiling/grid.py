"""Regular grids of patch windows over a raster: (size, stride) in pixels, last row/column snapped to the edge.

Along an axis of ``length`` pixels, patches of ``size`` start at ``0, stride, 2·stride, …``; when the
last regular start would leave the end of the raster uncovered, one more patch is added that ends
exactly at the edge (start ``length − size``). The number of patches along the axis is therefore::

    n = 1 + ceil((length − size) / stride)        for length ≥ size

so every pixel is covered and every patch is ``size`` pixels, inside the raster.

Rasters shorter than a patch along an axis (``length < size``) get one window starting at 0 and
``size`` pixels long, reaching past the edge (``small="pad"``, the default: readers fill the outside with
nodata so all patches share one size and batch together), or ``length`` pixels long (``small="clip"``),
or no window at all (``small="skip"``).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Literal

from rasterio.windows import Window

from aerialmtl.errors import InputError

SmallPolicy = Literal["pad", "clip", "skip"]


def _check(size: int, stride: int) -> None:
    if not isinstance(size, int) or size < 1:
        raise InputError(f"patch ‹size› must be a positive number of pixels, got {size!r}; pass e.g. ‹size=320›",
                         param="size")
    if not isinstance(stride, int) or stride < 1:
        raise InputError(f"‹stride› must be a positive number of pixels, got {stride!r}; pass e.g. ‹stride={size}›",
                         param="stride")
    if stride > size:
        raise InputError(
            f"stride {stride} is larger than the patch size {size}, which would leave gaps; "
            f"use ‹stride› ≤ ‹size› (e.g. ‹stride={size}›)", param="stride"
        )


def num_offsets(length: int, size: int, stride: int, small: SmallPolicy = "pad") -> int:
    """Number of patch starts along an axis of ``length`` pixels: ``1 + ceil((length − size) / stride)``."""
    _check(size, stride)
    if length < 1:
        return 0
    if length < size:
        return 0 if small == "skip" else 1
    return 1 + math.ceil((length - size) / stride)


def axis_offsets(length: int, size: int, stride: int, small: SmallPolicy = "pad") -> list[int]:
    """Patch start offsets along one axis (see the module docstring for the rule)."""
    n = num_offsets(length, size, stride, small)
    if n == 0:
        return []
    if length < size:
        return [0]
    offsets = [min(i * stride, length - size) for i in range(n)]
    return offsets


def tile_windows(
    width: int, height: int, size: int, stride: int | None = None, small: SmallPolicy = "pad"
) -> Iterator[Window]:
    """Windows of ``size`` × ``size`` pixels every ``stride`` pixels over a ``width`` × ``height`` raster.

    Row-major order (top row first). ``stride`` defaults to ``size`` (no overlap).

    Args:
        width, height: raster size in pixels.
        size: patch side in pixels.
        stride: step between patch starts in pixels (``1 ≤ stride ≤ size``).
        small: what to do along an axis shorter than ``size``: ``"pad"``, ``"clip"`` or ``"skip"``.

    Yields:
        ``rasterio.windows.Window(col_off, row_off, w, h)`` with integer offsets and sizes.
    """
    stride = size if stride is None else stride
    cols = axis_offsets(width, size, stride, small)
    rows = axis_offsets(height, size, stride, small)
    w = size if (width >= size or small == "pad") else width
    h = size if (height >= size or small == "pad") else height
    for r in rows:
        for c in cols:
            yield Window(c, r, w, h)


def count_windows(width: int, height: int, size: int, stride: int | None = None, small: SmallPolicy = "pad") -> int:
    """Number of windows :func:`tile_windows` yields."""
    stride = size if stride is None else stride
    return num_offsets(width, size, stride, small) * num_offsets(height, size, stride, small)


__all__ = ["SmallPolicy", "axis_offsets", "count_windows", "num_offsets", "tile_windows"]
