"""`aerialmtl synth`: write a procedural, georeferenced synthetic town or city (ortho, DSM, DTM, nDSM, labels)."""

from __future__ import annotations

from pathlib import Path

import click

from aerialmtl.cli.options import argument, overwrite_option


@click.command(name="synth")
@argument("out", type=click.Path(file_okay=False, path_type=Path), library="out_dir")
@click.option("--kind", type=click.Choice(["town", "city"]), default="town", show_default=True,
              help="town: houses, blocks, parks (the demo's scenes); city: towers to 60 m, halls whose roofs look "
                   "like the ground, stadium stands, a leaning (non-true) orthophoto and a random sensor look.")
@click.option("--size", type=click.IntRange(min=32), default=1024, show_default=True,
              help="Width and height of the scene in pixels.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (same seed → same rasters).")
@click.option("--gsd", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="Pixel size in metres.  [default: 0.25 for a town, 0.5 for a city]")
@click.option("--crs", default="EPSG:32631", show_default=True,
              help="Projected CRS of the outputs (metres or feet; --gsd stays in metres).")
@click.option("--origin", type=(float, float), default=(500000.0, 5000000.0), show_default=True,
              metavar="X Y", help="Map coordinates of the upper-left corner.")
@click.option("--lean", type=(float, float), default=None, metavar="MIN MAX",
              help="City: range of tan(view angle) of the orthophoto's lean (0 0: a true orthophoto).  "
                   "[default: 0 0.6]")
@click.option("--plain", is_flag=True, help="City: no sensor look (colour, haze, resampling, blur, noise, JPEG).")
@click.option("--textures", type=(str, str), default=None, metavar="ORTHO NDSM",
              help="City: lay ground textures cut from this orthophoto where this nDSM is near 0 on its surfaces.")
@overwrite_option(help="Replace existing outputs in OUT.")
def synth(out: Path, kind: str, size: int, seed: int, gsd: float | None, crs: str, origin: tuple[float, float],
          lean: tuple[float, float] | None, plain: bool, textures: tuple[str, str] | None, overwrite: bool) -> None:
    """Generate a synthetic town or city in OUT: ortho.tif (RGB), dsm/dtm/ndsm.tif (metres), labels.tif,
    classes.yaml (and for a town buildings.geojson, its true footprints and heights).

    Height is visible in the orthophoto through sun shadows, roof shading (and in a city the lean of tall
    things), so a model can learn both tasks from it. Use it to try `tile`, `train`, `predict` and `evaluate`
    without downloads.
    """
    if kind == "town":
        if lean is not None or plain or textures is not None:
            raise click.BadParameter("--lean, --plain and --textures apply to --kind city only", param_hint="--kind")
        # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
        from aerialmtl.data.synth import synthesize

        result = synthesize(out, size=size, seed=seed, gsd=gsd or 0.25, crs=crs, origin=origin, overwrite=overwrite)
        click.echo(
            f"Wrote a {size}x{size} px synthetic town ({size * (gsd or 0.25):g} m across, seed {seed}) to "
            f"{result.out_dir} in {result.seconds:.1f} s; sun azimuth {result.sun_azimuth:.0f}°, elevation "
            f"{result.sun_elevation:.0f}°"
        )
        return
    _city(out, size, seed, gsd or 0.5, crs, origin, lean, plain, textures, overwrite)


def _city(out: Path, size: int, seed: int, gsd: float, crs: str, origin: tuple[float, float],
          lean: tuple[float, float] | None, plain: bool, textures: tuple[str, str] | None, overwrite: bool) -> None:
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.data.synth import CityStyle, TexturePool, synthesize_city

    style = CityStyle.plain() if plain else CityStyle()
    if lean is not None:
        style = style.with_lean(*lean)
    pool = None if textures is None else TexturePool.from_files(textures[0], textures[1])
    result = synthesize_city(out, size=size, seed=seed, gsd=gsd, crs=crs, origin=origin, style=style,
                             textures=pool, overwrite=overwrite)
    im = result.imaging
    click.echo(
        f"Wrote a {size}x{size} px synthetic city ({size * gsd:g} m across, seed {seed}) to {result.out_dir} in "
        f"{result.seconds:.1f} s; sun azimuth {im.sun_azimuth:.0f}°, elevation {im.sun_elevation:.0f}°; lean "
        f"{im.lean_tan:.2f} towards {im.lean_azimuth:.0f}°"
    )
