"""Which sun ``predict`` uses for one orthophoto (``--sun auto|AZ,EL|none``), and where it came from.

``auto`` takes, in this order:

1. the acquisition time and place: ``--acquired``, else the ``datetime`` of a STAC item beside the orthophoto
   (``NAME.json``), else its TIFF ``DateTime`` tag — through pvlib's solar position algorithm
   (:mod:`aerialmtl.sun.solar_position`) at the raster's centre. A TIFF ``DateTime`` has no time zone (read as
   UTC) and is often when the file was written rather than flown: where it disagrees with the training fit of
   the same area by more than :data:`DISAGREE_DEG`, the fit is used and both are said;
2. else the sun fitted on the training area (``meta.sun``), when the orthophoto is **of the same flight**:
   its footprint lies within :data:`SAME_FLIGHT_M` of the training area's, and no acquisition time says
   otherwise. An orthophoto elsewhere (another town, another survey) gets no sun from the training area;
3. else none: the feature is off, said once, and the maps are those of ``--sun none``.

``AZ,EL`` is the sun given in degrees (azimuth clockwise from true north, elevation above the horizon, as flight
records and the STAC *view* extension give them); ``none`` switches the feature off. A sun lower than
:data:`~aerialmtl.sun.solar_position.MIN_ELEVATION_DEG` switches it off too (shadows too long and dim).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aerialmtl.errors import InputError
from aerialmtl.io.align import Grid
from aerialmtl.sun.record import TrainingSun
from aerialmtl.sun.solar_position import (
    MIN_ELEVATION_DEG,
    grid_convergence_deg,
    has_zone,
    lonlat,
    parse_time,
    sun_position,
    to_grid,
)

#: A time-and-place sun this far (degrees, azimuth or elevation) from the training fit of the same area is
#: doubted: the fit is used and both are said.
DISAGREE_DEG = 10.0
#: An orthophoto whose footprint lies within this distance (metres) of the training area's is of the same flight.
SAME_FLIGHT_M = 2000.0


def parse_sun(value: str) -> tuple[float, float] | str:
    """``--sun``'s value: ``"auto"``, ``"none"`` or ``(azimuth, elevation)`` in degrees.

    Raises:
        InputError: anything else, or angles out of range (names ``--sun``, the value and the ranges).
    """
    text = str(value).strip().lower()
    if text in ("auto", "none"):
        return text
    parts = text.replace(";", ",").split(",")
    try:
        az, el = (float(p) for p in parts)
    except ValueError:
        raise InputError(f"--sun: {value!r} is neither auto, none nor AZIMUTH,ELEVATION in degrees; pass e.g. "
                         "--sun 135,42 (azimuth clockwise from true north, elevation above the horizon)",
                         param="sun") from None
    if not (math.isfinite(az) and 0.0 <= az <= 360.0):
        raise InputError(f"--sun: azimuth {az:g}° is outside 0–360° (clockwise from true north)", param="sun")
    if not (math.isfinite(el) and 0.0 < el <= 90.0):
        raise InputError(f"--sun: elevation {el:g}° is outside (0, 90]° above the horizon", param="sun")
    return az % 360.0, el


@dataclass(frozen=True)
class SunChoice:
    """The sun used for one orthophoto, and why.

    Attributes:
        azimuth_deg, elevation_deg: the sun (true north; degrees), ``None`` when the feature is off.
        grid_azimuth_deg: the azimuth on the prediction grid (what shadows are cast along).
        source: ``--sun``, ``--acquired``, ``STAC datetime``, ``TIFF DateTime``, ``training fit`` or ``none``.
        note: one line for the user: what was used and why, or why the feature is off.
        acquired: the acquisition time used (ISO 8601, UTC), where one was.
    """

    azimuth_deg: float | None
    elevation_deg: float | None
    grid_azimuth_deg: float | None
    source: str
    note: str
    acquired: str | None = None

    @property
    def on(self) -> bool:
        """Whether the shadow features run."""
        return self.azimuth_deg is not None

    def record(self) -> dict[str, Any]:
        """``prediction.json``'s ``sun``."""
        return {"azimuth_deg": _round(self.azimuth_deg), "elevation_deg": _round(self.elevation_deg),
                "grid_azimuth_deg": _round(self.grid_azimuth_deg), "source": self.source, "note": self.note,
                "acquired": self.acquired}


