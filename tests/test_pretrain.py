"""Synthetic pretraining (aerialmtl.training.pretrain): corpus → tiles → a checkpoint at the asked GSD."""

from __future__ import annotations

from pathlib import Path

import pytest

from aerialmtl.errors import InputError, OutputExistsError
from aerialmtl.formats.checkpoint import load_model
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.pretrain import PretrainSettings, pretrain_synthetic

TINY = TrainConfig.from_dict({
    "model": {"growth_rate": 8, "block_config": [2, 2, 2, 2], "num_init_features": 16, "bn_size": 2},
    "data": {"batch_size": 2, "num_workers": 0},
    "schedule": {"epochs": 1},
    "device": "cpu",
})


def test_pretraining_writes_a_multitask_checkpoint_at_the_gsd(tmp_path: Path) -> None:
    settings = PretrainSettings(gsd=0.6, towns=2, town_size=96, patch=64, crs="EPSG:2994")
    lines: list[str] = []
    res = pretrain_synthetic(tmp_path / "pre", settings, TINY, max_steps=2, progress=False, log=lines.append)
    assert res.checkpoint.is_file() and res.checkpoint == tmp_path / "pre" / "run" / "best.pt"
    assert res.train.step == 2 and res.patches["train"] > 0
    model, meta = load_model(res.checkpoint)
    assert meta.gsd == pytest.approx(0.6)  # metres, although the corpus CRS is in feet
    assert tuple(meta.model.tasks) == ("height", "classes") and meta.classes is not None
    assert any("2 towns" in line for line in lines)
    with pytest.raises(OutputExistsError, match="overwrite"):
        pretrain_synthetic(tmp_path / "pre", settings, TINY, max_steps=1, progress=False)


def test_settings_are_checked() -> None:
    with pytest.raises(InputError, match="multiple of 32"):
        PretrainSettings(gsd=0.5, patch=100)
    with pytest.raises(InputError, match="town_size"):
        PretrainSettings(gsd=0.5, patch=256, town_size=128)
    with pytest.raises(InputError, match="gsd"):
        PretrainSettings(gsd=0.0)
