"""`aerialmtl pretrain`: synthetic batches made on the fly, resume, the exported start and its card, `train --init
NAME`, and predict saying that a start is not fine-tuned."""

from __future__ import annotations

import csv
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from affine import Affine
from helpers.cli import run_cli
from helpers.rasters import write_raster
from helpers.tilefolder import write_tile_folder
from test_sanity import one_error_line

from aerialmtl.data.synth.textures import TexturePool
from aerialmtl.data.synthetic_batches import SyntheticBatches, SyntheticStream
from aerialmtl.errors import CheckpointError, ConfigError, InputError, NonFiniteError, OutputExistsError
from aerialmtl.formats import starts
from aerialmtl.formats.checkpoint import load_checkpoint
from aerialmtl.formats.tiles import read_manifest
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.loop import train
from aerialmtl.training.lr_schedule import lr_factor
from aerialmtl.training.objective import Objective
from aerialmtl.training.pretrain import LAST_PT, PretrainSettings, pretrain
from aerialmtl.training.steploop import StepLoop

ROOT = Path(__file__).resolve().parents[1]

TINY_MODEL = {"growth_rate": 8, "block_config": [2, 2, 2, 2], "num_init_features": 16, "bn_size": 2,
              "aleatoric": True}
STREAM = SyntheticStream(patch_size=32, scene_size=64, gsd_range=(0.5, 1.0), scenes_per_step=2, scene_reuse=2)


def tiny_cfg() -> TrainConfig:
    return TrainConfig.from_dict({"model": TINY_MODEL, "data": {"batch_size": 2, "num_workers": 0},
                                  "optim": {"lr": 1e-3}, "schedule": {"log_every": 1}, "seed": 3, "device": "cpu"})


def settings(steps: int) -> PretrainSettings:
    return PretrainSettings(steps=steps, checkpoint_every=2, name="tiny-start", stream=STREAM)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("pre") / "run"
    pretrain(tiny_cfg(), out, settings(4), progress=False)
    return out


def test_synthetic_batches_depend_only_on_seed_and_step() -> None:
    stream = SyntheticStream(seed=1, batch_size=3, patch_size=32, scene_size=64)
    a, b = SyntheticBatches(stream, (127.0,) * 3, (128.0,) * 3, 10), SyntheticBatches(stream, (127.0,) * 3,
                                                                                      (128.0,) * 3, 10)
    b[7]  # another scene in b's memory first: the batch of a step does not depend on what was made before
    x, y = a[5], b[5]
    assert all(torch.equal(x[k], y[k]) for k in x)
    assert x["image"].shape == (3, 3, 32, 32) and x["height"].shape == (3, 1, 32, 32)
    assert x["classes"].dtype == torch.int64 and set(x["classes"].unique().tolist()) <= set(range(6)) | {255}
    assert not torch.equal(a[6]["image"], x["image"])


def test_interrupted_pretraining_resumes_to_the_same_weights(run: Path, tmp_path: Path) -> None:
    part = tmp_path / "part"
    first = pretrain(tiny_cfg(), part, settings(2), progress=False)
    assert first.step == 2
    with pytest.raises(OutputExistsError, match="resume"):
        pretrain(tiny_cfg(), part, settings(4), progress=False)
    payload = torch.load(part / LAST_PT, weights_only=False)
    payload["train_state"]["wall_time_s"] = 1000.0  # as if the first part had run for 1000 s
    torch.save(payload, part / LAST_PT)
    resumed = pretrain(tiny_cfg(), part, settings(4), resume=True, progress=False)
    assert (resumed.step, resumed.steps_this_call) == (4, 2)
    full, again = load_checkpoint(run / LAST_PT)[0], load_checkpoint(part / LAST_PT)[0]
    for k, v in full["state_dict"].items():
        assert torch.equal(v, again["state_dict"][k]), k

    def rows(folder: Path) -> list[list[str]]:  # the log without its time column
        return [ln.split(",")[:3] + ln.split(",")[4:8] for ln in (folder / "log.csv").read_text().splitlines()[1:]]

    assert [r[1] for r in rows(part)] == ["1", "2", "3", "4"] and rows(part) == rows(run)
    times = [float(ln.split(",")[3]) for ln in (part / "log.csv").read_text().splitlines()[1:]]
    assert times[1] < 1000 < times[2] <= times[3] <= resumed.wall_time_s  # the run's time: it goes on when resumed


