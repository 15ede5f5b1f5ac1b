"""The aleatoric height head (``model.aleatoric``): a Laplace scale per pixel, trained with the Laplace NLL,
combined with MC dropout into one predictive spread, on every engine and through the CLI."""

from __future__ import annotations

import json
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
from aerialmtl.models.config import HEIGHT_SCALE, ModelConfig
from aerialmtl.models.d3net import SCALE_MIN, D3Net
from aerialmtl.models.mc_dropout import accumulate_samples, mc_predict
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.losses import l1, laplace_nll


def _aleatoric(k: int = 3, **extra: object) -> tuple[D3Net, ModelMeta]:
    torch.manual_seed(0)
    scheme = ClassScheme.load("synthetic")
    scheme = ClassScheme(scheme.name, scheme.classes[:k])
    cfg = ModelConfig(num_classes=k, aleatoric=True, **{**TINY, **extra})  # type: ignore[arg-type]
    meta = ModelMeta(cfg, scheme, (1, 2, 3), (120.0, 110.0, 100.0), (40.0, 40.0, 40.0), 0.5, ("r", "g", "b"))
    return D3Net(cfg).eval(), meta


def test_laplace_nll_learns_the_absolute_error_and_masks() -> None:
    target = torch.tensor([[[[3.0, -1.0, 100.0]]]])
    pred = torch.zeros_like(target)
    mask = torch.tensor([[[[True, True, False]]]])
    # for a fixed prediction, the scale minimising the NLL is |error| per pixel
    raw = torch.zeros_like(target, requires_grad=True)
    opt = torch.optim.Adam([raw], lr=0.05)
    for _ in range(1500):
        opt.zero_grad()
        laplace_nll(pred, torch.nn.functional.softplus(raw) + SCALE_MIN, target, mask).backward()
        opt.step()
    b = torch.nn.functional.softplus(raw) + SCALE_MIN
    assert b[0, 0, 0, 0].item() == pytest.approx(3.0, rel=0.02)
    assert b[0, 0, 0, 1].item() == pytest.approx(1.0, rel=0.02)
    assert raw.grad is not None and raw.grad[0, 0, 0, 2] == 0  # the masked pixel never moves
    # the value: mean over valid pixels of |e|/b + log b
    scale = torch.tensor([[[[1.5, 2.0, 1.0]]]])
    want = ((3.0 / 1.5 + math.log(1.5)) + (1.0 / 2.0 + math.log(2.0))) / 2
    assert laplace_nll(pred, scale, target, mask).item() == pytest.approx(want, rel=1e-6)


def test_beta_one_gives_the_heights_the_gradient_of_l1() -> None:
    rng = torch.Generator().manual_seed(0)
    target = torch.randn((2, 1, 8, 8), generator=rng) * 5
    scale = torch.rand((2, 1, 8, 8), generator=rng) * 3 + 0.1
    mask = torch.rand((2, 1, 8, 8), generator=rng) > 0.2
    grads = {}
    for name in ("l1", "b1", "b0"):
        pred = torch.randn((2, 1, 8, 8), generator=torch.Generator().manual_seed(1), requires_grad=True)
        if name == "l1":
            loss = l1(pred, target, mask)
        else:
            loss = laplace_nll(pred, scale, target, mask, beta=1.0 if name == "b1" else 0.0)
        loss.backward()
        assert pred.grad is not None
        grads[name] = pred.grad.clone()
    torch.testing.assert_close(grads["b1"], grads["l1"])
    assert not torch.allclose(grads["b0"], grads["l1"])  # plain NLL: hard (large-b) pixels pull less


def test_model_outputs_a_positive_scale_and_the_paper_model_does_not() -> None:
    model, _ = _aleatoric()
    out = model(torch.randn(2, 3, 64, 96))
    assert tuple(out) == ("height", HEIGHT_SCALE, "classes") == model.outputs
    assert out["height"].shape == out[HEIGHT_SCALE].shape == (2, 1, 64, 96)
    assert (out[HEIGHT_SCALE] >= SCALE_MIN).all()
    assert out[HEIGHT_SCALE].mean().item() == pytest.approx(1.0, abs=0.2)  # starts near 1 m
    paper = D3Net(ModelConfig(num_classes=3, **TINY))  # type: ignore[arg-type]
    assert HEIGHT_SCALE not in paper(torch.randn(1, 3, 64, 64)) and paper.outputs == ("height", "classes")


