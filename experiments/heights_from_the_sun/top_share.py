"""How much of ``shadow_height.tif`` falls on open ground, and how many objects it measures, if the rendered height
were painted only where the network's height reaches a larger share of its object's 90th percentile (the
``top_share`` of :class:`aerialmtl.sun.RenderSettings`, 0.5 in the product).

An estimate from the study's finished predictions (``run.py --out DIR``), no new prediction: the ``shadows`` arm's
``shadow_height.tif`` masked with the ``recipe`` arm's heights (the same network before fusion; objects = its
connected pixels ≥ 2 m over the whole block, where predict labels them per window). At 0.5 it reproduces the
study's open-ground shares within a point. Usage::

    python -m experiments.heights_from_the_sun.top_share --out /work/study58
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import rasterio
from scipy import ndimage

from experiments.heights_from_the_sun.run import _reference_on

SHARES = (0.5, 0.7, 0.85)


def _read(path: Path) -> tuple[np.ndarray, float]:
    with rasterio.open(path) as src:
        data = src.read(1).astype(np.float32)
        return np.where(data == src.nodata, np.nan, data), abs(src.res[0])


def estimate(out: Path, block: str, seed: int, share: float) -> dict[str, float]:
    """Open-ground share with a value, median relative error and count of the reference objects ≥ 10 m measured
    (≥ half their pixels painted), and objects measured in all, for one block, seed and ``share``."""
    shadows, recipe = out / "pred" / f"shadows_{block}_s{seed}", out / "pred" / f"recipe_{block}_s{seed}"
    sh, _ = _read(shadows / "shadow_height.tif")
    base, gsd = _read(recipe / "height.tif")
    lab, _ = ndimage.label(np.nan_to_num(base) >= 2.0)
    p90 = np.zeros(lab.max() + 1, np.float32)
    for k, box in enumerate(ndimage.find_objects(lab), 1):
        if box is not None:
            p90[k] = np.percentile(base[box][lab[box] == k], 90)
    sh = np.where((lab > 0) & (np.nan_to_num(base) >= share * p90[lab]), sh, np.nan)
    ref = _reference_on(shadows / "height.tif")
    ref = np.where(np.isfinite(_read(shadows / "height.tif")[0]), ref, np.nan)
    objects, n = ndimage.label(np.nan_to_num(ref) >= 2.0)
    open_ground = np.isfinite(ref) & (ref < 1.0) & (ndimage.distance_transform_edt(objects == 0) * gsd >= 2.0)
    rows = []
    for k in range(1, n + 1):
        m = objects == k
        if m.sum() >= 20:
            s = sh[m][np.isfinite(sh[m])]
            rows.append((float(np.nanmedian(ref[m])), float(np.median(s)) if s.size >= 0.5 * m.sum() else math.nan))
    tall = [(r, s) for r, s in rows if r >= 10.0 and math.isfinite(s)]
    return {"open_ground": float(np.isfinite(sh[open_ground]).mean()),
            "rel_error_10m": float(np.median([s / r - 1.0 for r, s in tall])) if tall else math.nan,
            "measured_10m": len(tall), "objects_10m": sum(1 for r, _ in rows if r >= 10.0),
            "measured": sum(1 for _, s in rows if math.isfinite(s))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = ap.parse_args()
    print("| block | top_share | open ground with a value | objects ≥ 10 m measured | their median relative error "
          "| objects measured |\n|---|---|---|---|---|---|")
    for block in ("val", "test"):
        for share in SHARES:
            res = [estimate(args.out, block, s, share) for s in args.seeds]
            rel = [r["rel_error_10m"] for r in res if math.isfinite(r["rel_error_10m"])]
            print(f"| {block} | {share:g} | {np.mean([r['open_ground'] for r in res]):.3f} | "
                  f"{np.mean([r['measured_10m'] for r in res]):.1f} of {res[0]['objects_10m']} | "
                  f"{f'{np.mean(rel):+.2f}' if rel else 'none measured'} | "
                  f"{np.mean([r['measured'] for r in res]):.1f} |")


if __name__ == "__main__":
    main()
