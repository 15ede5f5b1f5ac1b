"""D3-Net architecture: shapes, tasks, input checks, parameter count, pretrained weight loading."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from helpers.models import TINY

from aerialmtl.errors import AerialMTLError, CheckpointError, ConfigError
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net, pad_to_multiple
from aerialmtl.models.densenet import DenseNetEncoder, count_parameters
from aerialmtl.models.encoders import ENCODERS, feature_channels
from aerialmtl.models.pretrained import adapt_first_conv, load_torchvision_densenet

SMALL = dict(growth_rate=12, block_config=(2, 4, 8, 6), num_init_features=32)


def _forward_backward(cfg: ModelConfig, shape: tuple[int, int, int, int]) -> dict[str, torch.Tensor]:
    torch.manual_seed(0)
    model = D3Net(cfg).train()
    x = torch.randn(*shape)
    out = model(x)
    loss = sum(v.float().square().mean() for v in out.values())
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is not None for g in grads), "every parameter must receive a gradient"
    assert all(torch.isfinite(g).all() for g in grads)
    return out


@pytest.mark.parametrize("size", [(64, 64), (64, 96)])
@pytest.mark.parametrize("kind", ["full", "small"])
def test_forward_backward_shapes(kind: str, size: tuple[int, int]) -> None:
    cfg = ModelConfig(in_channels=4, num_classes=6, **(SMALL if kind == "small" else {}))
    out = _forward_backward(cfg, (1, 4, *size))
    assert set(out) == {"height", "classes"}
    assert out["height"].shape == (1, 1, *size)
    assert out["classes"].shape == (1, 6, *size)


@pytest.mark.parametrize("tasks", [("height",), ("classes",)])
def test_single_task_configs(tasks: tuple[str, ...]) -> None:
    cfg = ModelConfig(tasks=tasks, num_classes=5, **SMALL)
    out = _forward_backward(cfg, (2, 3, 32, 64))
    assert set(out) == set(tasks)
    model = D3Net(cfg)
    assert set(model.heads) == set(tasks)


@pytest.mark.parametrize("task_blocks,dropout_blocks", [(1, 4), (3, 0), (4, 1)])
def test_other_splits_between_shared_and_task_blocks(task_blocks: int, dropout_blocks: int) -> None:
    cfg = ModelConfig(task_blocks=task_blocks, dropout_blocks=dropout_blocks, num_classes=3, **SMALL)
    model = D3Net(cfg).eval()
    assert len(model.shared) == 5 - task_blocks
    assert all(len(h.blocks) == task_blocks for h in model.heads.values())
    n_drop = sum(isinstance(m, torch.nn.Dropout) for m in model.modules())
    assert n_drop == 2 * dropout_blocks
    out = model(torch.randn(1, 3, 32, 32))
    assert out["classes"].shape == (1, 3, 32, 32)


def test_dropout_sits_only_in_the_deepest_shared_blocks() -> None:
    model = D3Net(ModelConfig(**SMALL))  # defaults: dropout 0.5 in the 2 deepest of 3 shared blocks
    assert [any(isinstance(m, torch.nn.Dropout) for m in b.modules()) for b in model.shared] == [True, True, False]
    assert not any(isinstance(m, torch.nn.Dropout) for m in model.encoder.modules())
    assert not any(isinstance(m, torch.nn.Dropout) for m in model.heads.modules())


def test_input_size_not_multiple_of_32_is_explained() -> None:
    model = D3Net(ModelConfig(**SMALL))
    with pytest.raises(AerialMTLError) as info:
        model(torch.randn(1, 3, 50, 64))
    assert isinstance(info.value, ValueError)
    msg = str(info.value)
    assert "(1, 3, 50, 64)" in msg and "multiples of 32" in msg and "pad_to_multiple" in msg


def test_wrong_band_count_is_explained() -> None:
    model = D3Net(ModelConfig(in_channels=4, **SMALL))
    with pytest.raises(ValueError, match=r"B×4×H×W.*\(1, 3, 64, 64\)"):
        model(torch.randn(1, 3, 64, 64))
    with pytest.raises(ValueError, match=r"\(3, 64, 64\)"):
        model(torch.randn(3, 64, 64))


def test_pad_to_multiple_round_trip() -> None:
    x = torch.randn(1, 3, 50, 70)
    padded, crop = pad_to_multiple(x, 32)
    assert padded.shape == (1, 3, 64, 96)
    assert torch.equal(padded[..., crop[0], crop[1]], x)
    model = D3Net(ModelConfig(**SMALL)).eval()
    with torch.no_grad():
        y = model(padded)["height"][..., crop[0], crop[1]]
    assert y.shape == (1, 1, 50, 70)
    tiny, _ = pad_to_multiple(torch.randn(1, 1, 5, 40), 32)  # too small to reflect: replicate
    assert tiny.shape == (1, 1, 32, 64)


def test_full_config_parameter_count() -> None:
    model = D3Net(ModelConfig())  # 3 bands, 20 classes, DenseNet-121, height + classes
    # Encoder: torchvision DenseNet-121 features (6,953,856) − its 7×7 conv0 (9,408) + our 3×3 conv0
    # (1,728) + 4×4 downconv0 (65,536) + norm1 (128) = 7,011,840.
    assert count_parameters(model.encoder) == 7_011_840
    # Up-block(in, out) = ConvT 16·in·out + conv3×3 9·out² + two BNs 4·out (no conv biases).
    up = lambda i, o: 16 * i * o + 9 * o * o + 4 * o  # noqa: E731
    shared = up(1024, 512) + up(512 + 512, 256) + up(256 + 256, 128)  # 16,731,648
    task = up(128 + 128, 64) + up(64 + 64, 64)  # 467,456 per task, + 3×3 head with bias
    expected = 7_011_840 + shared + task + (9 * 64 * 1 + 1) + task + (9 * 64 * 20 + 20)
    assert count_parameters(model) == expected == 24_690_517  # ≈ 25 M as in the paper


def test_channels_last_and_bf16_autocast() -> None:
    torch.manual_seed(0)
    model = D3Net(ModelConfig(**SMALL)).eval()
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        ref = model(x)
        model_cl = model.to(memory_format=torch.channels_last)
        out = model_cl(x.contiguous(memory_format=torch.channels_last))
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = model_cl(x.contiguous(memory_format=torch.channels_last))
    for t in ref:
        torch.testing.assert_close(out[t], ref[t], rtol=1e-4, atol=1e-4)
        assert torch.isfinite(low[t].float()).all()
        assert low[t].shape == ref[t].shape
    # bf16 keeps ~3 significant digits; outputs must still follow the fp32 ones.
    err = (low["classes"].float() - ref["classes"]).abs().mean() / ref["classes"].abs().mean()
    assert err < 0.1


def test_inference_dense_block_equals_training_path() -> None:
    torch.manual_seed(0)
    enc = DenseNetEncoder(3, **SMALL).eval()
    x = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        fast = enc(x)
    slow = enc(x)  # grad enabled: concatenation path
    for a, b in zip(fast, slow):
        torch.testing.assert_close(a, b.detach())
    assert [f.shape[1] for f in fast] == list(enc.out_channels)
    assert [64 // f.shape[-1] for f in fast] == list(enc.reductions)


def test_small_config_trains() -> None:
    torch.manual_seed(0)
    model = D3Net(ModelConfig(num_classes=3, **SMALL))
    x = torch.randn(2, 3, 64, 64)
    target_h = 5 + 3 * x[:, :1]  # heights that follow the image
    opt = torch.optim.Adam(model.parameters(), lr=2e-3, betas=(0.5, 0.999))
    losses = []
    for _ in range(12):
        out = model(x)
        loss = (out["height"] - target_h).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0]


# --------------------------------------------------------------------------- pretrained weights


def _torchvision_densenet121_shapes(old_style: bool) -> dict[str, tuple[int, ...]]:
    """Key → shape of torchvision's densenet121().state_dict(), written from its published structure."""
    shapes: dict[str, tuple[int, ...]] = {}

    def bn(prefix: str, c: int) -> None:
        for name in ("weight", "bias", "running_mean", "running_var"):
            shapes[f"{prefix}.{name}"] = (c,)
        shapes[f"{prefix}.num_batches_tracked"] = ()

    shapes["features.conv0.weight"] = (64, 3, 7, 7)
    bn("features.norm0", 64)
    c = 64
    for b, n in enumerate((6, 12, 24, 16), start=1):
        for i in range(1, n + 1):
            p = f"features.denseblock{b}.denselayer{i}"
            sep = "." if old_style else ""
            bn(f"{p}.norm{sep}1", c + (i - 1) * 32)
            shapes[f"{p}.conv{sep}1.weight"] = (128, c + (i - 1) * 32, 1, 1)
            bn(f"{p}.norm{sep}2", 128)
            shapes[f"{p}.conv{sep}2.weight"] = (32, 128, 3, 3)
        c += n * 32
        if b < 4:
            bn(f"features.transition{b}.norm", c)
            shapes[f"features.transition{b}.conv.weight"] = (c // 2, c, 1, 1)
            c //= 2
    bn("features.norm5", c)
    shapes["classifier.weight"] = (1000, 1024)
    shapes["classifier.bias"] = (1000,)
    return shapes


def _fake_state_dict(old_style: bool) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(7)
    return {k: (torch.randint(0, 100, s, generator=g) if k.endswith("num_batches_tracked")
                else torch.randn(s, generator=g)) for k, s in _torchvision_densenet121_shapes(old_style).items()}


@pytest.mark.parametrize("old_style", [False, True])
def test_load_torchvision_densenet121(tmp_path: Path, old_style: bool) -> None:
    sd = _fake_state_dict(old_style)
    path = tmp_path / "densenet121.pth"
    torch.save(sd, path)
    enc = DenseNetEncoder(in_channels=4)
    stem_before = enc.features.conv0.weight.detach().clone()
    report = load_torchvision_densenet(enc, path)
    mine = enc.state_dict()
    key_new = "features.denseblock3.denselayer24.norm2.running_var"
    key_src = key_new.replace("norm2", "norm.2") if old_style else key_new
    assert torch.equal(mine[key_new], sd[key_src])
    assert torch.equal(mine["features.transition2.conv.weight"], sd["features.transition2.conv.weight"])
    assert torch.equal(mine["features.norm5.bias"], sd["features.norm5.bias"])
    # Every non-stem tensor is loaded and equal to its source.
    non_stem = [k for k in mine if not k.startswith(("features.conv0", "features.norm0", "features.downconv0",
                                                      "features.norm1."))]
    assert sorted(report.loaded) == sorted(non_stem)
    assert report.missing == []
    assert set(report.unexpected) == {"classifier.weight", "classifier.bias"}
    assert torch.equal(enc.features.conv0.weight, stem_before)  # stem stays from scratch


def test_load_center_stem_adapts_bands(tmp_path: Path) -> None:
    sd = _fake_state_dict(False)
    path = tmp_path / "densenet121.pth"
    torch.save(sd, path)
    enc = DenseNetEncoder(in_channels=5)
    load_torchvision_densenet(enc, path, stem="center")
    w = enc.features.conv0.weight
    rgb = sd["features.conv0.weight"][:, :, 2:5, 2:5]
    torch.testing.assert_close(w[:, :3], rgb * 3 / 5)
    torch.testing.assert_close(w[:, 4], rgb.mean(1) * 3 / 5)
    assert torch.equal(enc.features.norm0.running_mean, sd["features.norm0.running_mean"])


def test_adapt_first_conv_preserves_response_to_grey_input() -> None:
    w = torch.randn(8, 3, 3, 3)
    x = torch.randn(1, 1, 9, 9)
    ref = torch.nn.functional.conv2d(x.repeat(1, 3, 1, 1), w)
    for c in (1, 2, 4, 7):
        out = torch.nn.functional.conv2d(x.repeat(1, c, 1, 1), adapt_first_conv(w, c))
        assert adapt_first_conv(w, c).shape == (8, c, 3, 3)
        torch.testing.assert_close(out, ref, rtol=1e-4, atol=1e-4)
    # C ≥ 3 keeps the RGB kernels of the first three bands (rescaled).
    torch.testing.assert_close(adapt_first_conv(w, 6)[:, :3], w * 0.5)


def test_load_rejects_non_densenet_and_mismatched_files(tmp_path: Path) -> None:
    enc = DenseNetEncoder()
    bad = tmp_path / "resnet.pth"
    torch.save({"conv1.weight": torch.zeros(64, 3, 7, 7), "fc.weight": torch.zeros(10, 512)}, bad)
    with pytest.raises(CheckpointError, match=r"resnet\.pth.*not a torchvision-format DenseNet"):
        load_torchvision_densenet(enc, bad)
    with pytest.raises(CheckpointError, match="do not exist"):
        load_torchvision_densenet(enc, tmp_path / "missing.pth")
    small = DenseNetEncoder(**SMALL)
    good = tmp_path / "d121.pth"
    torch.save(_fake_state_dict(False), good)
    with pytest.raises(CheckpointError, match=r"d121\.pth.*shape.*growth_rate"):
        load_torchvision_densenet(small, good)


def test_config_with_encoder_weights_loads_them(tmp_path: Path) -> None:
    sd = _fake_state_dict(False)
    path = tmp_path / "w.pth"
    torch.save(sd, path)
    model = D3Net(ModelConfig(encoder_weights=str(path)))
    assert torch.equal(model.encoder.features.denseblock1.denselayer1.conv1.weight,
                       sd["features.denseblock1.denselayer1.conv1.weight"])


def test_config_rejects_bad_dropout_blocks() -> None:
    with pytest.raises(ConfigError, match="dropout_blocks"):
        ModelConfig(task_blocks=2, dropout_blocks=4)


def test_batchnorm_folding_keeps_outputs_and_leaves_the_model_alone() -> None:
    from aerialmtl.models.d3net import fold_batchnorm

    torch.manual_seed(0)
    model = D3Net(ModelConfig(num_classes=4, growth_rate=4, block_config=(1, 1, 1, 1), num_init_features=8))
    model.train()
    with torch.no_grad():  # non-trivial running statistics
        model(torch.randn(2, 3, 64, 64))
    model.eval()
    folded = fold_batchnorm(model)
    assert folded is not model
    x = torch.randn(1, 3, 64, 64)
    with torch.no_grad():
        a, b = model(x), folded(x)
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=1e-4, atol=1e-5)
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules()) < \
        sum(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())


# ---- the encoder registry ---------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(ENCODERS))
def test_every_registered_encoder_feeds_the_decoder_forward_and_backward(name: str) -> None:
    """Every registry entry builds an encoder of five stride 2–32 features that the one decoder takes."""
    extra = TINY if name == "densenet121" else {}
    torch.manual_seed(0)
    model = D3Net(ModelConfig(num_classes=3, encoder=name, **extra))  # type: ignore[arg-type]
    feats = model.encode(torch.zeros(1, 3, 64, 64))
    assert [f.shape[1] for f in feats] == list(feature_channels(model.encoder))
    assert [f.shape[-1] for f in feats] == [32, 16, 8, 4, 2]
    out = model(torch.rand(1, 3, 64, 64))
    assert out["height"].shape == (1, 1, 64, 64) and out["classes"].shape == (1, 3, 64, 64)
    (out["height"].mean() + out["classes"].mean()).backward()
    assert all(p.grad is not None for p in model.encoder.parameters() if p.requires_grad)
