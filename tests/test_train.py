"""Training: configs, the loop (learning, resume, single task), checkpoints and the `train` command."""

from __future__ import annotations

import csv
import pickle
from pathlib import Path

import pytest
import torch
from tilefolder import write_tile_folder

from aerialmtl.errors import CheckpointError, ConfigError, OutputExistsError
from aerialmtl.formats.checkpoint import load_checkpoint, load_model
from aerialmtl.training.config import TrainConfig, load_train_config
from aerialmtl.training.loop import train

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
TINY_MODEL = {"growth_rate": 8, "block_config": [2, 2, 2, 2], "num_init_features": 16, "bn_size": 2}


def tiny_cfg(**over: dict) -> TrainConfig:
    base = TrainConfig.from_dict({
        "model": TINY_MODEL,
        "data": {"batch_size": 4, "num_workers": 0},
        "optim": {"lr": 2e-3},
        "schedule": {"epochs": 100, "log_every": 1},
        "seed": 0,
        "device": "cpu",
    })
    return base.with_overrides(**over) if over else base


def train_losses(log: Path) -> list[float]:
    with log.open() as fh:
        return [float(r["loss"]) for r in csv.DictReader(fh) if r["kind"] == "train"]


@pytest.fixture(scope="module")
def tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tile_folder(tmp_path_factory.mktemp("t") / "tiles", size=64, counts={"train": 8, "val": 2})


# ---- configs ------------------------------------------------------------------------------------
@pytest.mark.parametrize("name,k", [("d3net_dfc2018", 20), ("d3net_isprs", 6), ("d3net_small_synth", None)])
def test_shipped_configs_load(name: str, k: int | None) -> None:
    cfg = load_train_config(CONFIGS / f"{name}.yaml")
    assert cfg.model.num_classes == k
    assert cfg.predict.mc_samples == 30
    if name != "d3net_small_synth":  # the paper's settings
        assert cfg.model.block_config == (6, 12, 24, 16) and cfg.model.dropout == 0.5
        assert cfg.optim.lr == 2e-4 and cfg.optim.betas == (0.5, 0.999)
        assert cfg.loss.height == "l1" and cfg.weighting.method == "equal"
    model_cfg = cfg.model.resolve(3, ("height", "classes"), k or 6)
    assert model_cfg.tasks == ("height", "classes")


def test_config_errors_name_key_path(tmp_path: Path) -> None:
    text = (CONFIGS / "d3net_small_synth.yaml").read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("  lr: 1.0e-3", "  lr: 1.0e-3\n  lrr: 3"))
    with pytest.raises(ConfigError, match=r"bad.yaml.*optim\.lrr.*valid keys.*lr"):
        load_train_config(bad)
    bad.write_text(text.replace("height: l1", "height: l3"))
    with pytest.raises(ConfigError, match=r"loss\.height.*'l3'.*'berhu'"):
        load_train_config(bad)
    bad.write_text(text.replace("batch_size: 8", "batch_size: eight"))
    with pytest.raises(ConfigError, match=r"data\.batch_size.*integer"):
        load_train_config(bad)


def test_model_section_checks_data(tiles: Path) -> None:
    with pytest.raises(ConfigError, match="model.num_classes.*20.*3"):
        train(tiny_cfg(model={"num_classes": 20}), tiles, tiles.parent / "r0", max_steps=1, progress=False)
    with pytest.raises(ConfigError, match="crop_size.*multiples of 32"):
        train(tiny_cfg(data={"crop_size": 96}), tiles, tiles.parent / "r1", max_steps=1, progress=False)
    with pytest.raises(ConfigError, match="model.in_channels"):
        TrainConfig.from_dict({"model": {"in_channels": 4}}).model.resolve(3, ("height",), None)


def test_cuda_requested_without_gpu(tiles: Path, tmp_path: Path) -> None:
    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    with pytest.raises(ConfigError, match="cuda.*--device cpu"):
        train(tiny_cfg(device="cuda"), tiles, tmp_path / "r", max_steps=1, progress=False)


