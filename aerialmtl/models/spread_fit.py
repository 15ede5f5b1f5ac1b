"""A Gaussian spread against observed errors: fitting its factor and floor, scoring it (CRPS, NLL, coverage).

The spread of a pixel's height is ``σ = sqrt((scale · std)² + floor²)``: the MC-dropout (or learned) spread
``std`` times a factor, with a floor for pixels whose spread is ~0. :func:`fit_spread_crps` chooses the factor
and floor with the lowest mean Gaussian CRPS on a set of pixels (the calibration's fit, one per range of
predicted height: :func:`aerialmtl.models.calibration.fit_calibration`); :func:`fit_spread` the older fit to
±1σ/±2σ coverage. :func:`mean_crps` and :func:`mean_nll` score a spread (lower is better, both proper), and
:func:`interval_coverage` says how often the errors fall within ±1σ and ±2σ. Errors, spreads and scores are in
metres (the NLL in nats).
"""

from __future__ import annotations

import math

import numpy as np
import torch

#: Fraction of a Gaussian within ±1 σ and ±2 σ.
ONE_SIGMA = 0.6826894921370859
TWO_SIGMA = 0.9544997361036416


def _sampled_pairs(abs_error: np.ndarray, std: np.ndarray, max_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """``(|error|, std)`` as float64 1-D arrays, a seeded subsample of ``max_pixels`` pairs beyond that."""
    err = np.asarray(abs_error, dtype=np.float64).ravel()
    sd = np.asarray(std, dtype=np.float64).ravel()
    if err.size > max_pixels:
        keep = np.random.default_rng(0).choice(err.size, max_pixels, replace=False)
        err, sd = err[keep], sd[keep]
    return err, sd


def fit_spread(abs_error: np.ndarray, std: np.ndarray, max_pixels: int = 200_000) -> tuple[float, float]:
    """``(std_scale, std_floor)`` of the spread ``sqrt((scale·std)² + floor²)``.

    It covers :data:`ONE_SIGMA` of the pixels at ±1 σ and comes closest to :data:`TWO_SIGMA` at ±2 σ (floors
    tried: quantiles of the error).
    """
    err, sd = _sampled_pairs(abs_error, std, max_pixels)
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


def fit_spread_crps(abs_error: np.ndarray, std: np.ndarray, max_pixels: int = 50_000,
                    nll_bound: bool = False) -> tuple[float, float]:
    """``(scale, floor)`` of ``σ = sqrt((scale·std)² + floor²)`` with the lowest mean Gaussian CRPS on these pixels
    (with ``nll_bound``: among the spreads whose mean Gaussian NLL is no worse than the unscaled spread's).

    The CRPS is a proper score: its minimum is the spread that is right for these errors, and it grows with σ
    when σ is too wide, so a few pixels with a tiny MC spread cannot drive the factor to 1e7 (as matching a
    coverage can: the other pixels then get intervals of kilometres). A log-spaced grid of factors around
    ``median |error| / median std`` times floors at quantiles of the error, then a finer grid around the best.

    ``nll_bound``: the CRPS grows only linearly with a miss, so on ground pixels (errors of centimetres, a few of
    them trees the network missed, metres off) its optimum can be a spread of millimetres, and those few misses then
    lie hundreds of σ away. The calibration applies a spread map only if it lowers both the CRPS and the NLL
    (:func:`aerialmtl.models.calibration.fit_calibration`), so that optimum switched the whole map off: on
    ``autzen_west`` (3 seeds) the cross-fitted NLL went from 3.4–4.6 to 294–600 and every height range kept the
    raw MC spread. The calibration then fits again with the bound. ``scale`` 1 without a floor (the spread
    unchanged) always meets it.
    """
    err, sd = _sampled_pairs(abs_error, std, max_pixels)
    if err.size == 0:
        return 1.0, 0.0
    base = float(np.median(err)) / max(float(np.median(sd)), 1e-6)
    base = base if math.isfinite(base) and base > 0 else 1.0
    floors = [0.0, *np.quantile(err, (0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6)).tolist()]
    scores = _CrpsGrid(err, sd)
    best, limit = (math.inf, 1.0, 0.0), math.inf
    if nll_bound:  # the spread unchanged is the first candidate, and its NLL the bound
        crps_raw, limit = scores.scores(1.0, 0.0)
        best = (crps_raw, 1.0, 0.0)

    def consider(scale: float, floor: float) -> None:
        nonlocal best
        crps, nll = scores.scores(scale, floor) if nll_bound else (scores.mean(scale, floor), 0.0)
        if crps < best[0] and nll <= limit:
            best = (crps, scale, float(floor))

    for exps in (np.linspace(-4, 4, 17), None):
        if exps is None:  # refine around the best factor
            centre = math.log10(max(best[1], 1e-12) / base)
            exps = np.linspace(centre - 0.5, centre + 0.5, 11)
        for floor in floors:
            for e in exps:
                consider(base * 10.0 ** float(e), floor)
    # a floor alone (scale 0) where the spread carries nothing
    for floor in np.quantile(err, (0.2, 0.4, 0.6, 0.8)).tolist():
        consider(0.0, max(floor, 0.01))
    return best[1], best[2]


_SQRT2 = math.sqrt(2.0)
_TWO_PDF = 2.0 / math.sqrt(2.0 * math.pi)
_INV_SQRT_PI = 1.0 / math.sqrt(math.pi)


class _CrpsGrid:
    """The mean Gaussian CRPS of fixed errors under many spreads ``σ = hypot(scale·std, floor)`` (floored at 1 cm).

    The grid search of :func:`fit_spread_crps` scores ~230 spreads per height range on up to 50,000 pixels, and a
    calibration fits each range three to six times (all pixels, then each fold; again around the raw heights when
    the height map is off). With numpy each score was a dozen passes (``hypot``, scipy's scalar ``erf``, ``exp``,
    products) into new arrays, 2.2 ms per 50,000 pixels, and the fit took longer than the MC passes it follows
    (4.8 s of a checkpoint's 8.4 s on 2 AMD EPYC cores); here each is torch's vectorised float64 operations in
    place into three reused buffers (0.3 ms). Same formula as before; the scores agree to ~1e-15 relative.

    Args:
        err: absolute errors (metres, 1-D float64; not copied).
        std: the predicted spreads of the same pixels (metres, 1-D float64), for :meth:`mean`.
    """

    def __init__(self, err: np.ndarray, std: np.ndarray | None = None) -> None:
        self.err = torch.from_numpy(np.ascontiguousarray(err, np.float64))
        self.std = None if std is None else torch.from_numpy(np.ascontiguousarray(std, np.float64))
        self.sigma, self.z, self.term = (torch.empty_like(self.err) for _ in range(3))

    def _sigma(self, scale: float, floor: float) -> torch.Tensor:
        """``σ = hypot(scale·std, floor)`` into the reused buffer; ``scale`` 0: ``σ = floor`` everywhere."""
        if scale == 0.0:
            self.sigma.fill_(floor)
        else:
            assert self.std is not None, "a grid of spreads needs the predicted spreads"
            torch.mul(self.std, scale, out=self.sigma)
            torch.hypot(self.sigma, torch.tensor(floor, dtype=torch.float64), out=self.sigma)
        return self.sigma

    def mean(self, scale: float, floor: float) -> float:
        """Mean CRPS (metres) under ``σ = hypot(scale·std, floor)``; ``scale`` 0: ``σ = floor`` everywhere."""
        return self.mean_under(self._sigma(scale, floor))

    def scores(self, scale: float, floor: float) -> tuple[float, float]:
        """``(mean CRPS in metres, mean Gaussian NLL in nats)`` under ``σ = hypot(scale·std, floor)``, both with
        σ floored at 1 cm (as :func:`mean_crps` and :func:`mean_nll`).
        """
        sig = self._sigma(scale, floor)
        return self.mean_under(sig), self.nll_under(sig)

    def nll_under(self, sigma: torch.Tensor) -> float:
        """Mean Gaussian NLL (nats) under the spreads ``sigma`` (1-D float64, floored at 1 cm here, in place):
        ``log σ + ½·log 2π + ½·(error/σ)²``.
        """
        sig, z, t = sigma.clamp_min_(0.01), self.z, self.term
        torch.div(self.err, sig, out=z)
        torch.mul(z, z, out=z)
        torch.log(sig, out=t)
        return float(t.add_(z, alpha=0.5).mean()) + 0.5 * math.log(2.0 * math.pi)

    def mean_under(self, sigma: torch.Tensor) -> float:
        """Mean CRPS (metres) under the spreads ``sigma`` (1-D float64, floored at 1 cm here, in place).

        ``σ·(z·erf(z/√2) + 2·φ(z) − 1/√π)`` with ``z = |error|/σ`` (Gneiting & Raftery 2007).
        """
        sig, z, t = sigma.clamp_min_(0.01), self.z, self.term
        torch.div(self.err, sig, out=z)
        torch.div(z, _SQRT2, out=t)
        torch.special.erf(t, out=t)
        t.mul_(z)
        torch.mul(z, z, out=z)
        z.mul_(-0.5).exp_().mul_(_TWO_PDF)
        return float(t.add_(z).sub_(_INV_SQRT_PI).mul_(sig).mean())


def mean_crps(err: np.ndarray, sigma: np.ndarray) -> float:
    """Mean Gaussian CRPS (metres) of errors ``err`` under spreads ``sigma`` (floored at 1 cm)."""
    sig = torch.tensor(np.asarray(sigma, np.float64).ravel())
    return _CrpsGrid(np.asarray(err, np.float64).ravel()).mean_under(sig)


def mean_nll(err: np.ndarray, sigma: np.ndarray) -> float:
    """Mean Gaussian negative log-likelihood (nats) of errors ``err`` under spreads ``sigma`` (floored at 1 cm)."""
    sig = torch.tensor(np.asarray(sigma, np.float64).ravel())
    return _CrpsGrid(np.asarray(err, np.float64).ravel()).nll_under(sig)


def interval_coverage(abs_error: np.ndarray, std: np.ndarray) -> dict[str, float]:
    """Share of pixels within ±1 σ and ±2 σ (a calibrated Gaussian spread gives 0.683 and 0.954)."""
    n = max(1, np.size(abs_error))
    return {"within_1sigma": float(np.count_nonzero(abs_error <= std) / n),
            "within_2sigma": float(np.count_nonzero(abs_error <= 2 * std) / n)}



__all__ = ["ONE_SIGMA", "TWO_SIGMA", "fit_spread", "fit_spread_crps", "fit_std_scale", "interval_coverage", "mean_crps",
           "mean_nll"]
