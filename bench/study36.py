"""Issue 36's study table: the recipe, copy-paste, and the synthetic starts of several pretraining lengths
fine-tuned with the recipe, on ``autzen_west``'s fixed split (``middle-val``); validation chooses, the held-out
test block reports.

It reads what ``bench/real_data.py`` (training) and ``bench/uncertainty_study.py --val-block`` (the raw
predictions of the test and validation blocks, T = 16) left in ``OUT/runs/<run>/``, evaluates those raw
predictions once more with today's ``evaluate`` (cached as ``study36_{test,val}.json``: it adds, per reference-height
bin, Spearman(height_std, predicted height) and the unfamiliarity layer's ranks), and prints one Markdown table per
block with the mean (range) over the seeds of each arm (the run name without ``_s<seed>``).

Usage::

    python bench/study36.py --out /work/study_h36u --runs al_b0_s0 al_b0_s1 al_b0_s2 cp_s0 cp_s1 cp_s2 \\
        ft_s0 ft_s1 ft_s2 ft5k_s0 ft5k_s1 ft5k_s2
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from aerialmtl.evaluation.evaluate import EvaluateOptions, evaluate_prediction

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_data import DATA, DSM, DTM, TALL_M  # noqa: E402
from uncertainty_study import BINS, _fmt_range  # noqa: E402

#: where a run's raw predictions are (the unfamiliarity study's folder for runs trained before the layer existed)
FOLDERS = {"test": ("study_raw_best", "unfam_pred_l2_d32_gda_auto"), "val": ("study_valblock_raw",)}


def _evaluate(folder: Path) -> dict[str, Any]:
    return evaluate_prediction(folder, dsm_ref=DATA / DSM, dtm_ref=DATA / DTM, out=None,
                               options=EvaluateOptions(height_bins=BINS, plots=False))


def _report(run: Path, block: str) -> dict[str, Any] | None:
    cache = run / f"study36_{block}.json"
    if cache.is_file():
        return dict(json.loads(cache.read_text()))
    folder = next((run / f for f in FOLDERS[block] if (run / f / "height.tif").is_file()), None)
    if folder is None:
        return None
    rep = _evaluate(folder)
    extra = run / FOLDERS["test"][1]
    if block == "test" and "unfamiliarity" not in rep["uncertainty"] and (extra / "unfamiliarity.tif").is_file():
        # trained before the layer existed: its unfamiliarity was predicted into a folder of its own
        rep["uncertainty"]["unfamiliarity"] = _evaluate(extra)["uncertainty"]["unfamiliarity"]
    cache.write_text(json.dumps(rep, default=float))
    return dict(rep)


def _numbers(rep: dict[str, Any]) -> dict[str, Any]:
    h = rep["height"]
    tall = [b for b in h["per_bin"] if b["range_m"][0] >= TALL_M]
    n = sum(b["n_pixels"] for b in tall)
    strata = rep["uncertainty"]["height_std"]["strata"]
    unfam = rep["uncertainty"].get("unfamiliarity") or {}
    return {"mae": h["mae"], "mae_tall": sum(b["mae"] * b["n_pixels"] for b in tall) / max(n, 1),
            "bias_tall": sum(b["bias"] * b["n_pixels"] for b in tall) / max(n, 1),
            "crps": strata.get("crps_gaussian_m"), "nll": strata.get("nll_gaussian"),
            "bias_bin": [b["bias"] for b in h["per_bin"]],
            "cov_bin": [b.get("coverage_1sigma") for b in strata["bins"]],
            "rho_bin": [b.get("spearman_std_vs_abs_error") for b in strata["bins"]],
            "rho_h_bin": [b.get("spearman_std_vs_predicted_height") for b in strata["bins"]],
            "share_bin": [b.get("share") for b in strata["bins"]],
            "unfam_bin": [b.get("spearman_vs_abs_error") for b in unfam.get("bins", [])] or [None] * len(h["per_bin"])}


def _mean(values: list[Any]) -> float:
    vals = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return float(np.mean(vals)) if vals else math.nan


def _per_bin(rows: list[dict[str, Any]], key: str, sign: bool = True) -> str:
    f = "{:+.2f}" if sign else "{:.2f}"
    return " / ".join("n/a" if math.isnan(m := _mean([r[key][k] for r in rows])) else f.format(m)
                      for k in range(len(BINS) - 1))


def table(out: Path, runs: list[str]) -> str:
    arms: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for name in runs:
        run = out / "runs" / name
        arm = name.rsplit("_s", 1)[0]
        for block in ("val", "test"):
            rep = _report(run, block)
            if rep is not None:
                arms.setdefault(arm, {}).setdefault(block, []).append(_numbers(rep))
    lines = []
    for block, title in (("val", "validation block (chooses)"), ("test", "held-out test block (reports)")):
        lines += [f"**{title}** — per bin: 0–1 / 1–2 / 2–5 / 5–10 / 10–20 / ≥ 20 m", "",
                  "| arm | seeds | MAE | MAE ≥ 2 m | bias ≥ 2 m | CRPS | bias per bin | ±1σ per bin | "
                  "Spearman(std, \\|err\\|) per bin | Spearman(std, predicted h) per bin | "
                  "Spearman(unfamiliarity, \\|err\\|) per bin |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for arm, blocks in arms.items():
            rows = blocks.get(block, [])
            if not rows:
                continue
            lines.append(f"| {arm} | {len(rows)} | {_fmt_range([r['mae'] for r in rows])} | "
                         f"{_fmt_range([r['mae_tall'] for r in rows])} | "
                         f"{_fmt_range([r['bias_tall'] for r in rows], sign=True)} | "
                         f"{_fmt_range([r['crps'] for r in rows])} | {_per_bin(rows, 'bias_bin')} | "
                         f"{_per_bin(rows, 'cov_bin', False)} | {_per_bin(rows, 'rho_bin')} | "
                         f"{_per_bin(rows, 'rho_h_bin')} | {_per_bin(rows, 'unfam_bin')} |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="the bench/real_data.py --out folder")
    ap.add_argument("--runs", nargs="+", required=True)
    args = ap.parse_args()
    print(table(args.out, args.runs))


if __name__ == "__main__":
    main()
