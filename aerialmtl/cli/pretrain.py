"""`aerialmtl pretrain`: pretrain on synthetic scenes made on the fly and export a start for ``train --init``
(a thin command over :func:`aerialmtl.training.pretrain.pretrain`).
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

import click

from aerialmtl.cli.options import device_option, option, output_path, overwrite_option, precision_option, quiet_option

#: The training config pretraining uses unless --config says otherwise: the small-area recipe's network.
DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "resources" / "configs" / "small_area.yaml"


@click.command(name="pretrain")
@option("--out", "out_dir", type=output_path(file_okay=False), default=Path("runs/pretrain"), show_default=True,
        help="Run folder: last.pt (every --checkpoint-every steps), log.csv, config.yaml, and at the end the start "
             "NAME.pt with its model card NAME.yaml.")
@option("--steps", type=int, required=True, help="Optimisation steps in total (a resumed run continues to it).")
@option("--config", "config_path", library="config", type=click.Path(dir_okay=False, path_type=Path),
        help="Training YAML whose model, loss, optimiser (optim.ema too), schedule.lr_schedule/warmup_steps/log_every "
             "and data.batch_size are used as train uses them [default: the small-area recipe, "
             "configs/small_area.yaml; with --resume, OUT/config.yaml].")
@option("--checkpoint-every", type=int, default=500, show_default=True, help="Write last.pt every this many steps.")
@option("--name", default="synthcity-lite0", show_default=True,
        help="Name of the exported start (NAME.pt); not the name of a run or tile folder file (last, best, config...).")
@option("--seed", type=int, default=None, help="Overrides the config's seed (the scenes and the weights).")
@option("--batch-size", type=int, default=None, help="Overrides data.batch_size (patches per step).")
@option("--workers", type=int, default=None, help="Overrides data.num_workers (processes making scenes).")
@option("--patch-size", type=int, default=128, show_default=True, help="Patch side in pixels (multiple of 32).")
@option("--scene-size", type=int, default=256, show_default=True, help="Side of each synthetic scene in pixels.")
@option("--gsd-range", type=(float, float), default=(0.5, 1.0), show_default=True, metavar="LOW HIGH",
        help="Each scene's pixel size in metres is drawn from this range.")
@option("--scenes-per-step", type=int, default=4, show_default=True,
        help="Scenes a step's patches are cut from (patch i from scene i mod this).")
@option("--scene-reuse", type=int, default=4, show_default=True,
        help="Consecutive steps that cut their patches from the same scenes (a scene costs about a quarter step).")
@option("--textures", "textures", type=click.Path(file_okay=False, exists=True, path_type=Path), default=None,
        help="Tile folder (from `aerialmtl tile`) whose training patches lend the look of their open ground (nDSM "
             "≤ 0.5 m) to the synthetic roofs and ground: scenes restyled like your area, where a roof may look "
             "exactly like your ground [default: the generator's own materials].")
@option("--texture-share", type=float, default=None,
        help="With --textures: probability that a surface wears one of your textures [default: 0.5].")
@option("--real", "real", type=click.Path(file_okay=False, exists=True, path_type=Path), default=None,
        help="Tile folder (from `aerialmtl tile`) whose training patches (orthophoto and nDSM; not their labels) "
             "fill --real-share of every batch beside the synthetic scenes [default: synthetic scenes only].")
@option("--real-share", type=float, default=None,
        help="With --real: share of each batch's patches that are real [default: 0.25].")
@option("--ground-roofs", type=float, default=0.65, show_default=True,
        help="Probability that a synthetic flat roof is drawn in a ground material (asphalt, gravel, concrete, "
             "planted): the roofs that look like the ground around them.")
@option("--export-dtype", type=click.Choice(["float16", "float32"]), default="float16", show_default=True,
        help="Storage of the start's weights.")
@option("--resume", is_flag=True, help="Continue the run in --out from its last.pt.")
@device_option(default=None, help="Overrides the config's device.")
@precision_option(default=None, help="Overrides the config's precision.")
@overwrite_option(help="Start the run in --out again (its last.pt, log.csv and config.yaml are replaced).")
@quiet_option()
def pretrain(out_dir: Path, steps: int, config_path: Path | None, checkpoint_every: int, name: str,
             seed: int | None, batch_size: int | None, workers: int | None, patch_size: int, scene_size: int,
             gsd_range: tuple[float, float], scenes_per_step: int, scene_reuse: int, textures: Path | None,
             texture_share: float | None, real: Path | None, real_share: float | None, ground_roofs: float,
             export_dtype: str,
             resume: bool, device: str | None, precision: str | None, overwrite: bool, quiet: bool) -> None:
    """Pretrain the small-area recipe's network on synthetic cities generated on the fly (nothing downloaded,
    nothing written but the run folder), then export a start that `aerialmtl train --init` fine-tunes.

    The start is trained on synthetic scenes only: a start for fine-tuning, not a map of anywhere.
    Interrupted? Run the same command with --resume: it continues from last.pt and ends with the same
    weights as an uninterrupted run.
    \f

    One parameter per command-line option: click passes each option to the command.
    """
    # the library when the command runs, not for --help (CLI start time: tests/test_cli_imports.py)
    from aerialmtl.data.synthetic_batches import SyntheticStream
    from aerialmtl.training.config import load_train_config
    from aerialmtl.training.pretrain import CONFIG_YAML, PretrainSettings, folder_policy
    from aerialmtl.training.pretrain import pretrain as run_pretrain

    for share, folder, names in ((texture_share, textures, ("--texture-share", "--textures")),
                                 (real_share, real, ("--real-share", "--real"))):
        if share is not None and folder is None:
            raise click.BadParameter(f"{names[0]} applies to the tile folder of {names[1]}; pass {names[1]} TILES "
                                     f"too, or leave {names[0]} out", param_hint=names[0])
    stock = SyntheticStream()
    settings = PretrainSettings(steps=steps, checkpoint_every=checkpoint_every, name=name, export_dtype=export_dtype,
                                stream=SyntheticStream(patch_size=patch_size, scene_size=scene_size,
                                                       gsd_range=gsd_range, scenes_per_step=scenes_per_step,
                                                       scene_reuse=scene_reuse,
                                                       textures=None if textures is None else str(textures.resolve()),
                                                       texture_share=stock.texture_share if texture_share is None
                                                       else texture_share, ground_roofs=ground_roofs,
                                                       real=None if real is None else str(real.resolve()),
                                                       real_share=stock.real_share if real_share is None
                                                       else real_share))
    # the run-folder policy (the library's, as train's) before the config is read: says what is wrong first
    folder_policy(name).check(out_dir, resume=resume, overwrite=overwrite)
    if config_path is None:
        config_path = out_dir / CONFIG_YAML if resume else DEFAULT_CONFIG
    cfg = load_train_config(config_path)
    data = {k: v for k, v in (("batch_size", batch_size), ("num_workers", workers)) if v is not None}
    over: dict[str, object] = {k: v for k, v in (("device", device), ("precision", precision), ("seed", seed))
                               if v is not None}
    if data:
        over["data"] = data
    if over:
        cfg = cfg.with_overrides(**over)
    res = run_pretrain(cfg, out_dir, settings, resume=resume, overwrite=overwrite, progress=not quiet,
                       command=shlex.join(["aerialmtl", *sys.argv[1:]]))
    per_step = res.elapsed_s / res.steps_this_call if res.steps_this_call else float("nan")
    click.echo(f"pretrained to step {res.step} ({res.steps_this_call} steps in {res.elapsed_s:.0f} s, "
               f"{per_step:.2f} s/step; {res.wall_time_s:.0f} s of training in all); last loss {res.loss:.4g}")
    click.echo(f"last checkpoint: {res.last_checkpoint}")
    size = res.start.stat().st_size / 2**20
    click.echo(f"start: {res.start} ({size:.1f} MiB) and its card {res.start.with_suffix('.yaml')}; fine-tune with "
               f"`aerialmtl train --init {res.start} ...` (or copy both into aerialmtl/resources/starts/ to ship it "
               f"as `--init {name}`)")
