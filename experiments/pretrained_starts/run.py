"""Issue 36's study table: the recipe, copy-paste, and the synthetic starts of several pretraining lengths
fine-tuned with the recipe, on ``autzen_west``'s fixed split (``middle-val``); validation chooses, the held-out
test block reports.

It reads what ``experiments/real_data`` (training) and ``experiments/uncertainty --val-block`` (the raw
predictions of the test and validation blocks, T = 16) left in ``OUT/runs/<run>/``, evaluates those raw
predictions once more with today's ``evaluate`` (cached as ``study36_{test,val}.json``: it adds, per reference-height
bin, Spearman(height_std, predicted height) and the unfamiliarity layer's ranks), and prints one Markdown table per
block with the mean (range) over the seeds of each arm (the run name without ``_s<seed>``), through the shared study
runner (:mod:`experiments.common.study`: validation chooses, the test block reports).

Usage::

    python -m experiments.pretrained_starts.run --out /work/study_h36u \\
        --runs al_b0_s0 al_b0_s1 al_b0_s2 cp_s0 cp_s1 cp_s2 ft_s0 ft_s1 ft_s2 ft5k_s0 ft5k_s1 ft5k_s2
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from aerialmtl.evaluation.evaluate import EvaluateOptions, evaluate_prediction
from experiments.common import study
from experiments.common.autzen import DATA, DSM, DTM, TALL_M
from experiments.common.study import HEIGHT_EDGES
from experiments.common.study import fmt_range as _fmt_range
from experiments.common.study import per_bin as _study_per_bin

#: where a run's raw predictions are (the unfamiliarity study's folder for runs trained before the layer existed)
FOLDERS = {"test": ("study_raw_best", "unfam_pred_l2_d32_gda_auto"), "val": ("study_valblock_raw",)}


def _evaluate(folder: Path) -> dict[str, Any]:
    return evaluate_prediction(folder, dsm_ref=DATA / DSM, dtm_ref=DATA / DTM, out=None,
                               options=EvaluateOptions(height_bins=HEIGHT_EDGES, plots=False))


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


def _per_bin(rows: list[dict[str, Any]], key: str, sign: bool = True) -> str:
    return _study_per_bin(rows, key, sign, bins=len(HEIGHT_EDGES) - 1)


COLUMNS = [("seeds", "---", lambda rows: str(len(rows))),
           ("MAE", "---", lambda rows: _fmt_range([r["mae"] for r in rows])),
           ("MAE ≥ 2 m", "---", lambda rows: _fmt_range([r["mae_tall"] for r in rows])),
           ("bias ≥ 2 m", "---", lambda rows: _fmt_range([r["bias_tall"] for r in rows], sign=True)),
           ("CRPS", "---", lambda rows: _fmt_range([r["crps"] for r in rows])),
           ("bias per bin", "---", lambda rows: _per_bin(rows, "bias_bin")),
           ("±1σ per bin", "---", lambda rows: _per_bin(rows, "cov_bin", False)),
           ("Spearman(std, \\|err\\|) per bin", "---", lambda rows: _per_bin(rows, "rho_bin")),
           ("Spearman(std, predicted h) per bin", "---", lambda rows: _per_bin(rows, "rho_h_bin")),
           ("Spearman(unfamiliarity, \\|err\\|) per bin", "---", lambda rows: _per_bin(rows, "unfam_bin"))]


def table(out: Path, runs: list[str]) -> str:
    """The arms are the run names without ``_s<seed>``; validation (MAE ≥ 2 m) chooses, the test block reports."""
    arms = {name.rsplit("_s", 1)[0]: name.rsplit("_s", 1)[0] for name in runs}

    def score(run: str, _: str, arm: str) -> dict[str, Any] | None:
        if run.rsplit("_s", 1)[0] != arm:
            return None
        reports = {block: _report(out / "runs" / run, block) for block in study.BLOCKS}
        return {block: _numbers(rep) for block, rep in reports.items() if rep is not None}

    results = study.run_arms(arms, runs, score)
    chosen = study.choose(results, "mae_tall")
    return (f"validation (MAE ≥ 2 m) chooses: {chosen}; per bin: 0–1 / 1–2 / 2–5 / 5–10 / 10–20 / ≥ 20 m\n\n"
            + study.table(results, COLUMNS, chosen))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="the experiments/real_data --out folder")
    ap.add_argument("--runs", nargs="+", required=True)
    args = ap.parse_args()
    print(table(args.out, args.runs))


if __name__ == "__main__":
    main()
