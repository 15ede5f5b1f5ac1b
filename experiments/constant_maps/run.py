"""A prediction's height errors against constant maps on the same pixels (issue 36: "the start alone, against a
constant map").

For a prediction folder and its reference (an nDSM, or a DSM and a DTM, read as ``aerialmtl evaluate`` reads them),
prints the prediction's MAE, MAE and bias on pixels ≥ 2 m, and the MAE of three constant maps: 0 m (all ground),
the reference's median (the best constant under L1) and its mean. The constants are the reference's own (an
oracle a model cannot know), so they are a bar, not an arm. Usage::

    python -m experiments.constant_maps.run --pred alone/autzen --dsm samples/autzen_west/dsm_1m_utm.tif \\
        --dtm samples/autzen_west/dtm_1m_utm.tif
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import rasterio

from aerialmtl.io.align import HeightSource, grid_of

TALL_M = 2.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pred", type=Path, required=True)
    ap.add_argument("--height", type=Path)
    ap.add_argument("--dsm", type=Path)
    ap.add_argument("--dtm", type=Path)
    args = ap.parse_args()
    with rasterio.open(args.pred / "height.tif") as src:
        grid, pred, nodata = grid_of(src), src.read(1).astype(np.float64), src.nodata
    with HeightSource(grid, ndsm=args.height, dsm=args.dsm, dtm=args.dtm) as source:
        ref, valid = source.read(grid.full_window())
    ok = valid & np.isfinite(pred) & (pred != nodata)
    p, r = pred[ok], ref[ok].astype(np.float64)
    err, tall = p - r, r >= TALL_M
    print(f"{args.pred}: {ok.sum()} px, reference mean {r.mean():.2f} m, {tall.mean():.1%} ≥ {TALL_M:g} m")
    print(f"  prediction      MAE {np.abs(err).mean():.3f} m, MAE ≥ {TALL_M:g} m {np.abs(err[tall]).mean():.2f} m, "
          f"bias ≥ {TALL_M:g} m {err[tall].mean():+.2f} m")
    for name, value in (("0 m", 0.0), ("median", float(np.median(r))), ("mean", float(r.mean()))):
        print(f"  constant {name:7s} ({value:5.2f} m)  MAE {np.abs(value - r).mean():.3f} m")


if __name__ == "__main__":
    main()
