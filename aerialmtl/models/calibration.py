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

* **spread**: ``σ = sqrt((s_k · height_std)² + f_k²)`` with a factor ``s_k`` and a floor ``f_k`` per range
  ``k`` of the predicted height (:data:`SPREAD_EDGES`, ranges with too few validation pixels merged into
  their neighbour), each chosen for the lowest Gaussian CRPS of that range's validation pixels
  (:func:`~aerialmtl.models.spread_fit.fit_spread_crps`): the spread holds per height range, not only on
  average (one factor for all heights, fitted to a coverage, made ground ~0 m and roofs hundreds of metres
  wide). The floor matters: where the decoder's features are all zero, every MC sample gives the same height
  and the MC spread is ~0, which no factor can turn into an interval. (Checkpoints calibrated before this
  release hold one factor and floor fitted to ±1σ/±2σ coverage, :func:`~aerialmtl.models.spread_fit.fit_spread`;
  they are applied as they are.)

**Never worse than none** (:func:`fit_calibration` with ``folds``): each part is applied only if it is
better on validation pixels it was not fitted on (two folds of the validation patches, each fitted on the
other): the height map only if it lowers the MAE, the spread map only if it lowers both the CRPS and the
Gaussian NLL (proper scores of the spread: the CRPS alone accepts a few confident misses that the NLL
does not). A spread map refused on that check is fitted once more with each range kept within the raw
spread's NLL (:func:`~aerialmtl.models.spread_fit.fit_spread_crps`'s ``nll_bound``) and checked again. A part
that is not applied is the identity, and the checkpoint records why (:attr:`Calibration.notes`).

**Only where validation saw heights** (:func:`support_limit`): a calibration corrects a height only where
validation holds at least :data:`MIN_SUPPORT_PIXELS` pixels at or above it (reference height). From the
lowest edge of :data:`SPREAD_EDGES` that fewer validation pixels reach (the *limit*, :attr:`Calibration.height_limit`)
upwards, heights and spreads pass unchanged: the height map is cut there (its calibrated heights stay below
the limit and meet the identity at it) and the spread ranges above it keep factor 1 and no floor. And a
spread map is applied only if validation holds that many pixels ≥ :data:`TALL_HEIGHT` (above the ground):
a spread fitted on ground alone (errors of centimetres) shrinks every building's and tree's interval with it.
Without this, a validation split of bare ground (it happens on a small area) fitted "everything is ground":
heights above its highest prediction shifted down by a metre and spreads scaled by 0.09 everywhere.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from aerialmtl.models.spread_fit import fit_spread_crps, mean_crps, mean_nll

