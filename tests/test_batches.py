"""The training data path: the decoded patch cache, batches augmented on the device, the run's batch order."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from helpers.tilefolder import write_tile_folder

from aerialmtl.data.batches import (
    CachedBatches,
    EpochOrder,
    eval_batches,
    finish_on_device,
    item_seed,
    prepare_batch,
)
from aerialmtl.data.cache import PatchCache, ensure_patch_cache
from aerialmtl.data.dataset import PatchDataset
from aerialmtl.data.prefetch import AssembledBatches
from aerialmtl.data.transforms import build_eval_transform, build_train_transform
from aerialmtl.errors import InputError, OutputError
from aerialmtl.formats.tiles import PatchCacheIndex, TileFolderInfo, cache_dir, cache_file, read_manifest


@pytest.fixture
def tiles(tmp_path: Path) -> Path:
    return write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 6, "val": 3})


def _uint16(root: Path) -> Path:
    """Rewrite the image patches of a tile folder as uint16 (values × 200, above 255 and 32767)."""
    for row in read_manifest(root):
        path = root / row["image_path"]
        with rasterio.open(path) as src:
            data, mask, profile = src.read(), src.dataset_mask(), src.profile
        profile.update(dtype="uint16")
        with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(path, "w", **profile) as dst:
            dst.write(data.astype(np.uint16) * 200)
            dst.write_mask(mask)
    return root


def _reference(tiles: Path, split: str, transform, spec) -> dict[str, torch.Tensor]:
    """The per-sample path: GeoTIFFs → PatchDataset → per-sample transforms, collated."""
    ds = PatchDataset(tiles, split)
    samples = [transform(ds.load(i), torch.Generator().manual_seed(s)) for i, s in spec]
    return {k: torch.stack([s[k] for s in samples]) for k in ("image", "height", "height_valid", "classes")}


def _cached(tiles: Path, split: str, transform, spec, path: str = "cpu") -> dict[str, torch.Tensor]:
    """The training path: cache → compact batch → finished by torch ("device": what a GPU does) or in one
    compiled pass ("cpu"), or assembled straight from the cache by the CPU loader ("thread").
    """
    info = TileFolderInfo.read(tiles)
    index = ensure_patch_cache(info, split)
    mean, std = torch.tensor(info.mean), torch.tensor(info.std)
    cache = PatchCache(cache_dir(tiles), index)
    if path == "thread":
        (item,) = list(AssembledBatches(cache, transform, info.tasks, [spec], mean, std))
        return {k: v.clone() for k, v in prepare_batch(item, transform, mean, std, torch.device("cpu")).items()}
    raw = CachedBatches(cache, transform, info.tasks)[spec]
    if path == "device":
        return finish_on_device(raw["data"], raw["params"], transform, mean, std)
    return prepare_batch(raw, transform, mean, std, torch.device("cpu"))


@pytest.mark.parametrize("path", ["device", "cpu", "thread"])
@pytest.mark.parametrize("jitter", [False, True])
@pytest.mark.parametrize("dtype,crop", [("uint8", None), ("uint8", 32), ("uint16", None), ("uint16", 32)])
def test_cached_batches_equal_the_per_sample_geotiff_path(tiles: Path, dtype: str, crop: int | None, jitter: bool,
                                                          path: str) -> None:
    if dtype == "uint16":
        _uint16(tiles)
    transform = build_train_transform(flips=True, rot90=True, jitter=jitter, crop_size=crop)
    spec = [(i, item_seed(0, 3, p)) for p, i in enumerate([5, 0, 2, 2, 1, 3, 4, 0])]  # patch 0 has invalid pixels
    got = _cached(tiles, "train", transform, spec, path)
    ref = _reference(tiles, "train", transform, spec)
    assert got["image"].is_contiguous(memory_format=torch.channels_last)
    side = crop or 64
    assert got["image"].shape == (8, 3, side, side) and got["classes"].dtype == torch.int64
    for key in ("height", "height_valid", "classes"):
        assert torch.equal(got[key], ref[key]), key
    assert torch.equal(got["image"], ref["image"])  # the same arithmetic, sample by sample
    # several samples really were flipped/rotated/jittered differently within the batch
    assert len({tuple(x.flatten()[:50].tolist()) for x in got["classes"]}) > 4


@pytest.mark.parametrize("path", ["device", "cpu", "thread"])
def test_validation_batches_equal_patch_dataset(tiles: Path, path: str) -> None:
    transform = build_eval_transform(32)
    spec = [(i, 0) for i in range(3)]
    got, ref = _cached(tiles, "val", transform, spec, path), _reference(tiles, "val", transform, spec)
    for key in ("image", "height", "height_valid", "classes"):
        assert torch.equal(got[key], ref[key]), key


# ---- the cache ----------------------------------------------------------------------------------
def test_cache_is_compact_and_reused(tiles: Path) -> None:
    info = TileFolderInfo.read(tiles)
    index = ensure_patch_cache(info, "train")
    arrays = PatchCache(cache_dir(tiles), index).arrays()
    assert arrays["image"].dtype == np.uint8 and arrays["image"].shape == (6, 3, 64, 64)
    assert arrays["classes"].dtype == np.uint8 and arrays["height"].dtype == np.float32
    assert np.isnan(arrays["height"][0, 0, :4, :4]).all()  # invalid corner
    stamp = cache_file(cache_dir(tiles), "train", "image").stat().st_mtime_ns
    assert ensure_patch_cache(info, "train") == index  # fresh: not rebuilt
    assert cache_file(cache_dir(tiles), "train", "image").stat().st_mtime_ns == stamp


def test_stale_cache_is_rebuilt_never_used(tiles: Path) -> None:
    info = TileFolderInfo.read(tiles)
    folder = cache_dir(tiles)
    first = ensure_patch_cache(info, "train")
    # a patch rewritten with other values (same size): the cache must follow
    row = read_manifest(tiles, "train")[2]
    with rasterio.open(tiles / row["height_path"], "r+") as dst:
        dst.write(np.full((1, 64, 64), 42.0, np.float32))
    os.utime(tiles / row["height_path"], ns=(1, 1))  # even with an old modification time
    second = ensure_patch_cache(info, "train")
    assert second.fingerprint != first.fingerprint
    assert np.all(PatchCache(folder, second).gather([2])["height"].numpy() == 42.0)
    # fewer rows in the manifest (re-tiled): rebuilt with the new count
    text = (tiles / "manifest.csv").read_text().splitlines()
    (tiles / "manifest.csv").write_text("\n".join(text[:1] + text[2:]) + "\n")
    third = ensure_patch_cache(info, "train")
    assert third.count == 5
    # a truncated array or an index of another version: rebuilt
    cache_file(folder, "train", "classes").write_bytes(b"\x93NUMPY")
    assert ensure_patch_cache(info, "train").count == 5 and PatchCache(folder, third).gather([0])["classes"].shape
    idx = folder / "train.json"
    idx.write_text(idx.read_text().replace('"version": 1', '"version": 999'))
    assert PatchCacheIndex.read(folder, "train") is None
    assert ensure_patch_cache(info, "train").count == 5


def test_unwritable_cache_folder_names_the_setting(tiles: Path, tmp_path: Path) -> None:
    (tmp_path / "afile").write_text("x")
    with pytest.raises(OutputError, match=r"data\.cache_dir.*afile.*writable"):
        ensure_patch_cache(TileFolderInfo.read(tiles), "train", tmp_path / "afile" / "cache")


def test_empty_split_is_refused(tmp_path: Path) -> None:
    root = write_tile_folder(tmp_path / "t", counts={"train": 2, "val": 0})
    with pytest.raises(InputError, match="split 'val'.*no patches"):
        ensure_patch_cache(TileFolderInfo.read(root), "val")


# ---- the batch order ------------------------------------------------------------------------------
def test_ranks_split_each_global_batch_of_the_single_process_order() -> None:
    one = EpochOrder(n=20, batch_size=8, seed=3)
    two = EpochOrder(n=20, batch_size=4, seed=3, world_size=2)
    assert (one.steps_per_epoch, two.steps_per_epoch, two.global_batch) == (2, 2, 8)
    single, r0, r1 = one.batches(0, 0, 0), two.batches(0, 0, 0), two.batches(1, 0, 0)
    for _ in range(5):  # across epoch boundaries
        b, a0, a1 = next(single), next(r0), next(r1)
        assert a0 + a1 == b and not {i for i, _ in a0} & {i for i, _ in a1}
    # resuming at a position continues with the same batches
    whole = one.batches(0, 2, 0)
    next(whole)
    assert next(EpochOrder(20, 8, 3).batches(0, 2, 8)) == next(whole)


def test_resume_with_another_global_batch_continues_at_the_same_position() -> None:
    two = EpochOrder(n=16, batch_size=4, seed=0, world_size=2)  # global batch 8
    one = EpochOrder(n=16, batch_size=4, seed=0)  # global batch 4
    epoch, pos = 0, 0
    epoch, pos = two.advance(epoch, pos)
    assert (epoch, pos) == (0, 8)
    a = next(one.batches(0, epoch, pos))
    b = next(two.batches(0, 0, 0)) + next(two.batches(1, 0, 0))
    perm = one.permutation(0).tolist()
    assert [i for i, _ in a] == perm[8:12] and [i for i, _ in b] == perm[:8]
    assert one.advance(0, 12) == (1, 0)


def test_small_splits() -> None:
    assert EpochOrder(n=3, batch_size=8, seed=0).global_batch == 3  # one process: the whole split
    assert EpochOrder(n=5, batch_size=8, seed=0, world_size=2).rank_batch == 2
    with pytest.raises(InputError, match="3 patches, fewer than the 4 processes"):
        EpochOrder(n=3, batch_size=8, seed=0, world_size=4)


def test_validation_batches_are_dealt_to_ranks() -> None:
    full = eval_batches(10, 4)
    assert [len(b) for b in full] == [4, 4, 2]
    parts = eval_batches(10, 4, 0, 2) + eval_batches(10, 4, 1, 2)
    assert sorted(map(tuple, parts)) == sorted(map(tuple, full))


def test_read_only_tile_folder_trains_with_the_cache_elsewhere(tiles: Path, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    from aerialmtl.training.config import TrainConfig
    from aerialmtl.training.loop import train

    (tiles / "cache").write_text("a file where the cache folder would go: the folder cannot be written")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    cfg = TrainConfig.from_dict({"model": {"growth_rate": 8, "block_config": [2, 2, 2, 2], "num_init_features": 16,
                                           "bn_size": 2}, "data": {"batch_size": 2, "num_workers": 0},
                                 "device": "cpu"})
    with pytest.warns(UserWarning, match=r"data\.cache_dir: the tile folder .* is not writable; caching .*xdg"):
        res = train(cfg, tiles, tmp_path / "run", max_steps=1, progress=False)
    assert res.step == 1 and list((tmp_path / "xdg" / "aerialmtl").glob("*/train.json"))


@pytest.mark.parametrize("shape", [(5, 5), (4, 6)])
def test_flips_then_rotations_move_each_sample_once_to_the_same_pixels(shape: tuple[int, int]) -> None:
    """Every flip/quarter-turn combination, applied as one move per sample, gives exactly the pixels of the
    flip and the rotation applied one after the other (the speed-up must not change a batch)."""
    from aerialmtl.data.transforms import RandomFlip, RandomRot90, stack_params

    h, w = shape
    combos = [(a, b, k) for a in (False, True) for b in (False, True) for k in ((0, 1, 2, 3) if h == w else (0, 2))]
    n = len(combos)
    batch = {"image": torch.arange(n * 3 * h * w, dtype=torch.int32).reshape(n, 3, h, w).to(torch.uint8),
             "height": torch.randn(n, 1, h, w), "classes": torch.randint(0, 6, (n, h, w), dtype=torch.uint8)}
    params = stack_params([{"0.h": torch.tensor(a), "0.v": torch.tensor(b), "1.k": torch.tensor(k)}
                           for a, b, k in combos])
    pipeline = build_train_transform(flips=True, rot90=True, jitter=False)
    assert [type(t) for t in pipeline.transforms] == [RandomFlip, RandomRot90]
    fused = pipeline.apply(batch, params, stages=("permute",))
    flipped = pipeline.transforms[0].apply(batch, {"h": params["0.h"], "v": params["0.v"]})
    one_by_one = pipeline.transforms[1].apply(flipped, {"k": params["1.k"]})
    for key in batch:
        assert fused[key].shape == one_by_one[key].shape and torch.equal(fused[key], one_by_one[key]), key
