"""The height-bin head (``model.aleatoric: true`` with ``model.height_bins: K``): bin logits trained with
cross-entropy beside the L1 height, and a spread from the bins' second moment around the height, which can
be large where the network hesitates between the ground and a tall object."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from helpers.cli import run_cli
from helpers.models import TINY
from helpers.rasters import write_raster

from aerialmtl.classes import ClassScheme
from aerialmtl.errors import ConfigError
from aerialmtl.formats.checkpoint import ModelMeta, save_checkpoint
from aerialmtl.models.config import HEIGHT_BINS, HEIGHT_LAPLACE, HEIGHT_SCALE, ModelConfig
from aerialmtl.models.d3net import SCALE_MIN, D3Net
from aerialmtl.models.height_bins import bin_edges, bin_index, bins_scale, second_moment
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.losses import height_bins_ce, l1, laplace_nll
from aerialmtl.training.objective import Objective


def _bins_model(k: int = 3, bins: int = 8) -> tuple[D3Net, ModelMeta]:
    torch.manual_seed(0)
    scheme = ClassScheme.load("synthetic")
    scheme = ClassScheme(scheme.name, scheme.classes[:k])
    cfg = ModelConfig(num_classes=k, aleatoric=True, height_bins=bins, height_bin_max=30.0,
                      **TINY)  # type: ignore[arg-type]
    meta = ModelMeta(cfg, scheme, (1, 2, 3), (120.0, 110.0, 100.0), (40.0, 40.0, 40.0), 0.5, ("r", "g", "b"))
    return D3Net(cfg).eval(), meta


def test_bins_cover_zero_to_the_top_and_clamp_heights_outside() -> None:
    e = bin_edges(8, 30.0)
    assert e.shape == (9,) and e[0] == 0 and e[-1] == pytest.approx(30.0)
    w = e[1:] - e[:-1]
    assert (w[1:] > w[:-1]).all()  # narrow near the ground, wide for tall objects
    h = torch.tensor([-2.0, 0.0, float(e[3]) - 1e-3, float(e[3]), 29.9, 30.0, 250.0])
    assert bin_index(h, e).tolist() == [0, 0, 2, 3, 7, 7, 7]


def test_second_moment_of_one_bin_and_of_two_modes() -> None:
    e = bin_edges(8, 30.0)
    c = 0.5 * (e[1:] + e[:-1])
    w2 = (e[1:] - e[:-1]) ** 2 / 12
    one = torch.full((1, 8, 1, 1), -50.0)
    one[0, 5] = 50.0  # all the mass in bin 5
    mu = torch.full((1, 1, 1, 1), float(c[5]) + 2.0)
    assert second_moment(one, mu, e).item() == pytest.approx(4.0 + float(w2[5]), rel=1e-5)
    two = torch.full((1, 8, 1, 1), -50.0)
    two[0, 0] = two[0, 7] = 50.0  # half on the ground, half in the top bin: the network hesitates
    mu0 = torch.zeros((1, 1, 1, 1))
    want = 0.5 * (c[0] ** 2 + w2[0]) + 0.5 * (c[7] ** 2 + w2[7])
    assert second_moment(two, mu0, e).item() == pytest.approx(float(want), rel=1e-5)
    # so a height near the ground can carry a spread of metres, and b = std / √2 for every consumer
    b = bins_scale(two, mu0, e, SCALE_MIN)
    assert (2 * b**2).item() == pytest.approx(float(want), rel=1e-5) and b.item() * math.sqrt(2) > 10


def test_model_returns_the_logits_only_for_training_and_its_spread_from_them() -> None:
    model, _ = _bins_model()
    x = torch.randn(2, 3, 64, 64)
    model.train()
    out = model(x)
    assert out[HEIGHT_BINS].shape == (2, 8, 64, 64)
    assert out[HEIGHT_LAPLACE].shape == (2, 1, 64, 64) and (out[HEIGHT_LAPLACE] >= SCALE_MIN).all()
    expected = bins_scale(out[HEIGHT_BINS], out["height"], model.bin_edges, SCALE_MIN)
    torch.testing.assert_close(out[HEIGHT_SCALE], expected)
    model.eval()
    with torch.no_grad():
        ev = model(x)
    assert tuple(ev) == model.cfg.outputs == ("height", HEIGHT_SCALE, "classes")  # what the engines write


def test_training_loss_adds_the_bins_cross_entropy_and_validation_scores_l1_alone() -> None:
    cfg = TrainConfig.from_dict({"model": {"aleatoric": True, "height_bins": 8, "height_bin_max": 30.0},
                                 "loss": {"bins_weight": 0.5, "nll_beta": 0.5}})
    obj = Objective(cfg, ("height",), None)
    torch.manual_seed(1)
    height = torch.rand(2, 1, 8, 8) * 20
    valid = torch.ones_like(height, dtype=torch.bool)
    valid[0, 0, :4] = False
    batch = {"height": height, "height_valid": valid}
    mu = torch.zeros(2, 1, 8, 8, requires_grad=True)
    logits = torch.zeros(2, 8, 8, 8, requires_grad=True)
    b = torch.full((2, 1, 8, 8), 2.0)
    out = {"height": mu, HEIGHT_SCALE: torch.ones(2, 1, 8, 8), HEIGHT_LAPLACE: b, HEIGHT_BINS: logits}
    loss = obj(out, batch)["height"]
    ce = height_bins_ce(logits, height, valid, bin_edges(8, 30.0))
    assert ce.item() == pytest.approx(math.log(8), rel=1e-5)  # uniform logits: log K nats
    # the height trains as in the aleatoric head (Laplace NLL with the training scale), plus the bins
    want = laplace_nll(mu, b, height, valid, beta=0.5) + 0.5 * ce
    assert loss.item() == pytest.approx(want.item(), rel=1e-6)
    loss.backward()
    assert logits.grad is not None and logits.grad.abs().sum() > 0
    assert logits.grad[0, :, :4].abs().sum() == 0  # invalid pixels do not train the bins
    scored = obj(out, batch, scoring=True)["height"]
    assert scored.item() == pytest.approx(l1(mu, height, valid).item(), rel=1e-6)


def test_height_bins_need_the_aleatoric_head_and_a_sane_count() -> None:
    with pytest.raises(ConfigError, match="model.height_bins.*model.aleatoric: true"):
        ModelConfig(height_bins=8)
    with pytest.raises(ConfigError, match="model.height_bins: must be 0"):
        ModelConfig(aleatoric=True, height_bins=1)
    with pytest.raises(ConfigError, match="model.height_bin_max"):
        ModelConfig(aleatoric=True, height_bins=8, height_bin_max=0.5)
    with pytest.raises(ConfigError, match="loss.bins_weight"):
        TrainConfig.from_dict({"loss": {"bins_weight": 0}})


def test_cli_predict_writes_the_bins_spread_at_t1(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """At T = 1 there is no MC spread: ``height_std`` is the bins' own spread, √(second moment)."""
    model, meta = _bins_model()
    ckpt = tmp_path / "m.pt"
    save_checkpoint(ckpt, model, meta)
    img = np.random.default_rng(0).integers(1, 256, (3, 64, 64)).astype(np.uint8)
    ortho = write_raster(tmp_path / "o.tif", img)
    code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "p", "--mc", 1,
                           "--engine", "torch", "--precision", "fp32")
    assert code == 0, err
    with rasterio.open(tmp_path / "p" / "height_std.tif") as src:
        std = src.read(1)
    with rasterio.open(tmp_path / "p" / "height.tif") as src:
        h = src.read(1)
    # the head's spread is at least the bin width's share around the height and at most the whole range
    assert (std > 0).all() and (std <= 30.0 + np.abs(h)).all()
    assert float(std.std()) > 0  # it varies per pixel
