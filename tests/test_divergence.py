"""Divergence is a failure (issue 24, part 3): a run whose validation error explodes, or whose loss grows by
orders of magnitude, stops like a non-finite one and never writes best.pt; predict refuses maps far outside
the heights the checkpoint was trained on; tile warns on heights no surface has."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import run_cli, tiny_d3net, write_raster
from test_robustness import CRS, PREDICT, T05, assert_ok, no_final_outputs, rgb, tiny_train_yaml
from test_sanity import one_error_line
from tilefolder import write_tile_folder

from aerialmtl.errors import NonFiniteError
from aerialmtl.formats.checkpoint import load_checkpoint, save_checkpoint
from aerialmtl.training.distributed import DistContext
from aerialmtl.training.trainer import LOSS_GROWTH, LossWindow

run = run_cli


@pytest.fixture(scope="module")
def tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tile_folder(tmp_path_factory.mktemp("t") / "tiles", size=64, counts={"train": 8, "val": 2})


def test_a_diverged_but_finite_run_fails_and_writes_no_best(tiles: Path, tmp_path: Path, capsys) -> None:
    """optim.lr 0.1 for 3 steps: finite losses, validation heights off by kilometres."""
    cfg = tiny_train_yaml(tmp_path / "c.yaml")
    data = yaml.safe_load(cfg.read_text())
    data["optim"] = {"lr": 0.1}
    data["schedule"].update(val_every=1)
    cfg.write_text(yaml.safe_dump(data))
    run_dir = tmp_path / "run"
    line = one_error_line(run(capsys, "train", "--config", cfg, "--data", tiles, "--out", run_dir, "--max-steps", "3",
                              "--quiet"), "training diverged: the validation height MAE at step", "lower optim.lr")
    assert "it was not saved as best.pt" in line and " m for reference heights of 0..8 m" in line
    assert not (run_dir / "best.pt").exists()
    # the same run at the config's sane learning rate trains and records the heights it saw
    data["optim"] = {"lr": 2e-3}
    cfg.write_text(yaml.safe_dump(data))
    assert_ok(run(capsys, "train", "--config", cfg, "--data", tiles, "--out", tmp_path / "ok", "--max-steps", "3",
                  "--quiet"))
    meta = load_checkpoint(tmp_path / "ok" / "best.pt")[1]
    assert meta.height_range is not None and meta.height_range[0] == 0 and 5 < meta.height_range[1] <= 8


def test_a_loss_grown_by_orders_of_magnitude_is_a_divergence() -> None:
    window = LossWindow(("height", "classes"), DistContext.from_env("cpu"))
    window.add(1, torch.tensor(3.0), {"height": torch.tensor(2.0), "classes": torch.tensor(1.0)})
    window.add(2, torch.tensor(3.0), {"height": torch.tensor(2.0 * LOSS_GROWTH / 10), "classes": torch.tensor(1.0)})
    window.flush()  # 1000 times: a bad stretch, not yet a divergence
    window.add(3, torch.tensor(3.0), {"height": torch.tensor(2.0 * LOSS_GROWTH * 10), "classes": torch.tensor(1.0)})
    with pytest.raises(NonFiniteError, match=r"training diverged at step 3: the height loss grew from 2 to 2e\+05"):
        window.flush()


def _checkpoint(path: Path, bias: float, height_range: tuple[float, float] | None) -> Path:
    """A tiny model whose height head adds ``bias`` metres everywhere."""
    model, meta = tiny_d3net()
    with torch.no_grad():
        model.heads["height"].head.bias.fill_(bias)
    save_checkpoint(path, model, dataclasses.replace(meta, height_range=height_range))
    return path


@pytest.mark.parametrize(("bias", "height_range", "refused"), [
    (1e15, (0.0, 30.0), True),    # a diverged model: heights of 1e15 m
    (900.0, (0.0, 30.0), True),   # far above 30 m + 10 × 30 m + 100 m
    (60.0, (0.0, 30.0), False),   # taller than anything in training, still a height
    (5e3, None, True),            # an older checkpoint without the range: beyond any surface
])
def test_predict_refuses_heights_far_outside_the_trained_range(tmp_path: Path, capsys, bias: float,
                                                               height_range: tuple[float, float] | None,
                                                               refused: bool) -> None:
    ckpt = _checkpoint(tmp_path / "m.pt", bias, height_range)
    out = tmp_path / "pred"
    result = run(capsys, "predict", rgb(tmp_path), "--model", ckpt, "--out", out, *PREDICT)
    if refused:
        one_error_line(result, f"the model of checkpoint '{ckpt}' gives heights of", "so no prediction was written",
                       "lower optim.lr")
        assert no_final_outputs(out)
    else:
        assert_ok(result)


def test_tile_warns_on_heights_no_surface_has(tmp_path: Path, capsys) -> None:
    ortho = rgb(tmp_path)
    dsm = np.full((64, 64), 120.0, np.float32)
    dsm[:8, :8] = 3e38  # an undeclared nodata value
    dsm_path = write_raster(tmp_path / "dsm.tif", dsm, CRS, T05)
    dtm_path = write_raster(tmp_path / "dtm.tif", np.full((64, 64), 100.0, np.float32), CRS, T05)
    warnings = assert_ok(run(capsys, "tile", "--ortho", ortho, "--dsm", dsm_path, "--dtm", dtm_path, "--size", "32",
                             "--min-valid", "0", "--out", tmp_path / "t", "--quiet"))
    hits = [w for w in warnings if "no surface has" in w]
    assert len(hits) == 1 and "3e+38 m" in hits[0] and "DSM − DTM" in hits[0] and "gdal_edit.py -a_nodata" in hits[0]
    # plausible heights: no warning
    warnings = assert_ok(run(capsys, "tile", "--ortho", ortho, "--dsm", dtm_path, "--dtm", dtm_path, "--size", "32",
                             "--min-valid", "0", "--out", tmp_path / "t2", "--quiet"))
    assert not [w for w in warnings if "no surface has" in w]


def test_train_on_heights_no_surface_has_names_the_heights_not_the_learning_rate(tmp_path: Path, capsys) -> None:
    """A DSM with an undeclared nodata of 3e38: tile warns, and train's divergence message points at the heights."""
    ortho = rgb(tmp_path, size=(128, 128))
    dsm = np.full((128, 128), 110.0, np.float32)
    dsm[:40, :40] = 3e38
    dsm_path = write_raster(tmp_path / "dsm.tif", dsm, CRS, T05)
    dtm_path = write_raster(tmp_path / "dtm.tif", np.full((128, 128), 100.0, np.float32), CRS, T05)
    tiles = tmp_path / "t"
    assert_ok(run(capsys, "tile", "--ortho", ortho, "--dsm", dsm_path, "--dtm", dtm_path, "--size", "32",
                  "--split-block", "16", "--min-valid", "0", "--out", tiles, "--quiet"))
    line = one_error_line(run(capsys, "train", "--config", tiny_train_yaml(tmp_path / "c.yaml"), "--data", tiles,
                              "--out", tmp_path / "run", "--max-steps", "3", "--quiet"), "training diverged",
                          "reference heights reach 10..3e+38 m, which no surface has", "gdal_edit.py -a_nodata")
    assert "lower optim.lr" not in line