def test_a_run_started_by_an_earlier_version_resumes_and_a_changed_value_refuses(tmp_path: Path) -> None:
    """A pretraining run is long: one whose config predates a key added since (today's default fills it) or holds
    a retired one resumes after an upgrade; a value changed since still refuses, naming the config."""
    part = tmp_path / "part"
    pretrain(tiny_cfg(), part, settings(2), progress=False)
    payload = torch.load(part / LAST_PT, weights_only=False)
    old = payload["train_state"]["config"]
    added = next(k for k, v in old.items() if isinstance(v, dict) and k not in ("model", "data", "optim"))
    old.pop(added)
    old["predict"] = {"mc_samples": 30}  # a section an earlier version wrote
    torch.save(payload, part / LAST_PT)
    with pytest.warns(FutureWarning, match="predict"):
        resumed = pretrain(tiny_cfg(), part, settings(3), resume=True, progress=False)
    assert resumed.step == 3
    payload = torch.load(part / LAST_PT, weights_only=False)
    payload["train_state"]["config"]["optim"]["lr"] = 5e-4
    torch.save(payload, part / LAST_PT)
    with pytest.raises(CheckpointError, match="another config"):
        pretrain(tiny_cfg(), part, settings(4), resume=True, progress=False)


def test_the_start_is_small_weights_only_and_carded(run: Path) -> None:
    path = run / "tiny-start.pt"
    assert path.stat().st_size <= starts.MAX_BYTES
    payload = torch.load(path, weights_only=True)
    assert payload["train_state"] is None
    floats = [v for v in payload["state_dict"].values() if v.is_floating_point()]
    assert floats and all(v.dtype == torch.float16 for v in floats)
    meta = load_checkpoint(path)[1]
    assert meta.start == "tiny-start" and meta.classes is not None and meta.classes.name == "synthetic"
    card = yaml.safe_load((run / "tiny-start.yaml").read_text())
    assert card["name"] == "tiny-start" and card["sha256"] == starts.file_sha256(path)
    assert "not a map of anywhere" in card["intended_use"]
    assert card["training"]["steps"] == 4 and card["training"]["seed"] == 3
    assert card["training"]["wall_time_s"] > 0 and card["training"]["machine"]["cpu"]
    assert card["pretrained_cfg"]["input_size"] == [3, 32, 32] and card["trained_on"]["real_data"].startswith("none")


def test_init_resolves_a_shipped_start_by_name(run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                              capsys: pytest.CaptureFixture) -> None:
    shipped = tmp_path / "starts"
    shipped.mkdir()
    for suffix in (".pt", ".yaml"):
        shutil.copy(run / f"tiny-start{suffix}", shipped / f"tiny-start{suffix}")
    monkeypatch.setattr(starts, "STARTS_DIR", shipped)
    assert starts.shipped_starts() == {"tiny-start": shipped / "tiny-start.pt"}
    assert starts.resolve_start("tiny-start") == shipped / "tiny-start.pt"
    with pytest.raises(CheckpointError, match=r"shipped starts: tiny-start"):
        starts.resolve_start("no-such-start")
    code, out, err = run_cli(capsys, "train", "--config", tmp_path / "none.yaml", "--init", "no-such-start",
                             "--out", tmp_path / "x")
    assert code == 2 and "--init" in err and "tiny-start" in err
    tiles = write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 4})
    cfg = TrainConfig.from_dict({**tiny_cfg().to_dict(), "calibration": {"enabled": False}})
    with pytest.warns(UserWarning, match=r"the classes head \(the checkpoint has class scheme 'synthetic'"):
        res = train(cfg, tiles, tmp_path / "ft", max_steps=1, progress=False, init="tiny-start")
    tuned = load_checkpoint(res.last_checkpoint)[1]
    assert tuned.start is None  # fine-tuned on its tile folder: no longer the start


