"""Heights from the sun on real data (issue 45): fit the sun on ``autzen_west``'s training block, measure
per-object heights from shadows on its validation and held-out blocks, against the reference nDSM.

No network is involved: the objects are connected components of the **reference** nDSM > 2 m (≥ 20 m²), the
shadow probability comes from a :class:`~aerialmtl.sun.ShadowModel` fitted on the training block against the
cast shadows of its reference heights at the fitted sun. Two ways of measuring are reported:

* ``edge`` — runs measured from each object's shadow-casting edge (no heights used at all);
* ``located`` — each run measured from the pixel of the object whose sun ray reaches furthest, located with
  the reference heights (what the network's own height map would give at best: only positions are used);
* ``exact`` — not a measurement: ``located`` on the cast shadows of the reference heights instead of the
  shadow model's mask, to tell the geometry's error from the shadow mask's.

Per reference-height bin of the object (median nDSM over the object: 2–5, 5–10, 10–20, ≥ 20 m): objects,
share measured, median ratio shadow / reference, MAE and bias in metres. The split is
``samples/autzen_west/split.geojson`` (experiments/common/autzen.py's ``middle-val``) and ``test_block.geojson``.

Usage::

    OMP_NUM_THREADS=1 nice python -m experiments.heights_from_the_sun.shadow_heights [--gsd 0.6096] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from rasterio.features import geometry_mask
from scipy import ndimage

from aerialmtl.io.align import AlignedRaster, HeightSource, reference_grid
from aerialmtl.io.vector import load_geometries
from aerialmtl.sun import ShadowModel, Sun, cast_shadow_mask, fit_sun, shadow_heights
from experiments.common.autzen import DATA, DSM, DTM, ORTHO, cpu_model

BINS = ((2.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, math.inf))
MIN_AREA_M2 = 20.0
WAYS = ("edge", "located", "exact")


def block_masks(data: Path, grid: Any) -> dict[str, np.ndarray]:
    """bool (H, W) per block name (train, val, test) on ``grid``."""
    out: dict[str, np.ndarray] = {}
    for path in (data / "split.geojson", data / "test_block.geojson"):
        for geom, props in load_geometries(path, grid.crs, "split"):
            name = str(props.get("split"))
            m = geometry_mask([geom], out_shape=(grid.height, grid.width), transform=grid.transform, invert=True)
            out[name] = out.get(name, np.zeros_like(m)) | m
    return out


def per_bin(rows: list[dict[str, float]], key: str) -> list[dict[str, Any]]:
    """Per reference-height bin: objects, share measured, median ratio, MAE, bias of ``key`` vs ``ref``."""
    out = []
    for lo, hi in BINS:
        sel = [r for r in rows if lo <= r["ref"] < hi]
        got = [r for r in sel if math.isfinite(r[key])]
        err = np.array([r[key] - r["ref"] for r in got])
        ratio = np.array([r[key] / r["ref"] for r in got])
        out.append({"bin": f"{lo:g}–{hi:g} m" if math.isfinite(hi) else f"≥ {lo:g} m", "objects": len(sel),
                    "measured": len(got), "share": len(got) / len(sel) if sel else math.nan,
                    "median_ratio": float(np.median(ratio)) if len(got) else math.nan,
                    "mae": float(np.abs(err).mean()) if len(got) else math.nan,
                    "bias": float(err.mean()) if len(got) else math.nan})
    return out


def measure_block(rgb: np.ndarray, h: np.ndarray, ok: np.ndarray, block: np.ndarray, gsd: float, sun: Sun,
                  model: ShadowModel) -> list[dict[str, float]]:
    """Per object of the block: reference median height and the two shadow heights."""
    rows_, cols_ = np.nonzero(block)
    sl = (slice(rows_.min(), rows_.max() + 1), slice(cols_.min(), cols_.max() + 1))
    inside = block[sl] & ok[sl]
    prob = model.predict_proba(rgb[:, sl[0], sl[1]])
    prob = np.where(inside, prob, np.nan).astype(np.float32)
    href = np.where(inside, h[sl], np.nan)
    objects, _ = ndimage.label(np.nan_to_num(href) > 2.0)
    sizes = np.bincount(objects.ravel())
    small = sizes * gsd * gsd < MIN_AREA_M2
    small[0] = False
    objects[small[objects]] = 0
    objects, _ = ndimage.label(objects > 0)
    edge = shadow_heights(prob, gsd, sun, objects, threshold=model.threshold)
    located = shadow_heights(prob, gsd, sun, objects, height=href, threshold=model.threshold)
    cast = np.where(inside, cast_shadow_mask(h, gsd, sun)[sl], np.nan).astype(np.float32)
    exact = shadow_heights(cast, gsd, sun, objects, height=href)
    index = np.arange(1, objects.max() + 1)
    ref = ndimage.median(href, objects, index=index)
    top = ndimage.labeled_comprehension(href, objects, index, lambda v: np.percentile(v, 95), float, np.nan)
    rows = []
    for o_e, o_l, o_x, r, t in zip(edge.objects, located.objects, exact.objects, np.atleast_1d(ref),
                                   np.atleast_1d(top)):
        rows.append({"label": o_e.label, "ref": float(r), "ref95": float(t), "edge": o_e.height_m,
                     "located": o_l.height_m, "exact": o_x.height_m, "std": o_l.std_m})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--gsd", type=float, default=0.6096, help="working pixel size, metres (default 2 ft)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    load0 = os.getloadavg()
    grid = reference_grid(args.data / ORTHO, args.gsd)
    with AlignedRaster(args.data / ORTHO, grid, "image", bands=[1, 2, 3], role="orthophoto") as src:
        rgb, ok_rgb = src.read()
    with HeightSource(grid, dsm=args.data / DSM, dtm=args.data / DTM) as hs:
        h, ok_h = hs.read(grid.full_window())
    ok = ok_rgb & ok_h
    blocks = block_masks(args.data, grid)
    t0 = time.perf_counter()
    fit = fit_sun(rgb, h, grid.gsd, ok & blocks["train"])
    t_fit = time.perf_counter() - t0
    print(fit.reason)
    sun = fit.sun or fit.best
    assert sun is not None
    model = ShadowModel().fit(rgb, h, grid.gsd, sun, ok & blocks["train"])
    print(f"shadow model: threshold {model.threshold} (chosen by {model.threshold_by} on the training block)")
    result: dict[str, Any] = {"gsd_m": grid.gsd, "shape": [grid.height, grid.width], "fit": fit.to_dict(),
                              "fit_seconds": t_fit, "model": model.to_dict(), "cpu": cpu_model(),
                              "load_start": load0, "blocks": {}}
    for name in ("val", "test"):
        rows = measure_block(rgb, h, ok, blocks[name], grid.gsd, sun, model)
        result["blocks"][name] = {"objects": rows, **{way: per_bin(rows, way) for way in WAYS}}
        print(f"\n### {name} block: {len(rows)} objects ≥ {MIN_AREA_M2:g} m² of reference nDSM > 2 m\n")
        print("| way | bin | objects | measured | share | median shadow/ref | MAE m | bias m |")
        print("|---|---|---:|---:|---:|---:|---:|---:|")
        for way in WAYS:
            for b in result["blocks"][name][way]:
                print(f"| {way} | {b['bin']} | {b['objects']} | {b['measured']} | {b['share']:.2f} | "
                      f"{b['median_ratio']:.2f} | {b['mae']:.2f} | {b['bias']:+.2f} |")
        tall = [r for r in rows if r["ref95"] >= 20.0]
        for way in WAYS:
            got = [r for r in tall if math.isfinite(r[way])]
            ratios = [r[way] / r["ref95"] for r in got]
            print(f"\nobjects whose 95th percentile reference height is ≥ 20 m: {len(tall)}, {way}: {len(got)} measured"
                  + (f", median shadow / 95th percentile {np.median(ratios):.2f}, shadow / median "
                     f"{np.median([r[way] / r['ref'] for r in got]):.2f}" if got else ""), end="")
        print()
    result["load_end"] = os.getloadavg()
    print(f"\nsun fit {t_fit:.1f} s on {grid.width} × {grid.height} px; {result['cpu']}; load {load0} → "
          f"{result['load_end']}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=float))


if __name__ == "__main__":
    main()
