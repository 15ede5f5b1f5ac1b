"""Benchmark `aerialmtl buildings`: memory and time on large prediction folders, quality on synthetic towns.

Usage::

    python bench/buildings.py --memory [--sizes 2048,4096,8192] [--block-size 1024]
    python bench/buildings.py --quality --model RUN/best.pt [--seeds 101,102,103] [--size 1024] [--mc 8] [--reuse]

``--memory``: for each size N it writes an N×N prediction folder block by block (never a whole layer in
memory): ``classes.tif`` (synthetic scheme), ``height.tif``, ``height_std.tif``, ``class_entropy.tif``, tiled
512² GeoTIFFs at 0.25 m, with one rotated rectangular building of 7–20 m (4–30 m high) in most 24 m cells
and some 60 m long ones, so that many buildings cross block edges. It then runs ``aerialmtl buildings``
(GeoPackage + CityJSON) in a fresh subprocess and reports its wall time, CPU time (user + system, the
better measure on a shared machine; it includes the imports) and peak RSS
(``resource.getrusage(RUSAGE_SELF).ru_maxrss``). Prints a Markdown table.

``--quality``: for each held-out seed it runs, through the command line as a user would,
``aerialmtl synth`` (town of ``--size`` px), ``aerialmtl predict`` (``--model``, T = ``--mc``),
``aerialmtl buildings`` and ``aerialmtl evaluate --height --labels --buildings``; the same extraction on a
*perfect* prediction (the town's own labels and nDSM) gives the ceiling of the extraction step alone.
Prints the commands, a Markdown table of building F1 / height MAE next to the pixel metrics and the
height error when ``height_m`` is another percentile of the predicted heights.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

BLOCK = 512
CELL = 96  # pixels (24 m at 0.25 m)
ROOT = Path(__file__).resolve().parents[1]


def load_avg() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


# ---- (a) memory and time -------------------------------------------------------------------------
def _cell_buildings(i: int, j: int, seed: int) -> list[tuple[object, float]]:
    """The buildings (shapely polygon in pixel coordinates, height m) anchored in cell (i, j)."""
    from shapely import affinity
    from shapely.geometry import box

    rng = np.random.default_rng((seed, i, j))
    out = []
    if rng.random() < 0.8:
        w, h = rng.uniform(28, 80, 2)
        cx, cy = (j + 0.5) * CELL + rng.uniform(-8, 8), (i + 0.5) * CELL + rng.uniform(-8, 8)
        poly = affinity.rotate(box(cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2), rng.uniform(-30, 30))
        out.append((poly, float(rng.uniform(4, 30))))
    if rng.random() < 0.04:  # a long block across cells (and often block edges)
        x0, y0 = j * CELL + 10, i * CELL + 10
        out.append((box(x0, y0, x0 + 240, y0 + 40), float(rng.uniform(6, 20))))
    return out


def make_prediction(folder: Path, n: int, seed: int = 0) -> int:
    """Write an n×n prediction folder block by block; returns the number of buildings placed."""
    import rasterio
    from affine import Affine
    from rasterio.features import rasterize
    from rasterio.windows import Window

    from aerialmtl.classes import ClassScheme
    from aerialmtl.formats.prediction import (
        CLASS_ENTROPY,
        CLASS_NODATA,
        CLASS_SCHEME_TAG,
        CLASSES,
        FLOAT_NODATA,
        HEIGHT,
        HEIGHT_STD,
        layer_filename,
    )

    folder.mkdir(parents=True, exist_ok=True)
    t = Affine(0.25, 0, 500000.0, 0, -0.25, 5000000.0)
    common = dict(driver="GTiff", crs="EPSG:32631", transform=t, width=n, height=n, count=1, tiled=True,
                  blockxsize=BLOCK, blockysize=BLOCK, compress="deflate")
    scheme = ClassScheme.load("synthetic")
    names = {CLASSES: ("uint8", CLASS_NODATA), HEIGHT: ("float32", FLOAT_NODATA),
             HEIGHT_STD: ("float32", FLOAT_NODATA), CLASS_ENTROPY: ("float32", FLOAT_NODATA)}
    dsts = {k: rasterio.open(folder / layer_filename(k), "w", dtype=d, nodata=nd, **common) for k, (d, nd) in
            names.items()}
    dsts[CLASSES].update_tags(**{CLASS_SCHEME_TAG: json.dumps(scheme.to_dict())})
    rng = np.random.default_rng(seed)
    cells = -(-n // CELL)
    placed = sum(len(_cell_buildings(i, j, seed)) for i in range(cells) for j in range(cells))
    try:
        for r in range(0, n, BLOCK):
            for c in range(0, n, BLOCK):
                win = Window(c, r, min(BLOCK, n - c), min(BLOCK, n - r))
                h, w = int(win.height), int(win.width)
                shapes = []
                for i in range(max(0, r // CELL - 3), min(cells, (r + h) // CELL + 2)):
                    for j in range(max(0, c // CELL - 3), min(cells, (c + w) // CELL + 2)):
                        shapes += _cell_buildings(i, j, seed)
                ids = np.zeros((h, w), np.int32)
                heights = np.zeros(len(shapes) + 1, np.float32)
                if shapes:
                    burn = [(poly, k + 1) for k, (poly, _) in enumerate(shapes)]
                    ids = rasterize(burn, out_shape=(h, w), transform=Affine.translation(c, r), dtype="int32")
                    heights[1:] = [hh for _, hh in shapes]
                bld = ids > 0
                cls = np.where(bld, 2, 4).astype(np.uint8)  # building / low vegetation
                hgt = np.where(bld, heights[ids] + rng.normal(0, 0.3, (h, w)), rng.uniform(0, 0.5, (h, w)))
                std = np.where(bld, 0.3 + 0.02 * heights[ids], 0.1) * rng.uniform(0.8, 1.2, (h, w))
                ent = rng.uniform(0.0, 0.8, (h, w))
                dsts[CLASSES].write(cls[None], window=win)
                dsts[HEIGHT].write(hgt.astype(np.float32)[None], window=win)
                dsts[HEIGHT_STD].write(std.astype(np.float32)[None], window=win)
                dsts[CLASS_ENTROPY].write(ent.astype(np.float32)[None], window=win)
    finally:
        for d in dsts.values():
            d.close()
    return placed


CHILD = r"""
import json, resource, sys, time
from aerialmtl.buildings import BuildingOptions, write_buildings
p = json.loads(sys.argv[1])
t0 = time.perf_counter()
res = write_buildings(p["pred"], [p["out"] + ".gpkg", p["out"] + ".city.json"],
                      BuildingOptions(block_size=p["block"]), overwrite=True)
