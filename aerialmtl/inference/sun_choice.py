"""Which sun ``predict`` uses for one orthophoto (``--sun auto|AZ,EL|none``), and where it came from.

``auto`` takes, in this order:

1. the acquisition time and place: ``--acquired``, else the ``datetime`` of a STAC item beside the orthophoto
   (``NAME.json``, read with limits: :func:`aerialmtl.formats.stac.read_source_properties`), else its TIFF
   ``DateTime`` tag — through pvlib's solar position algorithm (:mod:`aerialmtl.sun.solar_position`) at the
   raster's centre. A time the user or a STAC item states is used as stated; where its sun is more than
   :data:`DISAGREE_DEG` from the training fit of the same area, a warning gives both suns. A TIFF ``DateTime`` has
   no time zone (read as UTC) and is often when the file was written rather than flown: where it disagrees with
   the fit so, the fit is used and a warning gives both suns (``--acquired`` makes the time count). A file's
   placeholder time (``0000:00:00 00:00:00``, blanks) or impossible one is no time, with a warning naming the file;
2. else the sun fitted on the training area (``meta.sun``), when the orthophoto is **of the same flight**:
   its footprint lies within :data:`SAME_FLIGHT_M` of the training area's, and where it covers part of the
   training area its pixels there are the training orthophoto's (:mod:`aerialmtl.sun.flight`: a later flight of
   the same town is not, and gets no sun from the training fit). An orthophoto elsewhere (another town, another
   survey) gets no sun from the training area; a time of its own (step 1) is used as stated;
3. else none: the feature is off, said once, and the maps are those of ``--sun none``.

``AZ,EL`` is the sun given in degrees (azimuth clockwise from true north, elevation above the horizon, as flight
records and the STAC *view* extension give them), used whatever the time says; ``none`` switches the feature off.
A sun lower than :data:`~aerialmtl.sun.solar_position.MIN_ELEVATION_DEG` switches it off too (shadows too long and
dim).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import rasterio

from aerialmtl.errors import InputError
from aerialmtl.formats.stac import read_source_properties, source_item_path
from aerialmtl.io.align import Grid, open_raster
from aerialmtl.io.place import NoPlace, wgs84_outline
from aerialmtl.sun.flight import SAME_FLIGHT_R, FlightChip, FlightMatch, grey_levels, match_chips
from aerialmtl.sun.record import TrainingSun
from aerialmtl.sun.solar_position import (
    MIN_ELEVATION_DEG,
    file_time,
    grid_convergence_deg,
    has_zone,
    lonlat,
    parse_time,
    sun_position,
    to_grid,
)

#: A time-and-place sun this far (degrees, azimuth or elevation) from the training fit of the same area is warned
#: about, both suns given; a TIFF ``DateTime``'s is doubted (the fit is used).
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
    if not (math.isfinite(el) and 0.0 < el < 90.0):
        raise InputError(f"--sun: elevation {el:g}° is outside (0, 90)° above the horizon (a sun at the zenith "
                         "casts no shadow to measure); pass e.g. --sun 135,42", param="sun")
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


#: What happens when a file's time is no time (said in its warning).
_NO_TIME = "pass --acquired (or --sun AZ,EL) if you know when it was flown"


@dataclass(frozen=True)
class Acquisition:
    """An acquisition time and where it was read: ``source`` (``--acquired``, ``STAC datetime (NAME.json)``,
    ``TIFF DateTime``); ``zoned``: whether the text named its time zone (a TIFF ``DateTime`` never does).
    """

    when: datetime
    source: str
    zoned: bool

    @property
    def stamp(self) -> str:
        """The time as ISO 8601 UTC (``2019-06-21T16:45:00Z``)."""
        return self.when.isoformat().replace("+00:00", "Z")


def acquisition_time(path: str | Path, tags: dict[str, str]) -> Acquisition | None:
    """The acquisition time of the orthophoto ``path``: a STAC item ``NAME.json`` beside it (its ``datetime``, or
    the middle of ``start_datetime``/``end_datetime``), else its TIFF ``DateTime`` tag (``tags``), else the common
    one of a VRT mosaic's sources; ``None`` when none states a usable one (a placeholder or impossible time is
    warned about, naming the file, and read as none). Only regular files are read (a FIFO is never opened).

    Raises:
        InputError: a mosaic's sources were flown at different times (see :func:`_mosaic_time`).
    """
    props = read_source_properties(path)
    if props is not None:
        item = source_item_path(path)
        source = f"STAC datetime ({item.name})"
        stated = props.get("datetime")
        if stated is not None:
            when = file_time(stated, f"STAC item '{item}': its datetime", _NO_TIME)
            if when is not None:
                return Acquisition(when, source, has_zone(str(stated)))
        elif props.get("start_datetime") is not None or props.get("end_datetime") is not None:
            a = file_time(props.get("start_datetime"), f"STAC item '{item}': its start_datetime", _NO_TIME)
            b = file_time(props.get("end_datetime"), f"STAC item '{item}': its end_datetime", _NO_TIME)
            if a is not None and b is not None:
                return Acquisition(a + (b - a) / 2, source, has_zone(str(props["start_datetime"])))
    stamp = tags.get("TIFFTAG_DATETIME")
    if stamp is not None:
        when = file_time(stamp, f"orthophoto '{path}': its TIFF DateTime", _NO_TIME)
        return Acquisition(when, "TIFF DateTime", has_zone(stamp)) if when is not None else None
    return _mosaic_time(path)


#: Source orthophotos of one mosaic whose acquisition times differ by more than this (seconds) are different
#: flights: their suns differ, and one sun for the mosaic would be wrong on part of it.
SAME_FLIGHT_S = 3 * 3600


def _mosaic_time(path: str | Path) -> Acquisition | None:
    """The common TIFF ``DateTime`` of the sources of a VRT mosaic ``path``, or ``None`` (not a VRT, no times).

    A mosaic some of whose sources state no usable time has none: their time is not taken to be the others'
    (a warning names them).

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
        stamps: dict[str, str | None] = {}
        for f in files:
            with rasterio.open(f) as part:
                stamps[f] = part.tags().get("TIFFTAG_DATETIME")
    except rasterio.errors.RasterioError:
        return None
    if not any(stamps.values()):
        return None
    parsed = {f: file_time(t, f"mosaic source '{f}': its TIFF DateTime", _NO_TIME) if t else None
              for f, t in stamps.items()}
    times = {f: t for f, t in parsed.items() if t is not None}
    undated = sorted(Path(f).name for f, t in parsed.items() if t is None)
    if undated:
        warnings.warn(f"mosaic '{path}': {len(undated)} of its {len(parsed)} sources state no acquisition time "
                      f"({', '.join(undated[:5])}{', ...' if len(undated) > 5 else ''}); the others' is not taken "
                      f"for theirs, so the mosaic has none; {_NO_TIME}", UserWarning, stacklevel=3)
        return None
    first, last = min(times.values()), max(times.values())
    if (last - first).total_seconds() > SAME_FLIGHT_S:
        named = ", ".join(f"{Path(f).name} {stamps[f]}" for f in sorted(times))
        raise InputError(f"--sun auto: the mosaic '{path}' joins orthophotos flown at different times ({named}): "
                         "their suns differ; predict them one by one (aerialmtl predict a.tif b.tif ...), each with "
                         "its own sun, or pass --sun none", param="sun")
    return Acquisition(first + (last - first) / 2, "TIFF DateTime", False)


