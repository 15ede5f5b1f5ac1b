"""The sun from the acquisition time and place, in the raster's grid.

The position comes from pvlib's implementation of NREL's Solar Position Algorithm (Reda & Andreas 2004;
±0.0003° over the years −2000 to 6000), imported only when a time is known. Angles follow the STAC *view*
extension: ``view:sun_azimuth`` clockwise from **true** north, ``view:sun_elevation`` above the horizon. Shadows
are cast on the raster's grid, whose north (the rows' up) differs from true north by the projection's grid
convergence (up to a few degrees at the edge of a UTM zone; :func:`grid_convergence_deg`); :func:`to_grid`
turns one into the other.
"""

from __future__ import annotations

import math
import warnings
from datetime import datetime, timezone

from aerialmtl.errors import InputError

#: Below this elevation (degrees) shadows are too long and too dim to measure: the feature is off.
MIN_ELEVATION_DEG = 5.0


#: The years an acquisition time may lie in: the first aerial photographs, to well past any flight to come. The
#: solar position algorithm covers far more; the limit keeps every later date computation inside the calendar.
FIRST_YEAR, LAST_YEAR = 1850, 2199


class NoTime(ValueError):
    """A time text that names no usable time: why, in words (``str(exc)``), and whether it is a placeholder."""

    def __init__(self, why: str, placeholder: bool = False) -> None:
        super().__init__(why)
        self.placeholder = placeholder


def read_time(text: object) -> datetime:
    """An ISO 8601 time or a TIFF ``DateTime`` read as an aware UTC datetime (see :func:`parse_time`).

    Raises:
        NoTime: not a string, a placeholder for an unknown time (blank, or all zeros as TIFF and EXIF write
            it: ``0000:00:00 00:00:00``), not a time of day, or outside :data:`FIRST_YEAR`–:data:`LAST_YEAR`.
    """
    if not isinstance(text, str):
        kind = ("a boolean" if isinstance(text, bool) else "a number" if isinstance(text, (int, float)) else
                "a list" if isinstance(text, list) else "an object" if isinstance(text, dict) else
                f"a {type(text).__name__}")
        raise NoTime(f"{text!r} is {kind}, not a time")
    raw = text.strip()
    if not raw.strip("0:-T ").strip():  # "", blanks, "0000:00:00 00:00:00", "    :  :     :  :  "
        raise NoTime(f"{text!r} is the placeholder for an unknown time", placeholder=True)
    candidate = raw
    if len(raw) >= 19 and raw[4] == ":" and raw[7] == ":":  # TIFF DateTime "YYYY:MM:DD HH:MM:SS"
        candidate = raw[:4] + "-" + raw[5:7] + "-" + raw[8:]
    candidate = candidate.replace("Z", "+00:00").replace("z", "+00:00")
    try:
        when = datetime.fromisoformat(candidate)
    except ValueError:
        when = None
    if when is None or len(candidate) <= 10:
        raise NoTime(f"{text!r} is not a time of day")
    if not FIRST_YEAR <= when.year <= LAST_YEAR:
        raise NoTime(f"{text!r} lies outside the years {FIRST_YEAR}–{LAST_YEAR} an aerial photograph can be of")
    if when.tzinfo is None:
        when = when.replace(tzinfo=timezone.utc)
    return when.astimezone(timezone.utc)


def parse_time(text: str, what: str = "--acquired") -> datetime:
    """An ISO 8601 time or a TIFF ``DateTime`` read as an aware UTC datetime.

    ISO 8601: ``2019-06-21T16:45:00Z``, ``2019-06-21 09:45-07:00``; a date alone is not enough. TIFF
    ``DateTime``: ``2019:06:21 16:45:00``, which has no time zone. Years :data:`FIRST_YEAR`–:data:`LAST_YEAR`.

    A time without a zone is read as UTC; the caller says so where it matters (:func:`has_zone`). This is the
    reader of a time the user gives (``--acquired``); a file's time goes through :func:`file_time`.

    Raises:
        InputError: not a time of day, or outside those years (names ``what``, the value and the expected form).
    """
    try:
        return read_time(text)
    except NoTime as exc:
        raise InputError(f"{what}: {exc}; give the acquisition time as ISO 8601, e.g. 2019-06-21T16:45:00Z (UTC) "
                         "or 2019-06-21T09:45:00-07:00", param="acquired") from None


