"""occplug.nn's focal and dice losses against hand-computed values and against each other."""

import math

import pytest
import torch
import torch.nn.functional as F

from occplug.nn import dice_loss, pairwise_dice_loss, pairwise_sigmoid_focal_loss, sigmoid_focal_loss


def test_sigmoid_focal_loss_equals_a_hand_computed_two_element_example():
    # p = sigmoid([0, ln 3]) = [1/2, 3/4]; targets [1, 0]
    logits, targets = torch.tensor([0.0, math.log(3.0)]), torch.tensor([1.0, 0.0])
    pos = 0.25 * (1 - 0.5) ** 2 * -math.log(0.5)  # a_t = alpha, p_t = 1/2
    neg = 0.75 * 0.75**2 * -math.log(1 - 0.75)  # a_t = 1 - alpha, p_t = 1/4, (1 - p_t)^2 = (3/4)^2
    assert pos + neg == pytest.approx(0.90625 * math.log(2.0))
    assert float(sigmoid_focal_loss(logits, targets)) == pytest.approx(pos + neg, rel=1e-6)
    per = sigmoid_focal_loss(logits, targets, reduction="none")
    assert per.tolist() == pytest.approx([pos, neg], rel=1e-6)
    assert float(sigmoid_focal_loss(logits, targets, reduction="mean")) == pytest.approx((pos + neg) / 2, rel=1e-6)


def test_sigmoid_focal_loss_without_focusing_is_weighted_bce():
    g = torch.Generator().manual_seed(0)
    logits, targets = torch.randn(4, 5, generator=g), (torch.rand(4, 5, generator=g) > 0.5).float()
    got = sigmoid_focal_loss(logits, targets, alpha=0.5, gamma=0.0)
    torch.testing.assert_close(got, 0.5 * F.binary_cross_entropy_with_logits(logits, targets, reduction="sum"))
    with pytest.raises(ValueError, match="reduction"):
        sigmoid_focal_loss(logits, targets, reduction="max")  # type: ignore[arg-type]


def test_focal_and_dice_costs_equal_hand_computed_values():
    logits, target = torch.tensor([[0.0, 2.0]]), torch.tensor([[1.0, 0.0]])
    p1 = 1 / (1 + math.exp(-2.0))
    focal_v0 = 0.25 * (1 - 0.5) ** 2 * -math.log(0.5)  # positive voxel, p = 0.5
    focal_v1 = 0.75 * p1**2 * -math.log(1 - p1)  # negative voxel
    assert float(pairwise_sigmoid_focal_loss(logits, target)) == pytest.approx((focal_v0 + focal_v1) / 2, rel=1e-6)
    dice = 1 - (2 * 0.5 + 1) / (0.5 + p1 + 1 + 1)
    assert float(pairwise_dice_loss(logits, target, eps=1.0)) == pytest.approx(dice, rel=1e-6)
    assert float(dice_loss(logits[0], target[0], eps=1.0)) == pytest.approx(dice, rel=1e-6)


def test_pairwise_losses_are_the_losses_of_each_pair():
    gen = torch.Generator().manual_seed(0)
    pred, gt = torch.randn(3, 50, generator=gen), (torch.rand(4, 50, generator=gen) > 0.5).float()
    focal = pairwise_sigmoid_focal_loss(pred, gt)
    dice = pairwise_dice_loss(pred, gt)
    assert focal.shape == dice.shape == (3, 4)
    for q in range(3):
        for m in range(4):
            torch.testing.assert_close(focal[q, m], sigmoid_focal_loss(pred[q], gt[m]) / 50)
            torch.testing.assert_close(dice[q, m], dice_loss(pred[q], gt[m]))


def test_dice_loss_of_a_half_sure_prediction_and_of_identical_masks():
    # p = 1/2 everywhere against [1, 1, 0, 0]: 1 - (2 * 1 + 1) / (2 + 2 + 1) = 2/5
    assert float(dice_loss(torch.zeros(4), torch.tensor([1.0, 1.0, 0.0, 0.0]))) == pytest.approx(0.4)
    # a confident prediction of the target mask: p = t (to float32 precision), loss 0
    target = torch.tensor([[1.0, 0.0, 1.0, 1.0], [0.0, 0.0, 0.0, 0.0]])
    logits = (target * 2 - 1) * 100
    assert dice_loss(logits, target).tolist() == pytest.approx([0.0, 0.0], abs=1e-6)  # empty masks too (eps)
    # the complement: no overlap, 1 - eps / (sum p + sum t + eps)
    assert float(dice_loss(-logits[0], target[0])) == pytest.approx(1 - 1 / (1 + 3 + 1), abs=1e-6)
