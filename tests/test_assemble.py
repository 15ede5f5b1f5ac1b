"""CPU batches: the one-pass assembly equals torch's finishing to the bit, and the CPU loader's thread behaves.

tests/test_batches.py compares whole batches with the per-sample GeoTIFF path; here every flip/rotation, crop
corners, non-square windows, image dtypes and absent layers are checked against torch's
:func:`~aerialmtl.data.batches.finish_on_device` (what a GPU computes), and the loader's thread is checked for what
a training run relies on: the sampler's order, errors raised in the loop, no thread left behind.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.tilefolder import write_tile_folder

from aerialmtl.data.assemble import assemble_batch, empty_batch
from aerialmtl.data.batches import CachedBatches, finish_on_device, item_seed, prepare_batch
from aerialmtl.data.cache import PatchCache, ensure_patch_cache
from aerialmtl.data.prefetch import AssembledBatches
from aerialmtl.data.transforms import Move, build_train_transform
from aerialmtl.formats.tiles import TileFolderInfo, cache_dir

#: every flip and quarter turn of a square: (transpose, flipped axes)
MOVES: list[Move] = [(t, frozenset(f)) for t in (False, True) for f in ((), (-2,), (-1,), (-2, -1))]


def _source(n: int, h: int, w: int, dtype: str, seed: int = 0) -> dict[str, np.ndarray]:
    """Random source patches with invalid image pixels, NaN heights and unlabelled classes."""
    rng = np.random.default_rng(seed)
    top = {"uint8": 255, "uint16": 65535, "float32": 1}[dtype]
    image = (rng.random((n, 3, h, w)) * top).astype(dtype)
    height = (rng.random((n, 1, h, w)) * 30).astype(np.float32)
    height[rng.random(height.shape) < 0.1] = np.nan
    classes = rng.integers(0, 7, (n, h, w)).astype(np.uint8)
    classes[rng.random(classes.shape) < 0.05] = 255
    return {"image": image, "image_valid": (rng.random((n, h, w)) > 0.1).astype(np.uint8), "height": height,
            "classes": classes}


def _torch_reference(source: dict[str, np.ndarray], index: list[int], corners: list[tuple[int, int]],
                     window: tuple[int, int], moves: list[Move], mean: torch.Tensor, std: torch.Tensor,
                     layers: tuple[str, ...]) -> dict[str, torch.Tensor]:
    """Crop, move, normalise with torch ops, sample by sample (the device path's arithmetic)."""
    h, w = window
    crops = {k: torch.from_numpy(np.stack([v[i, ..., r:r + h, c:c + w] for i, (r, c) in zip(index, corners)]))
             for k, v in source.items() if k in ("image", "image_valid") + layers}
    if crops["image"].dtype == torch.uint16:
        crops["image"] = crops["image"].to(torch.int32)  # as the cache's gather widens it

    def move(x: torch.Tensor, m: Move) -> torch.Tensor:
        y = x.transpose(-2, -1) if m[0] else x
        return torch.flip(y, dims=tuple(sorted(m[1]))) if m[1] else y

    moved = {k: torch.stack([move(v[b], m) for b, m in enumerate(moves)]) for k, v in crops.items()}
    from aerialmtl.data.dataset import normalise_batch

    return normalise_batch(moved["image"], moved["image_valid"], mean, std, moved.get("height"), moved.get("classes"))


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "float32"])
@pytest.mark.parametrize("channels_last", [True, False])
def test_every_move_and_crop_equals_torch_to_the_bit(dtype: str, channels_last: bool) -> None:
    source = _source(5, 40, 40, dtype)
    mean, std = torch.tensor([0.3, 0.5, 0.2]) * 200, torch.tensor([0.9, 1.3, 0.7]) * 50
    index = [4, 0, 2, 2, 1, 3, 0, 4]
    corners = [(0, 0), (3, 7), (16, 16), (9, 1), (0, 16), (16, 0), (5, 5), (11, 13)]
    out = empty_batch(8, 3, (24, 24), ["height", "classes"], channels_last=channels_last)
    got = assemble_batch(source, index, [r for r, _ in corners], [c for _, c in corners], MOVES, mean.numpy(),
                         std.numpy(), out)
    ref = _torch_reference(source, index, corners, (24, 24), MOVES, mean, std, ("height", "classes"))
    assert got["image"].is_contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
    for key in ("image", "height", "height_valid", "classes"):
        assert got[key].dtype == ref[key].dtype and torch.equal(got[key], ref[key]), key


