"""What training learnt of its area's sun, as a checkpoint stores it (``meta.sun``).

``train`` fits the sun on the training area's orthophoto and reference heights (:mod:`aerialmtl.training.sun`);
``predict --sun auto`` uses it for an orthophoto of the same flight (:mod:`aerialmtl.inference.sun_choice`).
Angles are stored both ways: true north (as the STAC *view* extension and flight records give them) and the
training grid's north (what the shadows were cast on).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from aerialmtl.errors import CheckpointError


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

    def summary(self) -> str:
        """One line: the fitted sun and its sharpness, or why there is none."""
        return self.reason


__all__ = ["TrainingSun"]
