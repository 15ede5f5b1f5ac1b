"""Checkpoints written before the format module moved (format_version 1, session of 2026-11-22) still load."""

from __future__ import annotations

from pathlib import Path

import torch
from helpers.models import TINY

from aerialmtl import load_checkpoint, load_model
from aerialmtl.classes import ClassScheme
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net


def _old_payload() -> tuple[dict, D3Net]:
    """The dict ``aerialmtl.training.checkpoint.save_checkpoint`` wrote then, key for key (dropout_blocks 3 was
    the drifted default of the training config then; the old field order of ModelConfig)."""
    torch.manual_seed(3)
    scheme = ClassScheme.load("synthetic")
    scheme = ClassScheme(scheme.name, scheme.classes[:4])
    model = D3Net(ModelConfig(num_classes=4, dropout_blocks=3, **TINY)).eval()  # type: ignore[arg-type]
    old_model_cfg = {"in_channels": 3, "tasks": ["height", "classes"], "num_classes": 4, "growth_rate": 4,
                     "block_config": [1, 1, 1, 1], "num_init_features": 8, "bn_size": 2, "compression": 0.5,
                     "dropout": 0.5, "dropout_blocks": 3, "task_blocks": 2, "encoder_weights": None}
    meta = {"model": old_model_cfg, "classes": scheme.to_dict(), "bands": [1, 2, 3], "mean": [120.0, 110.0, 100.0],
            "std": [40.0, 40.0, 40.0], "gsd": 0.5, "band_names": ["r", "g", "b"], "crs": "EPSG:32631"}
    train_state = {"step": 7, "epoch": 1, "batch_in_epoch": 3, "best_score": 0.9, "ref_losses": None}
    payload = {"format": "aerialmtl-checkpoint", "format_version": 1, "aerialmtl_version": "0.1.0", "meta": meta,
               "state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()},
               "train_state": train_state}
    return payload, model


def test_a_checkpoint_of_the_previous_layout_loads_with_its_model(tmp_path: Path) -> None:
    payload, model = _old_payload()
    path = tmp_path / "best.pt"
    torch.save(payload, path)
    loaded, meta = load_model(path)
    assert meta.model.dropout_blocks == 3 and meta.gsd == 0.5 and meta.classes is not None
    assert meta.classes.num_classes == 4 and tuple(meta.bands) == (1, 2, 3)
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        ref, out = model(x), loaded(x)
    assert torch.equal(ref["height"], out["height"]) and torch.equal(ref["classes"], out["classes"])
    raw, _ = load_checkpoint(path)
    assert raw["train_state"]["batch_in_epoch"] == 3  # the old resume position is still there to read