def test_non_square_windows_and_absent_layers() -> None:
    source = _source(3, 20, 30, "uint8", seed=1)
    mean, std = torch.tensor([100.0, 90.0, 80.0]), torch.tensor([40.0, 50.0, 60.0])
    moves: list[Move] = [(False, frozenset()), (False, frozenset({-2, -1})), (False, frozenset({-1}))]
    for layers in [(), ("height",), ("classes",)]:
        out = empty_batch(3, 3, (12, 18), list(layers))
        got = assemble_batch({k: v for k, v in source.items() if k in ("image", "image_valid") + layers}, [2, 0, 1],
                             [0, 8, 3], [12, 0, 5], moves, mean.numpy(), std.numpy(), out)
        ref = _torch_reference(source, [2, 0, 1], [(0, 12), (8, 0), (3, 5)], (12, 18), moves, mean, std, layers)
        assert set(got) == set(ref)
        for key in ref:
            assert torch.equal(got[key], ref[key]), (layers, key)
    # a transposed non-square window: its output side is the window's, turned
    out = empty_batch(1, 3, (18, 12), ["height"])
    got = assemble_batch(source, [1], [2], [4], [(True, frozenset({-2}))], mean.numpy(), std.numpy(), out)
    ref = _torch_reference(source, [1], [(2, 4)], (12, 18), [(True, frozenset({-2}))], mean, std, ("height",))
    assert torch.equal(got["image"], ref["image"]) and torch.equal(got["height"], ref["height"])


@pytest.fixture
def tiles(tmp_path: Path) -> Path:
    return write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 6, "val": 3})


def _loader(tiles: Path, specs, **kw) -> tuple[AssembledBatches, CachedBatches, torch.Tensor, torch.Tensor, object]:
    info = TileFolderInfo.read(tiles)
    cache = PatchCache(cache_dir(tiles), ensure_patch_cache(info, "train"))
    transform = build_train_transform(flips=True, rot90=True, jitter=False, crop_size=48)
    mean, std = torch.tensor(info.mean), torch.tensor(info.std)
    return (AssembledBatches(cache, transform, info.tasks, specs, mean, std, **kw),
            CachedBatches(cache, transform, info.tasks), mean, std, transform)


def test_the_loader_thread_gives_the_samplers_batches_in_order(tiles: Path) -> None:
    specs = [[(i % 6, item_seed(1, 0, 4 * s + i)) for i in range(4)] for s in range(7)]
    loader, reference, mean, std, transform = _loader(tiles, specs, ahead=1)
    n = 0
    for spec, item in zip(specs, loader, strict=True):  # each batch is checked before the next is taken
        time.sleep(0.05)  # the thread runs as far ahead as it may: it must not write into the batch in use
        raw = reference[spec]
        want = finish_on_device(raw["data"], raw["params"], transform, mean, std)
        got = prepare_batch(item, transform, mean, std, torch.device("cpu"))
        for key in want:
            assert torch.equal(got[key], want[key]), (n, key)
        n += 1
    assert n == 7
    assert not [t for t in threading.enumerate() if t.name == "aerialmtl-batches"]


def test_an_error_in_the_loader_thread_is_raised_in_the_loop(tiles: Path) -> None:
    specs = [[(0, 1), (1, 2)], [(0, 1), (99, 2)]]  # patch 99 does not exist
    loader = _loader(tiles, specs)[0]
    it = iter(loader)
    next(it)
    with pytest.raises(IndexError):
        next(it)
    assert not [t for t in threading.enumerate() if t.name == "aerialmtl-batches"]


def test_a_loop_that_stops_early_leaves_no_thread(tiles: Path) -> None:
    def endless():
        s = 0
        while True:
            yield [(s % 6, s)]
            s += 1

    loader = _loader(tiles, endless())[0]
    it = iter(loader)
    for _ in range(3):
        next(it)
    it.close()  # what the trainer's `del` of its generator does
    assert not [t for t in threading.enumerate() if t.name == "aerialmtl-batches"]
