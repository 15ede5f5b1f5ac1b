"""The model on batches of windows: raw pixels in, per-window statistics out, all on the model's device.

:class:`ModelRunner` copies a batch of raw windows to the device (asynchronously from pinned memory on
CUDA), normalises them with the checkpoint's per-band mean/std there, and runs either one
deterministic forward pass (T = 1: height and softmax probabilities) or MC dropout
(:func:`~aerialmtl.models.mc_dropout.mc_statistics`: encoder once, T decoder samples in chunks that fit
the device, dropout masks seeded per window so results do not depend on batching).

Also here: the batch-size choices (:func:`auto_batch_size`, :func:`mc_sample_batch`) and test-time
augmentation (:func:`combine_tta`). The engines (and the optional ``torch.compile`` of the torch engine)
are :mod:`aerialmtl.inference.engines`'; device, precision, autocast and the compile fallback come from
:mod:`aerialmtl.runtime`.

The engine (:func:`~aerialmtl.inference.engines.build_engine`) predicts with its own copy of the model,
prepared for inference (:func:`~aerialmtl.models.d3net.inference_model`):
decoder convolutions and their BatchNorms folded into one (:func:`~aerialmtl.models.d3net.fold_batchnorm`)
and channels-last activations (measured faster on CPU than class planes for the head, the softmax
and the blending alike; bench/RESULTS.md).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from typing import Literal

import numpy as np
import torch
from torch import nn

from aerialmtl import runtime
from aerialmtl.errors import cause
from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.inference.engines import (
    FALLBACK,
    Done,
    Engine,
    EngineSetup,
    Pending,
    build_engine,
    engine_spec,
    fallback_engine,
)
from aerialmtl.inference.model_record import CheckpointModel
from aerialmtl.inference.sanity import normalised
from aerialmtl.inference.settings import PredictSettings, ResolvedSettings
from aerialmtl.models.mc_dropout import McStatistics

#: Largest number of image pixels (windows × MC samples × h × w) decoded in one call, per device type.
#: The full D3-Net decoder needs about 1.2 GiB of activations per decoded megapixel in fp32, so a batch
#: of 4 windows of 512² with T = 30 decoded at once would need ~36 GiB; the MC samples are split into
#: chunks that fit instead (the result is the same: masks are drawn per window and sample).
DECODE_PIXELS = {"cpu": 2**21, "cuda": 2**23}
#: Windows per model call with ``batch_size="auto"`` on a CPU: one window already keeps the cores busy,
#: and a second one costs ~250 MiB of activations at tile 1024 for no measured speed (bench/RESULTS.md).
CPU_BATCH = 1
#: Share of the free device memory ``auto`` plans to use.
MEMORY_SHARE = 0.6


def mc_sample_batch(batch: int, height: int, width: int, device: torch.device, max_pixels: int | None = None) -> int:
    """MC samples decoded per call so that ``batch × samples × height × width ≤ max_pixels`` (at least 1)."""
    budget = DECODE_PIXELS.get(device.type, DECODE_PIXELS["cpu"]) if max_pixels is None else max_pixels
    return max(1, int(budget) // max(1, batch * height * width))


def batch_from_memory(free_bytes: int, bytes_per_window: int, limit: int = 64) -> int:
    """Windows per call that fit :data:`MEMORY_SHARE` of ``free_bytes`` (1 … ``limit``)."""
    return int(max(1, min(limit, (free_bytes * MEMORY_SHARE) // max(1, bytes_per_window))))


def auto_batch_size(model: nn.Module | Callable[[], nn.Module], in_channels: int, height: int, width: int,
                    device: torch.device, precision: Literal["bf16", "fp32"]) -> int:
    """Windows per model call for ``batch_size="auto"``.

    CPU: :data:`CPU_BATCH`. CUDA: one probe forward of a window measures the peak memory per window;
    the batch fills :data:`MEMORY_SHARE` of the free memory (at most 64). ``model`` may be a function that
    returns it (called on CUDA only: a CPU run on a warm OpenVINO cache never loads the torch model).
    """
    if device.type != "cuda":
        return CPU_BATCH
    if not isinstance(model, nn.Module):
        model = model()
    x = torch.zeros((1, in_channels, height, width), device=device).contiguous(memory_format=torch.channels_last)
    torch.cuda.synchronize(device)
    torch.cuda.reset_peak_memory_stats(device)
    base = torch.cuda.memory_allocated(device)
    with torch.inference_mode(), runtime.autocast(device, precision):
        model.eval()
        model.forward(x)
    torch.cuda.synchronize(device)
    per_window = torch.cuda.max_memory_allocated(device) - base
    free, _ = torch.cuda.mem_get_info(device)
    return batch_from_memory(int(free), int(per_window))


#: The 8 views of test-time augmentation: (90° rotations k, then a horizontal flip).
DIHEDRAL: tuple[tuple[int, bool], ...] = tuple((k, f) for f in (False, True) for k in range(4))


def dihedral(x: torch.Tensor, t: int, dims: tuple[int, int]) -> torch.Tensor:
    """View ``t`` of :data:`DIHEDRAL` of ``x`` over its two spatial ``dims``."""
    k, flip = DIHEDRAL[t]
    y = torch.rot90(x, k, dims) if k else x
    return torch.flip(y, (dims[1],)) if flip else y


def _undo(x: torch.Tensor, t: int) -> torch.Tensor:
    """The inverse of :func:`dihedral` view ``t`` on a (B, h, w[, K]) statistic."""
    k, flip = DIHEDRAL[t]
    y = torch.flip(x, (2,)) if flip else x
    return torch.rot90(y, -k, (1, 2)) if k else y


def invert_statistics(stats: McStatistics, t: int) -> McStatistics:
    """The statistics of view ``t`` back on the window's own grid."""
    return stats.map(lambda v: _undo(v, t).contiguous())


