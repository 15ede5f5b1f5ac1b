"""How familiar an input looks to the network: a density of its own encoder features (DDU-style).

MC dropout and ensembles disagree where their members disagree; a structure of a kind the model never saw
(a large flat roof that looks like a car park) is predicted as ground by every member alike, with a
ground-like spread. Deterministic uncertainty methods (Mukhoti et al., "Deep Deterministic Uncertainty",
CVPR 2023) take another signal: fit a density to the network's features on the training set; a feature of
low density is unlike anything the model was trained on.

:class:`FeatureDensity` is that density, stored in the checkpoint (:attr:`ModelMeta.familiarity
<aerialmtl.formats.checkpoint.ModelMeta.familiarity>`, a few tens of kB) and applied at predict time:

* **features**: the encoder's outputs at :attr:`FeatureDensity.levels` (indexes into the list ``encode``
  returns, strides 2, 4, 8, 16, 32); several levels are brought to the finest one's grid (bilinear) and
  concatenated. The encoder is deterministic and runs once per window on every engine (its outputs are the
  OpenVINO encoder graph's outputs), so no MC sample and no extra graph is needed; the chosen level and why
  are in bench/RESULTS.md ("unfamiliarity").
* **reduction**: each channel standardised by its training mean and standard deviation, then projected on
  the first ``d`` principal axes of the training features (:attr:`basis`, d × C).
* **density**: a Gaussian mixture in that space (``K`` components: full covariances stored as the
  Cholesky factors of their precisions). Fitted by :func:`fit_density`, either as class-conditional
  Gaussians over given labels (GDA, DDU's choice; here: reference-height bins) or by EM.
* **unit**: the negative log density (nats) is mapped through its quantiles on the training features
  (:attr:`quantiles`) to ``unfamiliarity`` ∈ [0, 1] = the share of training feature pixels more familiar
  than this one (0.5: a typical training pixel; 0.99: only 1 % of the training pixels looked as unusual;
  1: beyond everything seen). The map is upsampled to the output pixels bilinearly.

Cost at predict time: a 1×1 projection and K quadratic forms of dimension d per feature pixel (the default
stride 8: 1/64 of the output pixels; ~200 flops per output pixel at d = 32, K = 6), plus one bilinear
upsampling: no measurable change of a T = 16 prediction on 2 cores (bench/RESULTS.md, "unfamiliarity"). At
T = 1 the OpenVINO engine runs its encoder graph once more per window for it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
import torch.nn.functional as F

from aerialmtl.errors import CheckpointError

#: Quantile levels stored (share of training feature pixels), 0, 0.005, ..., 1.
QUANTILE_LEVELS = 201
#: The encoder's feature levels (strides 2, 4, 8, 16, 32: :func:`aerialmtl.models.encoders.feature_channels`).
ENCODER_LEVELS = 5
#: How far the mixture weights may sum from 1, and a basis's Gram matrix from the identity (a fit stores them to
#: ~1e-15; a float32 round trip ~1e-7).
WEIGHT_SUM_TOLERANCE = 1e-4
BASIS_TOLERANCE = 1e-3


def _short(values: Sequence[float], n: int = 4) -> str:
    """``[0.5, 0.5, ...]``: the first ``n`` values, for messages."""
    return "[" + ", ".join(f"{v:.3g}" for v in values[:n]) + (", ...]" if len(values) > n else "]")
_LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class FeatureDensity:
    """A Gaussian mixture over reduced encoder features and the training quantiles of its NLL.

    Attributes:
        levels: encoder outputs used (indexes into ``model.encode(x)``), finest first.
        stride: the finest level's stride (pixels per feature pixel).
        centre, scale: per-channel mean and standard deviation of the training features (C each).
        basis: d × C principal axes (rows) of the standardised training features.
        weights: K mixture weights (sum 1).
        means: K × d component means.
        precision_chol: K rows of d·d values: the lower Cholesky factor L of each component's precision
            (Σ⁻¹ = L Lᵀ), row-major.
        quantiles: the NLL (nats) of the training features at :data:`QUANTILE_LEVELS` evenly spaced levels
            (non-decreasing).
        n_pixels: training feature pixels fitted; ``method``: ``gda`` or ``em``; ``source``: what on.
    """

    levels: tuple[int, ...]
    stride: int
    centre: tuple[float, ...]
    scale: tuple[float, ...]
    basis: tuple[tuple[float, ...], ...]
    weights: tuple[float, ...]
    means: tuple[tuple[float, ...], ...]
    precision_chol: tuple[tuple[float, ...], ...]
    quantiles: tuple[float, ...]
    n_pixels: int = 0
    method: str = "gda"
    source: str = ""

    def __post_init__(self) -> None:
        c, d, k = len(self.centre), len(self.basis), len(self.weights)
        problems = []
        if not self.levels or self.stride < 1:
            problems.append("no feature level")
        if len(self.scale) != c or any(len(row) != c for row in self.basis) or d < 1:
            problems.append(f"basis is not d × {c}")
        if k < 1 or len(self.means) != k or any(len(m) != d for m in self.means):
            problems.append(f"means are not {k} × {d}")
        if len(self.precision_chol) != k or any(len(p) != d * d for p in self.precision_chol):
            problems.append(f"precision factors are not {k} × {d}²")
        q = np.asarray(self.quantiles, np.float64)
        if q.size < 2 or not np.isfinite(q).all() or (np.diff(q) < 0).any():
            problems.append("quantiles are not a finite non-decreasing table")
        flat = [*self.centre, *self.scale, *self.weights, *(v for r in self.basis for v in r),
                *(v for r in self.means for v in r), *(v for r in self.precision_chol for v in r)]
        if not all(math.isfinite(v) for v in flat) or any(s <= 0 for s in self.scale):
            problems.append("non-finite values or a scale ≤ 0")
        elif not problems:
            problems += self._fit_problems()
        bad_levels = [v for v in self.levels if not 0 <= v < ENCODER_LEVELS]
        if bad_levels or len(set(self.levels)) != len(self.levels):
            problems.append(f"encoder levels {list(self.levels)}, where the encoder has the distinct levels 0–"
                            f"{ENCODER_LEVELS - 1} (strides 2–32)")
        if problems:
            raise CheckpointError(f"checkpoint meta is invalid: its feature density (familiarity) has "
                                  f"{'; '.join(problems)} (no fit writes that: the file was edited or damaged, and "
                                  "its unfamiliarity layer would be NaN or constant); use the checkpoint as `train` "
                                  "wrote it, or refit the density (aerialmtl.training.familiarity."
                                  "familiarize_checkpoint)")

    def check_widths(self, channels: Sequence[int]) -> str | None:
        """Why this density does not fit an encoder whose levels have ``channels`` channels (``None``: it does)."""
        want = sum(int(channels[v]) for v in self.levels)
        if len(self.centre) != want:
            return (f"its feature density (familiarity) reads {len(self.centre)} channels at encoder levels "
                    f"{list(self.levels)}, where the model has {want}")
        return None

    def _fit_problems(self) -> list[str]:
        """What no fit (:func:`fit_density`) leaves, in a density of the right shapes and finite values: weights
        that are not positive or do not sum to 1, precision factors that are not lower triangular with a positive
        diagonal, a basis whose rows are not orthonormal (a zero basis makes every pixel alike), a quantile table
        without spread (a constant layer), values beyond float32 (predict computes in float32: NaN or inf).
        """
        out = []
        w = np.asarray(self.weights, np.float64)
        if (w <= 0).any() or abs(float(w.sum()) - 1.0) > WEIGHT_SUM_TOLERANCE:
            out.append(f"mixture weights {_short(self.weights)}, which must be > 0 and sum to 1")
        k, d = self.components, self.dims
        chol = np.asarray(self.precision_chol, np.float64).reshape(k, d, d)
        diag = np.diagonal(chol, axis1=1, axis2=2)
        if (diag <= 0).any() or np.triu(chol, 1).any():
            out.append("precision factors that are not lower triangular with a positive diagonal")
        basis = np.asarray(self.basis, np.float64)
        if np.abs(basis @ basis.T - np.eye(d)).max() > BASIS_TOLERANCE:
            out.append("a basis whose rows are not orthonormal principal axes")
        q = self.quantiles
        if not q[-1] > q[0]:
            out.append(f"a quantile table without spread ({q[0]:g}..{q[-1]:g} nats: every pixel would get one value)")
        big = float(np.finfo(np.float32).max)
        if not out and (max(abs(v) for v in (*self.centre, *self.scale, *self.quantiles, *w)) >= big
                        or not np.isfinite(self._tensors["const"].numpy()).all()
                        or not np.isfinite(self._tensors["basis"].numpy()).all()):
            out.append("values beyond float32, in which predict computes it")
        return out

    @property
    def dims(self) -> int:
        """d, the reduced feature dimension."""
        return len(self.basis)

    @property
    def components(self) -> int:
        """K, the mixture components."""
        return len(self.weights)

    def summary(self) -> str:
        """One line for logs and ``prediction.json``."""
        return (f"{self.method} density of {self.components} Gaussians in {self.dims} dims over encoder levels "
                f"{list(self.levels)} (stride {self.stride}), {self.n_pixels} training feature pixels")

    # ---- scoring --------------------------------------------------------------------------------
    @cached_property
    def _tensors(self) -> dict[str, torch.Tensor]:
        d, k = self.dims, self.components
        scale = torch.tensor(self.scale, dtype=torch.float32)
        basis = torch.tensor(self.basis, dtype=torch.float32) / scale  # standardising folded into the projection
        chol = torch.tensor(self.precision_chol, dtype=torch.float32).reshape(k, d, d)
        logdet = torch.log(torch.diagonal(chol, dim1=1, dim2=2)).sum(1)  # ½ log|Σ⁻¹|
        const = torch.log(torch.tensor(self.weights, dtype=torch.float32)) + logdet - 0.5 * d * _LOG_2PI
        return {"centre": torch.tensor(self.centre, dtype=torch.float32), "basis": basis,
                "means": torch.tensor(self.means, dtype=torch.float32), "chol": chol, "const": const,
                "quantiles": torch.tensor(self.quantiles, dtype=torch.float32)}

    def stack(self, feats: Sequence[torch.Tensor | np.ndarray]) -> torch.Tensor:
        """The encoder outputs at :attr:`levels` on the finest one's grid, concatenated: B×C×h×w float32."""
        picked = [torch.as_tensor(feats[i]).float() for i in self.levels]
        size = picked[0].shape[-2:]
        parts = [p if p.shape[-2:] == size else F.interpolate(p, size=size, mode="bilinear", align_corners=False)
                 for p in picked]
        return parts[0] if len(parts) == 1 else torch.cat(parts, 1)

    def nll(self, x: torch.Tensor) -> torch.Tensor:
        """Negative log density (nats) of B×C×h×w features → B×h×w (float32)."""
        t = self._tensors
        dev = x.device
        z = (x.float().permute(0, 2, 3, 1) - t["centre"].to(dev)) @ t["basis"].to(dev).T  # B×h×w×d
        y = (z.unsqueeze(-2) - t["means"].to(dev))  # B×h×w×K×d
        # ‖Lᵀ (z − μ_k)‖² per component: y @ L_k
        m = torch.einsum("...kd,kde->...ke", y, t["chol"].to(dev))
        logp = t["const"].to(dev) - 0.5 * m.square().sum(-1)
        return -torch.logsumexp(logp, -1)

    def to_unit(self, nll: torch.Tensor) -> torch.Tensor:
        """NLL (nats) → the share of training feature pixels with a lower NLL (0–1, piecewise linear)."""
        q = self._tensors["quantiles"].to(nll.device)
        n = q.numel()
        idx = torch.searchsorted(q, nll.contiguous(), right=True).clamp(1, n - 1)
        lo, hi = q[idx - 1], q[idx]
        frac = ((nll - lo) / (hi - lo).clamp_min(1e-12)).clamp(0.0, 1.0)
        u = (idx - 1 + frac) / (n - 1)
        u = torch.where(nll <= q[0], torch.zeros_like(u), u)
        return torch.where(nll >= q[-1], torch.ones_like(u), u)

    def unfamiliarity(self, feats: Sequence[torch.Tensor | np.ndarray], size: tuple[int, int]) -> torch.Tensor:
        """Encoder outputs of a B×C×H×W batch → B×H×W unfamiliarity in [0, 1] (float32; see the module docstring).

        Args:
            feats: the list ``model.encode(x)`` returns (torch tensors or the OpenVINO engine's arrays).
            size: (H, W) of the output.
        """
        x = self.stack(feats)
        with torch.autocast(x.device.type, enabled=False):  # float32 quadratic forms under a bf16 autocast too
            u = self.to_unit(self.nll(x)).unsqueeze(1)
            return F.interpolate(u, size=size, mode="bilinear", align_corners=False)[:, 0].clamp_(0.0, 1.0)


