"""The evaluation report: what ``aerialmtl evaluate`` writes (``--out report.json``).

::

    report.json                  every number (``nan`` → ``null``); ``plots`` lists the PNGs written
    report.md                    a short Markdown summary (same stem as the JSON)
    report_sparsification.png    optional plots (same stem; :data:`PLOT_SUFFIXES`)
    report_confusion.png
    report_reliability.png
    report_height_reliability.png

The JSON path must end in ``.json`` (:func:`report_files` refuses anything else, so the Markdown never
lands on the JSON). Every file is written through a staging file and renamed into place
(:mod:`aerialmtl.io.outputs`), which also replaces a symlink instead of writing through it.
``report.json`` is the proof of what a report owns: ``overwrite`` replaces the report's own file names
and removes plots of an earlier report (listed in its ``plots``) that this one does not draw; other files
beside it are never touched.
"""

from __future__ import annotations

import json
from pathlib import Path

from aerialmtl.errors import InputError

#: The report's suffix.
REPORT_SUFFIX = ".json"
#: The Markdown summary's suffix (beside the JSON, same stem).
SUMMARY_SUFFIX = ".md"
#: Plot kind → file name suffix after the report's stem.
PLOT_SUFFIXES = {"sparsification": "_sparsification.png", "confusion": "_confusion.png",
                 "reliability": "_reliability.png", "height_reliability": "_height_reliability.png"}


def report_files(out: str | Path, plots: bool = True) -> list[Path]:
    """Every file a report at ``out`` may write: the JSON, the Markdown, the plots (when ``plots``).

    Raises:
        InputError: ``out`` does not end in ``.json`` (``param="out"``).
    """
    out = Path(out)
    if out.suffix.lower() != REPORT_SUFFIX:
        raise InputError(f"‹out› must be the report's .json path (report.md and plots go beside it), got '{out}'; "
                         f"pass e.g. ‹out={out.with_suffix(REPORT_SUFFIX).name}›", param="out")
    stem = out.with_suffix("")
    files = [out, out.with_suffix(SUMMARY_SUFFIX)]
    if plots:
        files += [plot_path(stem, kind) for kind in PLOT_SUFFIXES]
    return files


def plot_path(stem: Path, kind: str) -> Path:
    """The PNG of plot ``kind`` for the report with stem ``stem`` (``report`` → ``report_<kind>.png``)."""
    return stem.with_name(stem.name + PLOT_SUFFIXES[kind])


def owned_plots(out: str | Path) -> list[Path]:
    """Plots the report at ``out`` lists as its own (empty when there is no readable report)."""
    out = Path(out)
    try:
        plots = json.loads(out.read_text(encoding="utf-8")).get("plots")
    except (OSError, ValueError, AttributeError):
        return []
    if not isinstance(plots, list):
        return []
    allowed = {p.name for p in report_files(out)[2:]}
    return [out.with_name(str(name)) for name in plots if str(name) in allowed]


__all__ = ["PLOT_SUFFIXES", "REPORT_SUFFIX", "SUMMARY_SUFFIX", "owned_plots", "plot_path", "report_files"]
