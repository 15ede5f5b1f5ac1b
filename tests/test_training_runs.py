"""Issue 60/59, training side: train and pretrain share one run-folder policy, one save and one resume; every
stage after the steps says what it does with a bar; a validation split that cannot judge heights is said plainly
by `tile` and `train`, and the best.pt line says what it was chosen on."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from click.testing import CliRunner
from helpers.rasters import write_raster
from helpers.tilefolder import write_tile_folder
from rasterio.warp import transform as warp_transform

from aerialmtl import progress
from aerialmtl.cli import cli
from aerialmtl.data.synthetic_batches import SyntheticStream
from aerialmtl.errors import CheckpointError, InputError, OutputExistsError
from aerialmtl.formats.tiles import read_manifest
from aerialmtl.tiling.height_support import TallCount, cannot_judge
from aerialmtl.tiling.splits import SplitSpec
from aerialmtl.tiling.tile import TileOptions, tile_dataset
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.loop import train
from aerialmtl.training.pretrain import PretrainSettings, pretrain

TINY = {"growth_rate": 8, "block_config": [2, 2, 2, 2], "num_init_features": 16, "bn_size": 2}
OFF = {"calibration": {"enabled": False}, "familiarity": {"enabled": False}, "sun": {"enabled": False}}


def train_cfg(**over: object) -> TrainConfig:
    return TrainConfig.from_dict({"model": TINY, "data": {"batch_size": 4, "num_workers": 0},
                                  "schedule": {"epochs": 100, "log_every": 1}, "seed": 0, "device": "cpu",
                                  **OFF, **over})


def pretrain_cfg() -> TrainConfig:
    return TrainConfig.from_dict({"model": {**TINY, "aleatoric": True}, "data": {"batch_size": 2, "num_workers": 0},
                                  "schedule": {"log_every": 1}, "seed": 3, "device": "cpu"})


def pre_settings(steps: int) -> PretrainSettings:
    return PretrainSettings(steps=steps, checkpoint_every=2, name="tiny-start",
                            stream=SyntheticStream(patch_size=32, scene_size=64, scenes_per_step=2, scene_reuse=2))


@pytest.fixture(scope="module")
def tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tile_folder(tmp_path_factory.mktemp("t") / "tiles", size=64, counts={"train": 4, "val": 2})


def run_train(tiles: Path, out: Path, **kw: object) -> object:
    return train(train_cfg(), tiles, out, max_steps=int(kw.pop("steps", 1)), progress=False, **kw)  # type: ignore


def run_pretrain(out: Path, **kw: object) -> object:
    return pretrain(pretrain_cfg(), out, pre_settings(int(kw.pop("steps", 2))), progress=False, **kw)  # type: ignore


def _same(message: str, folder: Path) -> str:
    return message.replace(str(folder), "RUN")


# ---- one folder policy, one resume ----------------------------------------------------------------------
def test_train_and_pretrain_judge_a_run_folder_the_same_way(tiles: Path, tmp_path: Path) -> None:
    """A folder holding a run's file is refused alike (even a lone config.yaml), accepted with overwrite; resume
    without last.pt and resume with overwrite are refused alike, naming the same options."""
    commands = {"train": lambda out, **kw: run_train(tiles, out, **kw), "pretrain": run_pretrain}
    refusals: dict[str, list[str]] = {}
    for name, command in commands.items():
        out = tmp_path / name
        out.mkdir()
        (out / "config.yaml").write_text("a run's config\n")
        seen = []
        with pytest.raises(OutputExistsError) as exc:
            command(out)
        seen.append(_same(str(exc.value), out))
        with pytest.raises(InputError) as exc:
            command(out, resume=True)
        seen.append(f"{exc.value.param}: {_same(str(exc.value), out)}")
        with pytest.raises(InputError) as exc:
            command(out, resume=True, overwrite=True)
        seen.append(f"{exc.value.param}: {_same(str(exc.value), out)}")
        refusals[name] = seen
        command(out, overwrite=True)  # replaces the run's files
        assert (out / "last.pt").is_file() and (out / "config.yaml").read_text() != "a run's config\n"
    assert refusals["train"] == refusals["pretrain"], refusals
    assert "already holds config.yaml" in refusals["train"][0] and refusals["train"][2].startswith("resume/overwrite")


def _poison_optimizer(path: Path) -> None:
    payload = torch.load(path, weights_only=False)
    state = payload["train_state"]["optimizer"]["state"]
    first = next(iter(state.values()))
    first["exp_avg"].fill_(float("nan"))
    torch.save(payload, path)


def test_train_and_pretrain_resume_through_the_same_checks(tiles: Path, tmp_path: Path) -> None:
    """A last.pt whose optimiser state holds NaN is refused by both resumes with the same words; a sound one
    continues both runs to the step asked."""
    messages = {}
    for name, command in (("train", lambda out, **kw: run_train(tiles, out, **kw)), ("pretrain", run_pretrain)):
        out = tmp_path / name
        command(out, steps=2)
        good = (out / "last.pt").read_bytes()
        _poison_optimizer(out / "last.pt")
        with pytest.raises(CheckpointError) as exc:
            command(out, steps=3, resume=True)
        messages[name] = _same(str(exc.value), out)
        (out / "last.pt").write_bytes(good)
        assert command(out, steps=3, resume=True).step == 3  # type: ignore[attr-defined]
    assert messages["train"] == messages["pretrain"], messages
    assert "optimizer state holds NaN or inf" in messages["train"]


# ---- no silent minutes ------------------------------------------------------------------------------------
def test_each_stage_after_the_steps_prints_its_line_and_bar(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    tiles = write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 4, "val": 2})
    cfg = train_cfg(**{k: {"enabled": True} for k in OFF})
    previous = progress.set_mode("json")
    try:
        train(cfg, tiles, tmp_path / "run", max_steps=1, progress=True)
    finally:
        progress.set_mode(previous)
    err = capsys.readouterr().err.splitlines()
    bars = [json.loads(line) for line in err if line.startswith("{")]
    text = [line for line in err if not line.startswith("{")]
    for stage, said in (("calibration", "best.pt: calibration on the 2 validation patches"),
                        ("feature density", "best.pt: feature density on the 4 training patches"),
                        ("sun fit", "sun fit on the 4 training patches")):
        assert any(line.startswith(said) for line in text), (stage, text)
        lines = [b for b in bars if b["stage"] == stage]
        assert lines and lines[0]["done"] == 0 and lines[-1]["done"] == lines[-1]["total"], (stage, lines)
    order = [next(i for i, line in enumerate(err) if stage in line) for stage in ("calibration", "feature density",
                                                                                "sun fit")]
    assert order == sorted(order) and min(order) > max(i for i, b in enumerate(err) if '"stage": "train"' in b)
    # quiet: nothing of it
    train(cfg, tiles, tmp_path / "quiet", max_steps=1, progress=False)
    assert capsys.readouterr().err == ""


# ---- a validation split that cannot judge heights ---------------------------------------------------------
def test_the_rule_weighs_count_and_share_against_training() -> None:
    train_split = TallCount(100_000, 30_000)
    assert cannot_judge(train_split, TallCount(10_000, 28)) is not None  # the field case: 28 px ≥ 2 m
    assert cannot_judge(train_split, TallCount(10_000, 3_000)) is None
    assert "against 30.0 % in train" in str(cannot_judge(train_split, TallCount(100_000, 5_000)))
    assert cannot_judge(TallCount(100_000, 0), TallCount(10_000, 0)) is None  # nothing tall to judge


def _flatten_val(tiles: Path, keep: int) -> None:
    """Make the val patches bare ground but for ``keep`` pixels of 10 m."""
    for row in read_manifest(tiles, "val"):
        path = tiles / row["height_path"]
        with rasterio.open(path, "r+") as dst:
            h = dst.read(1)
            flat = np.where(h == -9999.0, h, 0.2).astype(np.float32)
            flat.ravel()[:keep] = 10.0
            dst.write(flat[None])
        keep = 0


def test_train_warns_when_validation_cannot_judge_heights_and_best_line_says_why(tmp_path: Path) -> None:
    tiles = write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 4, "val": 2})
    _flatten_val(tiles, keep=28)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(json.dumps(train_cfg().to_dict()))
    with pytest.warns(UserWarning, match=r"the val split holds 28 px ≥ 2 m, fewer than the 1000 needed to judge "
                                         r"heights .*best\.pt would be chosen on the ground.*--split-block"):
        result = CliRunner().invoke(cli, ["train", "--config", str(cfg), "--data", str(tiles), "--out",
                                          str(tmp_path / "run"), "--max-steps", "2", "--quiet"])
    assert result.exit_code == 0, result.output
    best = next(line for line in result.output.splitlines() if line.startswith("best checkpoint:"))
    assert re.search(r"the lowest validation score of the run: step \d+, score [\d.]+ .*height MAE [\d.]+ m", best)
    assert re.search(r"validation holds 28 px ≥ 2 m of \d+, too few to judge heights", best), best


def _area(x0: float, y0: float, x1: float, y1: float, split: str) -> dict:
    """A GeoJSON feature (lon/lat) of the UTM rectangle, densified, with its split."""
    xs = list(np.linspace(x0, x1, 8)) + [x1] * 8 + list(np.linspace(x1, x0, 8)) + [x0] * 8
    ys = [y0] * 8 + list(np.linspace(y0, y1, 8)) + [y1] * 8 + list(np.linspace(y1, y0, 8))
    lon, lat = warp_transform("EPSG:32631", "EPSG:4326", xs, ys)
    ring = [[a, b] for a, b in zip(lon, lat)]
    return {"type": "Feature", "properties": {"split": split}, "geometry": {"type": "Polygon",
                                                                           "coordinates": [ring + [ring[0]]]}}


def test_tile_warns_when_validation_holds_a_few_tall_pixels(tmp_path: Path) -> None:
    """Not only at zero: validation (the right half) holds one small 10 m roof, training many."""
    transform = rasterio.Affine(1.0, 0, 500000.0, 0, -1.0, 5000000.0)
    img = np.random.default_rng(0).integers(1, 255, size=(3, 64, 64), dtype=np.uint8)
    ndsm = np.random.default_rng(1).uniform(0, 20, size=(64, 64)).astype(np.float32)
    ndsm[:, 32:] = 0.2
    ndsm[40:45, 40:45] = 10.0  # 25 px
    ortho = write_raster(tmp_path / "o.tif", img, "EPSG:32631", transform, nodata=0)
    heights = write_raster(tmp_path / "n.tif", ndsm, "EPSG:32631", transform, nodata=-9999.0)
    aoi = tmp_path / "aoi.geojson"
    aoi.write_text(json.dumps({"type": "FeatureCollection", "features": [
        _area(499995.0, 4999931.0, 500032.0, 5000005.0, "train"), _area(500032.0, 4999931.0, 500069.0, 5000005.0,
                                                                        "val")]}))
    with pytest.warns(UserWarning, match=r"the val split holds 25 px ≥ 2 m, fewer than the 1000 needed .*"
                                         r"--split-ratios"):
        res = tile_dataset(ortho, tmp_path / "out", ndsm=heights, progress=False,
                           options=TileOptions(size=16, stride=16, min_valid=0.0,
                                               splits=SplitSpec(method="aoi", aoi=str(aoi))))
    assert res.height_summary["val"]["tall_pixels"] == 25
