"""The shadow step's compiled kernels (aerialmtl.sun.kernels) compute what the numpy and scipy code they replace
computes: the walks, the maximum filter and the shadow surface to the bit, the classifier's logistic within float32
rounding."""

from __future__ import annotations

from dataclasses import astuple

import numpy as np
import pytest
from scipy import ndimage

from aerialmtl.sun import ShadowModel, Sun, kernels, shadow_heights
from aerialmtl.sun.cast import shadow_surface_sweep
from aerialmtl.sun.colour import _CONTEXTS, _EPS, _brightness, _local, _planes, unit_rgb
from aerialmtl.sun.heights import occluder_steps, shadow_runs
from tests.helpers.shadow_walks import (
    occluder_steps_numpy,
    shadow_heights_numpy,
    shadow_runs_numpy,
    shadow_surface_numpy,
)


@pytest.mark.parametrize("shape", [(1, 1), (2, 3), (5, 40), (37, 29), (64, 64)])
@pytest.mark.parametrize("size", [3, 5, 7, 41])
def test_max_filter_is_scipys_reflect_maximum_to_the_bit(shape: tuple[int, int], size: int) -> None:
    """Also where the window is wider than the image (a 2-pixel-wide window of a 1 m recipe at 40 m)."""
    img = np.random.default_rng(size + shape[0]).normal(size=shape).astype(np.float32)
    out = np.empty_like(img)
    kernels.max_filter_reflect(img, size, np.empty_like(img), out)
    np.testing.assert_array_equal(out, ndimage.maximum_filter(img, size=size, mode="reflect"))


def _scene(seed: int, n: int = 96) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Random blocks (objects), their heights with NaN holes, a shadow mask with noise and unknown pixels."""
    rng = np.random.default_rng(seed)
    height = np.zeros((n, n), np.float32)
    for _ in range(12):
        r, c = rng.integers(0, n - 8, 2)
        h, w = rng.integers(3, 14, 2)
        height[r:r + h, c:c + w] = rng.uniform(2.5, 30.0)
    height += rng.normal(0, 0.3, height.shape).astype(np.float32)
    height[rng.random(height.shape) < 0.01] = np.nan
    objects, _ = ndimage.label(np.nan_to_num(height) >= 2.0)
    shadow = (rng.random((n, n)) < 0.35) | ndimage.binary_dilation(objects > 0, iterations=3)
    known = rng.random((n, n)) > 0.02
    return height, objects, shadow & known, known


@pytest.mark.parametrize("azimuth", [0.0, 37.0, 90.0, 135.0, 181.0, 244.0, 300.0, 359.0])
@pytest.mark.parametrize("gap_px", [0, 1, 3])
def test_shadow_walks_equal_the_numpy_walks(azimuth: float, gap_px: int) -> None:
    sun = Sun(azimuth, 40.0)
    for seed in range(3):
        height, objects, shadow, known = _scene(seed)
        want = shadow_runs_numpy(shadow, known, objects, sun, 25, gap_px)
        got = shadow_runs(shadow, known, objects, sun, 25, gap_px)
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
        lab, _, _, rc = got
        np.testing.assert_array_equal(occluder_steps(height, objects, rc, lab, sun, 0.8, 25),
                                      occluder_steps_numpy(height, objects, rc, lab, sun, 0.8, 25))


def test_logistic_kernel_equals_the_numpy_features_within_float32_rounding() -> None:
    rng = np.random.default_rng(4)
    rgb = rng.integers(0, 256, (3, 50, 70), dtype=np.uint8)
    model = ShadowModel(gsd_m=0.5, mean=list(rng.normal(size=12)), scale=list(rng.uniform(0.5, 2, 12)),
                        weights=list(rng.normal(size=13)))
    x = unit_rgb(rgb)
    lum = _brightness(x)
    local = [_local(lum, job, 0.5) for job in _CONTEXTS]
    a = np.asarray(model.weights[1:]) / np.asarray(model.scale)
    bias = np.float32(model.weights[0] - float(a @ np.asarray(model.mean)))
    z = np.full(lum.shape, bias, np.float32)
    for ak, plane in zip(a.astype(np.float32), _planes(x, lum, local)):
        z += ak * plane
    want = (1.0 / (1.0 + np.exp(-np.clip(z, -40.0, 40.0)))).astype(np.float32)
    out = np.empty_like(lum)
    kernels.logistic_rows(x, lum, *local, a.astype(np.float32), bias, np.float32(_EPS), 0, 50, out)
    np.testing.assert_allclose(out, want, rtol=0, atol=1e-6)
    # the model's own bands of rows on threads: the same to the bit, whatever the threads
    one = model.predict_proba(rgb, workers=1)
    np.testing.assert_array_equal(one, out)
    np.testing.assert_array_equal(model.predict_proba(rgb, workers=3), one)


def test_shadow_heights_accept_every_integer_label_type() -> None:
    """ndimage.label gives int32, a user's labels may be int64 or uint16: each compiles, same heights."""
    height, objects, shadow, known = _scene(7)
    prob = np.where(known, shadow.astype(np.float32), np.nan)
    sun = Sun(120.0, 45.0)
    ref = shadow_heights(prob, 1.0, sun, objects.astype(np.int64), height=height)
    for dtype in (np.int32, np.uint16):
        got = shadow_heights(prob, 1.0, sun, objects.astype(dtype), height=height)
        np.testing.assert_array_equal(got.height, ref.height)


