"""The shadow head (``model.shadow_head``, issue 58): its labels (the cast shadows of the training heights at the
training sun, with the unknown border ignored), the labels moved with the image by every augmentation, the head
learning from them, training that fits the sun once, predict's ``shadow.tif`` from the head (the colour classifier
without it), and the paper's network unchanged when it is off."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from helpers.tilefolder import write_tile_folder

from aerialmtl.data.batches import CachedBatches, finish_on_device, prepare_batch
from aerialmtl.data.cache import PatchCache, ensure_patch_cache
from aerialmtl.data.prefetch import AssembledBatches
from aerialmtl.data.shadow_labels import SHADOW_IGNORE, patch_labels, shadow_labels
from aerialmtl.data.synth import synthesize
from aerialmtl.data.transforms import build_train_transform
from aerialmtl.errors import ConfigError
from aerialmtl.formats.tiles import TileFolderInfo, cache_dir
from aerialmtl.models.config import ModelConfig
from aerialmtl.models.d3net import D3Net
from aerialmtl.sun import Sun

TINY = {"growth_rate": 4, "block_config": (1, 1, 1, 1), "num_init_features": 8, "bn_size": 2}


# ---- labels -----------------------------------------------------------------------------------------------------
def _box(h: int = 40, w: int = 60) -> np.ndarray:
    """A 10 m box (rows 15-24, columns 20-29) on flat ground at 1 m."""
    z = np.zeros((h, w), np.float32)
    z[15:25, 20:30] = 10.0
    return z


def test_a_box_casts_the_shadow_worked_out_by_hand_and_the_sun_side_border_is_unknown() -> None:
    """Sun in the east at 45°: the 10 m box shades the 9 columns west of it (the 10th is within the 0.3 m
    tolerance), its own top and the ground elsewhere are lit, and the 9 columns at the eastern edge are unknown (a
    10 m object just beyond the edge could shade them); the western edge, facing away from the sun, is known."""
    lab = shadow_labels(_box(), 1.0, Sun(90.0, 45.0))
    expected = np.zeros((40, 60), np.uint8)
    expected[15:25, 11:20] = 1
    expected[:, 51:] = SHADOW_IGNORE
    np.testing.assert_array_equal(lab, expected)


def test_a_roof_slope_facing_away_from_the_sun_and_nodata_are_not_shadow() -> None:
    """A roof sloping 30° down to the west (self-shaded under a 45° sun in the east, but casting no shadow on itself)
    is lit in the labels; a nodata height is unknown, and so are the pixels it could shade."""
    z = np.zeros((40, 60), np.float32)
    z[10:30, 20:35] = 2.0 + np.tan(np.radians(30.0)) * np.arange(15, dtype=np.float32)  # rises eastwards
    lab = shadow_labels(z, 1.0, Sun(90.0, 45.0), cap_m=12.0)
    assert (lab[10:30, 20:35] == 0).all()  # the slope faces away from the sun: lit as far as cast shadow goes
    assert (lab[10:30, 5:20] == 1).any()  # the building's cast shadow on the ground to its west
    z[5, 40] = np.nan
    lab = shadow_labels(z, 1.0, Sun(90.0, 45.0), cap_m=12.0)
    assert lab[5, 40] == SHADOW_IGNORE and (lab[5, 29:40] == SHADOW_IGNORE).all()  # a 12 m unknown: 11 px of shade
    assert lab[5, 41] == 0 and lab[6, 40] == 0  # on the sun's side of it, and beside it: known


def test_overlapping_patches_see_their_neighbours_occluders_on_the_tile_grid() -> None:
    """Patch B holds the box's shadow but not the box (it is in patch A, east of B): labelled from the mosaic, B's
    shadow pixels are 1; labelled alone, they are unknown (the occluder is beyond B's sun-side edge)."""
    z = _box()
    a, b = z[:, 16:36], z[:, 0:20]  # A holds the box (columns 20-29), B its shadow (11-19) only
    heights = np.stack([a, b])
    together = patch_labels(heights, 1.0, Sun(90.0, 45.0), offsets=[(0, 16), (0, 0)])
    alone = patch_labels(heights, 1.0, Sun(90.0, 45.0))
    assert (together[1][15:25, 11:20] == 1).all() and (together[1][:15, :20] == 0).all()
    assert (alone[1][15:25, 11:20] == SHADOW_IGNORE).all()
    np.testing.assert_array_equal(together[1][:, 11:20], shadow_labels(z, 1.0, Sun(90.0, 45.0))[:, 11:20])


# ---- augmentation -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("path", ["device", "cpu", "thread"])
@pytest.mark.parametrize("crop", [None, 32])
def test_every_flip_rotation_and_crop_moves_the_labels_with_the_image(tmp_path: Path, path: str,
                                                                      crop: int | None) -> None:
    """Labels made from each patch's own image (band 0 above its median) come out of the training batches equal to
    the same function of the augmented image, pixel for pixel, on each data path (GPU's torch, CPU's compiled pass,
    the CPU loader's thread)."""
    tiles = write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 6, "val": 1},
                              invalid_corner=False)
    info = TileFolderInfo.read(tiles)
    index = ensure_patch_cache(info, "train")
    cache = PatchCache(cache_dir(tiles), index)
    image = np.asarray(cache.arrays()["image"])
    labels = (image[:, 0] > np.median(image[:, 0], axis=(1, 2), keepdims=True)).astype(np.uint8)
    transform = build_train_transform(flips=True, rot90=True, crop_size=crop)
    mean, std = torch.tensor(info.mean), torch.tensor(info.std)
    spec = [(i, 1000 + i) for i in range(6)]
    if path == "thread":
        (item,) = list(AssembledBatches(cache, transform, info.tasks, [spec], mean, std, shadow=labels))
        batch = prepare_batch(item, transform, mean, std, torch.device("cpu"))
    else:
        raw = CachedBatches(cache, transform, info.tasks, shadow=labels)[spec]
        batch = (finish_on_device(raw["data"], raw["params"], transform, mean, std) if path == "device"
                 else prepare_batch(raw, transform, mean, std, torch.device("cpu")))
    raw_band = batch["image"][:, 0] * std[0] + mean[0]  # the moved image's band 0, in stored values
    assert batch["shadow"].dtype == torch.uint8 and batch["shadow"].shape == raw_band.shape
    for n, (i, _) in enumerate(spec):
        threshold = np.median(image[i, 0])
        expected = (raw_band[n] > float(threshold) + 1e-3).to(torch.uint8)
        assert torch.equal(batch["shadow"][n], expected), (path, crop, n)