def _centre(grid: Grid) -> tuple[float, float]:
    t = grid.transform
    return t.c + t.a * grid.width / 2.0, t.f + t.e * grid.height / 2.0


def same_flight(grid: Grid, training: TrainingSun) -> bool:
    """Whether ``grid``'s footprint lies within :data:`SAME_FLIGHT_M` of the training area's.

    Measured on ``grid``'s CRS; a training area that cannot be brought there (no transformation between the two
    CRSs, bounds outside the training CRS's domain) is not of the same flight.
    """
    if training.crs is None or training.bounds is None:
        return False
    from rasterio.warp import transform_bounds

    try:
        b = transform_bounds(training.crs, grid.crs, *training.bounds)
        unit = grid.unit_m
    except Exception:  # noqa: BLE001 - PROJ's and the CRS checks' own errors: no common ground, not one flight
        return False
    if not all(math.isfinite(v) for v in b):
        return False
    left, bottom, right, top = grid.bounds
    gap = max(b[0] - right, left - b[2], b[1] - top, bottom - b[3], 0.0) * unit
    return bool(gap <= SAME_FLIGHT_M)


def flight_match(path: str | Path, training: TrainingSun) -> FlightMatch:
    """How the orthophoto ``path`` matches the training orthophoto's chips (``training.chips``) it covers.

    Each chip is read from ``path`` onto its own grid in the training CRS (bilinear, or averaged where the
    orthophoto is finer, as tiling does; the mean of ``training.chip_bands``; NaN where the orthophoto has no data by
    its nodata value, mask or alpha band). An orthophoto that cannot be read so (no transformation between the
    CRSs) compares no chip.
    """
    if not training.chips or training.crs is None:
        return FlightMatch(None, 0)
    from affine import Affine
    from rasterio.warp import Resampling, reproject, transform_bounds

    try:
        with open_raster(path, "orthophoto") as src:
            left, bottom, right, top = transform_bounds(src.crs, training.crs, *src.bounds)
            alpha = next((i + 1 for i, c in enumerate(src.colorinterp) if c.name == "alpha"), 0)
            bands = list(training.chip_bands) or [i for i in range(1, src.count + 1) if i != alpha][:3]
            if not bands or max(bands) > src.count:  # not the bands the model reads: predict says so itself
                return FlightMatch(None, 0)
            alpha = 0 if alpha in bands else alpha  # a band the model was trained on is data, whatever its tag
            coarser = (right - left) / src.width / training.chips[0].pixel  # its pixel over the chips'
            how = Resampling.average if coarser < 1.0 else Resampling.bilinear  # as the tiles were made

            def read(chip: FlightChip) -> np.ndarray | None:
                west, south, east, north = chip.bounds
                if west >= right or east <= left or south >= top or north <= bottom:
                    return None
                out = np.full((len(bands), chip.size, chip.size), np.nan, np.float32)
                for k, band in enumerate(bands):
                    reproject(rasterio.band(src, band), out[k], src_alpha=alpha, dst_nodata=np.nan,
                              dst_transform=Affine(chip.pixel, 0.0, chip.left, 0.0, -chip.pixel, chip.top),
                              dst_crs=training.crs, resampling=how)
                return grey_levels(out)

            return match_chips(training.chips, read, coarser)
    except Exception:  # noqa: BLE001 - unreadable here, or PROJ's own errors (CPLE_*): no chip compared
        return FlightMatch(None, 0)


