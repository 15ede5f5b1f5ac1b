"""PatchDataset reads tile folders correctly; augmentations keep every layer aligned."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
import yaml
from helpers.tilefolder import write_tile_folder

from aerialmtl.classes import IGNORE_INDEX
from aerialmtl.data.dataset import PatchDataset, read_tile_info
from aerialmtl.data.transforms import (
    Compose,
    PhotometricJitter,
    RandomCrop,
    RandomFlip,
    RandomRot90,
    build_train_transform,
)
from aerialmtl.errors import InputError


@pytest.fixture
def tiles(tmp_path: Path) -> Path:
    return write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 3, "val": 1, "test": 0})


def test_sample_keys_shapes_dtypes(tiles: Path) -> None:
    ds = PatchDataset(tiles, "train")
    assert len(ds) == 3
    s = ds[0]
    assert set(s) == {"image", "height", "height_valid", "classes", "patch_id"}
    assert s["image"].dtype == torch.float32 and s["image"].shape == (3, 64, 64)
    assert s["height"].dtype == torch.float32 and s["height"].shape == (1, 64, 64)
    assert s["height_valid"].dtype == torch.bool and s["height_valid"].shape == (1, 64, 64)
    assert s["classes"].dtype == torch.int64 and s["classes"].shape == (64, 64)
    assert s["patch_id"] == "p0000"


def test_normalisation_and_masks(tiles: Path) -> None:
    info = read_tile_info(tiles)
    ds = PatchDataset(tiles, "train")
    s = ds[0]
    with rasterio.open(tiles / ds.rows[0]["image_path"]) as src:
        raw = src.read().astype(np.float32)
    with rasterio.open(tiles / ds.rows[0]["height_path"]) as src:
        h = src.read(1)
    mean = np.array(info.mean, np.float32)[:, None, None]
    std = np.array(info.std, np.float32)[:, None, None]
    expected = (raw - mean) / std
    img = s["image"].numpy()
    np.testing.assert_allclose(img[:, 8:, 8:], expected[:, 8:, 8:], rtol=1e-5, atol=1e-5)
    # the 4×4 invalid corner: image 0, height invalid and 0, classes ignored
    assert np.all(img[:, :4, :4] == 0)
    assert not s["height_valid"][0, :4, :4].any() and s["height_valid"][0, 4:, 4:].all()
    assert torch.all(s["height"][0, :4, :4] == 0)
    np.testing.assert_allclose(s["height"][0, 4:, 4:].numpy(), h[4:, 4:])
    assert torch.all(s["classes"][:4, :4] == IGNORE_INDEX)
    assert s["classes"][10, 10] == IGNORE_INDEX
    labelled = s["classes"][s["classes"] != IGNORE_INDEX]
    assert labelled.min() >= 0 and labelled.max() < 3
    # train-split normalisation is close to zero-mean, unit-std over valid pixels
    all_img = torch.cat([ds[i]["image"].reshape(3, -1) for i in range(len(ds))], dim=1)
    assert torch.allclose(all_img.mean(1), torch.zeros(3), atol=0.05)


def test_tasks_subset_and_missing_layers(tmp_path: Path) -> None:
    root = write_tile_folder(tmp_path / "h", counts={"train": 1}, tasks=("height",))
    s = PatchDataset(root, "train")[0]
    assert "height" in s and "classes" not in s
    s2 = PatchDataset(root, "train", tasks=["classes"])[0]  # absent from the folder → simply absent
    assert set(s2) == {"image", "patch_id"}
    full = write_tile_folder(tmp_path / "f", counts={"train": 1})
    assert set(PatchDataset(full, "train", tasks=["classes"])[0]) == {"image", "classes", "patch_id"}


def test_errors_name_file_and_fix(tmp_path: Path, tiles: Path) -> None:
    with pytest.raises(InputError, match="dataset.yaml.*aerialmtl tile"):
        PatchDataset(tmp_path, "train")
    with pytest.raises(InputError, match="split 'test'.*no patches"):
        PatchDataset(tiles, "test")
    with pytest.raises(InputError, match="valid splits"):
        PatchDataset(tiles, "training")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "manifest.csv").write_text("patch_id,split\n")
    (bad / "dataset.yaml").write_text(yaml.safe_dump({"format": "something-else"}))
    with pytest.raises(InputError, match="aerialmtl-tiles"):
        PatchDataset(bad, "train")


def test_works_with_dataloader_workers(tiles: Path) -> None:
    ds = PatchDataset(tiles, "train")
    dl = torch.utils.data.DataLoader(ds, batch_size=3, num_workers=1)
    batch = next(iter(dl))
    assert batch["image"].shape == (3, 3, 64, 64) and batch["classes"].shape == (3, 64, 64)
    assert torch.equal(batch["image"][1], ds[1]["image"])


# ---- transforms ---------------------------------------------------------------------------------
def _coord_sample(h: int = 8, w: int = 8) -> dict:
    """Every layer encodes its pixel's (row, col): image = [row, col], height = row*w+col, classes = same."""
    rows, cols = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    code = rows * w + cols
    return {
        "image": torch.stack([rows, cols]).float(),
        "height": code[None].float(),
        "height_valid": (code % 3 == 0)[None],
        "classes": code.long(),
        "patch_id": "x",
    }


