"""Height and spread calibration fitted on the validation split, stored in the checkpoint, applied by predict.

A model trained on a small area finds where tall things are but compresses how tall they are, in a way
that is systematic on held-out data; its MC-dropout spread is not calibrated either. Two cheap maps
correct both after training, fitted on validation pixels only:

* **height**: a monotone, piecewise-linear map ``predicted → calibrated`` (metres), stored as knots
  ``(x_k, y_k)`` and applied by linear interpolation (``numpy.interp``/:func:`interp_torch`). Beyond the
  last knot it continues with slope 1 (a constant offset), below the first it is clamped at ``y_0``;
  results are never negative. Two fits:

  - ``isotonic``: the isotonic regression of the reference height on the predicted height over pixels
    binned by predicted height (equal-count bins, each a mean): the calibrated value is the validation
    mean of the reference among pixels predicted alike (least squares under monotonicity).
  - ``median``: the same with each bin's median reference height (an L1 fit, like the height loss): it
    leaves a mostly-ground bin at the ground instead of lifting it to the bin's mean, so it trades less
    overall MAE for less correction of tall pixels.
  - ``quantile``: quantile mapping: the k-th quantile of the predictions maps to the k-th quantile of
    the reference, so the calibrated heights have the validation's height distribution (it undoes a
    compression fully, at the price of more spread for pixels whose prediction is uncertain).

* **spread**: ``σ = sqrt((std_scale · height_std)² + std_floor²)`` with the factor and the floor fitted so
  that ±1 σ covers 68.3 % and ±2 σ as close to 95.4 % as the pair allows of the validation pixels'
  calibrated errors, as a Gaussian would. The floor matters: where the decoder's features are all zero
  (confident ground), every MC sample gives the same height and the MC spread is ~0, which no factor
  can turn into an interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

CalibrationMethod = Literal["isotonic", "median", "quantile"]
#: Fraction of a Gaussian within ±1 σ and ±2 σ.
ONE_SIGMA = 0.6826894921370859
TWO_SIGMA = 0.9544997361036416
DEFAULT_KNOTS = 64


@dataclass(frozen=True)
class Calibration:
    """A fitted height map and spread factor (saved in :class:`~aerialmtl.formats.checkpoint.ModelMeta`).

    Attributes:
        height_x: knots on the predicted height (metres, strictly increasing).
        height_y: calibrated heights at the knots (metres, non-decreasing).
        std_scale: factor applied to ``height_std`` (1 = unchanged).
        std_floor: metres added in quadrature to the scaled spread (0 = none; older calibrations).
        method: ``isotonic``, ``median`` or ``quantile``.
        n_pixels: validation pixels the maps were fitted on.
        source: what they were fitted on (e.g. ``val split of TILES, T=16``).
    """

    height_x: tuple[float, ...]
    height_y: tuple[float, ...]
    std_scale: float = 1.0
    method: str = "isotonic"
    n_pixels: int = 0
    source: str = ""
    std_floor: float = 0.0

    def __post_init__(self) -> None:
        if len(self.height_x) != len(self.height_y) or len(self.height_x) < 2:
            raise ValueError(f"Calibration: need ≥ 2 knots with as many x as y, got {len(self.height_x)} and "
                             f"{len(self.height_y)}")
        if any(b <= a for a, b in zip(self.height_x, self.height_x[1:], strict=False)):
            raise ValueError("Calibration: height_x must be strictly increasing")
        if not (math.isfinite(self.std_scale) and self.std_scale >= 0):
            raise ValueError(f"Calibration: std_scale must be finite and ≥ 0, got {self.std_scale}")
        if not (math.isfinite(self.std_floor) and self.std_floor >= 0):
            raise ValueError(f"Calibration: std_floor must be finite and ≥ 0, got {self.std_floor}")

    def height(self, h: np.ndarray) -> np.ndarray:
        """Calibrated heights (metres) of predicted heights ``h`` (any shape; NaN stays NaN)."""
        x, y = np.asarray(self.height_x), np.asarray(self.height_y)
        out = np.interp(h, x, y)
        beyond = h > x[-1]
        out = np.where(beyond, y[-1] + (h - x[-1]), out)
        return np.maximum(out, 0.0).astype(np.asarray(h).dtype, copy=False)

    def std(self, s: np.ndarray) -> np.ndarray:
        """Calibrated spreads (metres): ``sqrt((std_scale · s)² + std_floor²)``."""
        out = np.hypot(np.asarray(s, dtype=np.float64) * self.std_scale, self.std_floor)
        return out.astype(np.asarray(s).dtype, copy=False)

    def std_torch(self, s: torch.Tensor) -> torch.Tensor:
        """:meth:`std` on a tensor."""
        return torch.hypot(s * self.std_scale, torch.full_like(s, self.std_floor))

    def height_torch(self, h: torch.Tensor) -> torch.Tensor:
        """:meth:`height` on a tensor (any device, float dtype kept)."""
        x = torch.tensor(self.height_x, dtype=h.dtype, device=h.device)
        y = torch.tensor(self.height_y, dtype=h.dtype, device=h.device)
        return interp_torch(h, x, y).clamp_min_(0.0)

    def summary(self) -> str:
        """One line for logs: the height map's knots (a few) and the spread factor and floor."""
        pts = ", ".join(f"{a:.1f}→{b:.1f}" for a, b in zip(self.height_x[::max(1, len(self.height_x) // 6)],
                                                        self.height_y[::max(1, len(self.height_y) // 6)],
                                                        strict=False))
        return (f"{self.method} height map ({pts} m), std × {self.std_scale:.3g} ⊕ {self.std_floor:.2f} m, "
                f"{self.n_pixels} px")


def interp_torch(h: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear ``y(x)`` at ``h``: clamped below ``x[0]``, slope 1 beyond ``x[-1]`` (a new tensor)."""
    flat = h.reshape(-1)
    idx = torch.searchsorted(x, flat.contiguous()).clamp_(1, x.numel() - 1)
    x0, x1, y0, y1 = x[idx - 1], x[idx], y[idx - 1], y[idx]
    t = ((flat - x0) / (x1 - x0)).clamp_(0.0, 1.0)
    out = y0 + t * (y1 - y0)
    out = torch.where(flat > x[-1], y[-1] + (flat - x[-1]), out)
    return out.reshape(h.shape)


def _pava(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted isotonic (non-decreasing) least-squares fit of ``values`` (pool adjacent violators)."""
    means: list[float] = []
    wsum: list[float] = []
    counts: list[int] = []
    for v, w in zip(values.tolist(), weights.tolist(), strict=True):
        means.append(v)
        wsum.append(w)
        counts.append(1)
        while len(means) > 1 and means[-2] > means[-1]:
            w2 = wsum[-2] + wsum[-1]
            m2 = (means[-2] * wsum[-2] + means[-1] * wsum[-1]) / w2
            c2 = counts[-2] + counts[-1]
            means[-2:], wsum[-2:], counts[-2:] = [m2], [w2], [c2]
    return np.repeat(np.asarray(means), counts)


def _strictly_increasing(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    keep = np.concatenate([[True], np.diff(x) > 1e-6])
    return x[keep], y[keep]


def fit_height_map(pred: np.ndarray, ref: np.ndarray, method: CalibrationMethod = "isotonic",
                   knots: int = DEFAULT_KNOTS) -> tuple[np.ndarray, np.ndarray]:
    """Knots ``(x, y)`` of a monotone map from predicted to reference height (see the module docstring).

    Args:
        pred, ref: predicted and reference heights (metres) of the same valid pixels, 1-D.
        method: ``isotonic`` or ``quantile``.
        knots: number of equal-count bins / quantiles.
    """
    pred = np.asarray(pred, dtype=np.float64).ravel()
    ref = np.asarray(ref, dtype=np.float64).ravel()
    if pred.size < 2 * knots:
        knots = max(2, pred.size // 2)
    qs = np.linspace(0.0, 1.0, knots + 1)
    if method == "quantile":
        x = np.quantile(pred, qs)
        y = np.maximum.accumulate(np.quantile(ref, qs))
    elif method in ("isotonic", "median"):
        order = np.argsort(pred, kind="stable")
        ps, rs = pred[order], ref[order]
        edges = np.unique(np.round(qs * ps.size).astype(int))
        xs, ys, ws = [], [], []
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            if b > a:
                xs.append(ps[a:b].mean())
                ys.append(rs[a:b].mean() if method == "isotonic" else np.median(rs[a:b]))
                ws.append(b - a)
        x, y = np.asarray(xs), _pava(np.asarray(ys), np.asarray(ws, dtype=np.float64))
    else:
        raise ValueError(f"fit_height_map: method must be 'isotonic', 'median' or 'quantile', got {method!r}")
    x, y = _strictly_increasing(x, y)
    if x.size < 2:  # every prediction alike: a constant offset
        x = np.array([float(pred.min()), float(pred.min()) + 1.0])
        y = np.array([float(ref.mean()), float(ref.mean()) + 1.0])
    return x, y


def fit_spread(abs_error: np.ndarray, std: np.ndarray, max_pixels: int = 200_000) -> tuple[float, float]:
    """``(std_scale, std_floor)`` such that ``sqrt((scale·std)² + floor²)`` covers :data:`ONE_SIGMA` of the
    pixels at ±1 σ and comes closest to :data:`TWO_SIGMA` at ±2 σ (floors tried: quantiles of the error).
    """
    err = np.asarray(abs_error, dtype=np.float64).ravel()
    sd = np.asarray(std, dtype=np.float64).ravel()
    if err.size > max_pixels:
        keep = np.random.default_rng(0).choice(err.size, max_pixels, replace=False)
        err, sd = err[keep], sd[keep]
    if err.size == 0:
        return 1.0, 0.0

    def cover(scale: float, floor: float, k: float) -> float:
        return float(np.count_nonzero(err <= k * np.hypot(scale * sd, floor)) / err.size)

    best: tuple[float, float, float] | None = None
    for floor in [0.0, *np.quantile(err, np.linspace(0.02, 0.66, 33)).tolist()]:
        if cover(0.0, floor, 1.0) >= ONE_SIGMA:
            break
        lo, hi = 0.0, 1.0
        while cover(hi, floor, 1.0) < ONE_SIGMA and hi < 1e12:
            hi *= 4.0
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if cover(mid, floor, 1.0) < ONE_SIGMA else (lo, mid)
        miss = abs(cover(hi, floor, 2.0) - TWO_SIGMA)
        if best is None or miss < best[0]:
            best = (miss, hi, float(floor))
    if best is None:  # the smallest floor alone covers 68 %: a floor only
        return 0.0, float(np.quantile(err, ONE_SIGMA))
    return best[1], best[2]


def fit_std_scale(abs_error: np.ndarray, std: np.ndarray, coverage: float = ONE_SIGMA) -> float:
    """The factor ``s`` such that ``|error| ≤ s · std`` holds for ``coverage`` of the pixels."""
    std = np.asarray(std, dtype=np.float64).ravel()
    err = np.asarray(abs_error, dtype=np.float64).ravel()
    ok = std > 0
    if not ok.any():
        return 1.0
    s = float(np.quantile(err[ok] / std[ok], coverage))
    return s if math.isfinite(s) and s > 0 else 1.0


def fit_calibration(pred: np.ndarray, ref: np.ndarray, std: np.ndarray | None = None,
                    method: CalibrationMethod = "isotonic", knots: int = DEFAULT_KNOTS,
                    source: str = "") -> Calibration:
    """Fit the height map and (with ``std``) the spread factor on validation pixels (1-D arrays)."""
    x, y = fit_height_map(pred, ref, method, knots)
    cal = Calibration(tuple(float(v) for v in x), tuple(float(v) for v in y), 1.0, method, int(np.size(pred)), source)
    if std is not None:
        err = np.abs(cal.height(np.asarray(pred, dtype=np.float64)) - np.asarray(ref, dtype=np.float64))
        scale, floor = fit_spread(err, std)
        cal = Calibration(cal.height_x, cal.height_y, scale, method, cal.n_pixels, source, floor)
    return cal


def interval_coverage(abs_error: np.ndarray, std: np.ndarray) -> dict[str, float]:
    """Share of pixels within ±1 σ and ±2 σ (a calibrated Gaussian spread gives 0.683 and 0.954)."""
    n = max(1, np.size(abs_error))
    return {"within_1sigma": float(np.count_nonzero(abs_error <= std) / n),
            "within_2sigma": float(np.count_nonzero(abs_error <= 2 * std) / n)}


__all__ = ["Calibration", "CalibrationMethod", "fit_calibration", "fit_height_map", "fit_spread", "fit_std_scale",
           "interp_torch", "interval_coverage", "ONE_SIGMA"]
