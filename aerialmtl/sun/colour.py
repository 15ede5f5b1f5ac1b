"""How shadow-like pixels look: a fixed score (darkness + blueness) and a per-area learnt probability.

Shadows are lit by the sky only: darker than their surroundings and bluer than sunlit ground. The fixed
:func:`shadow_score` needs no fit (it is what :func:`aerialmtl.sun.fit_sun` correlates with cast shadows);
:class:`ShadowModel` learns ``P(shadow | colour)`` on an area whose heights are known, so that water or dark
roofs that the heights say are lit are not called shadows.
"""

from __future__ import annotations

from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, optimize

from aerialmtl.errors import InputError
from aerialmtl.sun import kernels
from aerialmtl.sun._patches import ArrayOrList, Patch, as_patches
from aerialmtl.sun.cast import cast_shadow_mask
from aerialmtl.sun.heights import shadow_heights
from aerialmtl.sun.position import Sun, as_float, as_floats
from aerialmtl.sun.record import SHADOW_FEATURES, SHADOW_WEIGHTS, shadow_model_problem

#: Added to the channel sum before chromaticities (0–1 scale per channel), so black pixels get no colour.
_EPS = 0.05


def unit_rgb(rgb: np.ndarray, scale: str | np.dtype | None = None) -> np.ndarray:
    """float32 (3, H, W) in 0–1 from uint8/uint16 (divided by the dtype's maximum) or float (taken as 0–1).

    ``scale``: the type whose values ``rgb`` holds, when not its own (values of a uint8 area held in a uint16 or
    float array: divided by 255); a float type takes them as they are.
    """
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[0] != 3:
        raise InputError(f"'rgb' must be a (3, H, W) image, got shape {a.shape}")
    kind = a.dtype if scale is None else np.dtype(scale)
    out: np.ndarray
    if np.issubdtype(kind, np.integer):
        out = (a.astype(np.float32) / np.float32(np.iinfo(kind).max)).astype(np.float32)
    else:
        out = a.astype(np.float32, copy=False)
    return out


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


#: Neighbourhoods (metres) the brightness is compared with: its mean over each (darker than the surroundings)
#: and, for the first two, its maximum (darker than the lit edge next to it).
MEAN_CONTEXTS_M = (2.0, 6.0, 12.0, 40.0)
PEAK_CONTEXTS_M = (2.0, 6.0)
#: Name of the feature set below, stored with a model so that a model of another set is refused.
FEATURES = SHADOW_FEATURES
N_FEATURES = 6 + len(MEAN_CONTEXTS_M) + len(PEAK_CONTEXTS_M)
if N_FEATURES + 1 != SHADOW_WEIGHTS:  # the record's check (aerialmtl.sun.record) counts the same weights
    raise ImportError(f"aerialmtl.sun.record.SHADOW_WEIGHTS is {SHADOW_WEIGHTS}, the features need {N_FEATURES + 1}")
#: Measured objects needed to choose the threshold from heights.
MIN_CALIBRATION_OBJECTS = 10


def _window(metres: float, gsd_m: float) -> int:
    return max(3, int(round(metres / gsd_m)) | 1)


def colour_features(rgb: np.ndarray, gsd_m: float, valid: np.ndarray | None = None) -> np.ndarray:
    """float32 (12, H, W) features of :class:`ShadowModel`.

    Log-brightness L, blue and red chromaticity, saturation, L², L × blue chromaticity, L minus its mean over
    each of :data:`MEAN_CONTEXTS_M` and L minus its maximum over each of :data:`PEAK_CONTEXTS_M` (windows in
    metres, so ``gsd_m`` matters). :meth:`ShadowModel.predict_proba` computes the same planes by bands of rows.

    Pixels that are not data (``valid`` False where given, a colour that is NaN or ±inf, or a brightness that is
    none) take no part in any neighbourhood (:func:`usable_pixels`): their features are NaN, and the others' are
    those of their valid neighbours only.
    """
    x = unit_rgb(rgb)
    lum = _brightness(x)
    ok = usable_pixels(x, lum, valid)
    if ok is not None:
        x, lum = _filled(x, lum, ok)
    planes = np.stack(_planes(x, lum, [_local(lum, job, gsd_m, ok) for job in _CONTEXTS]))
    if ok is not None:
        planes[:, ~ok] = np.nan
    return planes


