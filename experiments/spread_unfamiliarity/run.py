"""Issue 36 part 4: may the unfamiliarity layer be folded into the height spread? (post hoc, validation fits)

For runs of ``experiments/real_data/run.py`` whose validation and test blocks were predicted raw (T = 16) with the
unfamiliarity layer (``experiments/uncertainty/run.py --val-block``; for runs trained before the layer, the folders
named in :data:`FOLDERS`' second entries), this script fits on the **validation block** a spread per range of the
predicted height (the calibration's ranges, :data:`aerialmtl.models.calibration.SPREAD_EDGES`)::

    σ² = (s_k · height_std)² + f_k² [+ (a_k · q(u))²]        q(u) = u  or  −log(1 − u)

by the mean Gaussian CRPS or NLL of that range's pixels, and scores it on the **test block**: CRPS, NLL, and per
reference-height bin the ±1σ coverage, Spearman(σ, |error|) and Spearman(σ, predicted height). Nothing here ships
unless the validation says so: it is the analysis behind bench/results/pretraining.md ("eighth stage"). Arms are data
(:data:`ARMS`), run by the shared study runner (:mod:`experiments.common.study`). Usage::

    python -m experiments.spread_unfamiliarity.run --out /work/study_h36u --runs al_b0_s0 al_b0_s1 al_b0_s2
"""

from __future__ import annotations

import argparse
import functools
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from scipy import optimize, stats

from aerialmtl.models.calibration import SPREAD_EDGES
from experiments.common import study
from experiments.common.maps import reference_on
from experiments.common.study import BINS, crps, mean, nll

#: (validation, test) folders of a run, first found wins (the second: runs trained before the layer existed)
FOLDERS = {"val": ("study_valblock_raw", "valblock_unfam"), "test": ("study_raw_best", "unfam_pred_l2_d32_gda_auto")}
#: fewest validation pixels a range is fitted on alone (else with its neighbours)
MIN_PIXELS = 500
ARMS = {"raw": None, "s,f (crps)": ("crps", None), "s,f,u (crps)": ("crps", "u"), "s,f,-log(1-u) (crps)":
        ("crps", "logit"), "s,f (nll)": ("nll", None), "s,f,u (nll)": ("nll", "u"),
        "s,f,-log(1-u) (nll)": ("nll", "logit")}
Maps = dict[str, np.ndarray]


def load(run: Path, block: str) -> Maps | None:
    """Valid pixels of a block: ``h`` predicted height, ``s`` height_std, ``u`` unfamiliarity, ``r`` reference."""
    folder = next((run / f for f in FOLDERS[block] if (run / f / "unfamiliarity.tif").is_file()), None)
    if folder is None:
        return None
    maps = {}
    for key, name in (("h", "height"), ("s", "height_std"), ("u", "unfamiliarity")):
        with rasterio.open(folder / f"{name}.tif") as src:
            a = src.read(1).astype(np.float64)
            a[a == src.nodata] = np.nan
            maps[key] = a
    maps["r"] = reference_on(folder / "height.tif")
    ok = np.all([np.isfinite(v) for v in maps.values()], axis=0)
    return {k: v[ok] for k, v in maps.items()}


def feature(u: np.ndarray, kind: str | None) -> np.ndarray:
    if kind is None:
        return np.zeros_like(u)
    return u if kind == "u" else -np.log1p(-np.clip(u, 0.0, 1.0 - 1e-3))


def sigma(p: np.ndarray, s: np.ndarray, q: np.ndarray) -> np.ndarray:
    a, f, c = np.exp(p)
    return np.sqrt((a * s) ** 2 + f**2 + (c * q) ** 2)


def fit_range(err: np.ndarray, s: np.ndarray, q: np.ndarray, score: Callable[..., np.ndarray],
              with_u: bool) -> np.ndarray:
    """Log-parameters (scale, floor, unfamiliarity weight) minimising the mean score; Nelder-Mead, three starts."""
    def objective(p: np.ndarray) -> float:
        return float(score(err, sigma(p if with_u else np.r_[p[:2], -20.0], s, q)).mean())

    best = None
    for p0 in ([0.0, -1.0, -1.0], [-1.0, 0.5, 0.5], [0.5, -1.0, 1.0]):
        r = optimize.minimize(objective, np.array(p0), method="Nelder-Mead",
                              options={"maxiter": 1500, "xatol": 1e-3, "fatol": 1e-6})
        if best is None or r.fun < best.fun:
            best = r
    assert best is not None
    return best.x if with_u else np.r_[best.x[:2], -20.0]


