"""Look at a prediction folder: read its maps for display, find the most uncertain areas, draw them.

The helpers behind ``notebooks/uncertainty_maps.ipynb``. Everything is drawn in **map coordinates**
(``imshow`` with the raster's extent), so axis limits, the table of uncertain areas and QGIS agree.

* :func:`load_prediction_maps` reads the layers of a prediction folder (``docs/CONTRACTS.md``) and,
  optionally, the orthophoto onto one display grid, decimated so that the longer side has at most
  ``max_side`` pixels (large rasters stay cheap to draw);
* :func:`most_uncertain_areas` ranks the cells of a coarse square grid by the mean of an uncertainty
  layer (height std, class entropy or mutual information);
* :func:`plot_maps`, :func:`zoom_to`, :func:`plot_areas`, :func:`plot_sparsification` draw them with
  matplotlib's object API (pass a figure from ``pyplot`` to show it inline, or let them make one);
* :func:`uncertainty_summary` pulls AUSE/AURG/Spearman out of an evaluation report.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine
from rasterio.windows import Window

from aerialmtl.classes import IGNORE_INDEX, ClassScheme
from aerialmtl.errors import InputError
from aerialmtl.evaluation.evaluate import PREDICTION_FILES
from aerialmtl.formats.prediction import LAYER_UNITS, read_class_scheme_tag
from aerialmtl.formats.qgis_style import RAMPS
from aerialmtl.io.align import AlignedRaster, Grid, grid_of, open_raster

#: Float layers of a prediction folder that can be displayed, in panel order, with their titles.
FLOAT_LAYERS = {
    "height": "predicted height (m)",
    "height_std": "height std (m)",
    "class_entropy": "class entropy (nats)",
    "class_mutual_info": "mutual information (nats)",
}

#: Uncertainty layers that :func:`most_uncertain_areas` can rank.
UNCERTAINTY_LAYERS = ("height_std", "class_entropy", "class_mutual_info")


@dataclass
class PredictionMaps:
    """The layers of a prediction folder on one display grid.

    Attributes:
        grid: display grid (the prediction grid, possibly decimated).
        decimation: display pixel size / prediction pixel size (1 = full resolution).
        layers: float layers present (keys of :data:`FLOAT_LAYERS`), (H, W) float32, NaN = nodata.
        classes: (H, W) uint8 class indices, :data:`IGNORE_INDEX` = nodata; ``None`` without classes.
        scheme: class scheme (from the ``AERIALMTL_CLASS_SCHEME`` tag); ``None`` without classes.
        rgb: (H, W, 3) float in [0, 1] (percentile-stretched orthophoto), NaN outside it; or ``None``.
    """

    grid: Grid
    decimation: int = 1
    layers: dict[str, np.ndarray] = field(default_factory=dict)
    classes: np.ndarray | None = None
    scheme: ClassScheme | None = None
    rgb: np.ndarray | None = None

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(left, right, bottom, top)`` in map units, as ``imshow(extent=...)`` wants it."""
        t, g = self.grid.transform, self.grid
        x0, y0 = t @ (0, 0)
        x1, y1 = t @ (g.width, g.height)
        return (min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1))


def display_grid(grid: Grid, max_side: int | None) -> tuple[Grid, int]:
    """``grid`` decimated by an integer factor so that its longer side is ≤ ``max_side`` pixels."""
    if max_side is None or max(grid.width, grid.height) <= max_side:
        return grid, 1
    f = math.ceil(max(grid.width, grid.height) / max_side)
    return Grid(grid.crs, grid.transform @ Affine.scale(f), math.ceil(grid.width / f), math.ceil(grid.height / f)), f


def _stretch(data: np.ndarray, valid: np.ndarray, percentiles: tuple[float, float] = (2.0, 98.0)) -> np.ndarray:
    """(C, H, W) bands → (H, W, C) float in [0, 1], per-band percentile stretch over valid pixels."""
    out = np.full(data.shape[1:] + (data.shape[0],), np.nan, np.float32)
    for i, band in enumerate(data.astype(np.float64)):
        if not valid.any():
            continue
        lo, hi = np.percentile(band[valid], percentiles)
        scaled = (band - lo) / (hi - lo) if hi > lo else np.zeros_like(band)
        out[..., i] = np.where(valid, np.clip(scaled, 0.0, 1.0), np.nan)
    return out


