"""`aerialmtl train`: train a D3-Net on a tile folder (thin wrapper over :func:`aerialmtl.training.loop.train`)."""

from __future__ import annotations

import shutil
from pathlib import Path

import click

from aerialmtl.errors import OutputExistsError
from aerialmtl.io.outputs import make_output_dir


@click.command(name="train")
@click.option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path),
              help="Training YAML (e.g. configs/d3net_small_synth.yaml). With --resume, defaults to RUN/config.yaml.")
@click.option("--data", "data_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Tile folder written by `aerialmtl tile` (overrides data.dir of the config).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=Path("runs/train"),
              show_default=True, help="Run folder for last.pt, best.pt, log.csv and config.yaml.")
@click.option("--max-steps", type=int, help="Stop after this many optimisation steps in total.")
@click.option("--max-time", "max_time", type=float, help="Wall-clock budget of this call in seconds.")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its last.pt.")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), help="Overrides the config's device.")
@click.option("--precision", type=click.Choice(["fp32", "bf16"]), help="Overrides the config's precision.")
@click.option("--overwrite", is_flag=True, help="Delete the contents of a non-empty --out first.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def train(config_path: Path | None, data_dir: Path | None, out_dir: Path, max_steps: int | None,
          max_time: float | None, resume: bool, device: str | None, precision: str | None, overwrite: bool,
          quiet: bool) -> None:
    """Train the multi-task D3-Net (height + land cover) on patches made by `aerialmtl tile`.

    Writes RUN/last.pt (every validation and at the end), RUN/best.pt (best validation score),
    RUN/log.csv and RUN/config.yaml. A run stopped by --max-time or --max-steps continues with --resume.
    """
    from aerialmtl.training.config import load_train_config
    from aerialmtl.training.loop import train as train_loop

    if max_steps is not None and max_steps < 1:
        raise click.BadParameter(f"must be ≥ 1, got {max_steps}", param_hint="--max-steps")
    if max_time is not None and max_time <= 0:
        raise click.BadParameter(f"must be > 0 seconds, got {max_time}", param_hint="--max-time")
    if resume and overwrite:
        raise click.BadParameter("--resume continues a run and --overwrite deletes it; pass only one",
                                 param_hint="--resume/--overwrite")
    if out_dir.exists() and not out_dir.is_dir():
        raise click.BadParameter(f"'{out_dir}' is a file; pass a folder", param_hint="--out")
    non_empty = out_dir.is_dir() and any(out_dir.iterdir())
    if resume:
        if not (out_dir / "last.pt").is_file():
            raise click.BadParameter(f"'{out_dir / 'last.pt'}' does not exist; there is no run to resume there",
                                     param_hint="--resume")
        config_path = config_path or out_dir / "config.yaml"
    elif non_empty:
        if not overwrite:
            raise OutputExistsError(
                f"run folder '{out_dir}' is not empty; pass --resume to continue it, --overwrite to replace it, "
                "or another --out"
            )
        for child in out_dir.iterdir():
            shutil.rmtree(child) if child.is_dir() else child.unlink()
    if config_path is None:
        raise click.BadParameter("pass a training YAML, e.g. configs/d3net_small_synth.yaml", param_hint="--config")

    cfg = load_train_config(config_path)
    make_output_dir(out_dir, "run folder")
    overrides = {k: v for k, v in (("device", device), ("precision", precision)) if v is not None}
    if overrides:
        cfg = cfg.with_overrides(**overrides)
    result = train_loop(cfg, data_dir=data_dir, out_dir=out_dir, max_steps=max_steps, max_time_s=max_time,
                        resume=resume, progress=not quiet)
    m = result.metrics
    parts = [f"{k}={m[k]:.4g}" for k in ("height_mae", "height_rmse", "oa", "miou") if k in m]
    click.echo(f"stopped by {result.stopped_by} after {result.step} steps ({result.epoch} epochs, "
               f"{result.elapsed_s:.0f} s)" + (f"; validation: {', '.join(parts)}" if parts else ""))
    click.echo(f"best checkpoint: {result.best_checkpoint}")
    click.echo(f"last checkpoint: {result.last_checkpoint}")
    click.echo(f"log: {result.log_path}")
