"""Per-building attributes from the pixel values inside its footprint.

Definitions (all in metres / m² / m³ whatever the CRS unit):

* ``height_m`` — the ``percentile``-th percentile (default 50: the median) of the predicted heights of
  its pixels. The median is robust to what the footprint gets wrong: the blurred edge ring (heights
  between ground and roof), wall and ground pixels classified as building, and small rooftop
  structures all stay below half of the pixels, so they barely move it. For a flat roof it is the roof
  height; for a gable roof it is the height of the LoD1 block with the same volume (eave + half the
  rise).
* ``height_std_m`` — the median MC-dropout standard deviation (``height_std.tif``) of the same pixels:
  the typical spread of the heights the statistic is taken from. It is not divided by √n because the
  spreads of the pixels of one roof are strongly correlated (they come from the same dropout masks).
* ``ground_area_m2`` — area of the cleaned footprint polygon.
* ``volume_m3`` — mean predicted height above ground (negative heights count as 0) × ``ground_area_m2``:
  the volume between the ground and the predicted surface over the footprint.
* ``class_confidence`` — mean over the pixels of 1 − H / ln K, H the predictive entropy
  (``class_entropy.tif``, or computed from ``class_probabilities.tif``) and K the number of classes:
  1 = every MC sample certain of one class, 0 = all classes equally likely. Preferred to the mean
  maximum probability because it needs only the entropy layer every prediction with T > 1 has
  (``class_probabilities.tif`` is optional and K times larger) and it uses the whole distribution.
* ``n_pixels`` — pixels of the building in ``classes.tif``.
* ``class_name`` — the building class most of its pixels have.
* ``ground_z_m`` — median DTM elevation under the pixels (only when a DTM is given).

Undefined values (no valid height, no ``height_std.tif``, ...) are NaN.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from aerialmtl.formats.buildings import GROUND_Z_FIELD


def _nanstat(values: np.ndarray | None, fn: Any) -> float:
    if values is None:
        return math.nan
    finite = values[np.isfinite(values)]
    return float(fn(finite)) if finite.size else math.nan


def building_attributes(values: dict[str, np.ndarray], ground_area_m2: float, percentile: float,
                        class_names: Sequence[str]) -> dict[str, Any]:
    """Attributes of one building (see the module docstring).

    Args:
        values: layer → 1-D array over the building's pixels: ``class`` (uint8), ``height`` (m) and
            optionally ``height_std`` (m), ``confidence`` ([0, 1]), ``dtm`` (m); float32, NaN = nodata.
        ground_area_m2: area of the cleaned footprint, m².
        percentile: percentile of the heights giving ``height_m``.
        class_names: names of the class indices.

    Returns:
        field → value, in the order of :data:`aerialmtl.formats.buildings.PREDICTED_FIELDS` (without ``building_id``),
        plus ``ground_z_m`` when ``values`` has ``dtm``.
    """
    heights = values["height"]
    classes = values["class"]
    majority = int(np.argmax(np.bincount(classes))) if classes.size else 0
    mean_height = _nanstat(heights, lambda v: np.maximum(v, 0.0).mean())
    out: dict[str, Any] = {
        "class_name": class_names[majority] if majority < len(class_names) else str(majority),
        "height_m": _nanstat(heights, lambda v: np.percentile(v, percentile)),
        "height_std_m": _nanstat(values.get("height_std"), np.median),
        "ground_area_m2": float(ground_area_m2),
        "volume_m3": mean_height * float(ground_area_m2),
        "class_confidence": _nanstat(values.get("confidence"), np.mean),
        "n_pixels": int(classes.size),
    }
    if "dtm" in values:
        out[GROUND_Z_FIELD] = _nanstat(values["dtm"], np.median)
    return out


__all__ = ["building_attributes"]
