"""Heights by rendering shadows on tall buildings: ``flair_annecy`` (15–33 m blocks in rows, shadows on streets,
courtyards and other roofs). A check of the geometry, not of a network: too small to train on.

The sun is fitted on the patch from its own nDSM (:func:`aerialmtl.sun.fit_sun`); the shadow probability is a
:class:`~aerialmtl.sun.ShadowModel` fitted on the patch itself (``learnt``) or the nDSM's exact cast shadows at that
sun (``exact``). Objects are the connected components of the building label with nDSM ≥ 2 m (≥ 20 m²). Each
object's height is measured two ways and compared with its median nDSM:

* ``runs`` — today's :func:`aerialmtl.sun.shadow_heights`, runs located with the heights given;
* ``render`` — :func:`aerialmtl.sun.render.rendered_heights`: the height whose rendered cast shadow (the whole
  map's) best matches the shadow probability.

The heights given (the objects' shapes and everything around them) are the nDSM itself (``ndsm``), and a
network-like degraded copy (``degraded``: half the height, blurred by 1 m) from which the shadows must recover
the truth. Per bin of reference height: objects, share measured, median relative error, MAE.

Usage::

    OMP_NUM_THREADS=1 python -m experiments.heights_from_the_sun.annecy [--data DIR] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from scipy import ndimage

from aerialmtl.sun import ShadowModel, Sun, cast_shadow_mask, fit_sun, shadow_heights
from aerialmtl.sun.render import rendered_heights
from experiments.common.autzen import cpu_model

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "flair_annecy"
BINS = ((2.0, 10.0), (10.0, 15.0), (15.0, 20.0), (20.0, math.inf))
MIN_AREA_M2 = 20.0


def load(data: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(rgb uint8 (3, H, W), nDSM float32 (H, W) metres, labels uint8 (H, W), gsd metres)."""
    with rasterio.open(data / "ortho_0p2m_l93.tif") as src:
        rgb = src.read()
        gsd = float(src.res[0])
    with rasterio.open(data / "ndsm_0p2m_l93.tif") as src:
        ndsm = src.read(1, masked=True).filled(np.nan).astype(np.float32)
    with rasterio.open(data / "labels_0p2m_l93.tif") as src:
        labels = src.read(1)
    return rgb, ndsm, labels, gsd


def buildings(ndsm: np.ndarray, labels: np.ndarray, gsd: float, band_m: float = 4.0) -> np.ndarray:
    """int32 (H, W) building objects: the building label's pixels ≥ 2 m, split where the height changes.

    The blocks join into rows, so connected components of the label are whole streets. Each row is cut into
    its buildings by height: connected pixels within one ``band_m`` band of the median-filtered nDSM, ≥ 20 m²,
    each grown back over the row's pixels nearest to it (the smoothed walls between them).
    """
    build = (labels == 1) & (ndsm >= 2.0)
    smooth = ndimage.median_filter(np.nan_to_num(ndsm), size=int(round(1.0 / gsd)) | 1)
    band = np.floor(smooth / band_m).astype(np.int32)
    seeds = np.zeros(ndsm.shape, np.int32)
    n = 0
    for b in np.unique(band[build]):
        comp, k = ndimage.label(build & (band == b))
        sizes = ndimage.sum_labels(np.ones_like(ndsm), comp, index=np.arange(1, k + 1)) * gsd * gsd
        for i in np.flatnonzero(sizes >= MIN_AREA_M2):
            n += 1
            seeds[comp == i + 1] = n
    _, (rr, cc) = ndimage.distance_transform_edt(seeds == 0, return_indices=True)
    grown = seeds[rr, cc]
    return np.where(build, grown, 0).astype(np.int32)


def summarise(rows: list[dict[str, float]]) -> list[dict[str, Any]]:
    """Per bin of reference height: objects, share measured, median relative error, MAE (metres)."""
    out = []
    for lo, hi in BINS:
        sel = [r for r in rows if lo <= r["ref"] < hi]
        got = [r for r in sel if math.isfinite(r["est"])]
        rel = [r["est"] / r["ref"] - 1.0 for r in got]
        share = len(got) / len(sel) if sel else math.nan
        out.append({"bin": f"{lo:g}-{hi:g} m", "objects": len(sel), "measured": share,
                    "median_rel": float(np.median(rel)) if rel else math.nan,
                    "mae": float(np.mean([abs(r["est"] - r["ref"]) for r in got])) if got else math.nan})
    return out


def main() -> None:
    """Run every (shadow source × heights given × method) and print the tables."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    rgb, ndsm, labels, gsd = load(args.data)
    t0 = time.time()
    fit = fit_sun(rgb, ndsm, gsd)
    if fit.sun is None:
        raise SystemExit(f"no sun: {fit.reason}")
    sun: Sun = fit.sun
    print(f"sun fitted on the patch: azimuth {sun.azimuth_deg:.1f}°, elevation {sun.elevation_deg:.1f}° "
          f"({time.time() - t0:.1f} s)")
    model = ShadowModel().fit(rgb, ndsm, gsd, sun)
    learnt = model.predict_proba(rgb, gsd)
    exact = cast_shadow_mask(ndsm, gsd, sun).astype(np.float32)
    objects = buildings(ndsm, labels, gsd)
    ref = {int(k): float(np.median(ndsm[objects == k])) for k in np.unique(objects) if k}
    degraded = (ndimage.gaussian_filter(np.nan_to_num(ndsm), 1.0 / gsd) * 0.5).astype(np.float32)
    results: dict[str, Any] = {"sun": [sun.azimuth_deg, sun.elevation_deg], "machine": cpu_model(), "tables": {}}
    for shadow_name, prob in (("learnt", learnt), ("exact", exact)):
        for given_name, given in (("ndsm", ndsm), ("degraded", degraded)):
            for method in ("runs", "render"):
                t = time.time()
                if method == "runs":
                    got = shadow_heights(prob, gsd, sun, objects, height=given,
                                         threshold=model.threshold if shadow_name == "learnt" else 0.5)
                else:
                    got = rendered_heights(prob, gsd, sun, objects, given)
                est = {o.label: o.height_m for o in got.objects}
                rows = [{"ref": ref[k], "est": est.get(k, math.nan)} for k in ref]
                key = f"{shadow_name}/{given_name}/{method}"
                results["tables"][key] = {"bins": summarise(rows), "seconds": time.time() - t}
                print(f"\n{key} ({time.time() - t:.1f} s)")
                print("| bin | objects | measured | median relative error | MAE (m) |\n|---|---|---|---|---|")
                for b in results["tables"][key]["bins"]:
                    print(f"| {b['bin']} | {b['objects']} | {b['measured']:.2f} | {b['median_rel']:+.2f} | "
                          f"{b['mae']:.2f} |")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