def test_predict_says_once_that_a_start_is_not_fine_tuned(run: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture) -> None:
    rng = np.random.default_rng(0)
    ortho = write_raster(tmp_path / "ortho.tif", rng.integers(0, 255, (3, 64, 64), dtype=np.uint8),
                         transform=Affine(1.0, 0, 500000.0, 0, -1.0, 5000000.0))
    code, out, err = run_cli(capsys, "predict", ortho, "--model", run / "tiny-start.pt", "--out", tmp_path / "p",
                             "--mc", 2, "--engine", "torch", "--quiet")
    assert code == 0, err
    assert (out + err).count("pretrained start 'tiny-start'") == 1 and "not a map of anywhere" in out + err
    info = json.loads((tmp_path / "p" / "prediction.json").read_text())
    assert info["model"]["start"] == "tiny-start"
    code, out, err = run_cli(capsys, "predict", ortho, "--model", run / LAST_PT, "--out", tmp_path / "q", "--mc", 1,
                             "--engine", "torch", "--quiet")
    assert code == 0 and "pretrained start" in out + err  # the pretraining run's own checkpoint is not fine-tuned


def _tiles_with_white_validation(root: Path) -> Path:
    """A tile folder whose validation images are pure white on flat ground: a white texture can only come from them."""
    write_tile_folder(root, counts={"train": 3, "val": 2, "test": 0}, invalid_corner=False)
    import rasterio

    for row in read_manifest(root, "val"):
        with rasterio.open(root / row["image_path"], "r+") as dst:
            dst.write(np.full((3, dst.height, dst.width), 255, np.uint8))
        with rasterio.open(root / row["height_path"], "r+") as dst:
            dst.write(np.zeros((1, dst.height, dst.width), np.float32))
    return root


def test_textures_come_from_the_training_ground_of_a_tile_folder(tmp_path: Path) -> None:
    tiles = _tiles_with_white_validation(tmp_path / "tiles")
    pool = TexturePool.from_tile_folder(tiles, max_patches=64)
    assert pool.patches.shape[1:] == (3, 16, 16) and pool.gsd == 0.5
    # the toy ground is red ≈ 60, green ≈ 80; buildings (red 180) and trees (green 180) stand above 0.5 m
    assert pool.patches[:, 0].max() < 100 and pool.patches[:, 1].max() < 120
    assert (pool.patches < 255).all()  # nothing of the validation split
    again = TexturePool.from_tile_folder(tiles, max_patches=64)
    assert np.array_equal(pool.patches, again.patches)  # seeded
    write_tile_folder(tmp_path / "no_heights", tasks=("classes",))
    with pytest.raises(InputError, match="need 8-bit RGB patches with heights"):
        TexturePool.from_tile_folder(tmp_path / "no_heights")


def test_textured_scenes_wear_the_users_ground_and_stay_a_function_of_seed_and_step(tmp_path: Path) -> None:
    tiles = _tiles_with_white_validation(tmp_path / "tiles")
    plain = SyntheticStream(seed=1, batch_size=2, patch_size=32, scene_size=64)
    textured = dataclasses.replace(plain, textures=str(tiles), texture_share=1.0)
    a = SyntheticBatches(textured, (127.0,) * 3, (128.0,) * 3, 4)
    b = SyntheticBatches(textured, (127.0,) * 3, (128.0,) * 3, 4)
    p = SyntheticBatches(plain, (127.0,) * 3, (128.0,) * 3, 4)
    assert torch.equal(a[2]["image"], b[2]["image"])
    assert not torch.equal(a[2]["image"], p[2]["image"])
    assert torch.equal(a[2]["height"] > 1.0, p[2]["height"] > 1.0)  # the same city's structures, other surfaces
    with pytest.raises(ConfigError, match="texture_share"):
        dataclasses.replace(plain, texture_share=1.5)


