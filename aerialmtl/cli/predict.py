"""`aerialmtl predict`: height and land-cover maps (with MC-dropout uncertainty) for whole orthophotos.

A thin command over :func:`aerialmtl.inference.predict.predict_raster`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

if TYPE_CHECKING:
    from aerialmtl.formats.checkpoint import ModelMeta


def _check_input(ortho: Path, meta: ModelMeta) -> None:
    """Georeferencing and bands of ``ortho`` against the checkpoint (errors name the file and the fix).

    Run for every input before the first prediction starts, so a bad last input fails at once; bands
    beyond the trained ones are reported (with a warning) by ``predict_raster`` itself.
    """
    from aerialmtl.io.align import check_bands, open_raster, reference_grid

    reference_grid(ortho)  # readable, with a CRS and a north-up geotransform
    trained = f"bands {list(meta.bands)}" + (f" ({', '.join(meta.band_names)})" if meta.band_names else "")
    with open_raster(ortho, "orthophoto") as src:
        check_bands(src, meta.bands, "orthophoto", bands_from=f"the checkpoint (trained on {trained})",
                    fix="predict on an orthophoto with those bands, or train a model on this one's bands "
                        "(`aerialmtl tile --bands ...`)")


@click.command(name="predict")
@click.argument("orthos", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--model", "model", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Checkpoint (best.pt / last.pt) written by `aerialmtl train`.")
@click.option("--out", "out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Prediction folder; with several orthophotos, one sub-folder per input (file stem).")
@click.option("--mc", type=int, default=None,
              help="MC-dropout samples T (1 = single pass, no uncertainty maps). Default: 30 if the model has dropout.")
@click.option("--tile", type=int, default=1024, show_default=True,
              help="Largest window side (pixels, multiple of 32); smaller tiles use less memory but recompute more overlap.")
@click.option("--overlap", type=int, default=64, show_default=True,
              help="Minimum overlap between neighbouring windows (pixels), blended seamlessly.")
@click.option("--batch-size", type=int, default=2, show_default=True, help="Windows per model call.")
@click.option("--precision", type=click.Choice(["auto", "bf16", "fp32"]), default="auto", show_default=True,
              help="auto = bf16 autocast on CUDA, fp32 on CPU (CPUs without bf16 units run bf16 far slower).")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True)
@click.option("--aoi", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="GeoJSON polygons: compute only there, nodata elsewhere.")
@click.option("--probabilities", is_flag=True, help="Also write class_probabilities.tif (K float32 bands).")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def predict(
    orthos: tuple[Path, ...], model: Path, out: Path, mc: int | None, tile: int, overlap: int, batch_size: int,
    precision: str, device: str, aoi: Path | None, probabilities: bool, overwrite: bool, quiet: bool,
) -> None:
    """Predict ORTHO [ORTHO...] into Cloud-Optimized GeoTIFFs (height, classes, uncertainties)."""
    from aerialmtl.formats.checkpoint import load_model
    from aerialmtl.inference.predict import predict_raster
    from aerialmtl.inference.writer import check_outputs_free

    if mc is not None and mc < 1:
        raise click.BadParameter(f"must be ≥ 1 (1 = single pass), got {mc}", param_hint="--mc")
    if tile < 32 or tile % 32:
        raise click.BadParameter(f"must be a positive multiple of 32, got {tile}; try 512", param_hint="--tile")
    if not 0 <= overlap <= tile // 2:
        raise click.BadParameter(f"must be between 0 and --tile/2 = {tile // 2}, got {overlap}; try 64",
                                 param_hint="--overlap")
    if batch_size < 1:
        raise click.BadParameter(f"must be ≥ 1, got {batch_size}", param_hint="--batch-size")
    stems = [p.stem for p in orthos]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if len(orthos) > 1 and dup:
        raise click.BadParameter(f"several inputs share the file stem(s) {dup}, so their sub-folders would clash; "
                                 "rename them or run predict once per input", param_hint="ORTHOS")
    targets = [(p, out if len(orthos) == 1 else out / p.stem) for p in orthos]
    if not overwrite:  # refuse before spending time on the first input
        for _, d in targets:
            check_outputs_free(d, ["height.tif", "classes.tif", "prediction.json"], overwrite=False)
    loaded = load_model(model)
    for ortho in orthos:  # every input usable before the first one takes time
        _check_input(ortho, loaded[1])
    for ortho, target in targets:
        res = predict_raster(
            ortho, loaded, target, mc=mc, tile=tile, overlap=overlap, batch_size=batch_size,
            precision=precision, device=device, aoi=aoi, probabilities=probabilities, overwrite=overwrite,
            progress=not quiet, checkpoint_name=str(model),
        )
        t = res.timings
        click.echo(
            f"{ortho.name} → {target}: {res.grid.width}×{res.grid.height} px at {res.grid.gsd:.3g} m, T={res.mc}, "
            f"{res.windows_computed}/{res.windows_total} windows, overlap factor {res.overlap_factor:.2f}, "
            f"{t['total']:.1f} s ({res.megapixels_per_s:.2f} Mpx/s); files: {', '.join(p.name for p in res.files.values())}"
        )