def _assert_aligned(s: dict, w: int = 8) -> None:
    code = (s["image"][0] * w + s["image"][1]).long()
    assert torch.equal(code, s["classes"])
    assert torch.equal(code.float(), s["height"][0])
    assert torch.equal(code % 3 == 0, s["height_valid"][0])


@pytest.mark.parametrize("seed", range(8))
def test_geometric_transforms_keep_layers_aligned(seed: int) -> None:
    t = Compose([RandomFlip(), RandomRot90()])
    g = torch.Generator().manual_seed(seed)
    s = t(_coord_sample(), g)
    _assert_aligned(s)
    assert s["image"].shape == (2, 8, 8) and s["classes"].dtype == torch.int64


def test_transforms_actually_move_pixels_and_are_seeded() -> None:
    t = Compose([RandomFlip(), RandomRot90()])
    outs = [t(_coord_sample(), torch.Generator().manual_seed(s))["classes"] for s in range(16)]
    distinct = {tuple(o.flatten().tolist()) for o in outs}
    assert len(distinct) >= 4  # several of the 8 dihedral variants appear
    a = t(_coord_sample(), torch.Generator().manual_seed(3))
    b = t(_coord_sample(), torch.Generator().manual_seed(3))
    assert torch.equal(a["image"], b["image"])


def test_random_crop_aligned_and_sized() -> None:
    s = RandomCrop(4)(_coord_sample(), torch.Generator().manual_seed(1))
    assert s["image"].shape == (2, 4, 4) and s["classes"].shape == (4, 4)
    _assert_aligned(s)


def test_rot90_keeps_shape_of_non_square_patches() -> None:
    for seed in range(6):
        s = RandomRot90()(_coord_sample(8, 16), torch.Generator().manual_seed(seed))
        assert s["image"].shape == (2, 8, 16)
        _assert_aligned(s, w=16)


def test_jitter_changes_image_only() -> None:
    s = _coord_sample()
    s["image"] = s["image"] + 1.0  # no zero (= invalid) pixels
    out = PhotometricJitter(brightness=0.5, contrast=0.5, p=1.0)(s, torch.Generator().manual_seed(0))
    assert not torch.equal(out["image"], s["image"])
    for k in ("height", "height_valid", "classes"):
        assert torch.equal(out[k], s[k])
    # contrast/brightness are affine per band: correlation with the input stays 1
    for b in range(2):
        x, y = s["image"][b].flatten(), out["image"][b].flatten()
        assert torch.corrcoef(torch.stack([x, y]))[0, 1] > 0.999


def test_train_transform_on_dataset(tiles: Path) -> None:
    ds = PatchDataset(tiles, "train", transform=build_train_transform(jitter=True, crop_size=32))
    s = ds[0]
    assert s["image"].shape == (3, 32, 32) and s["height_valid"].shape == (1, 32, 32)
