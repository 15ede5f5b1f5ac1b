"""The sun's position over a raster: one (azimuth, elevation) pair for a whole flight.

Conventions (as in :mod:`aerialmtl.data.synth.shading`): the azimuth is the direction *towards* the sun in
degrees clockwise from grid north (the raster's up: row 0 is the northern edge, column 0 the western one;
90 = east, 180 = south), the elevation the sun's angle above the horizon in degrees.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import SupportsFloat, SupportsIndex

from aerialmtl.errors import InputError

#: Accepted ranges: azimuth in [0, 360), elevation in the open interval (0, 90).
AZIMUTH_RANGE = (0.0, 360.0)
ELEVATION_RANGE = (0.0, 90.0)


@dataclass(frozen=True)
class Sun:
    """The sun's direction.

    Attributes:
        azimuth_deg: direction towards the sun, degrees clockwise from grid north, in [0, 360).
        elevation_deg: degrees above the horizon, in (0, 90).

    Raises:
        InputError: (a ``ValueError``) a value outside its range or not a finite number; the message names
            the value and the range (``param="sun"``).
    """

    azimuth_deg: float
    elevation_deg: float

    def __post_init__(self) -> None:
        az, el = _number("azimuth", self.azimuth_deg), _number("elevation", self.elevation_deg)
        if not AZIMUTH_RANGE[0] <= az < AZIMUTH_RANGE[1]:
            raise InputError(f"'sun' azimuth {self.azimuth_deg!r} is outside [0, 360) degrees (clockwise from grid "
                             "north, towards the sun); pass e.g. 'sun=100,45'", param="sun")
        if not ELEVATION_RANGE[0] < el < ELEVATION_RANGE[1]:
            raise InputError(f"'sun' elevation {self.elevation_deg!r} is outside (0, 90) degrees above the horizon; "
                             "pass e.g. 'sun=100,45'", param="sun")
        object.__setattr__(self, "azimuth_deg", az)
        object.__setattr__(self, "elevation_deg", el)

    @property
    def tan_elevation(self) -> float:
        """tan(elevation): metres of height per metre of shadow."""
        return math.tan(math.radians(self.elevation_deg))

    def towards(self) -> tuple[float, float]:
        """Unit step towards the sun in raster (row, column) coordinates (rows grow southwards)."""
        az = math.radians(self.azimuth_deg)
        return -math.cos(az), math.sin(az)

    def to_dict(self) -> dict[str, float]:
        """``{"azimuth_deg": ..., "elevation_deg": ...}`` (plain floats)."""
        return {"azimuth_deg": float(self.azimuth_deg), "elevation_deg": float(self.elevation_deg)}

    @classmethod
    def from_dict(cls, d: Mapping[str, object]) -> Sun:
        """Inverse of :meth:`to_dict` (validated)."""
        try:
            return cls(as_float(d["azimuth_deg"]), as_float(d["elevation_deg"]))
        except KeyError as exc:
            raise InputError(f"a sun record needs 'azimuth_deg' and 'elevation_deg', got keys {sorted(d)}",
                             param="sun") from exc

    def __str__(self) -> str:
        return f"azimuth {self.azimuth_deg:.1f}°, elevation {self.elevation_deg:.1f}°"


def as_float(value: object) -> float:
    """``float(value)`` of a number read from a record (JSON/YAML: ``object`` until checked).

    Raises:
        TypeError: ``value`` is no number, numeric string or bytes (what :class:`float` itself refuses).
        ValueError: a string that is no number.
    """
    if isinstance(value, (SupportsFloat, SupportsIndex, str, bytes, bytearray)):
        return float(value)
    raise TypeError(f"float() argument must be a string or a real number, not {type(value).__name__!r}")


def as_floats(value: object) -> list[float]:
    """:func:`as_float` of each item of a list read from a record; TypeError when ``value`` is no iterable."""
    if not isinstance(value, Iterable):
        raise TypeError(f"{type(value).__name__!r} object is not iterable")
    return [as_float(v) for v in value]


def _number(name: str, value: object) -> float:
    try:
        out = as_float(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"'sun' {name} must be a number of degrees, got {value!r}; pass e.g. 'sun=100,45'",
                         param="sun") from exc
    if not math.isfinite(out):
        raise InputError(f"'sun' {name} must be a finite number of degrees, got {value!r}; pass e.g. 'sun=100,45'",
                         param="sun")
    return out