def test_pretrain_with_textures_records_them_in_the_card(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    tiles = _tiles_with_white_validation(tmp_path / "tiles")
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(yaml.safe_dump(tiny_cfg().to_dict()))
    code, out, err = run_cli(capsys, "pretrain", "--out", tmp_path / "run", "--steps", 1, "--config", cfg,
                             "--patch-size", 32, "--scene-size", 64, "--textures", tiles, "--name", "tex", "--quiet")
    assert code == 0, err
    card = yaml.safe_load((tmp_path / "run" / "tex.yaml").read_text())
    real = card["trained_on"]["real_data"]["textures"]
    assert real["folder"] == str(tiles.resolve()) and real["split"] == "train" and len(real["fingerprint"]) == 64
    assert "own licence" in card["meta"]["license"]
    code, out, err = run_cli(capsys, "pretrain", "--out", tmp_path / "mixed", "--steps", 1, "--config", cfg,
                             "--patch-size", 32, "--scene-size", 64, "--real", tiles, "--name", "mixed", "--quiet")
    assert code == 0, err
    real = yaml.safe_load((tmp_path / "mixed" / "mixed.yaml").read_text())["trained_on"]["real_data"]
    assert set(real) == {"patches"} and real["patches"]["per_batch"] == 1  # a quarter of a batch of 2, at least 1
    assert "own licence" in yaml.safe_load((tmp_path / "mixed" / "mixed.yaml").read_text())["meta"]["license"]
    code, out, err = run_cli(capsys, "pretrain", "--out", tmp_path / "run3", "--steps", 1, "--config", cfg,
                             "--real-share", 0.5, "--quiet")
    assert code == 2 and "--real-share applies to the tile folder of --real" in err  # not silently ignored
    assert not (tmp_path / "run3").exists()
    code, out, err = run_cli(capsys, "pretrain", "--out", tmp_path / "run2", "--steps", 1, "--config", cfg,
                             "--textures", tmp_path / "nowhere", "--quiet")
    assert code == 2 and "--textures" in err


def test_real_patches_fill_their_share_of_each_batch_with_heights_and_no_labels(tmp_path: Path) -> None:
    tiles = write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 3, "val": 1, "test": 0})
    stream = SyntheticStream(seed=2, batch_size=4, patch_size=32, scene_size=64, real=str(tiles), real_share=0.5)
    assert stream.real_count() == 2
    a, b = SyntheticBatches(stream, (127.0,) * 3, (128.0,) * 3, 4), SyntheticBatches(stream, (127.0,) * 3,
                                                                                      (128.0,) * 3, 4)
    x = a[1]
    assert all(torch.equal(x[k], b[1][k]) for k in x)  # a function of (seed, step)
    real_heights = x["height"][:2][x["height_valid"][:2]]
    assert set(real_heights.unique().tolist()) <= {0.0, 4.0, 8.0}  # the toy tiles' heights
    assert (x["classes"][:2] == 255).all() and (x["classes"][2:] != 255).any()  # labels of the other scheme unused
    assert not (x["height"][2:] == 4.0).all()
    with pytest.raises(InputError, match="--patch-size"):
        SyntheticBatches(dataclasses.replace(stream, patch_size=96, scene_size=96), (127.0,) * 3, (128.0,) * 3, 2)
    plain = dataclasses.replace(stream, real=None)
    assert plain.real_count() == 0


