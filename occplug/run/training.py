"""Optimizers and learning-rate schedules, named in configs by a fixed set of names."""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR, LRScheduler, StepLR

__all__ = [
    "OPTIMIZER_EXTRAS",
    "EffectiveBatch",
    "base_lr",
    "batch_notice",
    "build_optimizer",
    "build_scheduler",
    "optimizer_class",
    "scaled_lr",
    "scheduler_factory",
]

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


def cosine_schedule(
    optimizer: Optimizer, total_steps: int, warmup_steps: int = 0, min_lr_ratio: float = 0.0
) -> LRScheduler:
    """Linear warm-up over ``warmup_steps`` optimizer steps, then cosine decay to ``min_lr_ratio * lr``."""

    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / max(1, warmup_steps)
        progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
        return min_lr_ratio + (1 - min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))

    return LambdaLR(optimizer, factor)


def constant_schedule(
    optimizer: Optimizer, total_steps: int, warmup_steps: int = 0, warmup_start: float = 1.0 / 3.0
) -> LRScheduler:
    """Linear warm-up from ``warmup_start * lr`` to ``lr`` over ``warmup_steps`` optimizer steps, then constant (the
    mmcv-style schedule whose decay steps a run never reaches, as DuOcc's public code trains)."""

    def factor(step: int) -> float:
        if step < warmup_steps:
            return warmup_start + (1.0 - warmup_start) * step / warmup_steps
        return 1.0

    return LambdaLR(optimizer, factor)


def step_schedule(optimizer: Optimizer, total_steps: int, step_size: int = 1000, gamma: float = 0.1) -> LRScheduler:
    """Multiply the learning rate by ``gamma`` every ``step_size`` optimizer steps."""
    return StepLR(optimizer, step_size=step_size, gamma=gamma)


_SCHEDULERS: dict[str, Callable[..., LRScheduler | None]] = {
    "none": no_schedule,
    "cosine": cosine_schedule,
    "constant": constant_schedule,
    "step": step_schedule,
}


def scheduler_factory(name: str) -> Callable[..., LRScheduler | None]:
    """The schedule function behind a config name (``none``, ``cosine``, ``constant``, ``step``)."""
    return _SCHEDULERS[name]


_DEFAULT_OPTIMIZER = {"type": "adamw", "lr": 1e-3}
#: Keys of ``optimizer:`` read here, not passed to the torch optimizer.
OPTIMIZER_EXTRAS = ("lr_scaling", "reference_batch")


@dataclass(frozen=True)
class EffectiveBatch:
    """Samples per optimizer step over the whole run: ``devices x per_device x accumulation``.

    ``devices`` is the number of processes (all nodes), ``per_device`` the data module's
    ``batch_size``, ``accumulation`` the trainer's ``accumulate_grad_batches``.
    """

    devices: int
    per_device: int
    accumulation: int

    @property
    def total(self) -> int:
        return self.devices * self.per_device * self.accumulation

    def describe(self) -> str:
        return (
            f"{self.total} ({self.devices} device(s) x {self.per_device} per device x {self.accumulation} accumulation)"
        )


def base_lr(spec: dict[str, Any] | None) -> float:
    """The configured learning rate (the optimizer's default when the node sets none)."""
    spec = dict(spec or _DEFAULT_OPTIMIZER)
    if "lr" in spec:
        return float(spec["lr"])
    default = inspect.signature(optimizer_class(spec.get("type", "adamw"))).parameters["lr"].default
    return float(default)


def scaled_lr(spec: dict[str, Any] | None, batch: EffectiveBatch | None) -> float:
    """The learning rate a run uses: with ``lr_scaling: linear``, ``lr x total / reference_batch``."""
    lr = base_lr(spec)
    if spec and spec.get("lr_scaling", "none") == "linear" and batch is not None:
        return lr * batch.total / int(spec["reference_batch"])
    return lr


def batch_notice(spec: dict[str, Any] | None, batch: EffectiveBatch) -> str | None:
    """One line when the effective batch differs from the recipe's ``reference_batch``, else None."""
    ref = (spec or {}).get("reference_batch")
    if ref is None or int(ref) == batch.total:
        return None
    head = f"notice: effective batch {batch.describe()} differs from the recipe's reference batch {ref}; "
    lr, used = base_lr(spec), scaled_lr(spec, batch)
    if spec.get("lr_scaling", "none") == "linear":  # type: ignore[union-attr]
        return head + f"learning rate scaled linearly {lr:g} -> {used:g} (optimizer.lr_scaling=linear)"
    return (
        head
        + f"learning rate kept at {lr:g} (optimizer.lr_scaling=linear would scale it to {lr * batch.total / int(ref):g})"
    )


def build_optimizer(params: Any, spec: dict[str, Any] | None, batch: EffectiveBatch | None = None) -> Optimizer:
    """Build the optimizer of a config's ``optimizer:`` node (default: AdamW, lr 1e-3).

    ``lr_scaling`` / ``reference_batch`` are read here (see :func:`scaled_lr`); every other key is
    an argument of the torch optimizer.
    """
    spec = dict(spec or _DEFAULT_OPTIMIZER)
    lr = scaled_lr(spec, batch)
    for key in OPTIMIZER_EXTRAS:
        spec.pop(key, None)
    spec["lr"] = lr
    return optimizer_class(spec.pop("type", "adamw"))(params, **spec)


def build_scheduler(optimizer: Optimizer, spec: dict[str, Any] | None, total_steps: int) -> LRScheduler | None:
    """Build the schedule of a config's ``scheduler:`` node, stepped every optimizer step."""
    spec = dict(spec or {"type": "none"})
    return scheduler_factory(spec.pop("type", "none"))(optimizer, total_steps=total_steps, **spec)