@pytest.mark.parametrize("min_runs", [1, 3, 8])
def test_shadow_heights_equal_the_first_written_ones(min_runs: int) -> None:
    """The compiled walks and the medians by position give every object the same height and spread."""
    for seed, azimuth in ((1, 60.0), (2, 150.0), (3, 290.0)):
        height, objects, shadow, known = _scene(seed, 128)
        prob = np.where(known, np.random.default_rng(seed).random(known.shape) * 0.3 + shadow * 0.5, np.nan)
        sun = Sun(azimuth, 35.0)
        for h in (height, None):
            got = shadow_heights(prob, 0.5, sun, objects, height=h, threshold=0.4, min_runs=min_runs)
            want = shadow_heights_numpy(prob, 0.5, sun, objects, height=h, threshold=0.4, min_runs=min_runs)
            np.testing.assert_array_equal(got.height, want.height)
            np.testing.assert_array_equal(got.std, want.std)
            np.testing.assert_equal([astuple(o) for o in got.objects], [astuple(o) for o in want.objects])
            assert any(o.measured for o in got.objects)


@pytest.mark.parametrize("azimuth", [0.0, 30.0, 45.0, 90.0, 101.3, 135.0, 180.0, 200.0, 225.0, 270.0, 315.0, 359.0])
@pytest.mark.parametrize("elevation", [12.0, 44.0, 79.0])
def test_the_shadow_surface_equals_the_numpy_sweep_to_the_bit(azimuth: float, elevation: float) -> None:
    """Every direction (both axes dominant, both signs, diagonals) and sun height, on a stack of two non-square
    rasters with buildings, noise, NaN (no height), ±∞ and a one-pixel raster; the sweep's float32 maxima and
    differences give the same surface to the bit, NaN where numpy's maximum gives NaN."""
    rng = np.random.default_rng(int(azimuth * 10 + elevation))
    z = rng.gamma(1.0, 0.5, (2, 37, 53)).astype(np.float32)
    z[0, 5:15, 8:20] += 12.0
    z[1, 20:30, 30:50] += 25.0
    z[0, 3, 40], z[1, 33, 2], z[0, 20, 20], z[1, 0, 0] = np.nan, np.nan, np.inf, -np.inf
    for raster in (z, z[1], z[:, :1, :1], z[:, :, :1]):
        want = shadow_surface_numpy(raster, 0.5, azimuth, elevation)
        got = shadow_surface_sweep(raster, 0.5, azimuth, elevation)
        assert got.dtype == np.float32 and got.shape == raster.shape
        np.testing.assert_array_equal(got.view(np.int32), want.view(np.int32))