def load_prediction_maps(
    pred_dir: str | Path, ortho: str | Path | None = None, max_side: int | None = 2048
) -> PredictionMaps:
    """Read the displayable layers of a prediction folder (and the orthophoto) onto one grid.

    Args:
        pred_dir: folder written by ``aerialmtl predict``.
        ortho: orthophoto to show beside the maps (any CRS/GSD; resampled onto the prediction grid).
            Bands 1–3 are shown as RGB (band 1 as grey when it has fewer), percentile-stretched.
        max_side: longest side of the display grid in pixels; larger predictions are decimated by an
            integer factor (averaged floats, class mode). ``None`` reads at full resolution.

    Returns:
        A :class:`PredictionMaps`.

    Raises:
        InputError: the folder does not exist or holds neither ``height.tif`` nor ``classes.tif``.
    """
    pred_dir = Path(pred_dir)
    files = {k: pred_dir / v for k, v in PREDICTION_FILES.items() if (pred_dir / v).is_file()}
    if not pred_dir.is_dir() or ("height" not in files and "classes" not in files):
        raise InputError(
            f"prediction folder '{pred_dir}' holds neither height.tif nor classes.tif; set PRED_DIR / pred_dir "
            "to the --out folder of `aerialmtl predict`"
        )
    first = files["height"] if "height" in files else files["classes"]
    with open_raster(first, f"prediction {first.name}") as src:
        grid, factor = display_grid(grid_of(src), max_side)
    maps = PredictionMaps(grid, factor)
    for key in FLOAT_LAYERS:
        if key in files:
            with AlignedRaster(files[key], grid, "height", bands=[1], role=f"prediction {files[key].name}") as layer:
                data, valid = layer.read()
            maps.layers[key] = np.where(valid, data[0], np.nan).astype(np.float32)
    if "classes" in files:
        maps.scheme = read_class_scheme_tag(files["classes"])
        with AlignedRaster(files["classes"], grid, "labels", bands=[1], role="prediction classes.tif") as layer:
            data, valid = layer.read()
        maps.classes = np.where(valid, data[0], IGNORE_INDEX).astype(np.uint8)
    if ortho is not None:
        with open_raster(ortho, "orthophoto") as src:
            count = src.count
        bands = [1, 2, 3] if count >= 3 else [1]
        with AlignedRaster(ortho, grid, "image", bands=bands, role="orthophoto", check_overlap=False) as layer:
            data, valid = layer.read()
        rgb = _stretch(data, valid)
        maps.rgb = np.repeat(rgb, 3, axis=-1) if rgb.shape[-1] == 1 else rgb
    return maps


