"""How shadow-like pixels look: a fixed score (darkness + blueness) and a per-area learnt probability.

Shadows are lit by the sky only: darker than their surroundings and bluer than sunlit ground. The fixed
:func:`shadow_score` needs no fit (it is what :func:`aerialmtl.sun.fit_sun` correlates with cast shadows);
:class:`ShadowModel` learns ``P(shadow | colour)`` on an area whose heights are known, so that water or dark
roofs that the heights say are lit are not called shadows.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, optimize

from aerialmtl.errors import InputError
from aerialmtl.sun._patches import ArrayOrList, as_patches
from aerialmtl.sun.cast import cast_shadow_mask
from aerialmtl.sun.position import Sun

#: Added to the channel sum before chromaticities (0–1 scale per channel), so black pixels get no colour.
_EPS = 0.05


def unit_rgb(rgb: np.ndarray) -> np.ndarray:
    """float32 (3, H, W) in 0–1 from uint8/uint16 (divided by the dtype's maximum) or float (taken as 0–1)."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[0] != 3:
        raise InputError(f"‹rgb› must be a (3, H, W) image, got shape {a.shape}")
    if np.issubdtype(a.dtype, np.integer):
        return (a.astype(np.float32) / np.float32(np.iinfo(a.dtype).max)).astype(np.float32)
    return a.astype(np.float32, copy=False)


def shadow_score(rgb: np.ndarray) -> np.ndarray:
    """Darkness plus blueness of each pixel.

    Args:
        rgb: (3, H, W) uint8 (or uint16), or float in 0–1.

    Returns:
        float32 (H, W): ``(1 − mean(R, G, B)) + (B − R) / (R + G + B + 0.05)``, higher = more shadow-like
        (roughly −1 … 2; only its order and correlation matter).
    """
    x = unit_rgb(rgb)
    total = x.sum(0)
    score = (np.float32(1.0) - total / np.float32(3.0)) + (x[2] - x[0]) / (total + np.float32(_EPS))
    result: np.ndarray = score.astype(np.float32)
    return result


def colour_features(rgb: np.ndarray, gsd_m: float, context_m: float) -> np.ndarray:
    """float32 (6, H, W) features of :class:`ShadowModel`: log-brightness L, blue and red chromaticity, L minus
    its mean over ``context_m`` metres (darker than the surroundings), L², L × blue chromaticity.
    """
    x = unit_rgb(rgb)
    total = x.sum(0) + np.float32(_EPS)
    lum = np.log(x.mean(0) + np.float32(0.02))
    cb = x[2] / total - np.float32(1 / 3)
    cr = x[0] / total - np.float32(1 / 3)
    size = max(3, int(round(context_m / gsd_m)) | 1)
    local = lum - ndimage.uniform_filter(lum, size=size, mode="reflect")
    return np.stack([lum, cb, cr, local, lum * lum, lum * cb]).astype(np.float32)


@dataclass
class ShadowModel:
    """``P(shadow | colour)`` for one area: logistic regression on :func:`colour_features`, fitted against the
    cast shadows of the area's reference heights at its sun (labels, not a threshold).

    Attributes:
        gsd_m: pixel size the model was fitted at (the context window is in metres).
        context_m: side of the neighbourhood the brightness is compared with, metres.
        mean, scale: per-feature standardisation (6 values each).
        weights: 7 logistic weights (intercept first); empty before :meth:`fit`.
        shadow_share: share of the fitted pixels in cast shadow.
    """

    gsd_m: float = 0.0
    context_m: float = 12.0
    mean: list[float] = field(default_factory=list)
    scale: list[float] = field(default_factory=list)
    weights: list[float] = field(default_factory=list)
    shadow_share: float = 0.0

    #: pixels used for the fit at most (a fixed-seed random subset beyond)
    MAX_PIXELS = 300_000

    def fit(self, rgb: ArrayOrList, height: ArrayOrList, gsd_m: float, sun: Sun,
            valid: ArrayOrList | None = None, l2: float = 1e-3) -> ShadowModel:
        """Fit on one patch or a list of patches (see :func:`aerialmtl.sun.fit_sun` for the forms).

        Args:
            rgb: (3, H, W) image(s); height: float (H, W) reference heights above ground in metres (NaN invalid).
            gsd_m: pixel size in metres. sun: the area's sun. valid: optional bool (H, W) mask(s).
            l2: ridge penalty on the standardised weights.

        Returns:
            self.

        Raises:
            InputError: no valid pixels, or the heights cast no shadow (or nothing but shadow) at ``sun``.
        """
        self.gsd_m = float(gsd_m)
        feats, labels = [], []
        for im, h, ok in as_patches(rgb, height, valid):
            mask = cast_shadow_mask(h, gsd_m, sun)
            f = colour_features(im, gsd_m, self.context_m)
            feats.append(f[:, ok])
            labels.append(mask[ok])
        x = np.concatenate(feats, axis=1).T.astype(np.float64)
        y = np.concatenate(labels).astype(np.float64)
        if len(y) == 0:
            raise InputError("‹valid› leaves no pixel to fit the shadow model on")
        if len(y) > self.MAX_PIXELS:
            pick = np.random.default_rng(0).choice(len(y), self.MAX_PIXELS, replace=False)
            x, y = x[pick], y[pick]
        self.shadow_share = float(y.mean())
        if not 0.0 < self.shadow_share < 1.0:
            raise InputError(f"the heights cast {'no' if self.shadow_share == 0 else 'only'} shadow at the sun "
                             f"({sun}): nothing to learn what a shadow looks like from")
        mean, scale = x.mean(0), x.std(0) + 1e-6
        self.mean, self.scale = mean.tolist(), scale.tolist()
        self.weights = _logistic((x - mean) / scale, y, l2).tolist()
        return self

    def predict_proba(self, rgb: np.ndarray, gsd_m: float | None = None) -> np.ndarray:
        """float32 (H, W) probability of shadow, 0–1, of a (3, H, W) image at ``gsd_m`` (default: the fit's)."""
        if not self.weights:
            raise InputError("this ShadowModel is not fitted: call fit() first")
        f = colour_features(rgb, gsd_m or self.gsd_m, self.context_m).astype(np.float64)
        w = np.asarray(self.weights)
        z = w[0] + np.tensordot(w[1:] / np.asarray(self.scale), f - np.asarray(self.mean)[:, None, None], axes=1)
        out: np.ndarray = (1.0 / (1.0 + np.exp(-np.clip(z, -40, 40)))).astype(np.float32)
        return out

    def to_dict(self) -> dict[str, object]:
        """Plain JSON/YAML types (floats and lists of floats)."""
        return {"gsd_m": self.gsd_m, "context_m": self.context_m, "mean": list(self.mean),
                "scale": list(self.scale), "weights": list(self.weights), "shadow_share": self.shadow_share}

    @classmethod
    def from_dict(cls, d: Mapping[str, object]) -> ShadowModel:
        """Inverse of :meth:`to_dict`."""
        try:
            m = cls(gsd_m=float(d["gsd_m"]), context_m=float(d["context_m"]),  # type: ignore[arg-type]
                    mean=[float(v) for v in d["mean"]], scale=[float(v) for v in d["scale"]],  # type: ignore[attr-defined]
                    weights=[float(v) for v in d["weights"]],  # type: ignore[attr-defined]
                    shadow_share=float(d["shadow_share"]))  # type: ignore[arg-type]
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"not a shadow model record ({exc!r}); keys {sorted(d)}") from exc
        if m.weights and not (len(m.weights) == len(m.mean) + 1 == len(m.scale) + 1):
            raise InputError(f"shadow model record: {len(m.weights)} weights for {len(m.mean)} features")
        return m


def _logistic(x: np.ndarray, y: np.ndarray, l2: float) -> np.ndarray:
    """Weights (intercept first) of an L2-penalised logistic regression (L-BFGS on the mean log-loss);
    x (n, k) standardised features, y (n,) 0/1.
    """
    n, k = x.shape
    a = np.hstack([np.ones((n, 1)), x])
    pen = np.full(k + 1, l2)
    pen[0] = 0.0

    def loss(w: np.ndarray) -> tuple[float, np.ndarray]:
        z = a @ w
        # log(1 + e^z) − y·z, computed stably
        value = float(np.mean(np.logaddexp(0.0, z) - y * z) + 0.5 * np.sum(pen * w * w))
        p = 0.5 * (1.0 + np.tanh(0.5 * z))
        grad = a.T @ (p - y) / n + pen * w
        return value, grad

    w0 = np.zeros(k + 1)
    w0[0] = np.log(y.mean() / (1 - y.mean()))
    res = optimize.minimize(loss, w0, jac=True, method="L-BFGS-B", options={"maxiter": 500})
    weights: np.ndarray = res.x
    return weights