# ---- the model --------------------------------------------------------------------------------------------------
def test_the_head_off_keeps_the_papers_network_and_on_adds_one_branch_only() -> None:
    """Off (the default), the state_dict has the names and shapes of the paper's network; on, the same plus one
    ``heads.shadow`` branch with a one-channel output, and a ``shadow`` output after the tasks."""
    base = ModelConfig(in_channels=3, num_classes=4, tasks=("height", "classes"), **TINY)  # type: ignore[arg-type]
    off = D3Net(base).state_dict()
    paper = D3Net(ModelConfig(in_channels=3, num_classes=4, tasks=("height", "classes"), shadow_head=False,
                              **TINY)).state_dict()  # type: ignore[arg-type]
    assert [(k, v.shape) for k, v in off.items()] == [(k, v.shape) for k, v in paper.items()]
    assert not any("shadow" in k for k in off)
    on_cfg = ModelConfig(in_channels=3, num_classes=4, tasks=("height", "classes"), shadow_head=True,
                         **TINY)  # type: ignore[arg-type]
    on = D3Net(on_cfg)
    extra = [k for k in on.state_dict() if k not in off]
    assert extra and all(k.startswith("heads.shadow.") for k in extra)
    assert set(off) <= set(on.state_dict())
    out = on(torch.zeros(2, 3, 64, 64))
    assert on_cfg.outputs == ("height", "classes", "shadow") and out["shadow"].shape == (2, 1, 64, 64)
    with pytest.raises(ConfigError, match="model.shadow_head"):
        ModelConfig(in_channels=3, tasks=("classes",), shadow_head=True)


