"""Height and land-cover accuracy metrics on numpy arrays, exact and streaming-friendly.

Every metric is a pure function of arrays plus an optional boolean ``valid`` mask; the accumulators
(:class:`HeightStats`, :func:`confusion_matrix` added up over windows) let :func:`evaluate_prediction
<aerialmtl.evaluation.evaluate.evaluate_prediction>` process rasters of any size band by band and get
the same numbers as one call on the whole array.

Height conventions (all in metres, error = predicted − reference):

* MAE, RMSE, bias (mean signed error) and the median absolute error over valid pixels;
* threshold accuracy δ < 1.25ᵏ (k = 1, 2, 3): share of pixels whose ratio ``max(p/t, t/p)`` is below
  1.25ᵏ, counted **only on pixels whose reference height t is above** ``threshold`` (default 1 m; the
  ratio is meaningless on the ground). A predicted height ``p ≤ 0`` there has no finite ratio and
  counts as a failure at every threshold;
* errors per reference-height bin (``[lo, hi)`` in metres, default ``0, 1, 2, 5, 10, 20, inf``;
  reference heights below the first edge go to no bin) and per true class;
* errors per *predicted*-height bin (the same edges): where the map reads a height, how far off it is on average.
  The two differ: a reference bin selects pixels by their truth, so the objects the network missed (predicted
  low) drag its bias down, while the predicted bin holds what a user can select on the map.

Class conventions: confusion matrices have the **reference** class on rows and the **predicted** class
on columns; pixels whose reference or prediction is :data:`~aerialmtl.classes.IGNORE_INDEX` (or
outside ``0..K-1``) are not counted. mIoU and mean F1 average over the classes present in the
reference **or** the prediction (a class absent from both has an undefined IoU and is left out; a class
predicted but absent from the reference gets IoU 0 and is counted). Undefined values are ``nan``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from aerialmtl.classes import IGNORE_INDEX
from aerialmtl.models.calibration import SPREAD_EDGES

#: Default reference-height bin edges (metres) for per-bin errors: [0,1), [1,2), ..., [20, inf): the height
#: ranges the calibration fits its spread in (:data:`aerialmtl.models.calibration.SPREAD_EDGES`, their one owner),
#: so that the report's bins are the ranges the spread was fitted on.
DEFAULT_HEIGHT_BINS: tuple[float, ...] = (0.0, *SPREAD_EDGES, math.inf)

#: Ratio thresholds of the δ accuracies: 1.25, 1.25², 1.25³.
DELTA_THRESHOLDS: tuple[float, ...] = (1.25, 1.25**2, 1.25**3)


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def _valid_mask(*arrays: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """``valid`` (default all True) AND finite in every float array; shapes must agree."""
    shape = np.shape(arrays[0])
    for a in arrays[1:]:
        if np.shape(a) != shape:
            raise ValueError(f"array shapes differ: {shape} vs {np.shape(a)}; pass arrays on the same grid")
    mask = np.ones(shape, bool) if valid is None else np.asarray(valid, bool).copy()
    if mask.shape != shape:
        raise ValueError(f"valid mask has shape {mask.shape}, expected {shape}")
    for a in arrays:
        a = np.asarray(a)
        if a.dtype.kind == "f":
            mask &= np.isfinite(a)
    return mask


def _div(num: np.ndarray | float, den: np.ndarray | float) -> Any:
    """``num / den`` with ``nan`` where ``den == 0`` (no warnings)."""
    num_a = np.asarray(num, dtype=np.float64)
    den_a = np.asarray(den, dtype=np.float64)
    out = np.full(np.broadcast(num_a, den_a).shape, np.nan)
    np.divide(num_a, den_a, out=out, where=den_a != 0)
    return out if out.ndim else float(out)


def delta_ratio(pred: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per-pixel ratio ``max(p/t, t/p)`` (≥ 1); ``inf`` where ``p ≤ 0`` or ``t ≤ 0``.

    Args:
        pred, ref: predicted and reference heights (metres), same shape.
    """
    p = np.asarray(pred, np.float64)
    t = np.asarray(ref, np.float64)
    ok = (p > 0) & (t > 0)
    ratio = np.full(p.shape, np.inf)
    ratio[ok] = np.maximum(p[ok] / t[ok], t[ok] / p[ok])
    return ratio


