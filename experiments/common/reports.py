"""A prediction folder evaluated on the survey as ``aerialmtl evaluate`` does, in the studies' height bins
(:data:`experiments.common.study.HEIGHT_EDGES`), and the numbers the studies report from it.

:func:`evaluate_dir` gives the real-data benchmark's numbers (errors, the tall pixels' share, one rank
correlation), :func:`evaluate_spread` the spread studies' (coverage, CRPS, NLL, per bin).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import rasterio

from aerialmtl.evaluation.evaluate import EvaluateOptions, evaluate_prediction
from aerialmtl.formats.prediction import FLOAT_NODATA, HEIGHT, HEIGHT_STD, layer_filename
from experiments.common.autzen import DSM, DTM, TALL_M
from experiments.common.study import HEIGHT_EDGES


def summarise(report: dict[str, Any]) -> dict[str, float]:
    """MAE, RMSE, bias, MAE on pixels ≥ :data:`TALL_M`, their share, and Spearman(std, |err|)."""
    h = report["height"]
    tall = [b for b in h["per_bin"] if b["range_m"][0] >= TALL_M and b["n_pixels"]]
    n_tall = sum(b["n_pixels"] for b in tall)
    out = {
        "mae": h["mae"], "rmse": h["rmse"], "bias": h["bias"], "n_pixels": h["n_pixels"],
        "mae_tall": sum(b["mae"] * b["n_pixels"] for b in tall) / n_tall if n_tall else math.nan,
        "bias_tall": sum(b["bias"] * b["n_pixels"] for b in tall) / n_tall if n_tall else math.nan,
        "tall_share": n_tall / h["n_pixels"] if h["n_pixels"] else math.nan,
        "gsd_m": report["grid"]["gsd_m"],
    }
    unc = report.get("uncertainty", {}).get("height_std")
    out["spearman_std_abs_err"] = unc["spearman_std_vs_abs_error"] if unc else math.nan
    return out


def evaluate_dir(pred_dir: Path, data: Path, out_json: Path) -> dict[str, float]:
    """``aerialmtl evaluate`` of ``pred_dir`` against ``data``'s DSM − DTM (report at ``out_json``), summarised
    (:func:`summarise`)."""
    report = evaluate_prediction(
        pred_dir, dsm_ref=data / DSM, dtm_ref=data / DTM, out=out_json, overwrite=True,
        options=EvaluateOptions(height_bins=HEIGHT_EDGES, plots=False),
    )
    return summarise(report)


def spread_summary(report: dict[str, Any]) -> dict[str, Any]:
    """The spread studies' numbers from an evaluation report: errors overall and ≥ :data:`TALL_M`, the spread's
    coverage, CRPS, NLL and rank correlation, and the same per reference-height bin."""
    h = report["height"]
    per_bin = h["per_bin"]
    tall = [b for b in per_bin if b["range_m"][0] >= TALL_M]
    n_tall = sum(b["n_pixels"] for b in tall)
    hs = report["uncertainty"]["height_std"]
    strata = hs["strata"]
    bins = []
    for b, st in zip(per_bin, strata["bins"], strict=True):
        bins.append({"range_m": b["range_m"], "share": st.get("share"), "bias": b["bias"], "mae": b["mae"],
                     **{k: st.get(k) for k in ("coverage_1sigma", "coverage_2sigma", "median_std_m",
                                                "median_abs_error_m", "spearman_std_vs_abs_error",
                                                "nll_gaussian", "crps_gaussian_m", "max_std_m")}})
    return {"mae": h["mae"], "rmse": h["rmse"],
            "mae_tall": sum(b["mae"] * b["n_pixels"] for b in tall) / max(1, n_tall),
            "bias_tall": sum(b["bias"] * b["n_pixels"] for b in tall) / max(1, n_tall),
            "coverage_1sigma": hs["coverage_1sigma"], "coverage_2sigma": hs["coverage_2sigma"],
            "nll_gaussian": strata.get("nll_gaussian"), "crps_gaussian_m": strata.get("crps_gaussian_m"),
            "spearman": hs["spearman_std_vs_abs_error"], "max_height_m": None, "bins": bins}


def evaluate_spread(pred_dir: Path, data: Path, out_json: Path) -> dict[str, Any]:
    """``aerialmtl evaluate`` of ``pred_dir`` (height and height_std) against ``data``'s DSM − DTM (report at
    ``out_json``): :func:`spread_summary` with the highest height and spread."""
    report = evaluate_prediction(pred_dir, dsm_ref=data / DSM, dtm_ref=data / DTM, out=out_json, overwrite=True,
                                 options=EvaluateOptions(height_bins=HEIGHT_EDGES, plots=False))
    res = spread_summary(report)
    with rasterio.open(pred_dir / layer_filename(HEIGHT)) as src:
        h = src.read(1)
    with rasterio.open(pred_dir / layer_filename(HEIGHT_STD)) as src:
        s = src.read(1)
    ok = h != FLOAT_NODATA
    res["max_height_m"], res["max_std_m"] = float(h[ok].max()), float(s[ok].max())
    return res
