"""`aerialmtl train`: train a D3-Net on a tile folder (thin wrapper over :func:`aerialmtl.training.loop.train`).

Under ``torchrun`` every process runs this command; the run-folder policy (``--resume``, ``--overwrite``,
who prepares the folder) is the library's (:func:`aerialmtl.training.run_folder.check_run_folder`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from aerialmtl.cli.options import (
    compile_option,
    device_option,
    option,
    output_path,
    overwrite_option,
    precision_option,
    quiet_option,
)
from aerialmtl.errors import CheckpointError

if TYPE_CHECKING:
    from aerialmtl.training.trainer import TrainResult


@click.command(name="train")
@option("--config", "config_path", library="config", type=click.Path(dir_okay=False, path_type=Path),
              help="Training YAML (e.g. configs/d3net_small_synth.yaml). With --resume, defaults to RUN/config.yaml.")
@click.option("--data", "data_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Tile folder written by `aerialmtl tile` (overrides data.dir of the config).")
@click.option("--out", "out_dir", type=output_path(file_okay=False), default=Path("runs/train"),
              show_default=True, help="Run folder for last.pt, best.pt, log.csv and config.yaml.")
@click.option("--max-steps", type=int, help="Stop after this many optimisation steps in total.")
@option("--max-time", "max_time", type=float, library="max_time_s", help="Wall-clock budget of this call in seconds.")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its last.pt (any number of processes).")
@option("--init", "init_ckpt", type=click.Path(dir_okay=False, path_type=Path), library="init",
              help="Start from the weights of this aerialmtl checkpoint, or of the pretrained start of this name "
                   "shipped with the package (fine-tuning); task heads of other classes or tasks start afresh.")
@device_option(default=None, help="Overrides the config's device.")
@precision_option(default=None, help="Overrides the config's precision (auto: bf16 autocast on a GPU, fp32 on a CPU).")
@compile_option("compile_model")
@overwrite_option(help="Replace the run in --out (its last.pt, best.pt, log.csv, config.yaml; other files are kept).")
@quiet_option()
def train(config_path: Path | None, data_dir: Path | None, out_dir: Path, max_steps: int | None,
          max_time: float | None, resume: bool, init_ckpt: Path | None, device: str | None, precision: str | None,
          compile_model: bool, overwrite: bool, quiet: bool) -> None:
    """Train the multi-task D3-Net (height + land cover) on patches made by `aerialmtl tile`.

    Writes RUN/last.pt (every validation and at the end), RUN/best.pt (best validation score; the one to
    predict with), RUN/log.csv and RUN/config.yaml. A run stopped by --max-time or --max-steps continues
    with --resume. On N GPUs or machines, start it with torchrun (data.batch_size is then per process):

    \b
        torchrun --nproc_per_node N -m aerialmtl train --config C --data D --out RUN
    \f

    One parameter per command-line option: click passes each option to the command.
    """
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.formats.run import RunFolder
    from aerialmtl.runtime import Torchrun
    from aerialmtl.training.config import load_train_config
    from aerialmtl.training.distributed import install_stop_handler
    from aerialmtl.training.loop import check_budget
    from aerialmtl.training.loop import train as train_loop
    from aerialmtl.training.run_folder import check_run_folder

    check_budget(max_steps, max_time)  # before the run folder is touched
    # the option pairs (--resume with --overwrite or --init) first: the library's refusal names both options
    check_run_folder(out_dir, resume, overwrite, init_ckpt)  # before the config is read: says what is wrong first
    if init_ckpt is not None:  # a checkpoint file, or the name of a start shipped with the package
        # when the command runs (CLI start time)
        from aerialmtl.formats.starts import resolve_start

        try:
            init_ckpt = resolve_start(init_ckpt)
        except CheckpointError as exc:
            raise click.BadParameter(str(exc).removeprefix("init: "), param_hint="--init") from exc
    if resume and config_path is None:
        config_path = RunFolder(out_dir).config
    if config_path is None:
        raise click.BadParameter("pass a training YAML, e.g. configs/d3net_small_synth.yaml", param_hint="--config")

    cfg = load_train_config(config_path)
    overrides: dict[str, object] = {k: v for k, v in (("device", device), ("precision", precision)) if v is not None}
    if compile_model:
        overrides["compile"] = True
    if overrides:
        cfg = cfg.with_overrides(**overrides)
    process = Torchrun.from_env()
    if process.distributed:
        install_stop_handler()
    result = train_loop(cfg, data_dir=data_dir, out_dir=out_dir, max_steps=max_steps, max_time_s=max_time,
                        resume=resume, progress=not quiet, init=init_ckpt, overwrite=overwrite)
    if not process.is_main:
        return
    last = _scores(result.metrics)
    click.echo(f"stopped by {result.stopped_by} after {result.step} steps ({result.epoch} epochs, "
               f"{result.elapsed_s:.0f} s)" + (f"; last validation (step {result.step}, last.pt): {last}"
                                                if last else ""))
    click.echo(f"best checkpoint: {result.best_checkpoint} ({_chosen_on(result)})")
    if Path(result.best_checkpoint).is_file():
        # when the command runs (CLI start time)
        from aerialmtl.formats.checkpoint import load_checkpoint

        best_meta = load_checkpoint(result.best_checkpoint)[1]
        calibration = best_meta.calibration
        if calibration is not None:  # what validation kept, and why (predict applies exactly this)
            click.echo(f"calibration of best.pt (its scores: best.pt on the same validation patches, mean of "
                       f"{cfg.calibration.mc_samples} MC-dropout samples): {calibration.summary()}")
            if calibration.unsupported:  # the one thing a small or unlucky split must be told plainly
                click.echo(f"warning: calibration: {calibration.unsupported}; to calibrate these heights give "
                           "validation taller areas (aerialmtl tile --split-block, --split-ratios or --split-aoi)",
                           err=True)
        if best_meta.sun is not None:  # the training area's sun (predict --sun auto uses it for the same flight)
            click.echo(f"training area's {best_meta.sun.summary()}" + (
                "" if best_meta.sun.clear else "; predict writes no shadow layers"))
    click.echo(f"last checkpoint: {result.last_checkpoint}")
    click.echo(f"log: {result.log_path}")


def _scores(metrics: dict[str, float]) -> str:
    """Validation scores as one phrase: ``height MAE 3.304 m, RMSE 5.12 m, OA 0.912, mIoU 0.61``."""
    names = (("height_mae", "height MAE", " m"), ("height_rmse", "RMSE", " m"), ("oa", "OA", ""),
             ("miou", "mIoU", ""))
    return ", ".join(f"{label} {metrics[k]:.4g}{unit}" for k, label, unit in names if k in metrics)


def _chosen_on(result: TrainResult) -> str:
    """What ``best.pt`` was chosen on: the metric, its value and step, and what validation's heights rest on."""
    score = result.best_metrics.get("score", result.best_score)
    if result.best_step is None:  # best.pt is from before a resume and stayed the best
        return f"kept from before this call: the run's lowest score, {score:.4g}"
    if not any(k.startswith("val_loss_") for k in result.best_metrics):  # no val split
        return f"the lowest training loss between checks: step {result.best_step}, loss {score:.4g}; no val split"
    text = (f"the lowest validation score of the run: step {result.best_step}, score {score:.4g} (the task losses "
            "relative to the first validation's)")
    scores = _scores(result.best_metrics)
    if scores:
        text += f", {scores}"
    v = result.val_heights
    if v is not None:
        text += f"; validation holds {v.tall} px ≥ 2 m of {v.pixels}"
        if result.val_cannot_judge is not None:
            text += ", too few to judge heights (see the warning)"
    return text
