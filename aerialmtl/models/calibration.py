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

* **spread**: one factor ``std_scale`` multiplying ``height_std`` such that ±1 σ covers 68.3 % of the
  validation pixels' calibrated errors (the 68.3 % quantile of ``|error| / std``), as a Gaussian would.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

CalibrationMethod = Literal["isotonic", "median", "quantile"]
#: Fraction of a Gaussian within ±1 σ.
ONE_SIGMA = 0.6826894921370859
DEFAULT_KNOTS = 64


@dataclass(frozen=True)
class Calibration:
    """A fitted height map and spread factor (saved in :class:`~aerialmtl.formats.checkpoint.ModelMeta`).

    Attributes:
        height_x: knots on the predicted height (metres, strictly increasing).
        height_y: calibrated heights at the knots (metres, non-decreasing).
        std_scale: factor applied to ``height_std`` (1 = unchanged).
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

    def __post_init__(self) -> None:
        if len(self.height_x) != len(self.height_y) or len(self.height_x) < 2:
            raise ValueError(f"Calibration: need ≥ 2 knots with as many x as y, got {len(self.height_x)} and "
                             f"{len(self.height_y)}")
        if any(b <= a for a, b in zip(self.height_x, self.height_x[1:], strict=False)):
            raise ValueError("Calibration: height_x must be strictly increasing")
        if not (math.isfinite(self.std_scale) and self.std_scale > 0):
            raise ValueError(f"Calibration: std_scale must be finite and > 0, got {self.std_scale}")

    def height(self, h: np.ndarray) -> np.ndarray:
        """Calibrated heights (metres) of predicted heights ``h`` (any shape; NaN stays NaN)."""
        x, y = np.asarray(self.height_x), np.asarray(self.height_y)
        out = np.interp(h, x, y)
        beyond = h > x[-1]
        out = np.where(beyond, y[-1] + (h - x[-1]), out)
        return np.maximum(out, 0.0).astype(np.asarray(h).dtype, copy=False)

    def std(self, s: np.ndarray) -> np.ndarray:
        """Calibrated spreads (metres)."""
        return (s * self.std_scale).astype(np.asarray(s).dtype, copy=False)

    def height_torch(self, h: torch.Tensor) -> torch.Tensor:
        """:meth:`height` on a tensor (any device, float dtype kept)."""
        x = torch.tensor(self.height_x, dtype=h.dtype, device=h.device)
        y = torch.tensor(self.height_y, dtype=h.dtype, device=h.device)
        return interp_torch(h, x, y).clamp_min_(0.0)

    def summary(self) -> str:
        pts = ", ".join(f"{a:.1f}→{b:.1f}" for a, b in zip(self.height_x[::max(1, len(self.height_x) // 6)],
                                                        self.height_y[::max(1, len(self.height_y) // 6)],
                                                        strict=False))
        return f"{self.method} height map ({pts} m), std × {self.std_scale:.2f}, {self.n_pixels} px"


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
        cal = Calibration(cal.height_x, cal.height_y, fit_std_scale(err, std), method, cal.n_pixels, source)
    return cal


def interval_coverage(abs_error: np.ndarray, std: np.ndarray) -> dict[str, float]:
    """Share of pixels within ±1 σ and ±2 σ (a calibrated Gaussian spread gives 0.683 and 0.954)."""
    n = max(1, np.size(abs_error))
    return {"within_1sigma": float(np.count_nonzero(abs_error <= std) / n),
            "within_2sigma": float(np.count_nonzero(abs_error <= 2 * std) / n)}


__all__ = ["Calibration", "CalibrationMethod", "fit_calibration", "fit_height_map", "fit_std_scale",
           "interp_torch", "interval_coverage", "ONE_SIGMA"]
