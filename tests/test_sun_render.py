"""Heights chosen by rendering cast shadows (aerialmtl.sun.render), proven on scenes whose sun and heights are
exact: hand-made boxes, and synthetic cities seen through a shadow classifier and a network-like height map."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from aerialmtl.data.synth import CityStyle, sample_city
from aerialmtl.sun import (
    RenderedHeights,
    RenderSettings,
    ShadowModel,
    Sun,
    cast_shadow_mask,
    fuse_rendered,
    rendered_heights,
)

SCENES = [(13, 130.0, 40.0), (16, 250.0, 55.0), (17, 130.0, 40.0), (18, 60.0, 35.0), (19, 200.0, 50.0)]


def city(seed: int, azimuth: float, elevation: float, size: int = 192):
    """A true-orthophoto city patch (clean sensor) under a chosen sun, 0.5 m pixels."""
    style = replace(CityStyle.plain().with_lean(0.0), sun_azimuth=(azimuth, azimuth),
                    sun_elevation=(elevation, elevation))
    return sample_city(seed, size=size, gsd=0.5, style=style)


def network_like(truth: np.ndarray) -> np.ndarray:
    """What a height network gives: the shapes blurred (1 m) and read 40 % low."""
    return (ndimage.gaussian_filter(truth, 2.0) * 0.6).astype(np.float32)


def relative_errors(rh: RenderedHeights, objects: np.ndarray, truth: np.ndarray) -> list[float]:
    """Per measured object: its height / its median true height − 1 (objects whose truth is ≥ 2 m)."""
    out = []
    for o in rh.objects:
        ref = float(np.median(truth[objects == o.label]))
        if o.measured and ref >= 2.0:
            out.append(o.height_m / ref - 1.0)
    return out


def box_scene(height_m: float = 12.0, shape: tuple[int, int] = (80, 80)) -> tuple[np.ndarray, np.ndarray, Sun]:
    """One flat-roofed box on flat ground, its exact cast shadow (sun from the east: shadows run west)."""
    truth = np.zeros(shape, np.float32)
    truth[30:45, 50:62] = height_m
    sun = Sun(90.0, 45.0)
    return truth, cast_shadow_mask(truth, 0.5, sun).astype(np.float32), sun


def test_exact_shadows_give_every_object_its_height_from_a_network_that_reads_it_low() -> None:
    """Exact cast shadows, heights blurred and 40 % low: pooled over five cities under five suns, the rendered
    heights' median relative error is within ±10 % (today +2 %), their median |error| ≤ 10 % (today 7 %), and
    at least half the objects of 20 m² and more of each 128 m patch are measured (smaller ones are not tried)."""
    errors, shares = [], []
    for seed, azimuth, elevation in SCENES:
        sun = Sun(azimuth, elevation)
        p = city(seed, azimuth, elevation, size=256)
        truth = p.height.astype(np.float32)
        net = network_like(truth)
        objects, _ = ndimage.label(net >= 2.0)
        rh = rendered_heights(cast_shadow_mask(truth, p.gsd, sun).astype(np.float32), p.gsd, sun, objects, net)
        errors += relative_errors(rh, objects, truth)
        big = [o for o in rh.objects if o.n_edges * p.gsd ** 2 >= 20.0]  # n_edges: the object's pixels
        shares.append(sum(o.measured for o in big) / len(big))
        measured = np.isfinite(rh.height)
        assert (np.isfinite(rh.std) == measured).all() and (rh.std[measured] > 0).all()
    assert abs(np.median(errors)) <= 0.10, np.median(errors)
    assert np.median(np.abs(errors)) <= 0.10, np.median(np.abs(errors))
    assert min(shares) >= 0.5, shares  # some shadows leave the patch


def test_heights_from_the_image_through_a_learnt_shadow_classifier() -> None:
    """End to end from the image: the colour classifier fitted on three other scenes under the same sun gives the
    shadow probability, the heights are network-like (40 % low). Pooled over five scenes the rendered heights are
    much nearer the truth than the heights they started from: median |error| ≤ 30 % (today 25 %, against 40 %),
    and never more than 35 % high in the median (today +25 %: the classifier's probability spreads a little past
    the shadows' ends here; on real data, autzen_west's validation block, the same default reads its objects of
    10 m and more 6 % low — the study in experiments/heights_from_the_sun)."""
    errors = []
    for seed, azimuth, elevation in SCENES:
        sun = Sun(azimuth, elevation)
        train = [city(s, azimuth, elevation) for s in (1, 2, 3)]
        model = ShadowModel().fit([p.image for p in train], [p.height for p in train], 0.5, sun)
        p = city(seed, azimuth, elevation, size=256)
        truth = p.height.astype(np.float32)
        net = network_like(truth)
        objects, _ = ndimage.label(net >= 2.0)
        rh = rendered_heights(model.predict_proba(p.image), p.gsd, sun, objects, net,
                              RenderSettings(threshold=model.threshold))
        errors += relative_errors(rh, objects, truth)
    assert np.median(np.abs(errors)) <= 0.30, np.median(np.abs(errors))
    assert -0.10 <= np.median(errors) <= 0.35, np.median(errors)


@pytest.mark.parametrize("given", [6.0, 12.0, 24.0])
def test_a_box_gets_its_height_whatever_height_it_was_given(given: float) -> None:
    truth, shadow, sun = box_scene(12.0)
    net = np.where(truth > 0, np.float32(given), np.float32(0.0))
    objects, _ = ndimage.label(net >= 2.0)
    rh = rendered_heights(shadow, 0.5, sun, objects, net)
    (obj,) = rh.objects
    assert obj.measured and abs(obj.height_m - 12.0) <= 0.6, obj
    assert obj.std_m < 3.0


def test_a_shadow_falling_on_a_lower_roof_is_rendered_there() -> None:
    """A 20 m tower beside a 6 m hall down-sun: most of the tower's shadow lies on the hall's roof. Shadow runs
    stop at the hall; the rendering casts the tower's shadow onto the roof and gets the tower right."""
    truth = np.zeros((80, 140), np.float32)
    truth[30:45, 100:112] = 20.0  # the tower
    truth[25:50, 60:100] = 6.0  # the hall, west of it (sun from the east)
    sun = Sun(90.0, 45.0)
    shadow = cast_shadow_mask(truth, 0.5, sun).astype(np.float32)
    net = truth * np.float32(0.5)
    objects, _ = ndimage.label(net >= 2.0)  # one object of two heights: split them by height
    objects = np.where(truth >= 20.0, 2, np.where(objects > 0, 1, 0)).astype(np.int32)
    rh = rendered_heights(shadow, 0.5, sun, objects, net)
    tower = next(o for o in rh.objects if o.label == 2)
    assert tower.measured and abs(tower.height_m - 20.0) <= 1.5, tower


