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

import numpy as np
import torch
from scipy import ndimage

from aerialmtl.models.mc_dropout import McStatistics
from aerialmtl.sun import ShadowModel, Sun, fuse_heights, shadow_heights

#: Pixels the network predicts at least this high (metres) form its objects.
OBJECT_MIN_M = 2.0


class ShadowStep:
    """The shadow layers (and fusion) of one window batch; see the module docstring.

    Args:
        model: the training area's shadow classifier.
        gsd_m: the prediction grid's pixel size, metres.
        fuse: fuse the shadow heights into the height map and its spread.
    """

    def __init__(self, model: ShadowModel, gsd_m: float, fuse: bool) -> None:
        self.model, self.gsd_m, self.fuse = model, float(gsd_m), bool(fuse)

    def apply(self, stats: McStatistics, rgb: list[np.ndarray], valid: torch.Tensor, sun: Sun | None) -> None:
        """Set ``stats.shadow``, ``shadow_on``, ``shadow_height`` and ``shadow_weight`` (B, h, w) for the windows
        ``rgb`` (raw 8-bit (3, h, w) each, in batch order) under ``sun``; with :attr:`fuse`, replace
        ``height_mean`` and ``height_std`` inside measured objects. ``sun`` None: the layers' weights are 0 (the
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
            for n in range(b):
                ok = ok_all[n]
                prob = self.model.predict_proba(rgb[n][:3], self.gsd_m)
                prob = np.where(ok, prob, np.nan).astype(np.float32)
                objects, _ = ndimage.label((heights[n] >= OBJECT_MIN_M) & ok)
                measured = shadow_heights(prob, self.gsd_m, sun, objects, height=heights[n],
                                          threshold=self.model.threshold)
                has = np.isfinite(measured.height) & ok
                shadow[n] = torch.from_numpy(np.nan_to_num(prob, nan=0.0))
                s_on[n] = torch.from_numpy(ok.astype(np.float32))
                s_height[n] = torch.from_numpy(np.where(has, measured.height, 0.0).astype(np.float32))
                s_weight[n] = torch.from_numpy(has.astype(np.float32))
                if self.fuse and spreads is not None and has.any():
                    heights[n], spreads[n] = fuse_heights(heights[n], spreads[n], measured, objects)
                    fused = True
            if fused and spreads is not None:  # new tensors: the engine's may be inference-mode views
                stats.height_mean = torch.from_numpy(heights).to(stats.height_mean.device)
                stats.height_std = torch.from_numpy(spreads).to(dev)
        stats.shadow = shadow.to(dev)
        stats.shadow_on = s_on.to(dev)
        stats.shadow_height = s_height.to(dev)
        stats.shadow_weight = s_weight.to(dev)


__all__ = ["OBJECT_MIN_M", "ShadowStep"]