def test_leaky_task_blocks_keep_information_where_relu_features_are_all_zero() -> None:
    cfg = dict(num_classes=3, **TINY)
    relu = D3Net(ModelConfig(**cfg)).eval()  # type: ignore[arg-type]
    leaky = D3Net(ModelConfig(task_activation="leaky_relu", **cfg)).eval()  # type: ignore[arg-type]
    leaky.load_state_dict(relu.state_dict())
    for m, slope in ((relu, 0.0), (leaky, 0.01)):
        acts = [a for name, a in m.named_modules() if name.startswith("heads.") and "relu" in name]
        assert acts and all(getattr(a, "negative_slope", 0.0) == slope for a in acts)
    shared = [a for name, a in leaky.named_modules() if name.startswith("shared.") and "relu" in name]
    assert all(isinstance(a, torch.nn.ReLU) for a in shared)  # the shared blocks stay the paper's


def test_scale_decoder_gives_the_scale_blocks_of_its_own() -> None:
    """``model.scale_decoder``: the height head outputs the height alone and the scale comes from its own task
    blocks — changing them moves the scale, never the height; the shared-head model keeps its parameter names
    (checkpoints of it load as before)."""
    model, _ = _aleatoric(scale_decoder=True)
    shared_head, _ = _aleatoric()
    assert model.scale_decoder is not None and shared_head.scale_decoder is None
    assert model.heads["height"].head.out_channels == 1 and shared_head.heads["height"].head.out_channels == 2
    assert not any(k.startswith("scale_decoder.") for k in shared_head.state_dict())
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        before = model(x)
        assert tuple(before) == model.outputs and (before[HEIGHT_SCALE] >= SCALE_MIN).all()
        for p in model.scale_decoder.parameters():
            p.add_(0.1 * torch.randn_like(p))
        after = model(x)
    assert torch.equal(after["height"], before["height"]) and torch.equal(after["classes"], before["classes"])
    assert not torch.allclose(after[HEIGHT_SCALE], before[HEIGHT_SCALE])
    with pytest.raises(ConfigError, match="scale_decoder"):
        ModelConfig(scale_decoder=True)  # without the aleatoric head
    with pytest.raises(ConfigError, match="scale_decoder"):
        ModelConfig(aleatoric=True, height_bins=8, scale_decoder=True)


def test_predictive_std_combines_mc_spread_and_laplace_variance() -> None:
    """Two samples of one pixel: means 1 and 3 (variance 1), scales 1 and 2 (mean 2b² = 5) → std √6."""
    def decode(done: int, s: int) -> dict[str, torch.Tensor]:
        means = torch.tensor([1.0, 3.0])[done:done + s]
        scales = torch.tensor([1.0, 2.0])[done:done + s]
        return {"height": means.reshape(s, 1, 1, 1), HEIGHT_SCALE: scales.reshape(s, 1, 1, 1)}

    for chunk in (1, 2):
        stats = accumulate_samples(decode, 2, chunk, 1)
        assert stats.height_mean is not None and stats.height_std is not None and stats.height_aleatoric is not None
        assert stats.height_mean.item() == pytest.approx(2.0)
        assert stats.height_std.item() == pytest.approx(math.sqrt(6.0), rel=1e-6)
        assert stats.height_aleatoric.item() == pytest.approx(math.sqrt(5.0), rel=1e-6)


def test_mc_predict_reports_both_parts() -> None:
    model, _ = _aleatoric()
    res = mc_predict(model, torch.randn(1, 3, 64, 64), samples=4, seed=0, keys=[0])["height"]
    assert set(res) == {"mean", "std", "aleatoric_std"}
    assert (res["std"] >= res["aleatoric_std"] - 1e-6).all()  # the MC part only adds


def test_aleatoric_needs_the_l1_likelihood_and_a_beta_in_range() -> None:
    with pytest.raises(ConfigError, match="loss.height"):
        TrainConfig.from_dict({"model": {"aleatoric": True}, "loss": {"height": "berhu"}})
    with pytest.raises(ConfigError, match="nll_beta"):
        TrainConfig.from_dict({"model": {"aleatoric": True}, "loss": {"nll_beta": 2}})
    with pytest.raises(ConfigError, match="task_activation"):
        TrainConfig.from_dict({"model": {"task_activation": "gelu"}})