wall = time.perf_counter() - t0
use = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"wall_s": wall, "maxrss_mib": use.ru_maxrss / 1024, "cpu_s": use.ru_utime + use.ru_stime,
                  "buildings": res.count, "components": res.stats.components, "blocks": res.stats.blocks}))
"""


def bench_memory(sizes: list[int], block: int, work: Path, keep: bool) -> None:
    rows = []
    for n in sizes:
        t0 = time.perf_counter()
        placed = make_prediction(work / f"pred_{n}", n)
        gen = time.perf_counter() - t0
        args = {"pred": str(work / f"pred_{n}"), "out": str(work / f"buildings_{n}"), "block": block}
        before = load_avg()
        out = subprocess.run([sys.executable, "-c", CHILD, json.dumps(args)], capture_output=True, text=True,
                             check=True, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)))
        r = json.loads(out.stdout.strip().splitlines()[-1])
        r.update(n=n, gen_s=gen, placed=placed, load_before=before, load_after=load_avg(),
                 gpkg_mib=os.path.getsize(args["out"] + ".gpkg") / 2**20,
                 cityjson_mib=os.path.getsize(args["out"] + ".city.json") / 2**20)
        rows.append(r)
        print(f"# {n}: {r}", file=sys.stderr)
        if not keep:
            shutil.rmtree(work / f"pred_{n}", ignore_errors=True)
    print(f"block size {block} px; outputs: GeoPackage + CityJSON\n")
    print("| prediction (px) | Mpx | buildings placed | buildings written | pieces (block cuts) | wall (s) | CPU (s) "
          "| Mpx/s | peak RSS (MiB) | GPKG / CityJSON (MiB) | load avg before → after |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        mpx = r["n"] ** 2 / 1e6
        print(f"| {r['n']}×{r['n']} | {mpx:.1f} | {r['placed']} | {r['buildings']} | {r['components']} | "
              f"{r['wall_s']:.1f} | {r['cpu_s']:.1f} | {mpx / r['wall_s']:.1f} | {r['maxrss_mib']:.0f} | "
              f"{r['gpkg_mib']:.1f} / {r['cityjson_mib']:.1f} | {r['load_before']} → {r['load_after']} |")


# ---- (b) quality on held-out synthetic towns -------------------------------------------------------
def _cli(*args: object) -> str:
    cmd = [sys.executable, "-m", "aerialmtl", *(str(a) for a in args)]
    print("$ " + " ".join(["aerialmtl", *(str(a) for a in args)]), file=sys.stderr)
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    if out.returncode:
        raise SystemExit(f"command failed ({out.returncode}): {' '.join(cmd)}\n{out.stderr}")
    return out.stdout


def _perfect_prediction(town: Path, out: Path) -> None:
    """The town's own labels and nDSM as a prediction folder (what a perfect model would predict)."""
    import rasterio

    from aerialmtl.classes import ClassScheme
    from aerialmtl.formats.prediction import CLASS_NODATA, CLASS_SCHEME_TAG, CLASSES, HEIGHT, layer_filename

    out.mkdir(parents=True, exist_ok=True)
    scheme = ClassScheme.load("synthetic")
    with rasterio.open(town / "labels.tif") as src:
        profile = src.profile
        cls = scheme.remap(src.read(1), on_unknown="ignore")
    profile.update(nodata=CLASS_NODATA)
    with rasterio.open(out / layer_filename(CLASSES), "w", **profile) as dst:
        dst.write(cls, 1)
        dst.update_tags(**{CLASS_SCHEME_TAG: json.dumps(scheme.to_dict())})
    shutil.copyfile(town / "ndsm.tif", out / layer_filename(HEIGHT))


