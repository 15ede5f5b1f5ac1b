"""`aerialmtl predict`: height and land-cover maps (with MC-dropout uncertainty) for whole orthophotos.

A thin command over :func:`aerialmtl.inference.jobs.predict_many` (one process, or many under
``torchrun --nproc_per_node N -m aerialmtl predict ...``).
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, cast

import click

from aerialmtl.cli.options import (
    EngineName,
    compile_option,
    device_option,
    option,
    output_path,
    overwrite_option,
    precision_option,
    quiet_option,
    raster_argument,
    values_for,
)
from aerialmtl.errors import CheckpointError, InputError
from aerialmtl.io.paths import is_local, raster_name, raster_stem

if TYPE_CHECKING:
    from aerialmtl.inference.job import PredictResult

#: Environment variable naming the default checkpoint of `aerialmtl predict`.
MODEL_ENV = "AERIALMTL_MODEL"
#: Folder name suffix of the default prediction folder of one input (``ortho_aerialmtl/``).
OUT_SUFFIX = "_aerialmtl"
#: Default parent folder of several inputs' prediction folders.
MANY_OUT = "aerialmtl_predictions"


def default_out(orthos: tuple[str, ...]) -> Path:
    """The prediction folder when --out is not given.

    One input: ``<stem>_aerialmtl/`` beside a local file, in the current folder for a remote one. Several:
    ``aerialmtl_predictions/`` in the folder that holds them all (the current folder when one is remote),
    laid out as with --out (a sub-folder per input, the mosaics beside them).
    """
    if len(orthos) == 1:
        ortho = orthos[0]
        parent = Path(ortho).parent if is_local(ortho) else Path()
        return parent / f"{raster_stem(ortho)}{OUT_SUFFIX}"
    if all(is_local(o) for o in orthos):
        return Path(os.path.commonpath([Path(o).resolve().parent for o in orthos])) / MANY_OUT
    return Path(MANY_OUT)



def _batch_size(ctx: click.Context, param: click.Parameter, value: str) -> int | Literal["auto"]:
    """``auto`` or a number (the library checks the value)."""
    if value == "auto":
        return "auto"
    try:
        return int(value)
    except ValueError:  # PredictSettings refuses it, naming ‹batch_size›
        return cast(Literal["auto"], value)


def _say_if_start(model: Path) -> None:
    """Say once when ``model`` is a pretrained start (not fine-tuned on real data; prediction.json records it)."""
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.formats.checkpoint import load_checkpoint

    start = load_checkpoint(model)[1].start
    if start is not None:
        click.echo(f"note: '{model}' is the pretrained start '{start}', trained on synthetic scenes only and not "
                   "fine-tuned on real data: a start for fine-tuning, not a map of anywhere (fine-tune it with "
                   f"`aerialmtl train --init {model} --data TILES ...`); prediction.json records it as model.start",
                   err=True)


@click.command(name="predict")
@raster_argument("orthos", library="ortho", nargs=-1, required=True)
@option("--model", "model", envvar=MODEL_ENV, show_envvar=True, library="checkpoint",
        type=click.Path(dir_okay=False, path_type=Path),
        help="Checkpoint (best.pt / last.pt) written by `aerialmtl train` [default: the AERIALMTL_MODEL "
             "environment variable].")
@option("--out", "out", type=output_path(file_okay=False), library="out_dir",
        help="Prediction folder [default: <stem>_aerialmtl/ beside a local ORTHO, in the current folder for a "
             "remote one]; with several orthophotos, one sub-folder per input (file stem) and a "
             "<layer>.mosaic.vrt per layer over all of them [default: aerialmtl_predictions/ in their common "
             "folder, or the current folder if one is remote].")
@option("--mc", type=int, default=None,
        help="MC-dropout samples T (1 = single pass, no uncertainty maps). Default: 30 if the model has dropout.")
@option("--window", "window", library="tile", type=int, default=1024, show_default=True,
        help="Largest window side (pixels, multiple of 32); smaller windows use less memory but recompute more "
             "overlap.")
@option("--tile", "tile_alias", type=int, default=None, hidden=True, help="Deprecated name of --window.")
@option("--overlap", type=int, default=64, show_default=True,
        help="Minimum overlap between neighbouring windows (pixels), blended seamlessly.")
@option("--batch-size", "batch_size", default="auto", show_default=True, callback=_batch_size,
        help="Windows per model call, or 'auto' (from the free GPU memory; 1 on a CPU).")
@option("--engine", type=EngineName(), default="auto", show_default=True,
        help="What runs the model: auto = the engine measured fastest on this kind of CPU (OpenVINO where it is "
             "installed and was not measured slower), torch otherwise (and on CUDA).")
@option("--threads", "threads", default="auto", show_default=True,
        help="Inference threads on a CPU: a number, or auto = the AERIALMTL_THREADS environment variable if set, "
             "else the cores torch sees. OpenVINO splits them into streams that each run their own window, which "
             "keeps a CPU shared with other jobs busy; prediction.json records threads and streams.")
@precision_option(help="auto = bf16 where the hardware has it natively (CUDA; CPUs with AVX-512-BF16 or AMX on "
                       "OpenVINO, with AMX on torch), fp32 elsewhere (CPUs without bf16 units run bf16 far slower).")
@device_option()
@compile_option()
@option("--aoi", type=click.Path(dir_okay=False, path_type=Path), default=None,
        help="GeoJSON polygons: compute only there, nodata elsewhere.")
@option("--probabilities", is_flag=True, help="Also write class_probabilities.tif (K float32 bands).")
@option("--no-calibration", "calibration", is_flag=True, flag_value=False, default=True,
        help="Do not apply the checkpoint's calibration (height map and spread factor fitted on validation).")
@option("--tta", is_flag=True,
        help="Test-time augmentation: also run every window flipped and rotated (8 views) and combine them like "
             "MC samples; height_std then includes their disagreement. 8 times the work.")
@option("--rescale-input", is_flag=True,
        help="When an orthophoto's values do not look like the training images' (e.g. 16-bit on an 8-bit model), "
             "map them linearly onto the training range (mean ± 3 std of a sample) instead of refusing it.")
@option("--seed", type=int, default=0, show_default=True,
        help="Base seed of the per-window MC-dropout masks: the same seed gives the same maps.")
@option("--max-decode-pixels", type=int, default=None,
        help="Bound on the pixels decoded per model call with MC dropout (bounds memory, not results) "
             "[default: by device].")
@option("--reader-threads", type=int, default=2, show_default=True, help="Background threads reading windows.")
@option("--sun", default="auto", show_default=True,
        help="The sun for the shadow layers (shadow.tif, shadow_height.tif): auto = from the acquisition time and "
             "place (--acquired, a STAC item NAME.json beside the orthophoto, or its TIFF DateTime), else the sun "
             "fitted on the training area for an orthophoto of the same flight, else off; AZ,EL in degrees "
             "(azimuth clockwise from true north, elevation); none = off (maps as without the feature).")
@option("--acquired", default=None,
        help="Acquisition time of the orthophoto(s), ISO 8601 (e.g. 2019-06-21T16:45:00Z; no zone = UTC), for "
             "--sun auto.")
@option("--shadow-fusion/--no-shadow-fusion", "shadow_fusion", default=False, show_default=True,
        help="Move the heights of objects the network finds towards the heights their shadows measure, weighted "
             "by both spreads (never outside an object); the disagreement widens height_std. Needs the sun (not "
             "--sun none) and heights with a spread (--mc > 1, --tta, or a model with an aleatoric head); "
             "prediction.json's fusion says whether it was applied to each input.")
@option("--sun-tune", "sun_tune", type=click.IntRange(min=0), default=0, show_default=True, metavar="STEPS",
        help="Before predicting, tune the height decoder for STEPS steps on the orthophotos' own cast shadows: the "
             "shadows of its heights at each input's sun are made to match the shadow layer's (self-supervised, "
             "no reference heights; up to 8 crops of 512 px; 30 steps on one crop take 10-14 s on 2 CPU cores). "
             "30 lowered the validation MAE of pixels >= 2 m on the sample area from 6.94 to 6.69 m; 0 = off "
             "(an option: measured on one area); at most 200. Needs the sun (not --sun none); prediction.json's "
             "sun_tune says what it did.")
@overwrite_option()
@option("--skip-existing", is_flag=True,
        help="Skip inputs whose prediction folder is complete for this run (same model, settings and input, "
             "every layer whole); recompute the others, saying why (resume a job).")
@quiet_option()
def predict(orthos: tuple[str, ...], model: Path | None, out: Path | None, overwrite: bool, skip_existing: bool,
            quiet: bool, tile_alias: int | None = None, **options: Any) -> None:
    """Predict ORTHO [ORTHO...] into Cloud-Optimized GeoTIFFs (height, classes, uncertainties).

    ORTHO is a GeoTIFF, a VRT, a URL (https://, s3://) or a GDAL /vsi... path. With AERIALMTL_MODEL set,
    `aerialmtl predict ortho.tif` writes ortho_aerialmtl/ beside ortho.tif.
    \f

    One option per field of :class:`~aerialmtl.inference.settings.PredictSettings`, found by name (the option's
    own or its ``library=`` name; a field without its option fails here and in tests/test_predict_settings.py):
    click passes them in ``options``; the settings are built once and travel unchanged to the engine.
    """
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.inference.jobs import predict_many
    from aerialmtl.inference.settings import PredictSettings

    if tile_alias is not None:  # "tile" names the training patches of a tile folder only
        warnings.warn("--tile is deprecated for predict: pass --window (the side of the prediction window)",
                      FutureWarning, stacklevel=1)
        options["window"] = tile_alias
    if model is None:
        raise InputError(f"no model given: pass --model RUN/best.pt, or set {MODEL_ENV}=RUN/best.pt once for every "
                         "`aerialmtl predict`")
    default = out is None
    if out is None:
        out = default_out(orthos)
    settings = PredictSettings(**values_for(dataclasses.fields(PredictSettings), options))

    def report(res: PredictResult) -> None:
        t = res.timings
        click.echo(
            f"{raster_name(str(res.ortho))} → {res.out_dir}: "
            f"{res.grid.width}×{res.grid.height} px at {res.grid.gsd:.3g} m, T={res.mc}, "
            f"{res.windows_computed}/{res.windows_total} windows, overlap factor {res.overlap_factor:.2f}, "
            f"{t['total']:.1f} s ({res.megapixels_per_s:.2f} Mpx/s); {_sun(res.sun)}{_tuned(res.sun_tune)}"
            f"files: {', '.join(_written(res))}"
        )

    try:
        _say_if_start(model)
        job = predict_many(orthos, model, out, settings, overwrite=overwrite, skip_existing=skip_existing,
                           on_result=report, progress=not quiet)
    except CheckpointError as exc:  # a model the user did not type here: say where it came from
        source = click.get_current_context().get_parameter_source("model")
        if source is not click.core.ParameterSource.ENVIRONMENT:
            raise
        raise CheckpointError(f"{exc} (this checkpoint comes from the {MODEL_ENV} environment variable: set it "
                              f"to another model, e.g. `export {MODEL_ENV}=RUN/best.pt`, or pass --model)") from exc
    for path in job.skipped:
        click.echo(f"{raster_name(path)}: skipped, its prediction folder is complete (same model, settings, input)")
    if job.ranks.rank == 0:
        for path, why in job.recomputed.items():
            click.echo(f"{raster_name(path)}: recomputed, its earlier prediction folder was not complete for this "
                       f"run: {why}")
    if job.mosaics:
        click.echo(f"mosaics: {', '.join(str(p) for p in job.mosaics.values())}")
    if default and job.ranks.rank == 0:
        click.echo(f"outputs in {out} (the default without --out)")


def _sun(record: dict[str, Any] | None) -> str:
    """The sun of an input's shadow layers and where it came from, for its summary line ('' when the features are
    off for the whole run, or off for this input: its warning said why).
    """
    if not record or record.get("azimuth_deg") is None:
        return ""
    return f"sun {record['azimuth_deg']:.0f}° / {record['elevation_deg']:.0f}° ({record['source']}); "


def _tuned(record: dict[str, Any] | None) -> str:
    """What ``--sun-tune`` did, for the summary line ('' when the run did not tune)."""
    if not record:
        return ""
    crops = f"{record['crops']} crop" + ("s" if record["crops"] != 1 else "")
    return (f"heights tuned on the shadows ({record['steps']} steps, {crops}, shadow match "
            f"{record['shadow_match_before']:.3f} → {record['shadow_match_after']:.3f}); ")


def _written(res: PredictResult) -> list[str]:
    """Every file the prediction folder of ``res`` holds from this run: the layers, their ``.qml`` styles, the
    STAC ``item.json`` and ``prediction.json`` (the order of :func:`~aerialmtl.formats.prediction.folder_files`).
    """
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.formats.prediction import folder_files

    layers = [name for name in res.files if name != "prediction"]  # "prediction" is prediction.json
    return [f for f in folder_files(layers) if (res.out_dir / f).is_file()]
