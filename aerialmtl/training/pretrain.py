"""Synthetic pretraining: many synthetic towns at the user's GSD → tiles → a trained checkpoint.

A model that must learn heights from a small real area starts better from weights that already know
what shadows, roofs and crowns look like at that ground sampling distance. :func:`pretrain_synthetic`
writes a corpus of procedural towns (:func:`~aerialmtl.data.synth.corpus.synthesize_corpus`, one seed,
sun angle and layout per town) at ``gsd`` metres, tiles it with heights and land-cover labels (spatial
block split, 90 % train / 10 % val) and trains the multi-task D3-Net on it from scratch::

    OUT/corpus/   the towns and their mosaic VRTs
    OUT/tiles/    the tile folder
    OUT/run/      last.pt, best.pt, log.csv, config.yaml of the pretraining run

``OUT/run/best.pt`` is then the starting point of a fine-tuning run on the real area
(``aerialmtl train --init OUT/run/best.pt``; the class head is re-initialised when the real area has no
labels or another class scheme).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from aerialmtl.data.synth.corpus import synthesize_corpus
from aerialmtl.errors import InputError, OutputExistsError
from aerialmtl.tiling.splits import SplitSpec
from aerialmtl.tiling.tile import tile_dataset
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.loop import TrainResult, train


@dataclass(frozen=True)
class PretrainSettings:
    """The synthetic corpus and its tiling.

    Attributes:
        gsd: pixel size in metres; use the GSD the real area will be trained at.
        towns: number of synthetic towns (seeds ``seed`` … ``seed + towns - 1``).
        town_size: side of each town in pixels.
        patch: patch side in pixels (multiple of 32).
        stride: patch stride in pixels (default: half the patch).
        crs: projected CRS of the corpus (only the GSD in metres matters to the model).
        seed: seed of the first town.
        val_fraction: share of the corpus (in spatial blocks) kept for validation.
    """

    gsd: float
    towns: int = 16
    town_size: int = 1024
    patch: int = 256
    stride: int | None = None
    crs: str = "EPSG:32631"
    seed: int = 0
    val_fraction: float = 0.1

    def __post_init__(self) -> None:
        if not self.gsd > 0:
            raise InputError(f"‹gsd› must be a positive pixel size in metres, got {self.gsd}; pass e.g. ‹gsd=0.6›",
                             param="gsd")
        if self.patch < 32 or self.patch % 32:
            raise InputError(f"‹patch› must be a multiple of 32 pixels, got {self.patch}; pass e.g. ‹patch=256›",
                             param="patch")
        if self.patch > self.town_size:
            raise InputError(f"‹patch› {self.patch} is larger than ‹town_size› {self.town_size}; lower ‹patch› or "
                             "raise ‹town_size›", param="patch")
        if not 0 <= self.val_fraction < 1:
            raise InputError(f"‹val_fraction› must be in [0, 1), got {self.val_fraction}", param="val_fraction")


@dataclass(frozen=True)
class PretrainResult:
    """Where the corpus, tiles and run went; ``checkpoint`` is the run's ``best.pt``."""

    out_dir: Path
    corpus: Path
    tiles: Path
    checkpoint: Path
    train: TrainResult
    patches: dict[str, int]


def pretrain_synthetic(
    out_dir: str | Path,
    settings: PretrainSettings,
    cfg: TrainConfig,
    *,
    max_steps: int | None = None,
    max_time_s: float | None = None,
    overwrite: bool = False,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> PretrainResult:
    """Synthesise ``settings.towns`` towns, tile them and train ``cfg`` on them from scratch.

    Args:
        out_dir: output folder (``corpus/``, ``tiles/``, ``run/``).
        settings: corpus and tiling settings.
        cfg: training configuration (``data.crop_size`` must fit ``settings.patch``).
        max_steps, max_time_s: training budget (override ``cfg.schedule``).
        overwrite: replace an existing pretraining folder.
        progress: tqdm bars for tiling and training.
        log: called with one line per stage.

    Returns:
        A :class:`PretrainResult`.

    Raises:
        OutputExistsError: ``out_dir`` holds a previous pretraining and ``overwrite`` is False.
        InputError, ConfigError: bad settings (messages name the parameter).
    """
    out = Path(out_dir)
    say = log or (lambda _msg: None)
    run_dir = out / "run"
    if run_dir.is_dir() and any(run_dir.iterdir()) and not overwrite:
        raise OutputExistsError(f"'{out}' already holds a pretraining run; pass ‹overwrite=True› or choose another "
                                "‹out_dir›")
    s = settings
    say(f"synthesising {s.towns} towns of {s.town_size} px at {s.gsd:g} m")
    corpus = synthesize_corpus(out / "corpus", towns=s.towns, size=s.town_size, gsd=s.gsd, seed=s.seed, crs=s.crs,
                               gap_px=s.patch, overwrite=overwrite)
    stride = s.stride or s.patch // 2
    say(f"tiling into {s.patch}-px patches every {stride} px")
    split = SplitSpec(method="blocks", block_size=s.town_size * s.gsd / 4,
                      ratios=(1 - s.val_fraction, s.val_fraction, 0), seed=s.seed)
    tiles = tile_dataset(corpus.ortho, out / "tiles", ndsm=corpus.ndsm, labels=corpus.labels,
                         classes=corpus.classes, size=s.patch, stride=stride, splits=split, overwrite=overwrite,
                         progress=progress)
    say(f"training on {tiles.counts['train']} patches (val {tiles.counts['val']})")
    if run_dir.is_dir() and overwrite:
        for child in run_dir.iterdir():
            if child.is_file():
                child.unlink()
    result = train(cfg, data_dir=out / "tiles", out_dir=run_dir, max_steps=max_steps, max_time_s=max_time_s,
                   progress=progress)
    return PretrainResult(out, corpus.out_dir, out / "tiles", result.best_checkpoint, result, dict(tiles.counts))


__all__ = ["PretrainResult", "PretrainSettings", "pretrain_synthetic"]
