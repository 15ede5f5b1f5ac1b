"""How useful are the MC-dropout uncertainties? Sparsification, AUSE/AURG, ECE, Gaussian NLL, Spearman.

Sparsification (Ilg et al., ECCV 2018): sort pixels by uncertainty, remove the most uncertain fraction
``f`` and compute the mean error of the remaining pixels, for ``f`` = 0, 1/S, ..., (S−1)/S. The
*oracle* curve sorts by the true error instead (the best any uncertainty could do); the *random* curve
removes pixels at random and stays at the full-set mean error.

Conventions chosen here:

* curves are **normalised by the full-set mean error**, so every curve starts at 1 and AUSE/AURG are
  fractions of the full-set error, comparable between scenes and tasks (the full-set error is reported
  next to them). When the full-set error is 0 the curves are left unnormalised (all zero);
* **AUSE** = trapezoidal area between the uncertainty curve and the oracle curve over ``f`` in
  [0, (S−1)/S] (0 = perfect ranking, larger = worse);
* **AURG** = area between the random curve (constant 1) and the uncertainty curve (positive = better
  than random, negative = worse than random);
* pixels with **equal uncertainty** are removed in random order; the curve uses the expected error under
  that random tie-breaking, so a constant uncertainty gives exactly the random curve;
* heights: error = |predicted − reference| (m), uncertainty = MC standard deviation (m);
  classes: error = 1 − correct, uncertainty = predictive entropy or mutual information (nats);
* **ECE** uses the confidence = max class probability in 15 equal-width bins on [0, 1]
  (``Σ_b n_b/N · |accuracy_b − confidence_b|``);
* **Gaussian NLL** of the reference height under N(mean, σ²) with σ = max(std, ``min_std``), default
  ``min_std`` = 0.01 m, so that a zero spread does not give an infinite NLL (nats per pixel).
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np

#: Number of removal fractions of a sparsification curve (0, 1/S, ..., (S-1)/S).
DEFAULT_STEPS = 50

#: Bins of the expected calibration error.
DEFAULT_ECE_BINS = 15

#: Floor of the predicted height standard deviation in the Gaussian NLL (metres).
DEFAULT_MIN_STD = 0.01


def _kept_means(error: np.ndarray, key: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Mean error of the ``kept[i]`` pixels of lowest ``key`` (ties broken at random, in expectation)."""
    order = np.argsort(key, kind="stable")
    ks = key[order]
    es = error[order].astype(np.float64)
    cs = np.concatenate([[0.0], np.cumsum(es)])
    n = len(ks)
    starts = np.flatnonzero(np.concatenate([[True], ks[1:] != ks[:-1]]))
    ends = np.concatenate([starts[1:], [n]])
    g = np.searchsorted(ends, kept, side="left")  # group holding the kept-th pixel
    g = np.minimum(g, len(ends) - 1)
    start, end = starts[g], ends[g]
    group_mean = (cs[end] - cs[start]) / (end - start)
    sums = cs[start] + (kept - start) * group_mean
    return sums / kept


def sparsification(
    error: np.ndarray, uncertainty: np.ndarray, steps: int = DEFAULT_STEPS, normalise: bool = True
) -> dict[str, Any]:
    """Sparsification curve of ``uncertainty`` against ``error``, its oracle, AUSE and AURG.

    Args:
        error: (N,) per-pixel error, ≥ 0 (|height error| in metres, or 1 − correct).
        uncertainty: (N,) per-pixel uncertainty (larger = less trusted). Non-finite pairs are dropped.
        steps: number of removal fractions S (0, 1/S, ..., (S−1)/S).
        normalise: divide the curves by the full-set mean error (see the module docstring).

    Returns:
        dict with ``n_pixels``, ``mean_error`` (full set, error units), ``fractions`` (S,), ``curve`` (S,),
        ``oracle`` (S,), ``random`` (S,), ``ause``, ``aurg``, ``normalised``. Empty input gives ``nan``s.
    """
    e = np.asarray(error, np.float64).ravel()
    u = np.asarray(uncertainty, np.float64).ravel()
    if e.shape != u.shape:
        raise ValueError(f"error has {e.size} values but uncertainty has {u.size}; pass one value per pixel")
    ok = np.isfinite(e) & np.isfinite(u)
    e, u = e[ok], u[ok]
    n = e.size
    fractions = np.arange(steps) / steps
    if n == 0:
        nan = [math.nan] * steps
        return {"n_pixels": 0, "mean_error": math.nan, "fractions": fractions.tolist(), "curve": nan,
                "oracle": nan, "random": nan, "ause": math.nan, "aurg": math.nan, "normalised": normalise}
    kept = np.maximum(1, n - np.floor(fractions * n).astype(np.int64))
    curve = _kept_means(e, u, kept)
    oracle = _kept_means(e, e, kept)
    full = float(e.mean())
    random = np.full(steps, full)
    scale = full if (normalise and full > 0) else 1.0
    curve, oracle, random = curve / scale, oracle / scale, random / scale
    trapz = getattr(np, "trapezoid", None) or getattr(np, "trapz")  # noqa: B009 - numpy < 2 has only trapz
    return {
        "n_pixels": int(n),
        "mean_error": full,
        "fractions": fractions.tolist(),
        "curve": curve.tolist(),
        "oracle": oracle.tolist(),
        "random": random.tolist(),
        "ause": float(trapz(curve - oracle, fractions)),
        "aurg": float(trapz(random - curve, fractions)),
        "normalised": bool(normalise and full > 0),
    }


