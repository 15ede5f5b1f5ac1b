"""Score extracted buildings against reference footprints: the ``buildings`` part of ``aerialmtl evaluate``.

* **Footprints**: predicted and reference polygons are matched one-to-one, greedily by decreasing IoU
  among the pairs with IoU ≥ ``iou_threshold`` (0.5 by default, where a polygon of a set of disjoint
  polygons can have at most one such partner anyway); precision = matches / predicted buildings, recall
  = matches / reference buildings, F1 their harmonic mean.
* **Heights** on the matched pairs: error = predicted ``height_m`` − reference height (metres): MAE,
  RMSE, bias (mean error) and median absolute error.
* **Uncertainty**: Spearman rank correlation between the predicted ``height_std_m`` and the absolute
  height error of the matched buildings (1 = the spread ranks the errors perfectly).

Only reference buildings inside the area that was predicted count: reference footprints are clipped to
the prediction grid's bounds, and those left smaller than ``min_area_m2`` are dropped (as extraction
drops smaller predicted buildings). Areas are in m² whatever the CRS unit.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from rasterio.crs import CRS
from rasterio.warp import transform_geom
from shapely.geometry import box, mapping, shape
from shapely.strtree import STRtree

from aerialmtl.buildings.extract import Building, BuildingOptions, iter_buildings
from aerialmtl.errors import InputError, cause
from aerialmtl.evaluation.uncertainty import spearman
from aerialmtl.formats.buildings import read_footprints
from aerialmtl.io.units import metres_per_unit
from aerialmtl.io.vector import GEOJSON_DEFAULT_CRS, check_lonlat

#: Minimum IoU of a match.
DEFAULT_IOU_THRESHOLD = 0.5


def match_footprints(pred: Sequence[shapely.Geometry], ref: Sequence[shapely.Geometry],
                     iou_threshold: float = DEFAULT_IOU_THRESHOLD) -> list[tuple[int, int, float]]:
    """One-to-one matches ``(pred index, ref index, IoU)`` with IoU ≥ ``iou_threshold``, greedy by IoU.

    Ties are broken by (pred index, ref index), so the result does not depend on the STRtree's order.
    """
    if not len(pred) or not len(ref):
        return []
    tree = STRtree(np.asarray(ref, dtype=object))
    pi, ri = tree.query(np.asarray(pred, dtype=object), predicate="intersects")
    if pi.size == 0:
        return []
    p = np.asarray(pred, dtype=object)[pi]
    r = np.asarray(ref, dtype=object)[ri]
    inter = shapely.area(shapely.intersection(p, r))
    union = shapely.area(p) + shapely.area(r) - inter
    iou = np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
    keep = iou >= iou_threshold
    order = np.lexsort((ri[keep], pi[keep], -iou[keep]))
    used_p: set[int] = set()
    used_r: set[int] = set()
    matches = []
    for a, b, v in zip(pi[keep][order], ri[keep][order], iou[keep][order]):
        if int(a) in used_p or int(b) in used_r:
            continue
        used_p.add(int(a))
        used_r.add(int(b))
        matches.append((int(a), int(b), float(v)))
    return matches


def _ratio(a: int, b: int) -> float:
    return a / b if b else math.nan


def score_buildings(
    pred_geoms: Sequence[shapely.Geometry],
    pred_height: Sequence[float] | np.ndarray,
    pred_std: Sequence[float] | np.ndarray,
    ref_geoms: Sequence[shapely.Geometry],
    ref_height: Sequence[float] | np.ndarray | None,
    iou_threshold: float = DEFAULT_IOU_THRESHOLD,
) -> dict[str, Any]:
    """Footprint, height and uncertainty scores of predicted vs reference buildings (one CRS).

    Args:
        pred_geoms, pred_height, pred_std: predicted footprints, ``height_m`` and ``height_std_m``.
        ref_geoms, ref_height: reference footprints and heights (``None``: footprints only).
        iou_threshold: minimum IoU of a match.

    Returns:
        ``n_predicted``, ``n_reference``, ``n_matched``, ``precision``, ``recall``, ``f1``,
        ``mean_iou_matched``, ``height`` (``mae``, ``rmse``, ``bias``, ``median_abs_error``, ``n``, metres)
        and ``spearman_std_vs_abs_error``; undefined values are ``nan``.
    """
    matches = match_footprints(pred_geoms, ref_geoms, iou_threshold)
    n_p, n_r, n_m = len(pred_geoms), len(ref_geoms), len(matches)
    precision, recall = _ratio(n_m, n_p), _ratio(n_m, n_r)
    f1 = 2 * precision * recall / (precision + recall) if n_m else (0.0 if n_p or n_r else math.nan)
    out: dict[str, Any] = {
        "iou_threshold": iou_threshold, "n_predicted": n_p, "n_reference": n_r, "n_matched": n_m,
        "precision": precision, "recall": recall, "f1": f1,
        "mean_iou_matched": float(np.mean([m[2] for m in matches])) if matches else math.nan,
        "height": None, "spearman_std_vs_abs_error": math.nan,
    }
    if ref_height is not None and matches:
        ph = np.asarray(pred_height, np.float64)[[m[0] for m in matches]]
        rh = np.asarray(ref_height, np.float64)[[m[1] for m in matches]]
        sd = np.asarray(pred_std, np.float64)[[m[0] for m in matches]]
        ok = np.isfinite(ph) & np.isfinite(rh)
        err = ph[ok] - rh[ok]
        out["height"] = {
            "n": int(ok.sum()),
            "mae": float(np.abs(err).mean()) if err.size else math.nan,
            "rmse": float(np.sqrt((err**2).mean())) if err.size else math.nan,
            "bias": float(err.mean()) if err.size else math.nan,
            "median_abs_error": float(np.median(np.abs(err))) if err.size else math.nan,
        }
        out["spearman_std_vs_abs_error"] = spearman(sd[ok], np.abs(err))
    return out


def _to_crs(geoms: Iterable[shapely.Geometry], src: CRS | None, dst: CRS, path: str | Path,
            role: str) -> list[shapely.Geometry]:
    """``geoms`` of file ``path`` reprojected from ``src`` to ``dst``.

    Raises:
        InputError: a GeoJSON without a ``crs`` member (read as WGS 84, RFC 7946) whose coordinates are not
            degrees (naming the CRS to declare), or coordinates that cannot be reprojected.
    """
    geoms = list(geoms)
    if src is None or src == dst:
        return geoms
    if geoms and src == GEOJSON_DEFAULT_CRS and Path(path).suffix.lower() in (".geojson", ".json"):
        check_lonlat(path, role, geoms, dst)
    try:
        return [shape(transform_geom(src, dst, mapping(g))) for g in geoms]
    except Exception as exc:  # PROJ errors (CPLE_AppDefinedError) for coordinates outside the source CRS
        raise InputError(f"{role} '{path}': its polygons cannot be reprojected to the prediction's CRS "
                         f"({cause(exc)}); check the file's CRS") from exc


def evaluate_buildings(
    pred_dir: str | Path,
    reference: str | Path,
    grid: Any,
    pred_buildings: str | Path | None = None,
    options: BuildingOptions | None = None,
    iou_threshold: float = DEFAULT_IOU_THRESHOLD,
    height_field: str = "height_m",
    notes: list[str] | None = None,
) -> dict[str, Any]:
    """Score the buildings of a prediction against reference footprints (see the module docstring).

    Args:
        pred_dir: the prediction folder.
        reference: reference footprints (GeoPackage, GeoJSON, any OGR polygon file, any CRS) with a
            ``height_field`` (metres above ground) when heights are to be scored.
        grid: the prediction grid (:class:`~aerialmtl.io.align.Grid`): CRS and the bounds that clip the
            reference.
        pred_buildings: footprints written by ``aerialmtl buildings``; default: extracted from
            ``pred_dir`` now with ``options``.
        options: extraction settings when extracting (their ``min_area_m2`` also drops small reference
            footprints).
        iou_threshold: minimum IoU of a match.
        height_field: reference attribute holding building heights.
        notes: list that receives remarks for the report.

    Returns:
        :func:`score_buildings`'s dict plus ``reference``, ``predicted`` (the source), ``min_area_m2`` and
        ``n_reference_outside`` (reference footprints outside the prediction or too small once clipped).

    Raises:
        InputError: unreadable files, a predicted buildings file without ``height_m``/``height_std_m``.
    """
    options = options or BuildingOptions()
    notes = notes if notes is not None else []
    unit = metres_per_unit(grid.crs, "prediction", pred_dir)
    min_area = options.min_area_m2 / unit**2
    ref_geoms_all, ref_fields, ref_crs = read_footprints(reference, "building reference")
    if ref_crs is None:
        notes.append(f"building reference '{reference}' has no CRS: taken to be the prediction's")
    keep_idx = [i for i, g in enumerate(ref_geoms_all) if g is not None and not g.is_empty]
    ref_geoms = _to_crs([ref_geoms_all[i] for i in keep_idx], ref_crs, grid.crs, reference,
                       "building reference (‹buildings_ref›)")
    area = box(*grid.bounds)
    clipped = [shapely.make_valid(g).intersection(area) for g in ref_geoms]
    inside = [k for k, g in enumerate(clipped) if g.area >= max(min_area, 1e-12)]
    ref_final = [clipped[k] for k in inside]
    ref_height = None
    if height_field in ref_fields:
        ref_height = np.asarray(ref_fields[height_field], np.float64)[[keep_idx[k] for k in inside]]
    else:
        notes.append(f"building reference '{reference}' has no '{height_field}' field: building heights not scored")

    if pred_buildings is not None:
        geoms, fields, crs = read_footprints(pred_buildings, "predicted buildings")
        missing = [f for f in ("height_m", "height_std_m") if f not in fields]
        if missing:
            raise InputError(f"predicted buildings '{pred_buildings}' have no field(s) {', '.join(missing)}; pass "
                             "a file written by `aerialmtl buildings`")
        pred_geoms = _to_crs(geoms, crs, grid.crs, pred_buildings, "predicted buildings (‹pred_buildings›)")
        ph, ps = np.asarray(fields["height_m"], np.float64), np.asarray(fields["height_std_m"], np.float64)
        source = str(pred_buildings)
    else:
        found: list[Building] = list(iter_buildings(pred_dir, options))
        pred_geoms = [b.geometry for b in found]
        ph = np.array([b.attributes["height_m"] for b in found], np.float64)
        ps = np.array([b.attributes["height_std_m"] for b in found], np.float64)
        source = f"extracted from {pred_dir} with default settings" if options == BuildingOptions() \
            else f"extracted from {pred_dir}"
    result = score_buildings(pred_geoms, ph, ps, ref_final, ref_height, iou_threshold)
    result.update(reference=str(reference), predicted=source, min_area_m2=options.min_area_m2,
                  n_reference_outside=len(ref_geoms) - len(ref_final))
    return result


__all__ = ["DEFAULT_IOU_THRESHOLD", "evaluate_buildings", "match_footprints", "score_buildings"]
