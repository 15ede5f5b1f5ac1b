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
from typing import Any

import numpy as np

from aerialmtl.evaluation.metrics import Subsample
from aerialmtl.quiet import ignoring_warnings

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
    result: np.ndarray = sums / kept
    return result


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
    """Streaming reliability statistics: per confidence bin, the pixel count, summed confidence and correctness.

    Equal-width bins on [0, 1]; confidence 1 falls in the last bin.

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
    result: float = bins.result()["ece"]
    return result


def gaussian_nll_terms(
    mean: np.ndarray, std: np.ndarray, ref: np.ndarray, min_std: float = DEFAULT_MIN_STD
) -> np.ndarray:
    """Per-pixel negative log-likelihood (nats) of ``ref`` under N(``mean``, σ²), σ = max(``std``, ``min_std``).

    ``0.5·log(2πσ²) + (ref − mean)² / (2σ²)``; all arrays in metres, same shape.
    """
    sigma = np.maximum(np.asarray(std, np.float64), min_std)
    d = np.asarray(ref, np.float64) - np.asarray(mean, np.float64)
    result: np.ndarray = 0.5 * np.log(2 * np.pi * sigma * sigma) + d * d / (2 * sigma * sigma)
    return result


def gaussian_nll(
    mean: np.ndarray, std: np.ndarray, ref: np.ndarray, min_std: float = DEFAULT_MIN_STD
) -> float:
    """Mean Gaussian NLL (nats per pixel) over pixels where all three arrays are finite; ``nan`` if none."""
    terms = gaussian_nll_terms(mean, std, ref, min_std)
    terms = terms[np.isfinite(terms)]
    with ignoring_warnings():
        return float(terms.mean()) if terms.size else math.nan


# ---- the spread judged per stratum ---------------------------------------------------------------
#: Nominal central-interval probabilities of the reliability curves.
RELIABILITY_LEVELS: tuple[float, ...] = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.683, 0.8, 0.9, 0.954)
_SQRT2 = math.sqrt(2.0)


def _erf(x: np.ndarray) -> np.ndarray:
    from scipy.special import erf

    return np.asarray(erf(x), np.float64)


def crps_gaussian(mean: np.ndarray, std: np.ndarray, ref: np.ndarray, min_std: float = DEFAULT_MIN_STD) -> np.ndarray:
    """Per-pixel CRPS (metres) of N(``mean``, σ²), σ = max(``std``, ``min_std``), at ``ref``.

    Closed form (Gneiting & Raftery 2007): ``σ·[z(2Φ(z) − 1) + 2φ(z) − 1/√π]``, z = (ref − mean)/σ. A proper
    score: lower is better, and it reduces to |error| for a spread of 0.
    """
    sigma = np.maximum(np.asarray(std, np.float64), min_std)
    z = (np.asarray(ref, np.float64) - np.asarray(mean, np.float64)) / sigma
    pdf = np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)
    cdf = 0.5 * (1 + _erf(z / _SQRT2))
    return sigma * (z * (2 * cdf - 1) + 2 * pdf - 1 / math.sqrt(math.pi))


def laplace_terms(mean: np.ndarray, std: np.ndarray, ref: np.ndarray,
                  min_std: float = DEFAULT_MIN_STD) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel NLL (nats) and CRPS (metres) of ``ref`` under the Laplace law of the same standard deviation.

    b = σ/√2, σ = max(``std``, ``min_std``): NLL ``log 2b + |e|/b``, CRPS ``|e| + b·exp(−|e|/b) − 3b/4``.
    """
    b = np.maximum(np.asarray(std, np.float64), min_std) / _SQRT2
    e = np.abs(np.asarray(ref, np.float64) - np.asarray(mean, np.float64))
    return np.log(2 * b) + e / b, e + b * np.exp(-e / b) - 0.75 * b


def _gaussian_quantile(p: float) -> float:
    from scipy.special import erfinv

    return float(_SQRT2 * erfinv(p))


