"""The engine registry is the one list of engines: a third engine added as docs/CONTRACTS.md says (one module, one
entry of ``engines.names.ENGINE_MODULES``, nothing else edited) predicts from Python and from the command line, and
``auto`` chooses among the engines that can run (no OpenVINO needed)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rasterio
import torch
from helpers import fake_engine
from helpers.cli import run_cli
from helpers.models import IdentityModel, tiny_d3net
from helpers.rasters import write_raster

from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.inference.engine_choice import choose_engine
from aerialmtl.inference.engines import FALLBACK, usable_engines
from aerialmtl.inference.engines.names import ENGINE_MODULES
from aerialmtl.inference.predict import predict_raster


@pytest.fixture
def registered(monkeypatch: pytest.MonkeyPatch) -> None:
    """The fake engine's one entry, appended to the table of engines (it declares no speed: not chosen)."""
    monkeypatch.setitem(ENGINE_MODULES, fake_engine.NAME, fake_engine.__name__)
    fake_engine.BUILT.clear()


def _height(folder: Path) -> np.ndarray:
    with rasterio.open(folder / "height.tif") as src:
        return np.asarray(src.read(1))


def test_a_registered_engine_predicts_from_python_and_the_command_line(registered: None, tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    model, meta = tiny_d3net()
    ckpt = tmp_path / "m.pt"
    save_checkpoint(ckpt, model, meta)
    rng = np.random.default_rng(0)
    ortho = write_raster(tmp_path / "o.tif", rng.integers(1, 256, size=(3, 80, 72)).astype(np.uint8))
    settings: dict[str, Any] = {"mc": 2, "window": 64, "overlap": 16, "precision": "fp32", "device": "cpu", "seed": 3}
    predict_raster(ortho, ckpt, tmp_path / "fake", engine=fake_engine.NAME, progress=False, **settings)
    predict_raster(ortho, ckpt, tmp_path / "torch", engine="torch", progress=False, **settings)
    info = json.loads((tmp_path / "fake" / "prediction.json").read_text())
    assert info["engine"] == info["settings"]["engine"] == info["engine_choice"]["engine"] == fake_engine.NAME
    assert fake_engine.BUILT and fake_engine.BUILT[-1].windows > 0  # it computed the maps
    # the same torch model underneath: the same maps (same code path, float rounding only)
    np.testing.assert_allclose(_height(tmp_path / "fake"), _height(tmp_path / "torch"), rtol=0, atol=1e-5)

    code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "cli", "--engine",
                           fake_engine.NAME, "--mc", "2", "--window", "64", "--overlap", "16", "--device", "cpu",
                           "--quiet")
    assert code == 0, err
    assert json.loads((tmp_path / "cli" / "prediction.json").read_text())["engine"] == fake_engine.NAME
    code, _, err = run_cli(capsys, "predict", ortho, "--model", ckpt, "--out", tmp_path / "no", "--engine", "onnx")
    assert code == 2 and "onnx" in err and fake_engine.NAME in err  # the choices are the registry's


def test_auto_chooses_among_the_registered_engines_that_can_run(registered: None) -> None:
    model, _ = tiny_d3net()
    cpu = torch.device("cpu")
    assert fake_engine.NAME in [spec.name for spec in usable_engines(cpu, model)]
    assert choose_engine("auto", "auto", cpu, model).engine != fake_engine.NAME  # declares no speed: not chosen
    assert [spec.name for spec in usable_engines(torch.device("cuda"), model)] == [FALLBACK]  # the fake: CPU only
    assert [spec.name for spec in usable_engines(torch.device("cuda"), IdentityModel((1.0,), (1.0,)))] == [FALLBACK]
