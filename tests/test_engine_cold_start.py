"""A run that `--engine auto` gives to torch because OpenVINO's cache is cold does not pay for OpenVINO at all: its
import (~0.5 s) and its Core were a second of a small job that then ran on torch (issue 60: from a cold cache the
default must be as fast as `--engine torch`). Nor for OpenVINO's checkpoint record: hashing the file a second time
and a forward pass to list the dropout layers (~0.3 s of the DenseNet-121) are spent when OpenVINO runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from helpers.models import tiny_d3net
from helpers.rasters import write_raster

from aerialmtl.formats.checkpoint import save_checkpoint

CODE = """
import json, sys
from aerialmtl.cli import cli
cli.main(args=["predict", sys.argv[1], "--model", sys.argv[2], "--out", sys.argv[3], "--quiet"], standalone_mode=False)
print(json.dumps("openvino" in sys.modules and sys.modules["openvino"] is not None))
"""


def test_a_cold_cache_small_job_runs_torch_without_importing_openvino(tmp_path: Path) -> None:
    model, meta = tiny_d3net()
    ckpt = tmp_path / "m.pt"
    save_checkpoint(ckpt, model, meta)
    rng = np.random.default_rng(0)
    ortho = write_raster(tmp_path / "o.tif", rng.integers(1, 256, size=(3, 64, 64)).astype(np.uint8))
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "AERIALMTL_CACHE": str(tmp_path / "cache"), "AERIALMTL_CPU_KIND": "avx512",
           "AERIALMTL_OPENVINO_CACHE": str(tmp_path / "cache" / "openvino"),  # the suite's store is warm
           "PYTHONPATH": os.pathsep.join([str(root), str(root / "tests"), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-c", CODE, str(ortho), str(ckpt), str(tmp_path / "p")], env=env,
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    record = json.loads((tmp_path / "p" / "prediction.json").read_text())
    assert record["engine"] == "torch" and "cold" in record["engine_choice"]["reason"], record["engine_choice"]
    assert json.loads(proc.stdout.strip().splitlines()[-1]) is False, "OpenVINO was imported for a torch run"
    assert not list((tmp_path / "cache").rglob("*.record")), "OpenVINO's checkpoint record was made for a torch run"