@pytest.mark.slow
def test_the_head_learns_the_cast_shadows_of_a_synthetic_town(tmp_path: Path) -> None:
    """A tiny D3-Net with the head, trained on one synthetic town's patches against their labels only (Adam, 60
    steps), separates cast shadow from the rest: its binary cross-entropy falls to under half its first value."""
    from aerialmtl.training.losses import shadow_bce

    res = synthesize(tmp_path / "town", size=128, seed=3, gsd=0.5)
    with rasterio.open(res.ortho) as src:
        rgb = src.read().astype(np.float32)
    with rasterio.open(res.ndsm) as src:
        ndsm = src.read(1).astype(np.float32)
    sun = Sun(res.sun_azimuth % 360.0, res.sun_elevation)
    labels = torch.from_numpy(shadow_labels(ndsm, 0.5, sun))[None]
    assert (labels == 1).any() and (labels == 0).any()
    x = torch.from_numpy((rgb - rgb.mean()) / rgb.std())[None]
    torch.manual_seed(0)
    model = D3Net(ModelConfig(in_channels=3, tasks=("height",), shadow_head=True, dropout=0.0,
                              **TINY))  # type: ignore[arg-type]
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    seen = []
    for _ in range(60):
        loss = shadow_bce(model(x)["shadow"], labels, SHADOW_IGNORE)
        opt.zero_grad()
        loss.backward()
        opt.step()
        seen.append(float(loss.detach()))
    assert min(seen[-5:]) < 0.5 * seen[0], seen[::10]


def test_the_loss_skips_unknown_pixels() -> None:
    """Unknown labels change neither the loss nor its gradient; a batch without a known pixel gives 0."""
    from aerialmtl.training.losses import shadow_bce

    logits = torch.zeros(1, 1, 2, 2, requires_grad=True)
    lab = torch.tensor([[[1, SHADOW_IGNORE], [0, SHADOW_IGNORE]]], dtype=torch.uint8)
    loss = shadow_bce(logits, lab, SHADOW_IGNORE)
    loss.backward()
    assert float(loss.detach()) == pytest.approx(np.log(2.0))
    assert logits.grad is not None and (logits.grad[0, 0, :, 1] == 0).all()
    assert float(shadow_bce(logits, torch.full_like(lab, SHADOW_IGNORE), SHADOW_IGNORE).detach()) == 0.0