def fit(val: Maps, score: Callable[..., np.ndarray], kind: str | None) -> list[np.ndarray]:
    k = np.searchsorted(SPREAD_EDGES, val["h"], side="right")
    err, q = np.abs(val["h"] - val["r"]), feature(val["u"], kind)
    params = []
    for j in range(len(SPREAD_EDGES) + 1):
        m = k == j
        if m.sum() < MIN_PIXELS:
            m = np.abs(k - j) <= 1
        params.append(fit_range(err[m], val["s"][m], q[m], score, kind is not None))
    return params


def apply(params: list[np.ndarray], maps: Maps, kind: str | None) -> np.ndarray:
    k, q = np.searchsorted(SPREAD_EDGES, maps["h"], side="right"), feature(maps["u"], kind)
    out = np.empty_like(maps["s"])
    for j, p in enumerate(params):
        m = k == j
        out[m] = sigma(p, maps["s"][m], q[m])
    return out


def scores(maps: Maps, sig: np.ndarray) -> dict[str, Any]:
    err = np.abs(maps["h"] - maps["r"])
    out: dict[str, Any] = {"crps": float(crps(err, sig).mean()), "nll": float(nll(err, sig).mean()),
                           "cov": [], "rho": [], "rho_h": []}
    for lo, hi in BINS:
        m = (maps["r"] >= lo) & (maps["r"] < hi)
        out["cov"].append(float(np.mean(err[m] <= sig[m])))
        out["rho"].append(float(stats.spearmanr(sig[m], err[m]).statistic))
        out["rho_h"].append(float(stats.spearmanr(sig[m], maps["h"][m]).statistic))
    return out


@functools.cache
def study_run(run: Path) -> dict[str, Any] | None:
    """Every arm of one run: fitted on its validation block, scored on both (cached in ``spread_unfam.json``)."""
    cache = run / "spread_unfam.json"
    if cache.is_file():
        return dict(json.loads(cache.read_text()))
    val, test = load(run, "val"), load(run, "test")
    if val is None or test is None:
        return None
    res: dict[str, Any] = {}
    for arm, how in ARMS.items():
        if how is None:
            res[arm] = {"val": scores(val, val["s"]), "test": scores(test, test["s"])}
            continue
        score, kind = crps if how[0] == "crps" else nll, how[1]
        params = fit(val, score, kind)
        res[arm] = {"params": [np.exp(p).round(4).tolist() for p in params],
                    "val": scores(val, apply(params, val, kind)), "test": scores(test, apply(params, test, kind))}
    cache.write_text(json.dumps(res))
    return res


def _bins(key: str) -> Callable[[list[dict[str, Any]]], str]:
    def cell(rows: list[dict[str, Any]]) -> str:
        return " / ".join(f"{mean([r[key][i] for r in rows]):+.2f}".replace("+", "" if key == "cov" else "+")
                          for i in range(len(BINS)))
    return cell


COLUMNS = [("CRPS", "---", lambda rows: f"{mean(r['crps'] for r in rows):.3f}"),
           ("NLL", "---", lambda rows: f"{mean(r['nll'] for r in rows):.2f}"),
           ("±1σ per bin", "---", _bins("cov")), ("Spearman(σ, \\|err\\|) per bin", "---", _bins("rho")),
           ("Spearman(σ, predicted h) per bin", "---", _bins("rho_h"))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--runs", nargs="+", required=True)
    args = ap.parse_args()

    def score(run: str, arm: str, _: Any) -> dict[str, Any] | None:
        res = study_run(args.out / "runs" / run)
        return None if res is None else res[arm]

    results = study.run_arms(ARMS, args.runs, score)
    chosen = study.choose(results, "crps")  # the validation block's mean CRPS decides
    print(f"runs: {', '.join(args.runs)} (mean over them; bins 0–1 / 1–2 / 2–5 / 5–10 / 10–20 / ≥ 20 m); "
          f"validation (CRPS) chooses: {chosen}")
    print(study.table(results, COLUMNS, chosen))


if __name__ == "__main__":
    main()