@pytest.mark.parametrize("engine", ["torch", "openvino"])
def test_cli_predict_writes_the_predictive_spread_at_any_t(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                          engine: str) -> None:
    if engine == "openvino":
        pytest.importorskip("openvino")
    model, meta = _aleatoric()
    ckpt = tmp_path / "al.pt"
    save_checkpoint(ckpt, model, meta)
    img = np.random.default_rng(0).integers(1, 256, (3, 90, 70)).astype(np.uint8)
    ortho = write_raster(tmp_path / "o.tif", img)
    std = {}
    for mc in (1, 4):
        out = tmp_path / f"p{mc}"
        code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", out, "--mc", mc,
                               "--engine", engine, "--precision", "fp32")
        assert code == 0, err
        info = json.loads((out / "prediction.json").read_text())
        assert "height_std" in info["files"]
        with rasterio.open(out / "height_std.tif") as src:
            std[mc] = src.read(1)
            assert "aleatoric" in (src.descriptions[0] or "")
    assert (std[1] > 0.5).all()  # √2 · b with b ≈ 1 m at initialisation: never the 0 m of MC dropout alone
    assert (std[4] >= std[1] - 1e-3).mean() > 0.99  # the MC part adds variance (its masks differ from T = 1)


def test_tta_views_are_undone_exactly_and_their_disagreement_enters_the_spread(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A per-pixel model (1×1 convolutions) gives the same map in every view: --tta changes nothing and adds no
    spread; a D3-Net's views disagree, so --tta at T = 1 writes a height_std, equal on both engines."""
    from helpers.models import IdentityModel, identity_meta

    img = np.random.default_rng(0).integers(1, 256, (3, 70, 90)).astype(np.uint8)
    ortho = write_raster(tmp_path / "o.tif", img)
    ident = (IdentityModel((0.0,) * 3, (1.0,) * 3), identity_meta())
    from aerialmtl.inference.predict import predict_raster

    plain = predict_raster(ortho, ident, tmp_path / "plain", mc=1, progress=False, engine="torch", precision="fp32")
    tta = predict_raster(ortho, ident, tmp_path / "tta", mc=1, progress=False, engine="torch", precision="fp32",
                         tta=True)
    with rasterio.open(plain.out_dir / "height.tif") as a, rasterio.open(tta.out_dir / "height.tif") as b:
        np.testing.assert_allclose(b.read(1), a.read(1), rtol=1e-6)
    with rasterio.open(tta.out_dir / "height_std.tif") as s:
        assert float(np.abs(s.read(1)).max()) < 1e-4
    assert json.loads((tta.out_dir / "prediction.json").read_text())["tta"] is True
    model, meta = _aleatoric()
    ckpt = tmp_path / "al.pt"
    save_checkpoint(ckpt, model, meta)
    std = {}
    for engine in ("torch", "openvino"):
        if engine == "openvino":
            pytest.importorskip("openvino")
        out = tmp_path / f"tta_{engine}"
        code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", out, "--mc", 1, "--tta",
                               "--engine", engine, "--precision", "fp32")
        assert code == 0, err
        with rasterio.open(out / "height_std.tif") as s:
            std[engine] = s.read(1)
    np.testing.assert_allclose(std["openvino"], std["torch"], rtol=0, atol=1e-3)


def test_export_carries_the_aleatoric_spread(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """`export` of an aleatoric model has a height_std output (√2·b of one pass, metres), in the file with every
    output and alone as a Deepness Regressor; ONNX Runtime gives torch's numbers."""
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    from aerialmtl.formats.exported_model import read_metadata

    model, meta = _aleatoric()
    ckpt = tmp_path / "al.pt"
    save_checkpoint(ckpt, model, meta)
    code, _, err = run_cli(capsys, "export", ckpt, "--tile", 64, "--out", tmp_path / "all.onnx")
    assert code == 0, err
    code, _, err = run_cli(capsys, "export", ckpt, "--task", "height_std", "--tile", 64, "--out", tmp_path / "s.onnx")
    assert code == 0, err
    x = np.random.default_rng(0).normal(size=(1, 3, 64, 64)).astype(np.float32)
    with torch.no_grad():
        want = (model(torch.from_numpy(x))[HEIGHT_SCALE] * math.sqrt(2.0)).numpy()
    sess = ort.InferenceSession(str(tmp_path / "all.onnx"), providers=["CPUExecutionProvider"])
    names = [o.name for o in sess.get_outputs()]
    assert names == ["height", "height_std", "classes"]
    np.testing.assert_allclose(sess.run(["height_std"], {"image": x})[0], want, rtol=1e-4, atol=1e-4)
    alone = ort.InferenceSession(str(tmp_path / "s.onnx"), providers=["CPUExecutionProvider"])
    assert [o.name for o in alone.get_outputs()] == ["height_std"]
    np.testing.assert_allclose(alone.run(None, {"image": x})[0], want, rtol=1e-4, atol=1e-4)
    assert read_metadata(tmp_path / "s.onnx")["model_type"] == "Regressor"
