"""Experiment code of ``experiments/real_data/run.py``: height-stratified sampling, a corpus of many synthetic towns
and synthetic pretraining.

These recipes were measured on ``autzen_west`` (bench/RESULTS.md, "Learning from a small real area") and
did not beat training from scratch by more than the run-to-run spread, so they stay here, next to the
benchmark that tried them, rather than in the package.

* :func:`tall_shares`, :func:`stratified_weights`, :func:`repeat_counts` — draw patches with a probability
  that grows with their share of tall (≥ 2 m) pixels: ``w_i = 1 + a · s_i`` (mean 1) whose weighted mean
  tall share is ``target``, applied as whole repeats per patch;
* :func:`synthesize_corpus` — ``towns`` towns from :func:`aerialmtl.data.synth.synthesize` (seeds ``seed``,
  ``seed + 1``, ...) on a grid in one CRS with ``gap_px`` empty pixels between neighbours, and one mosaic
  VRT per layer, so that ``tile_dataset(ortho.vrt, ndsm=ndsm.vrt, labels=labels.vrt, ...)`` cuts them all
  in one pass (the orthophoto mosaic declares nodata 0; gaps at least a patch wide keep towns apart);
* :func:`pretrain_synthetic` — the product's pretraining (:func:`aerialmtl.training.pretrain.pretrain`: scenes made
  on the fly at the real area's GSD) whose exported start begins a fine-tuning run on the real area
  (``train --init``).
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
from rasterio.crs import CRS

from aerialmtl.data.synth.generate import MIN_SIZE, SYNTH_VERSION, synthesize
from aerialmtl.errors import InputError, OutputExistsError
from aerialmtl.formats.tiles import HEIGHT_NODATA, read_manifest
from aerialmtl.io.units import metres_per_unit
from aerialmtl.io.vrt import mosaic_vrt
from aerialmtl.training import pretrain as product_pretrain
from aerialmtl.training.config import TrainConfig

# ---- height-stratified sampling --------------------------------------------------------------------
#: Largest slope ``a`` of the weights: a patch full of tall pixels is drawn at most this + 1 times as often.
MAX_SLOPE = 20.0


def tall_shares(data_dir: str | Path, split: str = "train", threshold_m: float = 2.0) -> np.ndarray:
    """Share of valid height pixels ≥ ``threshold_m`` metres in every patch of ``split`` (manifest order).

    Returns:
        float64 (n,) in [0, 1]; 0 for a patch without valid heights.

    Raises:
        InputError: the split has no height layer.
    """
    root = Path(data_dir)
    rows = read_manifest(root, split)
    out = np.zeros(len(rows))
    for i, row in enumerate(rows):
        rel = (row.get("height_path") or "").strip()
        if not rel:
            raise InputError(f"manifest row '{row.get('patch_id')}' of '{root / 'manifest.csv'}' has no height_path; "
                             "height-stratified sampling needs a tile folder made with heights (‹dsm›/‹dtm› or ‹ndsm›)")
        with rasterio.open(root / rel) as src:
            h = src.read(1, masked=True)
        valid = ~np.ma.getmaskarray(h) & np.isfinite(h.filled(np.nan))
        n = int(valid.sum())
        out[i] = float((h.data[valid] >= threshold_m).sum()) / n if n else 0.0
    return out


def stratified_weights(shares: np.ndarray, target: float = 0.5) -> np.ndarray:
    """Sampling weights ``1 + a · s_i``, normalised to mean 1, whose weighted mean share is ``target``.

    Args:
        shares: (n,) tall share of each patch (see :func:`tall_shares`).
        target: wanted share of tall pixels per drawn patch, in (0, 1).

    Returns:
        float64 (n,) positive weights with mean 1 (all 1 when the plain mean share already reaches
        ``target`` or no patch has tall pixels; ``a`` is capped at :data:`MAX_SLOPE`).
    """
    if not 0 < target < 1:
        raise InputError(f"‹target›: the tall share to reach must be in (0, 1), got {target}", param="target")
    s = np.asarray(shares, dtype=np.float64)
    if s.size == 0:
        return s
    n, s1, s2 = s.size, s.sum(), (s**2).sum()
    denom = s2 - target * s1
    if s1 >= target * n or denom <= 0:  # already there, or unreachable by tilting towards tall patches
        a = 0.0 if s1 >= target * n else MAX_SLOPE
    else:
        a = min(MAX_SLOPE, (target * n - s1) / denom)
    w = 1.0 + a * s
    return w / w.mean()


def repeat_counts(weights: np.ndarray) -> np.ndarray:
    """Whole repeats per patch proportional to ``weights`` (the lightest patch once), int64 (n,)."""
    w = np.asarray(weights, dtype=np.float64)
    if w.size == 0:
        return np.zeros(0, np.int64)
    if (w <= 0).any():
        raise InputError("‹weights›: every patch needs a positive weight", param="weights")
    return np.maximum(1, np.rint(w / w.min())).astype(np.int64)


# ---- many synthetic towns as one dataset -----------------------------------------------------------
#: Layers mosaicked, with the nodata of pixels outside every town.
MOSAIC_LAYERS = {"ortho": 0, "dsm": HEIGHT_NODATA, "dtm": HEIGHT_NODATA, "ndsm": HEIGHT_NODATA, "labels": 0}


@dataclass(frozen=True)
class CorpusResult:
    """Paths of the corpus written by :func:`synthesize_corpus` (VRT mosaics and the class scheme)."""

    out_dir: Path
    ortho: Path
    dsm: Path
    dtm: Path
    ndsm: Path
    labels: Path
    classes: Path
    towns: int
    seconds: float


def synthesize_corpus(
    out_dir: str | Path,
    towns: int = 16,
    size: int = 1024,
    gsd: float = 0.25,
    seed: int = 0,
    crs: str = "EPSG:32631",
    gap_px: int = 512,
    overwrite: bool = False,
    on_town: Callable[[int, int], None] | None = None,
) -> CorpusResult:
    """Write ``towns`` synthetic towns of ``size`` px at ``gsd`` metres and mosaic VRTs over them.

    Args:
        out_dir: output folder.
        towns: number of towns (seeds ``seed`` … ``seed + towns - 1``).
        size: side of each town in pixels (≥ the synthesiser's minimum).
        gsd: pixel size in metres (use the working GSD of the real area).
        seed: seed of the first town.
        crs: projected CRS of the corpus (metres or feet; the GSD stays in metres).
        gap_px: empty pixels between neighbouring towns; at least the patch size you tile with.
        overwrite: replace an existing corpus in ``out_dir``.
        on_town: called as ``on_town(done, towns)`` after each town (progress reporting).

    Returns:
        A :class:`CorpusResult`.

    Raises:
        InputError: ``towns`` < 1, ``gap_px`` < 0, or what :func:`synthesize` refuses (size, gsd, crs).
        OutputExistsError: ``out_dir`` holds a corpus and ``overwrite`` is False.
    """
    t0 = time.perf_counter()
    if int(towns) != towns or towns < 1:
        raise InputError(f"‹towns› must be a positive number of towns, got {towns}; pass e.g. ‹towns=16›",
                         param="towns")
    if int(gap_px) != gap_px or gap_px < 0:
        raise InputError(f"‹gap_px› must be a number of pixels ≥ 0, got {gap_px}; use at least the patch size",
                         param="gap_px")
    if int(size) != size or size < MIN_SIZE:
        raise InputError(f"‹size› must be an integer ≥ {MIN_SIZE} pixels, got {size}; pass e.g. ‹size=1024›",
                         param="size")
    out = Path(out_dir)
    info_path = out / "corpus.json"
    if info_path.exists() or any((out / f"{name}.vrt").exists() for name in MOSAIC_LAYERS):
        if not overwrite:
            raise OutputExistsError(f"'{out}' already holds a synthetic corpus; pass ‹overwrite=True› to replace it "
                                    "or choose another ‹out_dir›")
        for child in out.glob("town_*"):
            shutil.rmtree(child)
    out.mkdir(parents=True, exist_ok=True)
    crs_obj = CRS.from_user_input(crs)
    step = (size + gap_px) * gsd / metres_per_unit(crs_obj, "corpus")  # CRS units between neighbouring towns' origins
    ncols = math.ceil(math.sqrt(towns))
    records = []
    for i in range(towns):
        row, col = divmod(i, ncols)
        origin = (500000.0 + col * step, 5000000.0 - row * step)
        res = synthesize(out / f"town_{i:03d}", size=size, seed=seed + i, gsd=gsd, crs=crs, origin=origin,
                         overwrite=overwrite)
        records.append({"seed": seed + i, "row": row, "col": col, "sun_azimuth": res.sun_azimuth,
                        "sun_elevation": res.sun_elevation})
        if on_town is not None:
            on_town(i + 1, towns)
    paths = {}
    for name, nodata in MOSAIC_LAYERS.items():
        paths[name] = mosaic_vrt(out / f"{name}.vrt", [out / f"town_{i:03d}" / f"{name}.tif" for i in range(towns)],
                                 categorical=name == "labels")
        with rasterio.open(paths[name], "r+") as vrt:  # the towns' orthophotos declare no nodata of their own
            vrt.nodata = nodata
    classes = out / "classes.yaml"
    shutil.copyfile(out / "town_000" / "classes.yaml", classes)
    info = {"synth_version": SYNTH_VERSION, "towns": towns, "size": size, "gsd": gsd, "seed": seed,
            "crs": crs_obj.to_string(), "gap_px": gap_px, "layout_columns": ncols, "town_list": records,
            "files": [f"{n}.vrt" for n in MOSAIC_LAYERS] + ["classes.yaml"]}
    info_path.write_text(json.dumps(info, indent=1))
    return CorpusResult(out, paths["ortho"], paths["dsm"], paths["dtm"], paths["ndsm"], paths["labels"], classes,
                        towns, time.perf_counter() - t0)


# ---- synthetic pretraining ------------------------------------------------------------------------
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
    """Where the run went; ``checkpoint`` is its exported start (``corpus`` and ``tiles``: the run folder, the
    scenes are made on the fly; ``patches`` empty).
    """

    out_dir: Path
    corpus: Path
    tiles: Path
    checkpoint: Path
    train: product_pretrain.PretrainResult
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
    """Pretrain ``cfg``'s network from scratch with the product's ``pretrain`` (``settings.towns``,
    ``stride``, ``crs``, ``seed`` and ``val_fraction`` no longer apply: scenes of ``town_size`` px are made on the
    fly; ``max_time_s`` is not a pretraining budget and is ignored).

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
    from aerialmtl.data.synthetic_batches import SyntheticStream

    out = Path(out_dir)
    say = log or (lambda _msg: None)
    s = settings
    steps = max_steps or cfg.schedule.max_steps or 1
    say(f"pretraining {steps} steps on {s.town_size}-px scenes at {s.gsd:g} m made on the fly (aerialmtl pretrain)")
    stream = SyntheticStream(patch_size=s.patch, scene_size=s.town_size, gsd_range=(s.gsd, s.gsd))
    cfg = cfg.with_overrides(schedule={"patience": None, "max_time_s": None})  # no validation split there
    start = product_pretrain.PretrainSettings(steps=steps, name="synthetic-start", stream=stream)
    result = product_pretrain.pretrain(cfg, out / "run", start, overwrite=overwrite, progress=progress)
    return PretrainResult(out, out / "run", out / "run", result.start, result, {})

