"""Issue 28's third stage: what the height spread is made of, and a neighbourhood spread fitted on validation.

For runs of ``experiments/real_data/run.py`` already studied by ``experiments/uncertainty/run.py`` (their raw
test-block maps in ``OUT/runs/<run>/study_raw_best``), this script

1. predicts the **validation band** the same way (raw, T = 16; ``study_val_raw``) and both blocks with the Laplace
   scale forced to its floor (``study_epi_val``, ``study_epi_raw_best``: ``height_std`` = the MC part alone;
   ``--engine torch``, since the scale is patched in the torch model);
2. prints, per reference-height bin of the test block, the rank correlations of the spread, of its MC part and of
   the absolute error with the predicted height, and the MC part's coverage (``--diagnose``);
3. fits spreads σ² = (a·s)² + (c·d_r)² + (e·μ)² + f² on the validation maps (s: the model's spread, μ: the
   predicted height, d_r: the highest predicted height within r pixels minus the pixel's own; subsets of the terms,
   r ∈ {3, 6, 10, 16}), by Gaussian NLL or CRPS, and scores each on the test block per bin (``--fit``;
   ``OUT/runs/<run>/ctx_spread.json``, and ``--table`` prints the mean over runs as Markdown).

Nothing here ships: it is the analysis behind bench/RESULTS.md ("Third stage"). Usage::

    python -m experiments.spread_diagnosis.run --out /work/study --runs al_b0_s0 al_b0_s1 al_b0_s2 \\
        --diagnose --fit --table
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import optimize, stats

import aerialmtl.models.d3net as d3net  # noqa: E402
from aerialmtl.formats.checkpoint import load_model  # noqa: E402
from aerialmtl.inference.predict import predict_raster  # noqa: E402
from experiments.common.autzen import DATA, ORTHO
from experiments.common.maps import load, neighbourhood
from experiments.common.study import BINS, crps, nll

#: the spread models: which of (a·s, c·d_r, e·μ, f) take part
TERMS = {"s": (1, 0, 0, 1), "s+d": (1, 1, 0, 1), "s+d+h": (1, 1, 1, 1)}
RADII = (3, 6, 10, 16)


def predict_maps(out: Path, run: str, split_dir: Path) -> None:
    """The validation band raw, and both blocks with the MC part alone (see the module docstring)."""
    rdir = out / "runs" / run
    model, meta = load_model(rdir / "best.pt")
    jobs = [("study_val_raw", "val", False), ("study_epi_val", "val", True), ("study_epi_raw_best", "test", True)]
    scale = d3net.laplace_scale
    for name, block, mc_only in jobs:
        if (rdir / name / "height_std.tif").is_file():
            continue
        d3net.laplace_scale = (lambda raw: torch.full_like(raw.float(), d3net.SCALE_MIN)) if mc_only else scale
        try:
            predict_raster(DATA / ORTHO, (model, meta), rdir / name, mc=16, aoi=split_dir / f"{block}.geojson",
                           engine="torch" if mc_only else "auto", overwrite=True, progress=False,
                           checkpoint_name=str(rdir / "best.pt"), calibration=False, seed=0)
        finally:
            d3net.laplace_scale = scale


def sigma(p: np.ndarray, s: np.ndarray, d: np.ndarray, h: np.ndarray) -> np.ndarray:
    """σ of log-parameters ``p`` = log(a, c, e, f)."""
    a, c, e, f = np.exp(p)
    return np.sqrt((a * s) ** 2 + (c * d) ** 2 + (e * np.maximum(h, 0)) ** 2 + f**2)


def fit(err: np.ndarray, s: np.ndarray, d: np.ndarray, h: np.ndarray,
        score: Callable[[np.ndarray, np.ndarray], np.ndarray], use: np.ndarray) -> np.ndarray:
    """Log-parameters minimising the mean ``score`` (terms not in ``use`` pinned at e^-20), Nelder-Mead from
    three starts."""
    def objective(p: np.ndarray) -> float:
        return float(score(err, sigma(np.where(use, p, -20.0), s, d, h)).mean())

    best = None
    for p0 in ([0, -1, -3, -1], [1, 0, -2, 0], [-1, -2, -1, -2]):
        r = optimize.minimize(objective, np.array(p0, float), method="Nelder-Mead",
                              options={"maxiter": 2000, "xatol": 1e-3, "fatol": 1e-5})
        if best is None or r.fun < best.fun:
            best = r
    assert best is not None
    return np.where(use, best.x, -20.0)


def per_bin(err: np.ndarray, sig: np.ndarray, ref: np.ndarray) -> dict[str, Any]:
    """CRPS, NLL, and per reference-height bin: ±1σ coverage and Spearman(σ, |error|) (bins ≥ 2 m)."""
    out: dict[str, Any] = {"crps": float(crps(err, sig).mean()), "nll": float(nll(err, sig).mean()),
                           "cov": [], "rho": []}
    for lo, hi in BINS:
        m = (ref >= lo) & (ref < hi)
        out["cov"].append(float(np.mean(err[m] <= sig[m])))
        out["rho"].append(float(stats.spearmanr(sig[m], err[m]).statistic) if lo >= 2 else None)
    return out


def diagnose(out: Path, runs: list[str]) -> None:
    """The table "what the recipe's spread is made of" (mean over ``runs``)."""
    rows: dict[int, list[list[float]]] = {}
    for run in runs:
        rdir = out / "runs" / run
        h, s, r = load(rdir / "study_raw_best")
        _, mc, _ = load(rdir / "study_epi_raw_best")
        ok = np.isfinite(h) & np.isfinite(r) & np.isfinite(s) & np.isfinite(mc)
        for i, (lo, hi) in enumerate(BINS):
            b = ok & (r >= lo) & (r < hi)
            e = np.abs(h - r)[b]
            rows.setdefault(i, []).append([
                stats.spearmanr(s[b], h[b]).statistic, stats.spearmanr(mc[b], h[b]).statistic,
                stats.spearmanr(e, h[b]).statistic, stats.spearmanr(s[b], e).statistic,
                stats.spearmanr(mc[b], e).statistic, float(np.mean(e <= mc[b])), float(np.median(mc[b])),
                float(np.median(np.sqrt(np.maximum(s[b] ** 2 - mc[b] ** 2, 0.0)))), float(np.mean(h[b] > r[b]))])
    names = ["Spearman(std, predicted height)", "Spearman(MC part alone, predicted height)",
             "Spearman(|error|, predicted height)", "Spearman(std, |error|)", "Spearman(MC part alone, |error|)",
             "±1σ coverage of the MC part alone", "median MC std (m)", "median Laplace part (m)",
             "share of pixels predicted above the reference"]
    print("| per reference-height bin | " + " | ".join(f"{lo:g}–{hi:g}" for lo, hi in BINS) + " |")
    print("|---" * (len(BINS) + 1) + "|")
    for j, name in enumerate(names):
        print(f"| {name} | " + " | ".join(f"{np.mean([x[j] for x in rows[i]]):.2f}" for i in range(len(BINS))) + " |")


def fit_run(out: Path, run: str) -> dict[str, Any]:
    """Every spread model fitted on the validation maps and scored on the test block's; ``ctx_spread.json``."""
    rdir = out / "runs" / run
    val, test = load(rdir / "study_val_raw"), load(rdir / "study_raw_best")
    masks = [np.isfinite(x[0]) & np.isfinite(x[1]) & np.isfinite(x[2]) for x in (val, test)]
    res: dict[str, Any] = {}
    for r in RADII:
        dv, dt = neighbourhood(val[0], r), neighbourhood(test[0], r)
        for terms, use in TERMS.items():
            if terms == "s" and r != RADII[0]:
                continue  # no neighbourhood term: one fit is enough
            for sname, score in (("nll", nll), ("crps", crps)):
                mv, mt = masks
                ev, et = np.abs(val[0] - val[2])[mv], np.abs(test[0] - test[2])[mt]
                p = fit(ev, val[1][mv], dv[mv], val[0][mv], score, np.array(use, bool))
                key = f"{terms}_r{r}_{sname}" if "d" in terms else f"{terms}_{sname}"
                res[key] = {"params": np.exp(p).round(4).tolist(),
                            "val": per_bin(ev, sigma(p, val[1][mv], dv[mv], val[0][mv]), val[2][mv]),
                            "test": per_bin(et, sigma(p, test[1][mt], dt[mt], test[0][mt]), test[2][mt])}
                print(run, key, f"val NLL {res[key]['val']['nll']:.2f} test NLL {res[key]['test']['nll']:.2f}",
                      flush=True)
    mv, mt = masks
    res["raw"] = {"val": per_bin(np.abs(val[0] - val[2])[mv], val[1][mv], val[2][mv]),
                  "test": per_bin(np.abs(test[0] - test[2])[mt], test[1][mt], test[2][mt])}
    (rdir / "ctx_spread.json").write_text(json.dumps(res, indent=1))
    return res