def combine_tta(parts: Sequence[McStatistics]) -> McStatistics:
    """The statistics of V views together, each a mixture component of equal weight.

    Mean height = mean of the view means; ``height_std² = mean of the view variances + variance of the view
    means`` (the law of total variance, as for the MC samples); probabilities averaged; the expected entropy
    averaged (per view: its mean per-sample entropy, or the entropy of its probabilities at T = 1).
    """
    n = len(parts)
    out = McStatistics()
    if parts[0].height_mean is not None:
        means = torch.stack([p.height_mean for p in parts if p.height_mean is not None])
        out.height_mean = means.mean(0)
        spread = means.var(0, unbiased=False)
        if parts[0].height_std is not None:
            spread = spread + torch.stack([p.height_std for p in parts if p.height_std is not None]).square().mean(0)
        out.height_std = spread.sqrt()
        if parts[0].height_aleatoric is not None:
            out.height_aleatoric = torch.stack([p.height_aleatoric for p in parts
                                                if p.height_aleatoric is not None]).square().mean(0).sqrt()
    if parts[0].probs is not None:
        probs = [p.probs for p in parts if p.probs is not None]
        out.probs = torch.stack(probs).mean(0)
        ents = [p.mean_entropy if p.mean_entropy is not None
                else -(q * torch.log(q.clamp_min(1e-12))).sum(-1) for p, q in zip(parts, probs)]
        out.mean_entropy = torch.stack(ents).sum(0) / n
    if parts[0].unfamiliarity is not None:  # the views' mean
        out.unfamiliarity = torch.stack([p.unfamiliarity for p in parts if p.unfamiliarity is not None]).mean(0)
    return out


