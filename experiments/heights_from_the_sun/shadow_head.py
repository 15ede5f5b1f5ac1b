"""The shadow head against the colour classifier on the validation block of ``autzen_west`` (issue 58, item 1).

For each run trained with ``model.shadow_head: true`` (``configs/small_area.yaml`` plus the head), the validation
block is predicted twice with the user's command, ``aerialmtl predict --mc 16 --aoi <val block>`` (``--sun auto``,
the default: the training fit, the same flight):

- ``head``: the checkpoint as trained: ``shadow.tif`` is the head's P(cast shadow) (mean over the MC samples);
- ``classifier`` (once, from the first run: the colour classifier is fitted on the training area at its sun, the same
  for every run): the same checkpoint with the head taken out (``meta.model.shadow_head: false``, the
  ``heads.shadow`` weights dropped; everything else, the sun and its colour classifier included, kept):
  ``shadow.tif`` is the colour classifier's, as for every checkpoint without a head.

Scored against the reference (DSM − DTM of the sample area on the prediction grid, with a margin of context so that
occluders outside the block still cast): ``cast`` = :func:`aerialmtl.sun.cast.cast_shadow_mask` of it at the fitted
sun. Per arm: IoU of the shadow mask with ``cast`` at 0.5 and at the arm's own threshold, chosen on the training block
(classifier: the one stored with it, chosen there when it was fitted; head: the threshold of best IoU there, the
training block predicted the same way), and the share of *self-shaded roof* pixels called shadow: reference
≥ 2 m, a slope ≥ 15° whose surface normal (from the reference's gradient) faces away from the sun, not in ``cast``.
The sample area has no land-cover labels, so water is not scored (the validation block's only water, a narrow
creek, lies under the canopy: see the README).

Usage::

    python -m experiments.heights_from_the_sun.shadow_head --tiles T --runs RUN... --out OUT [--threads 1]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from rasterio.enums import Resampling
from rasterio.transform import Affine
from rasterio.vrt import WarpedVRT

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "samples" / "autzen_west"
MC = 16
#: Pixels of reference context around the block (occluders outside it cast into it): 60 m at 1 m.
MARGIN_PX = 60
ROOF_MIN_M = 2.0
SLOPE_MIN_DEG = 15.0


def _run(args: list[str], threads: int) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    print("+", " ".join(args), flush=True)
    subprocess.run(args, check=True, env=env)


def _block(out: Path, split_name: str = "val") -> Path:
    """The ``split_name`` polygons of the fixed split as their own GeoJSON (predict's --aoi)."""
    path = out / f"{split_name}_block.geojson"
    if not path.is_file():
        split = json.loads((DATA / "split.geojson").read_text())
        split["features"] = [f for f in split["features"] if f["properties"].get("split") == split_name]
        path.write_text(json.dumps(split))
    return path


def train_threshold(pred: Path, gsd: float, grid_azimuth: float, elevation: float) -> tuple[float, float]:
    """The head's threshold of best IoU with the reference's cast shadows on the training block (0.05 steps), as the
    colour classifier's is chosen there, and that IoU."""
    from aerialmtl.sun import Sun, cast_shadow_mask

    ref_big, inner = reference(pred / "shadow.tif")
    cast = cast_shadow_mask(ref_big, gsd, Sun(grid_azimuth, elevation))[inner]
    prob = _read(pred / "shadow.tif")
    ok = np.isfinite(prob) & np.isfinite(ref_big[inner])
    best = (0.5, -1.0)
    for t in np.round(np.arange(0.05, 0.96, 0.05), 2):
        called = (prob > t) & ok
        iou = float((called & cast).sum() / max(((called | cast) & ok).sum(), 1))
        if iou > best[1]:
            best = (float(t), iou)
    return best


def without_head(src: Path, dst: Path) -> None:
    """Write ``src``'s checkpoint without its shadow head (the colour classifier's checkpoint); weights and meta
    otherwise unchanged."""
    import dataclasses

    from aerialmtl.formats.checkpoint import load_checkpoint, save_checkpoint
    from aerialmtl.models.d3net import D3Net

    payload, meta = load_checkpoint(src)
    cfg = dataclasses.replace(meta.model, shadow_head=False)
    model = D3Net(dataclasses.replace(cfg, encoder_weights=None))
    state = {k: v for k, v in payload["state_dict"].items() if not k.startswith("heads.shadow.")}
    model.load_state_dict(state)
    save_checkpoint(dst, model, dataclasses.replace(meta, model=cfg))


def reference(grid_file: Path, margin: int = MARGIN_PX) -> tuple[np.ndarray, tuple[slice, slice]]:
    """DSM − DTM (metres, NaN unknown) bilinear on ``grid_file``'s grid grown by ``margin`` pixels each side, and the
    slices that cut it back to the grid."""
    with rasterio.open(grid_file) as g:
        t = g.transform
        grown = Affine(t.a, t.b, t.c - margin * t.a, t.d, t.e, t.f - margin * t.e)
        opts = {"crs": g.crs, "transform": grown, "width": g.width + 2 * margin, "height": g.height + 2 * margin,
                "resampling": Resampling.bilinear}
        arrays = []
        for name in ("dsm_1m_utm.tif", "dtm_1m_utm.tif"):
            with rasterio.open(DATA / name) as src, WarpedVRT(src, src_nodata=src.nodata, nodata=np.nan,
                                                                dtype="float32", **opts) as vrt:
                arrays.append(vrt.read(1))
    inner = (slice(margin, margin + opts["height"] - 2 * margin), slice(margin, margin + opts["width"] - 2 * margin))
    return arrays[0] - arrays[1], inner


def self_shaded(ndsm: np.ndarray, gsd: float, azimuth_deg: float) -> np.ndarray:
    """Pixels ≥ :data:`ROOF_MIN_M` whose surface (slope ≥ :data:`SLOPE_MIN_DEG`) faces away from the sun (the
    horizontal part of its normal points away from the sun's azimuth, clockwise from grid north)."""
    z = np.nan_to_num(ndsm, nan=0.0)
    d_row, d_col = np.gradient(z, gsd)  # rows grow southwards
    east, north = -d_col, d_row  # the normal's horizontal part (−∂z/∂x, −∂z/∂y with y north)
    az = math.radians(azimuth_deg)
    towards = east * math.sin(az) + north * math.cos(az)
    slope = np.degrees(np.arctan(np.hypot(d_row, d_col)))
    return (np.nan_to_num(ndsm) >= ROOF_MIN_M) & (slope >= SLOPE_MIN_DEG) & (towards < 0)


def _read(path: Path) -> np.ndarray:
    with rasterio.open(path) as src:
        return np.where(src.read_masks(1) > 0, src.read(1), np.nan).astype(np.float32)


def score(pred: Path, gsd: float, grid_azimuth: float, elevation: float, threshold: float) -> dict[str, Any]:
    """The arm's numbers on the block (see the module docstring)."""
    from aerialmtl.sun import Sun, cast_shadow_mask

    ref_big, inner = reference(pred / "shadow.tif")
    cast = cast_shadow_mask(ref_big, gsd, Sun(grid_azimuth, elevation))[inner]
    ref = ref_big[inner]
    shaded = self_shaded(ref_big, gsd, grid_azimuth)[inner] & ~cast
    prob = _read(pred / "shadow.tif")
    ok = np.isfinite(prob) & np.isfinite(ref)
    height = _read(pred / "height.tif")
    h_ok = ok & np.isfinite(height)
    out: dict[str, Any] = {"pixels": int(ok.sum()), "cast_share": float(cast[ok].mean()),
                           "self_shaded_pixels": int((shaded & ok).sum()),
                           "height_mae": float(np.abs(height - ref)[h_ok].mean())}
    for name, t in (("own", threshold), ("half", 0.5)):
        called = (prob > t) & ok
        inter = (called & cast).sum()
        union = ((called | cast) & ok).sum()
        out[name] = {"threshold": t, "iou": float(inter / max(union, 1)),
                     "precision": float(inter / max(called.sum(), 1)),
                     "recall": float(inter / max((cast & ok).sum(), 1)),
                     "self_shaded_called": float(called[shaded & ok].mean()) if (shaded & ok).any() else math.nan}
    return out


def main() -> None:
    """Predict the validation block with and without each run's head; print and save the table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=Path, nargs="+", required=True, help="run folders trained with the head")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    from aerialmtl.formats.checkpoint import load_checkpoint

    args.out.mkdir(parents=True, exist_ok=True)
    aoi, train_aoi = _block(args.out), _block(args.out, "train")
    exe = [sys.executable, "-m", "aerialmtl"]
    rows = []
    for run in args.runs:
        best = run / "best.pt"
        _, meta = load_checkpoint(best)
        sun = meta.sun
        assert sun is not None and sun.clear and sun.shadow_model is not None
        assert sun.grid_azimuth_deg is not None and sun.elevation_deg is not None
        arms = [("head", best)]
        if run == args.runs[0]:  # the classifier depends on the training area and its sun only: the same for every run
            plain = args.out / f"{run.name}_classifier.pt"
            if not plain.is_file():
                without_head(best, plain)
            arms.append(("classifier", plain))
        for arm, ckpt in arms:
            pred = args.out / f"{arm}_{run.name}"
            if not (pred / "prediction.json").is_file():
                _run([*exe, "predict", str(DATA / "ortho_1ft.tif"), "--model", str(ckpt), "--aoi", str(aoi), "--mc",
                      str(MC), "--out", str(pred), "--overwrite", "--quiet"], args.threads)
            threshold = 0.5 if arm == "head" else float(sun.shadow_model["threshold"])
            numbers = score(pred, float(meta.gsd), sun.grid_azimuth_deg, sun.elevation_deg, threshold)
            if arm == "head":  # also at the threshold of best IoU on the training block
                on_train = args.out / f"train_{arm}_{run.name}"
                if not (on_train / "prediction.json").is_file():
                    _run([*exe, "predict", str(DATA / "ortho_1ft.tif"), "--model", str(ckpt), "--aoi", str(train_aoi),
                          "--mc", str(MC), "--out", str(on_train), "--overwrite", "--quiet"], args.threads)
                t, _ = train_threshold(on_train, float(meta.gsd), sun.grid_azimuth_deg, sun.elevation_deg)
                numbers["half"] = numbers["own"]
                numbers["own"] = score(pred, float(meta.gsd), sun.grid_azimuth_deg, sun.elevation_deg, t)["own"]
            rows.append({"run": run.name, "arm": arm, **numbers})
    (args.out / "shadow_head.json").write_text(json.dumps(rows, indent=1))
    print("| run | arm | threshold | IoU with the reference's cast shadows | precision | recall | self-shaded roof "
          "called shadow | height MAE (m) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        for key in ("own", "half"):
            m = r[key]
            print(f"| {r['run']} | {r['arm']} | {m['threshold']:.2f} | {m['iou']:.3f} | {m['precision']:.3f} | "
                  f"{m['recall']:.3f} | {100 * m['self_shaded_called']:.1f} % | {r['height_mae']:.2f} |")
    print(f"(block: {rows[0]['pixels']} px, {100 * rows[0]['cast_share']:.1f} % cast shadow, "
          f"{rows[0]['self_shaded_pixels']} self-shaded roof px)")


if __name__ == "__main__":
    main()