def usable_pixels(x: np.ndarray, lum: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray | None:
    """The pixels of unit RGB ``x`` (3, h, w) with brightness ``lum`` (h, w) whose colour the classifier can use,
    bool (h, w): ``valid`` (where given), every band finite and the brightness finite (a negative float
    value has none); ``None`` when that is every pixel (the filters then run as they always did, to the bit).
    """
    ok: np.ndarray = np.isfinite(lum)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    if ok.all():
        return None
    ok &= np.isfinite(x).all(0)
    return ok


def _filled(x: np.ndarray, lum: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``x`` and ``lum`` with every pixel outside ``ok`` set to 0 (finite: nothing NaN enters a filter or a kernel;
    the neighbourhood filters leave them out, :func:`_local`).
    """
    return (np.ascontiguousarray(np.where(ok, x, np.float32(0.0)), dtype=np.float32),
            np.where(ok, lum, np.float32(0.0)).astype(np.float32))


#: The neighbourhood filters of the context features, in feature order: (kind, window in metres).
_CONTEXTS = [("mean", m) for m in MEAN_CONTEXTS_M] + [("peak", m) for m in PEAK_CONTEXTS_M]


def _brightness(x: np.ndarray) -> np.ndarray:
    """Log-brightness L, float32 (h, w), of unit RGB ``x`` (3, h, w)."""
    lum: np.ndarray = np.log(x.mean(0) + np.float32(0.02))
    return lum


def _local(lum: np.ndarray, job: tuple[str, float], gsd_m: float, ok: np.ndarray | None = None) -> np.ndarray:
    """The mean (``"mean"``) or maximum (``"peak"``) of ``lum`` over a window of ``job[1]`` metres.

    ``ok`` (h, w) bool: over those pixels only, ``lum`` being 0 outside them (a normalised convolution for the
    mean: the filtered ``lum`` over the filtered ``ok``, twice the filtering); at a pixel of ``ok`` the window
    holds at least the pixel itself, so the result is finite there whatever the others hold. ``None``: every
    pixel (scipy's filters as they are).
    """
    kind, metres = job
    size = _window(metres, gsd_m)
    if kind == "mean":
        if ok is None:
            result: np.ndarray = ndimage.uniform_filter(lum, size=size, mode="reflect")
            return result
        share = ndimage.uniform_filter(ok.astype(np.float32), size=size, mode="reflect")
        total: np.ndarray = ndimage.uniform_filter(lum, size=size, mode="reflect")  # lum is 0 outside ok (_filled)
        total /= np.maximum(share, np.float32(1e-12))
        return total
    # scipy's maximum_filter(mode="reflect") to the bit, in one compiled pass per axis (2.5× faster)
    src = np.ascontiguousarray(lum) if ok is None else np.where(ok, lum, np.float32(-np.inf)).astype(np.float32)
    peak = np.empty_like(src)
    kernels.max_filter_reflect(src, size, np.empty_like(src), peak)
    return peak


def _planes(x: np.ndarray, lum: np.ndarray, local: list[np.ndarray]) -> list[np.ndarray]:
    """The 12 feature planes, float32 (h, w) each, of unit RGB ``x`` (3, h, w), its brightness ``lum`` and the
    :data:`_CONTEXTS` filters of it (``local``, cut to the same rows): per pixel, so any band of rows gives the
    rows of the whole image's planes to the bit.
    """
    total = x.sum(0) + np.float32(_EPS)
    cb = x[2] / total - np.float32(1 / 3)
    cr = x[0] / total - np.float32(1 / 3)
    top = x.max(0)
    sat = (top - x.min(0)) / (top + np.float32(0.02))
    return [lum, cb, cr, sat, lum * lum, lum * cb] + [lum - loc for loc in local]


@dataclass
class ShadowModel:
    """``P(shadow | colour)`` for one area: logistic regression on :func:`colour_features`, fitted against the
    cast shadows of the area's reference heights at its sun (labels, not a threshold).

    Attributes:
        gsd_m: pixel size the model was fitted at (the neighbourhoods are in metres).
        features: name of the feature set (:data:`FEATURES`).
        mean, scale: per-feature standardisation (:data:`N_FEATURES` values each).
        weights: logistic weights, intercept first; empty before :meth:`fit`.
        shadow_share: share of the fitted pixels in cast shadow.
        threshold: the probability from which a pixel is called shadow; pass it to
            :func:`~aerialmtl.sun.shadow_heights` (``threshold=``). Colour alone is ambiguous, so calibrated
            probabilities rarely pass 0.5 where a shadow is. Chosen on the fitted area (``threshold_by``): where
            the shadow heights of its own objects are closest to its reference heights (``"heights"``: smallest
            median |log(shadow / reference)|, needs :data:`MIN_CALIBRATION_OBJECTS` measured objects, else F1), or
            with the best F1 score of the shadow mask against the cast shadows (``"f1"``).
        threshold_by: how :attr:`threshold` was chosen: ``"heights"``, ``"f1"`` or ``"default"``.
    """

    gsd_m: float = 0.0
    features: str = FEATURES
    mean: list[float] = field(default_factory=list)
    scale: list[float] = field(default_factory=list)
    weights: list[float] = field(default_factory=list)
    shadow_share: float = 0.0
    threshold: float = 0.5
    threshold_by: str = "default"

    #: pixels used for the fit at most (a fixed-seed random subset beyond)
    MAX_PIXELS = 300_000

    def fit(self, rgb: ArrayOrList, height: ArrayOrList, gsd_m: float, sun: Sun,
            valid: ArrayOrList | None = None, l2: float = 1e-3, threshold_by: str = "heights") -> ShadowModel:
        """Fit on one patch or a list of patches (see :func:`aerialmtl.sun.fit_sun` for the forms).

        Args:
            rgb: (3, H, W) image(s); height: float (H, W) reference heights above ground in metres (NaN invalid).
            gsd_m: pixel size in metres. sun: the area's sun. valid: optional bool (H, W) mask(s).
            l2: ridge penalty on the standardised weights.
            threshold_by: ``"heights"`` or ``"f1"`` (see :attr:`threshold`).

        Returns:
            self.

        Raises:
            InputError: no valid pixels, the heights cast no shadow (or nothing but shadow) at ``sun``, or the fit
                gave no usable model (:func:`aerialmtl.sun.record.shadow_model_problem`).
        """
        if threshold_by not in ("heights", "f1"):
            raise InputError(f"'threshold_by' must be 'heights' or 'f1', got {threshold_by!r}", param="threshold_by")
        self.gsd_m = float(gsd_m)
        feats, labels = [], []
        patches = as_patches(rgb, height, valid)
        for im, h, ok in patches:
            mask = cast_shadow_mask(h, gsd_m, sun)
            f = colour_features(im, gsd_m)
            feats.append(f[:, ok])
            labels.append(mask[ok])
        f32 = np.concatenate(feats, axis=1)  # (12, n) float32
        y = np.concatenate(labels).astype(np.float64)
        if len(y) == 0:
            raise InputError("'valid' leaves no pixel to fit the shadow model on")
        if len(y) > self.MAX_PIXELS:  # the sample's pixels picked first: float64 rows made for them only
            pick = np.random.default_rng(0).choice(len(y), self.MAX_PIXELS, replace=False)
            f32, y = f32[:, pick], y[pick]
        x = f32.T.astype(np.float64)
        self.shadow_share = float(y.mean())
        if not 0.0 < self.shadow_share < 1.0:
            raise InputError(f"the heights cast {'no' if self.shadow_share == 0 else 'only'} shadow at the sun "
                             f"({sun}): nothing to learn what a shadow looks like from")
        mean, scale = x.mean(0), x.std(0) + 1e-6
        self.mean, self.scale = mean.tolist(), scale.tolist()
        w = _logistic((x - mean) / scale, y, l2)
        self.weights = w.tolist()
        p = 1.0 / (1.0 + np.exp(-np.clip(w[0] + _rows_dot((x - mean) / scale, w[1:]), -40, 40)))
        self.threshold, self.threshold_by = _best_f1_threshold(p, y > 0.5), "f1"
        if threshold_by == "heights":
            t = self._heights_threshold(patches, sun)
            if t is not None:
                self.threshold, self.threshold_by = t, "heights"
        problem = shadow_model_problem(self.to_dict())
        if problem is not None:  # what a checkpoint would refuse to hold (aerialmtl.sun.record)
            raise InputError(f"the shadow model's fit failed: {problem}")
        return self

    def _heights_threshold(self, patches: list[Patch], sun: Sun) -> float | None:
        """The threshold (0.04–0.5) at which the shadow heights of the patches' own objects (heights ≥ 2 m,
        ≥ 20 m²) are closest to their median reference heights (smallest median |log ratio|); ``None`` with too
        few objects.
        """
        cases = []
        for im, h, ok in patches:
            labels, n = ndimage.label(np.nan_to_num(h) >= 2.0)
            if n == 0:
                continue
            sizes = np.bincount(labels.ravel()) * self.gsd_m ** 2
            keep = sizes >= 20.0
            keep[0] = False
            labels = np.where(keep[labels], labels, 0)
            ref = np.zeros(len(sizes))
            idx = np.nonzero(keep)[0]
            ref[idx] = ndimage.median(np.nan_to_num(h), labels, index=idx)
            prob = np.where(ok, self.predict_proba(im), np.float32(np.nan)).astype(np.float32)
            cases.append((prob, h, labels, ref))
        best: tuple[float, float] | None = None
        for t in np.arange(0.04, 0.51, 0.02):
            ratios = []
            for prob, h, labels, ref in cases:
                sh = shadow_heights(prob, self.gsd_m, sun, labels, height=h, threshold=float(t))
                ratios += [o.height_m / ref[o.label] for o in sh.objects if o.measured and ref[o.label] > 0]
            if len(ratios) >= MIN_CALIBRATION_OBJECTS:
                miss = float(np.median(np.abs(np.log(np.maximum(ratios, 1e-3)))))
                if best is None or miss < best[0]:
                    best = (miss, float(round(t, 2)))
        return None if best is None else best[1]

    def shadow_mask(self, rgb: np.ndarray, gsd_m: float | None = None) -> np.ndarray:
        """The shadow pixels, bool (H, W): :meth:`predict_proba` ≥ :attr:`threshold`."""
        mask: np.ndarray = self.predict_proba(rgb, gsd_m) >= np.float32(self.threshold)
        return mask

    def predict_proba(self, rgb: np.ndarray, gsd_m: float | None = None, workers: int = 1,
                      valid: np.ndarray | None = None) -> np.ndarray:
        """float32 (H, W) probability of shadow, 0–1, of a (3, H, W) image at ``gsd_m`` (default: the fit's).

        NaN at the pixels that are not data (``valid`` (H, W) bool False, where given; a colour or brightness that
        is not finite: :func:`usable_pixels`); they take no part in any other pixel's neighbourhood, so one such
        pixel changes no other's probability beyond leaving its neighbourhoods.

        The features of :func:`colour_features`, never held as a (12, H, W) stack: the brightness and its
        neighbourhood filters (the same functions) over the whole image, then every per-pixel feature and the
        logistic in one compiled pass (:func:`aerialmtl.sun.kernels.logistic_rows`, float32 like the planes:
        within 2e-7 of the logistic on :func:`colour_features`) in bands of rows. ``workers`` > 1 runs the
        filters, and the bands, on that many threads (the filters and the kernel release the GIL); the result does
        not depend on it, to the bit.
        """
        if not self.weights:
            raise InputError("this ShadowModel is not fitted: call fit() first")
        gsd = gsd_m or self.gsd_m
        x = np.ascontiguousarray(unit_rgb(rgb))
        ok = usable_pixels(x, _brightness(x), valid)
        if ok is not None:
            x = np.ascontiguousarray(np.where(ok, x, np.float32(0.0)), dtype=np.float32)
        n_rows = x.shape[1]
        k = max(1, min(int(workers), n_rows))
        bands = [slice(i * n_rows // k, (i + 1) * n_rows // k) for i in range(k)]
        # the standardisation folded into the weights once
        a = np.asarray(self.weights[1:], np.float64) / np.asarray(self.scale, np.float64)
        a32 = a.astype(np.float32)
        bias = np.float32(self.weights[0] - float(a @ np.asarray(self.mean, np.float64)))
        lum = np.empty(x.shape[1:], np.float32)
        out = np.empty(x.shape[1:], np.float32)

        def brightness(rows: slice) -> None:
            lum[rows] = _brightness(x[:, rows])
            if ok is not None:
                lum[rows] = np.where(ok[rows], lum[rows], np.float32(0.0))

        def logistic(rows: slice) -> None:
            kernels.logistic_rows(x, lum, *locals_, a32, bias, np.float32(_EPS), rows.start, rows.stop, out)

        if k > 1:
            with ThreadPoolExecutor(k, thread_name_prefix="aerialmtl-colour") as pool:
                list(pool.map(brightness, bands))
                locals_ = list(pool.map(lambda job: _local(lum, job, gsd, ok), _CONTEXTS))
                list(pool.map(logistic, bands))
        else:
            brightness(bands[0])
            locals_ = [_local(lum, job, gsd, ok) for job in _CONTEXTS]
            logistic(bands[0])
        if ok is not None:
            out[~ok] = np.nan
        return out

    def to_dict(self) -> dict[str, object]:
        """Plain JSON/YAML types (floats and lists of floats)."""
        return {"gsd_m": self.gsd_m, "features": self.features, "mean": list(self.mean),
                "scale": list(self.scale), "weights": list(self.weights), "shadow_share": self.shadow_share,
                "threshold": self.threshold, "threshold_by": self.threshold_by}

    @classmethod
    def from_dict(cls, d: Mapping[str, object]) -> ShadowModel:
        """Inverse of :meth:`to_dict`."""
        try:
            m = cls(gsd_m=as_float(d["gsd_m"]), features=str(d["features"]),
                    mean=as_floats(d["mean"]), scale=as_floats(d["scale"]), weights=as_floats(d["weights"]),
                    shadow_share=as_float(d["shadow_share"]), threshold=as_float(d.get("threshold", 0.5)),
                    threshold_by=str(d.get("threshold_by", "default")))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"not a shadow model record ({exc!r}); keys {sorted(d)}") from exc
        problem = shadow_model_problem(m.to_dict())
        if problem is not None:
            raise InputError(f"not a usable shadow model record: {problem}; refit it (ShadowModel().fit)")
        return m


def _best_f1_threshold(p: np.ndarray, y: np.ndarray) -> float:
    """The probability threshold (0.02 steps) with the best F1 score of ``p ≥ t`` against ``y``."""
    best_t, best_f1 = 0.5, -1.0
    for t in np.arange(0.02, 0.99, 0.02):
        called = p >= t
        tp = float((called & y).sum())
        f1 = 2 * tp / (float(called.sum()) + float(y.sum())) if called.any() else 0.0
        if f1 > best_f1:
            best_t, best_f1 = float(round(t, 2)), f1
    return best_t


def _rows_dot(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``a @ w`` for float64 ``a`` (n, k) and ``w`` (k,), (n,), in numpy's own loop rather than BLAS (see
    :func:`_logistic`).
    """
    out: np.ndarray = np.einsum("ij,j->i", a, w)
    return out


def _logistic(x: np.ndarray, y: np.ndarray, l2: float) -> np.ndarray:
    """Weights (intercept first) of an L2-penalised logistic regression (L-BFGS on the mean log-loss);
    x (n, k) standardised features, y (n,) 0/1.

    The products over the n pixels are numpy's einsum loops, not BLAS (``@``): a threaded BLAS splits the sum over
    n by its thread count (``OPENBLAS_NUM_THREADS``/``OMP_NUM_THREADS``, the cores), so the weights would change in
    the last bits with the machine and the environment (1e-13 between 1 and 2 threads), and the training sun fitted
    beside the steps (:mod:`aerialmtl.training.sun_beside`, its own thread limits) would differ from the one fitted
    in the trainer. einsum sums in one fixed order on one thread: the same weights wherever the fit runs.
    """
    n, k = x.shape
    a = np.hstack([np.ones((n, 1)), x])
    pen = np.full(k + 1, l2)
    pen[0] = 0.0

    def loss(w: np.ndarray) -> tuple[float, np.ndarray]:
        z = _rows_dot(a, w)
        # log(1 + e^z) − y·z, computed stably
        value = float(np.mean(np.logaddexp(0.0, z) - y * z) + 0.5 * np.sum(pen * w * w))
        p = 0.5 * (1.0 + np.tanh(0.5 * z))
        grad = np.einsum("ij,i->j", a, p - y) / n + pen * w
        return value, grad

    w0 = np.zeros(k + 1)
    w0[0] = np.log(y.mean() / (1 - y.mean()))
    res = optimize.minimize(loss, w0, jac=True, method="L-BFGS-B", options={"maxiter": 500})
    weights: np.ndarray = res.x
    return weights
