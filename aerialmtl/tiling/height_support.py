"""Whether a tile folder's validation split can judge heights: enough reference pixels ≥ 2 m, compared with training.

``best.pt`` is the checkpoint with the best validation score, and the calibration is fitted on validation. A
validation split of bare ground scores a network that paints a few metres on everything as nearly perfect
(MAE 0.04 m on ground), so ``best.pt`` is then chosen on the ground alone. ``tile`` and ``train`` both say so
(:func:`validation_heights_warning`), with the options that draw other splits.

The rule (:func:`cannot_judge`), over valid reference heights, counting pixels as often as patches hold them:

* validation holds fewer than :data:`MIN_VAL_TALL_PIXELS` pixels ≥ :data:`TALL_M` — the count the calibration
  needs to correct a height (:data:`aerialmtl.models.calibration.MIN_SUPPORT_PIXELS`: about a thousand square
  metres at 1 m, a handful of buildings or trees); fewer, and a few roofs decide the score by chance; or
* its share of pixels ≥ :data:`TALL_M` is below :data:`MIN_TALL_SHARE_RATIO` (a quarter) of training's share:
  the validation score then weighs tall pixels four times less than training does, so it mostly measures the
  ground (a random block split varies far less than that between splits of one area).

Nothing is said when training itself holds no pixel ≥ :data:`TALL_M` (there is no tall height to judge).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aerialmtl.formats.tiles import HEIGHT_NODATA, cache_file
from aerialmtl.models.calibration import MIN_SUPPORT_PIXELS, TALL_HEIGHT

#: Height (metres) from which a pixel counts as tall (the calibration's :data:`TALL_HEIGHT`).
TALL_M = TALL_HEIGHT
#: Fewest validation pixels ≥ :data:`TALL_M` for validation to judge heights (the calibration's minimum).
MIN_VAL_TALL_PIXELS = MIN_SUPPORT_PIXELS
#: Validation's share of pixels ≥ :data:`TALL_M` must reach this fraction of training's share.
MIN_TALL_SHARE_RATIO = 0.25
#: What to do about a validation split that cannot judge heights (`aerialmtl tile`'s split options).
SPLIT_FIX = ("draw other splits with `aerialmtl tile ... --overwrite`: a smaller --split-block (more, smaller "
             "blocks), a larger validation share in --split-ratios (e.g. 0.7,0.2,0.1), another --split-seed, or "
             "--split-aoi with a validation area that holds buildings or trees")


@dataclass(frozen=True)
class TallCount:
    """Valid reference-height pixels of a split and how many of them are ≥ :data:`TALL_M`."""

    pixels: int
    tall: int

    @property
    def share(self) -> float:
        """Share of the pixels that are tall (0 without pixels)."""
        return self.tall / self.pixels if self.pixels else 0.0


def count_tall(heights: np.ndarray) -> TallCount:
    """:class:`TallCount` of valid heights (metres; NaN and the nodata value are not counted)."""
    ok = heights[np.isfinite(heights) & (heights != HEIGHT_NODATA)]
    return TallCount(int(ok.size), int(np.count_nonzero(ok >= TALL_M)))


def cache_tall_count(cache_folder: str | Path, split: str) -> TallCount | None:
    """:class:`TallCount` of a split's patch cache (read in chunks), or ``None`` without a height cache."""
    try:
        heights = np.load(cache_file(Path(cache_folder), split, "height"), mmap_mode="r")
    except (OSError, ValueError):
        return None
    pixels = tall = 0
    for start in range(0, len(heights), 64):
        part = count_tall(np.asarray(heights[start:start + 64]))
        pixels, tall = pixels + part.pixels, tall + part.tall
    return TallCount(pixels, tall)


def cannot_judge(train: TallCount, val: TallCount) -> str | None:
    """Why validation ``val`` cannot judge the heights training ``train`` teaches (a phrase), or ``None``."""
    if train.tall == 0:
        return None
    held = f"holds {val.tall} px ≥ {TALL_M:g} m" if val.tall else f"holds no pixel ≥ {TALL_M:g} m"
    if val.tall < MIN_VAL_TALL_PIXELS:
        return f"{held}, fewer than the {MIN_VAL_TALL_PIXELS} needed to judge heights"
    if val.share < MIN_TALL_SHARE_RATIO * train.share:
        return (f"{held}, {100 * val.share:.1f} % of its pixels against {100 * train.share:.1f} % in train: less than "
                f"{MIN_TALL_SHARE_RATIO:g} of train's share, so its scores mostly measure the ground")
    return None


def validation_heights_warning(where: str, train: TallCount, val: TallCount, val_patches: int | None = None,
                               mean_m: float | None = None) -> str | None:
    """The warning for tile folder ``where`` whose validation cannot judge heights (:func:`cannot_judge`), or None.

    It names the counts, what follows (``best.pt`` chosen on the ground, a calibration that corrects no building
    or tree) and the fix (:data:`SPLIT_FIX`).
    """
    why = cannot_judge(train, val)
    if why is None:
        return None
    patches = f"its {val_patches} patches: " if val_patches is not None else ""
    mean = f", mean {mean_m:.2f} m" if mean_m is not None and math.isfinite(mean_m) else ""
    return (f"tile folder '{where}': the val split {why} ({patches}{val.pixels} px{mean}) while train holds "
            f"{train.tall} ({100 * train.share:.0f} %): validation cannot judge heights — best.pt would be chosen on "
            "the ground, and the calibration fitted on it would correct no building or tree; " + SPLIT_FIX)


__all__ = ["MIN_TALL_SHARE_RATIO", "MIN_VAL_TALL_PIXELS", "SPLIT_FIX", "TALL_M", "TallCount", "cache_tall_count",
           "cannot_judge", "count_tall", "validation_heights_warning"]
