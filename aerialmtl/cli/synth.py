"""`aerialmtl synth`: write a procedural, georeferenced synthetic town (ortho, DSM, DTM, nDSM, labels)."""

from __future__ import annotations

from pathlib import Path

import click

from aerialmtl.cli.options import argument, overwrite_option


@click.command(name="synth")
@argument("out", type=click.Path(file_okay=False, path_type=Path), library="out_dir")
@click.option("--size", type=click.IntRange(min=32), default=1024, show_default=True,
              help="Width and height of the scene in pixels.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (same seed → same rasters).")
@click.option("--gsd", type=click.FloatRange(min=0.0, min_open=True), default=0.25, show_default=True,
              help="Pixel size in metres.")
@click.option("--crs", default="EPSG:32631", show_default=True,
              help="Projected CRS of the outputs (metres or feet; --gsd stays in metres).")
@click.option("--origin", type=(float, float), default=(500000.0, 5000000.0), show_default=True,
              metavar="X Y", help="Map coordinates of the upper-left corner.")
@overwrite_option(help="Replace existing outputs in OUT.")
def synth(out: Path, size: int, seed: int, gsd: float, crs: str, origin: tuple[float, float],
          overwrite: bool) -> None:
    """Generate a synthetic town in OUT: ortho.tif (RGB), dsm/dtm/ndsm.tif (metres), labels.tif, classes.yaml,
    buildings.geojson (true footprints and heights).

    Height is visible in the orthophoto through sun shadows and roof shading, so a model can learn
    both tasks from it. Use it to try `tile`, `train`, `predict` and `evaluate` without downloads.
    """
    from aerialmtl.data.synth import synthesize

    result = synthesize(out, size=size, seed=seed, gsd=gsd, crs=crs, origin=origin, overwrite=overwrite)
    click.echo(
        f"Wrote a {size}x{size} px synthetic town ({size * gsd:g} m across, seed {seed}) to {result.out_dir} "
        f"in {result.seconds:.1f} s; sun azimuth {result.sun_azimuth:.0f}°, elevation {result.sun_elevation:.0f}°"
    )