CalibrationMethod = Literal["isotonic", "median", "quantile"]
DEFAULT_KNOTS = 64
#: Inner edges (metres of predicted height) of the ranges whose spread is fitted alone.
SPREAD_EDGES: tuple[float, ...] = (1.0, 2.0, 5.0, 10.0, 20.0)
#: Fewest validation pixels a range needs to be fitted alone (else it joins the range above it; the top range
#: joins the one below).
MIN_RANGE_PIXELS = 2000
#: Fewest validation pixels at or above a height (reference, metres) for the calibration to correct that height
#: (:func:`support_limit`); about a thousand square metres at 1 m, a handful of buildings or trees.
MIN_SUPPORT_PIXELS = 1000
#: Metres from which a pixel stands above the ground (a building, a tree): a spread map needs
#: :data:`MIN_SUPPORT_PIXELS` validation pixels this tall, and ``tile`` warns when validation or test holds none.
TALL_HEIGHT = 2.0


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
        height_applied: the height map is applied (``False``: it did not lower the cross-fitted
            validation MAE, and heights pass unchanged).
        spread_applied: the spread map is applied (``False``: it did not lower the cross-fitted CRPS).
        std_edges: inner edges (metres of predicted height) of the spread ranges; empty = one range with
            ``std_scale``/``std_floor`` (older calibrations).
        std_scales, std_floors: factor and floor per range (``len(std_edges) + 1`` each).
        notes: what the validation said of each part (cross-fitted scores, why a part is off).
        height_limit: predicted heights (metres) from which nothing is calibrated, because fewer than
            :data:`MIN_SUPPORT_PIXELS` validation pixels reach it (:func:`support_limit`); ``None``: no limit.
        unsupported: what validation held too few pixels to calibrate, one phrase (also in ``notes``;
            ``train`` prints it on a line of its own); empty when it held enough at every height.
    """

    height_x: tuple[float, ...]
    height_y: tuple[float, ...]
    std_scale: float = 1.0
    method: str = "isotonic"
    n_pixels: int = 0
    source: str = ""
    std_floor: float = 0.0
    height_applied: bool = True
    spread_applied: bool = True
    std_edges: tuple[float, ...] = ()
    std_scales: tuple[float, ...] = ()
    std_floors: tuple[float, ...] = ()
    notes: str = ""
    height_limit: float | None = None
    unsupported: str = ""

    def __post_init__(self) -> None:
        if len(self.height_x) != len(self.height_y) or len(self.height_x) < 2:
            raise ValueError(f"Calibration: need ≥ 2 knots with as many x as y, got {len(self.height_x)} and "
                             f"{len(self.height_y)}")
        if not all(math.isfinite(v) for v in (*self.height_x, *self.height_y, *self.std_edges)):
            raise ValueError("Calibration: height_x, height_y and std_edges must be finite numbers of metres")
        if any(b <= a for a, b in zip(self.height_x, self.height_x[1:], strict=False)):
            raise ValueError("Calibration: height_x must be strictly increasing")
        if any(b < a for a, b in zip(self.height_y, self.height_y[1:], strict=False)):
            raise ValueError("Calibration: height_y must be non-decreasing (a height map keeps the order of heights)")
        if any(b <= a for a, b in zip(self.std_edges, self.std_edges[1:], strict=False)):
            raise ValueError(f"Calibration: std_edges must be strictly increasing, got {list(self.std_edges)}")
        if not (math.isfinite(self.std_scale) and self.std_scale >= 0):
            raise ValueError(f"Calibration: std_scale must be finite and ≥ 0, got {self.std_scale}")
        if not (math.isfinite(self.std_floor) and self.std_floor >= 0):
            raise ValueError(f"Calibration: std_floor must be finite and ≥ 0, got {self.std_floor}")
        if self.std_edges and not (len(self.std_scales) == len(self.std_floors) == len(self.std_edges) + 1):
            raise ValueError("Calibration: std_scales and std_floors need one value per range (len(std_edges) + 1)")
        if any(not (math.isfinite(v) and v >= 0) for v in (*self.std_scales, *self.std_floors)):
            raise ValueError("Calibration: std_scales and std_floors must be finite and ≥ 0")
        if self.height_limit is not None and not (math.isfinite(self.height_limit) and self.height_limit > 0):
            raise ValueError(f"Calibration: height_limit must be None or a positive number of metres, got "
                             f"{self.height_limit}")

    def height(self, h: np.ndarray) -> np.ndarray:
        """Calibrated heights (metres) of predicted heights ``h`` (any shape; NaN stays NaN)."""
        if not self.height_applied:
            return np.asarray(h)
        x, y = np.asarray(self.height_x), np.asarray(self.height_y)
        out = np.interp(h, x, y)
        beyond = h > x[-1]
        out = np.where(beyond, y[-1] + (h - x[-1]), out)
        result: np.ndarray = np.maximum(out, 0.0).astype(np.asarray(h).dtype, copy=False)
        return result

    def _range_values(self) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        if self.std_edges:
            return self.std_edges, self.std_scales, self.std_floors
        return (), (self.std_scale,), (self.std_floor,)

    def std(self, s: np.ndarray, h: np.ndarray | None = None) -> np.ndarray:
        """Calibrated spreads (metres): ``sqrt((s_k · s)² + f_k²)``.

        ``k`` is the range of the predicted (uncalibrated) height ``h`` (same shape; needed when the spread is
        fitted per range).
        """
        s_arr = np.asarray(s)
        if not self.spread_applied:
            return s_arr
        edges, scales, floors = self._range_values()
        if edges:
            if h is None:
                raise ValueError("Calibration.std: this calibration is fitted per height range; pass the heights")
            k = np.searchsorted(np.asarray(edges), np.asarray(h, np.float64), side="right")
            sc: np.ndarray | float = np.asarray(scales)[k]
            fl: np.ndarray | float = np.asarray(floors)[k]
        else:
            sc, fl = scales[0], floors[0]
        out = np.hypot(np.asarray(s, dtype=np.float64) * sc, fl)
        return out.astype(s_arr.dtype, copy=False)

    def std_torch(self, s: torch.Tensor, h: torch.Tensor | None = None) -> torch.Tensor:
        """:meth:`std` on tensors (``h``: the predicted, uncalibrated heights)."""
        if not self.spread_applied:
            return s
        edges, scales, floors = self._range_values()
        if edges:
            if h is None:
                raise ValueError("Calibration.std_torch: this calibration is fitted per height range; pass the heights")
            k = torch.bucketize(h.contiguous(), torch.tensor(edges, dtype=h.dtype, device=h.device), right=True)
            sc = torch.tensor(scales, dtype=s.dtype, device=s.device)[k]
            fl = torch.tensor(floors, dtype=s.dtype, device=s.device)[k]
            return torch.hypot(s * sc, fl)
        return torch.hypot(s * scales[0], torch.full_like(s, floors[0]))

    def height_torch(self, h: torch.Tensor) -> torch.Tensor:
        """:meth:`height` on a tensor (any device, float dtype kept)."""
        if not self.height_applied:
            return h
        x = torch.tensor(self.height_x, dtype=h.dtype, device=h.device)
        y = torch.tensor(self.height_y, dtype=h.dtype, device=h.device)
        return interp_torch(h, x, y).clamp_min_(0.0)

    def summary(self) -> str:
        """One line: what is applied, fitted on how many pixels."""
        pts = ", ".join(f"{a:.1f}→{b:.1f}" for a, b in zip(self.height_x[::max(1, len(self.height_x) // 6)],
                                                        self.height_y[::max(1, len(self.height_y) // 6)],
                                                        strict=False))
        height = f"{self.method} height map ({pts} m)" if self.height_applied else "heights unchanged"
        edges, scales, floors = self._range_values()
        spread = ("spread " + ", ".join(f"×{a:.3g}⊕{b:.2f} m" for a, b in zip(scales, floors, strict=True))
                  + (f" by predicted height (edges {', '.join(f'{e:g}' for e in edges)} m)" if edges else "")
                  if self.spread_applied else "spread unchanged")
        return f"{height}, {spread}, {self.n_pixels} px" + (f"; {self.notes}" if self.notes else "")


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


def spread_ranges(pred: np.ndarray, edges: tuple[float, ...] = SPREAD_EDGES,
                  min_pixels: int = MIN_RANGE_PIXELS) -> tuple[float, ...]:
    """The inner edges of :data:`SPREAD_EDGES` kept for ``pred`` (metres).

    A range with fewer than
    ``min_pixels`` predicted heights loses its upper edge (it joins the range above it); a top range that is
    too small loses its lower edge (it joins the range below).
    """
    kept: list[float] = []
    pred = np.asarray(pred, np.float64)
    lo = -np.inf
    for e in (*edges, np.inf):
        n = int(np.count_nonzero((pred >= lo) & (pred < e)))
        if n >= min_pixels and e != np.inf:
            kept.append(float(e))
            lo = e
        elif e == np.inf and n < min_pixels and kept:  # the top range is too small: join it below
            kept.pop()
    return tuple(kept)


def _fit_spread_ranges(err: np.ndarray, std: np.ndarray, pred: np.ndarray, edges: tuple[float, ...],
                       limit: float | None = None,
                       nll_bound: bool = False) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Factor and floor per range of ``edges``; a range from ``limit`` up keeps factor 1 and no floor."""
    k = np.searchsorted(np.asarray(edges), pred, side="right")
    scales, floors = [], []
    for r in range(len(edges) + 1):
        sel = k == r
        above = limit is not None and r > 0 and edges[r - 1] >= limit
        a, b = fit_spread_crps(err[sel], std[sel], nll_bound=nll_bound) if sel.any() and not above else (1.0, 0.0)
        scales.append(float(a))
        floors.append(float(b))
    return tuple(scales), tuple(floors)