# ---------------------------------------------------------------------------------------------
# streaming subsample
# ---------------------------------------------------------------------------------------------
class Subsample:
    """A seeded uniform random subsample (without replacement) of at most ``cap`` pixels of a stream.

    Every pixel added gets a uniform random key; the ``cap`` pixels with the smallest keys are kept.
    That is an exact uniform sample of everything added, in bounded memory, and deterministic for a
    given seed and order of :meth:`add` calls. While fewer than ``cap`` pixels were added the sample
    holds all of them (``complete`` is True).

    Args:
        cap: maximum number of pixels kept.
        seed: seed of the random keys.
    """

    def __init__(self, cap: int = 2_000_000, seed: int = 0) -> None:
        if cap < 1:
            raise ValueError(f"subsample cap must be a positive number of pixels, got {cap}")
        self.cap = int(cap)
        self.rng = np.random.default_rng(seed)
        self.total = 0
        self._keys = np.empty(0, np.float64)
        self._cols: dict[str, np.ndarray] = {}

    @property
    def complete(self) -> bool:
        """True while the sample holds every pixel added."""
        return self.total <= self.cap

    def add(self, **columns: np.ndarray) -> None:
        """Add pixels: 1-D arrays of equal length, one per named column (same names every call)."""
        lengths = {len(v) for v in columns.values()}
        if len(lengths) != 1:
            raise ValueError(f"columns have different lengths {sorted(lengths)}")
        n = lengths.pop()
        if self._cols and set(columns) != set(self._cols):
            raise ValueError(f"columns {sorted(columns)} differ from earlier ones {sorted(self._cols)}")
        if n == 0:
            if not self._cols:
                self._cols = {k: np.asarray(v).ravel() for k, v in columns.items()}
            return
        self.total += n
        keys = self.rng.random(n)
        if not self._cols:
            self._cols = {k: np.empty(0, np.asarray(v).dtype) for k, v in columns.items()}
        if len(self._keys) >= self.cap:  # only pixels with a key below the current largest can enter
            take = keys < self._keys.max()
            keys = keys[take]
            columns = {k: np.asarray(v)[take] for k, v in columns.items()}
        keys_all = np.concatenate([self._keys, keys])
        cols_all = {k: np.concatenate([self._cols[k], np.asarray(columns[k]).ravel()]) for k in self._cols}
        if len(keys_all) > self.cap:
            keep = np.argpartition(keys_all, self.cap - 1)[: self.cap]
            keep.sort()
            keys_all = keys_all[keep]
            cols_all = {k: v[keep] for k, v in cols_all.items()}
        self._keys = keys_all
        self._cols = cols_all

    def __len__(self) -> int:
        return len(self._keys)

    def get(self, name: str) -> np.ndarray:
        """The sampled values of column ``name`` (1-D)."""
        return self._cols[name]