def _place(grid: Grid) -> tuple[float, float, float] | str:
    """``(lon, lat, grid convergence)`` at ``grid``'s centre, or why it has none (a local CRS, outside its domain;
    an orthophoto is refused for that when it is opened, :meth:`~aerialmtl.inference.ortho.OrthoInput.open`).
    """
    x, y = _centre(grid)
    try:
        wgs84_outline(grid.crs, grid.bounds, 2)
        lon, lat = lonlat(grid.crs, x, y)
        convergence = grid_convergence_deg(grid.crs, x, y)
    except NoPlace as exc:
        return str(exc)
    except Exception:  # noqa: BLE001 - PROJ's own errors (CPLE_*)
        return "its centre lies outside the domain of its CRS"
    if not (math.isfinite(lon) and math.isfinite(lat) and math.isfinite(convergence)):
        return "its centre lies outside the domain of its CRS"
    return lon, lat, convergence


def _apart(az: float, el: float, fit: TrainingSun) -> float:
    assert fit.azimuth_deg is not None and fit.elevation_deg is not None
    return max(abs((az - fit.azimuth_deg + 180.0) % 360.0 - 180.0), abs(el - fit.elevation_deg))


def choose_sun(value: str, acquired: str | None, path: str | Path, grid: Grid, tags: dict[str, str],
               training: TrainingSun | None) -> SunChoice:
    """The sun for the orthophoto ``path`` on prediction grid ``grid`` (see the module docstring).

    A disagreement between a stated time's sun and the training fit is warned about (:class:`UserWarning`, both
    suns); the choice's :attr:`~SunChoice.note` says it too.

    Args:
        value: ``--sun`` (``auto``, ``none`` or ``AZ,EL``).
        acquired: ``--acquired`` (ISO 8601), or ``None``.
        path, tags: the orthophoto and its GDAL tags (for a STAC item beside it and ``TIFFTAG_DATETIME``).
        grid: the prediction grid.
        training: the checkpoint's :class:`~aerialmtl.sun.record.TrainingSun`, or ``None``.

    Raises:
        InputError: a bad ``--sun`` or ``--acquired``; a mosaic of flights at different times.
    """
    parsed = parse_sun(value)
    if parsed == "none":
        return _off("off (--sun none)")
    name = Path(str(path)).name
    place = _place(grid)
    if isinstance(parsed, tuple):
        az, el = parsed
        if isinstance(place, str):  # a grid with no place: its north is the only north there is
            return _checked(az, el, 0.0, "--sun", f"sun given: azimuth {az:.1f}°, elevation {el:.1f}° (on the "
                            f"grid's north: {place})")
        return _checked(az, el, place[2], "--sun", f"sun given: azimuth {az:.1f}°, elevation {el:.1f}°")
    if isinstance(place, str):
        return _off(f"off: the orthophoto has no place on Earth ({place}), so no sun of a time or a training "
                    "area; pass --sun AZ,EL")
    lon, lat, convergence = place
    fit = training if training is not None and training.clear else None
    fit_here = fit is not None and same_flight(grid, fit)
    flight = flight_match(path, fit) if fit_here and fit is not None else FlightMatch(None, 0)
    fit_here = fit_here and not flight.other_flight
    found = Acquisition(parse_time(acquired), "--acquired", True) if acquired else acquisition_time(path, tags)
    if found is not None:
        az, el = sun_position(found.when, lon, lat)
        stamp = found.stamp
        zone = "" if found.zoned else " (no time zone: read as UTC)"
        label = found.source.split(" (")[0] if found.source.startswith("STAC") else found.source
        note = (f"sun of the {found.source} {stamp}{zone} at {lat:.4f}°N {lon:.4f}°E: azimuth {az:.1f}°, "
                f"elevation {el:.1f}°")
        if fit_here and fit is not None and (d := _apart(az, el, fit)) > DISAGREE_DEG:
            both = (f"the sun of the {found.source} {stamp}{zone} (azimuth {az:.1f}°, elevation {el:.1f}°) is "
                    f"{d:.0f}° from the training fit of this area (azimuth {fit.azimuth_deg:.1f}°, elevation "
                    f"{fit.elevation_deg:.1f}°)")
            assert fit.azimuth_deg is not None and fit.elevation_deg is not None
            if label == "TIFF DateTime":  # no zone, often the file's write time: doubted, and said
                choice = _checked(fit.azimuth_deg, fit.elevation_deg, convergence, "training fit",
                                  f"{both}: using the fit (a TIFF DateTime is often when the file was written); "
                                  "pass --acquired with the time if it is right, or --sun AZ,EL", acquired=stamp)
            else:  # the user's or the STAC item's word: used as stated
                fix = ("if it is not when the orthophoto was flown, correct --acquired (its time zone too)"
                       if label == "--acquired" else "if the time is wrong, pass --acquired with the right one")
                choice = _checked(az, el, convergence, label,
                                  f"{both}: using the sun of the {found.source} as "
                                  f"{'given' if label == '--acquired' else 'stated'}; {fix}, or pass --sun AZ,EL",
                                  acquired=stamp)
            if choice.on:  # an off choice is said by its caller, with this note
                warnings.warn(f"{name}: {choice.note}", UserWarning, stacklevel=2)
            return choice
        return _checked(az, el, convergence, label, note, acquired=stamp)
    return _without_time(fit if fit_here else None, flight, training, convergence)