def average_ranks(x: np.ndarray) -> np.ndarray:
    """1-based ranks of a 1-D array, ties sharing their average rank (like ``scipy.stats.rankdata``)."""
    x = np.asarray(x).ravel()
    order = np.argsort(x, kind="stable")
    xs = x[order]
    starts = np.flatnonzero(np.concatenate([[True], xs[1:] != xs[:-1]]))
    ends = np.concatenate([starts[1:], [x.size]])
    avg = 0.5 * (starts + ends + 1)  # mean of ranks start+1 .. end
    ranks = np.empty(x.size, np.float64)
    ranks[order] = np.repeat(avg, ends - starts)
    return ranks


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman rank correlation of two 1-D arrays (average ranks for ties); ``nan`` if undefined.

    Non-finite pairs are dropped; fewer than 2 pixels or a constant array give ``nan``.
    """
    a = np.asarray(x, np.float64).ravel()
    b = np.asarray(y, np.float64).ravel()
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    if a.size < 2 or np.all(a == a[0]) or np.all(b == b[0]):
        return math.nan
    ra, rb = average_ranks(a), average_ranks(b)
    ra -= ra.mean()
    rb -= rb.mean()
    return float((ra * rb).sum() / math.sqrt((ra * ra).sum() * (rb * rb).sum()))


class CalibrationBins:
    """Streaming reliability statistics: per confidence bin, the pixel count, summed confidence and
    summed correctness. Equal-width bins on [0, 1]; confidence 1 falls in the last bin.

    Args:
        n_bins: number of bins (default 15).
    """

    def __init__(self, n_bins: int = DEFAULT_ECE_BINS) -> None:
        self.n_bins = n_bins
        self.count = np.zeros(n_bins, np.int64)
        self.sum_conf = np.zeros(n_bins)
        self.sum_correct = np.zeros(n_bins)

    def update(self, confidence: np.ndarray, correct: np.ndarray) -> None:
        """Add pixels: ``confidence`` in [0, 1] (max class probability), ``correct`` bool, same shape."""
        c = np.asarray(confidence, np.float64).ravel()
        ok = np.isfinite(c)
        c = np.clip(c[ok], 0.0, 1.0)
        r = np.asarray(correct, np.float64).ravel()[ok]
        b = np.minimum((c * self.n_bins).astype(np.int64), self.n_bins - 1)
        self.count += np.bincount(b, minlength=self.n_bins)
        self.sum_conf += np.bincount(b, weights=c, minlength=self.n_bins)
        self.sum_correct += np.bincount(b, weights=r, minlength=self.n_bins)

    def result(self) -> dict[str, Any]:
        """``ece``, ``n_pixels``, ``n_bins`` and per-bin ``bin_edges``, ``count``, ``confidence``, ``accuracy``."""
        n = int(self.count.sum())
        with np.errstate(invalid="ignore", divide="ignore"):
            conf = np.where(self.count > 0, self.sum_conf / np.maximum(self.count, 1), np.nan)
            acc = np.where(self.count > 0, self.sum_correct / np.maximum(self.count, 1), np.nan)
        gap = np.where(self.count > 0, np.abs(acc - conf), 0.0)
        return {
            "ece": float((self.count * gap).sum() / n) if n else math.nan,
            "n_pixels": n,
            "n_bins": self.n_bins,
            "bin_edges": np.linspace(0, 1, self.n_bins + 1).tolist(),
            "count": self.count.tolist(),
            "confidence": conf.tolist(),
            "accuracy": acc.tolist(),
        }


def expected_calibration_error(
    confidence: np.ndarray, correct: np.ndarray, n_bins: int = DEFAULT_ECE_BINS
) -> float:
    """ECE of ``confidence`` (max class probability, [0, 1]) against ``correct`` (bool).

    See :class:`CalibrationBins`.
    """
    bins = CalibrationBins(n_bins)
    bins.update(confidence, correct)
    return bins.result()["ece"]


def gaussian_nll_terms(
    mean: np.ndarray, std: np.ndarray, ref: np.ndarray, min_std: float = DEFAULT_MIN_STD
) -> np.ndarray:
    """Per-pixel negative log-likelihood (nats) of ``ref`` under N(``mean``, σ²), σ = max(``std``, ``min_std``).

    ``0.5·log(2πσ²) + (ref − mean)² / (2σ²)``; all arrays in metres, same shape.
    """
    sigma = np.maximum(np.asarray(std, np.float64), min_std)
    d = np.asarray(ref, np.float64) - np.asarray(mean, np.float64)
    return 0.5 * np.log(2 * np.pi * sigma * sigma) + d * d / (2 * sigma * sigma)


def gaussian_nll(
    mean: np.ndarray, std: np.ndarray, ref: np.ndarray, min_std: float = DEFAULT_MIN_STD
) -> float:
    """Mean Gaussian NLL (nats per pixel) over pixels where all three arrays are finite; ``nan`` if none."""
    terms = gaussian_nll_terms(mean, std, ref, min_std)
    terms = terms[np.isfinite(terms)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return float(terms.mean()) if terms.size else math.nan


__all__ = [
    "CalibrationBins",
    "DEFAULT_ECE_BINS",
    "DEFAULT_MIN_STD",
    "DEFAULT_STEPS",
    "expected_calibration_error",
    "gaussian_nll",
    "gaussian_nll_terms",
    "sparsification",
    "spearman",
    "average_ranks",
]
