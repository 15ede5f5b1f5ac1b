"""``optim.ema`` (a weight average in the checkpoints) and ``schedule.lr_schedule``/``warmup_steps``: what a
user relies on — the checkpoint holds the average, a resumed run continues exactly, the log shows the
learning rate the schedule says, and bad values are refused naming the key.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch
from helpers.tilefolder import write_tile_folder

from aerialmtl.errors import ConfigError
from aerialmtl.formats.checkpoint import load_checkpoint
from aerialmtl.training.averaging import WeightAverage
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.loop import train
from aerialmtl.training.lr_schedule import lr_factor

TINY = {"growth_rate": 8, "block_config": [2, 2, 2, 2], "num_init_features": 16, "bn_size": 2}


def cfg(**over: dict) -> TrainConfig:
    base = TrainConfig.from_dict({
        "model": TINY, "data": {"batch_size": 2, "num_workers": 0, "jitter": True},
        "optim": {"lr": 2e-3, "ema": 0.9},
        "schedule": {"epochs": 100, "log_every": 1, "lr_schedule": "cosine", "warmup_steps": 3},
        "seed": 0, "device": "cpu", "calibration": {"enabled": False},
    })
    return base.with_overrides(**over) if over else base


@pytest.fixture(scope="module")
def tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tile_folder(tmp_path_factory.mktemp("t") / "tiles", size=64, counts={"train": 8, "val": 2})


def log_rows(path: Path, kind: str) -> list[dict[str, str]]:
    with path.open() as fh:
        return [r for r in csv.DictReader(fh) if r["kind"] == kind]


def test_lr_factor_warms_up_then_decays_to_near_zero() -> None:
    assert [lr_factor(s, 10, "constant", 4) for s in range(5)] == [0.25, 0.5, 0.75, 1.0, 1.0]
    cos = [lr_factor(s, 10, "cosine", 2) for s in range(10)]
    assert cos[2] == 1.0 and all(a > b for a, b in zip(cos[2:], cos[3:]))
    assert 0 < cos[-1] < 0.05
    assert lr_factor(50, 10, "cosine") == lr_factor(9, 10, "cosine")  # beyond the plan: the last rate, not 0 or < 0


def test_average_moves_towards_the_weights_and_restores_them() -> None:
    model = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.BatchNorm1d(2))
    avg = WeightAverage(model, 0.75)
    start = model[0].weight.detach().clone()
    with torch.no_grad():
        model[0].weight.add_(4.0)
    avg.update(model)
    assert torch.allclose(avg.shadow["0.weight"], start + 1.0)  # 0.75 · w + 0.25 · (w + 4)
    assert avg.shadow["1.num_batches_tracked"].dtype == torch.long
    with avg.applied(model) as raw:
        assert torch.allclose(model[0].weight, start + 1.0)
        assert torch.allclose(raw["0.weight"], start + 4.0)
    assert torch.allclose(model[0].weight, start + 4.0)


def test_checkpoints_hold_the_average_and_the_log_the_schedule(tiles: Path, tmp_path: Path) -> None:
    res = train(cfg(schedule={"max_steps": 8}), tiles, tmp_path / "r", progress=False)
    payload, _ = load_checkpoint(tmp_path / "r" / "last.pt")
    raw = payload["train_state"]["raw_weights"]
    averaged = payload["state_dict"]
    moved = [k for k in raw if raw[k].is_floating_point() and not torch.equal(raw[k], averaged[k])]
    assert moved, "last.pt's weights are the trained ones, not their average"
    for k, v in res.model.state_dict().items():  # the returned model is last.pt's (the average)
        assert torch.equal(v, averaged[k]), k
    best, _ = load_checkpoint(tmp_path / "r" / "best.pt")
    assert "raw_weights" not in best["train_state"]  # best.pt is for predict: no second copy of the weights
    lrs = [float(r["lr"]) for r in log_rows(res.log_path, "train")]  # the row of step s: the rate step s used
    assert lrs == pytest.approx([2e-3 * lr_factor(s, 8, "cosine", 3) for s in range(8)], rel=1e-6)
    assert lrs[:3] == pytest.approx([2e-3 / 3, 4e-3 / 3, 2e-3], rel=1e-6)  # the warm-up


def test_resume_with_average_continues_identically(tiles: Path, tmp_path: Path) -> None:
    plan = cfg(schedule={"max_steps": 8})  # the cosine spans the config's 8 steps; the first call stops at 5
    full = train(plan, tiles, tmp_path / "full", progress=False)
    train(plan, tiles, tmp_path / "part", max_steps=5, progress=False)
    resumed = train(plan, tiles, tmp_path / "part", resume=True, progress=False)
    a = [float(r["loss"]) for r in log_rows(full.log_path, "train")]
    b = [float(r["loss"]) for r in log_rows(resumed.log_path, "train")]
    assert b[5:] == pytest.approx(a[5:], rel=1e-5, abs=1e-6)
    for (k, va), vb in zip(full.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.allclose(va.float(), vb.float(), atol=1e-5), k


@pytest.mark.parametrize("section,value,match", [
    ("optim", {"ema": 1.0}, r"optim\.ema.*\(0, 1\)"),
    ("optim", {"ema": 0.0}, r"optim\.ema"),
    ("schedule", {"warmup_steps": -1}, r"schedule\.warmup_steps"),
    ("schedule", {"lr_schedule": "step"}, r"schedule\.lr_schedule.*cosine"),
])
def test_bad_values_are_refused_naming_the_key(section: str, value: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        cfg(**{section: value})


def test_without_average_the_run_is_the_papers(tiles: Path, tmp_path: Path) -> None:
    res = train(cfg(optim={"ema": None}, schedule={"lr_schedule": "constant", "warmup_steps": 0}), tiles,
                tmp_path / "r", max_steps=3, progress=False)
    payload, _ = load_checkpoint(tmp_path / "r" / "last.pt")
    assert "raw_weights" not in payload["train_state"]
    assert {float(r["lr"]) for r in log_rows(res.log_path, "train")} == {2e-3}
    assert math.isfinite(res.best_score)
