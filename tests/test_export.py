"""`aerialmtl export`: ONNX / OpenVINO IR files that reproduce the torch model and carry QGIS plugin metadata."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.cli import run_cli
from helpers.models import tiny_d3net

from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.formats.exported_model import deepness_input_problem, export_metadata, read_metadata
from aerialmtl.inference.export import ExportHead
from aerialmtl.models.calibration import Calibration

pytestmark = pytest.mark.slow  # one torch → ONNX export (~15 s on 2 cores)

TILE = 64
#: A height calibration as training stores it (predict applies it; so does the exported graph).
CALIBRATION = Calibration((0.0, 0.5, 2.0, 8.0), (0.2, 0.4, 3.0, 10.0), std_scale=1.4, method="isotonic")


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A checkpoint of a tiny D3-Net and its exports: all tasks (ONNX), height, classes, OpenVINO IR."""
    from aerialmtl.inference.export import export_model

    root = tmp_path_factory.mktemp("export")
    model, meta = tiny_d3net()
    save_checkpoint(root / "best.pt", model, replace(meta, calibration=CALIBRATION))
    files = {"ckpt": root / "best.pt"}
    res = export_model(root / "best.pt", root / "model.onnx", tile=TILE, overlap=16)
    files["all"] = res.files[0]
    return files


def _torch(ckpt: Path, x: np.ndarray) -> dict[str, np.ndarray]:
    """What `aerialmtl predict --mc 1` computes per tile: heights through the checkpoint's calibration."""
    from aerialmtl.formats.checkpoint import load_model

    model, meta = load_model(ckpt)
    assert meta.calibration == CALIBRATION
    with torch.no_grad():
        out = model(torch.from_numpy(x))
    return {"height": CALIBRATION.height(out["height"].numpy()),
            "classes": torch.softmax(out["classes"], 1).numpy()}


def test_models_of_other_than_8_bit_images_are_flagged_for_deepness() -> None:
    _, meta = tiny_d3net()
    assert deepness_input_problem(replace(meta, input_dtype="uint8")) is None
    assert deepness_input_problem(meta) is None  # not recorded (older checkpoints): nothing to say
    problem = deepness_input_problem(replace(meta, input_dtype="uint16"))
    assert problem is not None and "uint16" in problem and "8-bit" in problem
    md = json.loads(export_metadata(replace(meta, input_dtype="uint16"), "height", 512, 64)["aerialmtl"])
    assert md["input_dtype"] == "uint16"


def test_the_calibration_in_the_graph_is_the_checkpoint_s() -> None:
    head = ExportHead(torch.nn.Identity(), ("height",), CALIBRATION)
    h = torch.linspace(-5.0, 40.0, 2001).reshape(1, 1, 1, -1)
    np.testing.assert_allclose(head.calibrate(h).numpy(), CALIBRATION.height(h.numpy()), atol=1e-5)


def _image(n: int = 3, seed: int = 0) -> np.ndarray:
    """Raw 8-bit band values, N×3×TILE×TILE."""
    return np.random.default_rng(seed).integers(0, 256, (n, 3, TILE, TILE)).astype(np.float32)


