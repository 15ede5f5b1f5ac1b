"""Does ``unfamiliarity.tif`` flag the misses? Its rank correlation with the height error, per height bin.

The unfamiliarity layer (:mod:`aerialmtl.models.familiarity`) says how unlike the training set the network
found each pixel's features (0–1, the share of training feature pixels that were more typical). A user opens
it to find the structures the model missed; what matters is whether it ranks the errors *among pixels of
similar reference height* (a layer that merely follows the height would rank them overall and not within a
bin). :class:`UnfamiliarityScores` accumulates a seeded subsample window by window and reports, overall and per
reference-height bin, Spearman(unfamiliarity, |height error|) and Spearman(unfamiliarity, predicted height).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from aerialmtl.evaluation.metrics import Subsample
from aerialmtl.evaluation.uncertainty import height_bins, spearman


class UnfamiliarityScores:
    """Spearman of ``unfamiliarity`` against |height error| and against the predicted height, per bin.

    Args:
        edges: reference-height bin edges (metres, increasing; the last may be ``inf``); heights below the first
            edge count in the first bin.
        sample_cap, seed: the seeded uniform subsample the ranks are computed on.
    """

    def __init__(self, edges: Any, sample_cap: int = 2_000_000, seed: int = 0) -> None:
        self.edges = np.asarray(edges, np.float64)
        self.sample = Subsample(sample_cap, seed)

    def update(self, unfamiliarity: np.ndarray, pred: np.ndarray, ref: np.ndarray) -> None:
        """Add pixels: 1-D ``unfamiliarity`` (0–1), predicted and reference heights (metres), all finite."""
        u, p, r = (np.asarray(a, np.float64).ravel() for a in (unfamiliarity, pred, ref))
        if u.size == 0:
            return
        self.sample.add(u=u, abs_error=np.abs(p - r), pred=p, bin=height_bins(self.edges, r).astype(np.int64))

    def result(self) -> dict[str, Any]:
        """``n_sampled``, overall ``spearman_vs_abs_error``, and ``bins``: per reference-height bin ``range_m``,
        ``n_sampled``, ``spearman_vs_abs_error``, ``spearman_vs_predicted_height`` and the median unfamiliarity
        (``nan`` where a bin has fewer than 2 pixels or a constant column).
        """
        nb = len(self.edges) - 1
        if self.sample.total == 0:
            return {"n_sampled": 0, "spearman_vs_abs_error": math.nan, "bins": []}
        u, err, pred, b = (self.sample.get(k) for k in ("u", "abs_error", "pred", "bin"))
        bins = []
        for k in range(nb):
            sel = b == k
            n = int(sel.sum())
            bins.append({"range_m": [float(self.edges[k]), float(self.edges[k + 1])], "n_sampled": n,
                         "spearman_vs_abs_error": spearman(u[sel], err[sel]) if n > 1 else math.nan,
                         "spearman_vs_predicted_height": spearman(u[sel], pred[sel]) if n > 1 else math.nan,
                         "median_unfamiliarity": float(np.median(u[sel])) if n else math.nan})
        return {"n_sampled": len(self.sample), "spearman_vs_abs_error": spearman(u, err), "bins": bins}


__all__ = ["UnfamiliarityScores"]
