"""Height and class metrics against values computed by hand on tiny arrays."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aerialmtl.classes import IGNORE_INDEX
from aerialmtl.evaluation.metrics import (
    HeightStats,
    Subsample,
    classification_metrics,
    cohen_kappa,
    confusion_matrix,
    delta_ratio,
    height_metrics,
)


def test_height_basic_errors_and_nan_masking() -> None:
    pred = np.array([[1.0, 2.0], [3.0, 100.0]], np.float32)
    ref = np.array([[2.0, 2.0], [5.0, np.nan]], np.float32)  # NaN reference → skipped
    m = height_metrics(pred, ref, threshold=1.0)
    # errors: -1, 0, -2
    assert m["n_pixels"] == 3
    assert m["mae"] == pytest.approx(1.0)
    assert m["rmse"] == pytest.approx(math.sqrt(5 / 3))
    assert m["bias"] == pytest.approx(-1.0)
    assert m["median_abs_error"] == pytest.approx(1.0)
    assert m["median_exact"] is True


def test_height_valid_mask_excludes_pixels() -> None:
    pred = np.array([1.0, 5.0, 9.0])
    ref = np.array([1.0, 4.0, 0.0])
    valid = np.array([True, True, False])  # e.g. nodata in the reference
    m = height_metrics(pred, ref, valid=valid)
    assert m["n_pixels"] == 2
    assert m["mae"] == pytest.approx(0.5)
    assert m["rmse"] == pytest.approx(math.sqrt(0.5))


def test_delta_thresholds_only_above_threshold_and_nonpositive_predictions_fail() -> None:
    ref = np.array([0.5, 2.0, 2.0, 2.0, 2.0, 4.0])
    pred = np.array([9.0, 2.4, 3.0, 3.8, 0.0, 4.0])
    # ref 0.5 is below the 1 m threshold → not counted. Ratios: 1.2, 1.5, 1.9, inf (p ≤ 0), 1.0
    m = height_metrics(pred, ref, threshold=1.0)["delta"]
    assert m["n_pixels"] == 5
    assert m["delta_1"] == pytest.approx(2 / 5)  # < 1.25: 1.2, 1.0
    assert m["delta_2"] == pytest.approx(3 / 5)  # < 1.5625: + 1.5
    assert m["delta_3"] == pytest.approx(4 / 5)  # < 1.953: + 1.9
    np.testing.assert_allclose(delta_ratio(np.array([2.0, -1.0]), np.array([1.0, 3.0])), [2.0, np.inf])


def test_delta_with_no_pixel_above_threshold_is_undefined() -> None:
    m = height_metrics(np.array([0.2, 0.4]), np.array([0.1, 0.3]), threshold=1.0)
    assert m["delta"]["n_pixels"] == 0 and math.isnan(m["delta"]["delta_1"])


def test_height_errors_per_bin() -> None:
    ref = np.array([0.5, 0.8, 1.5, 3.0, 25.0, -0.2])
    pred = np.array([1.0, 0.8, 0.5, 4.0, 20.0, 0.0])
    m = height_metrics(pred, ref, bins=(0.0, 1.0, 2.0, 10.0, math.inf))
    bins = m["per_bin"]
    assert [b["n_pixels"] for b in bins] == [2, 1, 1, 1]  # -0.2 falls below the first edge
    assert bins[0]["mae"] == pytest.approx(0.25) and bins[0]["bias"] == pytest.approx(0.25)
    assert bins[1]["mae"] == pytest.approx(1.0) and bins[1]["bias"] == pytest.approx(-1.0)
    assert bins[3]["rmse"] == pytest.approx(5.0)
    assert bins[3]["range_m"] == [10.0, math.inf]
    assert m["n_pixels"] == 6  # the global metrics still count every valid pixel


def test_a_reading_of_the_map_has_its_own_bias_per_predicted_height() -> None:
    """A network that finds every 15 m tree right and misses a fifth of them (0 m): per bin of the reference the
    10–20 m bias is −3 m (a fifth of the trees read 15 m low); per bin of the prediction, a 15 m reading is right on
    average (bias 0) and the misses sit in the 0–1 m bin as readings 3.75 m low on average there (with the ground).
    The Markdown summary shows both tables."""
    from aerialmtl.evaluation.report import markdown_summary

    ref = np.array([15.0] * 5 + [0.0] * 3)
    pred = np.array([15.0] * 4 + [0.0] + [0.0] * 3)
    m = height_metrics(pred, ref, bins=(0.0, 1.0, 10.0, 20.0))
    by_ref, by_pred = m["per_bin"], m["per_predicted_bin"]
    assert [b["n_pixels"] for b in by_ref] == [3, 0, 5] and by_ref[2]["bias"] == pytest.approx(-3.0)
    assert [b["n_pixels"] for b in by_pred] == [4, 0, 4] and by_pred[2]["bias"] == pytest.approx(0.0)
    assert by_pred[0]["bias"] == pytest.approx(-15.0 / 4)
    text = markdown_summary({"prediction": "p", "height": m})
    assert "per reference-height bin" in text and "per predicted-height bin" in text


def test_empty_bin_is_nan_not_zero() -> None:
    m = height_metrics(np.array([0.5]), np.array([0.5]), bins=(0.0, 1.0, 2.0))
    assert m["per_bin"][1]["n_pixels"] == 0 and math.isnan(m["per_bin"][1]["mae"])


def test_height_errors_per_true_class_ignore_unlabelled() -> None:
    ref = np.array([1.0, 2.0, 3.0, 4.0])
    pred = np.array([2.0, 2.0, 6.0, 0.0])
    labels = np.array([0, 0, 1, IGNORE_INDEX], np.uint8)
    m = height_metrics(pred, ref, labels=labels, num_classes=2, class_names=["ground", "building"])
    assert m["per_class"]["ground"] == pytest.approx({"n_pixels": 2, "mae": 0.5, "rmse": math.sqrt(0.5), "bias": 0.5})
    assert m["per_class"]["building"]["mae"] == pytest.approx(3.0)
    assert m["n_pixels"] == 4


def test_streaming_height_stats_equal_one_shot(rng: np.random.Generator) -> None:
    ref = rng.uniform(0, 30, (20, 16))
    pred = ref + rng.normal(0, 2, ref.shape)
    whole = height_metrics(pred, ref)
    stats = HeightStats()
    for r in range(0, 20, 7):
        stats.update(pred[r:r + 7], ref[r:r + 7])
    parts = stats.result()
    for key in ("mae", "rmse", "bias", "median_abs_error"):
        assert parts[key] == pytest.approx(whole[key])
    assert parts["delta"] == pytest.approx(whole["delta"])


def test_subsample_is_uniform_bounded_and_seeded() -> None:
    a, b = Subsample(cap=100, seed=3), Subsample(cap=100, seed=3)
    for s in (a, b):
        for chunk in np.array_split(np.arange(10_000), 7):
            s.add(v=chunk)
    assert len(a) == 100 and a.total == 10_000 and not a.complete
    np.testing.assert_array_equal(a.get("v"), b.get("v"))
    assert len(np.unique(a.get("v"))) == 100
    assert 3000 < a.get("v").mean() < 7000  # a uniform sample, not the first chunk


def test_confusion_matrix_rows_reference_cols_prediction_and_ignore() -> None:
    ref = np.array([0, 0, 1, 1, 2, IGNORE_INDEX, 2], np.uint8)
    pred = np.array([0, 1, 1, 1, 0, 2, IGNORE_INDEX], np.uint8)
    cm = confusion_matrix(ref, pred, 3)
    expected = np.array([[1, 1, 0], [0, 2, 0], [1, 0, 0]])
    np.testing.assert_array_equal(cm, expected)
    valid = np.array([True, False, True, True, True, True, True])
    assert confusion_matrix(ref, pred, 3, valid)[0, 1] == 0


def test_kappa_2x2_by_hand() -> None:
    # N=50, po = (20+15)/50 = 0.7; row sums 25, 25; col sums 25, 25 → pe = 0.5; κ = 0.2/0.5 = 0.4
    cm = np.array([[20, 5], [10, 15]])
    assert cohen_kappa(cm) == pytest.approx(0.4)


def test_classification_metrics_3x3_by_hand() -> None:
    cm = np.array([[5, 1, 0], [2, 3, 1], [0, 0, 4]])  # N = 16
    m = classification_metrics(cm, ["a", "b", "c"])
    assert m["overall_accuracy"] == pytest.approx(12 / 16)
    # rows 6, 6, 4; cols 7, 4, 5 → pe = (42 + 24 + 20) / 256
    pe = 86 / 256
    assert m["kappa"] == pytest.approx((12 / 16 - pe) / (1 - pe))
    iou = [5 / (6 + 7 - 5), 3 / (6 + 4 - 3), 4 / (4 + 5 - 4)]
    f1 = [10 / 13, 6 / 10, 8 / 9]
    assert [m["per_class"][c]["iou"] for c in "abc"] == pytest.approx(iou)
    assert [m["per_class"][c]["f1"] for c in "abc"] == pytest.approx(f1)
    assert m["miou"] == pytest.approx(np.mean(iou))
    assert m["per_class"]["b"]["precision"] == pytest.approx(3 / 4)
    assert m["per_class"]["b"]["recall"] == pytest.approx(3 / 6)


def test_miou_skips_classes_absent_from_reference_and_prediction() -> None:
    cm = np.array([[3, 1, 0], [0, 0, 0], [0, 0, 0]])  # class 2 nowhere; class 1 only predicted
    m = classification_metrics(cm, ["a", "b", "c"])
    assert m["classes_in_mean"] == ["a", "b"]
    assert m["miou"] == pytest.approx((3 / 4 + 0.0) / 2)
    assert math.isnan(m["per_class"]["c"]["iou"])


def test_kappa_of_single_class_agreement_is_undefined() -> None:
    assert math.isnan(cohen_kappa(np.array([[4, 0], [0, 0]])))
    assert math.isnan(cohen_kappa(np.zeros((2, 2))))


# ---- the training loop's validation meters (aerialmtl.training.metrics) ------------------------------------


def test_training_height_meter_is_the_masked_mae_and_rmse_over_batches(rng: np.random.Generator) -> None:
    """The meter that picks best.pt reads only valid pixels (a NaN where the reference is invalid does not
    leak), and its batches add up to the metric over all of them at once."""
    import torch

    from aerialmtl.training.metrics import HeightMeter

    ref = rng.uniform(0, 30, (6, 1, 9, 11)).astype(np.float32)
    pred = (ref + rng.normal(0, 2, ref.shape)).astype(np.float32)
    valid = rng.random(ref.shape) > 0.3
    ref[~valid] = np.nan  # nodata references: invalid, must not count
    meter = HeightMeter()
    for b in range(0, 6, 4):  # a full and a short batch
        meter.update(torch.from_numpy(pred[b:b + 4]), torch.from_numpy(ref[b:b + 4]), torch.from_numpy(valid[b:b + 4]))
    err = pred[valid].astype(np.float64) - ref[valid].astype(np.float64)
    got = meter.compute()
    assert got["height_mae"] == pytest.approx(np.abs(err).mean(), rel=1e-6)
    assert got["height_rmse"] == pytest.approx(np.sqrt((err ** 2).mean()), rel=1e-6)
    meter.sync(lambda t: t.mul_(3))  # three identical processes: the same means
    assert meter.compute()["height_mae"] == pytest.approx(got["height_mae"], rel=1e-12)
    assert math.isnan(HeightMeter().compute()["height_mae"])  # no valid pixel: undefined, not 0


def test_training_confusion_meter_counts_as_the_evaluation_matrix(rng: np.random.Generator) -> None:
    import torch

    from aerialmtl.training.metrics import ConfusionMeter

    k = 5
    logits = rng.normal(size=(3, k, 8, 7)).astype(np.float32)
    target = rng.integers(0, k, (3, 8, 7))
    target[0, :2] = IGNORE_INDEX
    target[1, 0, :3] = [k, -1, k + 7]  # out of range: not counted
    meter = ConfusionMeter(k)
    meter.update(torch.from_numpy(logits[:2]), torch.from_numpy(target[:2]))
    meter.update(torch.from_numpy(logits[2:]), torch.from_numpy(target[2:]))
    expected = confusion_matrix(target, logits.argmax(axis=1), k)
    np.testing.assert_array_equal(meter.matrix.numpy(), expected)
    assert meter.compute()["oa"] == pytest.approx(np.trace(expected) / expected.sum())