# ---------------------------------------------------------------------------------------------
# height
# ---------------------------------------------------------------------------------------------
class HeightStats:
    """Accumulates height errors over windows; :meth:`result` gives the metrics dict.

    Args:
        threshold: reference heights above this (metres) count for the δ accuracies.
        bins: reference-height bin edges (metres, increasing; the last may be ``inf``).
        num_classes: number of classes for per-class errors (``None``: no per-class errors).
        class_names: names of the classes (default ``class_0``, ...).
        sample_cap: maximum number of absolute errors kept for the median (exact when fewer pixels).
        seed: seed of that subsample.
    """

    def __init__(
        self,
        threshold: float = 1.0,
        bins: Sequence[float] = DEFAULT_HEIGHT_BINS,
        num_classes: int | None = None,
        class_names: Sequence[str] | None = None,
        sample_cap: int = 2_000_000,
        seed: int = 0,
    ) -> None:
        edges = np.asarray(bins, np.float64)
        if edges.ndim != 1 or len(edges) < 2 or np.any(np.diff(edges) <= 0):
            raise ValueError(f"height bins must be at least 2 increasing edges (metres), got {list(bins)}")
        self.threshold = float(threshold)
        self.edges = edges
        nb = len(edges) - 1
        self.n = 0
        self.sum_err = 0.0
        self.sum_abs = 0.0
        self.sum_sq = 0.0
        self.n_above = 0
        self.n_delta = np.zeros(len(DELTA_THRESHOLDS), np.int64)
        #: per bin of the reference ("reference") and of the predicted height ("predicted"): n, Σ|e|, Σe², Σe
        self.bins = {by: (np.zeros(nb, np.int64), np.zeros(nb), np.zeros(nb), np.zeros(nb))
                     for by in ("reference", "predicted")}
        self.num_classes = num_classes
        if num_classes is not None:
            self.class_names = (list(class_names) if class_names is not None
                                else [f"class_{i}" for i in range(num_classes)])
            self.cls_n = np.zeros(num_classes, np.int64)
            self.cls_abs = np.zeros(num_classes)
            self.cls_sq = np.zeros(num_classes)
            self.cls_err = np.zeros(num_classes)
        self.sample = Subsample(sample_cap, seed)

    def update(
        self,
        pred: np.ndarray,
        ref: np.ndarray,
        valid: np.ndarray | None = None,
        labels: np.ndarray | None = None,
    ) -> np.ndarray:
        """Add one window.

        Args:
            pred, ref: (H, W) predicted and reference heights in metres (NaN = invalid).
            valid: optional (H, W) bool mask of usable pixels.
            labels: optional (H, W) reference class indices (``IGNORE_INDEX`` = unlabelled) for
                per-class errors.

        Returns:
            the (H, W) bool mask of the pixels that were counted.
        """
        mask = _valid_mask(pred, ref, valid=valid)
        p = np.asarray(pred, np.float64)[mask]
        t = np.asarray(ref, np.float64)[mask]
        err = p - t
        ab = np.abs(err)
        sq = err * err
        self.n += int(mask.sum())
        self.sum_err += float(err.sum())
        self.sum_abs += float(ab.sum())
        self.sum_sq += float(sq.sum())
        above = t > self.threshold
        self.n_above += int(above.sum())
        ratio = delta_ratio(p[above], t[above])
        for i, d in enumerate(DELTA_THRESHOLDS):
            self.n_delta[i] += int((ratio < d).sum())
        nb = len(self.edges) - 1
        for by, key in (("reference", t), ("predicted", p)):
            b = np.searchsorted(self.edges, key, side="right") - 1
            inb = (b >= 0) & (b < nb)
            n, s_abs, s_sq, s_err = self.bins[by]
            n += np.bincount(b[inb], minlength=nb)
            s_abs += np.bincount(b[inb], weights=ab[inb], minlength=nb)
            s_sq += np.bincount(b[inb], weights=sq[inb], minlength=nb)
            s_err += np.bincount(b[inb], weights=err[inb], minlength=nb)
        if self.num_classes is not None and labels is not None:
            lab = np.asarray(labels)[mask].astype(np.int64)
            ok = (lab >= 0) & (lab < self.num_classes)
            k = self.num_classes
            self.cls_n += np.bincount(lab[ok], minlength=k)
            self.cls_abs += np.bincount(lab[ok], weights=ab[ok], minlength=k)
            self.cls_sq += np.bincount(lab[ok], weights=sq[ok], minlength=k)
            self.cls_err += np.bincount(lab[ok], weights=err[ok], minlength=k)
        self.sample.add(abs_error=ab.astype(np.float32))
        return mask

    def result(self) -> dict[str, Any]:
        """The metrics: ``n_pixels, mae, rmse, bias, median_abs_error`` (m), ``delta``, ``per_bin`` (bins of the
        reference height) and ``per_predicted_bin`` (bins of the predicted height), and ``per_class`` when labels
        were given; ``median_exact`` says whether the median used every pixel or the seeded subsample.
        """

        def per_bin(by: str) -> list[dict[str, Any]]:
            n, s_abs, s_sq, s_err = self.bins[by]
            return [{"range_m": [float(self.edges[i]), float(self.edges[i + 1])], "n_pixels": int(n[i]),
                     "mae": _div(s_abs[i], n[i]), "rmse": math.sqrt(s_sq[i] / n[i]) if n[i] else math.nan,
                     "bias": _div(s_err[i], n[i])} for i in range(len(n))]

        out: dict[str, Any] = {
            "n_pixels": self.n,
            "mae": _div(self.sum_abs, self.n),
            "rmse": math.sqrt(self.sum_sq / self.n) if self.n else math.nan,
            "bias": _div(self.sum_err, self.n),
            "median_abs_error": float(np.median(self.sample.get("abs_error"))) if self.n else math.nan,
            "median_exact": self.sample.complete,
            "delta": {
                "reference_above_m": self.threshold,
                "n_pixels": self.n_above,
                **{f"delta_{k + 1}": _div(self.n_delta[k], self.n_above) for k in range(len(DELTA_THRESHOLDS))},
            },
            "per_bin": per_bin("reference"),
            "per_predicted_bin": per_bin("predicted"),
        }
        if self.num_classes is not None:
            out["per_class"] = {
                name: {
                    "n_pixels": int(self.cls_n[i]),
                    "mae": _div(self.cls_abs[i], self.cls_n[i]),
                    "rmse": math.sqrt(self.cls_sq[i] / self.cls_n[i]) if self.cls_n[i] else math.nan,
                    "bias": _div(self.cls_err[i], self.cls_n[i]),
                }
                for i, name in enumerate(self.class_names)
            }
        return out


