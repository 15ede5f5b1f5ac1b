"""The height decoder tuned on the orthophotos being mapped, self-supervised by their cast shadows
(``predict --sun-tune STEPS``).

A network trained on one area reads the tall objects of another low, and its blurred objects cast almost no
shadow: on autzen_west's validation block the cast shadows of its heights cover 3.5 % of the pixels where the
lidar heights cast 21 %. The orthophoto itself shows where the shadows are. Before predicting, the height
branch (the ``height`` task blocks and output convolution; encoder and shared blocks frozen, BatchNorm in eval,
dropout off) takes ``steps`` Adam steps on crops of the inputs, with no reference heights. The cast shadows of its
heights as the run writes them (calibrated unless ``--no-calibration``) at each input's sun, rendered
differentiably (:func:`aerialmtl.sun.soft.soft_cast_shadow`), are compared with the shadow probability ``P`` of
the checkpoint's colour shadow classifier (the shadow layer's, for a checkpoint without a shadow head), with the
evidence the rendered heights weigh (:mod:`aerialmtl.sun.render`)::

    LL = Σ_scored s(h) · clip(logit P − logit π, ±MAX_LLR) / n        (π: the mean P of the scored pixels)
    loss = −LL + RAISE_WEIGHT · mean(relu(h − h₀) where h₀ < 2 m)      (flat ground is not raised)

The crops (:data:`CROP` pixels, at most :data:`MAX_CROPS`, spread over the inputs) are read once; each step takes
one of them in turn, so the cost is bounded by the steps whatever the size of the job. Scored pixels are the valid
(and AOI) pixels whose ray towards the sun, up to the longest shadow considered, stays inside the crop: a shadow
cast by an occluder outside the crop is not rendered, so it is not compared.

The number of steps is the bound: the shadows are matched better and better (the evidence's LL passes the
lidar heights' own after ~60 steps on that block) while the heights first improve and then get worse, so it was
chosen on the validation block (experiments/heights_from_the_sun, "self-supervised"). Deterministic: the same
inputs and settings give the same weights.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from rasterio.windows import Window

from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.models.d3net import decode_features, encode_features
from aerialmtl.sun.cast import sun_steps
from aerialmtl.sun.heights import walk_offsets
from aerialmtl.sun.position import Sun
from aerialmtl.sun.render import EPS, pixel_evidence

if TYPE_CHECKING:
    from aerialmtl.inference.ortho import OrthoInput
    from aerialmtl.models.calibration import Calibration
    from aerialmtl.sun.colour import ShadowModel

#: Softness of the rendered shadows, metres (τ of :func:`~aerialmtl.sun.soft.soft_cast_shadow`): at 0.5 the
#: lidar heights' soft shadows cover 27 % of autzen_west's validation block against their hard 21 %; at 0.2, 21 %.
TEMPERATURE_M = 0.2
#: Learning rate of the steps (Adam, the recipe's β₁ 0.5): chosen with the steps on the validation block.
LEARNING_RATE = 1.0e-4
#: Weight of the penalty on raising a pixel the network put below :data:`FLAT_M`.
RAISE_WEIGHT = 1.0
#: Pixels below this height (metres) before tuning are flat ground: raising them is penalised.
FLAT_M = 2.0
#: The tallest object whose whole shadow is rendered (metres) and the longest shadow considered (metres): the
#: rendering's length is ``min(MAX_SHADOW_M, TALLEST_M / tan(elevation))``.
TALLEST_M = 40.0
MAX_SHADOW_M = 80.0
#: The side of the crops tuned on (pixels, a multiple of the encoder's stride 32), and how many at most.
CROP = 512
MAX_CROPS = 8
#: A crop is used when at least this share of its pixels is scored.
MIN_SCORED_SHARE = 0.25


def shadow_length_m(sun: Sun) -> float:
    """The longest shadow rendered at ``sun``, metres (:data:`TALLEST_M`, :data:`MAX_SHADOW_M`)."""
    return min(MAX_SHADOW_M, TALLEST_M / max(sun.tan_elevation, 1e-6))


def inside_rays(shape: tuple[int, int], sun: Sun, gsd_m: float, length_m: float) -> np.ndarray:
    """The pixels (bool (h, w)) whose ray towards ``sun`` stays inside the ``shape`` raster for ``length_m``
    metres: their rendered shadow sees every occluder that can shade them.
    """
    _, _, slope = sun_steps(sun.azimuth_deg)
    n = max(1, int(length_m // (gsd_m * math.hypot(1.0, slope))))  # the steps soft_cast_shadow renders
    off_r, off_c = walk_offsets(sun, n, away=False)
    dr, dc = int(off_r[n]), int(off_c[n])
    h, w = shape
    r = np.arange(h)[:, None] + dr
    c = np.arange(w)[None, :] + dc
    return ((r >= 0) & (r < h)) & ((c >= 0) & (c < w))


@dataclass
class TuneCrop:
    """One crop to tune on.

    Attributes:
        x: float32 (1, C, H, W) the normalised image (H, W multiples of 32; 0 where invalid).
        prob: float32 (H, W) the shadow probability, 0–1 (any value where not ``scored``).
        scored: bool (H, W) the pixels compared (:func:`inside_rays`, valid, in the AOI, with a probability).
        sun: the sun on the crop's grid (azimuth from the grid's north).
    """

    x: torch.Tensor
    prob: np.ndarray
    scored: np.ndarray
    sun: Sun


@dataclass(frozen=True)
class TuneReport:
    """What tuning did (``prediction.json``'s ``sun_tune``).

    Attributes:
        steps: Adam steps taken; crops: crops tuned on; pixels: scored pixels in all.
        ll_before, ll_after: the evidence's mean log-likelihood of the rendered shadows (per scored pixel) before
            and after (higher: the heights' shadows match the orthophoto's better).
        seconds: wall time of the tuning.
    """

    steps: int
    crops: int
    pixels: int
    ll_before: float
    ll_after: float
    seconds: float

    def record(self) -> dict[str, Any]:
        """The JSON fields."""
        return {"steps": self.steps, "crops": self.crops, "scored_pixels": self.pixels,
                "shadow_match_before": round(self.ll_before, 5), "shadow_match_after": round(self.ll_after, 5),
                "seconds": round(self.seconds, 2), "learning_rate": LEARNING_RATE, "temperature_m": TEMPERATURE_M}


def _evidence(crops: list[TuneCrop]) -> list[torch.Tensor]:
    """Per crop, float32 (H, W): :func:`aerialmtl.sun.render.pixel_evidence` of its probability on its scored
    pixels (0 elsewhere), against the mean probability of every crop's scored pixels (one area, one base rate).
    """
    pi = float(np.concatenate([np.clip(c.prob[c.scored], EPS, 1 - EPS) for c in crops]).mean())
    return [torch.from_numpy(pixel_evidence(c.prob, c.scored, pi)) for c in crops]


def tune_height_branch(model: torch.nn.Module, meta: ModelMeta, crops: list[TuneCrop], steps: int,
                       calibration: Calibration | None = None) -> TuneReport:
    """Tune ``model``'s height branch in place on ``crops`` for ``steps`` Adam steps (module docstring); the heights
    are the network's through ``calibration`` (the run's: ``None`` for raw heights), as the maps will be.

    Each step takes one crop, in turn (so a step costs one crop's decoding whatever the job's size). The model is
    left in eval mode with its parameters' ``requires_grad`` as they were.
    """
    from aerialmtl.sun.soft import soft_cast_shadow  # torch's shadows: only a run that tunes

    t0 = time.perf_counter()
    model.eval()
    flags = [p.requires_grad for p in model.parameters()]
    for prm in model.parameters():
        prm.requires_grad_(False)
    branch = list(model.heads["height"].parameters())  # type: ignore[index,union-attr]
    for prm in branch:
        prm.requires_grad_(True)
    evidence = _evidence(crops)
    counts = [int(c.scored.sum()) for c in crops]
    n = max(sum(counts), 1)
    with torch.no_grad():
        feats = [[f.detach() for f in encode_features(model, c.x)] for c in crops]

    def heights(k: int) -> torch.Tensor:
        rows, cols = crops[k].scored.shape
        h = decode_features(model, feats[k], tasks=("height",))["height"][0, 0, :rows, :cols]
        return calibration.height_torch(h) if calibration is not None else h.clamp_min(0.0)

    def match(k: int, h: torch.Tensor) -> torch.Tensor:  # Σ s · evidence over crop k's scored pixels
        c = crops[k]
        return (soft_cast_shadow(h, meta.gsd, c.sun, shadow_length_m(c.sun), temperature_m=TEMPERATURE_M)
                * evidence[k]).sum()

    with torch.no_grad():
        first = [heights(k) for k in range(len(crops))]
        before = sum(float(match(k, h)) for k, h in enumerate(first)) / n
    flat = [h < FLAT_M for h in first]
    opt = torch.optim.Adam(branch, lr=LEARNING_RATE, betas=(0.5, 0.999))
    try:
        for step in range(steps):
            k = step % len(crops)  # one crop per step, in turn: the cost of a step does not grow with the job
            opt.zero_grad()
            h = heights(k)
            raised = torch.relu(h - first[k])[flat[k]].sum() / max(int(flat[k].sum()), 1)
            (-match(k, h) / max(counts[k], 1) + RAISE_WEIGHT * raised).backward()
            opt.step()
        with torch.no_grad():
            after = sum(float(match(k, heights(k))) for k in range(len(crops))) / n
    finally:
        for prm, flag in zip(model.parameters(), flags, strict=True):
            prm.requires_grad_(flag)
        model.eval()
    return TuneReport(steps, len(crops), n, before, after, time.perf_counter() - t0)


def crop_starts(size: int, crop: int, count: int) -> list[int]:
    """``count`` crop offsets spread evenly over ``size`` pixels, the ends included (one: the middle; one at 0
    when the crop covers it).
    """
    if size <= crop:
        return [0]
    if count <= 1:
        return [(size - crop) // 2]
    return sorted({round(i * (size - crop) / (count - 1)) for i in range(count)})


def read_crops(inputs: Sequence[tuple[OrthoInput, Sun]], meta: ModelMeta, shadow_model: ShadowModel,
               aoi: str | Path | None, workers: int = 1) -> list[TuneCrop]:
    """Up to :data:`MAX_CROPS` crops of :data:`CROP` pixels spread over ``inputs`` (each input with its sun on its
    prediction grid), each with the colour classifier's shadow probability (as the shadow layer computes it) and
    at least :data:`MIN_SCORED_SHARE` scored pixels; ``[]`` where none has enough.
    """
    from aerialmtl.inference.reader import Aoi
    from aerialmtl.inference.sanity import normalised, rescaled
    from aerialmtl.inference.shadows import colour_probability, unit_colours
    from aerialmtl.io.align import AlignedRaster

    per_input = max(1, -(-MAX_CROPS // max(len(inputs), 1)))
    side = max(1, math.ceil(math.sqrt(per_input)))
    found: list[TuneCrop] = []
    mean = torch.tensor(meta.mean, dtype=torch.float32)[:, None, None]
    std = torch.tensor(meta.std, dtype=torch.float32)[:, None, None]
    step = max(1, len(inputs) // MAX_CROPS)
    for src, sun in list(inputs)[::step]:
        grid = src.grid
        mask = Aoi(aoi, grid) if aoi is not None else None
        length = shadow_length_m(sun)
        with AlignedRaster(src.path, grid, "image", bands=list(meta.bands), role="orthophoto") as raster:
            for r0 in crop_starts(grid.height, CROP, side):
                for c0 in crop_starts(grid.width, CROP, side):
                    h, w = min(CROP, grid.height - r0), min(CROP, grid.width - c0)
                    win = Window(c0, r0, w, h)
                    data, valid = raster.read(win)
                    scored = valid & inside_rays((h, w), sun, meta.gsd, length)
                    if mask is not None:
                        scored &= mask.mask(win)
                    if scored.mean() < MIN_SCORED_SHARE:
                        continue
                    prob = colour_probability(shadow_model, unit_colours(data[:3], src.rescale, meta.input_dtype),
                                              valid, meta.gsd, workers)
                    scored &= prob.made
                    x = normalised(rescaled(torch.from_numpy(data.astype(np.float32))[None], src.rescale),
                                   torch.from_numpy(valid)[None], mean, std)
                    x = torch.nn.functional.pad(x, (0, (-w) % 32, 0, (-h) % 32))
                    found.append(TuneCrop(x, np.nan_to_num(prob.prob, nan=0.5), scored, sun))
    if len(found) > MAX_CROPS:
        found = [found[round(i * (len(found) - 1) / (MAX_CROPS - 1))] for i in range(MAX_CROPS)]
    return found


__all__ = ["CROP", "LEARNING_RATE", "MAX_CROPS", "TEMPERATURE_M", "TuneCrop", "TuneReport", "crop_starts",
           "inside_rays", "read_crops", "shadow_length_m", "tune_height_branch"]
