"""The studies' one runner: arms as data, validation chooses, the test block reports.

A study is a mapping of **arms** (name → what the study's code needs to make that arm's maps: a fitted spread's
kind, a run name prefix, ...) and a function that **scores** one arm on one run and one block (``val`` or
``test``) into named numbers. :func:`run_arms` scores every arm on every run and block; :func:`choose` picks the arm
with the best mean *validation* score (the test block never chooses); :func:`table` writes one Markdown row per
arm and block with the mean (range) over the runs (seeds), marking the chosen arm. The scoring helpers every
spread study uses (Gaussian CRPS and NLL of absolute errors, the reference-height bins, mean and range over seeds)
are here once.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, TypeVar

import numpy as np

from aerialmtl.evaluation.uncertainty import crps_gaussian, gaussian_nll_terms

A = TypeVar("A")
#: block → metric → value (a number, or a list of per-bin numbers)
Scores = dict[str, Any]
#: arm → block → one score dict per run
Results = dict[str, dict[str, list[Scores]]]
BLOCKS = ("val", "test")
#: The studies' reference-height bins (metres) as edges, 0–1 / 1–2 / 2–5 / 5–10 / 10–20 / ≥ 20 m: the evaluation's
#: ``height_bins`` of every study (the package's default bins today, :data:`aerialmtl.evaluation.metrics.
#: DEFAULT_HEIGHT_BINS`, fixed here so that the studies' published tables stay comparable if that default moves).
HEIGHT_EDGES: tuple[float, ...] = (0.0, 1.0, 2.0, 5.0, 10.0, 20.0, math.inf)
#: The same bins as ``(low, high)`` pairs, for the per-bin columns.
BINS: tuple[tuple[float, float], ...] = tuple(zip(HEIGHT_EDGES[:-1], HEIGHT_EDGES[1:], strict=True))


def run_arms(arms: Mapping[str, A], runs: Iterable[str],
             score: Callable[[str, str, A], Mapping[str, Scores] | None]) -> Results:
    """Score every arm on every run: ``score(run, arm_name, arm)`` → ``{"val": ..., "test": ...}`` (``None``: the
    run lacks what the arm needs; it is left out)."""
    results: Results = {name: {b: [] for b in BLOCKS} for name in arms}
    for run in runs:
        for name, arm in arms.items():
            got = score(run, name, arm)
            if got is None:
                continue
            for block in BLOCKS:
                if block in got:
                    results[name][block].append(dict(got[block]))
    return results


def choose(results: Results, key: str, lower: bool = True) -> str:
    """The arm whose mean validation ``key`` is best (lowest with ``lower``); only validation decides."""
    means = {arm: mean([s.get(key) for s in blocks["val"]]) for arm, blocks in results.items()}
    finite = {a: m for a, m in means.items() if math.isfinite(m)}
    if not finite:
        raise ValueError(f"no arm has a validation {key!r}")
    return (min if lower else max)(finite, key=finite.__getitem__)


def table(results: Results, columns: Sequence[tuple[str, str, Callable[[list[Scores]], str]]],
          chosen: str | None = None) -> str:
    """Markdown: one row per arm and block; ``columns``: (header, alignment, rows → cell)."""
    lines = ["| arm | block | " + " | ".join(c[0] for c in columns) + " |",
             "|---|---|" + "|".join(c[1] for c in columns) + "|"]
    for arm, blocks in results.items():
        name = f"**{arm}** (chosen)" if arm == chosen else arm
        for block in BLOCKS:
            rows = blocks[block]
            if rows:
                lines.append(f"| {name} | {block} | " + " | ".join(c[2](rows) for c in columns) + " |")
    return "\n".join(lines)


# ---- numbers over seeds ------------------------------------------------------------------------------
def mean(values: Iterable[Any]) -> float:
    """Mean of the finite values (``None`` and NaN left out); NaN when none."""
    vals = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return float(np.mean(vals)) if vals else math.nan


def fmt_range(vals: Iterable[float | None], digits: int = 2, sign: bool = False) -> str:
    """``mean (min–max)`` of the finite values (just the mean for one), ``n/a`` for none."""
    finite = [float(v) for v in vals if v is not None and math.isfinite(v)]
    if not finite:
        return "n/a"
    f = f"{{:+.{digits}f}}" if sign else f"{{:.{digits}f}}"
    m = f.format(float(np.mean(finite)))
    return m if len(finite) == 1 else f"{m} ({f.format(min(finite))}–{f.format(max(finite))})"


def per_bin(rows: list[Scores], key: str, sign: bool = True, bins: int = len(BINS)) -> str:
    """The mean over ``rows`` of each bin of the list ``key``, ``a / b / ...``."""
    f = "{:+.2f}" if sign else "{:.2f}"
    return " / ".join("n/a" if math.isnan(m := mean([r[key][k] for r in rows])) else f.format(m)
                      for k in range(bins))


# ---- proper scores of a spread -----------------------------------------------------------------------
def crps(err: np.ndarray, sig: np.ndarray) -> np.ndarray:
    """Gaussian CRPS (metres) of absolute errors ``err`` under spreads ``sig`` (the evaluation's, σ floored)."""
    return np.asarray(crps_gaussian(err, sig, np.zeros_like(err)))


def nll(err: np.ndarray, sig: np.ndarray) -> np.ndarray:
    """Gaussian negative log-likelihood (nats; the evaluation's, σ floored)."""
    return np.asarray(gaussian_nll_terms(err, sig, np.zeros_like(err)))
