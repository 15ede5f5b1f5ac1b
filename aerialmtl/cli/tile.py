"""`aerialmtl tile`: cut an orthophoto plus height and/or label layers into training patches."""

from __future__ import annotations

from pathlib import Path

import click

from aerialmtl.cli.options import option, output_path, overwrite_option, quiet_option, raster_option

_FILE = click.Path(exists=True, dir_okay=False, path_type=Path)


def _int_list(ctx: click.Context, param: click.Parameter, value: str | None) -> list[int] | None:
    if value is None:
        return None
    try:
        out = [int(v) for v in value.split(",") if v.strip()]
    except ValueError:
        raise click.BadParameter(f"expected comma-separated 1-based band numbers like 1,2,3, got {value!r}", ctx,
                                 param) from None
    if not out or any(b < 1 for b in out):
        raise click.BadParameter(f"expected 1-based band numbers like 1,2,3, got {value!r}", ctx, param)
    return out


def _ratios(ctx: click.Context, param: click.Parameter, value: str) -> tuple[float, float, float]:
    try:
        r = tuple(float(v) for v in value.split(","))
    except ValueError:
        r = ()
    if len(r) != 3 or any(x < 0 for x in r) or sum(r) <= 0:
        raise click.BadParameter(
            f"expected three non-negative numbers train,val,test like 0.7,0.15,0.15, got {value!r}", ctx, param)
    return r