# ---- one training loop: pretraining applies every step key as train does (issue 47) -----------------------
def test_pretrain_applies_the_weight_average_and_the_cosine_schedule(tmp_path: Path) -> None:
    """optim.ema and a warmed-up cosine mean in pretrain what they mean in train: the log's lr follows the schedule,
    last.pt and the exported start hold the average, and an interrupted run resumes to the same start."""
    cfg = tiny_cfg().with_overrides(optim={"lr": 1e-3, "ema": 0.5},
                                    schedule={"lr_schedule": "cosine", "warmup_steps": 2})
    full = pretrain(cfg, tmp_path / "full", settings(6), progress=False)
    with (tmp_path / "full" / "log.csv").open() as fh:
        rows = [r for r in csv.DictReader(fh) if r["kind"] == "train"]
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4, 5, 6]
    expected = [1e-3 * lr_factor(s, 6, "cosine", 2) for s in range(6)]  # the row of step s + 1: the rate it used
    assert [float(r["lr"]) for r in rows] == pytest.approx(expected, rel=1e-9)
    assert expected[0] < expected[1] == expected[2] == 1e-3 > expected[3] > expected[5] > 0
    payload = load_checkpoint(full.last_checkpoint)[0]
    averaged, raw = payload["state_dict"], payload["train_state"]["raw_weights"]
    moved = [k for k, v in raw.items() if v.is_floating_point() and not torch.equal(v, averaged[k])]
    assert moved, "last.pt holds the trained weights, not their average"
    start = torch.load(full.start, weights_only=True)["state_dict"]
    for k in moved:  # the start is the average (stored as float16)
        assert torch.equal(start[k], averaged[k].half()), k
    part = tmp_path / "part"
    pretrain(cfg, part, settings(3), progress=False)
    again = pretrain(cfg, part, settings(6), resume=True, progress=False)
    resumed = load_checkpoint(again.last_checkpoint)[0]
    for k, v in averaged.items():
        assert torch.equal(v, resumed["state_dict"][k]), k
    assert torch.equal(torch.load(again.start, weights_only=True)["state_dict"][moved[0]], start[moved[0]])


@pytest.mark.parametrize(("section", "value", "key"), [
    ("schedule", {"patience": 3}, "schedule.patience"),
    ("schedule", {"max_time_s": 60.0}, "schedule.max_time_s"),
    ("data", {"copy_paste": {"prob": 0.5}}, "data.copy_paste.prob"),
])
def test_keys_pretraining_cannot_apply_are_refused_by_name(tmp_path: Path, section: str, value: dict,
                                                           key: str) -> None:
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        pretrain(tiny_cfg().with_overrides(**{section: value}), tmp_path / "run", settings(2), progress=False)
    assert not (tmp_path / "run").exists()


