"""Optimizers and learning-rate schedules, named in configs by a fixed set of names."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR, LRScheduler, StepLR

__all__ = ["build_optimizer", "build_scheduler", "optimizer_class", "scheduler_factory"]

_OPTIMIZERS: dict[str, type[Optimizer]] = {
    "adamw": torch.optim.AdamW,
    "adam": torch.optim.Adam,
    "sgd": torch.optim.SGD,
}


def optimizer_class(name: str) -> type[Optimizer]:
    """The torch optimizer behind a config name (``adamw``, ``adam``, ``sgd``)."""
    return _OPTIMIZERS[name]


def no_schedule(optimizer: Optimizer, total_steps: int) -> None:
    """A constant learning rate."""
    return None


def cosine_schedule(optimizer: Optimizer, total_steps: int, warmup_steps: int = 0, min_lr_ratio: float = 0.0) -> LRScheduler:
    """Linear warm-up over ``warmup_steps`` optimizer steps, then cosine decay to ``min_lr_ratio * lr``."""

    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / max(1, warmup_steps)
        progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
        return min_lr_ratio + (1 - min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))

    return LambdaLR(optimizer, factor)


def step_schedule(optimizer: Optimizer, total_steps: int, step_size: int = 1000, gamma: float = 0.1) -> LRScheduler:
    """Multiply the learning rate by ``gamma`` every ``step_size`` optimizer steps."""
    return StepLR(optimizer, step_size=step_size, gamma=gamma)


_SCHEDULERS: dict[str, Callable[..., LRScheduler | None]] = {
    "none": no_schedule,
    "cosine": cosine_schedule,
    "step": step_schedule,
}


def scheduler_factory(name: str) -> Callable[..., LRScheduler | None]:
    """The schedule function behind a config name (``none``, ``cosine``, ``step``)."""
    return _SCHEDULERS[name]


def build_optimizer(params: Any, spec: dict[str, Any] | None) -> Optimizer:
    """Build the optimizer of a config's ``optimizer:`` node (default: AdamW, lr 1e-3)."""
    spec = dict(spec or {"type": "adamw", "lr": 1e-3})
    return optimizer_class(spec.pop("type", "adamw"))(params, **spec)


def build_scheduler(optimizer: Optimizer, spec: dict[str, Any] | None, total_steps: int) -> LRScheduler | None:
    """Build the schedule of a config's ``scheduler:`` node, stepped every optimizer step."""
    spec = dict(spec or {"type": "none"})
    return scheduler_factory(spec.pop("type", "none"))(optimizer, total_steps=total_steps, **spec)
