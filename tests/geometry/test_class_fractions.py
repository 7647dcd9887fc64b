"""occplug.geometry.class_fractions: labels on a coarser grid as per-class shares."""

import pytest
import torch

from occplug.geometry import class_fractions


def test_each_coarse_voxel_holds_the_shares_of_its_labelled_children():
    labels = torch.full((1, 4, 2, 2), 255, dtype=torch.int64)
    labels[0, :2] = torch.tensor([[[0, 0], [0, 2]], [[2, 2], [1, 255]]])  # coarse voxel 0: 3x0, 3x2, 1x1, 1 unknown
    labels[0, 2:] = 7  # coarse voxel 1: a label outside [0, K) only
    got = class_fractions(labels, 3, 2)
    assert got.shape == (1, 3, 2, 1, 1) and got.dtype == torch.float32
    torch.testing.assert_close(got[0, :, 0, 0, 0], torch.tensor([3 / 7, 1 / 7, 3 / 7]))
    assert torch.equal(got[0, :, 1], torch.zeros(3, 1, 1))  # nothing labelled: all zero


def test_factor_one_is_the_one_hot_and_the_shares_sum_to_one():
    labels = torch.randint(0, 5, (2, 4, 4, 2))
    onehot = class_fractions(labels, 5, 1)
    assert torch.equal(onehot.argmax(1), labels) and torch.equal(onehot.sum(1), torch.ones(2, 4, 4, 2))
    torch.testing.assert_close(class_fractions(labels, 5, 2).sum(1), torch.ones(2, 2, 2, 1))
    # the coarse shares are the mean of the children's one-hots
    torch.testing.assert_close(class_fractions(labels, 5, 2), torch.nn.functional.avg_pool3d(onehot, 2))


def test_a_shape_that_does_not_divide_is_one_line():
    with pytest.raises(ValueError, match=r"^class_fractions: label shape \(3, 2, 2\) is not divisible by factor 2$"):
        class_fractions(torch.zeros(1, 3, 2, 2, dtype=torch.int64), 4, 2)
    with pytest.raises(ValueError, match="must be"):
        class_fractions(torch.zeros(3, 2, 2, dtype=torch.int64), 4, 2)
