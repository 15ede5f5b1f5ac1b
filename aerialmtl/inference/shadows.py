"""Heights from the sun inside predict: per window, the shadow layer, heights measured from shadow runs, and
(with ``shadow_fusion``) those heights fused into the network's own objects.

For each window the model has computed (its statistics still per window, before blending,
:mod:`aerialmtl.inference.stitch`):

1. ``shadow`` — the probability that each pixel is a cast shadow, from its colour and its neighbourhood, by the
   shadow classifier fitted on the training area at its sun (:class:`aerialmtl.sun.ShadowModel`, stored in the
   checkpoint's ``meta.sun``): learnt there from the training heights' cast shadows, so the area's water and
   dark roofs are not shadows;
2. ``shadow_height`` — per object the network finds (connected pixels predicted ≥ :data:`OBJECT_MIN_M`), the
   median height of the shadow runs beside it (:func:`aerialmtl.sun.shadow_heights`), painted over the object;
   nodata where nothing is measurable (a third of tall objects: shadows on other objects, runs clipped at the
   window's edge — the neighbouring window, which overlaps, may measure them);
3. with ``shadow_fusion``, the height and its spread of each measured object move towards the shadow height by
   inverse-variance weighting (:func:`aerialmtl.sun.fuse_heights`): never outside an object (flat ground is
   never raised), and the disagreement of the two widens the spread.

The statistics leave here as they came where the sun is off (``--sun none`` or no sun for the input): the
maps are then those of a run without the feature, to the bit.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
import torch
from scipy import ndimage

from aerialmtl.models.mc_dropout import McStatistics
from aerialmtl.sun import ShadowModel, Sun, fuse_heights, shadow_heights
from aerialmtl.sun.colour import unit_rgb

#: Pixels the network predicts at least this high (metres) form its objects.
OBJECT_MIN_M = 2.0


def unit_colours(data: np.ndarray, rescale: tuple[float, float] | None, train_dtype: str | None) -> np.ndarray:
    """float32 (3, h, w) colours of a window's raw values ``data`` (3, h, w) as the shadow classifier was fitted
    on them: the values the model trained on (``rescale`` = ``--rescale-input``'s ``(a, b)``: ``a·x + b``) on the
    scale of the training data's type ``train_dtype`` (:func:`aerialmtl.sun.colour.unit_rgb`, as it scaled the
    training patches), whatever this orthophoto's own type: a uint16 orthophoto holding 8-bit values is read as
    8-bit values, not as 1/257 of them.
    """
    x = data.astype(np.float32)
    if rescale is not None:
        x = x * np.float32(rescale[0]) + np.float32(rescale[1])
    return unit_rgb(x, train_dtype or "uint8")


class _Window(NamedTuple):
    """One window's layers, (h, w) each: shadow probability (0 where invalid), measured shadow height in metres
    (0 where none), where one was measured, and the fused (height, spread) or ``None``.
    """

    shadow: np.ndarray
    height: np.ndarray
    measured: np.ndarray
    fused: tuple[np.ndarray, np.ndarray] | None


class ShadowStep:
    """The shadow layers (and fusion) of one window batch; see the module docstring.

    Args:
        model: the training area's shadow classifier.
        gsd_m: the prediction grid's pixel size, metres.
        fuse: fuse the shadow heights into the height map and its spread.
        workers: threads of the step (the run's inference threads: the model waits meanwhile at T > 1, and
            scipy's filters and numpy release the GIL): a batch's windows at once, or a lone window's shadow
            classifier (its filters and bands of rows); the layers do not depend on it.
    """

    def __init__(self, model: ShadowModel, gsd_m: float, fuse: bool, workers: int = 1) -> None:
        self.model, self.gsd_m, self.fuse = model, float(gsd_m), bool(fuse)
        self.workers = max(1, int(workers))

    def _window(self, rgb: np.ndarray, ok: np.ndarray, height: np.ndarray, spread: np.ndarray | None,
                sun: Sun, workers: int = 1) -> _Window:
        """The layers of one window: ``rgb`` (3, h, w) colours (:func:`unit_colours`), ``ok`` bool (h, w),
        ``height``/``spread`` float32 (h, w) metres (the network's); fused height and spread only with :attr:`fuse`
        and a measure; ``workers`` threads for the shadow classifier (:meth:`~aerialmtl.sun.ShadowModel.predict_proba`).
        """
        prob = self.model.predict_proba(rgb, self.gsd_m, workers)
        prob = np.where(ok, prob, np.nan).astype(np.float32)
        objects, _ = ndimage.label((height >= OBJECT_MIN_M) & ok)
        measured = shadow_heights(prob, self.gsd_m, sun, objects, height=height, threshold=self.model.threshold)
        has = np.isfinite(measured.height) & ok
        fused = None
        if self.fuse and spread is not None and has.any():
            fused = fuse_heights(height, spread, measured, objects)
        return _Window(np.nan_to_num(prob, nan=0.0), np.where(has, measured.height, 0.0).astype(np.float32), has,
                       fused)

    def apply(self, stats: McStatistics, rgb: list[np.ndarray], valid: torch.Tensor, sun: Sun | None) -> None:
        """Set ``stats.shadow``, ``shadow_on``, ``shadow_height`` and ``shadow_weight`` (B, h, w) for the windows
        ``rgb`` (colours (3, h, w) each, :func:`unit_colours`, in batch order) under ``sun``; with :attr:`fuse`,
        replace ``height_mean`` and ``height_std`` inside measured objects. ``sun`` None: the layers' weights are 0 (the
        stitcher writes nodata) and nothing else changes.
        """
        b, h, w = valid.shape
        dev = valid.device
        shadow = torch.zeros((b, h, w), dtype=torch.float32)
        s_on = torch.zeros((b, h, w), dtype=torch.float32)
        s_height = torch.zeros((b, h, w), dtype=torch.float32)
        s_weight = torch.zeros((b, h, w), dtype=torch.float32)
        if sun is not None and stats.height_mean is not None:
            heights = stats.height_mean.detach().float().cpu().numpy().copy()
            spreads = None if stats.height_std is None else stats.height_std.detach().float().cpu().numpy().copy()
            ok_all = valid.cpu().numpy()
            fused = False

            # windows on threads of their own; a lone window (a CPU's batch) spreads its filters over them
            inner = max(1, self.workers // b)

            def one(n: int) -> _Window:
                return self._window(rgb[n][:3], ok_all[n], heights[n], None if spreads is None else spreads[n], sun,
                                    inner)

            if self.workers > 1 and b > 1:
                with ThreadPoolExecutor(min(self.workers, b), thread_name_prefix="aerialmtl-shadows") as pool:
                    done = list(pool.map(one, range(b)))
            else:
                done = [one(n) for n in range(b)]
            for n, win in enumerate(done):
                shadow[n] = torch.from_numpy(win.shadow)
                s_on[n] = torch.from_numpy(ok_all[n].astype(np.float32))
                s_height[n] = torch.from_numpy(win.height)
                s_weight[n] = torch.from_numpy(win.measured.astype(np.float32))
                if win.fused is not None and spreads is not None:
                    heights[n], spreads[n] = win.fused
                    fused = True
            if fused and spreads is not None:  # new tensors: the engine's may be inference-mode views
                stats.height_mean = torch.from_numpy(heights).to(stats.height_mean.device)
                stats.height_std = torch.from_numpy(spreads).to(dev)
        stats.shadow = shadow.to(dev)
        stats.shadow_on = s_on.to(dev)
        stats.shadow_height = s_height.to(dev)
        stats.shadow_weight = s_weight.to(dev)


__all__ = ["OBJECT_MIN_M", "ShadowStep", "unit_colours"]
