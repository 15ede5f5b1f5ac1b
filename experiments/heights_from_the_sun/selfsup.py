"""Issue 58, item 3: the height decoder tuned on the area being mapped, self-supervised by its cast shadows.

Arms on the study's checkpoints (``runs/s*/best.pt``, 3 seeds) and blocks, each the user's command
``aerialmtl predict --mc 16 --sun-tune STEPS`` (:mod:`aerialmtl.inference.self_tune`): ``tuneN`` (the tuned
network's maps, shadow layers beside them) and ``tuneN_shadows`` (with ``--shadow-fusion`` as well). The
validation block chooses the steps; the held-out block reports.

Usage::

    python -m experiments.heights_from_the_sun.selfsup --out /work/study58 --steps 20 30 40
    python -m experiments.heights_from_the_sun.selfsup --out /work/study58 --steps 20 30 40 --table
    python -m experiments.heights_from_the_sun.selfsup --out /work/study58 --steps 30 --spread
    python -m experiments.heights_from_the_sun.selfsup --out /work/study58 --steps 30 --annecy
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from experiments.heights_from_the_sun.run import DATA, MC, _run, _val_block, table

#: The arms' predict flags by suffix of the arm's name.
ARMS = {"": [], "_shadows": ["--shadow-fusion"]}


def spread_arm(out: Path, seeds: list[int], steps: int) -> None:
    """Print, per block and seed, what widening ``tune{steps}``'s spread by the move tuning made
    (``hypot(std, |h_tuned − h_recipe|)``) does to Spearman(std, |error|) and Spearman(std, h) at 5–10 and 10–20 m,
    and Spearman(move, |error|): estimated from the predictions, no predict."""
    import numpy as np
    import rasterio
    from scipy.stats import spearmanr

    from experiments.heights_from_the_sun.run import _reference_on

    def read(path: Path) -> np.ndarray:
        with rasterio.open(path) as src:
            a = src.read(1).astype(np.float64)
            return np.where(a == src.nodata, np.nan, a)

    for block in ("val", "test"):
        for seed in seeds:
            tuned = out / "pred" / f"tune{steps}_{block}_s{seed}"
            h0, ht = read(out / "pred" / f"recipe_{block}_s{seed}" / "height.tif"), read(tuned / "height.tif")
            sd, ref = read(tuned / "height_std.tif"), _reference_on(tuned / "height.tif")
            ok = np.isfinite(h0) & np.isfinite(ht) & np.isfinite(sd) & np.isfinite(ref)
            err, move = np.abs(ht - ref), np.abs(ht - h0)
            wide = np.hypot(sd, move)
            cols = []
            for lo, hi in ((5.0, 10.0), (10.0, 20.0)):
                k = ok & (ref >= lo) & (ref < hi)
                cols.append(f"{lo:g}–{hi:g} m: Spearman(std, |err|) {spearmanr(sd[k], err[k])[0]:+.2f} → "
                            f"{spearmanr(wide[k], err[k])[0]:+.2f}, Spearman(std, h) {spearmanr(sd[k], ht[k])[0]:+.2f}"
                            f" → {spearmanr(wide[k], ht[k])[0]:+.2f}, Spearman(move, |err|) "
                            f"{spearmanr(move[k], err[k])[0]:+.2f}")
            print(block, seed, " | ".join(cols))


def annecy(out: Path, seed: int, steps: int, threads: int) -> None:
    """Predict ``flair_annecy`` (15–33 m buildings; its sun fitted from its nDSM, ``annecy.py``) with seed ``seed``'s
    autzen_west checkpoint, without and with ``--sun-tune steps``, and print the bias per bin of nDSM height: a
    network trained on another area, on tall buildings (not a score: one 100 m patch)."""
    import numpy as np
    import rasterio
    from rasterio.warp import Resampling, reproject

    from experiments.heights_from_the_sun.annecy import DATA as ANNECY

    exe = [sys.executable, "-m", "aerialmtl"]
    for arm, flags in (("plain", []), (f"tune{steps}", ["--sun-tune", str(steps)])):
        pred = out / "pred" / f"annecy_{arm}_s{seed}"
        if not (pred / "prediction.json").is_file():
            _run([*exe, "predict", str(ANNECY / "ortho_0p2m_l93.tif"), "--model",
                  str(out / "runs" / f"s{seed}" / "best.pt"), "--mc", str(MC), "--sun", "137.5,57.2", "--out",
                  str(pred), "--overwrite", "--quiet", *flags], threads)
        with rasterio.open(pred / "height.tif") as grid, rasterio.open(ANNECY / "ndsm_0p2m_l93.tif") as src:
            h = grid.read(1)
            ref = np.full(h.shape, np.nan, np.float32)
            reproject(rasterio.band(src, 1), ref, dst_transform=grid.transform, dst_crs=grid.crs,
                      resampling=Resampling.average, dst_nodata=np.nan)
        ok = np.isfinite(ref)
        cols = [f"MAE {np.abs(h - ref)[ok].mean():.2f}"]
        for lo, hi in ((2.0, 10.0), (10.0, 15.0), (15.0, 20.0), (20.0, np.inf)):
            k = ok & (ref >= lo) & (ref < hi)
            cols.append(f"{lo:g}–{hi:g} m: {int(k.sum())} px, bias {(h - ref)[k].mean():+.2f}")
        print(arm, " | ".join(cols))


def main() -> None:
    """Run the missing arms, then print the tables (or only the tables)."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--steps", type=int, nargs="+", default=[30])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--table", action="store_true", help="print the tables of what is there; run nothing")
    ap.add_argument("--spread", action="store_true",
                    help="the spread widened by the move tuning made, estimated from the first --steps' arm")
    ap.add_argument("--annecy", action="store_true",
                    help="flair_annecy predicted with the first seed's checkpoint, without and with the first --steps")
    a = ap.parse_args()
    if a.annecy:
        annecy(a.out, a.seeds[0], a.steps[0], a.threads)
        return
    if a.spread:
        spread_arm(a.out, a.seeds, a.steps[0])
        return
    blocks = {"val": _val_block(a.out), "test": DATA / "test_block.geojson"}
    if not a.table:
        exe = [sys.executable, "-m", "aerialmtl"]
        for steps in a.steps:
            for seed in a.seeds:
                for block, aoi in blocks.items():
                    for suffix, flags in ARMS.items():
                        pred = a.out / "pred" / f"tune{steps}{suffix}_{block}_s{seed}"
                        if not (pred / "prediction.json").is_file():
                            _run([*exe, "predict", str(DATA / "ortho_1ft.tif"), "--model",
                                  str(a.out / "runs" / f"s{seed}" / "best.pt"), "--aoi", str(aoi), "--mc", str(MC),
                                  "--sun-tune", str(steps), "--out", str(pred), "--overwrite", "--quiet", *flags],
                                 a.threads)
    tags = [f"tune{s}" for s in a.steps]
    print(table(a.out, a.seeds, arms=["recipe", "shadows", *[t + s for t in tags for s in ARMS]],
                shadow_arms=["shadows", *[t + "_shadows" for t in tags]]))


if __name__ == "__main__":
    main()
