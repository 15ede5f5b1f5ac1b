"""Blend window outputs into row bands and hand back the rows that are final.

:class:`BandStitcher` keeps weighted sums for one window row (``window height × grid width`` pixels)
plus the rows it shares with the next window row; nothing else of the raster is held in memory.
Blended quantities (each ``(C, h, w)`` float32 per window):

* ``height``: MC mean height (metres);
* ``height_std``: MC standard deviation (metres);
* ``probs``: MC mean class probabilities (K channels);
* ``expected_entropy``: MC mean of the per-sample entropies (nats), i.e. entropy − mutual information.

When rows are flushed, predictive entropy is recomputed from the blended probabilities and mutual
information as ``entropy − expected_entropy`` (clamped at 0), so ``0 ≤ MI ≤ entropy ≤ log K`` holds
exactly in the blended result too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aerialmtl.classes import IGNORE_INDEX
from aerialmtl.inference.windows import Plan

#: float nodata of every float output (same as the height patches).
FLOAT_NODATA = -9999.0


@dataclass
class FinalRows:
    """Finished output rows ``[row_start, row_stop)`` over the full grid width.

    Attributes:
        valid: (h, W) bool, input valid (and inside the AOI) and computed.
        layers: output name → (bands, h, W) arrays in the output dtype with nodata filled in
            (``height``, ``height_std``, ``classes``, ``class_entropy``, ``class_mutual_info``,
            ``class_probabilities``; only those requested).
    """

    row_start: int
    row_stop: int
    valid: np.ndarray
    layers: dict[str, np.ndarray]


class BandStitcher:
    """Accumulate blended window outputs band by band.

    Args:
        plan: the window plan.
        channels: blended quantity name → number of channels (e.g. ``{"height": 1, "probs": K}``).
        outputs: names of the output layers to produce on flush (see :class:`FinalRows`).
    """

    def __init__(self, plan: Plan, channels: dict[str, int], outputs: tuple[str, ...]) -> None:
        self.plan = plan
        self.channels = dict(channels)
        self.outputs = outputs
        self.width = plan.cols.length
        self._ext_w = plan.cols.extent
        self._band = -1
        self._row0 = 0
        self._acc: dict[str, np.ndarray] = {}
        self._wsum = np.zeros((0, self._ext_w), np.float32)
        self._valid = np.zeros((0, self._ext_w), bool)

    # ------------------------------------------------------------------------------------------
    def start_band(self, i: int) -> None:
        """Move to window row ``i``, keeping the rows it shares with the previous window row."""
        rows = self.plan.rows
        new_row0, h = rows.starts[i], rows.size
        keep = max(0, self._row0 + self._wsum.shape[0] - new_row0) if self._band >= 0 else 0
        shift = new_row0 - self._row0

        def moved(old: np.ndarray, shape: tuple[int, ...], dtype: type) -> np.ndarray:
            new = np.zeros(shape, dtype)
            if keep:
                new[..., :keep, :] = old[..., shift:shift + keep, :]
            return new

        self._acc = {k: moved(self._acc.get(k, np.zeros((c, 0, self._ext_w), np.float32)), (c, h, self._ext_w),
                              np.float32) for k, c in self.channels.items()}
        self._wsum = moved(self._wsum, (h, self._ext_w), np.float32)
        self._valid = moved(self._valid, (h, self._ext_w), bool)
        self._band, self._row0 = i, new_row0

    def add(self, j: int, values: dict[str, np.ndarray], valid: np.ndarray) -> None:
        """Add the outputs of window (current row, column ``j``).

        Args:
            j: window column index.
            values: quantity name → (C, h, w) float32 for the whole window.
            valid: (h, w) bool input validity of the window.
        """
        i = self._band
        w = self.plan.weight(i, j) * valid
        c0 = self.plan.cols.starts[j]
        sl = (slice(0, self.plan.rows.size), slice(c0, c0 + self.plan.cols.size))
        for k, acc in self._acc.items():
            acc[(slice(None), *sl)] += values[k] * w
        self._wsum[sl] += w
        self._valid[sl] |= valid

    def flush(self) -> FinalRows:
        """Rows that are final after the current window row, converted to output layers."""
        band = self.plan.bands[self._band]
        a, b = band.out_start - self._row0, band.out_stop - self._row0
        wsum = self._wsum[a:b, : self.width]
        valid = self._valid[a:b, : self.width] & (wsum > 0)
        safe = np.where(valid, wsum, 1.0).astype(np.float32)
        mean = {k: acc[:, a:b, : self.width] / safe for k, acc in self._acc.items()}
        layers: dict[str, np.ndarray] = {}
        inv = ~valid

        def fl(x: np.ndarray) -> np.ndarray:
            x = x.astype(np.float32, copy=False)
            x[..., inv] = FLOAT_NODATA
            return x

        if "height" in self.outputs:
            layers["height"] = fl(mean["height"])
        if "height_std" in self.outputs:
            layers["height_std"] = fl(np.maximum(mean["height_std"], 0.0))
        if "probs" in mean:
            probs = mean["probs"]
            if "classes" in self.outputs:
                cls = np.argmax(probs, axis=0).astype(np.uint8)
                cls[inv] = IGNORE_INDEX
                layers["classes"] = cls[None]
            if "class_entropy" in self.outputs or "class_mutual_info" in self.outputs:
                p = np.clip(probs, 1e-12, 1.0)
                ent = np.maximum(-(probs * np.log(p)).sum(axis=0), 0.0)[None]
                if "class_mutual_info" in self.outputs:
                    layers["class_mutual_info"] = fl(np.clip(ent - mean["expected_entropy"], 0.0, ent))
                if "class_entropy" in self.outputs:
                    layers["class_entropy"] = fl(ent)
            if "class_probabilities" in self.outputs:
                layers["class_probabilities"] = fl(probs.copy())
        return FinalRows(band.out_start, band.out_stop, valid, layers)


__all__ = ["FLOAT_NODATA", "BandStitcher", "FinalRows"]