def file_time(text: object, what: str, fallback: str) -> datetime | None:
    """The time a file states (a TIFF ``DateTime``, a STAC ``datetime``), or ``None`` with a warning.

    A placeholder (``0000:00:00 00:00:00``, blanks), a text that is no time of day and a year outside
    :data:`FIRST_YEAR`–:data:`LAST_YEAR` are no time: a :class:`UserWarning` says which file holds it (``what``,
    e.g. ``"orthophoto 'o.tif': its TIFF DateTime"``) and what happens instead (``fallback``). Train and predict
    read the tag through this one function.
    """
    try:
        return read_time(text)
    except NoTime as exc:
        warnings.warn(f"{what} {exc}: read as no acquisition time; {fallback}", UserWarning, stacklevel=2)
        return None


def has_zone(text: str) -> bool:
    """Whether time ``text`` names its time zone (``Z`` or an offset); TIFF ``DateTime`` never does."""
    t = text.strip()
    return t.endswith(("Z", "z")) or (len(t) > 19 and t[-6] in "+-" and t[-3] == ":")


def sun_position(when: datetime, lon: float, lat: float) -> tuple[float, float]:
    """``(azimuth, elevation)`` of the sun seen from (``lon``, ``lat``) at ``when``.

    ``lon``, ``lat`` in WGS 84 degrees. Azimuth in degrees clockwise from true north in [0, 360), elevation in
    degrees above the horizon with atmospheric refraction.
    """
    import pandas as pd
    from pvlib import solarposition

    stamp = pd.DatetimeIndex([when.astimezone(timezone.utc)])
    pos = solarposition.get_solarposition(stamp, lat, lon, method="nrel_numpy")
    return float(pos["azimuth"].iloc[0]) % 360.0, float(pos["apparent_elevation"].iloc[0])


def grid_convergence_deg(crs: object, x: float, y: float) -> float:
    """Azimuth of true north on the grid of ``crs`` at map point (``x``, ``y``).

    Degrees clockwise from the grid's north: 0 where the grid follows the meridian, negative east of a UTM
    zone's central meridian (true north leans west of the grid's there).
    """
    from rasterio.crs import CRS
    from rasterio.warp import transform

    src = CRS.from_user_input(crs)
    if src.is_geographic:
        return 0.0
    (lon,), (lat,) = transform(src, "EPSG:4326", [x], [y])
    step = 1e-4 if lat < 89.9 else -1e-4
    (x2,), (y2,) = transform("EPSG:4326", src, [lon], [lat + step])
    angle = math.degrees(math.atan2(x2 - x, y2 - y))
    return angle if step > 0 else angle + 180.0


def to_grid(azimuth_true_deg: float, convergence_deg: float) -> float:
    """A true-north azimuth as an azimuth clockwise from the grid's north (see :func:`grid_convergence_deg`)."""
    return (azimuth_true_deg + convergence_deg) % 360.0


def lonlat(crs: object, x: float, y: float) -> tuple[float, float]:
    """WGS 84 ``(lon, lat)`` of map point (``x``, ``y``) in ``crs``."""
    from rasterio.warp import transform

    (lon,), (lat,) = transform(crs, "EPSG:4326", [x], [y])
    return float(lon), float(lat)


__all__ = ["FIRST_YEAR", "LAST_YEAR", "MIN_ELEVATION_DEG", "NoTime", "file_time", "grid_convergence_deg", "has_zone",
           "lonlat", "parse_time", "read_time", "sun_position", "to_grid"]
