"""Window plan and seamless stitching: an identity model stitched over any grid returns its input."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from conftest import write_raster
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from torch import nn

from aerialmtl.classes import ClassDef, ClassScheme
from aerialmtl.errors import InputError
from aerialmtl.formats.checkpoint import ModelMeta
from aerialmtl.inference.predict import predict_raster
from aerialmtl.inference.windows import axis_plan, plan_bands
from aerialmtl.models.config import ModelConfig


class IdentityModel(nn.Module):
    """Receptive-field-free model: height = band 1 de-normalised; class logits = band values (argmax band)."""

    def __init__(self, mean: tuple[float, ...], std: tuple[float, ...], dropout: float = 0.0) -> None:
        super().__init__()
        c = len(mean)
        self.height = nn.Conv2d(c, 1, 1)
        self.classes = nn.Conv2d(c, c, 1)
        self.drop = nn.Dropout2d(dropout)
        with torch.no_grad():
            self.height.weight.zero_()
            self.height.weight[0, 0] = std[0]
            self.height.bias.fill_(mean[0])
            self.classes.weight.copy_(torch.diag(torch.tensor(std, dtype=torch.float32))[:, :, None, None])
            self.classes.bias.copy_(torch.tensor(mean, dtype=torch.float32))

    def encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        return [x]

    def decode(self, feats: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        x = feats[0]
        return {"height": self.height(x), "classes": self.classes(self.drop(x))}

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.decode(self.encode(x))


def identity_meta(bands: int = 3, mean: float = 0.0, std: float = 1.0, gsd: float = 0.5) -> ModelMeta:
    scheme = ClassScheme("bands", tuple(ClassDef(i + 1, f"band {i + 1}", (40 * i, 80, 200 - 40 * i))
                                        for i in range(bands)))
    return ModelMeta(ModelConfig(in_channels=bands, num_classes=bands), scheme, tuple(range(1, bands + 1)),
                     (mean,) * bands, (std,) * bands, gsd)


# ---- plan --------------------------------------------------------------------------------------
@pytest.mark.parametrize("length", [1, 31, 100, 512, 513, 1106, 2048, 5000])
def test_axis_plan_covers_with_overlap_and_weights_sum_to_one(length: int) -> None:
    p = axis_plan(length, 512, 64)
    assert p.size % 32 == 0 and p.size <= 512
    assert p.starts[0] == 0 and p.extent >= length
    assert all(a + p.size - b >= 64 for a, b in zip(p.starts, p.starts[1:]))  # neighbours overlap ≥ 64
    total = np.zeros(p.extent)
    for s, w in zip(p.starts, p.weights):
        total[s:s + p.size] += w
    np.testing.assert_allclose(total[:length], 1.0, atol=1e-6)
    n = len(p.starts)
    assert n == max(1, int(np.ceil((length - 64) / (512 - 64))))  # the documented count formula


def test_bands_partition_rows_and_only_touch_their_sources() -> None:
    plan = plan_bands(1500, 700, 256, 64)
    rows = plan.rows
    assert plan.bands[0].out_start == 0 and plan.bands[-1].out_stop == 1500
    for a, b in zip(plan.bands, plan.bands[1:]):
        assert a.out_stop == b.out_start
    for band in plan.bands:
        # rows that become final at this band get no weight from later window rows
        for later in range(band.index + 1, len(rows.starts)):
            s = rows.starts[later]
            lo, hi = max(band.out_start, s), min(band.out_stop, s + rows.size)
            if hi > lo:
                assert not rows.weights[later][lo - s:hi - s].any()
        # ... nor from window rows older than its sources
        for older in range(0, min(band.sources)):
            s = rows.starts[older]
            assert s + rows.size <= band.out_start or not rows.weights[older][band.out_start - s:].any()


def test_overlap_factor_close_to_theory_on_large_rasters() -> None:
    plan = plan_bands(8192, 8192, 512, 64)
    assert plan.overlap_factor == pytest.approx(
        len(plan.rows.starts) ** 2 * plan.rows.size ** 2 / 8192 ** 2)
    assert plan.overlap_factor < 1.45


@pytest.mark.parametrize("tile,overlap", [(100, 10), (0, 0), (512, 300), (512, -1)])
def test_bad_tiling_is_refused(tile: int, overlap: int) -> None:
    with pytest.raises(InputError, match="tile|overlap"):
        plan_bands(100, 100, tile, overlap)


# ---- property: identity model ------------------------------------------------------------------
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    height=st.integers(1, 150),
    width=st.integers(1, 150),
    tile=st.sampled_from([32, 64, 96, 128]),
    overlap_frac=st.floats(0.0, 0.5),
    seed=st.integers(0, 2**16),
)
def test_identity_model_is_reproduced_exactly(height: int, width: int, tile: int, overlap_frac: float,
                                              seed: int) -> None:
    overlap = int(tile * overlap_frac)
    rng = np.random.default_rng(seed)
    img = rng.integers(1, 256, size=(3, height, width)).astype(np.uint8)
    meta = identity_meta()
    model = IdentityModel(meta.mean, meta.std)
    with tempfile.TemporaryDirectory() as tmp:
        src = write_raster(Path(tmp) / "ortho.tif", img)
        res = predict_raster(src, (model, meta), Path(tmp) / "pred", mc=1, tile=tile, overlap=overlap,
                             batch_size=3, precision="fp32", progress=False)
        with rasterio.open(res.files["height"]) as h, rasterio.open(res.files["classes"]) as c:
            height_out, classes_out = h.read(1), c.read(1)
    np.testing.assert_array_equal(height_out, img[0].astype(np.float32))
    np.testing.assert_array_equal(classes_out, np.argmax(img, axis=0).astype(np.uint8))


def test_flush_in_column_chunks_equals_one_pass() -> None:
    from aerialmtl.inference.stitch import BandStitcher

    plan = plan_bands(150, 230, 64, 16)
    outputs = ("height", "height_std", "classes", "class_entropy", "class_mutual_info", "class_probabilities")
    channels = {"height": 1, "height_std": 1, "probs": 4, "expected_entropy": 1}
    rng = np.random.default_rng(3)
    stitchers = [BandStitcher(plan, channels, outputs) for _ in range(2)]
    for band in plan.bands:
        for st_ in stitchers:
            st_.start_band(band.index)
        for j, win in enumerate(band.windows):
            h, w = int(win.height), int(win.width)
            p = rng.dirichlet(np.ones(4), size=(h, w)).transpose(2, 0, 1).astype(np.float32)
            vals = {"height": rng.normal(5, 2, (1, h, w)).astype(np.float32),
                    "height_std": rng.random((1, h, w)).astype(np.float32), "probs": p,
                    "expected_entropy": rng.random((1, h, w)).astype(np.float32) * 0.1}
            valid = rng.random((h, w)) > 0.1
            for st_ in stitchers:
                st_.add(j, vals, valid)
        one, chunked = stitchers[0].flush(), stitchers[1].flush(chunk_cols=7)
        assert (one.row_start, one.row_stop) == (chunked.row_start, chunked.row_stop)
        np.testing.assert_array_equal(one.valid, chunked.valid)
        assert one.layers.keys() == chunked.layers.keys() == set(outputs)
        for name in outputs:
            np.testing.assert_array_equal(one.layers[name], chunked.layers[name])
