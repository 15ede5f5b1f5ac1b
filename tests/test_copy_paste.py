"""Copy-paste of real tall objects (``data.copy_paste``): the bank, the pasting, and a run with it off or on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.tilefolder import write_tile_folder

from aerialmtl.data.batches import CachedBatches
from aerialmtl.data.copy_paste import SEED_SALT, CopyPaste, CopyPaster, Placement, build_object_bank, find_objects
from aerialmtl.data.prefetch import AssembledBatches
from aerialmtl.errors import ConfigError
from aerialmtl.training.config import TrainConfig
from aerialmtl.training.loop import train
from aerialmtl.training.setup import prepare_training

TINY_MODEL = {"growth_rate": 8, "block_config": [2, 2, 2, 2], "num_init_features": 16, "bn_size": 2}


def _arrays(n: int = 4, size: int = 48, seed: int = 0) -> dict[str, np.ndarray]:
    """A split of ``n`` patches; patch 0 holds one 12 m building (8×6 px) well inside, the others are flat."""
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 200, (n, 3, size, size), dtype=np.uint8)
    height = rng.uniform(0.0, 0.5, (n, 1, size, size)).astype(np.float32)
    classes = np.zeros((n, size, size), np.uint8)
    height[0, 0, 20:28, 20:26] = np.linspace(10, 12, 48, dtype=np.float32).reshape(8, 6)
    classes[0, 20:28, 20:26] = 1
    image[0, :, 20:28, 20:26] = 250
    return {"image": image, "image_valid": np.ones((n, size, size), np.uint8), "height": height, "classes": classes}


def _batch(arrays: dict[str, np.ndarray], indices: list[int]) -> dict[str, torch.Tensor]:
    return {k: torch.from_numpy(np.ascontiguousarray(v[indices])) for k, v in arrays.items()}


def test_bank_finds_whole_objects_with_their_margin() -> None:
    arrays = _arrays()
    spec = CopyPaste(prob=1.0, min_height_m=2.5, margin_m=1.0, margin_ratio=0.25)
    bank = build_object_bank(arrays, spec, gsd=1.0, seed=0)
    assert len(bank) == 1
    obj = bank.objects[0]
    margin = int(np.ceil(1.0 + 0.25 * 12.0))  # 4 px
    assert obj.source == 0 and obj.shape == (8 + 2 * margin, 6 + 2 * margin)
    assert obj.mask.all()  # a rectangle dilated by a square is its whole margin box
    assert obj.height_max == pytest.approx(12.0)
    assert obj.height[margin:-margin, margin:-margin].min() >= 10.0 and obj.classes is not None
    # an object whose margin leaves the patch is not banked (its shadow would be cut)
    arrays["height"][1, 0, 0:5, 30:36] = 8.0
    assert len(build_object_bank(arrays, spec, gsd=1.0, seed=0)) == 1
    # the same object in two overlapping patches (same place on the tile grid) is banked once
    arrays = _arrays()
    arrays["height"][1, 0, 10:18, 10:16] = arrays["height"][0, 0, 20:28, 20:26]
    twice = build_object_bank(arrays, spec, gsd=1.0, seed=0)
    once = build_object_bank(arrays, spec, gsd=1.0, seed=0, offsets=[(0, 0), (10, 10), (0, 100), (0, 200)])
    assert (len(twice), len(once)) == (2, 1)


def test_pasted_pixels_carry_their_height_and_labels_together() -> None:
    arrays = _arrays()
    spec = CopyPaste(prob=1.0, max_objects=3, margin_m=1.0, margin_ratio=0.0)
    paster = CopyPaster(build_object_bank(arrays, spec, gsd=1.0, seed=0), spec)
    obj = paster.bank.objects[0]
    spec_b = [(1, 11), (2, 12), (3, 13), (0, 14)]
    before = _batch(arrays, [i for i, _ in spec_b])
    after = paster.paste({k: v.clone() for k, v in before.items()}, spec_b)
    assert {k: (v.shape, v.dtype) for k, v in after.items()} == {k: (v.shape, v.dtype) for k, v in before.items()}
    pasted_any = False
    for b, (target, seed) in enumerate(spec_b):
        placements = paster.draw(torch.Generator().manual_seed((seed + SEED_SALT) % 2**63), target, (48, 48))
        if target == 0:  # never pasted into the patch it was cut from
            assert placements == []
        expected = {k: v[b].clone() for k, v in before.items()}
        for p in placements:
            h, w = np.rot90(obj.mask, p.k).shape
            assert 0 <= p.row and p.row + h <= 48 and 0 <= p.col and p.col + w <= 48  # inside the patch
            def turn(a: np.ndarray, p: Placement = p) -> np.ndarray:
                out = np.rot90(a, p.k, axes=(-2, -1))
                return np.ascontiguousarray(out[..., ::-1] if p.flip else out)

            m = torch.from_numpy(turn(obj.mask))
            rows, cols = slice(p.row, p.row + h), slice(p.col, p.col + w)
            expected["image"][:, rows, cols][:, m] = torch.from_numpy(turn(obj.image))[:, m]
            expected["height"][0, rows, cols][m] = torch.from_numpy(turn(obj.height))[m]
            expected["classes"][rows, cols][m] = torch.from_numpy(turn(obj.classes))[m]
            pasted_any = True
        for k in ("image", "height", "classes", "image_valid"):
            assert torch.equal(after[k][b], expected[k]), (b, k)
        # every pixel of a building label carries a building height and a building colour, wherever it went
        building = after["classes"][b] == 1
        assert (after["height"][b, 0][building] >= 10.0).all()
        assert (after["image"][b][:, building] == 250).all()
        assert int(building.sum()) == 48 * len(placements) or target == 0
    assert pasted_any


def test_pasting_is_deterministic_per_seed_and_off_at_prob_zero() -> None:
    arrays = _arrays()
    on = CopyPaste(prob=1.0, max_objects=3, margin_m=1.0, margin_ratio=0.0)
    bank = build_object_bank(arrays, on, gsd=1.0, seed=0)
    batch = _batch(arrays, [1, 2, 3])

    def run(seeds: list[int], spec: CopyPaste) -> dict[str, torch.Tensor]:
        return CopyPaster(bank, spec).paste({k: v.clone() for k, v in batch.items()}, list(zip([1, 2, 3], seeds)))

    a, b, c = run([5, 6, 7], on), run([5, 6, 7], on), run([8, 9, 10], on)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)
    off = run([5, 6, 7], CopyPaste(prob=0.0))
    assert all(torch.equal(off[k], batch[k]) for k in batch)


def test_config_section_defaults_off_and_validates() -> None:
    assert not TrainConfig().data.copy_paste.enabled
    cfg = TrainConfig.from_dict({"data": {"copy_paste": {"prob": 0.5, "max_objects": 2}}})
    assert cfg.data.copy_paste == CopyPaste(prob=0.5, max_objects=2)
    with pytest.raises(ConfigError, match=r"data\.copy_paste\.prob"):
        TrainConfig.from_dict({"data": {"copy_paste": {"prob": 1.5}}})
    with pytest.raises(ConfigError, match=r"data\.copy_paste"):
        TrainConfig.from_dict({"data": {"copy_paste": {"colour": 1}}})
    assert find_objects(np.zeros((16, 16), np.float32), CopyPaste(prob=1.0), 1.0) == []


@pytest.fixture(scope="module")
def tiles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tile_folder(tmp_path_factory.mktemp("cp") / "tiles", size=64, counts={"train": 8, "val": 2})


def _cfg(**data: object) -> TrainConfig:
    return TrainConfig.from_dict({"model": TINY_MODEL, "data": {"batch_size": 4, "num_workers": 0, **data},
                                  "schedule": {"epochs": 100, "log_every": 1}, "seed": 0, "device": "cpu"})


def _first_batches(cfg: TrainConfig, tiles: Path, out: Path, n: int = 3) -> list[dict[str, torch.Tensor]]:
    """The run's first ``n`` training batches, finished (kept: copied out of the loader's reused buffers)."""
    setup = prepare_training(cfg, tiles, out, progress=False)
    it = iter(setup.loaders.train_loader)
    return [{k: v.clone() for k, v in next(it)["ready"].items()} for _ in range(n)]


def _first_params(cfg: TrainConfig, tiles: Path, out: Path, n: int = 3) -> list[dict[str, torch.Tensor]]:
    """The augmentation parameters of the run's first ``n`` batches, as its loader draws them around the pasting."""
    setup = prepare_training(cfg, tiles, out, progress=False)
    loader = setup.loaders.train_loader
    assert isinstance(loader, AssembledBatches)  # a CPU run
    batches = CachedBatches(loader.cache, loader.transform, ("height", "classes"), loader.paster)
    specs = iter(loader.specs)
    return [batches[next(specs)]["params"] for _ in range(n)]