def height_bins(edges: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Index of the reference-height bin of each value of ``ref`` (metres) among ``edges``.

    ``edges`` increase; the last may be ``inf``. Heights below the first edge count in the first bin, above the
    last in the last.
    """
    return np.clip(np.searchsorted(edges, ref, side="right") - 1, 0, len(edges) - 2)


class SpreadStrata:
    """Is the height spread right where users look?

    Coverage, proper scores, medians and rank correlation of ``height_std`` per reference-height bin (and per
    class), accumulated window by window.

    Exact sums per stratum: pixels, pixels within ±1σ and ±2σ, Gaussian and Laplace NLL and CRPS (σ = the
    layer's value, floored at ``min_std``). From a seeded uniform subsample of at most ``sample_cap`` pixels:
    the median std and median |error| per bin, Spearman(std, |error|) within each bin (does the spread rank
    the errors among pixels of similar height, which a spread that follows the predicted height alone cannot),
    Spearman(std, predicted height) within each bin (near 1: the spread is the height map rescaled there),
    and the reliability curve (observed share of pixels inside the central Gaussian interval of each nominal
    probability in :data:`RELIABILITY_LEVELS`).

    Args:
        edges: reference-height bin edges (metres, increasing; the last may be ``inf``); heights below the
            first edge count in the first bin.
        class_names: names of the reference classes (``None``: no per-class strata).
        sample_cap, seed: the subsample.
        min_std: floor of σ (metres) in the scores.
    """

    def __init__(self, edges: Any, class_names: list[str] | None = None, sample_cap: int = 2_000_000,
                 seed: int = 0, min_std: float = DEFAULT_MIN_STD) -> None:
        self.edges = np.asarray(edges, np.float64)
        self.class_names = class_names
        self.min_std = float(min_std)
        nb = len(self.edges) - 1
        nc = len(class_names) if class_names else 0
        #: rows: height bins then classes; columns: n, ≤1σ, ≤2σ, NLL gauss, NLL laplace, CRPS gauss, CRPS laplace
        self.sums = np.zeros((nb + nc, 7))
        self.sample = Subsample(sample_cap, seed)

    def update(self, pred: np.ndarray, std: np.ndarray, ref: np.ndarray, labels: np.ndarray | None = None) -> None:
        """Add pixels: 1-D ``pred``, ``std``, ``ref`` (metres, finite) and optional reference class indices.

        Values outside the classes are ignored for the per-class rows.
        """
        pred, std, ref = (np.asarray(a, np.float64).ravel() for a in (pred, std, ref))
        if pred.size == 0:
            return
        nb = len(self.edges) - 1
        err = np.abs(ref - pred)
        sigma = np.maximum(std, self.min_std)
        g_nll = gaussian_nll_terms(pred, std, ref, self.min_std)
        l_nll, l_crps = laplace_terms(pred, std, ref, self.min_std)
        g_crps = crps_gaussian(pred, std, ref, self.min_std)
        cols = np.stack([np.ones_like(err), err <= sigma, err <= 2 * sigma, g_nll, l_nll, g_crps, l_crps], 1)
        b = height_bins(self.edges, ref)
        lab = np.asarray(labels).ravel().astype(np.int64) if labels is not None else np.full(b.size, -1)
        rows = [(b, np.ones(b.size, bool))]
        if self.class_names:
            rows.append((nb + lab, (lab >= 0) & (lab < len(self.class_names))))
        for idx, ok in rows:
            for k in range(cols.shape[1]):
                self.sums[:, k] += np.bincount(idx[ok], weights=cols[ok, k], minlength=self.sums.shape[0])
        self.sample.add(abs_error=err, std=std, pred=pred, bin=b.astype(np.int64), label=lab)

    def _row(self, k: int) -> dict[str, Any]:
        n, w1, w2, gn, ln, gc, lc = self.sums[k]
        if n == 0:
            return {"n_pixels": 0}
        return {"n_pixels": int(n), "coverage_1sigma": w1 / n, "coverage_2sigma": w2 / n,
                "nll_gaussian": gn / n, "nll_laplace": ln / n, "crps_gaussian_m": gc / n, "crps_laplace_m": lc / n}

    @staticmethod
    def _sampled(err: np.ndarray, std: np.ndarray, pred: np.ndarray) -> dict[str, Any]:
        if err.size == 0:
            return {}
        sigma = np.maximum(std, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = [float(np.mean(err <= _gaussian_quantile(p) * sigma)) for p in RELIABILITY_LEVELS]
        med_err, med_std = float(np.median(err)), float(np.median(std))
        return {"median_abs_error_m": med_err, "median_std_m": med_std,
                "median_std_over_median_abs_error": med_std / med_err if med_err > 0 else math.nan,
                "mean_abs_error_m": float(err.mean()), "max_std_m": float(std.max()),
                "spearman_std_vs_abs_error": spearman(std, err),
                "spearman_std_vs_predicted_height": spearman(std, pred), "reliability_observed": rel}

    def result(self) -> dict[str, Any]:
        """The scores per reference-height bin, per class and overall.

        ``bins`` (one dict per reference-height bin: ``range_m``, ``share``, the exact scores and the sampled
        medians, Spearman and reliability), ``classes`` (the same per class, when given),
        ``reliability_levels`` and the overall scores.
        """
        nb = len(self.edges) - 1
        if self.sample.total:
            err, std, pred = self.sample.get("abs_error"), self.sample.get("std"), self.sample.get("pred")
            bins_s, labels_s = self.sample.get("bin"), self.sample.get("label")
        else:
            err = std = pred = np.empty(0)
            bins_s = labels_s = np.empty(0, np.int64)
        total = self.sums[:nb, 0].sum()
        bins = []
        for k in range(nb):
            sel = bins_s == k
            row = {"range_m": [float(self.edges[k]), float(self.edges[k + 1])],
                   "share": float(self.sums[k, 0] / total) if total else math.nan, **self._row(k),
                   **self._sampled(err[sel], std[sel], pred[sel])}
            bins.append(row)
        out: dict[str, Any] = {"reliability_levels": list(RELIABILITY_LEVELS), "bins": bins,
                               "min_std_m": self.min_std}
        if total:
            n = total
            keys = ("nll_gaussian", "nll_laplace", "crps_gaussian_m", "crps_laplace_m")
            out.update({key: float(self.sums[:nb, 3 + i].sum() / n) for i, key in enumerate(keys)})
        if self.class_names:
            out["classes"] = {name: {**self._row(nb + c), **self._sampled(err[labels_s == c], std[labels_s == c],
                                                                          pred[labels_s == c])}
                              for c, name in enumerate(self.class_names)}
        return out


__all__ = [
    "RELIABILITY_LEVELS",
    "SpreadStrata",
    "crps_gaussian",
    "height_bins",
    "laplace_terms",
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