def most_uncertain_areas(
    values: np.ndarray, transform: Affine, size: int = 64, top_k: int = 5, min_valid: float = 0.5
) -> list[dict[str, Any]]:
    """Rank the cells of a square grid by the mean of an uncertainty layer, most uncertain first.

    Cells are ``size`` × ``size`` pixels, starting at the upper-left corner (the last row/column of
    cells may be smaller); a cell counts only when at least ``min_valid`` of its pixels are finite.

    Args:
        values: (H, W) float uncertainty (e.g. height std in metres, mutual information in nats), NaN =
            nodata.
        transform: affine transform of ``values`` (pixel → map coordinates).
        size: cell side in pixels (> 0).
        top_k: number of cells returned (fewer when fewer cells qualify).
        min_valid: minimum fraction of finite pixels in a cell, in (0, 1].

    Returns:
        dicts with ``rank`` (1 = most uncertain), ``mean``, ``max`` (layer units), ``valid_fraction``,
        ``col_off``, ``row_off``, ``width``, ``height`` (pixels), ``left``, ``bottom``, ``right``,
        ``top``, ``x``, ``y`` (cell centre), all map units. Ties keep grid order (row-major).

    Raises:
        InputError: ``values`` is not 2-D, or ``size``/``top_k``/``min_valid`` is out of range.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 2:
        raise InputError(f"most_uncertain_areas: expected an (H, W) layer, got shape {values.shape}")
    if int(size) != size or size < 1:
        raise InputError(f"most_uncertain_areas: size must be a positive number of pixels, got {size!r}")
    if int(top_k) != top_k or top_k < 1:
        raise InputError(f"most_uncertain_areas: top_k must be ≥ 1, got {top_k!r}")
    if not 0 < min_valid <= 1:
        raise InputError(f"most_uncertain_areas: min_valid must be in (0, 1], got {min_valid!r}")
    h, w = values.shape
    cells: list[dict[str, Any]] = []
    for r in range(0, h, size):
        for c in range(0, w, size):
            block = values[r:r + size, c:c + size]
            finite = np.isfinite(block)
            frac = float(finite.mean())
            if frac < min_valid or not finite.any():
                continue
            win = Window(c, r, block.shape[1], block.shape[0])
            left, top = transform @ (c, r)
            right, bottom = transform @ (c + block.shape[1], r + block.shape[0])
            left, right = min(left, right), max(left, right)
            bottom, top = min(bottom, top), max(bottom, top)
            cells.append({
                "mean": float(block[finite].mean()), "max": float(block[finite].max()),
                "valid_fraction": frac, "col_off": int(win.col_off), "row_off": int(win.row_off),
                "width": int(win.width), "height": int(win.height),
                "left": left, "bottom": bottom, "right": right, "top": top,
                "x": 0.5 * (left + right), "y": 0.5 * (bottom + top),
            })
    order = sorted(range(len(cells)), key=lambda i: -cells[i]["mean"])  # stable: ties keep grid order
    return [{"rank": n + 1, **cells[i]} for n, i in enumerate(order[: int(top_k)])]


def format_areas(areas: Sequence[dict[str, Any]], units: str = "") -> str:
    """A plain-text table of :func:`most_uncertain_areas` results (centre and bounds in map units)."""
    head = (f"{'rank':>4} {'mean ' + units:>12} {'max ' + units:>12} {'centre x':>12} {'centre y':>12}   "
            "bounds (left, bottom, right, top)")
    rows = [head]
    for a in areas:
        rows.append(
            f"{a['rank']:>4} {a['mean']:>12.4g} {a['max']:>12.4g} {a['x']:>12.2f} {a['y']:>12.2f}   "
            f"({a['left']:.2f}, {a['bottom']:.2f}, {a['right']:.2f}, {a['top']:.2f})"
        )
    return "\n".join(rows)


def _new_figure(fig: Any, size: tuple[float, float]) -> Any:
    """``fig`` resized to ``size`` inches, or a new pyplot-free ``Figure`` of that size."""
    if fig is not None:
        fig.set_size_inches(*size)
        return fig
    from matplotlib.figure import Figure

    return Figure(figsize=size)


def _panels(maps: PredictionMaps) -> list[tuple[str, str]]:
    """(key, title) of the panels to draw, in order."""
    out = [("rgb", "orthophoto")] if maps.rgb is not None else []
    for key in ("height", "height_std"):
        if key in maps.layers:
            out.append((key, FLOAT_LAYERS[key]))
    if maps.classes is not None:
        out.append(("classes", "predicted classes"))
    for key in ("class_entropy", "class_mutual_info"):
        if key in maps.layers:
            out.append((key, FLOAT_LAYERS[key]))
    return out


def _vrange(data: np.ndarray, hi: float = 99.5) -> tuple[float, float]:
    finite = data[np.isfinite(data)]
    if finite.size == 0:
        return 0.0, 1.0
    vmax = float(np.percentile(finite, hi))
    return 0.0, vmax if vmax > 0 else 1.0


def layer_cmap(name: str) -> str:
    """The matplotlib colour map of float layer ``name``: the ramp of its QGIS style, so PNGs and QGIS agree."""
    ramp = RAMPS.get(name)
    return ramp.name if ramp is not None else "viridis"


def add_colorbar(ax: Any, image: Any, name: str, label: str | None = None) -> Any:
    """A colour bar beside ``ax`` for ``image`` of float layer ``name``, labelled with its unit.

    Args:
        label: the bar's label; default: the layer's title (e.g. ``"height std (m)"``) or its unit.
    """
    unit = LAYER_UNITS.get(name, "")
    if label is None:
        label = FLOAT_LAYERS.get(name, f"{name} ({unit})" if unit else name)
    bar = ax.figure.colorbar(image, ax=ax, fraction=0.046, pad=0.02)
    bar.set_label(label, fontsize=8)
    bar.ax.tick_params(labelsize=7)
    return bar


def add_class_legend(ax: Any, scheme: ClassScheme, fontsize: int = 7) -> Any:
    """A legend of the class **names** with their colours, outside ``ax`` on its right."""
    from matplotlib.patches import Patch

    handles = [Patch(facecolor=(c[0] / 255, c[1] / 255, c[2] / 255), edgecolor="k", label=n)
               for c, n in zip(scheme.colors, scheme.names, strict=True)]
    return ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=fontsize,
                     frameon=False, title="classes", title_fontsize=fontsize + 1)


def _draw(ax: Any, maps: PredictionMaps, key: str, extent: Sequence[float], crop: tuple[slice, slice] | None = None,
          colorbar: bool = True, legend: bool = True) -> None:
    from matplotlib.colors import ListedColormap

    sl = crop or (slice(None), slice(None))
    common = dict(extent=extent, interpolation="nearest")
    if key == "rgb":
        assert maps.rgb is not None
        ax.imshow(np.nan_to_num(maps.rgb[sl], nan=1.0), **common)
        return
    if key == "classes":
        assert maps.classes is not None
        k = (maps.scheme.num_classes if maps.scheme is not None
             else int(maps.classes[maps.classes != IGNORE_INDEX].max(initial=0)) + 1)
        colors = np.array(maps.scheme.colors, float) / 255 if maps.scheme is not None else None
        cmap = ListedColormap(colors) if colors is not None else "tab10"
        data = np.ma.masked_equal(maps.classes[sl], IGNORE_INDEX)
        ax.imshow(data, cmap=cmap, vmin=-0.5, vmax=k - 0.5, **common)
        if legend and maps.scheme is not None:
            add_class_legend(ax, maps.scheme)
        return
    full = maps.layers[key]
    vmin, vmax = _vrange(full)
    im = ax.imshow(np.ma.masked_invalid(full[sl]), cmap=layer_cmap(key), vmin=vmin, vmax=vmax, **common)
    if colorbar:
        add_colorbar(ax, im, key)


def plot_maps(maps: PredictionMaps, fig: Any = None, cols: int = 3, panel_size: float = 4.0) -> tuple[Any, np.ndarray]:
    """Orthophoto, height, height std, classes (scheme colours + legend), entropy and mutual information.

    All panels share their x and y axes (map coordinates), so zooming or panning one — or calling
    :func:`zoom_to` — moves all of them.

    Args:
        maps: from :func:`load_prediction_maps`.
        fig: figure to draw into (e.g. ``plt.figure()`` to show it inline); default a new
            ``matplotlib.figure.Figure``.
        cols: panels per row.
        panel_size: inches per panel.

    Returns:
        ``(fig, axes)`` with ``axes`` the array of panel axes in drawing order (length = panels).
    """
    panels = _panels(maps)
    rows = max(1, math.ceil(len(panels) / cols))
    fig = _new_figure(fig, (panel_size * cols * 1.15, panel_size * rows))
    grid_axes = np.atleast_1d(fig.subplots(rows, cols, sharex=True, sharey=True, squeeze=False)).ravel()
    for ax in grid_axes[len(panels):]:
        ax.set_visible(False)
    for ax, (key, title) in zip(grid_axes, panels):
        _draw(ax, maps, key, maps.extent)
        ax.set_title(title, fontsize=9)
        ax.tick_params(labelsize=7)
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.locator_params(nbins=4)
    fig.tight_layout()
    return fig, grid_axes[: len(panels)]


def zoom_to(axes: Iterable[Any], area: dict[str, Any], margin: float = 0.0,
            within: Sequence[float] | None = None) -> None:
    """Set every axis to the bounds of ``area`` (a :func:`most_uncertain_areas` row) ± ``margin`` map units.

    ``within``: ``(left, right, bottom, top)`` the view may not leave (e.g. ``maps.extent``).
    """
    left, right = area["left"] - margin, area["right"] + margin
    bottom, top = area["bottom"] - margin, area["top"] + margin
    if within is not None:
        left, right = max(left, within[0]), min(right, within[1])
        bottom, top = max(bottom, within[2]), min(top, within[3])
    for ax in axes:
        ax.set_xlim(left, right)
        ax.set_ylim(bottom, top)


def plot_areas(maps: PredictionMaps, areas: Sequence[dict[str, Any]], fig: Any = None, panel_size: float = 2.4) -> Any:
    """One row per area (the :func:`most_uncertain_areas` rows), one column per layer, cropped to it.

    Colour scales are those of the whole scene (as in :func:`plot_maps`), so rows can be compared.
    """
    panels = _panels(maps)
    rows = max(1, len(areas))
    fig = _new_figure(fig, (panel_size * len(panels) * 1.1, panel_size * rows))
    axes = fig.subplots(rows, len(panels), squeeze=False)
    for i, area in enumerate(areas):
        r0, c0 = area["row_off"], area["col_off"]
        crop = (slice(r0, r0 + area["height"]), slice(c0, c0 + area["width"]))
        extent = (area["left"], area["right"], area["bottom"], area["top"])
        for j, (key, title) in enumerate(panels):
            ax = axes[i, j]
            _draw(ax, maps, key, extent, crop, colorbar=False, legend=False)
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(title, fontsize=8)
            if j == 0:
                ax.set_ylabel(f"#{area['rank']}\n({area['x']:.0f}, {area['y']:.0f})", fontsize=7)
    fig.tight_layout()
    return fig


#: Titles of the sparsification panels.
_SPARSIFICATION_TITLES = {
    "height_std": "height std vs |height error|",
    "class_entropy": "class entropy vs misclassified",
    "class_mutual_info": "mutual information vs misclassified",
}


def uncertainty_summary(report: dict[str, Any]) -> dict[str, dict[str, float]]:
    """AUSE, AURG, Spearman and the full-set mean error per uncertainty layer of an evaluation report.

    Returns:
        ``{layer: {"ause", "aurg", "spearman", "mean_error", "n_pixels"}}`` for the layers of
        ``report["uncertainty"]`` that have a sparsification curve (``nan`` where undefined).
    """
    out: dict[str, dict[str, float]] = {}
    for key, sec in (report.get("uncertainty") or {}).items():
        sp = sec.get("sparsification") if isinstance(sec, dict) else None
        if not sp:
            continue
        rho = sec.get("spearman_std_vs_abs_error", sec.get("spearman_vs_error"))
        out[key] = {
            "ause": _num(sp.get("ause")), "aurg": _num(sp.get("aurg")), "spearman": _num(rho),
            "mean_error": _num(sp.get("mean_error")), "n_pixels": _num(sp.get("n_pixels")),
        }
    return out


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


def plot_sparsification(report: dict[str, Any], fig: Any = None, panel_size: float = 4.0) -> Any:
    """Sparsification curves of every uncertainty layer in ``report`` with their oracle and random curves."""
    keys = [k for k in UNCERTAINTY_LAYERS if (report.get("uncertainty") or {}).get(k, {}).get("sparsification")]
    if not keys:
        raise InputError("the evaluation report has no sparsification curves: predict with T > 1 (--mc) and "
                         "evaluate against reference heights and/or labels")
    fig = _new_figure(fig, (panel_size * 1.1 * len(keys), panel_size))
    axes = fig.subplots(1, len(keys), squeeze=False)[0]
    summary = uncertainty_summary(report)
    for ax, key in zip(axes, keys):
        sp = report["uncertainty"][key]["sparsification"]
        f = np.asarray(sp["fractions"], float)
        s = summary[key]
        ax.plot(f, np.asarray(sp["curve"], float), label=f"by uncertainty (AUSE {s['ause']:.3f})")
        ax.plot(f, np.asarray(sp["oracle"], float), "--", label="oracle (by true error)")
        ax.plot(f, np.asarray(sp["random"], float), ":", label=f"random (AURG {s['aurg']:.3f})")
        ax.set_xlabel("fraction removed (most uncertain first)", fontsize=8)
        ax.set_ylabel("remaining mean error / full-set error" if sp.get("normalised") else "remaining mean error",
                      fontsize=8)
        ax.set_title(f"{_SPARSIFICATION_TITLES[key]}\nSpearman ρ = {s['spearman']:.2f}", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


__all__ = ["FLOAT_LAYERS", "UNCERTAINTY_LAYERS", "PredictionMaps", "display_grid", "format_areas",
           "add_class_legend", "add_colorbar", "layer_cmap",
           "load_prediction_maps", "most_uncertain_areas", "plot_areas", "plot_maps", "plot_sparsification",
           "uncertainty_summary", "zoom_to"]
