"""Put every layer on the orthophoto's grid, window by window.

The orthophoto (optionally resampled to a working GSD) defines the reference :class:`Grid`. Other
layers (DSM, DTM, nDSM, labels, reference maps) are opened as :class:`AlignedRaster` objects that
reproject/resample onto that grid lazily through a GDAL warped VRT, so that reading one window never
loads a whole raster. Resampling follows the layer kind:

* ``image``: ``average`` when the source is finer than the grid (downsampling), ``bilinear`` otherwise;
* ``height``: ``bilinear``;
* ``labels``: ``mode`` when downsampling, ``nearest`` otherwise.

Every read returns the data and a boolean validity mask (nodata, NaN, alpha = 0 and pixels outside the
source are invalid).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import rasterio
from affine import Affine
from rasterio.crs import CRS
from rasterio.enums import ColorInterp, MaskFlags, Resampling
from rasterio.errors import NotGeoreferencedWarning, RasterioError, RasterioIOError
from rasterio.vrt import WarpedVRT
from rasterio.warp import transform_bounds
from rasterio.windows import Window, from_bounds
from rasterio.windows import transform as window_transform

from aerialmtl.errors import AlignmentError, InputError
from aerialmtl.io.paths import (
    ARCHIVE_VSI,
    REMOTE_OPEN_OPTIONS,
    archive_parts,
    configure_remote,
    gdal_path,
    is_local,
    is_remote,
    probe_url,
)
from aerialmtl.io.place import check_place
from aerialmtl.io.raster_errors import gdal_message, raise_if_blocking, read_error
from aerialmtl.io.units import VerticalUnit, metres_per_unit, require_projected, vertical_unit
from aerialmtl.quiet import ignoring_warnings

LayerKind = Literal["image", "height", "labels"]



@dataclass(frozen=True)
class Grid:
    """A georeferenced pixel grid: ``height`` × ``width`` pixels of ``transform`` in ``crs``.

    ``transform`` maps (col, row) to map coordinates of the pixel's upper-left corner (north-up).
    """

    crs: CRS
    transform: Affine
    width: int
    height: int

    @property
    def res(self) -> tuple[float, float]:
        """Pixel size (x, y) in CRS units (metres, feet, ... : see :attr:`unit_m`)."""
        return (abs(self.transform.a), abs(self.transform.e))

    @property
    def unit_m(self) -> float:
        """Metres per CRS unit (1 for metres, 0.3048 for international feet).

        Raises:
            AlignmentError: the CRS is geographic (degrees).
        """
        return metres_per_unit(self.crs)

    @property
    def gsd(self) -> float:
        """Ground sampling distance in metres: the mean of the x and y pixel sizes."""
        return 0.5 * (self.res[0] + self.res[1]) * self.unit_m

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(left, bottom, right, top) in CRS units."""
        left, top = self.transform @ (0, 0)
        right, bottom = self.transform @ (self.width, self.height)
        return (min(left, right), min(bottom, top), max(left, right), max(bottom, top))

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) in pixels."""
        return (self.height, self.width)

    def window_transform(self, window: Window) -> Affine:
        """Transform of ``window`` (``rasterio.windows.transform`` on this grid)."""
        result: Affine = window_transform(window, self.transform)
        return result

    def full_window(self) -> Window:
        """The window of the whole grid."""
        return Window(0, 0, self.width, self.height)

    def window_from_bounds(self, bounds: Sequence[float]) -> Window:
        """Pixel window (rounded outwards, clipped to the grid) covering map ``bounds``."""
        win = from_bounds(*bounds, transform=self.transform)
        col0 = max(0, math.floor(win.col_off + 1e-6))
        row0 = max(0, math.floor(win.row_off + 1e-6))
        col1 = min(self.width, math.ceil(win.col_off + win.width - 1e-6))
        row1 = min(self.height, math.ceil(win.row_off + win.height - 1e-6))
        return Window(col0, row0, max(0, col1 - col0), max(0, row1 - row0))


def open_raster(path: str | Path, role: str = "raster") -> rasterio.io.DatasetReader:
    """Open ``path``, with a message that names the role and the fix when it cannot be read.

    ``path``: a file, a URL or a ``/vsi...`` path (:mod:`aerialmtl.io.paths`).

    Raises:
        InputError: a local file is missing or unreadable, or a remote one cannot be reached (the
            message names the URL, what the server or GDAL said, and what to check).
    """
    gpath = gdal_path(path)
    if is_local(gpath) and not Path(gpath).exists():
        raise InputError(f"{role} '{gpath}' does not exist; check the path")
    if is_local(gpath):
        raise_if_blocking(gpath, role)
    remote = is_remote(gpath)
    if remote:
        configure_remote()
    opening = {k: v for k, v in REMOTE_OPEN_OPTIONS.items() if k not in os.environ} if remote else {}
    try:
        # a missing CRS/geotransform: our own message
        with ignoring_warnings(NotGeoreferencedWarning), rasterio.Env(**opening):
            return rasterio.open(gpath)
    except RasterioIOError as exc:
        if remote:
            fix = ("give AWS credentials (AWS_ACCESS_KEY_ID/AWS_SECRET_ACCESS_KEY or ~/.aws), or "
                   "AWS_NO_SIGN_REQUEST=YES "
                   "for a public bucket" if "/vsis3/" in gpath else
                   "a server that needs a login takes GDAL_HTTP_AUTH/GDAL_HTTP_USERPWD or GDAL_HTTP_HEADERS")
            why = gdal_message(exc)
            if "not recognized" in why:  # what GDAL says after its retries, whatever the server did: ask it
                why = probe_url(gpath) or why
            raise InputError(
                f"{role} '{gpath}' cannot be opened ({why}); check the URL and the network; {fix}"
            ) from exc
        if gpath.startswith(ARCHIVE_VSI):  # the archive or the file inside it is missing, before any pixel
            parts = archive_parts(gpath)
            if parts is None:
                raise InputError(f"{role} '{gpath}': no archive file was found along this path; check the archive's "
                                 "path (e.g. /vsizip//data/area.zip/ortho.tif)") from exc
            raise InputError(f"{role} '{gpath}': the archive '{parts[0]}' holds no raster '{parts[1]}' (GDAL: "
                             f"{gdal_message(exc)}); list its files (`unzip -l {parts[0]}`) and give one of them"
                             ) from exc
        raise InputError(
            f"{role} '{gpath}' cannot be read as a raster ({' '.join(str(exc).split())}); "
            "is it a complete GeoTIFF? re-download or re-export it"
        ) from exc


def check_bands(
    src: rasterio.io.DatasetReader, bands: Sequence[int], role: str, bands_from: str = "the requested bands",
    fix: str | None = None,
) -> None:
    """Raise :class:`InputError` if a 1-based band index of ``bands`` is not in the open raster ``src``.

    Args:
        src: the open raster.
        bands: requested 1-based band indexes.
        role: what the raster is (``"orthophoto"``), named in the message.
        bands_from: where the band list came from (a parameter mark such as ``‹bands›``, or a checkpoint).
        fix: what to do about it (default: choose bands that exist, with the option if it is one).
    """
    bad = [int(b) for b in bands if not 1 <= int(b) <= src.count]
    if bad:
        if fix is None:
            fix = f"choose bands within 1..{src.count}" + (f" with {bands_from}" if bands_from.startswith("‹") else "")
        raise InputError(
            f"{role} '{src.name}': band(s) {bad} requested by {bands_from} but the file has {src.count} band(s); {fix}"
        )


def _check_georeferenced(src: rasterio.io.DatasetReader, role: str) -> None:
    if src.crs is None:
        raise AlignmentError(
            f"{role} '{src.name}' has no CRS; assign one first (e.g. `gdal_edit.py -a_srs EPSG:XXXX {src.name}`)"
        )
    if src.transform == Affine.identity() and not src.gcps[0]:
        raise AlignmentError(
            f"{role} '{src.name}' has no geotransform; georeference it first (e.g. `gdal_edit.py -a_ullr ...`)"
        )
    if src.transform.b != 0 or src.transform.d != 0:
        raise AlignmentError(
            f"{role} '{src.name}' is rotated; warp it north-up first (`gdalwarp {src.name} north_up.tif`)"
        )


def grid_of(src: rasterio.io.DatasetReader) -> Grid:
    """The native grid of an open dataset."""
    return Grid(src.crs, src.transform, src.width, src.height)


def reference_grid(ortho: str | Path, gsd: float | None = None) -> Grid:
    """The reference grid defined by the orthophoto, optionally resampled to ``gsd`` metres.

    With ``gsd`` the grid keeps the ortho's upper-left corner and covers its extent with square pixels
    of ``gsd`` metres (converted to the CRS's unit, e.g. feet; the last row/column may extend up to one
    pixel beyond the ortho's edge).

    Raises:
        AlignmentError: the ortho has no CRS / geotransform, a geographic CRS (degrees: pixels without a
            size in metres), or ``gsd`` is not positive.
    """
    with open_raster(ortho, "orthophoto") as src:
        grid = ortho_grid(src)
    return grid if gsd is None else resampled_grid(grid, gsd)


def ortho_grid(src: rasterio.io.DatasetReader) -> Grid:
    """The grid of an open orthophoto, checked as :func:`reference_grid` checks it (projected, north-up, with a
    place on Earth: :func:`~aerialmtl.io.place.check_place`).
    """
    _check_georeferenced(src, "orthophoto")
    t = src.transform
    if t.e > 0 or t.a < 0:  # south-up or east-to-west rows: every window, stitch and output assumes north-up
        which = "south-up (its pixel height is positive)" if t.e > 0 else "mirrored (its pixel width is negative)"
        raise AlignmentError(
            f"orthophoto '{src.name}' is {which}, not north-up; warp it north-up first "
            f"(`gdalwarp {src.name} north_up.tif`)")
    check_place(src.crs, tuple(src.bounds), "orthophoto", src.name)  # a local CRS, outside its domain: refused here
    if not src.crs.is_projected:
        lon, lat = transform_bounds(src.crs, "EPSG:4326", *src.bounds)[:2]
        require_projected(src.crs, "orthophoto", src.name, (lon, lat))
    return grid_of(src)


def resampled_grid(grid: Grid, gsd: float) -> Grid:
    """``grid`` with square pixels of ``gsd`` metres over its extent, from its upper-left corner.

    See :func:`reference_grid`.
    """
    if not gsd > 0:
        raise AlignmentError(f"‹gsd› must be a positive pixel size in metres, got {gsd}", param="gsd")
    size = gsd / grid.unit_m  # CRS units
    left, bottom, right, top = grid.bounds
    width = max(1, math.ceil((right - left) / size - 1e-6))
    height = max(1, math.ceil((top - bottom) / size - 1e-6))
    return Grid(grid.crs, Affine(size, 0.0, left, 0.0, -size, top), width, height)


def _fmt_bounds(b: Sequence[float]) -> str:
    return "(" + ", ".join(f"{v:.6g}" for v in b) + ")"


def _default_resampling(kind: LayerKind, src_res: float, dst_res: float) -> Resampling:
    finer = src_res < dst_res * (1 - 1e-6)  # source finer than grid → downsampling
    if kind == "image":
        return Resampling.average if finer else Resampling.bilinear
    if kind == "height":
        return Resampling.bilinear
    return Resampling.mode if finer else Resampling.nearest


class AlignedRaster:
    """A raster seen through the reference grid; read windows of it as if it were on that grid.

    Args:
        path: raster file.
        grid: the reference grid.
        kind: ``image``, ``height`` or ``labels`` (chooses the default resampling).
        bands: 1-based band indexes to read (default: all non-alpha bands).
        resampling: override the default resampling.
        role: name used in messages (``"DSM"``, ``"labels"``, ...).
        check_overlap: raise :class:`AlignmentError` if the layer does not overlap the grid.
        bands_from: where ``bands`` came from, named in the message when one is out of range.
        z_unit: for ``height`` layers, the unit of the values when the file states none (``"m"``,
            ``"ft"``, ``"us-ft"``; ``None`` = metres); values are read as metres
            (:func:`aerialmtl.io.units.vertical_unit`, resolved into :attr:`z`).

    Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        path: str | Path,
        grid: Grid,
        kind: LayerKind,
        bands: Sequence[int] | None = None,
        resampling: Resampling | None = None,
        role: str | None = None,
        check_overlap: bool = True,
        bands_from: str = "the requested bands",
        z_unit: str | None = None,
    ) -> None:
        self.path = gdal_path(path)
        self.grid = grid
        self.kind = kind
        self.role = role or kind
        self.src = open_raster(path, self.role)
        #: the unit of a height layer's values (converted to metres on read); ``None`` for other kinds
        self.z: VerticalUnit | None = None
        try:
            self._setup(bands, resampling, check_overlap, bands_from)
            if kind == "height":
                self.z = vertical_unit(self.src.crs, self.src.units[self.bands[0] - 1], z_unit, self.role, self.path)
        except Exception:
            self.src.close()
            raise

    def _setup(self, bands: Sequence[int] | None, resampling: Resampling | None, check_overlap: bool,
               bands_from: str) -> None:
        src, grid = self.src, self.grid
        _check_georeferenced(src, self.role)
        alpha = [i + 1 for i, ci in enumerate(src.colorinterp) if ci == ColorInterp.alpha]
        self.alpha_band = alpha[0] if alpha else None
        if bands is None:
            bands = [i for i in range(1, src.count + 1) if i != self.alpha_band]
        check_bands(src, bands, self.role, bands_from)
        self.bands = list(bands)
        self.nodata = src.nodata
        if check_overlap:
            sb = transform_bounds(src.crs, grid.crs, *src.bounds, densify_pts=21)
            gb = grid.bounds
            if sb[0] >= gb[2] or sb[2] <= gb[0] or sb[1] >= gb[3] or sb[3] <= gb[1]:
                raise AlignmentError(
                    f"{self.role} '{self.path}' does not overlap the orthophoto grid: its bounds "
                    f"{_fmt_bounds(src.bounds)} in {src.crs.to_string()} are {_fmt_bounds(sb)} in "
                    f"{grid.crs.to_string()}, the grid covers {_fmt_bounds(gb)}; check that the files show "
                    "the same area and carry the right CRS"
                )
        self.same_grid = (
            src.crs == grid.crs and src.transform.almost_equals(grid.transform, 1e-9)
            and src.width == grid.width and src.height == grid.height
        )
        if self.same_grid:
            self.reader = src
            self.vrt = None
            self.resampling = Resampling.nearest
            return
        src_res = 0.5 * (abs(src.transform.a) + abs(src.transform.e))
        if src.crs != grid.crs:  # compare in grid units: resolution of the source footprint in grid CRS
            sb = transform_bounds(src.crs, grid.crs, *src.bounds)
            src_res = 0.5 * ((sb[2] - sb[0]) / src.width + (sb[3] - sb[1]) / src.height)
        grid_res = 0.5 * (grid.res[0] + grid.res[1])  # same units as src_res: the grid CRS's
        self.resampling = resampling or _default_resampling(self.kind, src_res, grid_res)
        has_mask = self.nodata is not None or self.alpha_band is not None or any(
            MaskFlags.per_dataset in f for f in src.mask_flag_enums
        )
        vrt_kwargs = dict(crs=grid.crs, transform=grid.transform, width=grid.width, height=grid.height,
                          resampling=self.resampling)
        if not has_mask:
            vrt_kwargs["add_alpha"] = True  # so that pixels outside the source read as invalid
        with ignoring_warnings():
            self.vrt = WarpedVRT(src, **vrt_kwargs)
        self.reader = self.vrt

    # ------------------------------------------------------------------------------------------
    def read(self, window: Window | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Read ``window`` of the reference grid.

        Returns:
            ``(data, valid)``: ``data`` is (bands, h, w) in the source dtype (float32 metres for heights,
            with invalid pixels set to NaN); ``valid`` is a (h, w) bool mask, ``False`` for nodata, NaN,
            alpha = 0 and pixels outside the source.
        """
        window = window or self.grid.full_window()
        h, w = int(window.height), int(window.width)
        r0, c0 = int(window.row_off), int(window.col_off)
        # part of the window inside the grid; the rest reads as invalid
        ir0, ic0 = max(r0, 0), max(c0, 0)
        ir1, ic1 = min(r0 + h, self.grid.height), min(c0 + w, self.grid.width)
        data = np.zeros((len(self.bands), h, w), dtype=self.src.dtypes[self.bands[0] - 1])
        mask = np.zeros((h, w), dtype=bool)
        if ir1 > ir0 and ic1 > ic0:
            inner = Window(ic0, ir0, ic1 - ic0, ir1 - ir0)
            sl = (slice(ir0 - r0, ir1 - r0), slice(ic0 - c0, ic1 - c0))
            try:
                data[:, sl[0], sl[1]] = self.reader.read(self.bands, window=inner)
                inner_mask = self.reader.read_masks(1, window=inner) > 0
                if self.vrt is None and self.alpha_band is not None:
                    inner_mask &= self.reader.read(self.alpha_band, window=inner) > 0
            except RasterioError as exc:
                raise read_error(self.role, self.path, exc) from exc
            mask[sl] = inner_mask
        if self.nodata is not None and not (isinstance(self.nodata, float) and math.isnan(self.nodata)):
            mask &= ~np.any(data == np.asarray(self.nodata).astype(data.dtype), axis=0)
        if data.dtype.kind == "f":
            mask &= np.all(np.isfinite(data), axis=0)
        if self.kind == "height":
            data = data.astype(np.float32, copy=False)
            if self.z is not None and self.z.factor != 1.0:
                data = data * np.float32(self.z.factor)  # metres
            data[:, ~mask] = np.nan
        return data, mask

    def close(self) -> None:
        """Close the source dataset (and its warped view)."""
        if self.vrt is not None:
            self.vrt.close()
        self.src.close()

    def __enter__(self) -> AlignedRaster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class NdsmOptions:
    """How heights above ground are derived.

    ``clip_negative`` sets nDSM < 0 to 0; ``max_height``
    (metres) marks taller pixels as invalid (``None`` keeps all); ``z_unit`` is the unit of the height
    rasters' values when a file states none (``"m"``, ``"ft"``, ``"us-ft"``; ``None`` = metres; see
    :mod:`aerialmtl.io.units`). Heights are always derived in metres.
    """

    clip_negative: bool = True
    max_height: float | None = None
    z_unit: str | None = None

    def __post_init__(self) -> None:
        if self.max_height is not None and not self.max_height > 0:
            raise InputError(f"‹max_height› must be a positive height in metres, got {self.max_height}",
                             param="max_height")


class HeightSource:
    """Heights above ground (nDSM, metres) on the reference grid, from ``ndsm`` or ``dsm`` − ``dtm``.

    nDSM = DSM − DTM is computed on the reference grid after resampling both with bilinear
    interpolation; a pixel is invalid where either is nodata/NaN. Negative values are clipped to 0 and
    values above ``max_height`` made invalid, per :class:`NdsmOptions`.
    """

    def __init__(
        self,
        grid: Grid,
        ndsm: str | Path | None = None,
        dsm: str | Path | None = None,
        dtm: str | Path | None = None,
        options: NdsmOptions = NdsmOptions(),
    ) -> None:
        if ndsm is not None and (dsm is not None or dtm is not None):
            raise InputError("give either an nDSM (‹ndsm›) or a DSM and a DTM (‹dsm›/‹dtm›), not both")
        if ndsm is None and (dsm is None) != (dtm is None):
            raise InputError("‹dsm› and ‹dtm› go together: pass both, or pass a ready nDSM with ‹ndsm›")
        if ndsm is None and dsm is None:
            raise InputError("no height layer given: pass ‹ndsm›, or ‹dsm› with ‹dtm›")
        self.options = options
        self.layers: list[AlignedRaster] = []
        try:
            z = options.z_unit
            if ndsm is not None:
                self.layers.append(AlignedRaster(ndsm, grid, "height", bands=[1], role="nDSM", z_unit=z))
            elif dsm is not None and dtm is not None:  # both, as checked above
                self.layers.append(AlignedRaster(dsm, grid, "height", bands=[1], role="DSM", z_unit=z))
                self.layers.append(AlignedRaster(dtm, grid, "height", bands=[1], role="DTM", z_unit=z))
                self.check_dsm_above_dtm()
        except Exception:
            self.close()
            raise

    #: a DSM below its DTM by more than this (metres) counts as "below" in :meth:`check_dsm_above_dtm`
    SWAP_TOLERANCE_M = 0.5
    #: fraction of the sampled pixels where DSM and DTM differ that must lie below for the swap error
    SWAP_FRACTION = 0.75

    def sample_windows(self, n: int = 4, side: int = 64) -> list[Window]:
        """An ``n`` × ``n`` spread of windows of ``side`` pixels over the grid (fewer on a small grid)."""
        grid = self.layers[0].grid
        w, h = min(side, grid.width), min(side, grid.height)
        cols = sorted({int(round(k * (grid.width - w) / max(1, n - 1))) for k in range(n)})
        rows = sorted({int(round(k * (grid.height - h) / max(1, n - 1))) for k in range(n)})
        return [Window(c, r, w, h) for r in rows for c in cols]

    def check_dsm_above_dtm(self) -> None:
        """Refuse a DSM that lies below its DTM on most pixels where the two differ.

        They are swapped, or on different vertical datums: every height would be clipped to 0 or negative.

        Reads a spread of 16 windows of 64 × 64 pixels (not the whole rasters). Pixels where
        |DSM − DTM| ≤ :attr:`SWAP_TOLERANCE_M` (bare ground, noise) are not counted.

        Raises:
            InputError: naming both files, the fraction below and the fix (``param="dsm"``).
        """
        dsm_layer, dtm_layer = self.layers
        below = above = 0
        diffs: list[np.ndarray] = []
        for win in self.sample_windows():
            dsm, v1 = dsm_layer.read(win)
            dtm, v2 = dtm_layer.read(win)
            d = (dsm[0] - dtm[0])[v1 & v2]
            below += int((d < -self.SWAP_TOLERANCE_M).sum())
            above += int((d > self.SWAP_TOLERANCE_M).sum())
            diffs.append(d)
        differ = below + above
        if differ < 10 or below < self.SWAP_FRACTION * differ:
            return
        median = float(np.median(np.concatenate(diffs)))
        raise InputError(
            f"the DSM '{dsm_layer.path}' lies below the DTM '{dtm_layer.path}' on {100 * below / differ:.0f} % of the "
            f"sampled pixels where they differ (median DSM − DTM {median:.3g} m), so every height would be 0 or "
            "negative: the two are probably swapped: pass the surface model (with buildings and trees) as ‹dsm› and "
            "the bare-earth terrain model as ‹dtm› (or, if they are right, bring them to one vertical datum and unit, "
            "see ‹z_unit›)",
            param="dsm",
        )

    def read(self, window: Window) -> tuple[np.ndarray, np.ndarray]:
        """Returns ``(height, valid)``: (h, w) float32 metres (NaN where invalid) and a (h, w) bool mask."""
        data, valid = self.layers[0].read(window)
        height = data[0]
        if len(self.layers) == 2:
            dtm, valid_dtm = self.layers[1].read(window)
            valid = valid & valid_dtm
            height = height - dtm[0]
        if self.options.clip_negative:
            height = np.where(valid, np.maximum(height, 0.0), height)
        if self.options.max_height is not None:
            valid = valid & ~(height > self.options.max_height)
        height = np.where(valid, height, np.nan).astype(np.float32)
        return height, valid

    def units(self) -> dict[str, dict[str, object]]:
        """Per layer (``"DSM"``, ``"DTM"`` or ``"nDSM"``): the unit its values were read in and where it came from.

        For example ``{"DSM": {"unit": "us-ft", "metres_per_unit": 0.3048006, "source": "z_unit"}}``.
        """
        return {layer.role: {"unit": layer.z.name, "metres_per_unit": layer.z.factor, "source": layer.z.source}
                for layer in self.layers if layer.z is not None}

    def close(self) -> None:
        """Close every source raster."""
        for layer in self.layers:
            layer.close()

    def __enter__(self) -> HeightSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