def test_onnx_reproduces_torch_and_carries_the_metadata(exported: dict[str, Path]) -> None:
    import onnxruntime as ort

    _, meta = tiny_d3net()
    raw = _image()
    x = ((raw - np.array(meta.mean, np.float32)[:, None, None]) / np.array(meta.std, np.float32)[:, None, None])
    sess = ort.InferenceSession(str(exported["all"]), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["image"] and sess.get_inputs()[0].shape[1:] == [3, TILE, TILE]
    height, probs = sess.run(["height", "classes"], {"image": x})
    ref = _torch(exported["ckpt"], x)
    np.testing.assert_allclose(height, ref["height"], atol=1e-4, rtol=0)  # metres
    np.testing.assert_allclose(probs, ref["classes"], atol=1e-5, rtol=0)

    md = read_metadata(exported["all"])
    assert "model_type" not in md  # two tasks: not one Deepness model type
    assert md["resolution"] == pytest.approx(50.0) and md["tile_size"] == TILE and md["tiles_overlap"] == 25
    assert md["standardization_mean"] == pytest.approx([m / 255 for m in meta.mean])
    assert md["aerialmtl"]["mean"] == list(meta.mean) and md["aerialmtl"]["outputs"]["height"]["unit"] == "m"
    assert md["aerialmtl"]["height_calibration"].startswith("isotonic height map")
    assert [c["name"] for c in md["aerialmtl"]["classes"]] == [c.name for c in meta.classes.classes]  # type: ignore[union-attr]

    # Deepness's own preprocessing (8-bit values / 255, then its standardisation) gives the same input
    std_mean = np.array(md["standardization_mean"], np.float32)[:, None, None]
    std_std = np.array(md["standardization_std"], np.float32)[:, None, None]
    np.testing.assert_allclose((raw / 255.0 - std_mean) / std_std, x, atol=1e-4)


def test_qgis_files_per_task_and_openvino_ir(exported: dict[str, Path], capsys: pytest.CaptureFixture) -> None:
    import onnxruntime as ort

    from aerialmtl.runtime import openvino_core

    ckpt, root = exported["ckpt"], exported["ckpt"].parent
    x = (_image(2, seed=1) - 110.0) / 40.0
    ref = _torch(ckpt, x)
    # QGIS (Deepness) takes one task per file: a Segmentor as ONNX, a Regressor here as OpenVINO IR
    code, out, err = run_cli(capsys, "export", ckpt, "--task", "classes", "--tile", TILE, "--out", root / "c.onnx")
    assert code == 0, err
    assert "Deepness Segmentor" in out
    sess = ort.InferenceSession(str(root / "c.onnx"), providers=["CPUExecutionProvider"])
    assert [o.name for o in sess.get_outputs()] == ["classes"]
    (probs,) = sess.run(None, {"image": x})
    np.testing.assert_allclose(probs, ref["classes"], atol=1e-5, rtol=0)
    md = read_metadata(root / "c.onnx")
    _, meta = tiny_d3net()
    assert md["model_type"] == "Segmentor" and md["tiles_overlap"] == 13  # default overlap: tile / 8
    assert md["class_names"] == {str(i): c.name for i, c in enumerate(meta.classes.classes)}  # type: ignore[union-attr]

    code, out, err = run_cli(capsys, "export", ckpt, "--format", "openvino", "--task", "height", "--tile", TILE,
                             "--out", root / "h.xml")
    assert code == 0, err
    assert "Deepness Regressor" in out and (root / "h.xml").is_file() and (root / "h.bin").is_file()
    compiled = openvino_core().compile_model(str(root / "h.xml"), "CPU", {"INFERENCE_PRECISION_HINT": "f32"})
    assert [o.get_any_name() for o in compiled.outputs] == ["height"]
    height = compiled({"image": x})[compiled.output(0)]
    np.testing.assert_allclose(height, ref["height"], atol=1e-4, rtol=0)
    md = read_metadata(root / "h.xml")
    assert md["model_type"] == "Regressor" and md["reg_output_scaling"] == 1.0
    assert md["class_names"] == {"0": "height (m)"}

    # refusals: existing file, wrong extension, a bad tile: one line or a usage error, nothing written
    code, _, err = run_cli(capsys, "export", ckpt, "--out", root / "model.onnx")
    assert code == 1 and "--overwrite" in err and len(err.strip().splitlines()) == 1
    code, _, err = run_cli(capsys, "export", ckpt, "--format", "openvino", "--out", root / "x.onnx")
    assert code == 2 and "--out" in err and ".xml" in err
    code, _, err = run_cli(capsys, "export", ckpt, "--tile", "100", "--out", root / "y.onnx")
    assert code == 2 and "--tile" in err and not (root / "y.onnx").exists()
    assert not list(root.glob(".aerialmtl-export-*"))  # no staging left behind
    assert json.loads(json.dumps(read_metadata(root / "model.onnx")))  # plain JSON values
