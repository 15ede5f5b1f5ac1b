"""Training: configs, the loop (learning, resume, single task), checkpoints and the `train` command."""

from __future__ import annotations

import csv
import pickle
from pathlib import Path

import pytest
import torch
from helpers.tilefolder import write_tile_folder

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
@pytest.mark.parametrize("name,k", [("d3net_dfc2018", 20), ("d3net_isprs", 6), ("d3net_small_synth", None),
                                    ("small_area", None)])
def test_shipped_configs_load(name: str, k: int | None) -> None:
    cfg = load_train_config(CONFIGS / f"{name}.yaml")
    assert cfg.model.num_classes == k
    assert "predict" not in cfg.to_dict()  # predict's T is predict's option
    if name in ("d3net_dfc2018", "d3net_isprs"):  # the paper's settings
        assert cfg.model.encoder == "densenet121"
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
    with pytest.raises(ConfigError, match="cuda.*device=cpu"):
        train(tiny_cfg(device="cuda"), tiles, tmp_path / "r", max_steps=1, progress=False)


# ---- the loop -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def synth_tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 256 × 256 px synthetic town at 0.5 m tiled into 64 px patches (stride 32), 3/4 train, 1/4 val."""
    from aerialmtl.data.synth import synthesize
    from aerialmtl.tiling.splits import SplitSpec
    from aerialmtl.tiling.tile import TileOptions, tile_dataset

    root = tmp_path_factory.mktemp("synth")
    town = synthesize(root / "town", size=256, seed=1, gsd=0.5)
    tile_dataset(
        town.ortho, root / "tiles", ndsm=town.ndsm, labels=town.labels, classes=town.classes, progress=False,
        options=TileOptions(size=64, stride=32, splits=SplitSpec(block_size=64.0, ratios=(0.75, 0.25, 0.0), seed=0)),
    )
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
    from aerialmtl.cli.options import flags_for

    cfg_path = tmp_path / "c.yaml"
    cfg_path.write_text(yaml.safe_dump(tiny_cfg().to_dict()))
    run = tmp_path / "run"
    args = ["train", "--config", str(cfg_path), "--data", str(tiles), "--out", str(run), "--max-steps", "2",
            "--quiet", "--device", "cpu"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert str(run / "best.pt") in res.output and str(run / "last.pt") in res.output
    res = CliRunner().invoke(cli, args)
    assert isinstance(res.exception, OutputExistsError)  # the message names the options on the command line
    assert "--resume" in res.exception.render(flags_for("train")) and "--overwrite" in res.exception.render(
        flags_for("train"))
    res = CliRunner().invoke(cli, ["train", "--data", str(tiles), "--out", str(run), "--max-steps", "3",
                                   "--resume", "--quiet"])  # config taken from RUN/config.yaml
    assert res.exit_code == 0, res.output
    assert "after 3 steps" in res.output
    res = CliRunner().invoke(cli, args + ["--overwrite"])
    assert res.exit_code == 0 and "after 2 steps" in res.output
    res = CliRunner().invoke(cli, args[:-3] + ["--max-steps", "0"])
    assert res.exit_code == 2 and "--max-steps" in res.output


# ---- precision, compile, optimizer ----------------------------------------------------------------
def test_precision_auto_is_fp32_on_cpu_and_the_default() -> None:
    from aerialmtl.runtime import resolve_precision

    assert TrainConfig().precision == "auto"
    assert resolve_precision("auto", torch.device("cpu")) == "fp32"
    assert resolve_precision("bf16", torch.device("cpu")) == "bf16"


def test_loss_registries_match_the_config_choices() -> None:
    import typing

    from aerialmtl.training import losses
    from aerialmtl.training.config import HeightLoss, LossSection

    assert set(typing.get_args(HeightLoss)) == set(losses.HEIGHT_LOSSES)
    assert set(typing.get_args(typing.get_type_hints(LossSection)["classes"])) == set(losses.CLASS_LOSSES)


def test_weight_decay_spares_biases_batchnorm_and_task_weighting() -> None:
    from aerialmtl.models.d3net import D3Net
    from aerialmtl.training.setup import build_optimizer
    from aerialmtl.training.weighting import build_weighting

    cfg = tiny_cfg(optim={"name": "adamw", "lr": 0.1, "weight_decay": 0.5})
    model = D3Net(cfg.model.resolve(3, ("height", "classes"), 3))
    weighting = build_weighting("uncertainty", ["height", "classes"])
    opt = build_optimizer(cfg.optim, model, weighting)
    decay, rest = opt.param_groups
    assert decay["weight_decay"] == 0.5 and rest["weight_decay"] == 0.0
    n_params = len(list(model.parameters())) + len(list(weighting.parameters()))
    assert len(decay["params"]) + len(rest["params"]) == n_params
    conv = model.encoder.features.conv0.weight
    bn = model.encoder.features.norm0.weight
    log_var = weighting.log_vars["height"]
    before = {"conv": conv.detach().clone(), "bn": bn.detach().clone(), "s": log_var.detach().clone()}
    for p in list(model.parameters()) + list(weighting.parameters()):
        p.grad = torch.zeros_like(p)
    opt.step()  # zero gradients: AdamW only applies its decoupled decay, p ← p (1 − lr·wd)
    torch.testing.assert_close(conv.detach(), before["conv"] * (1 - 0.1 * 0.5))
    assert torch.equal(bn.detach(), before["bn"]) and torch.equal(log_var.detach(), before["s"])
    with pytest.raises(ConfigError, match="optim.weight_decay.*≥ 0"):
        tiny_cfg(optim={"weight_decay": -1.0})


def test_compile_failure_falls_back_to_eager(tiles: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def broken_compile(model: torch.nn.Module, **kw: object) -> object:
        def run(*a: object, **k: object) -> object:
            raise RuntimeError("no C++ compiler for inductor")
        return run

    monkeypatch.setattr(torch, "compile", broken_compile)
    with pytest.warns(UserWarning, match="compile: torch.compile failed.*no C\\+\\+ compiler.*without it"):
        res = train(tiny_cfg(compile=True), tiles, tmp_path / "r", max_steps=2, progress=False)
    assert res.step == 2 and all(v == v for v in train_losses(res.log_path))


# ---- early stopping ---------------------------------------------------------------------------------
def test_early_stopping_after_patience_validations_without_improvement(tiles: Path, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    from aerialmtl.training.trainer import Trainer

    val_losses = iter([1.0, 0.8, 0.9, 0.85, 0.7])  # best at the 2nd validation, then two worse ones

    def fake_validate(self: Trainer) -> dict[str, float]:
        v = next(val_losses)
        return {"val_loss_height": v, "val_loss_classes": v}

    monkeypatch.setattr(Trainer, "validate", fake_validate)
    cfg = tiny_cfg(schedule={"patience": 2})  # 8 patches / batch 4: a validation every 2 steps
    res = train(cfg, tiles, tmp_path / "r", progress=False)
    assert res.stopped_by == "patience" and res.step == 8
    with res.log_path.open() as fh:
        assert [int(r["step"]) for r in csv.DictReader(fh) if r["kind"] == "val"] == [2, 4, 6, 8]
    best = load_checkpoint(res.best_checkpoint)[0]["train_state"]
    assert best["step"] == 4 and best["best_score"] == pytest.approx(1.6)
    assert load_checkpoint(res.last_checkpoint)[0]["train_state"]["since_best"] == 2
    with pytest.raises(ConfigError, match="schedule.patience"):
        tiny_cfg(schedule={"patience": 0})


# ---- fine-tuning from a checkpoint (--init) -------------------------------------------------------
@pytest.fixture(scope="module")
def trained(tiles: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("init") / "run"
    return train(tiny_cfg(), tiles, run, max_steps=2, progress=False).last_checkpoint


def _retag(src: Path, dst: Path, **changes: object) -> Path:
    """A copy of tile folder ``src`` whose dataset.yaml has ``changes`` (e.g. another class scheme)."""
    import dataclasses
    import shutil

    from aerialmtl.formats.tiles import TileFolderInfo

    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("cache"))
    info = TileFolderInfo.read(dst)
    dataclasses.replace(info, **changes).write()
    return dst


def test_init_loads_what_fits_and_reinitialises_other_class_heads(trained: Path, tiles: Path, tmp_path: Path) -> None:
    from aerialmtl.classes import ClassScheme

    scheme = ClassScheme.from_dict({"name": "other", "classes": [
        {"code": 1, "name": "water", "color": [0, 0, 255]}, {"code": 2, "name": "road", "color": [90, 90, 90]},
        {"code": 3, "name": "grass", "color": [0, 200, 0]}]})
    other = _retag(tiles, tmp_path / "other", classes=scheme)
    with pytest.warns(UserWarning, match=r"init: loaded \d+ tensors.*the classes head \(the checkpoint has class "
                                         r"scheme 'toy' \(3 classes\), the tile folder class scheme 'other'"):
        # lr 1e-30: one step leaves the weights as they were loaded
        res = train(tiny_cfg(optim={"lr": 1e-30}), other, tmp_path / "ft", max_steps=1, init=trained, progress=False)
    assert res.model is not None
    source, state = load_checkpoint(trained)[0]["state_dict"], res.model.state_dict()
    for key in ("encoder.features.conv0.weight", "shared.0.up.weight", "heads.height.head.weight"):
        torch.testing.assert_close(state[key], source[key])
    assert not torch.allclose(state["heads.classes.head.weight"], source["heads.classes.head.weight"])  # afresh


def test_init_refuses_other_bands_and_architectures(trained: Path, tiles: Path, tmp_path: Path) -> None:
    from aerialmtl.errors import CheckpointError

    other = _retag(tiles, tmp_path / "bands", bands=(4, 1, 2))
    with pytest.raises(CheckpointError, match=r"init: .*bands \[1, 2, 3\].*bands \[4, 1, 2\].*same bands"):
        train(tiny_cfg(), other, tmp_path / "a", max_steps=1, init=trained, progress=False)
    with pytest.raises(CheckpointError, match=r"init: .*another architecture \(model.growth_rate: checkpoint 8, "
                                              r"config 12\).*config.yaml"):
        train(tiny_cfg(model={"growth_rate": 12}), tiles, tmp_path / "b", max_steps=1, init=trained, progress=False)


def test_init_between_lite0_configs_ignores_the_unused_densenet_fields(tiles: Path, tmp_path: Path) -> None:
    """A Lite0 start (made from one config) fine-tunes under a Lite0 recipe whose DenseNet fields, unused by
    that encoder, hold other values; a DenseNet pair with other fields is still refused (test above).
    """
    lite = {"encoder": "efficientnet_lite0", "encoder_weights": None}
    start = train(tiny_cfg(model=lite), tiles, tmp_path / "start", max_steps=1, progress=False).last_checkpoint
    res = train(tiny_cfg(model={**lite, "growth_rate": 12, "block_config": [2, 4, 6, 4]}, optim={"lr": 1e-30}),
                tiles, tmp_path / "ft", max_steps=1, init=start, progress=False)
    assert res.model is not None
    source = load_checkpoint(start)[0]["state_dict"]
    key = next(k for k in source if k.startswith("encoder.") and k.endswith(".weight"))
    torch.testing.assert_close(res.model.state_dict()[key], source[key])


def test_init_into_a_new_task_and_cli_flags(trained: Path, tmp_path: Path) -> None:
    from click.testing import CliRunner

    from aerialmtl.cli import cli

    height_only = write_tile_folder(tmp_path / "h", counts={"train": 4, "val": 0}, tasks=("height",))
    res = train(tiny_cfg(), height_only, tmp_path / "r", max_steps=1, init=trained, progress=False)  # no warning
    assert res.model is not None and tuple(res.model.tasks) == ("height",)
    runner = CliRunner()
    out = runner.invoke(cli, ["train", "--data", str(height_only), "--out", str(tmp_path / "r"), "--resume",
                              "--init", str(trained)])
    assert out.exit_code == 2 and "--resume/--init" in out.output
    out = runner.invoke(cli, ["train", "--data", str(height_only), "--out", str(tmp_path / "x"), "--init",
                              str(tmp_path / "missing.pt")])
    assert out.exit_code == 2 and "--init" in out.output and "missing.pt" in out.output


def test_sync_bn_is_a_training_option_not_saved_in_the_model(tiles: Path, tmp_path: Path) -> None:
    res = train(tiny_cfg(model={"sync_bn": True}), tiles, tmp_path / "r", max_steps=1, progress=False)
    _, meta = load_checkpoint(res.last_checkpoint)
    assert not hasattr(meta.model, "sync_bn")
    assert load_train_config(res.config_path).model.sync_bn is True  # --resume keeps it
    with pytest.raises(ConfigError, match=r"model\.sync_bn.*true or false"):
        TrainConfig.from_dict({"model": {"sync_bn": "yes"}})
