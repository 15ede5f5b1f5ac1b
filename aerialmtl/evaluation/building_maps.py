"""Draw extracted buildings in map coordinates: footprints coloured by height and by its uncertainty.

The helpers behind the buildings section of ``notebooks/uncertainty_maps.ipynb``; matplotlib's object API
(pass a figure from ``pyplot`` to show it inline, or let them make one), like
:mod:`aerialmtl.evaluation.maps`, whose :class:`~aerialmtl.evaluation.maps.PredictionMaps` can give the
orthophoto drawn underneath.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import shapely
from shapely.geometry import Polygon

from aerialmtl.evaluation.maps import add_colorbar, layer_cmap
from aerialmtl.formats.buildings import ID_FIELD
from aerialmtl.formats.prediction import HEIGHT, HEIGHT_STD


def _path(poly: Polygon) -> Any:
    """A matplotlib ``Path`` of a polygon with its holes."""
    from matplotlib.path import Path as MplPath

    verts, codes = [], []
    for ring in (poly.exterior, *poly.interiors):
        xy = np.asarray(ring.coords)
        verts.append(xy)
        codes += [MplPath.MOVETO] + [MplPath.LINETO] * (len(xy) - 2) + [MplPath.CLOSEPOLY]
    return MplPath(np.concatenate(verts), codes)


def most_uncertain_buildings(fields: dict[str, np.ndarray], geoms: Sequence[shapely.Geometry],
                             top_k: int = 5) -> list[dict[str, Any]]:
    """The ``top_k`` buildings with the largest ``height_std_m`` (their id, centroid, height, spread, area)."""
    std = np.asarray(fields["height_std_m"], np.float64)
    order = [int(i) for i in np.argsort(-np.nan_to_num(std, nan=-np.inf), kind="stable")[:top_k]]
    out = []
    for i in order:
        c = geoms[i].centroid
        out.append({ID_FIELD: int(fields[ID_FIELD][i]), "x": c.x, "y": c.y, "height_m": float(fields["height_m"][i]),
                    "height_std_m": float(std[i]), "ground_area_m2": float(fields["ground_area_m2"][i])})
    return out


def format_buildings(rows: Sequence[dict[str, Any]]) -> str:
    """A plain-text table of :func:`most_uncertain_buildings` rows (centroids in map units)."""
    lines = [f"{'id':>5} {'height m':>9} {'std m':>7} {'area m²':>9} {'centroid x':>12} {'centroid y':>12}"]
    for r in rows:
        lines.append(f"{r[ID_FIELD]:>5} {r['height_m']:>9.2f} {r['height_std_m']:>7.2f} {r['ground_area_m2']:>9.1f} "
                     f"{r['x']:>12.2f} {r['y']:>12.2f}")
    return "\n".join(lines)


def plot_buildings(geoms: Sequence[shapely.Geometry], fields: dict[str, np.ndarray], maps: Any = None,
                   fig: Any = None, panel_size: float = 5.0) -> tuple[Any, np.ndarray]:
    """Two panels sharing their axes: footprints coloured by ``height_m`` and by ``height_std_m``.

    Args:
        geoms: footprints (map coordinates), e.g. from :func:`aerialmtl.formats.buildings.read_footprints`.
        fields: their attributes (``height_m``, ``height_std_m``).
        maps: a :class:`~aerialmtl.evaluation.maps.PredictionMaps` whose orthophoto (or, without one, predicted
            height) is drawn underneath in grey; its extent sets the view.
        fig: figure to draw into; default a new ``matplotlib.figure.Figure``.
        panel_size: inches per panel.

    Returns:
        ``(fig, axes)``.
    """
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import PathPatch

    if fig is None:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(2.3 * panel_size, panel_size))
    else:
        fig.set_size_inches(2.3 * panel_size, panel_size)
    axes = np.atleast_1d(fig.subplots(1, 2, sharex=True, sharey=True, squeeze=False)).ravel()
    polys = [g for g in geoms if isinstance(g, Polygon) and not g.is_empty]
    for ax, (key, title, layer) in zip(axes, (("height_m", "building height (m)", HEIGHT),
                                              ("height_std_m", "height std (m)", HEIGHT_STD))):
        cmap = layer_cmap(layer)  # the colour map of the layer's QGIS style
        if maps is not None:
            if maps.rgb is not None:
                ax.imshow(np.nan_to_num(maps.rgb.mean(axis=-1), nan=1.0), cmap="gray", extent=maps.extent,
                          interpolation="nearest", alpha=0.6)
            elif "height" in maps.layers:
                ax.imshow(np.ma.masked_invalid(maps.layers["height"]), cmap="gray", extent=maps.extent,
                          interpolation="nearest", alpha=0.6)
            ax.set_xlim(maps.extent[0], maps.extent[1])
            ax.set_ylim(maps.extent[2], maps.extent[3])
        values = np.asarray(fields.get(key, np.full(len(polys), np.nan)), np.float64)[: len(polys)]
        if polys:
            coll = PatchCollection([PathPatch(_path(p)) for p in polys], cmap=cmap, edgecolor="black", linewidth=0.5)
            coll.set_array(np.ma.masked_invalid(values))
            finite = values[np.isfinite(values)]
            if finite.size:
                coll.set_clim(0.0, max(float(finite.max()), 1e-6))
            ax.add_collection(coll)
            add_colorbar(ax, coll, layer, label=title)
            if maps is None:
                ax.autoscale_view()
        ax.set_title(f"{title}, {len(polys)} buildings", fontsize=9)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.locator_params(nbins=4)
    fig.tight_layout()
    return fig, axes


__all__ = ["format_buildings", "most_uncertain_buildings", "plot_buildings"]
