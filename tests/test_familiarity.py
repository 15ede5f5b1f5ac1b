"""Unfamiliarity: a density of the encoder's features fitted after training, written by predict as its own layer."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from helpers.rasters import write_raster
from helpers.tilefolder import toy_patch, write_tile_folder

from aerialmtl.errors import CheckpointError
from aerialmtl.formats.checkpoint import ModelMeta, load_checkpoint, load_model, save_checkpoint
from aerialmtl.formats.prediction import FLOAT_NODATA, UNFAMILIARITY, layer_filename, style_filename
from aerialmtl.inference.predict import predict_raster
from aerialmtl.models.familiarity import fit_density
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.loop import train


def _blobs(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """N×12 features from three Gaussian blobs and their labels."""
    labels = rng.integers(0, 3, n)
    centres = rng.normal(0, 4, (3, 12))
    return centres[labels] + rng.normal(0, 1, (n, 12)), labels


def _as_map(x: np.ndarray) -> list[torch.Tensor]:
    """N×C rows as one level-0 feature map (1×C×1×N)."""
    return [torch.from_numpy(x.T[None, :, None, :].astype(np.float32))]


@pytest.mark.parametrize("labelled", [True, False])
def test_density_ranks_new_points_like_the_training_ones_and_far_ones_at_the_top(labelled: bool) -> None:
    rng = np.random.default_rng(0)
    x, labels = _blobs(rng, 3000)
    dens = fit_density(x, (0,), 1, dims=6, labels=labels if labelled else None, components=3)
    assert dens.method == ("gda" if labelled else "em") and dens.dims == 6 and dens.components == 3
    # new points of the same blobs: about uniform over 0..1 (the share of training points more familiar)
    new = x[rng.permutation(len(x))[:1000]] + rng.normal(0, 0.05, (1000, 12))
    u = dens.unfamiliarity(_as_map(new), (1, 1000))[0, 0].numpy()
    assert np.isfinite(u).all() and u.min() >= 0.0 and u.max() <= 1.0
    assert 0.35 < float(np.median(u)) < 0.65
    # far from every blob: beyond all training points
    far = rng.normal(0, 1, (50, 12)) + 40.0
    assert float(dens.unfamiliarity(_as_map(far), (1, 50)).min()) == 1.0
    # stored as plain values: a round trip through the checkpoint's dict gives the same density
    assert ModelMeta.from_dict({**_meta().to_dict(), "familiarity": dataclasses.asdict(dens)}).familiarity == dens


def _meta() -> ModelMeta:
    from helpers.models import tiny_d3net

    return tiny_d3net()[1]


def test_a_damaged_density_is_refused_with_the_fix() -> None:
    dens = fit_density(np.random.default_rng(1).normal(size=(200, 4)), (0,), 1, dims=2)
    with pytest.raises(CheckpointError, match="refit the density"):
        dataclasses.replace(dens, quantiles=tuple(reversed(dens.quantiles)))
    with pytest.raises(CheckpointError, match="basis"):
        dataclasses.replace(dens, basis=dens.basis[:1] + ((1.0,),))


# ---- end to end ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny D3-Net trained 4 steps (feature density fitted after training on its stride-8 level: the tiny
    encoder has 4 channels at stride 16)."""
    root = tmp_path_factory.mktemp("fam")
    tiles = write_tile_folder(root / "tiles", size=64, counts={"train": 8, "val": 2}, tasks=("height",))
    cfg = TrainConfig.from_dict({
        "model": {"growth_rate": 4, "block_config": [1, 1, 1, 1], "num_init_features": 8, "bn_size": 2},
        "data": {"batch_size": 4, "num_workers": 0}, "schedule": {"epochs": 100, "log_every": 1}, "seed": 0,
        "device": "cpu", "calibration": {"enabled": False}, "familiarity": {"levels": [2], "dims": 8}})
    return train(cfg, tiles, root / "run", max_steps=4, progress=False).best_checkpoint