# ---- fitting --------------------------------------------------------------------------------------
def _cholesky_precision(cov: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor L of Σ⁻¹ (Σ⁻¹ = L Lᵀ) of a d×d covariance (float64)."""
    prec = np.linalg.inv(cov)
    prec = 0.5 * (prec + prec.T)
    return np.linalg.cholesky(prec)


def _gaussians(z: np.ndarray, resp: np.ndarray, reg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weights, means and precision factors of a mixture from responsibilities (N×K)."""
    nk = resp.sum(0) + 1e-10
    means = (resp.T @ z) / nk[:, None]
    d = z.shape[1]
    chol = np.empty((len(nk), d, d))
    for k in range(len(nk)):
        y = z - means[k]
        cov = (resp[:, k, None] * y).T @ y / nk[k] + reg * np.eye(d)
        chol[k] = _cholesky_precision(cov)
    return nk / nk.sum(), means, chol


def _log_prob(z: np.ndarray, weights: np.ndarray, means: np.ndarray, chol: np.ndarray) -> np.ndarray:
    """N×K log(w_k N(z; μ_k, Σ_k)) (float64)."""
    d = z.shape[1]
    out = np.empty((z.shape[0], len(weights)))
    for k in range(len(weights)):
        m = (z - means[k]) @ chol[k]
        out[:, k] = (np.log(weights[k]) + np.log(np.diag(chol[k])).sum() - 0.5 * d * _LOG_2PI
                     - 0.5 * np.square(m).sum(1))
    return out


def _logsumexp(a: np.ndarray) -> np.ndarray:
    top = a.max(1, keepdims=True)
    return np.asarray((top + np.log(np.exp(a - top).sum(1, keepdims=True)))[:, 0], np.float64)


def _fit_gda(z: np.ndarray, labels: np.ndarray, need: int,
             eps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One Gaussian per label with at least ``need`` of the N×d rows ``z`` (the most frequent label if none has);
    a rarer label's rows join the kept Gaussian whose mean is nearest to theirs. Returns weights, means and
    the precisions' Cholesky factors (:func:`_gaussians`).
    """
    if labels.shape[0] != z.shape[0]:
        raise ValueError(f"fit_density: {labels.shape[0]} labels for {z.shape[0]} feature rows")
    values, counts = np.unique(labels, return_counts=True)
    kept = values[counts >= need]
    if kept.size == 0:
        kept = values[[int(np.argmax(counts))]]
    kept_means = np.stack([z[labels == v].mean(0) for v in kept])
    index = {int(v): i for i, v in enumerate(kept)}
    assign = np.empty(z.shape[0], np.int64)
    for v in values:
        rows = labels == v
        if int(v) in index:
            assign[rows] = index[int(v)]
        else:  # a rare label joins the kept component whose mean is nearest to its own
            mu = z[rows].mean(0)
            assign[rows] = int(np.argmin(((kept_means - mu) ** 2).sum(1)))
    return _gaussians(z, np.eye(kept.size)[assign], eps)


def _fit_mixture(z: np.ndarray, k: int, eps: float, iterations: int,
                 seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A ``k``-Gaussian mixture of the N×d rows ``z`` by EM from a k-means++ start (seeded); returns weights,
    means and the precisions' Cholesky factors (:func:`_gaussians`).
    """
    rng = np.random.default_rng(seed)
    centres = [z[rng.integers(z.shape[0])]]
    for _ in range(1, k):  # k-means++
        dist = np.min([((z - c) ** 2).sum(1) for c in centres], 0)
        centres.append(z[rng.choice(z.shape[0], p=dist / dist.sum())])
    assign = np.argmin(np.stack([((z - c) ** 2).sum(1) for c in centres], 1), 1)
    resp = np.eye(k)[assign]
    prev = -np.inf
    for _ in range(iterations):
        weights, means, chol = _gaussians(z, resp, eps)
        lp = _log_prob(z, weights, means, chol)
        total = _logsumexp(lp)
        resp = np.exp(lp - total[:, None])
        ll = float(total.mean())
        if ll - prev < 1e-4:
            break
        prev = ll
    return _gaussians(z, resp, eps)


def fit_density(x: np.ndarray, levels: Sequence[int], stride: int, *, dims: int = 32,
                labels: np.ndarray | None = None, components: int = 8, min_count: int | None = None,
                reg: float = 1e-3, iterations: int = 100, seed: int = 0, source: str = "") -> FeatureDensity:
    """Fit a :class:`FeatureDensity` to training feature vectors.

    Args:
        x: N×C training features (one row per feature pixel).
        levels, stride: the encoder levels they come from and the finest level's stride.
        dims: d, principal axes kept (at most C and N − 1).
        labels: N integer labels: class-conditional Gaussians (GDA), one per label with at least
            ``min_count`` rows (default 2·d; rarer labels join the nearest kept one by mean); ``None``: a
            ``components``-Gaussian mixture fitted by EM from a k-means++ start.
        reg: added to every covariance's diagonal, relative to the mean variance of the reduced features.
        iterations: EM iterations (``labels=None``).
        seed: the k-means++ start.
        source: what the features are (recorded).

    Raises:
        ValueError: fewer than 2 rows, or non-finite features.
    """
    x = np.asarray(x, np.float64)
    if x.ndim != 2 or x.shape[0] < 2 or not np.isfinite(x).all():
        raise ValueError(f"fit_density: expected N×C finite features with N ≥ 2, got shape {x.shape}")
    centre = x.mean(0)
    scale = np.maximum(x.std(0), 1e-6)
    xs = (x - centre) / scale
    d = int(max(1, min(dims, xs.shape[1], xs.shape[0] - 1)))
    _, _, vt = np.linalg.svd(xs, full_matrices=False)
    basis = vt[:d]
    z = xs @ basis.T
    eps = reg * float(z.var(0).mean()) + 1e-9
    if labels is not None:
        need = min_count if min_count is not None else 2 * d
        weights, means, chol = _fit_gda(z, np.asarray(labels).reshape(-1), need, eps)
        method = "gda"
    else:
        weights, means, chol = _fit_mixture(z, int(max(1, min(components, z.shape[0] // max(2, d)))), eps,
                                            iterations, seed)
        method = "em"
    nll = -_logsumexp(_log_prob(z, weights, means, chol))
    quantiles = np.quantile(nll, np.linspace(0.0, 1.0, QUANTILE_LEVELS))
    quantiles = np.maximum.accumulate(quantiles)
    k = len(weights)
    return FeatureDensity(
        levels=tuple(int(v) for v in levels), stride=int(stride),
        centre=tuple(float(v) for v in centre), scale=tuple(float(v) for v in scale),
        basis=tuple(tuple(float(v) for v in row) for row in basis),
        weights=tuple(float(v) for v in weights), means=tuple(tuple(float(v) for v in row) for row in means),
        precision_chol=tuple(tuple(float(v) for v in chol[i].reshape(-1)) for i in range(k)),
        quantiles=tuple(float(v) for v in quantiles), n_pixels=int(z.shape[0]), method=method, source=source)


__all__ = ["BASIS_TOLERANCE", "ENCODER_LEVELS", "QUANTILE_LEVELS", "WEIGHT_SUM_TOLERANCE", "FeatureDensity",
           "fit_density"]
