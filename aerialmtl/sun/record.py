"""What training learnt of its area's sun, as a checkpoint stores it (``meta.sun``).

``train`` fits the sun on the training area's orthophoto and reference heights (:mod:`aerialmtl.training.sun`);
``predict --sun auto`` uses it for an orthophoto of the same flight (:mod:`aerialmtl.inference.sun_choice`).
Angles are stored both ways: true north (as the STAC *view* extension and flight records give them) and the
training grid's north (what the shadows were cast on).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from aerialmtl.errors import CheckpointError
from aerialmtl.sun.flight import FlightChip

#: The feature set of the shadow classifier this version computes (:data:`aerialmtl.sun.colour.FEATURES`) and its
#: logistic weights, intercept first (:data:`aerialmtl.sun.colour.N_FEATURES` + 1): what a stored classifier must
#: hold. Here, not in :mod:`aerialmtl.sun.colour`, so that reading a checkpoint checks its classifier without
#: importing scipy and the numba kernels.
SHADOW_FEATURES = "colour-v1"
SHADOW_WEIGHTS = 13


def shadow_model_problem(record: Mapping[str, Any]) -> str | None:
    """What makes ``record`` (:meth:`aerialmtl.sun.ShadowModel.to_dict`) unusable as a fitted shadow classifier, or
    ``None`` when it is sound.

    A fitted classifier of feature set :data:`SHADOW_FEATURES`: :data:`SHADOW_WEIGHTS` finite weights, one finite
    mean and one finite scale > 0 per feature, a threshold in (0, 1] and a pixel size > 0 (metres). A record
    that fails gives no shadow layer worth writing: NaN weights or a zero scale make every probability NaN (a
    ``shadow.tif`` of nothing), a NaN threshold finds no shadow run (an empty ``shadow_height.tif``).
    """
    if not isinstance(record, Mapping):
        return f"it is a {type(record).__name__}, not a mapping"
    missing = [k for k in ("gsd_m", "features", "mean", "scale", "weights") if k not in record]
    if missing:
        return f"it lacks {', '.join(missing)} (keys: {', '.join(sorted(map(str, record)))})"
    if record["features"] != SHADOW_FEATURES:
        return f"its feature set is {record['features']!r}, this version computes {SHADOW_FEATURES!r}"
    n = SHADOW_WEIGHTS - 1
    for name, count in (("weights", SHADOW_WEIGHTS), ("mean", n), ("scale", n)):
        values = record[name]
        if not isinstance(values, (list, tuple)) or len(values) != count:
            size = len(values) if isinstance(values, (list, tuple)) else type(values).__name__
            return f"it holds {size} {name} where the feature set needs {count}"
        if not all(_finite(v) for v in values):
            return f"its {name} are not all finite numbers"
    if not all(float(v) > 0 for v in record["scale"]):
        return "its scales are not all > 0 (a zero scale divides every feature by zero)"
    threshold = record.get("threshold", 0.5)
    if not (_finite(threshold) and 0.0 < float(threshold) <= 1.0):
        return f"its threshold {threshold!r} is not a probability in (0, 1]"
    if not (_finite(record["gsd_m"]) and float(record["gsd_m"]) > 0):
        return f"its pixel size gsd_m {record['gsd_m']!r} is not a positive number of metres"
    return None


def _finite(value: object) -> bool:
    """Whether ``value`` is a finite real number (not a bool, a string or NaN)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class TrainingSun:
    """The sun fitted on the training area, with what is needed to reuse it.

    Attributes:
        clear: the fit found one clear optimum (the shadow features may be used); when False the angles are
            ``None`` and :attr:`reason` says why (overcast, a sun near the zenith, no tall structures).
        azimuth_deg: sun azimuth, degrees clockwise from true north, [0, 360).
        elevation_deg: sun elevation above the horizon, degrees, (0, 90).
        grid_azimuth_deg: the azimuth on the training grid (clockwise from the grid's north).
        score: the fit's objective at its optimum (correlation of the shadow score with the cast shadows).
        sharpness: how clear the optimum is (see :class:`aerialmtl.sun.SunFit`).
        reason: one line for the user: the fit, or why there is none.
        crs: the training area's CRS (WKT or EPSG code).
        bounds: the training area's footprint in :attr:`crs`, ``(left, bottom, right, top)``.
        acquired: the training orthophoto's acquisition time (ISO 8601 UTC) where it records one, else ``None``.
        time_sun: the sun of that time and place ``[azimuth, elevation]`` (true north), where known.
        shadow_model: the area's shadow classifier (:meth:`aerialmtl.sun.ShadowModel.to_dict`), or ``None``.
        chips: squares of the training orthophoto (:mod:`aerialmtl.sun.flight`): an orthophoto that covers the
            training area is of the training flight, and so has its sun, only where its pixels match them. Empty in
            checkpoints fitted before they were kept (place alone decides there).
        chip_bands: the 1-based orthophoto bands the chips' grey levels average (``tile --bands``'s first three);
            empty: the orthophoto's first three (its alpha band left out).
    """

    clear: bool
    reason: str
    azimuth_deg: float | None = None
    elevation_deg: float | None = None
    grid_azimuth_deg: float | None = None
    score: float = 0.0
    sharpness: float = 0.0
    crs: str | None = None
    bounds: tuple[float, float, float, float] | None = None
    acquired: str | None = None
    time_sun: tuple[float, float] | None = None
    shadow_model: dict[str, Any] | None = None
    chips: tuple[FlightChip, ...] = ()
    chip_bands: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.clear and (self.azimuth_deg is None or self.elevation_deg is None or self.grid_azimuth_deg is None):
            raise CheckpointError("checkpoint meta is invalid: sun.clear needs azimuth_deg, elevation_deg and "
                                  "grid_azimuth_deg")
        for name in ("azimuth_deg", "grid_azimuth_deg"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and 0.0 <= v < 360.0):
                raise CheckpointError(f"checkpoint meta is invalid: sun.{name} must be in [0, 360) degrees, got {v}")
        if self.elevation_deg is not None and not (math.isfinite(self.elevation_deg) and 0 < self.elevation_deg < 90):
            raise CheckpointError("checkpoint meta is invalid: sun.elevation_deg must be in (0, 90) degrees, got "
                                  f"{self.elevation_deg}")
        if not all(isinstance(b, int) and b >= 1 for b in self.chip_bands):
            raise CheckpointError(f"checkpoint meta is invalid: sun.chip_bands must be 1-based band numbers, got "
                                  f"{self.chip_bands}")
        if self.shadow_model is not None:
            problem = shadow_model_problem(self.shadow_model)
            if problem is not None:
                raise CheckpointError(
                    f"checkpoint meta is invalid: its shadow classifier (sun.shadow_model) is unusable: {problem}; "
                    "refit it on the training tiles (aerialmtl.training.sun.sun_checkpoint(CHECKPOINT, TILES))")

    def summary(self) -> str:
        """One line: the fitted sun and its sharpness, or why there is none."""
        return self.reason


__all__ = ["SHADOW_FEATURES", "SHADOW_WEIGHTS", "TrainingSun", "shadow_model_problem"]
