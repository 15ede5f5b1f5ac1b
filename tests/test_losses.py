"""Masked losses against hand-computed values, and task weighting."""

from __future__ import annotations

import math

import pytest
import torch

from aerialmtl.errors import ConfigError
from aerialmtl.training import losses as L
from aerialmtl.training.weighting import EqualWeighting, UncertaintyWeighting, build_weighting

# pred 1 2 / 3 4, target 1.5 2 / 0 NaN, the last pixel invalid → errors −0.5, 0, 3.
PRED = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])
TARGET = torch.tensor([[[[1.5, 2.0], [0.0, float("nan")]]]])
MASK = torch.tensor([[[[True, True], [True, False]]]])

HAND = {
    "l1": (0.5 + 0 + 3) / 3,
    "l2": (0.25 + 0 + 9) / 3,
    "huber": (0.5 * 0.25 + 0 + 1.0 * (3 - 0.5)) / 3,  # δ = 1
    "berhu": (0.5 + 0 + (9 + 0.6**2) / (2 * 0.6)) / 3,  # c = 0.2 · 3 = 0.6
}


@pytest.mark.parametrize("name", sorted(HAND))
def test_regression_losses_hand_values(name: str) -> None:
    value = L.HEIGHT_LOSSES[name](PRED, TARGET, MASK)
    assert value.item() == pytest.approx(HAND[name], rel=1e-6)
    assert L.HeightLoss(name)(PRED, TARGET, MASK).item() == pytest.approx(HAND[name], rel=1e-6)


def test_scale_invariant_hand_value() -> None:
    d = [math.log(2 / 2.5), math.log(3 / 3), math.log(4 / 1)]  # log(h + 1 m) differences
    n = 3
    expected = sum(v * v for v in d) / n - 0.5 * (sum(d) / n) ** 2
    assert L.scale_invariant(PRED, TARGET, MASK).item() == pytest.approx(expected, rel=1e-5)


def test_scale_invariant_ignores_a_global_scale() -> None:
    target = torch.tensor([[[[1.0, 3.0], [7.0, 15.0]]]])  # log(t + 1) = log 2, 4, 8, 16
    pred = 2 * (target + 1) - 1  # every log error is log 2
    assert L.scale_invariant(pred, target, lam=1.0).item() == pytest.approx(0.0, abs=1e-6)
    assert L.scale_invariant(pred, target, lam=0.5).item() == pytest.approx(0.5 * math.log(2) ** 2, rel=1e-5)


def test_scale_invariant_gradient_hand_value() -> None:
    a = torch.tensor([[[[0.0, 1.0], [2.0, 4.0]]]])
    target = torch.zeros_like(a)
    pred = torch.exp(a) - 1  # log(pred + 1) − log(0 + 1) = a
    si = (0 + 1 + 4 + 16) / 4 - 0.5 * (7 / 4) ** 2
    grad = (abs(1 - 0) + abs(4 - 2) + abs(2 - 0) + abs(4 - 1)) / 4  # 2 horizontal + 2 vertical pairs
    value = L.scale_invariant_gradient(pred, target, alpha=0.5)
    assert value.item() == pytest.approx(si + 0.5 * grad, rel=1e-5)


def test_cross_entropy_hand_values() -> None:
    logits = torch.tensor([[[[0.0, 0.0, 5.0]], [[math.log(3), 0.0, -5.0]]]])  # 1×2×1×3
    target = torch.tensor([[[1, 0, 255]]])
    plain = (math.log(4 / 3) + math.log(2)) / 2
    assert L.cross_entropy(logits, target).item() == pytest.approx(plain, rel=1e-6)
    weighted = (2 * math.log(4 / 3) + 1 * math.log(2)) / 3
    w = torch.tensor([1.0, 2.0])
    assert L.cross_entropy(logits, target, weight=w).item() == pytest.approx(weighted, rel=1e-6)
    assert L.CrossEntropyLoss(w)(logits, target).item() == pytest.approx(weighted, rel=1e-6)
    mask = torch.tensor([[[True, False, True]]])
    assert L.cross_entropy(logits, target, mask=mask).item() == pytest.approx(math.log(4 / 3), rel=1e-6)


