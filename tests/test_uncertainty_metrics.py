"""Sparsification / AUSE / AURG, ECE, Gaussian NLL and Spearman on small hand-checkable inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aerialmtl.evaluation.uncertainty import (
    CalibrationBins,
    average_ranks,
    expected_calibration_error,
    gaussian_nll,
    sparsification,
    spearman,
)


def test_sparsification_curve_by_hand() -> None:
    error = np.array([4.0, 1.0, 3.0, 0.0])
    unc = np.array([0.1, 0.2, 0.3, 0.4])  # ranks the pixels badly
    sp = sparsification(error, unc, steps=4, normalise=False)
    assert sp["fractions"] == [0.0, 0.25, 0.5, 0.75]
    # keep the 4, 3, 2, 1 least uncertain: means of [4,1,3,0], [4,1,3], [4,1], [4]
    assert sp["curve"] == pytest.approx([2.0, 8 / 3, 2.5, 4.0])
    # oracle removes the largest errors first: [0,1,3,4], [0,1,3], [0,1], [0]
    assert sp["oracle"] == pytest.approx([2.0, 4 / 3, 0.5, 0.0])
    assert sp["mean_error"] == pytest.approx(2.0)
    diff = np.array(sp["curve"]) - np.array(sp["oracle"])
    expected_ause = 0.25 * (diff[:-1] + diff[1:]).sum() / 2
    assert sp["ause"] == pytest.approx(expected_ause)


def test_perfect_uncertainty_has_zero_ause_and_positive_aurg(rng: np.random.Generator) -> None:
    err = rng.exponential(1.0, 500)
    sp = sparsification(err, err * 3.0 + 1.0)  # any increasing function of the error is perfect
    assert sp["ause"] == pytest.approx(0.0, abs=1e-12)
    assert sp["aurg"] > 0.2
    assert sp["curve"][0] == pytest.approx(1.0)  # normalised by the full-set error


def test_reversed_uncertainty_has_large_ause_and_negative_aurg(rng: np.random.Generator) -> None:
    err = rng.exponential(1.0, 500)
    good = sparsification(err, err)
    bad = sparsification(err, -err)
    assert bad["ause"] > 0.5 > good["ause"]
    assert bad["aurg"] < 0


def test_constant_uncertainty_equals_random_order() -> None:
    err = np.array([0.0, 0.0, 1.0, 1.0, 5.0])
    sp = sparsification(err, np.zeros(5), steps=5)
    assert sp["curve"] == pytest.approx([1.0] * 5)  # ties broken at random, in expectation
    assert sp["aurg"] == pytest.approx(0.0, abs=1e-12)


def test_class_sparsification_with_entropy() -> None:
    wrong = np.array([1, 0, 0, 1, 0, 0], np.float64)  # error = 1 - correct
    entropy = np.array([0.9, 0.1, 0.2, 0.8, 0.3, 0.05])
    sp = sparsification(wrong, entropy, steps=3)
    assert sp["ause"] == pytest.approx(0.0, abs=1e-12)
    assert sp["curve"][2] == pytest.approx(0.0)  # the 2 most uncertain (wrong) pixels are gone


def test_sparsification_drops_nonfinite_and_handles_empty() -> None:
    sp = sparsification(np.array([1.0, np.nan, 2.0]), np.array([1.0, 1.0, np.nan]))
    assert sp["n_pixels"] == 1
    empty = sparsification(np.array([]), np.array([]))
    assert empty["n_pixels"] == 0 and math.isnan(empty["ause"])


def test_ece_perfectly_calibrated_toy_case_is_zero() -> None:
    # 10 pixels at confidence 0.8 with 8 right, 20 pixels at confidence 0.35 with 7 right
    conf = np.r_[np.full(10, 0.8), np.full(20, 0.35)]
    correct = np.r_[np.ones(8), np.zeros(2), np.ones(7), np.zeros(13)].astype(bool)
    assert expected_calibration_error(conf, correct) == pytest.approx(0.0, abs=1e-12)


def test_ece_overconfident_by_hand() -> None:
    conf = np.array([0.95, 0.95, 0.55, 0.55])
    correct = np.array([True, False, True, True])
    # bin of 0.95: acc 0.5, gap 0.45; bin of 0.55: acc 1.0, gap 0.45 → ECE 0.45
    assert expected_calibration_error(conf, correct, n_bins=15) == pytest.approx(0.45)
    bins = CalibrationBins(15)
    bins.update(np.array([1.0]), np.array([True]))  # confidence 1 goes in the last bin
    assert bins.result()["count"][-1] == 1


def test_gaussian_nll_by_hand_and_sigma_floor() -> None:
    nll = gaussian_nll(np.array([1.0]), np.array([2.0]), np.array([3.0]))
    assert nll == pytest.approx(0.5 * math.log(2 * math.pi * 4) + 4 / 8)
    floored = gaussian_nll(np.array([0.0]), np.array([0.0]), np.array([0.0]), min_std=0.01)
    assert floored == pytest.approx(0.5 * math.log(2 * math.pi * 1e-4))
    assert math.isnan(gaussian_nll(np.array([np.nan]), np.array([1.0]), np.array([1.0])))


def test_spearman_matches_rank_definition() -> None:
    x = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    assert spearman(x, x ** 3) == pytest.approx(1.0)
    assert spearman(x, -x) == pytest.approx(-1.0)
    # ranks of y = [2, 1, 4, 3, 5]; d² = 1+1+1+1+0 = 4 → ρ = 1 - 6·4 / (5·24) = 0.8
    assert spearman(x, np.array([20.0, 10.0, 40.0, 30.0, 50.0])) == pytest.approx(0.8)
    assert math.isnan(spearman(x, np.ones(5)))


def test_average_ranks_share_ties_and_agree_with_scipy(rng: np.random.Generator) -> None:
    np.testing.assert_allclose(average_ranks(np.array([3.0, 1.0, 3.0, 2.0])), [3.5, 1.0, 3.5, 2.0])
    stats = pytest.importorskip("scipy.stats")
    x = rng.integers(0, 10, 300).astype(float)
    y = x + rng.normal(0, 3, 300)
    assert spearman(x, y) == pytest.approx(stats.spearmanr(x, y).statistic)