def test_off_by_default_gives_bit_equal_training_batches(tiles: Path, tmp_path: Path) -> None:
    plain = _first_batches(_cfg(), tiles, tmp_path / "a")
    zero = _first_batches(_cfg(copy_paste={"prob": 0.0, "max_objects": 5}), tiles, tmp_path / "b")
    on_cfg = _cfg(copy_paste={"prob": 1.0, "min_height_m": 3.0, "margin_m": 0.5, "margin_ratio": 0.0})
    on = _first_batches(on_cfg, tiles, tmp_path / "c")

    def same(x: list[dict[str, torch.Tensor]], y: list[dict[str, torch.Tensor]]) -> bool:
        return all(torch.equal(a[k], b[k]) for a, b in zip(x, y) for k in a)

    assert same(plain, zero)
    assert not same(plain, on)
    # pasting draws from its own generator: the flips and rotations of every sample stay those of a plain run
    p_plain, p_on = _first_params(_cfg(), tiles, tmp_path / "d"), _first_params(on_cfg, tiles, tmp_path / "e")
    assert len(p_plain) == len(p_on) == 3
    assert all(torch.equal(a[k], b[k]) for a, b in zip(p_plain, p_on) for k in a)


def test_training_with_copy_paste_runs_and_needs_heights(tiles: Path, tmp_path: Path) -> None:
    cfg = _cfg(copy_paste={"prob": 1.0, "min_height_m": 3.0, "margin_m": 0.5, "margin_ratio": 0.0})
    res = train(cfg, tiles, tmp_path / "run", max_steps=2, progress=False)
    assert res.step == 2
    classes_only = write_tile_folder(tmp_path / "cls", size=64, counts={"train": 4}, tasks=("classes",))
    with pytest.raises(ConfigError, match="data.copy_paste"):
        train(cfg, classes_only, tmp_path / "run2", max_steps=1, progress=False)
