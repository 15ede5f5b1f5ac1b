"""Window plan and seamless stitching: an identity model stitched over any grid returns its input."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
import rasterio
import torch
from helpers.models import IdentityModel, identity_meta
from helpers.rasters import write_raster
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from aerialmtl.classes import ClassDef, ClassScheme
from aerialmtl.errors import InputError
from aerialmtl.formats.prediction import prediction_layers
from aerialmtl.inference.predict import predict_raster
from aerialmtl.inference.windows import axis_plan, plan_windows
from aerialmtl.models.mc_dropout import McStatistics


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
    plan = plan_windows(1500, 700, 256, 64)
    rows = plan.rows
    assert plan.window_rows[0].out_start == 0 and plan.window_rows[-1].out_stop == 1500
    for a, b in zip(plan.window_rows, plan.window_rows[1:]):
        assert a.out_stop == b.out_start
    for band in plan.window_rows:
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
    plan = plan_windows(8192, 8192, 512, 64)
    assert plan.overlap_factor == pytest.approx(
        len(plan.rows.starts) ** 2 * plan.rows.size ** 2 / 8192 ** 2)
    assert plan.overlap_factor < 1.45


@pytest.mark.parametrize("window,overlap", [(100, 10), (0, 0), (512, 300), (512, -1)])
def test_bad_tiling_is_refused(window: int, overlap: int) -> None:
    with pytest.raises(InputError, match="window|overlap"):
        plan_windows(100, 100, window, overlap)


# ---- property: identity model ------------------------------------------------------------------
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    height=st.integers(1, 150),
    width=st.integers(1, 150),
    window=st.sampled_from([32, 64, 96, 128]),
    overlap_frac=st.floats(0.0, 0.5),
    seed=st.integers(0, 2**16),
)
def test_identity_model_is_reproduced_exactly(height: int, width: int, window: int, overlap_frac: float,
                                              seed: int) -> None:
    overlap = int(window * overlap_frac)
    rng = np.random.default_rng(seed)
    img = rng.integers(1, 256, size=(3, height, width)).astype(np.uint8)
    meta = identity_meta()
    model = IdentityModel(meta.mean, meta.std)
    with tempfile.TemporaryDirectory() as tmp:
        src = write_raster(Path(tmp) / "ortho.tif", img)
        res = predict_raster(src, (model, meta), Path(tmp) / "pred", mc=1, window=window, overlap=overlap,
                             batch_size=3, precision="fp32", progress=False)
        with rasterio.open(res.files["height"]) as h, rasterio.open(res.files["classes"]) as c:
            height_out, classes_out = h.read(1), c.read(1)
    np.testing.assert_array_equal(height_out, img[0].astype(np.float32))
    np.testing.assert_array_equal(classes_out, np.argmax(img, axis=0).astype(np.uint8))


def _random_windows(plan, k: int, seed: int, skip: float = 0.15) -> dict[tuple[int, int], tuple]:
    """Random per-window statistics (h, w[, K]) and validity; some windows skipped (None)."""
    rng = np.random.default_rng(seed)
    out: dict[tuple[int, int], tuple] = {}
    h, w = plan.rows.size, plan.cols.size
    for i in range(len(plan.rows.starts)):
        for j in range(len(plan.cols.starts)):
            if rng.random() < skip:
                out[i, j] = (None, None)
                continue
            p = rng.dirichlet(np.ones(k), size=(h, w)).astype(np.float32)
            stats = McStatistics(rng.normal(5, 2, (h, w)).astype(np.float32), rng.random((h, w)).astype(np.float32),
                                 p, (rng.random((h, w)) * 0.5).astype(np.float32))
            out[i, j] = (stats, rng.random((h, w)) > 0.1)
    return out


def _numpy_blend(plan, windows: dict, k: int) -> dict[str, np.ndarray]:
    """Whole-raster float32 accumulation in plan order (acc += value * weight), finalised like the old stitcher."""
    ext = (plan.rows.extent, plan.cols.extent)
    acc = {"w": np.zeros(ext, np.float32), "h": np.zeros(ext, np.float32), "s": np.zeros(ext, np.float32),
           "p": np.zeros(ext + (k,), np.float32), "e": np.zeros(ext, np.float32)}
    for (i, j), (stats, valid) in windows.items():
        if stats is None:
            continue
        r, c = plan.rows.starts[i], plan.cols.starts[j]
        sl = (slice(r, r + plan.rows.size), slice(c, c + plan.cols.size))
        w = plan.weight(i, j) * valid
        acc["w"][sl] += w
        acc["h"][sl] += stats.height_mean * w
        acc["s"][sl] += stats.height_std * w
        acc["p"][sl] += stats.probs * w[..., None]
        acc["e"][sl] += stats.mean_entropy * w
    hh, ww = plan.rows.length, plan.cols.length
    wsum = acc["w"][:hh, :ww]
    valid = wsum > 0
    safe = np.where(valid, wsum, np.float32(1.0))
    probs = acc["p"][:hh, :ww] / safe[..., None]
    ent = np.maximum(-(probs * np.log(np.clip(probs, 1e-12, 1.0))).sum(-1), 0.0)
    cls = probs.argmax(-1).astype(np.uint8)
    cls[~valid] = 255
    out = {"height": acc["h"][:hh, :ww] / safe, "height_std": np.maximum(acc["s"][:hh, :ww] / safe, 0.0),
           "class_entropy": ent, "class_mutual_info": np.clip(ent - acc["e"][:hh, :ww] / safe, 0.0, ent)}
    layers = {n: np.where(valid, v, np.float32(-9999.0)).astype(np.float32)[None] for n, v in out.items()}
    layers["class_probabilities"] = np.where(valid, np.moveaxis(probs, -1, 0), np.float32(-9999.0))
    layers["classes"] = cls[None]
    return layers


def _stitch(plan, windows: dict, k: int, start: int = 0, stop: int | None = None,
            chunk: int | None = None, carry_in_memory: int | None = None, mc: int = 3) -> dict[str, np.ndarray]:
    """Run the Stitcher and paint its blocks into full-size arrays (NaN where no block landed).

    ``mc`` 3: every layer (class probabilities too); 1: height and classes only (as a T = 1 predict writes).
    """
    import aerialmtl.inference.stitch as stitch_mod

    specs = prediction_layers(("height", "classes"), _scheme(k), mc=mc, probabilities=mc > 1)
    old = stitch_mod.CHUNK_ELEMENTS, stitch_mod.CARRY_IN_MEMORY
    if chunk is not None:
        stitch_mod.CHUNK_ELEMENTS = chunk
    if carry_in_memory is not None:
        stitch_mod.CARRY_IN_MEMORY = carry_in_memory
    try:
        st = stitch_mod.Stitcher(plan, specs, k, "cpu", start, stop)
    finally:
        stitch_mod.CHUNK_ELEMENTS, stitch_mod.CARRY_IN_MEMORY = old
    hh, ww = plan.rows.length, plan.cols.length
    out = {s.name: np.full((s.count, hh, ww), np.nan if s.dtype == "float32" else 254, s.dtype) for s in specs}
    hits = np.zeros((hh, ww), int)
    for i in range(st.first_row, st.stop):
        for j in range(len(plan.cols.starts)):
            stats, valid = windows[i, j]
            t = None if stats is None else McStatistics(*(torch.from_numpy(a) for a in (
                stats.height_mean, stats.height_std, stats.probs, stats.mean_entropy)))
            for b in st.add(i, j, t, None if valid is None else torch.from_numpy(valid)):
                sl = (slice(b.row_off, b.row_off + b.height), slice(b.col_off, b.col_off + b.width))
                hits[sl] += 1
                for name, arr in b.layers.items():
                    out[name][(slice(None), *sl)] = arr
    assert st.finished
    rows = slice(plan.window_rows[start].out_start, plan.window_rows[(stop or len(plan.window_rows)) - 1].out_stop)
    assert (hits[rows] == 1).all() and (hits.sum() == hits[rows].sum())  # every pixel of the strip exactly once
    return out


def _scheme(k: int) -> ClassScheme:
    return ClassScheme("k", tuple(ClassDef(i + 1, f"c{i}", (10 * i, 20, 30)) for i in range(k)))


@pytest.mark.parametrize("shape,tile,overlap", [((150, 230), 64, 16), ((100, 100), 64, 32), ((33, 200), 32, 8),
                                                ((20, 45), 64, 0), ((97, 131), 96, 40)])
def test_stitcher_equals_a_whole_raster_blend(shape: tuple[int, int], tile: int, overlap: int) -> None:
    plan = plan_windows(*shape, tile, overlap)
    windows = _random_windows(plan, 4, seed=sum(shape))
    ref = _numpy_blend(plan, windows, 4)
    got = _stitch(plan, windows, 4)
    for name in ("height", "height_std", "classes", "class_probabilities"):
        np.testing.assert_array_equal(got[name], ref[name], err_msg=name)
    for name in ("class_entropy", "class_mutual_info"):  # numpy's and torch's log differ in the last bit
        np.testing.assert_allclose(got[name], ref[name], rtol=0, atol=2e-6, err_msg=name)


def test_a_t1_run_writes_the_blends_classes_and_heights() -> None:
    # T = 1 without probabilities: the CPU's class map comes from the compiled kernel alone (no quotients made)
    plan = plan_windows(150, 230, 64, 16)
    windows = _random_windows(plan, 6, seed=3)
    ref = _numpy_blend(plan, windows, 6)
    got = _stitch(plan, windows, 6, mc=1, chunk=1000)
    assert set(got) == {"height", "classes"}
    for name in got:
        np.testing.assert_array_equal(got[name], ref[name], err_msg=name)


def _torch_classes(sums: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """The class map as torch finishes it on a GPU (stitch.Stitcher._layer_values): argmax of the quotients."""
    invalid = weight <= 0
    safe = torch.where(invalid, torch.ones_like(weight), weight)
    return torch.where(invalid, torch.tensor(255, dtype=torch.uint8),
                       (sums / safe.unsqueeze(-1)).argmax(-1).to(torch.uint8))


@pytest.mark.parametrize("k", [7, 20])
def test_the_cpu_class_kernel_is_torchs_argmax_of_the_quotients(k: int) -> None:
    """Ties, ties made by the division's rounding, NaN and ∞ sums, zero, negative, NaN and ∞ weights, zeros and
    subnormals: the compiled kernel gives torch's class (the first of equal maxima, the first NaN) everywhere.
    """
    from aerialmtl.inference.stitch_kernel import finished_classes

    rng = np.random.default_rng(k)
    n = 4000
    sums = rng.random((n, k)).astype(np.float32)
    weight = (rng.random(n) * 1.5).astype(np.float32)
    # sums one float apart whose quotients round to the same float: torch takes the first, not the larger
    x = rng.random(1000).astype(np.float32) + np.float32(0.5)
    sums[:1000] *= np.float32(0.4)
    sums[:1000, 2] = x
    sums[:1000, 5] = np.nextafter(x, np.float32(2))
    weight[:1000] = np.float32(3.0)
    made = (sums[:1000, 2] / weight[:1000] == sums[:1000, 5] / weight[:1000]) & (sums[:1000, 2] < sums[:1000, 5])
    assert made.sum() > 50  # the case is really there
    sums[1000:1100] = 0.25  # exact ties
    sums[1100:1110, 3] = np.nan
    sums[1110:1120, [1, 4]] = np.nan
    sums[1120:1130, 2] = np.inf
    sums[1130:1140, [0, 6]] = np.inf
    sums[1220:1230, k - 1] = np.nan  # in the last, partial group of four
    sums[1230:1240, k - 1] = np.float32(2.0)  # the largest last
    sums[1140:1150, 1] = -np.inf
    sums[1150:1160] = 0.0
    sums[1160:1170] = np.float32(1e-44) * np.arange(k, dtype=np.float32)[::-1]  # subnormal sums
    weight[1160:1165] = np.float32(1e-3)
    weight[1170:1180] = 0.0
    weight[1180:1190] = -1.0
    weight[1190:1200] = np.nan
    weight[1200:1210] = np.inf
    weight[1210:1220] = np.float32(1e-40)  # quotients overflow to ∞: every large sum ties
    sums[1210:1220] = np.float32(3e38) - np.arange(k, dtype=np.float32) * np.float32(1e31)
    sums_t, weight_t = torch.from_numpy(sums), torch.from_numpy(weight)
    want = _torch_classes(sums_t, weight_t)
    got = torch.full((n,), 77, dtype=torch.uint8)  # a pixel left unwritten shows
    finished_classes(sums_t.unsqueeze(1), weight_t.unsqueeze(1), 255, got.unsqueeze(1))
    np.testing.assert_array_equal(got.numpy(), want.numpy())
    assert (got[:1000][torch.from_numpy(made)] == 2).all()
    # strided views of wider accumulators (the usual block), into a band of a wider block
    wide_sums = torch.from_numpy(rng.random((40, 60, k)).astype(np.float32))
    wide_weight = torch.from_numpy(rng.random((40, 60)).astype(np.float32) - np.float32(0.1))
    block = torch.zeros((2, 40, 50), dtype=torch.uint8)
    finished_classes(wide_sums[:, 5:55], wide_weight[:, 5:55], 255, block[1, :, :50])
    np.testing.assert_array_equal(block[1].numpy(), _torch_classes(wide_sums[:, 5:55], wide_weight[:, 5:55]).numpy())
    assert not block[0].any()


def test_strips_give_the_rows_of_the_whole_run_and_chunking_changes_nothing() -> None:
    plan = plan_windows(100, 120, 64, 32)  # small tiles, large overlap: window rows reach two rows down
    assert any(len(b.sources) > 2 for b in plan.window_rows)
    windows = _random_windows(plan, 3, seed=7)
    whole = _stitch(plan, windows, 3)
    chunked = _stitch(plan, windows, 3, chunk=257)
    on_disk = _stitch(plan, windows, 3, carry_in_memory=0)  # the carry of a wide raster, in a file
    for name in whole:
        np.testing.assert_array_equal(chunked[name], whole[name], err_msg=name)
        np.testing.assert_array_equal(on_disk[name], whole[name], err_msg=name)
    n = len(plan.window_rows)
    for a, b in ((0, 1), (1, n), (2, n), (n - 1, n)):
        strip = _stitch(plan, windows, 3, a, b)
        rows = slice(plan.window_rows[a].out_start, plan.window_rows[b - 1].out_stop)
        for name in whole:
            np.testing.assert_array_equal(strip[name][:, rows], whole[name][:, rows], err_msg=f"{name} bands {a}:{b}")
