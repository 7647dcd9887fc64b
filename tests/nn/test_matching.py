"""occplug.nn.linear_assignment: the Hungarian solver against brute force, rectangles, NaN costs, no scipy."""

import itertools
import sys

import pytest
import torch

from occplug.nn import linear_assignment


def test_linear_assignment_hand_made_3x3():
    cost = torch.tensor([[4.0, 1.0, 3.0], [2.0, 0.0, 5.0], [3.0, 2.0, 2.0]])
    rows, cols = linear_assignment(cost)
    assert rows.tolist() == [0, 1, 2] and cols.tolist() == [1, 0, 2]  # total 5, the unique optimum
    assert rows.dtype == cols.dtype == torch.int64


@pytest.mark.parametrize("seed", range(5))
def test_linear_assignment_equals_brute_force_4x4(seed):
    cost = torch.rand(4, 4, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    rows, cols = linear_assignment(cost)
    best = min(itertools.permutations(range(4)), key=lambda p: sum(float(cost[i, p[i]]) for i in range(4)))
    assert rows.tolist() == [0, 1, 2, 3] and cols.tolist() == list(best)


@pytest.mark.parametrize("seed", range(3))
def test_more_predictions_than_ground_truths_match_each_ground_truth_once(seed):
    cost = torch.rand(5, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    rows, cols = linear_assignment(cost)
    # brute force over which 3 of the 5 predictions take the ground truths, in every order
    best = min(itertools.permutations(range(5), 3), key=lambda p: sum(float(cost[p[g], g]) for g in range(3)))
    assert sorted(zip(rows.tolist(), cols.tolist(), strict=True)) == sorted((p, g) for g, p in enumerate(best))
    assert rows.tolist() == sorted(rows.tolist())


def test_nan_and_minus_inf_costs_count_as_large():
    cost = torch.tensor([[float("nan"), 1.0], [2.0, float("-inf")]])
    rows, cols = linear_assignment(cost)  # both diagonal entries count as 1e8: the anti-diagonal wins
    assert rows.tolist() == [0, 1] and cols.tolist() == [1, 0]


def test_empty_costs_give_empty_matches():
    for shape in [(0, 3), (4, 0), (0, 0)]:
        rows, cols = linear_assignment(torch.zeros(shape))
        assert rows.shape == cols.shape == (0,) and rows.dtype == torch.int64


def test_float32_and_gradient_carrying_costs_are_solved_detached():
    cost = torch.tensor([[1.0, 0.0], [0.0, 1.0]], requires_grad=True)
    rows, cols = linear_assignment(cost * 2)
    assert cols.tolist() == [1, 0]


def test_missing_scipy_is_a_one_line_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "scipy.optimize", None)  # makes `from scipy.optimize import ...` fail
    with pytest.raises(ImportError, match="needs scipy") as err:
        linear_assignment(torch.zeros(2, 2))
    assert "\n" not in str(err.value)