def percentile_sweep(seeds: list[int], work: Path, percentiles: tuple[float, ...] = (50, 60, 70, 75, 80, 90)) -> None:
    """Height MAE / bias of the matched buildings when ``height_m`` is another percentile (pooled over seeds)."""
    from aerialmtl.buildings import BuildingLayers, BuildingOptions
    from aerialmtl.evaluation.buildings import evaluate_buildings

    print("\n| height_m = percentile | matched | height MAE (m) | bias (m) | F1 |\n|---|---|---|---|---|")
    for q in percentiles:
        n = tp = npred = nref = 0
        abs_sum = bias_sum = 0.0
        for seed in seeds:
            with BuildingLayers(work / f"pred_{seed}") as layers:
                grid = layers.grid
            r = evaluate_buildings(work / f"pred_{seed}", work / f"town_{seed}" / "buildings.geojson", grid,
                                   options=BuildingOptions(height_percentile=q))
            k = r["height"]["n"]
            n, abs_sum, bias_sum = n + k, abs_sum + r["height"]["mae"] * k, bias_sum + r["height"]["bias"] * k
            tp, npred, nref = tp + r["n_matched"], npred + r["n_predicted"], nref + r["n_reference"]
        f1 = 2 * tp / max(npred + nref, 1)
        print(f"| {q:g}{' (default)' if q == 50 else ''} | {n} | {abs_sum / n:.2f} | {bias_sum / n:+.2f} | {f1:.3f} |")


