"""`aerialmtl predict`: height and land-cover maps (with MC-dropout uncertainty) for whole orthophotos.

A thin command over :func:`aerialmtl.inference.jobs.predict_many` (one process, or many under
``torchrun --nproc_per_node N -m aerialmtl predict ...``).
"""

from __future__ import annotations

from pathlib import Path

import click


def _batch_size(value: str) -> int | str:
    """``auto`` or a number (the library checks the value)."""
    try:
        return value if value == "auto" else int(value)
    except ValueError:
        return value


@click.command(name="predict")
@click.argument("orthos", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--model", "model", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Checkpoint (best.pt / last.pt) written by `aerialmtl train`.")
@click.option("--out", "out", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Prediction folder; with several orthophotos, one sub-folder per input (file stem) and "
                   "a <layer>.mosaic.vrt per layer over all of them.")
@click.option("--mc", type=int, default=None,
              help="MC-dropout samples T (1 = single pass, no uncertainty maps). Default: 30 if the model has dropout.")
@click.option("--tile", type=int, default=1024, show_default=True,
              help="Largest window side (pixels, multiple of 32); smaller tiles use less memory but recompute more "
                   "overlap.")
@click.option("--overlap", type=int, default=64, show_default=True,
              help="Minimum overlap between neighbouring windows (pixels), blended seamlessly.")
@click.option("--batch-size", "batch_size", default="auto", show_default=True,
              help="Windows per model call, or 'auto' (from the free GPU memory; 2 on a CPU).")
@click.option("--precision", type=click.Choice(["auto", "bf16", "fp32"]), default="auto", show_default=True,
              help="auto = bf16 autocast on CUDA, fp32 on CPU (CPUs without bf16 units run bf16 far slower).")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True,
              help="Under torchrun, each process uses GPU LOCAL_RANK.")
@click.option("--compile", "compile_", is_flag=True,
              help="torch.compile the model (a warning and the plain model where compiling is unavailable).")
@click.option("--aoi", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="GeoJSON polygons: compute only there, nodata elsewhere.")
@click.option("--probabilities", is_flag=True, help="Also write class_probabilities.tif (K float32 bands).")
@click.option("--overwrite", is_flag=True, help="Replace existing outputs.")
@click.option("--skip-existing", is_flag=True, help="Skip inputs whose prediction folder is complete (resume a job).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def predict(
    orthos: tuple[Path, ...], model: Path, out: Path, mc: int | None, tile: int, overlap: int, batch_size: str,
    precision: str, device: str, compile_: bool, aoi: Path | None, probabilities: bool, overwrite: bool,
    skip_existing: bool, quiet: bool,
) -> None:
    """Predict ORTHO [ORTHO...] into Cloud-Optimized GeoTIFFs (height, classes, uncertainties)."""
    from aerialmtl.inference.jobs import predict_many
    from aerialmtl.inference.predict import PredictResult

    batch = _batch_size(batch_size)

    def report(res: PredictResult) -> None:
        t = res.timings
        click.echo(
            f"{Path(str(res.ortho)).name} → {res.out_dir}: "
            f"{res.grid.width}×{res.grid.height} px at {res.grid.gsd:.3g} m, T={res.mc}, "
            f"{res.windows_computed}/{res.windows_total} windows, overlap factor {res.overlap_factor:.2f}, "
            f"{t['total']:.1f} s ({res.megapixels_per_s:.2f} Mpx/s); "
            f"files: {', '.join(p.name for p in res.files.values())}"
        )

    job = predict_many(
        orthos, model, out, aoi=aoi, overwrite=overwrite, skip_existing=skip_existing, progress=not quiet,
        on_result=report, mc=mc, tile=tile, overlap=overlap, batch_size=batch, precision=precision,
        device=device, probabilities=probabilities, compile=compile_, checkpoint_name=str(model),
    )
    for path in job.skipped:
        click.echo(f"{path.name}: skipped, its prediction folder is complete")
    if job.mosaics:
        click.echo(f"mosaics: {', '.join(str(p) for p in job.mosaics.values())}")