def _ortho(path: Path) -> Path:
    """A 128×64 orthophoto: left half a training-like scene, right half a saturated magenta/green checkerboard
    the training patches never show."""
    image, _, _ = toy_patch(np.random.default_rng(7), 64)
    yy, xx = np.mgrid[0:64, 0:64]
    check = ((yy // 4 + xx // 4) % 2).astype(bool)
    odd = np.where(check, np.array([255, 0, 255])[:, None, None], np.array([0, 255, 0])[:, None, None])
    return write_raster(path, np.concatenate([image, odd.astype(np.uint8)], axis=2))


@pytest.mark.parametrize("engine", ["openvino", "torch"])
@pytest.mark.parametrize("mc", [1, 3])
def test_predict_writes_lists_and_styles_an_unfamiliarity_layer_higher_on_unseen_texture(
        trained: Path, tmp_path: Path, engine: str, mc: int) -> None:
    _, meta = load_checkpoint(trained)
    assert meta.familiarity is not None and meta.familiarity.levels == (2,) and meta.familiarity.n_pixels > 0
    res = predict_raster(_ortho(tmp_path / "o.tif"), trained, tmp_path / "pred", mc=mc, engine=engine,
                         progress=False)
    out = res.out_dir
    with rasterio.open(out / layer_filename(UNFAMILIARITY)) as src:
        u = src.read(1)
        assert src.nodata == FLOAT_NODATA and src.dtypes[0] == "float32"
    assert np.isfinite(u).all() and u.min() >= 0.0 and u.max() <= 1.0
    # away from the seam (the receptive field mixes the halves there)
    assert float(u[:, 80:].mean()) > float(u[:, :40].mean()) + 0.2
    info = json.loads((out / "prediction.json").read_text())
    assert info["files"][UNFAMILIARITY] == layer_filename(UNFAMILIARITY)
    assert info["engine"] == engine and "gda density" in info["model"]["unfamiliarity"]
    item = json.loads((out / "item.json").read_text())
    assert "uncertainty" in item["assets"][UNFAMILIARITY]["roles"]
    qml = (out / style_filename(UNFAMILIARITY)).read_text()
    assert 'classificationMax="1"' in qml and 'classificationMin="0"' in qml


def test_both_engines_give_the_same_unfamiliarity(trained: Path, tmp_path: Path) -> None:
    ortho = _ortho(tmp_path / "o.tif")
    maps = []
    for engine in ("openvino", "torch"):
        res = predict_raster(ortho, trained, tmp_path / engine, mc=3, engine=engine, precision="fp32",
                             progress=False)
        with rasterio.open(res.out_dir / layer_filename(UNFAMILIARITY)) as src:
            maps.append(src.read(1))
    np.testing.assert_allclose(maps[0], maps[1], atol=2e-3)


def test_an_old_checkpoint_without_a_density_predicts_without_the_layer(trained: Path, tmp_path: Path) -> None:
    model, meta = load_model(trained)
    path = tmp_path / "old.pt"
    save_checkpoint(path, model, dataclasses.replace(meta, familiarity=None))
    payload = torch.load(path, weights_only=True)
    payload["meta"].pop("familiarity")  # what checkpoints written before the field hold
    torch.save(payload, path)
    assert load_checkpoint(path)[1].familiarity is None
    res = predict_raster(_ortho(tmp_path / "o.tif"), path, tmp_path / "pred", mc=3, engine="torch", progress=False)
    info = json.loads((res.out_dir / "prediction.json").read_text())
    assert UNFAMILIARITY not in info["files"] and not (res.out_dir / layer_filename(UNFAMILIARITY)).exists()
    assert info["model"]["unfamiliarity"].startswith("none")
    assert (res.out_dir / "height.tif").is_file()


def test_a_run_whose_last_validation_was_its_best_fits_its_density_once(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """best.pt and last.pt of a 2-step run hold the same network: the encoder runs over the training patches once
    and both checkpoints carry the same density (the one fitted on it)."""
    from aerialmtl.training import familiarity

    calls = []
    real = familiarity.feature_pixels

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(familiarity, "feature_pixels", counted)
    tiles = write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 8, "val": 2}, tasks=("height",))
    cfg = TrainConfig.from_dict({
        "model": {"growth_rate": 4, "block_config": [1, 1, 1, 1], "num_init_features": 8, "bn_size": 2},
        "data": {"batch_size": 4, "num_workers": 0}, "schedule": {"epochs": 100}, "seed": 0,
        "device": "cpu", "calibration": {"enabled": False}, "familiarity": {"levels": [2], "dims": 8}})
    res = train(cfg, tiles, tmp_path / "run", max_steps=2, progress=False)
    best, last = load_checkpoint(res.best_checkpoint)[1], load_checkpoint(res.last_checkpoint)[1]
    assert len(calls) == 1 and best.familiarity is not None
    assert last.familiarity == best.familiarity
