"""Write an evaluation report: JSON (all numbers), a short Markdown summary and PNG plots.

``write_report(report, "out/report.json")`` writes ``out/report.json``, ``out/report.md`` and, when
matplotlib is installed (the optional ``plot`` extra), ``out/report_sparsification.png``,
``out/report_confusion.png`` and ``out/report_reliability.png`` (the format: :mod:`aerialmtl.formats.report`).
In the JSON, undefined values (``nan``) and open-ended bin edges (``inf``) are written as ``null``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from aerialmtl.errors import OutputError
from aerialmtl.filesafety import atomic_write
from aerialmtl.formats.report import owned_plots, plot_path
from aerialmtl.io.outputs import write_text_atomic


def to_jsonable(obj: Any) -> Any:
    """Replace ``nan``/``inf`` with ``None`` and numpy scalars/arrays with Python ones (recursively)."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def _fmt(v: Any, digits: int = 3, pct: bool = False) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{100 * v:.1f} %" if pct else f"{v:.{digits}f}"


def headline(report: dict[str, Any]) -> list[tuple[str, str]]:
    """The headline numbers as (label, formatted value) pairs, for the CLI and the Markdown summary."""
    rows: list[tuple[str, str]] = []
    h = report.get("height")
    if h:
        rows += [("height MAE (m)", _fmt(h["mae"])), ("height RMSE (m)", _fmt(h["rmse"])),
                 ("height median abs error (m)", _fmt(h["median_abs_error"])),
                 (f"δ<1.25 (ref > {h['delta']['reference_above_m']:g} m)", _fmt(h["delta"]["delta_1"], pct=True))]
    c = report.get("classes")
    if c:
        rows += [("overall accuracy", _fmt(c["overall_accuracy"], pct=True)), ("mIoU", _fmt(c["miou"], pct=True)),
                 ("Cohen's kappa", _fmt(c["kappa"]))]
    u = report.get("uncertainty") or {}
    if "height_std" in u:
        hs = u["height_std"]
        rows += [("height std AUSE", _fmt(hs["sparsification"]["ause"])),
                 ("height std Spearman", _fmt(hs["spearman_std_vs_abs_error"])),
                 ("height NLL (nats)", _fmt(hs["nll"])),
                 ("height ±1σ / ±2σ coverage", f"{_fmt(hs['coverage_1sigma'], pct=True)} / "
                                             f"{_fmt(hs['coverage_2sigma'], pct=True)}")]
        if hs.get("strata", {}).get("crps_gaussian_m") is not None:
            rows.append(("height CRPS (m)", _fmt(hs["strata"]["crps_gaussian_m"])))
    if "class_entropy" in u:
        rows.append(("class entropy AUSE", _fmt(u["class_entropy"]["sparsification"]["ause"])))
    if "calibration" in u:
        rows.append(("class ECE", _fmt(u["calibration"]["ece"])))
    b = report.get("buildings")
    if b:
        rows += [(f"building F1 (IoU ≥ {b['iou_threshold']:g})", _fmt(b["f1"])),
                 ("building precision / recall", f"{_fmt(b['precision'])} / {_fmt(b['recall'])}"),
                 ("buildings matched / reference / predicted",
                  f"{b['n_matched']} / {b['n_reference']} / {b['n_predicted']}")]
        if b.get("height"):
            rows += [("building height MAE (m)", _fmt(b["height"]["mae"])),
                     ("building height RMSE (m)", _fmt(b["height"]["rmse"])),
                     ("building height std Spearman", _fmt(b["spearman_std_vs_abs_error"]))]
    return rows


