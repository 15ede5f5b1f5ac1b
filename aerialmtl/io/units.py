"""Units of length: every distance aerialmtl reasons about is in metres.

Horizontal: a raster's pixel size and coordinates are in the linear unit of its CRS (metre, foot, US
survey foot, ...). :func:`metres_per_unit` gives the conversion factor from the CRS itself
(``CRS.linear_units_factor``), so a GSD, a split block or a window extent in metres is converted to
CRS units in one place. A geographic CRS (degrees) has no such factor; it cannot define a pixel grid
in metres and is refused with a message that says how to reproject (:func:`require_projected`).

Vertical: heights (DSM, DTM, nDSM, reference heights) are converted to metres when they are read.
Their unit comes from the file when it states one — the vertical part of a compound CRS (e.g.
``EPSG:2994+6360``, NAVD88 height in US survey feet) or the band's unit type (GDAL reads the GeoTIFF
``VerticalUnitsGeoKey`` into it) — otherwise from the caller's ``z_unit`` (``"m"``, ``"ft"`` or
``"us-ft"``; default metres). A file that states a unit which contradicts an explicit ``z_unit`` is an
error rather than a guess.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Literal

from rasterio.crs import CRS

from aerialmtl.errors import AlignmentError, InputError

ZUnit = Literal["m", "ft", "us-ft"]

#: Metres per unit of each vertical unit a user can name.
Z_UNITS: dict[str, float] = {"m": 1.0, "ft": 0.3048, "us-ft": 1200.0 / 3937.0}

#: How files spell those units (lower case, spaces and underscores removed) → our name.
_UNIT_ALIASES = {
    "m": "m", "metre": "m", "meter": "m", "metres": "m", "meters": "m",
    "ft": "ft", "foot": "ft", "feet": "ft", "internationalfoot": "ft", "intlfoot": "ft", "foot(international)": "ft",
    "us-ft": "us-ft", "usft": "us-ft", "ftus": "us-ft", "ussurveyfoot": "us-ft", "ussurveyfeet": "us-ft",
    "us-survey-foot": "us-ft", "foot_us": "us-ft", "footus": "us-ft", "us-foot": "us-ft",
}


def utm_epsg(lon: float, lat: float) -> int:
    """EPSG code of the WGS 84 / UTM zone containing (``lon``, ``lat``) (326xx north, 327xx south)."""
    zone = min(60, max(1, int(math.floor((lon + 180.0) / 6.0)) + 1))
    return (32600 if lat >= 0 else 32700) + zone


def require_projected(crs: CRS, role: str, path: object, lonlat: tuple[float, float] | None = None) -> None:
    """Raise :class:`AlignmentError` unless ``crs`` is projected (has a linear unit).

    Args:
        crs: the raster's CRS.
        role: what the raster is (``"orthophoto"``), named in the message.
        path: the file, named in the message.
        lonlat: a point of the raster in degrees, to suggest its UTM zone.
    """
    if crs.is_projected:
        return
    target = f"EPSG:{utm_epsg(*lonlat)}" if lonlat is not None else "EPSG:326xx (the UTM zone of the area)"
    raise AlignmentError(
        f"{role} '{path}' is in a geographic CRS ({crs.to_string()}, degrees), so its pixels have no size in "
        f"metres; reproject it to a projected CRS in metres first, e.g. "
        f"`gdalwarp -t_srs {target} -r bilinear {path} projected.tif`"
    )


def metres_per_unit(crs: CRS | None, role: str = "raster", path: object = "<grid>") -> float:
    """Metres per linear unit of the projected ``crs`` (1 for metres, 0.3048 for international feet).

    Args:
        crs: the CRS (``None`` when the file has none).
        role, path: the layer and file, named in messages.

    Raises:
        AlignmentError: ``crs`` is missing or geographic (see :func:`require_projected`).
    """
    if crs is None:
        raise AlignmentError(
            f"{role} '{path}' has no CRS, so its pixels have no size in metres; assign one "
            f"(e.g. `gdal_edit.py -a_srs EPSG:XXXX {path}`)"
        )
    if not crs.is_projected:
        require_projected(crs, role, path)
    return float(crs.linear_units_factor[1])


def linear_unit_name(crs: CRS) -> str:
    """The CRS's own name of its linear unit (``"metre"``, ``"foot"``, ``"US survey foot"``, ...)."""
    return str(crs.linear_units_factor[0]) if crs.is_projected else "degree"


