"""`aerialmtl evaluate`: compare a prediction folder with reference heights and/or labels."""

from __future__ import annotations

import math
import os
from pathlib import Path

import click

from aerialmtl.cli.options import option, output_path, overwrite_option, quiet_option, raster_option
from aerialmtl.errors import OutputError


def _parse_bins(ctx: click.Context, param: click.Parameter, value: str | None) -> tuple[float, ...]:
    if value is None:
        from aerialmtl.evaluation.metrics import DEFAULT_HEIGHT_BINS  # torch: imported only when the command runs

        return DEFAULT_HEIGHT_BINS
    try:
        edges = tuple(math.inf if v.strip().lower() in ("inf", "infinity") else float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter(f"expected comma-separated metres like '0,1,2,5,10,20,inf', got {value!r}", ctx,
                                 param) from None
    if len(edges) < 2 or any(b <= a for a, b in zip(edges, edges[1:])):
        raise click.BadParameter(f"need at least 2 increasing edges, got {value!r}", ctx, param)
    return edges


def _check_writable(folder: Path) -> None:
    """Fail before the (long) evaluation if the report's folder cannot be created or written."""
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        what = "is a file" if probe.exists() and not probe.is_dir() else "is not writable"
        raise OutputError(f"cannot write the report into '{folder}': '{probe}' {what}; choose a writable --out")


@click.command(name="evaluate")
@option("--pred", "pred", required=True, library="pred_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Prediction folder written by `aerialmtl predict`.")
@raster_option("--height", "height_ref",
               help="Reference nDSM (heights above ground); any CRS/GSD, reprojected onto the prediction grid.")
@raster_option("--dsm", "dsm_ref",
               help="Reference DSM, with --dtm, instead of --height: the reference is DSM − DTM (negatives → 0).")
@raster_option("--dtm", "dtm_ref", help="Reference DTM (with --dsm).")
@click.option("--z-unit", type=click.Choice(["m", "ft", "us-ft"]), default=None,
              help="Unit of the reference heights when a file does not state it [default: m].")
@raster_option("--labels", "labels_ref", help="Reference label raster (raw class codes); any CRS/GSD.")
@click.option("--buildings", "buildings_ref", type=click.Path(dir_okay=False, path_type=Path),
              help="Reference building footprints with a height_m field (e.g. buildings.geojson of `aerialmtl synth`).")
@click.option("--pred-buildings", type=click.Path(dir_okay=False, path_type=Path),
              help="Footprints from `aerialmtl buildings` to score against --buildings [default: extracted from "
                   "--pred with the default settings].")
@click.option("--classes", "classes", type=str, default=None,
              help="Class scheme YAML or built-in name; default: the scheme stored in classes.tif.")
@click.option("--height-threshold", type=float, default=1.0, show_default=True,
              help="δ accuracies use pixels whose reference height is above this (metres).")
@click.option("--height-bins", callback=_parse_bins, default=None,
              help="Reference-height bin edges in metres for per-bin errors [default: 0,1,2,5,10,20,inf].")
@click.option("--ignore-unknown-codes", is_flag=True, help="Treat label codes missing from the scheme as no label.")
@click.option("--sample-size", type=int, default=2_000_000, show_default=True,
              help="Max pixels of the seeded subsample for median, AUSE/AURG and Spearman.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of that subsample.")
@click.option("--no-plots", is_flag=True, help="Do not write PNG plots.")
@click.option("--out", "out", required=True, type=output_path(dir_okay=False),
              help="Report JSON path; report.md and PNG plots are written beside it.")
@overwrite_option(help="Replace an existing report.")
@quiet_option()
def evaluate(pred: Path, height_ref: str | None, dsm_ref: str | None, dtm_ref: str | None, z_unit: str | None,
             labels_ref: str | None, buildings_ref: Path | None, pred_buildings: Path | None, classes: str | None,
             height_threshold: float, height_bins: tuple[float, ...], ignore_unknown_codes: bool,
             sample_size: int, seed: int, no_plots: bool, out: Path, overwrite: bool, quiet: bool) -> None:
    """Accuracy of heights and classes, and quality of their uncertainties, in a JSON + Markdown report.

    Example: aerialmtl evaluate --pred pred/ --height ndsm.tif --labels gt.tif --out eval/report.json
    \f

    One parameter per command-line option: click passes each option to the command.
    """
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.evaluation.evaluate import EvaluateOptions, evaluate_prediction
    from aerialmtl.evaluation.report import headline

    if height_ref is None and dsm_ref is None and labels_ref is None and buildings_ref is None:
        raise click.UsageError("give at least one reference: --height NDSM.tif (or --dsm with --dtm) and/or "
                               "--labels LABELS.tif and/or --buildings FOOTPRINTS")
    _check_writable(out.parent)
    report = evaluate_prediction(
        pred, height_ref=height_ref, labels_ref=labels_ref, dsm_ref=dsm_ref, dtm_ref=dtm_ref, classes=classes,
        out=out, overwrite=overwrite, progress=not quiet, buildings_ref=buildings_ref, pred_buildings=pred_buildings,
        options=EvaluateOptions(z_unit=z_unit, height_threshold=height_threshold, height_bins=height_bins,
                                ignore_unknown_codes=ignore_unknown_codes, sample_size=sample_size, seed=seed,
                                plots=not no_plots),
    )
    width = max((len(k) for k, _ in headline(report)), default=0)
    for key, value in headline(report):
        click.echo(f"{key:<{width}}  {value}")
    for note in report["notes"]:
        click.echo(f"note: {note}")
    click.echo(f"report: {out} (+ {out.with_suffix('.md').name}"
               + "".join(f", {p}" for p in report.get("plots", [])) + ")")
