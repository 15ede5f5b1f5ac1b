"""``aerialmtl demo``: the whole pipeline on embedded synthetic towns (no data, no download)."""

from __future__ import annotations

import textwrap
from pathlib import Path

import click

from aerialmtl.cli.options import overwrite_option


@click.command(name="demo")
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@click.option("--train-steps", type=click.IntRange(min=1), default=800, show_default=True,
              help="Training budget in optimizer steps (fixed, so the load does not change the model; another CPU "
                   "kind or thread count rounds floats in another order, and the defaults' numbers then stay "
                   "inside the band printed, measured on AVX-512 and AVX2 kernels with 1 and 2 threads).")
@click.option("--train-seconds", type=click.FloatRange(min=1), default=None,
              help="Optional wall-clock cap on top of --train-steps (a capped run is no longer comparable).")
@click.option("--train-size", type=click.IntRange(min=256), default=1536, show_default=True,
              help="Side of the synthetic training town in pixels (0.25 m).")
@click.option("--test-size", type=click.IntRange(min=128), default=768, show_default=True,
              help="Side of the synthetic test town in pixels.")
@click.option("--mc", type=click.IntRange(min=1), default=16, show_default=True, help="MC-dropout samples.")
@overwrite_option(help="Reuse a non-empty OUT folder.")
def demo(out: Path, train_steps: int, train_seconds: float | None, train_size: int, test_size: int, mc: int,
         overwrite: bool) -> None:
    """Synthesize a training and a test town, tile, train the small D3-Net, predict with MC dropout,
    evaluate, and write GeoTIFFs, a report and PNG previews into OUT.
    """
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.demo import EXPECTED, EXPECTED_BAND, DemoSettings, run_demo

    settings = DemoSettings(train_size=train_size, test_size=test_size, train_steps=train_steps,
                            train_seconds=train_seconds, mc=mc)
    res = run_demo(out, settings, overwrite=overwrite, log=lambda m: click.echo(m, err=True))
    rep = res.report
    h = rep.get("height", {})
    c = rep.get("classes", {})
    click.echo("")
    click.echo(f"Done in {res.timings.get('total', 0):.0f} s. Test town results:")
    got = {"height MAE (m)": h.get("mae"), "height RMSE (m)": h.get("rmse"),
           "classes OA": c.get("overall_accuracy"), "classes mIoU": c.get("miou")}
    defaults = settings == DemoSettings()
    for key, value in got.items():
        if value is None:
            continue
        line = f"  {key:<16} {value:.3f}"
        if defaults:  # what the defaults gave when measured, and whether this run is within the band
            ok = abs(value - EXPECTED[key]) <= EXPECTED_BAND[key]
            line += (f"   expected {EXPECTED[key]:.3f} ± {EXPECTED_BAND[key]:g}"
                     f"{'' if ok else '  <- outside the expected band'}")
        click.echo(line)
    click.echo("Outputs:")
    for name, path in res.paths.items():
        click.echo(f"  {name:<11} {path}")
        if name == "prediction":  # every file it holds, the shadow layers included where the sun was known
            files = sorted(p.name for p in path.iterdir() if p.is_file())
            maps = [f for f in files if f.endswith(".tif")]
            click.echo(_listing("", ", ".join(maps) + " (each with its QGIS style, .qml)"))
            records = [f for f in files if not f.endswith((".tif", ".qml"))]
            if records:
                click.echo(_listing("", ", ".join(records)))
        if name == "summary" and rep.get("plots"):  # evaluate's plots, beside its report
            click.echo(_listing("plots", ", ".join(Path(p).name for p in rep["plots"])))
    click.echo("Open prediction/*.tif in QGIS next to data/test_town/ortho.tif.")


def _listing(label: str, text: str) -> str:
    """``text`` under the Outputs list's ``label``, wrapped at 80 columns in the list's second column."""
    return textwrap.fill(text, width=80, initial_indent=f"  {label:<11} ", subsequent_indent=" " * 14,
                         break_on_hyphens=False, break_long_words=False)
