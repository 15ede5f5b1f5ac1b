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
        """Move to window row ``i``, keeping the rows it shares with the previous window row.

        The accumulators are reused in place (every window row has the same height), so moving on
        never holds two bands' worth of memory.
        """
        rows = self.plan.rows
        new_row0, h = rows.starts[i], rows.size
        keep = max(0, self._row0 + self._wsum.shape[0] - new_row0) if self._band >= 0 else 0
        shift = new_row0 - self._row0

        def moved(old: np.ndarray | None, shape: tuple[int, ...], dtype: type) -> np.ndarray:
            if old is None or old.shape != shape:
                return np.zeros(shape, dtype)
            if keep:
                old[..., :keep, :] = old[..., shift:shift + keep, :].copy()
            old[..., keep:, :] = 0
            return old

        self._acc = {k: moved(self._acc.get(k), (c, h, self._ext_w), np.float32) for k, c in self.channels.items()}
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

    def flush(self, chunk_cols: int = 2048) -> FinalRows:
        """Rows that are final after the current window row, converted to output layers.

        The conversion runs over column chunks of ``chunk_cols`` pixels, so its temporaries (K-channel
        means, logs for the entropy) stay bounded whatever the raster width; only the output layers
        themselves span the full width.
        """
        band = self.plan.bands[self._band]
        a, b = band.out_start - self._row0, band.out_stop - self._row0
        rows, width = b - a, self.width
        valid = self._valid[a:b, :width] & (self._wsum[a:b, :width] > 0)
        counts = {"height": 1, "height_std": 1, "classes": 1, "class_entropy": 1, "class_mutual_info": 1,
                  "class_probabilities": self.channels.get("probs", 0)}
        wanted = [n for n in counts if n in self.outputs and (n.startswith("height") or "probs" in self.channels)]
        layers = {n: np.empty((counts[n], rows, width), np.uint8 if n == "classes" else np.float32) for n in wanted}
        for c0 in range(0, width, chunk_cols):
            cs = slice(c0, min(width, c0 + chunk_cols))
            self._convert(a, b, cs, valid[:, cs], {n: arr[:, :, cs] for n, arr in layers.items()})
        return FinalRows(band.out_start, band.out_stop, valid, layers)

    def _convert(self, a: int, b: int, cs: slice, valid: np.ndarray, out: dict[str, np.ndarray]) -> None:
        """Fill the output views ``out`` for accumulator rows ``[a, b)`` and columns ``cs``."""
        safe = np.where(valid, self._wsum[a:b, cs], 1.0).astype(np.float32)
        inv = ~valid

        def mean(key: str) -> np.ndarray:
            return self._acc[key][:, a:b, cs] / safe

        def fl(name: str, x: np.ndarray) -> None:
            x = x.astype(np.float32, copy=False)
            x[..., inv] = FLOAT_NODATA
            out[name][...] = x

        if "height" in out:
            fl("height", mean("height"))
        if "height_std" in out:
            fl("height_std", np.maximum(mean("height_std"), 0.0))
        if "probs" not in self._acc:
            return
        probs = mean("probs")
        if "classes" in out:
            cls = np.argmax(probs, axis=0).astype(np.uint8)
            cls[inv] = IGNORE_INDEX
            out["classes"][0] = cls
        if "class_entropy" in out or "class_mutual_info" in out:
            ent = np.maximum(-(probs * np.log(np.clip(probs, 1e-12, 1.0))).sum(axis=0), 0.0)[None]
            if "class_mutual_info" in out:
                fl("class_mutual_info", np.clip(ent - mean("expected_entropy"), 0.0, ent))
            if "class_entropy" in out:
                fl("class_entropy", ent)
        if "class_probabilities" in out:
            fl("class_probabilities", probs)


__all__ = ["FLOAT_NODATA", "BandStitcher", "FinalRows"]