def markdown_summary(report: dict[str, Any]) -> str:
    """A short Markdown summary: headline table, per-class and per-bin tables, notes."""
    lines = ["# aerialmtl evaluation", "", f"Prediction: `{report['prediction']}`  "]
    refs = report.get("references") or {}
    for key in ("height", "labels", "buildings"):
        if refs.get(key):
            lines.append(f"Reference {key}: `{refs[key]}`  ")
    lines += ["", "| metric | value |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in headline(report)]
    h = report.get("height")
    if h:
        for key, title, intro in (
                ("per_bin", "reference-height bin", "Pixels grouped by their true height: how well each height is "
                 "found. The pixels of an object the network missed are predicted low, so they pull a tall bin's "
                 "bias down."),
                ("per_predicted_bin", "predicted-height bin", "Pixels grouped by the height the map reads: how far "
                 "a reading of that height is off on average (bias = predicted − reference: a bias of −2 m means "
                 "the truth is on average 2 m higher).")):
            if key not in h:  # reports written before the predicted-height bins
                continue
            lines += ["", f"## Height error per {title}", "", intro, "",
                      "| bin (m) | pixels | MAE (m) | RMSE (m) | bias (m) |", "|---|---|---|---|---|"]
            for b in h[key]:
                lo, hi = b["range_m"]
                hi_s = "∞" if hi is None or (isinstance(hi, float) and math.isinf(hi)) else f"{hi:g}"
                lines.append(f"| [{lo:g}, {hi_s}) | {b['n_pixels']} | {_fmt(b['mae'])} | {_fmt(b['rmse'])} | "
                             f"{_fmt(b['bias'])} |")
    strata = ((report.get("uncertainty") or {}).get("height_std") or {}).get("strata")
    if strata:
        lines += ["", "## Height spread per reference-height bin", "",
                  "±1σ / ±2σ: share of pixels whose error lies within one / two `height_std` (0.68 / 0.95 for a "
                  "Gaussian, 0.76 / 0.94 for a Laplace law); Spearman: rank correlation of `height_std` and |error| "
                  "within the bin (does the spread rank the misses?); vs height: its rank correlation with the "
                  "predicted height within the bin (near 1: the spread there is the height map rescaled); NLL "
                  "(Gaussian) and CRPS: proper scores, lower is better.", "",
                  "| bin (m) | share | ±1σ | ±2σ | median std (m) | median abs error (m) | Spearman | vs height | "
                  "NLL | CRPS (m) |", "|---|---|---|---|---|---|---|---|---|---|"]
        for b in strata["bins"]:
            lo, hi = b["range_m"]
            hi_s = "∞" if hi is None or (isinstance(hi, float) and math.isinf(hi)) else f"{hi:g}"
            lines.append(f"| [{lo:g}, {hi_s}) | {_fmt(b.get('share'), pct=True)} | "
                         f"{_fmt(b.get('coverage_1sigma'), 2)} | {_fmt(b.get('coverage_2sigma'), 2)} | "
                         f"{_fmt(b.get('median_std_m'), 2)} | {_fmt(b.get('median_abs_error_m'), 2)} | "
                         f"{_fmt(b.get('spearman_std_vs_abs_error'), 2)} | "
                         f"{_fmt(b.get('spearman_std_vs_predicted_height'), 2)} | {_fmt(b.get('nll_gaussian'), 2)} | "
                         f"{_fmt(b.get('crps_gaussian_m'), 2)} |")
    unfam = (report.get("uncertainty") or {}).get("unfamiliarity")
    if unfam and unfam.get("bins"):
        lines += ["", "## Unfamiliarity per reference-height bin", "",
                  "Spearman of `unfamiliarity` with |height error| within the bin (does it flag the misses among "
                  "pixels of similar height?) and with the predicted height (does it merely follow the height?); "
                  f"overall Spearman with |error| {_fmt(unfam.get('spearman_vs_abs_error'), 2)}.", "",
                  "| bin (m) | sampled px | median unfamiliarity | Spearman vs error | vs height |",
                  "|---|---|---|---|---|"]
        for b in unfam["bins"]:
            lo, hi = b["range_m"]
            hi_s = "∞" if hi is None or (isinstance(hi, float) and math.isinf(hi)) else f"{hi:g}"
            lines.append(f"| [{lo:g}, {hi_s}) | {b['n_sampled']} | {_fmt(b.get('median_unfamiliarity'), 2)} | "
                         f"{_fmt(b.get('spearman_vs_abs_error'), 2)} | "
                         f"{_fmt(b.get('spearman_vs_predicted_height'), 2)} |")
    c = report.get("classes")
    if c:
        lines += ["", "## Classes", "", "| class | IoU | F1 | reference px | predicted px |", "|---|---|---|---|---|"]
        for name, m in c["per_class"].items():
            lines.append(f"| {name} | {_fmt(m['iou'], pct=True)} | {_fmt(m['f1'], pct=True)} | "
                         f"{m['n_reference']} | {m['n_predicted']} |")
        lines.append("")
        lines.append("mIoU and mean F1 average the classes present in the reference or the prediction.")
    s = report.get("sampling") or {}
    lines += ["", f"Rank-based metrics (median, AUSE/AURG, Spearman) use at most {s.get('max_pixels')} "
              f"pixels sampled with seed {s.get('seed')}; sparsification curves are normalised by the "
              "full-set mean error."]
    if report.get("notes"):
        lines += ["", "## Notes", ""] + [f"- {n}" for n in report["notes"]]
    if report.get("plots"):
        lines += ["", "## Plots", ""] + [f"![{Path(p).stem}]({Path(p).name})" for p in report["plots"]]
    return "\n".join(lines) + "\n"


def _save(fig: Any, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    with atomic_write(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")


def write_plots(report: dict[str, Any], stem: Path) -> list[Path]:
    """PNG plots beside ``stem`` (``<stem>_sparsification.png``, ...); returns the paths written.

    Uses matplotlib's object API with the Agg canvas (no pyplot, no global backend change): one figure per
    plot, in the order of the report, each drawn only when the report has its numbers.
    Raises ImportError when matplotlib is missing.
    """
    u = report.get("uncertainty") or {}
    figures = [
        ("sparsification", _sparsification_figure(u)),
        ("confusion", _confusion_figure(report.get("classes"))),
        ("height_reliability", _height_reliability_figure(u)),
        ("reliability", _calibration_figure(u)),
    ]
    written: list[Path] = []
    for name, fig in figures:
        if fig is not None:
            path = plot_path(stem, name)
            _save(fig, path)
            written.append(path)
    return written


def _sparsification_figure(u: dict[str, Any]) -> Any:
    """Sparsification curves of each uncertainty layer beside its oracle and random curves, or ``None``."""
    from matplotlib.figure import Figure

    curves = [(k, u[k]["sparsification"]) for k in ("height_std", "class_entropy", "class_mutual_info") if k in u]
    if not curves:
        return None
    fig = Figure(figsize=(4.2 * len(curves), 3.6))
    for i, (key, sp) in enumerate(curves):
        ax = fig.add_subplot(1, len(curves), i + 1)
        f = np.asarray(sp["fractions"], float)
        ax.plot(f, np.asarray(sp["curve"], float), label=f"uncertainty (AUSE {_fmt(sp['ause'])})")
        ax.plot(f, np.asarray(sp["oracle"], float), "--", label="oracle")
        ax.plot(f, np.asarray(sp["random"], float), ":", label=f"random (AURG {_fmt(sp['aurg'])})")
        ax.set_xlabel("fraction of pixels removed")
        ax.set_ylabel("mean error / full-set mean error" if sp["normalised"] else "mean error")
        ax.set_title(key.replace("_", " "))
        ax.legend(fontsize=7)
    return fig


def _confusion_figure(c: dict[str, Any] | None) -> Any:
    """The row-normalised confusion matrix of the classes, or ``None`` without class pixels."""
    from matplotlib.figure import Figure

    if not (c and c["n_pixels"]):
        return None
    cm = np.asarray(c["confusion_matrix"], float)
    norm = cm / np.maximum(cm.sum(1, keepdims=True), 1)
    names = list(c["per_class"])
    size = 2.5 + 0.45 * len(names)
    fig = Figure(figsize=(size + 1, size))
    ax = fig.add_subplot(1, 1, 1)
    im = ax.imshow(norm, vmin=0, vmax=1, cmap="Blues")
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right", fontsize=7)
    ax.set_yticks(range(len(names)), names, fontsize=7)
    ax.set_xlabel("predicted")
    ax.set_ylabel("reference")
    ax.set_title(f"confusion (row-normalised), OA {_fmt(c['overall_accuracy'], pct=True)}")
    fig.colorbar(im, ax=ax, fraction=0.046)
    return fig


def _height_reliability_figure(u: dict[str, Any]) -> Any:
    """Observed vs nominal coverage of the height spread per reference-height bin, or ``None``."""
    from matplotlib.figure import Figure

    strata = (u.get("height_std") or {}).get("strata")
    if not (strata and any(b.get("reliability_observed") for b in strata["bins"])):
        return None
    fig = Figure(figsize=(4.6, 4.2))
    ax = fig.add_subplot(1, 1, 1)
    levels = np.asarray(strata["reliability_levels"], float)
    for b in strata["bins"]:
        obs = b.get("reliability_observed")
        if not obs:
            continue
        lo, hi = b["range_m"]
        label = f"{lo:g}–{hi:g} m" if hi is not None and math.isfinite(hi) else f"≥ {lo:g} m"
        ax.plot(levels, np.asarray(obs, float), marker="o", ms=3,
                label=f"{label} ({_fmt(b.get('share'), pct=True)})")
    ax.plot([0, 1], [0, 1], "k--", label="nominal")
    ax.set_xlabel("nominal probability of the central ±zσ interval")
    ax.set_ylabel("observed share of pixels inside")
    ax.set_title("height spread reliability per reference height")
    ax.legend(fontsize=7)
    return fig


def _calibration_figure(u: dict[str, Any]) -> Any:
    """The class-confidence reliability diagram, or ``None`` without calibration numbers."""
    from matplotlib.figure import Figure

    cal = u.get("calibration")
    if not (cal and cal["n_pixels"]):
        return None
    fig = Figure(figsize=(4.2, 4))
    ax = fig.add_subplot(1, 1, 1)
    edges = np.asarray(cal["bin_edges"], float)
    centres = 0.5 * (edges[1:] + edges[:-1])
    acc = np.array([np.nan if a is None else a for a in cal["accuracy"]], float)
    ax.bar(centres, np.nan_to_num(acc), width=edges[1] - edges[0], edgecolor="k", alpha=0.7, label="accuracy")
    ax.plot([0, 1], [0, 1], "k--", label="perfect calibration")
    ax.set_xlabel("confidence (max class probability)")
    ax.set_ylabel("accuracy")
    ax.set_title(f"reliability, ECE {_fmt(cal['ece'])}")
    ax.legend(fontsize=7)
    return fig


def write_report(report: dict[str, Any], out: str | Path, plots: bool = True) -> Path:
    """Write ``report`` as JSON to ``out``, a Markdown summary beside it and (optionally) PNG plots.

    Adds ``report["plots"]`` (file names written) and a note when matplotlib is missing. Every file goes
    through a staging file renamed into place, the JSON last, so a failed run leaves no partial report;
    plots an earlier report at ``out`` listed and this one does not draw are removed.

    Raises:
        OutputError: the folder cannot be created or written.
    """
    out = Path(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create the folder of ‹out› '{out}' ({exc}); choose a writable location") from exc
    stem = out.with_suffix("")
    old_plots = owned_plots(out)
    report["plots"] = []
    try:
        if plots:
            try:
                report["plots"] = [p.name for p in write_plots(report, stem)]
            except ImportError:
                report["notes"].append("matplotlib is not installed: plots skipped (pip install 'aerialmtl[plot]')")
        write_text_atomic(out.with_suffix(".md"), markdown_summary(report))
        write_text_atomic(out, json.dumps(to_jsonable(report), indent=2, allow_nan=False) + "\n")
        for path in old_plots:
            if path.name not in report["plots"]:
                path.unlink(missing_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot write the report '{out}' ({exc}); choose a writable ‹out›") from exc
    return out


__all__ = ["headline", "markdown_summary", "to_jsonable", "write_plots", "write_report"]