@pytest.mark.parametrize("name", sorted(L.HEIGHT_LOSSES))
def test_invalid_pixels_change_nothing(name: str) -> None:
    fn = L.HEIGHT_LOSSES[name]
    g = torch.Generator().manual_seed(0)
    pred = torch.rand(2, 1, 8, 8, generator=g) * 10
    target = torch.rand(2, 1, 8, 8, generator=g) * 10
    mask = torch.rand(2, 1, 8, 8, generator=g) > 0.3
    p1 = pred.clone().requires_grad_(True)
    v1 = fn(p1, target, mask)
    v1.backward()
    pred2 = torch.where(mask, pred, torch.full_like(pred, -1e4))
    target2 = torch.where(mask, target, torch.full_like(target, float("nan")))
    p2 = pred2.clone().requires_grad_(True)
    v2 = fn(p2, target2, mask)
    v2.backward()
    assert v1.item() == pytest.approx(v2.item(), rel=1e-6)
    assert p1.grad is not None and p2.grad is not None
    assert torch.all(p2.grad[~mask] == 0) and torch.isfinite(p2.grad).all()
    torch.testing.assert_close(p1.grad[mask], p2.grad[mask])


@pytest.mark.parametrize("name", sorted(L.HEIGHT_LOSSES))
def test_all_invalid_batch_gives_zero_with_grad(name: str) -> None:
    pred = torch.randn(2, 1, 4, 4, requires_grad=True)
    target = torch.full((2, 1, 4, 4), float("nan"))
    value = L.HEIGHT_LOSSES[name](pred, target, torch.zeros(2, 1, 4, 4, dtype=torch.bool))
    assert value.item() == 0.0 and value.requires_grad
    value.backward()
    assert pred.grad is not None and torch.count_nonzero(pred.grad) == 0


def test_cross_entropy_all_ignored_gives_zero_with_grad() -> None:
    logits = torch.randn(1, 3, 4, 4, requires_grad=True)
    value = L.cross_entropy(logits, torch.full((1, 4, 4), 255), weight=torch.ones(3))
    assert value.item() == 0.0
    value.backward()
    assert logits.grad is not None and torch.isfinite(logits.grad).all()


def test_loss_shape_errors_and_names() -> None:
    with pytest.raises(ValueError, match="B×1×H×W"):
        L.l1(torch.zeros(1, 1, 4, 4), torch.zeros(1, 1, 4, 5))
    with pytest.raises(ValueError, match="B×H×W"):
        L.cross_entropy(torch.zeros(1, 3, 4, 4), torch.zeros(1, 1, 4, 4, dtype=torch.long))
    with pytest.raises(ConfigError, match="berhu"):
        L.HeightLoss("l3")


# --------------------------------------------------------------------------- task weighting


def test_equal_weighting() -> None:
    losses = {"height": torch.tensor(2.0), "classes": torch.tensor(3.0)}
    assert EqualWeighting(["height", "classes"])(losses).item() == 5.0
    w = build_weighting("equal", ["height", "classes"], weights={"height": 0.5})
    assert w(losses).item() == 4.0
    assert w.weights() == {"height": 0.5, "classes": 1.0}
    with pytest.raises(ConfigError, match="depth"):
        EqualWeighting(["height"], weights={"depth": 1.0})
    with pytest.raises(KeyError, match="classes"):
        EqualWeighting(["height", "classes"])({"height": torch.tensor(1.0)})


def test_uncertainty_weighting_forms_and_gradients() -> None:
    w = build_weighting("uncertainty", ["height", "classes"])
    assert isinstance(w, UncertaintyWeighting)
    lh, lc = torch.tensor(2.0, requires_grad=True), torch.tensor(3.0, requires_grad=True)
    with torch.no_grad():
        w.log_vars["height"].fill_(math.log(4.0))  # σ² = 4
        w.log_vars["classes"].fill_(math.log(0.5))  # σ² = 0.5
    total = w({"height": lh, "classes": lc})
    expected = (0.5 / 4 * 2 + 0.5 * math.log(4)) + (1 / 0.5 * 3 + 0.5 * math.log(0.5))
    assert total.item() == pytest.approx(expected, rel=1e-6)
    total.backward()
    # d/ds [f·e^{-s}·L + s/2] = −f·e^{-s}·L + 1/2
    assert w.log_vars["height"].grad.item() == pytest.approx(-0.5 / 4 * 2 + 0.5, rel=1e-6)
    assert w.log_vars["classes"].grad.item() == pytest.approx(-1 / 0.5 * 3 + 0.5, rel=1e-6)
    assert lh.grad.item() == pytest.approx(0.5 / 4)
    assert w.weights() == pytest.approx({"height": 0.125, "classes": 2.0})
    assert {n for n, _ in w.named_parameters()} == {"log_vars.height", "log_vars.classes"}