def _aoi(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> str | dict[str, str] | None:
    if not values:
        return None
    if len(values) == 1 and "=" not in values[0]:
        path = values[0]
        if not Path(path).is_file():
            raise click.BadParameter(f"file {path!r} does not exist", ctx, param)
        return path
    out: dict[str, str] = {}
    for v in values:
        name, sep, path = v.partition("=")
        if not sep or name not in ("train", "val", "test") or not Path(path).is_file():
            raise click.BadParameter(
                f"expected one GeoJSON with a 'split' property, or SPLIT=FILE per split (train=a.geojson), got {v!r}",
                ctx, param)
        out[name] = path
    return out


@click.command(name="tile")
@raster_option("--ortho", required=True, help="Orthophoto; defines the reference grid.")
@raster_option("--dsm", help="Digital surface model; needs --dtm.")
@raster_option("--dtm", help="Digital terrain model; needs --dsm.")
@raster_option("--ndsm", help="Ready heights above ground (nDSM/CHM) instead of --dsm/--dtm.")
@click.option("--z-unit", type=click.Choice(["m", "ft", "us-ft"]), default=None,
              help="Unit of the DSM/DTM/nDSM values when a file does not state it (its vertical CRS or band unit) "
                   "[default: m]. Heights are always written in metres.")
@raster_option("--labels", help="Label raster of raw class codes.")
@click.option("--labels-vector", type=_FILE, help="GeoJSON label polygons (EPSG:4326 unless it has a 'crs').")
@click.option("--class-field", help="Attribute of --labels-vector holding class codes or names.")
@click.option("--classes", "classes", help="Class scheme YAML, or a built-in name: dfc2018, isprs, synthetic.")
@click.option("--size", default=320, show_default=True, type=click.IntRange(min=1), help="Patch size (pixels).")
@click.option("--stride", type=click.IntRange(min=1), help="Step between patches (pixels) [default: --size].")
@click.option("--gsd", type=float, help="Resample every layer to this pixel size in metres (also for feet CRSs).")
@click.option("--min-valid", default=0.9, show_default=True, type=click.FloatRange(0, 1),
              help="Keep patches with at least this fraction of valid image pixels.")
@option("--split-block", default=100.0, show_default=True, type=float, library="block_size",
              help="Split block side in metres, snapped to a whole number of patch strides.")
@option("--split-ratios", default="0.7,0.15,0.15", show_default=True, callback=_ratios, library="ratios",
              help="Fractions of blocks for train,val,test.")
@option("--split-seed", default=0, show_default=True, type=int, library="seed", help="Seed of the block shuffle.")
@option("--split-aoi", multiple=True, callback=_aoi, library="aoi",
              help="AOI polygons instead of blocks: one GeoJSON with a 'split' property, or SPLIT=FILE (repeat).")
@click.option("--bands", callback=_int_list, help="1-based ortho bands to keep, e.g. 1,2,3 [default: all but alpha].")
@click.option("--clip-negative/--no-clip-negative", default=True, show_default=True,
              help="Set negative heights above ground to 0.")
@click.option("--max-height", type=float, help="Treat heights above this (metres) as invalid.")
@click.option("--ignore-unknown-codes", is_flag=True, help="Label codes outside the scheme become 'no label'.")
@option("--out", "out", required=True, type=output_path(file_okay=False), library="out_dir",
        help="Output folder.")
@overwrite_option(help="Replace an existing tile dataset in --out.")
@quiet_option()
def tile(ortho: str, dsm: str | None, dtm: str | None, ndsm: str | None, z_unit: str | None, labels: str | None,
         labels_vector: Path | None, class_field: str | None, classes: str | None, size: int, stride: int | None,
         gsd: float | None, min_valid: float, split_block: float, split_ratios: tuple[float, float, float],
         split_seed: int, split_aoi: str | dict[str, str] | None, bands: list[int] | None, clip_negative: bool,
         max_height: float | None, ignore_unknown_codes: bool, out: Path, overwrite: bool, quiet: bool) -> None:
    """Cut ORTHO and aligned height/label layers into patches with spatial train/val/test splits.

    Writes OUT/{train,val,test}/{image,height,classes}/*.tif, OUT/manifest.csv and OUT/dataset.yaml.
    \f

    One parameter per command-line option: click passes each option to the command.
    """
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.io.align import NdsmOptions
    from aerialmtl.tiling.splits import SplitSpec
    from aerialmtl.tiling.tile import TileOptions, tile_dataset

    if split_aoi is not None:
        spec = SplitSpec(method="aoi", aoi=split_aoi)
    else:
        spec = SplitSpec(method="blocks", block_size=split_block, ratios=split_ratios, seed=split_seed)
    result = tile_dataset(
        ortho, out, dsm=dsm, dtm=dtm, ndsm=ndsm, labels=labels, labels_vector=labels_vector,
        class_field=class_field, classes=classes, overwrite=overwrite, progress=not quiet,
        options=TileOptions(
            size=size, stride=stride, gsd=gsd, min_valid=min_valid, splits=spec, bands=bands,
            heights=NdsmOptions(clip_negative=clip_negative, max_height=max_height, z_unit=z_unit),
            ignore_unknown_codes=ignore_unknown_codes),
    )
    total = sum(result.counts.values())
    click.echo(f"{total} patches ({', '.join(f'{k} {v}' for k, v in result.counts.items())}) "
               f"of {result.windows} windows; dropped {result.dropped_invalid} with < {min_valid:g} valid pixels, "
               f"{result.dropped_split} straddling splits")
    click.echo(f"tasks: {', '.join(result.tasks)}")
    if result.height_summary:  # does validation look like training? (README: "Training on a small area")
        click.echo("heights: " + "; ".join(
            f"{k} mean {v['mean_m']:.2f} m, {100 * v['tall_share']:.0f} % of pixels ≥ 2 m"
            for k, v in result.height_summary.items()))
    click.echo(f"manifest: {result.manifest}")
    click.echo(f"dataset:  {result.dataset_yaml}")
    if total == 0:
        click.echo("warning: no patch was written; lower --min-valid or --split-block, or check the layers' overlap",
                   err=True)
    elif result.counts["train"] == 0:
        click.echo("warning: no train patch; normalisation statistics are missing (adjust the splits)", err=True)
    empty = [k for k, r in zip(("train", "val", "test"), split_ratios) if r > 0 and result.counts[k] == 0]
    if total and empty and split_aoi is None:
        blocks = f"split blocks of {result.block_size_m:.4g} m ({result.block_patches}×{result.block_patches} patches)"
        if (result.block_patches or 1) > -(-size // (stride or size)):
            fix = "lower --split-block to get more blocks"
        else:  # already the smallest block that holds a patch
            fix = "the area holds too few blocks for these ratios: give a larger area, or other --split-ratios"
        click.echo(f"warning: no {'/'.join(empty)} patch: {blocks} are too few here; {fix}", err=True)