def _normalise(name: str) -> str | None:
    key = re.sub(r"[\s_]", "", name.strip().lower())
    return _UNIT_ALIASES.get(key) or _UNIT_ALIASES.get(name.strip().lower())


def _factor_name(factor: float) -> str | None:
    for name, f in Z_UNITS.items():
        if math.isclose(factor, f, rel_tol=1e-6):
            return name
    return None


def stated_vertical_unit(crs: CRS | None, band_unit: str | None) -> tuple[float, str, str] | None:
    """The vertical unit a raster states, if any: ``(metres per unit, name, where it was found)``.

    Looks at the vertical component of a compound CRS first, then at the band's unit type.
    A unit that is stated but not a length aerialmtl knows (e.g. ``"dm"``) is returned with its factor
    from the CRS when there is one; an unknown band unit string is ignored (it is free text).
    """
    if crs is not None:
        wkt = crs.to_wkt()
        match = re.search(r'VERT_CS\[.*?UNIT\["([^"]+)",\s*([0-9.eE+-]+)', wkt, flags=re.DOTALL)
        if match is None:  # WKT2 spelling
            match = re.search(r'VERTCRS\[.*?LENGTHUNIT\["([^"]+)",\s*([0-9.eE+-]+)', wkt, flags=re.DOTALL)
        if match is not None:
            factor = float(match.group(2))
            return factor, _factor_name(factor) or match.group(1), "its vertical CRS"
    if band_unit:
        name = _normalise(band_unit)
        if name is not None:
            return Z_UNITS[name], name, f"its band unit '{band_unit}'"
    return None


@dataclass(frozen=True)
class VerticalUnit:
    """How a height raster's values convert to metres.

    Attributes:
        factor: metres per unit of the file's values.
        name: ``"m"``, ``"ft"``, ``"us-ft"`` (or the file's own name for another unit).
        source: where the unit came from (``"its vertical CRS"``, ``"its band unit 'ft'"``,
            ``"z_unit"`` or ``"default (metres)"``).
    """

    factor: float
    name: str
    source: str


def vertical_unit(
    crs: CRS | None, band_unit: str | None, z_unit: str | None, role: str, path: object
) -> VerticalUnit:
    """Resolve the vertical unit of a height raster (see the module docstring).

    Args:
        crs, band_unit: what the file states (its CRS and its band's unit type).
        z_unit: the caller's unit, ``None`` when not given (then metres unless the file says otherwise).
        role, path: the layer (``"DSM"``) and file, named in messages.

    Raises:
        InputError: ``z_unit`` is not a known unit, or contradicts the unit the file states.
    """
    if z_unit is not None and z_unit not in Z_UNITS:
        raise InputError(f"z_unit {z_unit!r} is not a known height unit; use one of {', '.join(Z_UNITS)}")
    stated = stated_vertical_unit(crs, band_unit)
    if stated is not None:
        factor, name, where = stated
        if z_unit is not None and not math.isclose(Z_UNITS[z_unit], factor, rel_tol=1e-6):
            raise InputError(
                f"{role} '{path}' states its heights are in {name} ({where}) but z_unit {z_unit!r} was given; "
                f"drop the z_unit or fix the file's unit (e.g. `gdal_edit.py -units m {path}`)"
            )
        return VerticalUnit(factor, name, where)
    if z_unit is not None:
        return VerticalUnit(Z_UNITS[z_unit], z_unit, "z_unit")
    return VerticalUnit(1.0, "m", "default (metres)")


__all__ = [
    "VerticalUnit", "Z_UNITS", "ZUnit", "linear_unit_name", "metres_per_unit", "require_projected",
    "stated_vertical_unit", "utm_epsg", "vertical_unit",
]