def test_uncertainty_weighting_learns_to_downweight_a_large_loss() -> None:
    w = UncertaintyWeighting(["height"])
    opt = torch.optim.SGD(w.parameters(), lr=0.1)
    for _ in range(200):
        opt.zero_grad()
        w({"height": torch.tensor(10.0)}).backward()
        opt.step()
    # Optimum of ½e^{-s}·10 + s/2: s = log 10.
    assert w.log_vars["height"].item() == pytest.approx(math.log(10), rel=0.05)


def test_unknown_weighting_name() -> None:
    with pytest.raises(ConfigError, match="uncertainty"):
        build_weighting("gradnorm", ["height"])


def test_height_balance_weights_lift_the_rare_tall_pixels() -> None:
    """``loss.height_balance``: 90 ground pixels and 10 at 25 m; at power 0.5 each bin's pixels weigh
    ∝ n^−0.5, mean 1 over the valid pixels, so a tall pixel weighs 3× a ground one; invalid pixels weigh 0."""
    target = torch.tensor([0.0] * 90 + [25.0] * 10 + [float("nan")] * 4).reshape(1, 1, 8, 13)
    mask = torch.isfinite(target)
    w = L.height_balance_weights(target, mask, 0.5)
    ground, tall = 1 / math.sqrt(90), 1 / math.sqrt(10)
    scale = 100 / (90 * ground + 10 * tall)
    assert w[0, 0, 0, 0].item() == pytest.approx(ground * scale, rel=1e-6)
    assert w[0, 0, 7, 8].item() == pytest.approx(tall * scale, rel=1e-6)  # index 99: the last tall pixel
    assert w[~mask].eq(0).all() and w[mask].mean().item() == pytest.approx(1.0, rel=1e-6)
    assert not w.requires_grad
    assert torch.equal(L.height_balance_weights(target, mask, 0.0), mask.float())  # power 0: the plain mean
    # the weighted L1 of a map at 0 m is then the weighted mean of the errors
    pred = torch.zeros_like(target)
    assert L.l1(pred, target, mask, weight=w).item() == pytest.approx(10 * 25 * tall * scale / 100, rel=1e-6)
    scale_b = torch.ones_like(target)
    assert L.laplace_nll(pred, scale_b, target, mask, weight=w).item() == pytest.approx(
        L.l1(pred, target, mask, weight=w).item(), rel=1e-6)  # b = 1: the NLL is the L1


def test_height_balance_config_errors() -> None:
    from aerialmtl.training.config import LossSection

    with pytest.raises(ConfigError, match="height_balance"):
        LossSection(height_balance=1.5)
    with pytest.raises(ConfigError, match="loss.height: l1"):
        LossSection(height="l2", height_balance=0.5)
    assert LossSection(height_balance=0.5).height_balance == 0.5


def test_height_balance_weighs_the_bins_cross_entropy_too() -> None:
    """With a height-bin head the balance weights every height term: the bins' cross-entropy is the weighted
    mean of the per-pixel terms (weights of 1 give the plain mean)."""
    from aerialmtl.models.height_bins import bin_edges

    edges = bin_edges(4, 40.0)
    target = torch.tensor([0.0, 0.0, 0.0, 25.0]).reshape(1, 1, 2, 2)
    mask = torch.ones_like(target, dtype=torch.bool)
    logits = torch.zeros(1, 4, 2, 2)
    logits[:, 0] = 2.0  # every pixel confident of the lowest bin: the 25 m pixel is the costly one
    plain = L.height_bins_ce(logits, target, mask, edges)
    assert L.height_bins_ce(logits, target, mask, edges, weight=torch.ones_like(target)).item() == pytest.approx(
        plain.item(), rel=1e-6)
    w = L.height_balance_weights(target, mask, 1.0)  # ground 3 × 2/3, tall 1 × 2
    per = torch.nn.functional.cross_entropy(logits, torch.tensor([[[0, 0], [0, 3]]]), reduction="none")[0]
    expected = (per * w[0, 0]).mean()
    assert L.height_bins_ce(logits, target, mask, edges, weight=w).item() == pytest.approx(expected.item(), rel=1e-6)
    assert L.height_bins_ce(logits, target, mask, edges, weight=w).item() > plain.item()