def test_a_shadow_cut_by_the_edge_measures_nothing() -> None:
    """A box whose shadow runs off the raster: the match curve is flat, no height (no vote)."""
    truth = np.zeros((60, 60), np.float32)
    truth[20:35, 2:14] = 12.0  # shadows run west, off the raster within 4 px
    sun = Sun(90.0, 45.0)
    shadow = cast_shadow_mask(truth, 0.5, sun).astype(np.float32)
    objects, _ = ndimage.label(truth > 0)
    rh = rendered_heights(shadow, 0.5, sun, objects, truth * np.float32(0.5))
    assert not rh.objects[0].measured
    assert np.isnan(rh.height).all()


def test_unknown_shadow_pixels_are_not_evidence() -> None:
    """NaN (nodata) over the whole shadow: nothing measured; over half of it: the other half still measures."""
    truth, shadow, sun = box_scene(12.0)
    objects, _ = ndimage.label(truth > 0)
    net = truth * np.float32(0.5)
    hidden = shadow.copy()
    hidden[:, :50] = np.nan
    assert not rendered_heights(hidden, 0.5, sun, objects, net).objects[0].measured
    half = shadow.copy()
    half[:37, :50] = np.nan
    obj = rendered_heights(half, 0.5, sun, objects, net).objects[0]
    assert obj.measured and abs(obj.height_m - 12.0) <= 0.6


def test_spill_into_the_own_shadow_is_taken_as_ground() -> None:
    """The network's box runs 3 px into its own shadow (blurred edge): those pixels are its spill, and the
    height is still right."""
    truth, shadow, sun = box_scene(12.0)
    net = np.where(truth > 0, np.float32(7.0), np.float32(0.0))
    net[30:45, 47:50] = 4.0  # spill on the down-sun (west) side, inside the shadow
    objects, _ = ndimage.label(net >= 2.0)
    rh = rendered_heights(shadow, 0.5, sun, objects, net)
    obj = rh.objects[0]
    assert obj.measured and abs(obj.height_m - 12.0) <= 1.0, obj
    assert rh.spill[30:45, 47:50].all() and not rh.spill[:, 50:].any()
    assert obj.trimmed_px == 45


def test_fusion_never_raises_ground_and_only_lowers_spill() -> None:
    truth, shadow, sun = box_scene(12.0)
    net = np.where(truth > 0, np.float32(7.0), np.float32(0.0))
    net[30:45, 47:50] = 4.0
    net[5:10, 5:10] = 0.5  # a low bump on open ground: not an object
    std = np.full(net.shape, 2.0, np.float32)
    objects, _ = ndimage.label(net >= 2.0)
    rh = rendered_heights(shadow, 0.5, sun, objects, net)
    fh, fs = fuse_rendered(net, std, rh)
    outside = objects == 0
    assert np.array_equal(fh[outside], net[outside]) and np.array_equal(fs[outside], std[outside])
    assert (fh[30:45, 50:62] > 7.0).all() and (fh[30:45, 50:62] < 12.5).all()  # moved towards 12 m
    assert (fh[30:45, 47:50] < 4.0).all()  # spill lowered towards the ground
    assert (fs[30:45, 50:62] > 0).all()


def test_a_disagreement_widens_the_spread() -> None:
    truth, shadow, sun = box_scene(12.0)
    objects, _ = ndimage.label(truth > 0)
    std = np.full(truth.shape, 1.0, np.float32)
    near = np.where(truth > 0, np.float32(11.5), np.float32(0.0))
    far = np.where(truth > 0, np.float32(6.0), np.float32(0.0))
    _, s_near = fuse_rendered(near, std, rendered_heights(shadow, 0.5, sun, objects, near))
    _, s_far = fuse_rendered(far, std, rendered_heights(shadow, 0.5, sun, objects, far))
    inside = truth > 0
    assert np.median(s_far[inside]) > np.median(s_near[inside])


def test_one_multiplier_first_when_every_object_reads_low() -> None:
    """Every object of a city at half its height: the common multiplier found first is about 2."""
    sun = Sun(130.0, 40.0)
    p = city(13, 130.0, 40.0)
    truth = p.height.astype(np.float32)
    objects, _ = ndimage.label(truth >= 2.0)
    rh = rendered_heights(cast_shadow_mask(truth, p.gsd, sun).astype(np.float32), p.gsd, sun, objects,
                          truth * np.float32(0.5))
    assert 1.7 <= rh.global_scale <= 2.3, rh.global_scale


def test_shapes_must_agree() -> None:
    with pytest.raises(ValueError, match="one shape"):
        rendered_heights(np.zeros((4, 4)), 0.5, Sun(90.0, 45.0), np.zeros((4, 5), np.int32), np.zeros((4, 4)))
