"""The window plan of streaming prediction: which windows the model sees and how their outputs blend.

Along each axis of ``length`` output pixels the plan places ``n`` windows of one common ``size``
(a multiple of 32, at most ``window``), evenly spread from the first to the last pixel, so that
neighbours share at least ``overlap`` pixels::

    n    = max(1, ceil((length − overlap) / (window − overlap)))
    size = min(window, round_up_32(ceil((length + (n − 1) · overlap) / n)))

Spreading the windows (instead of snapping a last full window to the edge) keeps the computed area
close to ``(window / (window − overlap))²`` times the output area. An axis shorter than 32 pixels gets one
32-pixel window reaching past the edge (the reader fills the outside as invalid).

Blending. Inside an overlap of ``overlap`` pixels each window drops its outer ``margin = overlap // 4``
pixels (the pixels with the least context) and the two windows cross-fade linearly over the remaining
``overlap − 2·margin`` pixels. The 1-D weights are normalised to sum to 1 at every pixel and the 2-D
weight of a window is the product of its row and column weights. The 1-D weights are rounded to
multiples of 1/256 that still sum to exactly 1, so a model that returns the same value in two windows
gives that value back bit for bit (for values with ≤ 8 significant bits, e.g. 8-bit imagery, and to
float rounding otherwise) and no seam can appear.

Window rows. The windows are processed one :class:`WindowRow` at a time, top to bottom; after window row
``i`` the output rows ``[out_start, out_stop)`` of that window row are final (no later window touches
them) and can be written. They depend only on the window rows :attr:`WindowRow.sources` (usually ``i − 1``
and ``i``; with small tiles and a large overlap a window row can reach two rows down), so a raster can be
cut into strips of window rows shared among processes: a worker whose strip starts at window row ``a``
runs window rows ``sources[0] … a − 1`` first. The same holds along a window row for columns
(:meth:`AxisPlan.final_until`), which lets the stitcher hand back finished blocks while it moves left to
right and keep only one window of accumulators per window row.

(Words: a *window row* is a row of windows of this plan; *bands* are always the spectral bands of a
raster.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from rasterio.windows import Window

from aerialmtl.errors import InputError

#: Window sizes are multiples of this (the D3-Net input constraint).
SIZE_MULTIPLE = 32
#: 1-D blending weights are multiples of 2^-WEIGHT_BITS (256 cross-fade levels).
WEIGHT_BITS = 8


def _round_up(value: int, multiple: int = SIZE_MULTIPLE) -> int:
    return int(math.ceil(value / multiple) * multiple)


def check_tiling(window: int, overlap: int) -> None:
    """Validate the window side ``window`` and ``overlap`` (pixels).

    Raises:
        InputError: ``window`` is not a positive multiple of 32, or ``overlap`` is outside ``[0, window / 2]``.
    """
    if not isinstance(window, int) or window < SIZE_MULTIPLE or window % SIZE_MULTIPLE:
        raise InputError(
            f"‹window› must be a positive multiple of {SIZE_MULTIPLE} pixels, got {window!r}; pass e.g. ‹window=512›",
            param="window")
    if not isinstance(overlap, int) or not 0 <= overlap <= window // 2:
        raise InputError(
            f"‹overlap› must be between 0 and ‹window›/2 = {window // 2} pixels, got {overlap!r}; pass e.g. "
            f"‹overlap={min(64, window // 4)}›",
            param="overlap")


@dataclass(frozen=True)
class AxisPlan:
    """Windows along one axis.

    Attributes:
        length: output pixels along the axis.
        size: window size (pixels, multiple of 32; may exceed ``length`` for short axes).
        starts: window start offsets (pixels), increasing.
        margin: pixels dropped at each interior window side.
        weights: (n, size) float32 blending weights, summing to 1 over windows at every output pixel.
    """

    length: int
    size: int
    starts: tuple[int, ...]
    margin: int
    weights: np.ndarray

    @property
    def extent(self) -> int:
        """Pixels from 0 to the end of the last window (≥ ``length``)."""
        return self.starts[-1] + self.size

    def final_until(self, i: int) -> int:
        """First pixel still touched by a window after window ``i`` (everything before is final)."""
        if i + 1 >= len(self.starts):
            return self.length
        return min(self.length, self.starts[i + 1] + self.margin)

    def reach(self, i: int) -> int:
        """One past the last pixel to which window ``i`` gives a non-zero weight."""
        nonzero = np.flatnonzero(self.weights[i])
        return self.starts[i] + int(nonzero[-1]) + 1 if nonzero.size else self.starts[i]


def _base_weight(size: int, margin: int, ramp: int, left: bool, right: bool) -> np.ndarray:
    """Trapezoid: 0 in the dropped margin of interior sides, linear ramp, then 1."""
    p = np.arange(size, dtype=np.float64)
    w = np.ones(size, dtype=np.float64)
    if ramp > 0:
        if left:
            w = np.minimum(w, np.clip((p - margin + 0.5) / ramp, 0.0, 1.0))
        if right:
            w = np.minimum(w, np.clip((size - 1 - p - margin + 0.5) / ramp, 0.0, 1.0))
    return w


def axis_plan(length: int, window: int, overlap: int) -> AxisPlan:
    """Plan the windows along an axis of ``length`` pixels (see the module docstring)."""
    check_tiling(window, overlap)
    if length < 1:
        raise InputError(f"cannot plan windows over an empty axis (length {length})")
    n = max(1, math.ceil((length - overlap) / (window - overlap)))
    size = min(window, _round_up(math.ceil((length + (n - 1) * overlap) / n)))
    if n == 1:
        starts = [0]
    else:
        starts = [round(i * (length - size) / (n - 1)) for i in range(n)]
    margin = overlap // 4
    ramp = overlap - 2 * margin
    base = np.stack([_base_weight(size, margin, ramp, i > 0, i < n - 1) for i in range(n)])
    total = np.zeros(starts[-1] + size, dtype=np.float64)
    for s, b in zip(starts, base):
        total[s:s + size] += b
    if not np.all(total[:length] > 0):  # pragma: no cover - guarded by the size/overlap rules above
        raise AssertionError(f"window plan leaves pixels uncovered (length {length}, window {window}, "
                             f"overlap {overlap})")
    dense = np.zeros((n, total.size), dtype=np.float64)  # window × position
    for k, (s, b) in enumerate(zip(starts, base)):
        t = total[s:s + size]
        dense[k, s:s + size] = np.divide(b, t, out=np.zeros_like(b), where=t > 0)
    # Dyadic weights (multiples of 2^-WEIGHT_BITS) that sum to exactly 1: identical window values then
    # blend back to the identical value, bit for bit.
    q = np.round(dense * 2**WEIGHT_BITS) / 2**WEIGHT_BITS
    covered = total > 0
    top = np.argmax(dense, axis=0)
    cols = np.arange(total.size)
    q[top[covered], cols[covered]] += 1.0 - q[:, covered].sum(axis=0)
    weights = np.stack([q[k, s:s + size] for k, s in enumerate(starts)])
    return AxisPlan(length, size, tuple(int(s) for s in starts), margin, weights.astype(np.float32))


@dataclass(frozen=True)
class WindowRow:
    """One row of windows of the plan.

    Attributes:
        index: window row ``i``.
        row_off: first grid row of the window row.
        height: window height (pixels).
        out_start, out_stop: grid rows that become final once window rows ``≤ i`` are done.
        windows: the windows of the row, left to right (may reach past the grid edges).
        first_source: the first window row whose weights reach row ``out_start``.
    """

    index: int
    row_off: int
    height: int
    out_start: int
    out_stop: int
    windows: tuple[Window, ...]
    first_source: int = 0

    @property
    def sources(self) -> tuple[int, ...]:
        """Window rows whose outputs reach rows ``[out_start, out_stop)``."""
        return tuple(range(min(self.first_source, self.index), self.index + 1))


@dataclass(frozen=True)
class Plan:
    """Windows over a ``height`` × ``width`` grid: row and column :class:`AxisPlan` and the window rows."""

    rows: AxisPlan
    cols: AxisPlan
    window_rows: tuple[WindowRow, ...]

    @property
    def num_windows(self) -> int:
        """Number of windows of the plan."""
        return len(self.rows.starts) * len(self.cols.starts)

    @property
    def overlap_factor(self) -> float:
        """Pixels computed / output pixels when every window is computed."""
        return self.computed_overlap(self.num_windows)

    def computed_overlap(self, computed: int) -> float:
        """Pixels computed per output pixel (≥ 1 when every window is: their overlap) for ``computed`` windows."""
        return computed * self.rows.size * self.cols.size / float(self.rows.length * self.cols.length)

    def weight(self, i: int, j: int) -> np.ndarray:
        """(height, width) float32 blending weight of window (row ``i``, column ``j``)."""
        result: np.ndarray = self.rows.weights[i][:, None] * self.cols.weights[j][None, :]
        return result


def plan_windows(height: int, width: int, window: int = 512, overlap: int = 64) -> Plan:
    """Plan the prediction windows over a ``height`` × ``width`` grid, grouped in window rows.

    Pure function of its arguments; window rows are independent given their :attr:`WindowRow.sources`.

    Args:
        height, width: grid size in pixels.
        window: largest window side (pixels, multiple of 32).
        overlap: minimum overlap between neighbouring windows (pixels, ``0 ≤ overlap ≤ window / 2``).

    Returns:
        A :class:`Plan`.
    """
    rows = axis_plan(height, window, overlap)
    cols = axis_plan(width, window, overlap)
    window_rows = []
    out_start = 0
    reach = [rows.reach(k) for k in range(len(rows.starts))]
    for i, r in enumerate(rows.starts):
        out_stop = rows.final_until(i)
        wins = tuple(Window(c, r, cols.size, rows.size) for c in cols.starts)
        first = next(k for k in range(i + 1) if k == i or reach[k] > out_start)
        window_rows.append(WindowRow(i, r, rows.size, out_start, out_stop, wins, first))
        out_start = out_stop
    return Plan(rows, cols, tuple(window_rows))


__all__ = ["SIZE_MULTIPLE", "AxisPlan", "Plan", "WindowRow", "axis_plan", "check_tiling", "plan_windows"]
