"""Every model option on every engine, through the CLI.

Each encoder (the paper's DenseNet-121, small, and the EfficientNet-Lite options) × head (the paper's,
aleatoric Laplace scale; the height-bin head and the scale's own decoder on the paper's encoder and the
small-area recipe's, since they sit after the shared decoder whatever the encoder) × engine (torch, openvino)
× precision (fp32, bf16) × T (1, > 1), on rasters whose sides are not multiples of 32. OpenVINO at fp32
equals torch within float rounding; bf16 stays close to fp32 (stated tolerances below)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from helpers.cli import run_cli
from helpers.models import TINY
from helpers.rasters import write_raster

from aerialmtl.classes import ClassScheme
from aerialmtl.formats.checkpoint import ModelMeta, save_checkpoint
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net, TaskDecoder
from aerialmtl.models.encoders import ENCODERS

pytest.importorskip("openvino")

#: fp32 OpenVINO vs fp32 torch: float rounding of a different kernel order (metres; nats).
FP32_ATOL = 1e-3
#: bf16 (either engine) vs fp32 torch: mean absolute height difference relative to the mean |height|, and the
#: share of pixels whose class agrees (8-bit mantissa through a random, untrained network).
BF16_REL_MAE, BF16_CLASS_AGREE = 0.1, 0.9


def _model(encoder: str, aleatoric: bool, height_bins: int = 0, scale_decoder: bool = False) -> tuple[D3Net, ModelMeta]:
    torch.manual_seed(0)
    scheme = ClassScheme.load("synthetic")
    scheme = ClassScheme(scheme.name, scheme.classes[:3])
    extra = TINY if encoder == "densenet121" else {}
    cfg = ModelConfig(num_classes=3, encoder=encoder, aleatoric=aleatoric, height_bins=height_bins,
                      scale_decoder=scale_decoder, **extra)  # type: ignore[arg-type]
    model = D3Net(cfg).eval()
    with torch.no_grad():  # outputs of a few metres and confident classes, not the near-zero ones of a fresh head
        for head in [*model.heads.values(), *([model.scale_decoder] if model.scale_decoder is not None else [])]:
            assert isinstance(head, TaskDecoder)
            torch.nn.init.normal_(head.head.weight, std=0.3)
    meta = ModelMeta(cfg, scheme, (1, 2, 3), (120.0, 110.0, 100.0), (40.0, 40.0, 40.0), 0.5, ("r", "g", "b"))
    return model, meta


def _layers(folder: Path) -> dict[str, np.ndarray]:
    info = json.loads((folder / "prediction.json").read_text())
    out = {}
    for name, file in info["files"].items():
        if str(file).endswith(".tif"):
            with rasterio.open(folder / file) as src:
                out[name] = src.read()
    return out


HEADS = {"paper_head": (False, 0, False), "aleatoric": (True, 0, False), "height_bins": (True, 8, False),
         "scale_decoder": (True, 0, True)}
#: the heads after the decoder (height bins, the scale's own decoder) on the paper's encoder and the recipe's
CASES = [(e, h) for e in ENCODERS for h in HEADS
         if h not in ("height_bins", "scale_decoder") or e in ("densenet121", "efficientnet_lite0")]


@pytest.mark.slow
@pytest.mark.parametrize(("encoder", "head"), CASES, ids=[f"{e}-{h}" for e, h in CASES])
def test_every_encoder_and_head_predicts_on_every_engine_precision_and_t(
        encoder: str, head: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    aleatoric, bins, scale_decoder = HEADS[head]
    model, meta = _model(encoder, aleatoric, bins, scale_decoder)
    ckpt = tmp_path / "m.pt"
    save_checkpoint(ckpt, model, meta)
    img = np.random.default_rng(1).integers(1, 256, (3, 71, 90)).astype(np.uint8)  # sides not multiples of 32
    img[:, 50:, :30] = 0  # a nodata corner
    ortho = write_raster(tmp_path / "o.tif", img, nodata=0)
    for mc in (1, 3):
        maps: dict[tuple[str, str], dict[str, np.ndarray]] = {}
        for engine in ("torch", "openvino"):
            for precision in ("fp32", "bf16"):
                out = tmp_path / f"{engine}_{precision}_{mc}"
                code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", out, "--mc", mc,
                                       "--engine", engine, "--precision", precision, "--window", 96, "--overlap", 16)
                assert code == 0, f"{engine}/{precision}/T={mc}: {err}"
                info = json.loads((out / "prediction.json").read_text())
                assert (info["engine"], info["precision"]) == (engine, precision)
                maps[engine, precision] = _layers(out)
        ref = maps["torch", "fp32"]
        assert ("height_std" in ref) == (mc > 1 or aleatoric)
        ok = ref["classes"] != 255
        assert ok.any() and (~ok).any()
        ov = maps["openvino", "fp32"]
        assert set(ov) == set(ref)
        for name in set(ref) - {"classes"}:
            np.testing.assert_allclose(ov[name][:, ok[0]], ref[name][:, ok[0]], rtol=0, atol=FP32_ATOL,
                                       err_msg=f"{encoder} {name} T={mc}")
        np.testing.assert_array_equal(ov["classes"], ref["classes"])
        scale = float(np.abs(ref["height"][:, ok[0]]).mean())
        assert scale > 0.05  # the maps carry values, so the comparisons mean something
        for engine in ("torch", "openvino"):
            low = maps[engine, "bf16"]
            assert set(low) == set(ref)
            diff = float(np.abs(low["height"][:, ok[0]] - ref["height"][:, ok[0]]).mean())
            assert diff <= BF16_REL_MAE * scale, f"{encoder} {engine} bf16 T={mc}: {diff:.3g} m vs {scale:.3g} m"
            assert (low["classes"][ok] == ref["classes"][ok]).mean() >= BF16_CLASS_AGREE
            assert (low["classes"] == 255).sum() == (ref["classes"] == 255).sum()  # the same nodata


def test_auto_falls_back_to_torch_with_a_warning_when_openvino_cannot_run_the_model(
        tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    from aerialmtl.inference.engines import OpenVINOEngine

    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("Check 'TRShape::broadcast_merge_into(...)' failed")

    monkeypatch.setattr(OpenVINOEngine, "statistics", broken)
    # the fallback once auto has taken OpenVINO: auto weighs a cold cache's compilation and takes torch for a job
    # this small from the start (tests/test_engine_auto.py), so the cache says it is warm
    monkeypatch.setattr("aerialmtl.inference.model.Predictor._cached", lambda self, *args: True)
    model, meta = _model("densenet121", False)
    ckpt = tmp_path / "m.pt"
    save_checkpoint(ckpt, model, meta)
    ortho = write_raster(tmp_path / "o.tif", np.random.default_rng(0).integers(1, 256, (3, 40, 50)).astype(np.uint8))
    code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "p", "--mc", 2)
    assert code == 0, err
    assert "cannot run this model" in err and "torch engine" in err
    assert json.loads((tmp_path / "p" / "prediction.json").read_text())["engine"] == "torch"
    code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "q", "--engine", "openvino")
    assert code != 0  # asked for by name: no silent substitute