def _without_time(fit: TrainingSun | None, flight: FlightMatch, training: TrainingSun | None,
                  convergence: float) -> SunChoice:
    """The sun of an orthophoto without an acquisition time: the training fit ``fit`` where it is of the training
    flight (``None`` where not), else off, saying why (``flight``: how its pixels matched the training chips).
    """
    if fit is not None and fit.azimuth_deg is not None and fit.elevation_deg is not None:
        why = (f"its pixels match the training orthophoto's at r = {flight.r:.3f} over {flight.chips} places"
               if flight.r is not None else f"within {SAME_FLIGHT_M / 1000:g} km of the training area")
        return _checked(fit.azimuth_deg, fit.elevation_deg, convergence, "training fit",
                        f"sun of the training fit (same flight: {why}): azimuth {fit.azimuth_deg:.1f}°, elevation "
                        f"{fit.elevation_deg:.1f}°")
    if flight.other_flight:
        return _off(f"off: no acquisition time, and the orthophoto covers the training area but is another flight "
                    f"(its pixels there match the training orthophoto's at r = {flight.r:.3f} over {flight.chips} "
                    f"places; the same flight gives {SAME_FLIGHT_R:g} or more), so the training fit's sun is not its "
                    "sun: pass --acquired with when it was flown, or --sun AZ,EL")
    if training is not None and not training.clear:
        return _off(f"off: the training area's sun fit found no clear sun ({training.reason})")
    if training is not None:
        return _off("off: no acquisition time (pass --acquired or --sun AZ,EL) and the orthophoto is not of the "
                    f"training flight (more than {SAME_FLIGHT_M / 1000:g} km from the training area)")
    return _off("off: no acquisition time (pass --acquired or --sun AZ,EL) and the model holds no sun fit")


def _checked(az: float, el: float, convergence: float, source: str, note: str,
             acquired: str | None = None) -> SunChoice:
    if el < MIN_ELEVATION_DEG:
        return _off(f"off: {note} — a sun below {MIN_ELEVATION_DEG:g}° casts no measurable shadows", source)
    return SunChoice(az, el, to_grid(az, convergence), source, note, acquired)


__all__ = ["DISAGREE_DEG", "SAME_FLIGHT_M", "Acquisition", "SunChoice", "acquisition_time", "choose_sun",
           "flight_match", "parse_sun", "same_flight"]
