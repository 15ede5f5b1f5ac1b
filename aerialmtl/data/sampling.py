"""Height-stratified patch sampling: show the model tall objects more often than a small area does.

On a small real area most pixels are ground, so an L1-trained model learns "mostly ground" and
flattens trees and buildings. Sampling patches with a probability that grows with their share of tall
pixels raises the share of tall pixels the model sees per step without changing any label.

* :func:`tall_shares` — per patch of a split, the share of valid height pixels ≥ ``threshold_m``;
* :func:`stratified_weights` — weights ``w_i = 1 + a · s_i`` (mean 1) whose weighted mean tall share is
  ``target`` (``a = 0`` when the split already reaches it);
* :func:`repeat_counts` — the same weights as whole repeats per patch (for sampling by epoch).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio

from aerialmtl.data.dataset import read_manifest
from aerialmtl.errors import InputError

#: Largest slope ``a`` of the weights: a patch full of tall pixels is drawn at most this + 1 times as often.
MAX_SLOPE = 20.0


def tall_shares(data_dir: str | Path, split: str = "train", threshold_m: float = 2.0) -> np.ndarray:
    """Share of valid height pixels ≥ ``threshold_m`` metres in every patch of ``split`` (manifest order).

    Returns:
        float64 (n,) in [0, 1]; 0 for a patch without valid heights.

    Raises:
        InputError: the split has no height layer.
    """
    root = Path(data_dir)
    rows = read_manifest(root, split)
    out = np.zeros(len(rows))
    for i, row in enumerate(rows):
        rel = (row.get("height_path") or "").strip()
        if not rel:
            raise InputError(f"manifest row '{row.get('patch_id')}' of '{root / 'manifest.csv'}' has no height_path; "
                             "height-stratified sampling needs a tile folder made with heights (‹dsm›/‹dtm› or ‹ndsm›)")
        with rasterio.open(root / rel) as src:
            h = src.read(1, masked=True)
        valid = ~np.ma.getmaskarray(h) & np.isfinite(h.filled(np.nan))
        n = int(valid.sum())
        out[i] = float((h.data[valid] >= threshold_m).sum()) / n if n else 0.0
    return out


def stratified_weights(shares: np.ndarray, target: float = 0.5) -> np.ndarray:
    """Sampling weights ``1 + a · s_i``, normalised to mean 1, whose weighted mean share is ``target``.

    Args:
        shares: (n,) tall share of each patch (see :func:`tall_shares`).
        target: wanted share of tall pixels per drawn patch, in (0, 1).

    Returns:
        float64 (n,) positive weights with mean 1 (all 1 when the plain mean share already reaches
        ``target`` or no patch has tall pixels; ``a`` is capped at :data:`MAX_SLOPE`).
    """
    if not 0 < target < 1:
        raise InputError(f"‹target›: the tall share to reach must be in (0, 1), got {target}", param="target")
    s = np.asarray(shares, dtype=np.float64)
    if s.size == 0:
        return s
    n, s1, s2 = s.size, s.sum(), (s**2).sum()
    denom = s2 - target * s1
    if s1 >= target * n or denom <= 0:  # already there, or unreachable by tilting towards tall patches
        a = 0.0 if s1 >= target * n else MAX_SLOPE
    else:
        a = min(MAX_SLOPE, (target * n - s1) / denom)
    w = 1.0 + a * s
    return w / w.mean()


def repeat_counts(weights: np.ndarray) -> np.ndarray:
    """Whole repeats per patch proportional to ``weights`` (the lightest patch once), int64 (n,)."""
    w = np.asarray(weights, dtype=np.float64)
    if w.size == 0:
        return np.zeros(0, np.int64)
    if (w <= 0).any():
        raise InputError("‹weights›: every patch needs a positive weight", param="weights")
    return np.maximum(1, np.rint(w / w.min())).astype(np.int64)


__all__ = ["MAX_SLOPE", "repeat_counts", "stratified_weights", "tall_shares"]