def table(out: Path, runs: list[str]) -> None:
    """Mean over ``runs`` of every spread model (validation and test block) as Markdown."""
    rows: dict[str, list[dict[str, Any]]] = {}
    for run in runs:
        for k, v in json.loads((out / "runs" / run / "ctx_spread.json").read_text()).items():
            rows.setdefault(k, []).append(v)
    print("| spread (fit) | val NLL | val CRPS | test NLL | test CRPS | test ±1σ per bin | test Spearman ≥ 2 m bins |")
    print("|---|---|---|---|---|---|---|")
    for k, vs in rows.items():
        def mean(f: Callable[[dict[str, Any]], float], vs: list[dict[str, Any]] = vs) -> float:
            return float(np.mean([f(v) for v in vs]))
        cov = "/".join(f"{mean(lambda v, i=i: v['test']['cov'][i]):.2f}" for i in range(len(BINS)))
        rho = "/".join(f"{mean(lambda v, i=i: v['test']['rho'][i]):.2f}" for i in range(2, len(BINS)))
        print(f"| {k} | {mean(lambda v: v['val']['nll']):.2f} | {mean(lambda v: v['val']['crps']):.2f} | "
              f"{mean(lambda v: v['test']['nll']):.2f} | {mean(lambda v: v['test']['crps']):.2f} | {cov} | {rho} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="the experiments/real_data/run.py --out folder")
    ap.add_argument("--runs", nargs="+", required=True)
    ap.add_argument("--diagnose", action="store_true")
    ap.add_argument("--fit", action="store_true")
    ap.add_argument("--table", action="store_true")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    split_dir = args.out / "split_middle-val"
    for run in args.runs:
        predict_maps(args.out, run, split_dir)
    if args.diagnose:
        diagnose(args.out, args.runs)
    if args.fit:
        for run in args.runs:
            fit_run(args.out, run)
    if args.table:
        table(args.out, args.runs)


if __name__ == "__main__":
    main()