def test_shadow_sums_count_the_shaded_ground_and_add_its_scores() -> None:
    """The fit's one-pass score of a sun: exactly the pixels of ``cast_shadow_mask & ground`` counted, and their
    scores (arbitrary float64, not the few values of an 8-bit image) summed within 1e-12 of numpy's sum; NaN, ±∞
    heights and a stack with no ground pixel included."""
    from aerialmtl.sun.cast import TOL_M, cast_shadow_mask, sweep_stack

    rng = np.random.default_rng(7)
    h = rng.gamma(1.0, 0.4, (3, 41, 67)).astype(np.float32)
    h[0, 5:15, 8:20] += 12.0
    h[1, 20:30, 30:50] += 25.0
    h[2, 10:12, 10:60] += 6.0
    h[0, 3, 40], h[1, 33, 2], h[0, 20, 20], h[2, 0, 0] = np.nan, np.nan, np.inf, -np.inf
    score = rng.random(h.shape) * 3.0 - 1.0
    ground = (rng.random(h.shape) < 0.8) & (np.nan_to_num(h, nan=99.0) < 0.5)
    z = np.nan_to_num(h, nan=-np.inf, posinf=np.inf, neginf=-np.inf)
    for az, el in [(0.0, 30.0), (77.0, 20.0), (135.0, 45.0), (250.0, 12.0), (315.0, 70.0)]:
        for g in (ground, np.zeros_like(ground)):
            mask = cast_shadow_mask(h, 0.5, Sun(az, el)) & g
            count, total = kernels.shadow_sums(z, sweep_stack(z, 0.5, az, el), g, score, np.float32(TOL_M))
            assert count == int(mask.sum()) and (count > 0) == bool(g.any())
            assert total == pytest.approx(float(score[mask].sum()), rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("azimuth", [20.0, 101.3, 200.0, 290.0])
def test_scaled_shadow_sums_equal_the_rendering_of_each_multiplier(azimuth: float) -> None:
    """The common multiplier's search (render._global_scale) in one call: for each multiplier, the evidence summed
    over the known pixels that ``where(inside, z · s, z)`` shades is the sum the separate sweep and count give, to
    the bit (the same float32 products, the same sums), on both sweep axes; unknown heights (−∞) included."""
    from aerialmtl.sun.cast import TOL_M, sweep_plan, sweep_stack

    rng = np.random.default_rng(int(azimuth))
    z = rng.gamma(1.0, 0.3, (1, 45, 61)).astype(np.float32)
    z[0, 5:15, 8:20] += 9.0
    z[0, 25:33, 30:52] += 17.0
    z[0, 3, 40] = -np.inf
    inside = z > 2.0
    known = rng.random(z.shape) < 0.9
    score = (rng.random(z.shape) * 4.0 - 2.0).astype(np.float32).astype(np.float64)
    scales = np.geomspace(0.5, 4.0, 9).astype(np.float32)
    rows, step, deltas, drop = sweep_plan(z.shape, 0.5, azimuth, 35.0)
    got = np.empty(len(scales))
    kernels.scaled_shadow_sums(z, inside, scales, rows, step, deltas, drop, known, score, np.float32(TOL_M),
                               np.empty_like(z), np.empty_like(z), got)
    for k, s in enumerate(scales):
        zs = np.ascontiguousarray(np.where(inside, z * s, z))
        _, want = kernels.shadow_sums(zs, sweep_stack(zs, 0.5, azimuth, 35.0), known, score, np.float32(TOL_M))
        assert got[k] == want
    assert len(set(got)) > 1


def test_the_fits_score_of_a_sun_is_the_correlation_with_the_cast_shadow_mask() -> None:
    """The objective's score at any sun is the point-biserial correlation of the shadow score with
    ``cast_shadow_mask`` over ground pixels, computed in numpy (to 1e-12), with half of a patch's buildings of
    unknown height (NaN); NaN where no ground pixel is shaded."""
    from aerialmtl.data.synth import CityStyle, sample_city
    from aerialmtl.sun.cast import cast_shadow_mask
    from aerialmtl.sun.colour import shadow_score
    from aerialmtl.sun.fit import GROUND_M, _Objective

    patches = [sample_city(s, size=size, gsd=0.5, style=CityStyle.plain()) for s, size in ((3, 96), (4, 64))]
    tall = np.argwhere(patches[0].height > 3.0)
    assert len(tall) > 50
    patches[0].height[tuple(tall[: len(tall) // 2].T)] = np.nan  # no height known: casts no shadow, is not ground
    f = _Objective([p.image for p in patches], [p.height for p in patches], 0.5, None, GROUND_M)
    scores = np.concatenate([shadow_score(p.image).astype(np.float64)[p.height < GROUND_M].ravel() for p in patches])
    seen_nan = False
    for az, el in [(10.0, 30.0), (140.0, 55.0), (230.0, 15.0), (300.0, 40.0), (45.0, 89.0)]:
        shade = np.concatenate([cast_shadow_mask(p.height, 0.5, Sun(az, el))[p.height < GROUND_M].ravel()
                                for p in patches])
        got = f._corr(Sun(az, el))
        if shade.any():
            assert got == pytest.approx(float(np.corrcoef(scores, shade)[0, 1]), rel=1e-12, abs=1e-12)
        else:
            seen_nan = True
            assert np.isnan(got)
    assert seen_nan
