"""Height-stratified sampling weights (aerialmtl.data.sampling)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from tilefolder import write_tile_folder

from aerialmtl.data.dataset import read_manifest
from aerialmtl.data.sampling import MAX_SLOPE, repeat_counts, stratified_weights, tall_shares
from aerialmtl.errors import InputError


def test_tall_shares_count_valid_pixels_at_or_above_the_threshold(tmp_path: Path) -> None:
    root = write_tile_folder(tmp_path / "tiles", size=64, counts={"train": 3, "val": 1, "test": 0})
    shares = tall_shares(root, "train", threshold_m=5.0)
    rows = read_manifest(root, "train")
    assert shares.shape == (3,)
    for share, row in zip(shares, rows):
        with rasterio.open(root / row["height_path"]) as src:
            h = src.read(1)
            valid = src.read_masks(1) > 0
        assert share == pytest.approx((h[valid] >= 5.0).sum() / valid.sum())
    assert 0 < shares.max() <= 1  # the toy scene has 8 m buildings
    assert (tall_shares(root, "train", threshold_m=100.0) == 0).all()


def test_weights_reach_the_target_share_and_keep_mean_one() -> None:
    shares = np.array([0.0, 0.0, 0.1, 0.2, 0.6])
    w = stratified_weights(shares, target=0.35)
    assert w.mean() == pytest.approx(1.0)
    assert (w * shares).sum() / w.sum() == pytest.approx(0.35)
    assert np.all(np.diff(w) >= 0)  # taller patches are drawn more often
    assert (w > 0).all()


def test_weights_stay_uniform_when_the_split_is_already_tall_enough_and_cap_otherwise() -> None:
    np.testing.assert_allclose(stratified_weights(np.array([0.5, 0.7, 0.9]), target=0.5), 1.0)
    np.testing.assert_allclose(stratified_weights(np.zeros(4), target=0.5), 1.0)
    w = stratified_weights(np.array([0.0, 0.1]), target=0.9)  # unreachable: the tallest patch has 10 %
    assert w[1] / w[0] == pytest.approx(1 + MAX_SLOPE * 0.1)
    with pytest.raises(InputError, match="target"):
        stratified_weights(np.array([0.1]), target=1.0)


def test_repeat_counts_follow_the_weights() -> None:
    np.testing.assert_array_equal(repeat_counts(np.array([0.5, 1.0, 1.6])), [1, 2, 3])
    with pytest.raises(InputError, match="positive"):
        repeat_counts(np.array([0.0, 1.0]))