def bench_quality(model: Path, seeds: list[int], size: int, mc: int, work: Path, reuse: bool = False) -> None:
    variants = {"default": [], "--height-step 2.5": ["--height-step", "2.5"], "--no-orthogonal": ["--no-orthogonal"]}
    rows = []
    for seed in seeds:
        town, pred = work / f"town_{seed}", work / f"pred_{seed}"
        t0 = time.perf_counter()
        if not (reuse and (pred / "prediction.json").is_file()):
            _cli("synth", town, "--size", size, "--seed", seed, "--overwrite")
            t0 = time.perf_counter()
            _cli("predict", town / "ortho.tif", "--model", model, "--out", pred, "--mc", mc, "--window", 512,
                 "--precision", "fp32", "--overwrite", "--quiet")
        predict_s = time.perf_counter() - t0
        for name, extra in variants.items():
            tag = name.replace("-", "").replace(" ", "_")
            t0 = time.perf_counter()
            _cli("buildings", pred, "--out", work / f"b_{seed}_{tag}.gpkg", "--out", work / f"b_{seed}_{tag}.city.json",
                 *extra, "--overwrite", "--quiet")
            buildings_s = time.perf_counter() - t0
            report = work / f"eval_{seed}_{tag}.json"
            _cli("evaluate", "--pred", pred, "--height", town / "ndsm.tif", "--labels", town / "labels.tif",
                 "--buildings", town / "buildings.geojson", "--pred-buildings", work / f"b_{seed}_{tag}.gpkg",
                 "--out", report, "--overwrite", "--no-plots", "--quiet")
            r = json.loads(report.read_text())
            rows.append({"seed": seed, "variant": name, "predict_s": predict_s, "buildings_s": buildings_s,
                         "height_mae": r["height"]["mae"], "miou": r["classes"]["miou"],
                         "building_iou": r["classes"]["per_class"]["building"]["iou"], **r["buildings"],
                         "pixel_spearman": r["uncertainty"]["height_std"]["spearman_std_vs_abs_error"]})
        perfect = work / f"perfect_{seed}"
        _perfect_prediction(town, perfect)
        _cli("buildings", perfect, "--out", work / f"p_{seed}.gpkg", "--overwrite", "--quiet")
        _cli("evaluate", "--pred", perfect, "--buildings", town / "buildings.geojson", "--pred-buildings",
             work / f"p_{seed}.gpkg", "--out", work / f"perfect_{seed}.json", "--overwrite", "--no-plots", "--quiet")
        r = json.loads((work / f"perfect_{seed}.json").read_text())
        rows.append({"seed": seed, "variant": "perfect prediction (labels + nDSM)", **r["buildings"]})
        print(f"# seed {seed} done, load {load_avg()}", file=sys.stderr)
    (work / "quality.json").write_text(json.dumps(rows, indent=2, default=float))

    def f(v: object, d: int = 3) -> str:
        return "—" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{d}f}"

    print("| seed | extraction | pixel height MAE (m) | mIoU | building IoU (px) | buildings ref / pred / matched "
          "| precision | recall | **building F1** | mean IoU | **height MAE (m)** | height RMSE (m) | bias (m) "
          "| Spearman(std, \\|err\\|) buildings / pixels |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        h = r.get("height") or {}
        print(f"| {r['seed']} | {r['variant']} | {f(r.get('height_mae'), 2)} | {f(r.get('miou'))} | "
              f"{f(r.get('building_iou'))} | {r['n_reference']} / {r['n_predicted']} / {r['n_matched']} | "
              f"{f(r['precision'])} | {f(r['recall'])} | {f(r['f1'])} | {f(r['mean_iou_matched'])} | "
              f"{f(h.get('mae'), 2)} | {f(h.get('rmse'), 2)} | {f(h.get('bias'), 2)} | "
              f"{f(r['spearman_std_vs_abs_error'], 2)} / {f(r.get('pixel_spearman'), 2)} |")
    for name in [*variants, "perfect prediction (labels + nDSM)"]:
        sel = [r for r in rows if r["variant"] == name]
        tp = sum(r["n_matched"] for r in sel)
        npred, nref = sum(r["n_predicted"] for r in sel), sum(r["n_reference"] for r in sel)
        p, rec = tp / max(npred, 1), tp / max(nref, 1)
        mae = sum((r["height"] or {}).get("mae", 0) * r["n_matched"] for r in sel) / max(tp, 1)
        f1 = 2 * p * rec / max(p + rec, 1e-9)
        print(f"\npooled over seeds, {name}: precision {p:.3f}, recall {rec:.3f}, F1 {f1:.3f}, "
              f"height MAE {mae:.2f} m over {tp} matched buildings")
    percentile_sweep(seeds, work)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--memory", action="store_true")
    ap.add_argument("--sizes", default="2048,4096,8192")
    ap.add_argument("--block-size", type=int, default=1024)
    ap.add_argument("--quality", action="store_true")
    ap.add_argument("--model", type=Path)
    ap.add_argument("--seeds", default="101,102,103")
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--mc", type=int, default=8)
    ap.add_argument("--reuse", action="store_true", help="--quality: keep towns and predictions already in --workdir")
    ap.add_argument("--workdir", default="/tmp/aerialmtl-bench-buildings")
    ap.add_argument("--keep", action="store_true", help="keep the generated prediction folders")
    args = ap.parse_args()
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    print(f"load average at start: {load_avg()}", file=sys.stderr)
    if args.memory:
        bench_memory([int(s) for s in args.sizes.split(",")], args.block_size, work, args.keep)
    if args.quality:
        if args.model is None:
            ap.error("--quality needs --model RUN/best.pt")
        bench_quality(args.model.resolve(), [int(s) for s in args.seeds.split(",")], args.size, args.mc, work,
                      args.reuse)


if __name__ == "__main__":
    main()