def support_limit(ref: np.ndarray, min_pixels: int = MIN_SUPPORT_PIXELS,
                  edges: tuple[float, ...] = SPREAD_EDGES) -> float | None:
    """The lowest of ``edges`` (metres) that fewer than ``min_pixels`` reference heights ``ref`` reach (≥).

    From that height up a calibration fitted on them corrects nothing; ``None`` when every edge is reached that
    often.
    """
    ref = np.asarray(ref, np.float64)
    for e in edges:
        if int(np.count_nonzero(ref >= e)) < min_pixels:
            return float(e)
    return None


def _cut_height_map(x: np.ndarray, y: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """Knots of the map below ``limit`` with their heights capped at it, then ``(limit, limit)``.

    From the limit up the map is the identity (slope 1, no offset), and it stays continuous and non-decreasing.
    """
    keep = x < limit
    xs, ys = np.append(x[keep], limit), np.append(np.minimum(y[keep], limit), limit)
    if xs.size < 2:  # no knot below the limit: the identity
        xs, ys = np.array([0.0, limit]), np.array([0.0, limit])
    return xs, ys


def _fit_parts(pred: np.ndarray, ref: np.ndarray, std: np.ndarray | None, method: CalibrationMethod, knots: int,
               edges: tuple[float, ...], height: bool = True, limit: float | None = None,
               nll_bound: bool = False) -> Calibration:
    """The height map and the per-range spread map fitted around it, both cut at ``limit``.

    The height map is the identity unless ``height``. ``limit`` is in metres of predicted height; ``edges``
    must then hold it. ``nll_bound``: each range's spread within the raw spread's NLL
    (:func:`~aerialmtl.models.spread_fit.fit_spread_crps`).
    """
    x, y = fit_height_map(pred, ref, method, knots)
    if limit is not None:
        x, y = _cut_height_map(x, y, limit)
    cal = Calibration(tuple(float(v) for v in x), tuple(float(v) for v in y), 1.0, method, int(np.size(pred)),
                      height_applied=height, height_limit=limit)
    if std is None:
        return dataclasses.replace(cal, spread_applied=False)
    err = np.abs(cal.height(pred) - ref)
    scales, floors = _fit_spread_ranges(err, std, pred, edges, limit, nll_bound)
    if not edges:
        return dataclasses.replace(cal, std_scale=scales[0], std_floor=floors[0])
    return dataclasses.replace(cal, std_edges=edges, std_scales=scales, std_floors=floors)


def _cross_fitted_spread_scores(pred: np.ndarray, ref: np.ndarray, sd: np.ndarray,
                                fitted: list[tuple[np.ndarray, Calibration]]) -> tuple[float, float, float, float]:
    """``(CRPS raw, CRPS calibrated, NLL raw, NLL calibrated)`` over all pixels, each fold's calibration scored on
    the pixels it was not fitted on (``fitted``: ``(scored pixels mask, calibration)`` per fold), around the heights
    that calibration gives.
    """
    crps_raw = crps_cal = nll_raw = nll_cal = 0.0
    for score, c in fitted:
        err = np.abs(c.height(pred[score]) - ref[score])
        w = float(score.sum()) / pred.size
        sigma = c.std(sd[score], pred[score])
        crps_raw += w * mean_crps(err, sd[score])
        crps_cal += w * mean_crps(err, sigma)
        nll_raw += w * mean_nll(err, sd[score])
        nll_cal += w * mean_nll(err, sigma)
    return crps_raw, crps_cal, nll_raw, nll_cal


def fit_calibration(pred: np.ndarray, ref: np.ndarray, std: np.ndarray | None = None,
                    method: CalibrationMethod = "isotonic", knots: int = DEFAULT_KNOTS,
                    source: str = "", folds: np.ndarray | None = None,
                    edges: tuple[float, ...] | None = None) -> Calibration:
    """Fit the height map and (with ``std``) the per-range spread map on validation pixels (1-D arrays, metres).

    Args:
        pred, ref, std: predicted height, reference height and predicted spread of the same pixels.
        method, knots: the height map (:func:`fit_height_map`).
        source: recorded in the result.
        folds: one label (0 or 1) per pixel, e.g. by validation patch: each part is then kept only if,
            fitted on one fold and scored on the other (both ways), it beats no calibration — the height
            map on MAE, the spread map on CRPS (see the module docstring). ``None``: both parts applied.
        edges: inner edges of the spread ranges (default: :func:`spread_ranges` of ``pred``).

    Heights from :func:`support_limit` of ``ref`` up keep no calibration, and the spread map is fitted only if
    :data:`MIN_SUPPORT_PIXELS` reference heights reach :data:`TALL_HEIGHT` (see the module docstring); the notes
    say so.
    """
    pred = np.asarray(pred, np.float64).ravel()
    ref = np.asarray(ref, np.float64).ravel()
    sd = None if std is None else np.asarray(std, np.float64).ravel()
    if edges is None:
        edges = spread_ranges(pred)
    support: list[str] = []
    if ref.size < MIN_SUPPORT_PIXELS:
        note = (f"validation holds {ref.size} px, fewer than {MIN_SUPPORT_PIXELS}: no calibration (height map and "
                "spread map off)")
        return Calibration((0.0, 1.0), (0.0, 1.0), 1.0, method, int(ref.size), source, height_applied=False,
                           spread_applied=False, notes=note, unsupported=note)
    limit = support_limit(ref)
    if limit is not None:
        edges = tuple(sorted({e for e in edges if e < limit} | {limit}))
        support.append(f"validation holds {int(np.count_nonzero(ref >= limit))} px ≥ {limit:g} m, fewer than "
                       f"{MIN_SUPPORT_PIXELS}: heights ≥ {limit:g} m keep no calibration")
    n_tall = int(np.count_nonzero(ref >= TALL_HEIGHT))
    if sd is not None and n_tall < MIN_SUPPORT_PIXELS:
        sd = None
        support.append(f"validation holds {n_tall} px ≥ {TALL_HEIGHT:g} m, fewer than {MIN_SUPPORT_PIXELS}: "
                       "spread map off (it would be fitted on the ground alone)")
    cal = dataclasses.replace(_fit_parts(pred, ref, sd, method, knots, edges, limit=limit), source=source,
                              unsupported="; ".join(support))
    if folds is None:
        return dataclasses.replace(cal, notes="; ".join(support))
    folds = np.asarray(folds).ravel()
    parts = [folds == 0, folds == 1]
    if not (parts[0].any() and parts[1].any()):
        return dataclasses.replace(cal, notes="; ".join(["one validation fold: both parts applied unchecked",
                                                         *support]))
    n = pred.size
    fitted = [(score, _fit_parts(pred[fit], ref[fit], None if sd is None else sd[fit], method, knots, edges,
                                 limit=limit))
              for fit, score in (parts, parts[::-1])]
    mae_raw = float(np.abs(pred - ref).mean())
    mae_cal = sum(float(np.abs(c.height(pred[score]) - ref[score]).sum()) for score, c in fitted) / n
    height_ok = mae_cal < mae_raw
    notes = [f"validation MAE {mae_raw:.3f} m raw, {mae_cal:.3f} m with the height map (cross-fitted)"
             + ("" if height_ok else ": height map off"), *support]
    spread_ok = False
    if sd is not None:
        for bound in (False, True):  # the CRPS's own optimum; where the check refuses it, within the raw NLL
            if bound or not height_ok:  # (the spread is fitted and judged around the heights the user will get)
                cal = dataclasses.replace(_fit_parts(pred, ref, sd, method, knots, edges, height=height_ok,
                                                     limit=limit, nll_bound=bound),
                                          source=source, unsupported="; ".join(support))
                fitted = [(score, _fit_parts(pred[fit], ref[fit], sd[fit], method, knots, edges, height=height_ok,
                                             limit=limit, nll_bound=bound))
                          for fit, score in (parts, parts[::-1])]
            crps_raw, crps_cal, nll_raw, nll_cal = _cross_fitted_spread_scores(pred, ref, sd, fitted)
            spread_ok = crps_cal < crps_raw and nll_cal < nll_raw
            which = "the spread map fitted within the raw spread's NLL per height range" if bound else "the spread map"
            verdict = "" if spread_ok else (": spread map off" if bound else ": fitted again within the raw spread's "
                                            "NLL per height range")
            notes.append(f"validation CRPS {crps_raw:.3f} → {crps_cal:.3f} m, Gaussian NLL {nll_raw:.3g} → "
                         f"{nll_cal:.3g} with {which} (cross-fitted){verdict}")
            if spread_ok:
                break
    return dataclasses.replace(cal, height_applied=height_ok, spread_applied=spread_ok, notes="; ".join(notes))


__all__ = ["MIN_RANGE_PIXELS", "MIN_SUPPORT_PIXELS", "SPREAD_EDGES", "TALL_HEIGHT", "Calibration",
           "CalibrationMethod", "fit_calibration", "fit_height_map", "interp_torch", "spread_ranges", "support_limit"]
