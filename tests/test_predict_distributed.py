"""`aerialmtl predict` under torchrun: two CPU processes (gloo) give the maps of one process.

Three inputs over two ranks (the middle one is cut into row strips, one per rank) and one raster split
across both ranks; the outputs must equal a one-process run bit for bit (same windows, batches and
per-window dropout masks; one torch thread in every process), the mosaic must cover every input, and a
rank that fails must fail the run naming the input while leaving no file at a final path.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from helpers.models import tiny_d3net
from helpers.rasters import write_raster
from helpers.sun_town import sun_town

from aerialmtl.formats.checkpoint import save_checkpoint
from aerialmtl.formats.prediction import ALL_FILES, mosaic_filename

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
ARGS = ("--mc", "2", "--window", "64", "--overlap", "16", "--quiet")

pytestmark = pytest.mark.slow


def _predict(orthos: list[Path], ckpt: Path, out: Path, ranks: int, *extra: str) -> subprocess.CompletedProcess:
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(ranks)]
    launch = [sys.executable, "-m", "aerialmtl"] if ranks == 1 else [*torchrun, "-m", "aerialmtl"]
    cmd = [*launch, "predict", *map(str, orthos), "--model", str(ckpt), "--out", str(out), *ARGS, *extra]
    return subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=600)


def _layers(folder: Path) -> dict[str, np.ndarray]:
    out = {}
    for path in sorted(folder.glob("*.tif")):
        with rasterio.open(path) as ds:
            out[path.name] = ds.read()
    return out


def _two_ranks_equal_one(ortho: Path, ckpt: Path, tmp_path: Path, *extra: str) -> dict[str, np.ndarray]:
    """Predict ``ortho`` in one process and over two ranks with ``extra`` options; every layer equal to the bit.
    Returns the layers."""
    one = _predict([ortho], ckpt, tmp_path / "one", 1, *extra)
    assert one.returncode == 0, one.stderr
    two = _predict([ortho], ckpt, tmp_path / "two", 2, *extra)
    assert two.returncode == 0, two.stderr
    a, b = _layers(tmp_path / "one"), _layers(tmp_path / "two")
    assert a.keys() == b.keys()
    for name in a:
        np.testing.assert_array_equal(b[name], a[name], err_msg=name)
    return a


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("dist")
    model, meta = tiny_d3net()
    save_checkpoint(root / "m.pt", model, meta)
    rng = np.random.default_rng(11)
    paths = {"ckpt": root / "m.pt"}
    for k, (x0, y0) in enumerate(((500000.0, 5000000.0), (500040.0, 4999980.0), (500100.0, 5000010.0))):
        img = rng.integers(1, 256, size=(3, 96, 96)).astype(np.uint8)
        img[:, :10, :10] = 0
        paths[f"t{k}"] = write_raster(root / f"t{k}.tif", img, nodata=0, transform=Affine(0.5, 0, x0, 0, -0.5, y0))
    model, meta = tiny_d3net(aleatoric=True)  # the small-area recipe's head
    save_checkpoint(root / "aleatoric.pt", model, meta)
    paths["aleatoric"] = root / "aleatoric.pt"
    big = rng.integers(1, 256, size=(3, 200, 90)).astype(np.uint8)
    paths["big"] = write_raster(root / "big.tif", big)
    return paths


def test_three_inputs_over_two_ranks_equal_one_process(inputs: dict[str, Path], tmp_path: Path) -> None:
    orthos = [inputs["t0"], inputs["t1"], inputs["t2"]]
    one = _predict(orthos, inputs["ckpt"], tmp_path / "one", 1)
    assert one.returncode == 0, one.stderr
    two = _predict(orthos, inputs["ckpt"], tmp_path / "two", 2)
    assert two.returncode == 0, two.stderr
    for ortho in orthos:
        a, b = _layers(tmp_path / "one" / ortho.stem), _layers(tmp_path / "two" / ortho.stem)
        assert a.keys() == b.keys() and len(a) == 5
        for name in a:
            np.testing.assert_array_equal(b[name], a[name], err_msg=f"{ortho.stem}/{name}")
    info = json.loads((tmp_path / "two" / "t1" / "prediction.json").read_text())
    assert info["processes"] == 2  # the middle input was cut into strips computed by both ranks
    assert not any(p.name.startswith(".") for p in (tmp_path / "two").rglob("*"))  # no hidden leftovers
    with rasterio.open(tmp_path / "two" / mosaic_filename("height")) as vrt:
        for ortho in orthos:
            with rasterio.open(ortho) as src:
                b = src.bounds
            assert vrt.bounds.left <= b.left and vrt.bounds.right >= b.right
            assert vrt.bounds.bottom <= b.bottom and vrt.bounds.top >= b.top
            with rasterio.open(tmp_path / "two" / ortho.stem / "height.tif") as layer:
                assert (vrt.read(1, window=vrt.window(*layer.bounds)) != -9999.0).any()


def test_one_raster_split_across_two_ranks_equals_one_process(inputs: dict[str, Path], tmp_path: Path) -> None:
    assert len(_two_ranks_equal_one(inputs["big"], inputs["ckpt"], tmp_path)) == 5
    assert json.loads((tmp_path / "two" / "prediction.json").read_text())["processes"] == 2


def test_a_failing_rank_fails_the_run_naming_the_input(inputs: dict[str, Path], tmp_path: Path) -> None:
    bad = tmp_path / "bad.tif"
    data = inputs["big"].read_bytes()
    bad.write_bytes(data[: len(data) * 2 // 3])  # header intact, pixels cut off: fails while reading
    res = _predict([inputs["t0"], bad], inputs["ckpt"], tmp_path / "out", 2)
    assert res.returncode != 0
    assert f"failed on input '{bad}'" in res.stderr and "truncated or corrupt" in res.stderr
    assert not any((tmp_path / "out" / "bad" / f).exists() for f in ALL_FILES)
    assert (tmp_path / "out" / "t0" / "prediction.json").exists()  # the other input is complete


def test_aleatoric_head_with_tta_split_across_two_ranks_equals_one_process(inputs: dict[str, Path],
                                                                          tmp_path: Path) -> None:
    """The recipe's options under torchrun: the aleatoric spread and ``--tta`` give one process's maps."""
    assert "height_std.tif" in _two_ranks_equal_one(inputs["big"], inputs["aleatoric"], tmp_path, "--tta")
    info = json.loads((tmp_path / "two" / "prediction.json").read_text())
    assert info["processes"] == 2 and info["tta"]


def test_sun_tune_split_across_two_ranks_equals_one_process(tmp_path: Path) -> None:
    """`--sun-tune` under torchrun: every rank tunes the same weights (the same crops, one thread), so the raster
    split across two ranks has one process's maps, and its record names the same tuned weights."""
    town = sun_town(tmp_path)
    assert "shadow_height.tif" in _two_ranks_equal_one(town["ortho"], town["ckpt"], tmp_path, "--sun-tune", "3")
    info_one = json.loads((tmp_path / "one" / "prediction.json").read_text())
    info_two = json.loads((tmp_path / "two" / "prediction.json").read_text())
    assert info_two["processes"] == 2 and info_two["sun_tune"]["steps"] == 3
    assert info_two["provenance"]["checkpoint"] == info_one["provenance"]["checkpoint"]
