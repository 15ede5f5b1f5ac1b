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


# ---- the spread per stratum -----------------------------------------------------------------------
def test_spread_strata_coverage_scores_and_ranking_per_bin() -> None:
    """A spread that is the true σ of Gaussian errors covers 68 % / 95 % in every bin and ranks the errors
    within bins; a spread proportional to height alone covers on average but ranks nothing within a bin."""
    import math

    from aerialmtl.evaluation.uncertainty import SpreadStrata, crps_gaussian, laplace_terms

    rng = np.random.default_rng(42)  # not the subsample's seed: its keys would be the heights themselves
    n = 200_000
    ref = rng.uniform(0, 30, n)
    sigma = rng.uniform(0.2, 3.0, n) * (1 + ref / 10)  # varies within every bin
    pred = ref + rng.normal(0, 1, n) * sigma
    good = SpreadStrata((0, 1, 2, 5, 10, 20, math.inf), sample_cap=50_000)
    good.update(pred, sigma, ref)
    res = good.result()
    assert [b["range_m"][0] for b in res["bins"]] == [0, 1, 2, 5, 10, 20]
    for b in res["bins"]:
        assert b["coverage_1sigma"] == pytest.approx(0.683, abs=0.02)
        assert b["coverage_2sigma"] == pytest.approx(0.954, abs=0.015)
        assert b["spearman_std_vs_abs_error"] > 0.2
        assert b["reliability_observed"][-1] == pytest.approx(0.954, abs=0.02)
    assert sum(b["share"] for b in res["bins"]) == pytest.approx(1.0)
    flat = SpreadStrata((0, 1, 2, 5, 10, 20, math.inf), sample_cap=50_000)
    flat.update(pred, np.full(n, float(np.median(sigma))), ref)
    assert res["crps_gaussian_m"] < flat.result()["crps_gaussian_m"]  # the proper score prefers the true σ
    assert res["nll_gaussian"] < flat.result()["nll_gaussian"]
    height_only = SpreadStrata((0, 1, 2, 5, 10, 20, math.inf), sample_cap=50_000)
    height_only.update(pred, 0.5 + pred * 0.0 + 1.0, ref)  # constant within a bin: no ranking at all
    assert all(math.isnan(b["spearman_std_vs_abs_error"]) for b in height_only.result()["bins"])
    # the tutorial's old map: the spread is the predicted height rescaled; per bin it reads ~1 against the
    # predicted height, while the true σ (drawn apart from the height) reads near 0 in the narrow bins
    rescaled = SpreadStrata((0, 1, 2, 5, 10, 20, math.inf), sample_cap=50_000)
    rescaled.update(pred, 1.09 * pred + 50.0, ref)
    assert all(b["spearman_std_vs_predicted_height"] > 0.99 for b in rescaled.result()["bins"])
    assert all(abs(b["spearman_std_vs_predicted_height"]) < 0.5 for b in res["bins"][:3])
    # closed forms against numerical integration of the CRPS (∫ (F(x) − 1{x ≥ y})² dx)
    from scipy import stats

    x = np.linspace(-40, 40, 400_001)
    for dist, value in ((stats.norm(1.0, 2.0), crps_gaussian(np.array([1.0]), np.array([2.0]), np.array([3.5]))[0]),
                        (stats.laplace(1.0, 2.0 / math.sqrt(2)),
                         laplace_terms(np.array([1.0]), np.array([2.0]), np.array([3.5]))[1][0])):
        integrand = (dist.cdf(x) - (x >= 3.5)) ** 2
        trapz = getattr(np, "trapezoid", None) or getattr(np, "trapz")  # noqa: B009 - numpy < 2 has only trapz
        assert value == pytest.approx(trapz(integrand, x), rel=1e-4)


def test_unfamiliarity_scores_rank_the_errors_within_a_bin_not_the_height() -> None:
    """A layer that follows the error ranks it within every bin; one that follows the predicted height ranks
    the height (≈ 1) and says little of the errors inside a narrow bin."""
    import math

    from aerialmtl.evaluation.unfamiliarity import UnfamiliarityScores

    rng = np.random.default_rng(5)
    n = 100_000
    ref = rng.uniform(0, 30, n)
    pred = ref + rng.normal(0, 1, n) * rng.uniform(0.2, 3.0, n)
    edges = (0, 1, 2, 5, 10, 20, math.inf)
    follows_error = UnfamiliarityScores(edges, sample_cap=40_000)
    follows_error.update(np.abs(pred - ref) / 20, pred, ref)
    follows_height = UnfamiliarityScores(edges, sample_cap=40_000)
    follows_height.update(1 / (1 + np.exp(-(pred - 15) / 5)), pred, ref)
    e, h = follows_error.result(), follows_height.result()
    assert e["n_sampled"] == 40_000 and len(e["bins"]) == 6
    assert all(b["spearman_vs_abs_error"] > 0.99 for b in e["bins"])
    assert all(b["spearman_vs_predicted_height"] > 0.99 for b in h["bins"])
    assert all(abs(b["spearman_vs_abs_error"]) < 0.5 for b in h["bins"][2:])
    assert UnfamiliarityScores(edges).result()["n_sampled"] == 0
