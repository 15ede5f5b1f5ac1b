"""Heights from the sun on ``autzen_west``: the recipe against the recipe with the shadow heights fused into its
objects, 3 seeds, the sample area's fixed split; the validation block chooses, the held-out block reports.

Every step is the user's command (``aerialmtl tile``, ``train``, ``predict``), so the study measures the product
path; it resumes where it stopped (a finished step's output is kept). Arms:

- ``recipe``: ``predict --sun none`` — the maps of today's recipe, to the bit;
- ``shadows``: ``predict`` with the default ``--sun auto`` (the training fit: the same flight) and
  ``--shadow-fusion``: each object's height chosen by rendering its cast shadow (:mod:`aerialmtl.sun.render`).

Usage::

    python -m experiments.heights_from_the_sun.run --out /work/study45 [--seeds 0 1 2] [--threads 2]
    python -m experiments.heights_from_the_sun.run --out /work/study45 --table   # the tables only
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import yaml

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "samples" / "autzen_west"
BINS = (0.0, 1.0, 2.0, 5.0, 10.0, 20.0, math.inf)
ARMS = {"recipe": ["--sun", "none"], "shadows": ["--shadow-fusion"]}
MC = 16


def _run(args: list[str], threads: int) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    print("+", " ".join(args), flush=True)
    subprocess.run(args, check=True, env=env)


def _val_block(out: Path) -> Path:
    """The validation polygon of the fixed split as its own GeoJSON (predict's --aoi)."""
    path = out / "val_block.geojson"
    if not path.is_file():
        split = json.loads((DATA / "split.geojson").read_text())
        split["features"] = [f for f in split["features"] if f["properties"].get("split") == "val"]
        path.write_text(json.dumps(split))
    return path


def _current_sun(run: Path, tiles: Path, out: Path, seed: int, threads: int) -> None:
    """Fit the sun of ``run``'s checkpoints again when the package's shadow classifier changed since they were
    trained (the weights stay; only ``meta.sun``), and drop that seed's shadow predictions made with the old one."""
    from aerialmtl.sun.colour import ShadowModel

    version = ShadowModel().features
    marker = run / "sun.version"
    if marker.is_file() and marker.read_text() == version:
        return
    for name in ("best.pt", "last.pt"):
        _run([sys.executable, "-c", "import sys; from aerialmtl.training.sun import sun_checkpoint; "
              "print(sun_checkpoint(sys.argv[1], sys.argv[2]).reason)", str(run / name), str(tiles)], threads)
    import shutil

    for stale in (out / "pred").glob(f"shadows_*_s{seed}*"):
        shutil.rmtree(stale) if stale.is_dir() else stale.unlink()
    marker.write_text(version)


def prepare(out: Path, seeds: list[int], threads: int) -> None:
    """Tile, train each seed, predict both blocks with both arms (each skipped when its output exists)."""
    exe = [sys.executable, "-m", "aerialmtl"]
    tiles = out / "tiles"
    if not (tiles / "dataset.yaml").is_file():
        _run([*exe, "tile", "--ortho", str(DATA / "ortho_1ft.tif"), "--dsm", str(DATA / "dsm_1m_utm.tif"), "--dtm",
              str(DATA / "dtm_1m_utm.tif"), "--gsd", "1", "--size", "128", "--stride", "32", "--split-aoi",
              str(DATA / "split.geojson"), "--out", str(tiles)], threads)
    blocks = {"val": _val_block(out), "test": DATA / "test_block.geojson"}
    for seed in seeds:
        run = out / "runs" / f"s{seed}"
        if not (run / "best.pt").is_file():
            cfg = yaml.safe_load((ROOT / "configs" / "small_area.yaml").read_text())
            cfg["seed"] = seed
            config = out / f"small_area_s{seed}.yaml"
            config.write_text(yaml.safe_dump(cfg))
            _run([*exe, "train", "--config", str(config), "--data", str(tiles), "--out", str(run), "--quiet",
                  *(["--resume"] if (run / "last.pt").is_file() else [])], threads)
        _current_sun(run, tiles, out, seed, threads)
        for block, aoi in blocks.items():
            for arm, flags in ARMS.items():
                pred = out / "pred" / f"{arm}_{block}_s{seed}"
                if not (pred / "prediction.json").is_file():
                    _run([*exe, "predict", str(DATA / "ortho_1ft.tif"), "--model", str(run / "best.pt"), "--aoi",
                          str(aoi), "--mc", str(MC), "--out", str(pred), "--overwrite", "--quiet", *flags], threads)


def _report(pred: Path) -> dict[str, Any]:
    cache = pred.parent / f"{pred.name}.report.json"
    if cache.is_file():
        return dict(json.loads(cache.read_text()))
    from aerialmtl.evaluation.evaluate import EvaluateOptions, evaluate_prediction

    rep = evaluate_prediction(pred, dsm_ref=DATA / "dsm_1m_utm.tif", dtm_ref=DATA / "dtm_1m_utm.tif", out=None,
                              options=EvaluateOptions(height_bins=BINS, plots=False))
    cache.write_text(json.dumps(rep, default=float))
    return dict(rep)


def _numbers(rep: dict[str, Any]) -> dict[str, Any]:
    h = rep["height"]
    tall = [b for b in h["per_bin"] if b["range_m"][0] >= 2.0]
    n = sum(b["n_pixels"] for b in tall)
    strata = rep["uncertainty"]["height_std"]["strata"]
    return {"mae": h["mae"], "mae_tall": sum(b["mae"] * b["n_pixels"] for b in tall) / max(n, 1),
            "bias_tall": sum(b["bias"] * b["n_pixels"] for b in tall) / max(n, 1),
            "crps": strata.get("crps_gaussian_m"),
            "bias_bin": [b["bias"] for b in h["per_bin"]],
            "cov_bin": [b.get("coverage_1sigma") for b in strata["bins"]],
            "rho_bin": [b.get("spearman_std_vs_abs_error") for b in strata["bins"]],
            "rho_h_bin": [b.get("spearman_std_vs_predicted_height") for b in strata["bins"]]}


def _reference_on(grid_file: Path) -> np.ndarray:
    """DSM − DTM of the sample area, bilinear on the grid of ``grid_file`` (NaN where either has no value)."""
    from experiments.heights_from_the_sun.shadow_head import reference

    return reference(grid_file, margin=0)[0]


def shadow_objects(pred: Path) -> dict[str, Any]:
    """Per object of the reference nDSM (≥ 2 m, ≥ 20 m²) on the prediction grid: its median shadow height
    against its median reference height, per height bin, and the share of objects measured; ``open_ground``: the
    share of open ground (reference < 1 m and ≥ 2 m from any pixel ≥ 2 m) where ``shadow_height.tif`` has a value.
    """
    from scipy import ndimage

    with rasterio.open(pred / "shadow_height.tif") as src:
        sh = src.read(1)
        sh = np.where(sh == src.nodata, np.nan, sh)
    ref = _reference_on(pred / "height.tif")
    with rasterio.open(pred / "height.tif") as src:
        ref = np.where(src.read(1) == src.nodata, np.nan, ref)  # the block's pixels only (--aoi: nodata elsewhere)
    labels, n = ndimage.label(np.nan_to_num(ref) >= 2.0)
    gsd = abs(rasterio.open(pred / "height.tif").res[0])
    far = ndimage.distance_transform_edt(labels == 0) * gsd >= 2.0
    open_ground = np.isfinite(ref) & (ref < 1.0) & far
    rows = []
    for k in range(1, n + 1):
        m = labels == k
        if m.sum() < 20:
            continue
        r = float(np.nanmedian(ref[m]))
        s = sh[m]
        s = s[np.isfinite(s)]
        rows.append((r, float(np.median(s)) if s.size >= 0.5 * m.sum() else math.nan))
    out: dict[str, Any] = {"open_ground": float(np.isfinite(sh[open_ground]).mean()) if open_ground.any() else None}
    tall = [(r, s) for r, s in rows if r >= 10.0 and math.isfinite(s)]
    out["median_rel_error_10m"] = float(np.median([s / r - 1.0 for r, s in tall])) if tall else None
    for lo, hi in zip(BINS[2:-1], BINS[3:]):
        sel = [(r, s) for r, s in rows if lo <= r < hi]
        got = [(r, s) for r, s in sel if math.isfinite(s)]
        err = [s - r for r, s in got]
        out[f"{lo:g}-{hi:g}"] = {"objects": len(sel), "measured": len(got),
                                 "median_error_m": float(np.median(err)) if err else None,
                                 "mae_m": float(np.mean(np.abs(err))) if err else None,
                                 "median_rel_error": float(np.median([abs(e) / r for e, (r, _) in zip(err, got)]))
                                 if err else None}
    return out


def _fmt(values: list[float], sign: bool = False) -> str:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    if not vals:
        return "n/a"
    f = "{:+.2f}" if sign else "{:.2f}"
    return f"{f.format(np.mean(vals))} ({f.format(min(vals))}–{f.format(max(vals))})" if len(vals) > 1 \
        else f.format(vals[0])


def _per_bin(rows: list[dict[str, Any]], key: str, sign: bool = True) -> str:
    f = "{:+.2f}" if sign else "{:.2f}"
    cols = []
    for k in range(len(BINS) - 1):
        vals = [r[key][k] for r in rows if r[key][k] is not None and math.isfinite(r[key][k])]
        cols.append(f.format(np.mean(vals)) if vals else "n/a")
    return " / ".join(cols)


def table(out: Path, seeds: list[int], arms: Sequence[str] = tuple(ARMS), shadow_arms: Sequence[str] = ("shadows",)
          ) -> str:
    """The study's Markdown tables: per block and arm (``arms``: their predictions' folder prefixes), mean (range)
    over the seeds; the shadow heights per object of each of ``shadow_arms``."""
    lines = []
    for block, title in (("val", "validation block (chooses)"), ("test", "held-out test block (reports)")):
        lines += [f"**{title}** — per bin: 0–1 / 1–2 / 2–5 / 5–10 / 10–20 / ≥ 20 m", "",
                  "| arm | seeds | MAE | MAE ≥ 2 m | bias ≥ 2 m | CRPS | bias per bin | ±1σ per bin | "
                  "Spearman(std, \\|err\\|) per bin | Spearman(std, predicted h) per bin |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for arm in arms:
            rows = [_numbers(_report(p)) for s in seeds
                    if (p := out / "pred" / f"{arm}_{block}_s{s}").joinpath("prediction.json").is_file()]
            if rows:
                lines.append(f"| {arm} | {len(rows)} | {_fmt([r['mae'] for r in rows])} | "
                             f"{_fmt([r['mae_tall'] for r in rows])} | {_fmt([r['bias_tall'] for r in rows], True)} | "
                             f"{_fmt([r['crps'] for r in rows])} | {_per_bin(rows, 'bias_bin')} | "
                             f"{_per_bin(rows, 'cov_bin', False)} | {_per_bin(rows, 'rho_bin')} | "
                             f"{_per_bin(rows, 'rho_h_bin')} |")
        lines.append("")
        for sarm in shadow_arms:
            lines += _objects_table(out, seeds, block, title, sarm)
    return "\n".join(lines)


def _objects_table(out: Path, seeds: list[int], block: str, title: str, arm: str) -> list[str]:
    """The shadow heights per reference object of ``arm``'s predictions of ``block`` (no lines where none)."""
    lines: list[str] = []
    objs = [shadow_objects(p) for s in seeds
            if (p := out / "pred" / f"{arm}_{block}_s{s}").joinpath("shadow_height.tif").is_file()]
    if objs:
        lines += [f"shadow heights per reference object ({title.split(' (')[0]}, `{arm}`, {len(objs)} seeds):", "",
                  "| bin | objects | measured | median error | MAE | median relative error |",
                  "|---|---|---|---|---|---|"]
        for key in objs[0]:
            if not isinstance(objs[0][key], dict):
                continue
            o = [x[key] for x in objs]
            lines.append(f"| {key} m | {o[0]['objects']} | {_fmt([x['measured'] for x in o])} | "
                         f"{_fmt([x['median_error_m'] for x in o], True)} | {_fmt([x['mae_m'] for x in o])} | "
                         f"{_fmt([x['median_rel_error'] for x in o])} |")
        lines += ["", f"objects ≥ 10 m, median relative error of the shadow height: "
                  f"{_fmt([x['median_rel_error_10m'] for x in objs], True)}; open ground with a shadow height: "
                  f"{_fmt([x['open_ground'] for x in objs])}", ""]
    return lines


def main() -> None:
    """Run what is missing, then print the tables."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--table", action="store_true", help="print the tables of what is there, run nothing")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    if not a.table:
        prepare(a.out, a.seeds, a.threads)
    print(table(a.out, a.seeds))


if __name__ == "__main__":
    main()