# ---- the loop -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def synth_tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 256 × 256 px synthetic town at 0.5 m tiled into 64 px patches (stride 32), 3/4 train, 1/4 val."""
    from aerialmtl.data.synth import synthesize
    from aerialmtl.tiling.splits import SplitSpec
    from aerialmtl.tiling.tile import tile_dataset

    root = tmp_path_factory.mktemp("synth")
    town = synthesize(root / "town", size=256, seed=1, gsd=0.5)
    tile_dataset(town.ortho, root / "tiles", ndsm=town.ndsm, labels=town.labels, classes=town.classes, size=64,
                 stride=32, splits=SplitSpec(block_size=64.0, ratios=(0.75, 0.25, 0.0), seed=0), progress=False)
    return root / "tiles"


@pytest.mark.slow  # ~7 s on an idle 2-core CPU, much more when the machine is shared
def test_training_on_synthetic_town_reduces_loss(synth_tiles: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    res = train(tiny_cfg(), synth_tiles, run, max_steps=60, progress=False)
    assert res.stopped_by == "max_steps" and res.step == 60
    for f in ("last.pt", "best.pt", "log.csv", "config.yaml"):
        assert (run / f).is_file()
    losses = train_losses(res.log_path)
    assert len(losses) == 60
    first, last = sum(losses[:5]) / 5, sum(losses[-5:]) / 5
    assert last <= 0.5 * first, (first, last)
    assert {"height_mae", "height_rmse", "oa", "miou", "score"} <= set(res.metrics)
    # best.pt holds the lowest validation score of the log
    with res.log_path.open() as fh:
        scores = [float(r["score"]) for r in csv.DictReader(fh) if r["kind"] == "val"]
    payload, meta = load_checkpoint(run / "best.pt")
    assert payload["train_state"]["best_score"] == pytest.approx(min(scores))
    assert meta.classes is not None and meta.classes.name == "synthetic" and meta.gsd == pytest.approx(0.5)
    assert len(meta.mean) == 3 and meta.crs is not None and "32631" in meta.crs
    resolved = load_train_config(res.config_path)
    assert resolved.model.in_channels == 3 and resolved.model.num_classes == 6


def test_resume_continues_identically(tiles: Path, tmp_path: Path) -> None:
    # 8 patches / batch 2 = 4 steps per epoch: stopping at step 5 is mid-epoch; jitter and learned
    # weighting exercise the RNG and the weighting state.
    cfg = tiny_cfg(data={"batch_size": 2, "jitter": True}, weighting={"method": "uncertainty"})
    full = train(cfg, tiles, tmp_path / "full", max_steps=8, progress=False)
    part = train(cfg, tiles, tmp_path / "part", max_steps=5, progress=False)
    assert part.step == 5
    resumed = train(cfg, tiles, tmp_path / "part", max_steps=8, resume=True, progress=False)
    assert resumed.step == 8
    a, b = train_losses(full.log_path), train_losses(resumed.log_path)
    assert len(a) == len(b) == 8
    assert b[5:] == pytest.approx(a[5:], rel=1e-5, abs=1e-6)
    for (k, va), vb in zip(full.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.allclose(va.float(), vb.float(), atol=1e-5), k


def test_workers_do_not_change_batches(tiles: Path, tmp_path: Path) -> None:
    cfg = tiny_cfg(data={"jitter": True})
    a = train(cfg, tiles, tmp_path / "w0", max_steps=3, progress=False)
    b = train(cfg.with_overrides(data={"num_workers": 2}), tiles, tmp_path / "w2", max_steps=3, progress=False)
    assert train_losses(b.log_path) == pytest.approx(train_losses(a.log_path), rel=1e-5)


def test_time_budget_stops_cleanly(tiles: Path, tmp_path: Path) -> None:
    res = train(tiny_cfg(), tiles, tmp_path / "r", max_time_s=1e-3, progress=False)
    assert res.stopped_by == "max_time" and res.step >= 1
    assert (tmp_path / "r" / "last.pt").is_file()


def test_checkpoint_alone_rebuilds_model(tiles: Path, tmp_path: Path) -> None:
    res = train(tiny_cfg(), tiles, tmp_path / "r", max_steps=3, progress=False)
    model, meta = load_model(res.last_checkpoint)
    ref = res.model.eval()
    x = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        a, b = ref(x), model(x)
    assert set(a) == set(b) == {"height", "classes"}
    for k in a:
        torch.testing.assert_close(a[k], b[k])
    assert meta.model.num_classes == 3 and meta.mean == pytest.approx(load_checkpoint(res.last_checkpoint)[1].mean)


class _Evil:
    def __reduce__(self):  # noqa: D105 - runs print() when unpickled
        return (print, ("code ran while loading a checkpoint",))


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
def test_checkpoint_with_code_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = tmp_path / "evil.pt"
    torch.save({"format": "aerialmtl-checkpoint", "format_version": 1, "payload": _Evil()}, path)
    with pytest.raises(CheckpointError, match="refused"):
        load_model(path)
    assert "code ran" not in capsys.readouterr().out
    # a raw pickle (not torch.save) is refused as well
    raw = tmp_path / "raw.pt"
    raw.write_bytes(pickle.dumps({"x": _Evil()}))
    with pytest.raises(CheckpointError):
        load_checkpoint(raw)


@pytest.mark.parametrize("tasks", [("height",), ("classes",)])
def test_single_task_training(tiles: Path, tmp_path: Path, tasks: tuple[str, ...]) -> None:
    res = train(tiny_cfg(model={"tasks": list(tasks)}), tiles, tmp_path / "r", max_steps=4, progress=False)
    with res.log_path.open() as fh:
        row = next(r for r in csv.DictReader(fh) if r["kind"] == "train")
    other = "classes" if tasks == ("height",) else "height"
    assert row[f"loss_{tasks[0]}"] != "" and row[f"loss_{other}"] == ""
    model, meta = load_model(res.best_checkpoint)
    assert meta.model.tasks == tasks
    with torch.no_grad():
        assert set(model(torch.zeros(1, 3, 64, 64))) == set(tasks)


def test_height_only_folder_and_bf16(tmp_path: Path) -> None:
    tiles = write_tile_folder(tmp_path / "h", counts={"train": 4, "val": 0}, tasks=("height",))
    res = train(tiny_cfg(precision="bf16", loss={"height": "berhu"}), tiles, tmp_path / "r", max_steps=2,
                progress=False)
    assert res.step == 2 and "height" in res.model.tasks  # no val split: scored by the training loss
    assert all(v == v for v in train_losses(res.log_path))  # finite (not NaN)


def test_balanced_class_weights(tiles: Path, tmp_path: Path) -> None:
    from aerialmtl.data.dataset import read_tile_info
    from aerialmtl.training.objective import class_weights as _class_weights

    w = _class_weights(tiny_cfg(loss={"class_weights": "balanced"}), read_tile_info(tiles), 3)
    assert w is not None and w.shape == (3,) and w.mean() == pytest.approx(1.0)
    assert w[0] < w[1]  # ground is the most frequent class of the toy scene, so it weighs least
    with pytest.raises(ConfigError, match="class_weights.*2 weights.*3 classes"):
        _class_weights(tiny_cfg(loss={"class_weights": [1.0, 2.0]}), read_tile_info(tiles), 3)


# ---- the command --------------------------------------------------------------------------------
def test_cli_train_and_refuse_reuse(tiles: Path, tmp_path: Path) -> None:
    import yaml
    from click.testing import CliRunner

    from aerialmtl.cli import cli

    cfg_path = tmp_path / "c.yaml"
    cfg_path.write_text(yaml.safe_dump(tiny_cfg().to_dict()))
    run = tmp_path / "run"
    args = ["train", "--config", str(cfg_path), "--data", str(tiles), "--out", str(run), "--max-steps", "2",
            "--quiet", "--device", "cpu"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert str(run / "best.pt") in res.output and str(run / "last.pt") in res.output
    res = CliRunner().invoke(cli, args)
    assert isinstance(res.exception, OutputExistsError) and "--resume" in str(res.exception)
    res = CliRunner().invoke(cli, ["train", "--data", str(tiles), "--out", str(run), "--max-steps", "3",
                                   "--resume", "--quiet"])  # config taken from RUN/config.yaml
    assert res.exit_code == 0, res.output
    assert "after 3 steps" in res.output
    res = CliRunner().invoke(cli, args + ["--overwrite"])
    assert res.exit_code == 0 and "after 2 steps" in res.output
    res = CliRunner().invoke(cli, args[:-3] + ["--max-steps", "0"])
    assert res.exit_code == 2 and "--max-steps" in res.output