def _round(v: float | None) -> float | None:
    return None if v is None else round(float(v), 3)


def _off(note: str, source: str = "none") -> SunChoice:
    return SunChoice(None, None, None, source, note)


def acquisition_time(path: str | Path, tags: dict[str, str]) -> tuple[str, str, bool] | None:
    """``(time text, source, has zone)`` of the orthophoto ``path``: a STAC item ``NAME.json`` beside it (its
    ``datetime``, or the middle of ``start_datetime``/``end_datetime``), else its TIFF ``DateTime`` tag
    (``tags``); ``None`` when neither is there. Only regular files are read (a FIFO is never opened).
    """
    p = Path(str(path))
    item = p.with_suffix(".json")
    if item.is_file() and item.stat().st_size < 10_000_000:
        try:
            data = json.loads(item.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            data = None
        props = data.get("properties") if isinstance(data, dict) and data.get("type") == "Feature" else None
        if isinstance(props, dict):
            when = props.get("datetime")
            if not when and props.get("start_datetime") and props.get("end_datetime"):
                a, b = parse_time(props["start_datetime"], item.name), parse_time(props["end_datetime"], item.name)
                when = (a + (b - a) / 2).isoformat()
            if isinstance(when, str) and when:
                return when, f"STAC datetime ({item.name})", has_zone(when)
    tiff = tags.get("TIFFTAG_DATETIME") or _mosaic_time(path)
    if tiff:
        return tiff, "TIFF DateTime", has_zone(tiff)
    return None


#: Source orthophotos of one mosaic whose acquisition times differ by more than this (seconds) are different
#: flights: their suns differ, and one sun for the mosaic would be wrong on part of it.
SAME_FLIGHT_S = 3 * 3600


def _mosaic_time(path: str | Path) -> str | None:
    """The common TIFF ``DateTime`` of the sources of a VRT mosaic ``path``, or ``None`` (not a VRT, no times).

    Raises:
        InputError: the sources were flown at different times (names them; the fix: predict them one by one, or
            ``--sun none``).
    """
    if not str(path).lower().endswith(".vrt"):
        return None
    import rasterio

    try:
        with rasterio.open(str(path)) as src:
            files = [f for f in src.files if not f.lower().endswith(".vrt")]
        times: dict[str, str] = {}
        for f in files:
            with rasterio.open(f) as part:
                stamp = part.tags().get("TIFFTAG_DATETIME")
            if stamp:
                times[f] = stamp
    except rasterio.errors.RasterioError:
        return None
    if not times:
        return None
    parsed = {f: parse_time(t, f) for f, t in times.items()}
    first, last = min(parsed.values()), max(parsed.values())
    if (last - first).total_seconds() > SAME_FLIGHT_S:
        named = ", ".join(f"{Path(f).name} {t}" for f, t in sorted(times.items()))
        raise InputError(f"--sun auto: the mosaic '{path}' joins orthophotos flown at different times ({named}): "
                         "their suns differ; predict them one by one (aerialmtl predict a.tif b.tif ...), each with "
                         "its own sun, or pass --sun none", param="sun")
    return str(next(iter(times.values())))


def _centre(grid: Grid) -> tuple[float, float]:
    t = grid.transform
    return t.c + t.a * grid.width / 2.0, t.f + t.e * grid.height / 2.0


def same_flight(grid: Grid, training: TrainingSun) -> bool:
    """Whether ``grid``'s footprint lies within :data:`SAME_FLIGHT_M` of the training area's."""
    if training.crs is None or training.bounds is None:
        return False
    from rasterio.warp import transform_bounds

    t = grid.transform
    left, top = t.c, t.f
    right, bottom = left + t.a * grid.width, top + t.e * grid.height
    try:
        b = transform_bounds(grid.crs, training.crs, min(left, right), min(top, bottom), max(left, right),
                             max(top, bottom))
    except Exception:  # noqa: BLE001 - a CRS pair without a transformation: not the same flight
        return False
    from rasterio.crs import CRS

    unit = CRS.from_user_input(training.crs).linear_units_factor[1]
    t0, t1, t2, t3 = training.bounds
    gap = max(t0 - b[2], b[0] - t2, t1 - b[3], b[1] - t3, 0.0) * unit
    return bool(gap <= SAME_FLIGHT_M)


def choose_sun(value: str, acquired: str | None, path: str | Path, grid: Grid, tags: dict[str, str],
               training: TrainingSun | None) -> SunChoice:
    """The sun for the orthophoto ``path`` on prediction grid ``grid`` (see the module docstring).

    Args:
        value: ``--sun`` (``auto``, ``none`` or ``AZ,EL``).
        acquired: ``--acquired`` (ISO 8601), or ``None``.
        path, tags: the orthophoto and its GDAL tags (for a STAC item beside it and ``TIFFTAG_DATETIME``).
        grid: the prediction grid.
        training: the checkpoint's :class:`~aerialmtl.sun.record.TrainingSun`, or ``None``.

    Raises:
        InputError: a bad ``--sun`` or ``--acquired``.
    """
    parsed = parse_sun(value)
    x, y = _centre(grid)
    convergence = grid_convergence_deg(grid.crs, x, y)
    if parsed == "none":
        return _off("off (--sun none)")
    if isinstance(parsed, tuple):
        az, el = parsed
        return _checked(az, el, convergence, "--sun", f"sun given: azimuth {az:.1f}°, elevation {el:.1f}°")
    fit = training if training is not None and training.clear else None
    fit_here = fit is not None and same_flight(grid, fit)
    found = (acquired, "--acquired", True) if acquired else acquisition_time(path, tags)
    if found is not None:
        text, source, zoned = found
        when = parse_time(text, source)
        lon, lat = lonlat(grid.crs, x, y)
        az, el = sun_position(when, lon, lat)
        stamp = when.isoformat().replace("+00:00", "Z")
        if fit_here and fit is not None and fit.azimuth_deg is not None and fit.elevation_deg is not None:
            d_az = abs((az - fit.azimuth_deg + 180.0) % 360.0 - 180.0)
            d_el = abs(el - fit.elevation_deg)
            if max(d_az, d_el) > DISAGREE_DEG:
                zone = "" if zoned else ", a time without a zone read as UTC"
                return _checked(
                    fit.azimuth_deg, fit.elevation_deg, convergence, "training fit",
                    f"the sun of the {source} {stamp}{zone} (azimuth {az:.1f}°, elevation {el:.1f}°) is "
                    f"{max(d_az, d_el):.0f}° from the training fit of this area (azimuth {fit.azimuth_deg:.1f}°, "
                    f"elevation {fit.elevation_deg:.1f}°): using the fit; pass --acquired or --sun AZ,EL if the "
                    "time is right", acquired=stamp)
        zone = "" if zoned else " (no time zone: read as UTC)"
        return _checked(az, el, convergence, source.split(" (")[0] if source.startswith("STAC") else source,
                        f"sun of the {source} {stamp}{zone} at {lat:.4f}°N {lon:.4f}°E: azimuth {az:.1f}°, "
                        f"elevation {el:.1f}°", acquired=stamp)
    if fit_here and fit is not None and fit.azimuth_deg is not None and fit.elevation_deg is not None:
        return _checked(fit.azimuth_deg, fit.elevation_deg, convergence, "training fit",
                        f"sun of the training fit (same flight: within {SAME_FLIGHT_M / 1000:g} km of the training "
                        f"area): azimuth {fit.azimuth_deg:.1f}°, elevation {fit.elevation_deg:.1f}°")
    if training is not None and not training.clear:
        return _off(f"off: the training area's sun fit found no clear sun ({training.reason})")
    if fit is not None:
        return _off("off: no acquisition time (pass --acquired or --sun AZ,EL) and the orthophoto is not of the "
                    f"training flight (more than {SAME_FLIGHT_M / 1000:g} km from the training area)")
    return _off("off: no acquisition time (pass --acquired or --sun AZ,EL) and the model holds no sun fit")


def _checked(az: float, el: float, convergence: float, source: str, note: str,
             acquired: str | None = None) -> SunChoice:
    if el < MIN_ELEVATION_DEG:
        return _off(f"off: {note} — a sun below {MIN_ELEVATION_DEG:g}° casts no measurable shadows", source)
    return SunChoice(az, el, to_grid(az, convergence), source, note, acquired)


__all__ = ["DISAGREE_DEG", "SAME_FLIGHT_M", "SunChoice", "acquisition_time", "choose_sun", "parse_sun",
           "same_flight"]
