"""`aerialmtl buildings`: LoD1 building models (footprints, heights, uncertainty) from a prediction folder."""

from __future__ import annotations

from pathlib import Path

import click

from aerialmtl.cli.options import output_path, overwrite_option, quiet_option, raster_option
from aerialmtl.errors import InputError


@click.command(name="buildings")
@click.argument("pred_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--out", "outputs", multiple=True, required=True, type=output_path(dir_okay=False),
              help="Output file, repeatable; the format follows the name: .gpkg (GeoPackage), .geojson (GeoJSON), "
                   ".city.json (CityJSON LoD1 solids).")
@raster_option("--dtm",
               help="Terrain model (metres, any CRS/GSD): ground elevation per building; CityJSON solids stand on it "
                   "instead of z = 0.")
@click.option("--building-class", "building_classes", multiple=True, metavar="NAME|INDEX",
              help="Class that is a building, repeatable [default: the classes named 'building(s)' in the scheme "
                   "stored in classes.tif].")
@click.option("--min-area", type=click.FloatRange(min=0), default=10.0, show_default=True,
              help="Drop buildings smaller than this (m²).")
@click.option("--max-hole", type=click.FloatRange(min=0), default=10.0, show_default=True,
              help="Fill holes smaller than this (m²); larger ones (courtyards) are kept.")
@click.option("--simplify", type=click.FloatRange(min=0), default=None,
              help="Simplification tolerance (metres) [default: 1.5 pixels].")
@click.option("--no-orthogonal", is_flag=True, help="Do not square the outlines onto their main direction.")
@click.option("--height-step", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Split touching buildings where the height jumps by at least this (metres) [default: never].")
@click.option("--height-percentile", type=click.FloatRange(0, 100), default=50.0, show_default=True,
              help="Percentile of the pixel heights reported as height_m (50 = median).")
@click.option("--block-size", type=click.IntRange(min=64), default=1024, show_default=True,
              help="Side of the blocks read at once (pixels); memory grows with its square.")
@overwrite_option()
@quiet_option()
def buildings(pred_dir: Path, outputs: tuple[Path, ...], dtm: str | None, building_classes: tuple[str, ...],
              min_area: float, max_hole: float, simplify: float | None, no_orthogonal: bool,
              height_step: float | None, height_percentile: float, block_size: int, overwrite: bool,
              quiet: bool) -> None:
    """Building footprints with height, height uncertainty, area, volume and class confidence from PRED_DIR.

    PRED_DIR is a folder written by `aerialmtl predict` with classes.tif and height.tif (height_std.tif and
    class_entropy.tif give the uncertainty attributes). Outputs are in the prediction's CRS; areas and
    heights are in metres whatever its unit.

    Example: aerialmtl buildings pred/ --out buildings.gpkg --out buildings.city.json
    \f

    One parameter per command-line option: click passes each option to the command.
    """
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.buildings import BuildingLayers, BuildingOptions, building_class_indices, write_buildings
    from aerialmtl.buildings.export import output_format

    if not pred_dir.is_dir():
        raise click.BadParameter(f"folder '{pred_dir}' does not exist; pass the --out folder of `aerialmtl predict`",
                                 param_hint="PRED_DIR")
    for out in outputs:
        try:
            output_format(out)
        except InputError as exc:
            raise click.BadParameter(str(exc), param_hint="--out") from None
    with BuildingLayers(pred_dir) as layers:  # the building classes are checked before the (long) extraction
        try:
            building_class_indices(layers.scheme, building_classes or None)
        except InputError as exc:
            text = str(exc).replace("building_classes: ", "").replace("building_classes", "--building-class")
            raise click.BadParameter(text, param_hint="--building-class") from None
    options = BuildingOptions(min_area_m2=min_area, max_hole_m2=max_hole, simplify_m=simplify,
                              orthogonal=not no_orthogonal, height_step_m=height_step,
                              height_percentile=height_percentile, block_size=block_size)
    result = write_buildings(pred_dir, outputs, options, dtm=dtm, building_classes=building_classes or None,
                             overwrite=overwrite, progress=not quiet)
    s = result.stats
    click.echo(f"{result.count} buildings (classes: {', '.join(s.building_classes)}) from {s.building_pixels} "
               f"building pixels in {s.blocks} blocks; {s.too_small} smaller than {min_area:g} m² dropped; "
               f"{result.seconds:.1f} s")
    for path, fmt in result.outputs.items():
        click.echo(f"{fmt}: {path} ({result.crs})")