# ---- predict ----------------------------------------------------------------------------------------------------
class _HeadModel(torch.nn.Module):
    """Height 5 m everywhere with a 1 m spread; with ``shadow``, a shadow logit that is band 1's normalised value
    times 3 (so P(cast shadow) = sigmoid(3·x₁) is known per pixel)."""

    def __init__(self, shadow: bool) -> None:
        super().__init__()
        self.shadow = shadow
        self.dummy = torch.nn.Parameter(torch.zeros(()))

    def encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        return [x]

    def decode(self, feats: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        x = feats[0]
        out = {"height": torch.full_like(x[:, :1], 5.0), "height_scale": torch.full_like(x[:, :1], 0.7)}
        if self.shadow:
            out["shadow"] = 3.0 * x[:, 1:2]
        return out

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.decode(self.encode(x))


def test_predict_writes_shadow_from_the_head_where_the_checkpoint_has_one(tmp_path: Path) -> None:
    """With the head, shadow.tif is its P(cast shadow) per pixel (float32 in [0, 1], the mean over the MC samples),
    nodata where the orthophoto is; without it, the checkpoint's colour classifier writes it (other values)."""
    from aerialmtl.classes import ClassDef, ClassScheme
    from aerialmtl.formats.checkpoint import ModelMeta
    from aerialmtl.inference.jobs import predict_raster
    from aerialmtl.sun import ShadowModel
    from aerialmtl.sun.record import TrainingSun

    res = synthesize(tmp_path / "town", size=128, seed=7, gsd=0.5)
    with rasterio.open(res.ortho) as src:
        rgb, profile = src.read(), src.profile
    rgb[:, :8, :8] = 0  # a nodata corner (0 is the orthophoto's nodata)
    profile.update(nodata=0)
    ortho = tmp_path / "ortho.tif"
    with rasterio.open(ortho, "w", **profile) as dst:
        dst.write(rgb)
    with rasterio.open(res.ndsm) as src:
        ndsm = src.read(1)
    sun = Sun(res.sun_azimuth % 360.0, res.sun_elevation)
    with rasterio.open(ortho) as src:
        bounds, crs = tuple(src.bounds), src.crs.to_string()
    training = TrainingSun(clear=True, reason="test", azimuth_deg=sun.azimuth_deg, elevation_deg=sun.elevation_deg,
                           grid_azimuth_deg=sun.azimuth_deg, crs=crs, bounds=bounds,  # type: ignore[arg-type]
                           shadow_model=ShadowModel().fit(rgb, ndsm, 0.5, sun).to_dict())
    mean, std = (100.0, 100.0, 100.0), (50.0, 50.0, 50.0)
    shadows = {}
    for head in (True, False):
        cfg = ModelConfig(in_channels=3, num_classes=1, tasks=("height",), aleatoric=True, shadow_head=head)
        meta = ModelMeta(cfg, ClassScheme("one", (ClassDef(1, "all", (0, 0, 0)),)), (1, 2, 3), mean, std, 0.5,
                         ("red", "green", "blue"), sun=training)
        out = tmp_path / f"pred_{head}"
        predict_raster(ortho, (_HeadModel(head), meta), out, mc=2, window=64, overlap=16,  # type: ignore[arg-type]
                       precision="fp32", engine="torch", progress=False, sun=f"{sun.azimuth_deg},{sun.elevation_deg}")
        with rasterio.open(out / "shadow.tif") as src:
            assert src.dtypes[0] == "float32"
            shadows[head] = np.where(src.read_masks(1) > 0, src.read(1), np.nan)
    valid = np.isfinite(shadows[True])
    assert not valid[:8, :8].any() and valid[8:, 8:].all()
    expected = 1.0 / (1.0 + np.exp(-3.0 * (rgb[1].astype(np.float64) - mean[1]) / std[1]))
    np.testing.assert_allclose(shadows[True][valid], expected[valid], atol=1e-5)
    assert np.nanmax(np.abs(shadows[False] - shadows[True])) > 0.2  # the classifier's layer is another one


# ---- training -----------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_training_with_the_head_fits_the_sun_once_and_stores_the_head(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """`train` with the head fits the training sun once, before the steps (not again after them), trains the head's
    loss into the total (the logged loss exceeds the height loss by it), and both checkpoints hold the head's weights,
    ``model.shadow_head`` and that sun."""
    import csv

    from aerialmtl.formats.checkpoint import load_checkpoint
    from aerialmtl.tiling.tile import TileOptions, tile_dataset
    from aerialmtl.training import setup, trainer
    from aerialmtl.training.config import TrainConfig
    from aerialmtl.training.loop import train

    res = synthesize(tmp_path / "town", size=256, seed=11, gsd=0.5)
    tiles = tmp_path / "tiles"
    tile_dataset(res.ortho, tiles, ndsm=res.ndsm, options=TileOptions(size=64, stride=64), progress=False)
    fits = []
    real = setup.fit_training_sun

    def counted(root: Path) -> object:
        fits.append(root)
        return real(root)

    monkeypatch.setattr(setup, "fit_training_sun", counted)
    monkeypatch.setattr(trainer, "fit_training_sun", counted)
    cfg = TrainConfig.from_dict({
        "model": {**TINY, "block_config": [1, 1, 1, 1], "shadow_head": True},
        "loss": {"shadow_weight": 2.0}, "data": {"batch_size": 4, "num_workers": 0},
        "schedule": {"epochs": 100, "log_every": 1}, "seed": 0, "device": "cpu",
        "calibration": {"enabled": False}, "familiarity": {"enabled": False}})
    result = train(cfg, tiles, tmp_path / "run", max_steps=2, progress=False)
    assert len(fits) == 1
    with open(result.log_path) as f:
        rows = [r for r in csv.DictReader(f) if r["kind"] == "train"]
    assert rows and all(float(r["loss"]) > float(r["loss_height"]) + 0.1 for r in rows)  # + 2 × BCE (≈ 0.69 at 0)
    for path in (result.best_checkpoint, result.last_checkpoint):
        payload, meta = load_checkpoint(path)
        assert meta.model.shadow_head and any(k.startswith("heads.shadow.") for k in payload["state_dict"])
        assert meta.sun is not None and meta.sun.clear