class ModelRunner:
    """Run the model on batches of raw windows, on the engine of :func:`~aerialmtl.inference.engines.resolve_engine`.

    Args:
        model: a D3-Net-like model (``encode``/``decode``/``forward``); the engine works on a prepared copy
            (made on first use on the OpenVINO engine, which needs it only to convert the model). On the OpenVINO
            engine also a :class:`~aerialmtl.inference.model_record.CheckpointModel`, loaded only when needed.
        meta: its checkpoint metadata (bands' mean/std for normalisation).
        settings: predict's settings; the runner applies ``tta``, ``seed`` and ``max_decode_pixels`` around the
            engine, and falls back to the torch engine when ``engine`` is ``auto`` and the engine it chose fails
            on the first batch. ``tta``: every window is also run flipped and rotated by 90°, 180°, 270° (8
            views), combined like MC samples (:func:`combine_tta`), so ``height_std`` also holds their
            disagreement; 8 times the model's work.
        resolved: what they resolved to (device, engine, precision, threads, MC samples T).
        weights_key: the checkpoint's fingerprint, when the caller has it: keys the OpenVINO cache without
            hashing the weights again.
    """

    def __init__(self, model: nn.Module | CheckpointModel, meta: ModelMeta, settings: PredictSettings,
                 resolved: ResolvedSettings, weights_key: str | None = None) -> None:
        self.settings, self.resolved = settings, resolved
        self.device = resolved.device
        self.precision = resolved.precision
        self.mc = resolved.mc
        self.tta = settings.tta
        self.seed = settings.seed
        self.fallback = settings.engine == "auto"
        self._ran = False
        self.threads = resolved.threads
        self.mean = torch.tensor(meta.mean, dtype=torch.float32, device=self.device)[:, None, None]
        self.std = torch.tensor(meta.std, dtype=torch.float32, device=self.device)[:, None, None]
        self._setup = EngineSetup(model, meta, settings, resolved, weights_key)
        self.engine: Engine = build_engine(self._setup)

    @property
    def model(self) -> nn.Module:
        """The model prepared for prediction (:func:`~aerialmtl.models.d3net.inference_model`).

        On the OpenVINO engine, its own copy there.
        """
        return self.engine.model

    @property
    def net(self) -> nn.Module:
        """What measures the memory of a window (:attr:`Engine.net <aerialmtl.inference.engines.Engine.net>`)."""
        return self.engine.net

    @property
    def in_flight(self) -> int:
        """Batches a caller keeps submitted ahead of the one it stitches (:meth:`submit`).

        The engine's :meth:`~aerialmtl.inference.engines.Engine.ahead` (one per stream on OpenVINO at T = 1), none
        with TTA (the views are computed one after the other).
        """
        return 0 if self.tta else self.engine.ahead(self.mc)

    def to_device(self, data: Sequence[np.ndarray | torch.Tensor], valid: Sequence[np.ndarray]) -> tuple[
            torch.Tensor, torch.Tensor]:
        """Stack raw windows and their validity on the device: (B, C, h, w) raw, (B, h, w) bool."""
        raw = torch.stack([d if isinstance(d, torch.Tensor) else torch.from_numpy(d) for d in data])
        ok = torch.from_numpy(np.stack(valid))
        if self.device.type == "cuda":
            if not raw.is_pinned():
                raw = raw.pin_memory()
            raw = raw.to(self.device, non_blocking=True)
            ok = ok.pin_memory().to(self.device, non_blocking=True)
        return raw, ok

    def normalise(self, raw: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """(B, C, h, w) raw → normalised float32 channels-last, 0 where invalid (:func:`normalised`)."""
        return normalised(raw, valid, self.mean, self.std)

    def __call__(self, x: torch.Tensor, keys: Sequence[int]) -> McStatistics:
        """Normalised (B, C, h, w) batch → statistics of each window (see :class:`McStatistics`).

        With :attr:`tta`, those of the 8 flips and 90° rotations combined (:func:`combine_tta`).

        With :attr:`fallback` (``engine: auto``), an OpenVINO engine that fails on the first batch is
        replaced by the torch engine, with a warning, and the batch is computed again: the whole raster then
        comes from one engine, and ``prediction.json`` names it.
        """
        first, self._ran = not self._ran, True
        try:
            return self._statistics(x, keys)
        except Exception as exc:
            if not (first and self.fallback and self.engine.name != FALLBACK):
                raise
            label = engine_spec(self.engine.name).label
            fallback = engine_spec(FALLBACK)
            warnings.warn(f"the {label} engine cannot run this model ({type(exc).__name__}: "
                          f"{cause(exc)}); predicting with the {fallback.label} engine "
                          f"instead (pass --engine {FALLBACK} to choose it directly)", UserWarning, stacklevel=2)
            self.engine = fallback_engine(self.engine, self._setup)  # over the engine's folded copy
            return self._statistics(x, keys)

    def _statistics(self, x: torch.Tensor, keys: Sequence[int]) -> McStatistics:
        b, _, h, w = x.shape
        chunk = mc_sample_batch(b, h, w, self.device, self.settings.max_decode_pixels)
        if not self.tta:
            return self.engine.statistics(x, keys, self.mc, self.seed, chunk)
        parts = []
        for t in range(len(DIHEDRAL)):
            xt = dihedral(x, t, (2, 3)).contiguous(memory_format=torch.channels_last)
            tkeys = [int(k) * len(DIHEDRAL) + t for k in keys]  # other masks per view, still seeded per window
            parts.append(invert_statistics(self.engine.statistics(xt, tkeys, self.mc, self.seed, chunk), t))
        return combine_tta(parts)

    def submit(self, x: torch.Tensor, keys: Sequence[int]) -> Pending:
        """Start the statistics of a normalised (B, C, h, w) batch; ``.result()`` gives them.

        The same numbers as :meth:`__call__`. Up to :attr:`in_flight` batches run while the caller stitches. Computed
        here, synchronously: with :attr:`tta` (the views one after the other), and the first batch when
        :attr:`fallback` may still switch engines.
        """
        if self.tta or (self.fallback and not self._ran):
            return Done(self(x, keys))
        b, _, h, w = x.shape
        chunk = mc_sample_batch(b, h, w, self.device, self.settings.max_decode_pixels)
        return self.engine.submit(x, keys, self.mc, self.seed, chunk)


__all__ = ["CPU_BATCH", "DECODE_PIXELS", "ModelRunner", "auto_batch_size", "batch_from_memory", "mc_sample_batch"]