def test_a_diverging_pretraining_stops_like_train_and_keeps_the_last_good_checkpoint(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    run = tmp_path / "run"
    pretrain(tiny_cfg(), run, settings(2), progress=False)
    good = torch.load(run / LAST_PT, weights_only=False)["state_dict"]
    real = Objective.__call__

    def poisoned(self: Objective, out: dict, batch: dict, scoring: bool = False) -> dict:
        return {t: v * float("nan") for t, v in real(self, out, batch, scoring).items()}

    monkeypatch.setattr(Objective, "__call__", poisoned)
    with pytest.raises(NonFiniteError, match=r"training diverged at step 3: the loss is nan .*keeps step 2"):
        pretrain(tiny_cfg(), run, settings(4), resume=True, progress=False)
    kept = torch.load(run / LAST_PT, weights_only=False)["state_dict"]
    assert all(torch.equal(v, kept[k]) for k, v in good.items())


def test_the_paper_network_is_refused_before_the_first_step_when_its_start_cannot_be_exported(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The DenseNet-121 D3-Net (24.7 M weights, 47 MiB in float16) is larger than a start may be: said at once."""
    paper = TrainConfig.from_dict({**yaml.safe_load((ROOT / "configs" / "d3net_dfc2018.yaml").read_text()),
                                   "device": "cpu"}).with_overrides(model={"num_classes": None},
                                                                    data={"batch_size": 1, "num_workers": 0})

    def no_step(*args: object) -> None:
        raise AssertionError("a step ran before the export was checked")

    monkeypatch.setattr(StepLoop, "train_step", no_step)
    with pytest.raises(CheckpointError, match=r"would be 4\d\.\d MiB, more than the 30 MiB"):
        pretrain(paper, tmp_path / "run", settings(2), progress=False)
    assert not (tmp_path / "run").exists()


# ---- a folder's own files and its lock (issue 49) -----------------------------------------------------------
@pytest.mark.parametrize("name", ["last", "config", "log", "best", "dataset"])
def test_a_start_name_that_is_a_run_or_tile_folder_file_is_refused(name: str) -> None:
    with pytest.raises(InputError, match=f"name '{name}' would write the start over a run's or a tile folder's"):
        PretrainSettings(steps=1, name=name)


def test_pretrain_never_replaces_a_file_it_did_not_write(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(yaml.safe_dump(tiny_cfg().to_dict()))
    tiles = write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 4})
    manifest = (tiles / "dataset.yaml").read_bytes()
    base = ("pretrain", "--steps", 1, "--config", cfg, "--patch-size", 32, "--scene-size", 64, "--quiet")
    for extra, needle, code in ((("--out", tiles, "--real", tiles, "--name", "dataset"), "start over", 2),
                                (("--out", tiles, "--name", "dataset"), "would write the start over", 2),
                                (("--out", tiles, "--real", tiles, "--name", "mine"), "is the input", 2)):
        one_error_line(run_cli(capsys, *base, *extra), needle, code=code)
    assert (tiles / "dataset.yaml").read_bytes() == manifest and not (tiles / "mine.pt").exists()
    # a file of the user's at the start's path: refused before any step, kept
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.yaml").write_text("my: notes\n")
    one_error_line(run_cli(capsys, *base, "--out", mine, "--name", "notes"), "notes.yaml", "not a start",
                   "pass another --name")
    assert (mine / "notes.yaml").read_text() == "my: notes\n" and not (mine / LAST_PT).exists()
    # a training run's folder: its checkpoints are not pretraining's to replace, even with --overwrite
    trained = tmp_path / "trained"
    trained.mkdir()
    (trained / "best.pt").write_bytes(b"a training run's")
    one_error_line(run_cli(capsys, *base, "--out", trained, "--overwrite"), "best.pt", "aerialmtl train")
    assert (trained / "best.pt").read_bytes() == b"a training run's" and not (trained / LAST_PT).exists()
    # the same start name again in its own run folder is replaced (the run is started again)
    assert run_cli(capsys, *base, "--out", tmp_path / "again", "--name", "s")[0] == 0
    assert run_cli(capsys, *base, "--out", tmp_path / "again", "--name", "s", "--overwrite")[0] == 0


def test_a_running_job_holds_the_folder_against_pretrain(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Two pretrain runs into one folder, or pretrain --overwrite into a running train --resume: the second
    is refused naming the first, and nothing of the folder changes."""
    from test_outputs import _hold_lock

    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(yaml.safe_dump(tiny_cfg().to_dict()))
    run = tmp_path / "run"
    base = ("pretrain", "--steps", 1, "--config", cfg, "--patch-size", 32, "--scene-size", 64, "--quiet",
            "--out", run)
    assert run_cli(capsys, *base)[0] == 0
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    for command, extra in (("pretrain", ("--resume", "--steps", 2)), ("train", ("--overwrite",))):
        holder = _hold_lock(run, command)
        try:
            one_error_line(run_cli(capsys, *base, *extra), f"in use by aerialmtl {command} (PID {holder.pid} ",
                           "wait for it to finish")
        finally:
            holder.kill()
            holder.wait()
        assert {p.name: p.read_bytes() for p in run.iterdir() if p.name in before} == before


@pytest.mark.parametrize("damage", ["utf16", "step"])
def test_resume_with_a_damaged_log_names_the_file_and_the_fix(tmp_path: Path, damage: str) -> None:
    run = tmp_path / "run"
    pretrain(tiny_cfg(), run, settings(2), progress=False)
    log = run / "log.csv"
    text = log.read_text(encoding="utf-8")
    if damage == "utf16":
        log.write_text(text, encoding="utf-16")
        match = r"log\.csv' is not UTF-8 text .*save it as UTF-8, or move it away"
    else:
        lines = text.splitlines(keepends=True)
        lines[2] = lines[2].replace(",2,", ",two,", 1)
        log.write_text("".join(lines), encoding="utf-8")
        match = r"log\.csv' line 3: step 'two' is not a number; .*move .* away"
    with pytest.raises(InputError, match=match):
        pretrain(tiny_cfg(), run, settings(3), resume=True, progress=False)
    log.unlink()  # the fix the message names: the resumed run starts a new log
    assert pretrain(tiny_cfg(), run, settings(3), resume=True, progress=False).step == 3
    assert [ln.split(",")[1] for ln in log.read_text().splitlines()[1:]] == ["3"]
