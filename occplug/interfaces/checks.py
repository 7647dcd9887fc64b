"""Assertions the kinds' conformance checks share (each kind's check is its interface's ``check_conformance``)."""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn

__all__ = ["CHECK_CHANNELS", "assert_finite", "assert_gradient", "eval_twice"]

#: Channels of the synthetic inputs the checks feed to view transforms, scenes and heads.
CHECK_CHANNELS = 8


def assert_finite(obj: Any, where: str) -> None:
    """Every floating value of a tensor (or a dict of them) is finite."""
    if isinstance(obj, Tensor):
        assert not obj.is_floating_point() or torch.isfinite(obj).all(), f"{where}: non-finite values"
    elif isinstance(obj, dict):
        for k, v in obj.items():
            assert_finite(v, f"{where}[{k}]")


def assert_gradient(module: nn.Module, what: str) -> None:
    """Some trainable parameter of ``module`` received a non-zero gradient."""
    trainable = [p for p in module.parameters() if p.requires_grad]
    if trainable and all(p.grad is None or p.grad.abs().sum() == 0 for p in trainable):
        raise AssertionError(f"{what}: no parameter received a gradient")


def eval_twice(module: nn.Module, fn: Callable[[nn.Module], Any]) -> tuple[Any, Any]:
    """``fn`` of the module and of a deep copy, both in eval mode (the module is left in train mode)."""
    module.eval()
    first = fn(module)
    second = fn(copy.deepcopy(module))
    module.train()
    return first, second