def height_metrics(
    pred: np.ndarray,
    ref: np.ndarray,
    valid: np.ndarray | None = None,
    threshold: float = 1.0,
    bins: Sequence[float] = DEFAULT_HEIGHT_BINS,
    labels: np.ndarray | None = None,
    num_classes: int | None = None,
    class_names: Sequence[str] | None = None,
) -> dict[str, Any]:
    """Height metrics of ``pred`` against ``ref`` (metres, same shape; NaN or ``valid=False`` = skipped).

    See :class:`HeightStats` and the module docstring for the definitions. ``labels`` (reference class
    indices) with ``num_classes`` adds errors per true class.
    """
    if labels is not None and num_classes is None:
        num_classes = int(np.max(np.where(np.asarray(labels) == IGNORE_INDEX, -1, labels), initial=-1)) + 1
    stats = HeightStats(threshold, bins, num_classes, class_names, sample_cap=max(1, np.size(pred)))
    stats.update(pred, ref, valid, labels)
    return stats.result()


# ---------------------------------------------------------------------------------------------
# classes
# ---------------------------------------------------------------------------------------------
def confusion_matrix(
    ref: np.ndarray, pred: np.ndarray, num_classes: int, valid: np.ndarray | None = None
) -> np.ndarray:
    """(K, K) int64 confusion matrix, rows = reference class, columns = predicted class.

    Pixels where either array is outside ``0..K-1`` (e.g. ``IGNORE_INDEX``) or ``valid`` is False are
    not counted. Matrices of windows add up: ``sum(confusion_matrix(window_i))`` is the matrix of the
    whole raster.
    """
    r = np.asarray(ref).astype(np.int64, copy=False)
    p = np.asarray(pred).astype(np.int64, copy=False)
    mask = _valid_mask(r, p, valid=valid)
    mask &= (r >= 0) & (r < num_classes) & (p >= 0) & (p < num_classes)
    idx = r[mask] * num_classes + p[mask]
    return np.bincount(idx, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def cohen_kappa(cm: np.ndarray) -> float:
    """Cohen's κ = (p_o − p_e) / (1 − p_e) of a confusion matrix; ``nan`` when undefined (p_e = 1 or empty)."""
    cm = np.asarray(cm, np.float64)
    n = cm.sum()
    if n == 0:
        return math.nan
    po = np.trace(cm) / n
    pe = float((cm.sum(1) * cm.sum(0)).sum()) / (n * n)
    return (po - pe) / (1 - pe) if pe < 1 else math.nan


def classification_metrics(cm: np.ndarray, class_names: Sequence[str] | None = None) -> dict[str, Any]:
    """Overall accuracy, Cohen's κ, mIoU, mean F1 and per-class IoU/F1/precision/recall from a confusion matrix.

    Args:
        cm: (K, K) confusion matrix, rows = reference, columns = prediction.
        class_names: K names (default ``class_0``, ...).

    Returns:
        dict with ``n_pixels, overall_accuracy, kappa, miou, mean_f1, classes_in_mean`` (names of the
        classes averaged: present in reference or prediction), ``per_class`` (name → ``iou, f1,
        precision, recall, n_reference, n_predicted``) and ``confusion_matrix`` (list of lists).
    """
    cm = np.asarray(cm, np.int64)
    k = cm.shape[0]
    names = list(class_names) if class_names is not None else [f"class_{i}" for i in range(k)]
    tp = np.diag(cm).astype(np.float64)
    n_ref = cm.sum(1)
    n_pred = cm.sum(0)
    n = int(cm.sum())
    iou = _div(tp, n_ref + n_pred - tp)
    f1 = _div(2 * tp, n_ref + n_pred)
    present = (n_ref + n_pred) > 0
    return {
        "n_pixels": n,
        "overall_accuracy": _div(tp.sum(), n),
        "kappa": cohen_kappa(cm),
        "miou": float(np.mean(iou[present])) if present.any() else math.nan,
        "mean_f1": float(np.mean(f1[present])) if present.any() else math.nan,
        "classes_in_mean": [names[i] for i in np.flatnonzero(present)],
        "per_class": {
            names[i]: {
                "iou": float(iou[i]),
                "f1": float(f1[i]),
                "precision": float(_div(tp[i], n_pred[i])),
                "recall": float(_div(tp[i], n_ref[i])),
                "n_reference": int(n_ref[i]),
                "n_predicted": int(n_pred[i]),
            }
            for i in range(k)
        },
        "confusion_matrix": cm.tolist(),
    }


__all__ = [
    "DEFAULT_HEIGHT_BINS",
    "DELTA_THRESHOLDS",
    "HeightStats",
    "Subsample",
    "classification_metrics",
    "cohen_kappa",
    "confusion_matrix",
    "delta_ratio",
    "height_metrics",
]
