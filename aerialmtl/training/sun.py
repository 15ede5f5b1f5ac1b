"""The training area's sun, fitted after training and stored in the checkpoint (``meta.sun``).

In a sunlit orthophoto an object of height h casts a shadow h / tan(elevation) long away from the sun, and the
sun is one pair of angles for a whole flight. After training, :func:`sun_checkpoint` pieces the tile folder's
training patches back into one mosaic (orthophoto and reference heights on the tile grid), fits the sun on it
(:func:`aerialmtl.sun.fit_sun`: the sun whose cast shadows best follow how shadow-like the ground looks), fits
the area's shadow classifier at that sun (:class:`aerialmtl.sun.ShadowModel`: the cast shadows of the reference
heights are its labels, so water and dark roofs are learnt not to be shadows) and stores both with the
training area's footprint and a few squares of its orthophoto (:class:`~aerialmtl.sun.record.TrainingSun`; the
squares tell the training flight from a later one where an orthophoto covers the training area:
:mod:`aerialmtl.sun.flight`). ``predict --sun auto`` uses them for an orthophoto of the same flight
(:mod:`aerialmtl.inference.sun_choice`). A fit without a clear optimum (overcast, a sun near the zenith, no tall
structures) is stored as such and switches the feature off.
Training patches only: no validation or test pixel takes part.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import numpy as np
import rasterio

from aerialmtl.data.dataset import read_raw_patch
from aerialmtl.errors import InputError
from aerialmtl.formats.checkpoint import update_meta
from aerialmtl.formats.tiles import TileFolderInfo, read_manifest
from aerialmtl.progress import tqdm_auto as tqdm
from aerialmtl.sun import ShadowModel, fit_sun
from aerialmtl.sun.flight import FlightChip, cut_chip, pick_chips
from aerialmtl.sun.record import TrainingSun
from aerialmtl.sun.solar_position import file_time, grid_convergence_deg, lonlat, sun_position

log = logging.getLogger(__name__)

#: The largest training mosaic pieced together for the fit (pixels): the fit casts shadows for ~300 suns, about
#: 30 s on 1.4 Mpx on one core (experiments/heights_from_the_sun/shadow_heights.py); a larger area is fitted on a
#: seeded sample of its patches holding about as many pixels (shadows clipped at patch edges then count as noise).
MAX_MOSAIC_PIXELS = 4_000_000


@dataclasses.dataclass
class AreaImage:
    """The training split as one mosaic: ``rgb`` uint8 (3, H, W), ``height`` float32 (H, W) metres (NaN
    invalid), ``valid`` bool (H, W); ``crs`` and ``bounds`` (left, bottom, right, top) of the area; ``gsd`` m/px.
    Several mosaics (a list) when the area is too large for one.
    """

    rgb: list[np.ndarray]
    height: list[np.ndarray]
    valid: list[np.ndarray]
    gsd: float
    crs: str | None
    bounds: tuple[float, float, float, float] | None
    ortho: str | None = None  # the orthophoto the tile folder was cut from (its provenance), where recorded
    chips: list[FlightChip] = dataclasses.field(default_factory=list)  # one per textured patch (aerialmtl.sun.flight)
    bands: tuple[int, ...] = ()  # the orthophoto bands the patches hold (tile --bands)

    def add_chip(self, patch: Any, row: dict[str, Any]) -> None:
        """Keep the centre chip of a training patch read with :func:`read_raw_patch` (on the grid its manifest row
        gives), where it is textured enough (:func:`aerialmtl.sun.flight.cut_chip`).
        """
        pixel = (float(row["right"]) - float(row["left"])) / float(row["width"])
        chip = cut_chip(patch.image, patch.image_valid, float(row["left"]), float(row["top"]), pixel)
        if chip is not None:
            self.chips.append(chip)


def training_area(data_dir: str | Path, split: str = "train", bar: Any = None) -> AreaImage:
    """The ``split`` patches of tile folder ``data_dir`` pieced together on the tile grid (see :class:`AreaImage`).

    ``bar``: a progress bar counted one step per patch read (none by default).

    Raises:
        InputError: not 8-bit RGB patches with heights, or no patch in ``split``.
    """
    root = Path(data_dir)
    info = TileFolderInfo.read(root)
    if info.num_bands < 3 or info.dtype not in (None, "uint8") or "height" not in info.tasks:
        raise InputError(f"sun: the tile folder '{root}' holds {info.num_bands}-band {info.dtype} patches with "
                         f"tasks {list(info.tasks)}; the sun is fitted on 8-bit RGB patches with heights")
    rows = read_manifest(root, split)
    if not rows:
        raise InputError(f"sun: the tile folder '{root}' has no '{split}' patches")
    cols = [int(r["col_off"]) for r in rows]
    rws = [int(r["row_off"]) for r in rows]
    c0, r0 = min(cols), min(rws)
    w = max(c + int(r["width"]) for c, r in zip(cols, rows)) - c0
    h = max(q + int(r["height"]) for q, r in zip(rws, rows)) - r0
    left = min(float(r["left"]) for r in rows)
    bottom = min(float(r["bottom"]) for r in rows)
    right = max(float(r["right"]) for r in rows)
    top = max(float(r["top"]) for r in rows)
    ortho = info.provenance.get("ortho")
    area = AreaImage([], [], [], float(info.gsd), info.crs, (left, bottom, right, top), str(ortho) if ortho else None,
                     bands=tuple(int(b) for b in info.bands[:3]))
    if w * h <= MAX_MOSAIC_PIXELS:
        rgb = np.zeros((3, h, w), np.uint8)
        height = np.full((h, w), np.nan, np.float32)
        valid = np.zeros((h, w), bool)
        for row, c, q in zip(rows, cols, rws):
            p = read_raw_patch(root, row, info.num_bands, ("height",))
            s = np.s_[q - r0:q - r0 + p.image.shape[1], c - c0:c - c0 + p.image.shape[2]]
            rgb[:, s[0], s[1]] = p.image[:3]
            if p.height is not None:
                height[s] = p.height
            valid[s] |= p.image_valid
            area.add_chip(p, row)
            if bar is not None:
                bar.update(1)
        area.rgb, area.height, area.valid = [rgb], [height], [valid]
    else:
        per_patch = max(1, int(rows[0]["width"]) * int(rows[0]["height"]))
        pick = np.random.default_rng(0).permutation(len(rows))[:max(1, MAX_MOSAIC_PIXELS // per_patch)]
        for i in sorted(pick):
            p = read_raw_patch(root, rows[i], info.num_bands, ("height",))
            area.rgb.append(np.ascontiguousarray(p.image[:3]))  # its own type: unit_rgb scales by its largest value
            area.height.append(p.height if p.height is not None else np.full(p.image_valid.shape, np.nan, np.float32))
            area.valid.append(p.image_valid)
            area.add_chip(p, rows[i])
            if bar is not None:
                bar.update(1)
    return area


def _acquired(path: str | None) -> str | None:
    """The training orthophoto's TIFF ``DateTime`` (as written, read by
    :func:`~aerialmtl.sun.solar_position.file_time` as predict reads it), where the file is still there and has one.
    """
    if not path or not Path(str(path)).is_file():
        return None
    try:
        with rasterio.open(str(path)) as src:
            stamp = src.tags().get("TIFFTAG_DATETIME")
        return str(stamp) if stamp is not None else None
    except rasterio.errors.RasterioError:
        return None


def fit_training_sun(data_dir: str | Path, split: str = "train", progress: bool = False) -> TrainingSun:
    """Fit the sun and the shadow classifier on ``data_dir``'s ``split`` (see the module docstring).

    ``progress``: a ``sun fit`` bar: one step per patch read, one for the sun, one for the shadow classifier.
    """
    try:
        steps: int | None = len(read_manifest(Path(data_dir), split)) + 2 if progress else None
    except (OSError, InputError):  # not a tile folder: training_area says so
        steps = None
    with tqdm(total=steps, desc="sun fit", unit="step", disable=not progress, dynamic_ncols=True) as bar:
        sun = _fit_training_sun(data_dir, split, bar)
        if steps is not None and bar.n < steps:  # no shadow classifier to fit (no clear sun): the stage is done
            bar.update(steps - bar.n)
        return sun


def _fit_training_sun(data_dir: str | Path, split: str, bar: Any) -> TrainingSun:
    """:func:`fit_training_sun` counting its steps on ``bar``."""
    area = training_area(data_dir, split, bar)
    fit = fit_sun(area.rgb, area.height, area.gsd, area.valid)
    bar.update(1)
    if not fit.clear or fit.sun is None or area.crs is None or area.bounds is None:
        return TrainingSun(clear=False, reason=fit.reason, score=_finite(fit.score), sharpness=_finite(fit.sharpness),
                           crs=area.crs, bounds=area.bounds)
    x = (area.bounds[0] + area.bounds[2]) / 2.0
    y = (area.bounds[1] + area.bounds[3]) / 2.0
    convergence = grid_convergence_deg(area.crs, x, y)
    true_az = (fit.sun.azimuth_deg - convergence) % 360.0
    try:
        shadows = ShadowModel().fit(area.rgb, area.height, area.gsd, fit.sun, area.valid)
        model = shadows.to_dict()
        bar.update(1)
    except InputError as exc:
        return TrainingSun(clear=False, reason=f"no shadow model: {exc}", score=fit.score, sharpness=fit.sharpness,
                           crs=area.crs, bounds=area.bounds)
    reason = (f"sun fitted: azimuth {true_az:.1f}° from true north ({fit.sun.azimuth_deg:.1f}° on the training "
              f"grid), elevation {fit.sun.elevation_deg:.1f}° (correlation {fit.score:.2f}, sharpness "
              f"{fit.sharpness:.2f})")
    acquired, time_sun = None, None
    stamp = _acquired(area.ortho)
    when = file_time(stamp, f"training orthophoto '{area.ortho}': its TIFF DateTime",
                     "the sun fitted on its shadows is used") if stamp is not None else None
    if when is not None:
        lon, lat = lonlat(area.crs, x, y)
        time_sun = sun_position(when, lon, lat)
        acquired = when.isoformat().replace("+00:00", "Z")
        d = max(abs((time_sun[0] - true_az + 180.0) % 360.0 - 180.0), abs(time_sun[1] - fit.sun.elevation_deg))
        if d > 10.0:
            log.warning("the training orthophoto's DateTime %s gives a sun (azimuth %.1f°, elevation %.1f°) %.0f° "
                        "from the one its shadows show (azimuth %.1f°, elevation %.1f°): the fit is kept (a "
                        "DateTime is often when the file was written)", acquired, *time_sun, d, true_az,
                        fit.sun.elevation_deg)
    return TrainingSun(clear=True, reason=reason, azimuth_deg=round(true_az, 4), elevation_deg=fit.sun.elevation_deg,
                       grid_azimuth_deg=fit.sun.azimuth_deg, score=fit.score, sharpness=fit.sharpness,
                       acquired=acquired, time_sun=time_sun, shadow_model=model, crs=area.crs,
                       bounds=area.bounds, chips=pick_chips(area.chips), chip_bands=area.bands)


def _finite(v: float) -> float:
    return float(v) if np.isfinite(v) else 0.0


def store_sun(path: str | Path, sun: TrainingSun, out: str | Path | None = None) -> None:
    """Store ``sun`` in checkpoint ``path`` (or write the checkpoint with it to ``out``); weights unchanged."""
    update_meta(path, out, sun=sun)


def sun_checkpoint(path: str | Path, data_dir: str | Path, out: str | Path | None = None) -> TrainingSun:
    """Fit the training area's sun (:func:`fit_training_sun`) and store it in checkpoint ``path`` (or ``out``)."""
    sun = fit_training_sun(data_dir)
    store_sun(path, sun, out)
    return sun


__all__ = ["AreaImage", "fit_training_sun", "store_sun", "sun_checkpoint", "training_area"]
