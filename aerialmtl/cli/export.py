"""`aerialmtl export`: a checkpoint's inference model as ONNX (for QGIS's Deepness plugin and any ONNX
runtime) or as an OpenVINO IR; a thin command over :func:`aerialmtl.inference.export.export_model`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import click

from aerialmtl.cli.options import argument, option, output_path, overwrite_option

if TYPE_CHECKING:  # the library itself only when the command runs: --help stays fast
    from aerialmtl.inference.export import Format, Task


@click.command(name="export")
@argument("checkpoint", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@option("--format", "format_", type=click.Choice(["onnx", "openvino"]), default="onnx", show_default=True,
        library="format", help="onnx: one .onnx file with metadata; openvino: an IR (.xml + .bin).")
@option("--task", type=click.Choice(["all", "height", "height_std", "classes"]), default="all", show_default=True,
        help="all: every output in one file; height: a Deepness Regressor (metres); height_std: the one-pass "
             "spread of a model with an aleatoric head (metres, a Regressor); classes: a Deepness Segmentor "
             "(class probabilities). QGIS's Deepness plugin takes one task per file.")
@option("--tile", type=int, default=512, show_default=True,
        help="Input tile side in pixels (multiple of 32); QGIS plugins cut the map into tiles of this size.")
@option("--overlap", type=int, default=None,
        help="Overlap between tiles in pixels, recorded for QGIS plugins as a percentage of --tile "
             "[default: --tile / 8, 64 px for 512].")
@option("--out", "out", required=True, type=output_path(dir_okay=False),
        help="Output file: model.onnx, or model.xml for OpenVINO (its weights go to model.bin beside it).")
@option("--no-calibration", "no_calibration", is_flag=True, library="calibration",
        help="Leave out the checkpoint's height calibration (applied in the graph by default, as predict does).")
@overwrite_option()
def export(checkpoint: Path, format_: Format, task: Task, tile: int, overlap: int | None, out: Path,
           no_calibration: bool, overwrite: bool) -> None:
    """Export the model of CHECKPOINT (best.pt) for use without aerialmtl, e.g. in QGIS.

    The input is the orthophoto's bands standardised per band ((raw - mean) / std, stored in the file's
    metadata); outputs are height in metres and/or class probabilities. MC-dropout uncertainty is not
    exported. For QGIS (Deepness plugin), export one file per task:

    \b
        aerialmtl export best.pt --task height --out height.onnx
        aerialmtl export best.pt --task classes --out classes.onnx
    """
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.inference.export import export_model

    result = export_model(checkpoint, out, format=format_, task=task, tile=tile,
                          overlap=tile // 8 if overlap is None else overlap, calibration=not no_calibration,
                          overwrite=overwrite)
    kinds = {"height": "Deepness Regressor", "height_std": "Deepness Regressor", "classes": "Deepness Segmentor"}
    kind = kinds.get(result.task, "all tasks in one file")
    bands = len(json.loads(result.metadata["standardization_mean"]))
    click.echo(f"{result.format} model, {kind}: input N×{bands}×{tile}×{tile}, outputs {', '.join(result.outputs)}; "
               f"{', '.join(str(f) for f in result.files)}")
