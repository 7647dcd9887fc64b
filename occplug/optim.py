"""Optimizers and learning-rate schedules, named in configs (the vocabulary the config validator checks and the
model builds from; a leaf module beside :mod:`torch.optim`, re-exported by :mod:`occplug.run.training`).

``optimizer.type`` is any ``torch.optim`` optimizer by its lower-case class name (``adamw``, ``sgd``,
``rmsprop``, ...), its arguments checked against the class's signature. Besides those arguments the node takes
(:data:`OPTIMIZER_EXTRAS`) ``lr_scaling`` / ``reference_batch`` (:func:`scaled_lr`) and the parameter groups::

    optimizer:
      type: adamw
      lr: 2.0e-4
      weight_decay: 0.01
      no_decay_norm_bias: true          # norm layers' weights and every bias: weight decay 0
      param_groups:                     # by parameter-name prefix; the longest matching prefix wins
        - {prefix: encoder, lr_mult: 0.1}
        - {prefix: heads.occupancy, weight_decay: 0.0}

Every trainable parameter lands in exactly one torch parameter group (:func:`parameter_groups`).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR, LRScheduler, StepLR

from occplug.errors import ConfigError, closest

__all__ = [
    "OPTIMIZER_EXTRAS",
    "EffectiveBatch",
    "ParamGroupRule",
    "check_param_groups",
    "optimizer_names",
    "parameter_groups",
    "base_lr",
    "batch_notice",
    "build_optimizer",
    "build_scheduler",
    "optimizer_class",
    "scaled_lr",
    "scheduler_factory",
]

#: Every optimizer ``torch.optim`` exports, by its lower-case class name.
_OPTIMIZERS: dict[str, type[Optimizer]] = {
    name.lower(): cls
    for name, cls in sorted(vars(torch.optim).items())
    if isinstance(cls, type) and issubclass(cls, Optimizer) and cls is not Optimizer
}


def optimizer_names() -> tuple[str, ...]:
    """The names ``optimizer.type`` accepts: every ``torch.optim`` optimizer's class name, lower case."""
    return tuple(_OPTIMIZERS)


def optimizer_class(name: str) -> type[Optimizer]:
    """The torch optimizer behind a config name (``adamw`` -> ``torch.optim.AdamW``, ``rmsprop``, ...)."""
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
OPTIMIZER_EXTRAS = ("lr_scaling", "reference_batch", "param_groups", "no_decay_norm_bias")


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


def _default(cls: type[Optimizer], key: str) -> Any:
    param = inspect.signature(cls).parameters.get(key)
    return None if param is None or param.default is inspect.Parameter.empty else param.default


@dataclass(frozen=True)
class ParamGroupRule:
    """One entry of ``optimizer.param_groups``: the parameters whose name is ``prefix`` or starts with
    ``prefix.`` train at ``lr_mult x lr`` with ``weight_decay`` (None: the optimizer node's)."""

    prefix: str
    lr_mult: float = 1.0
    weight_decay: float | None = None

    def matches(self, name: str) -> bool:
        return name == self.prefix or name.startswith(self.prefix + ".")


def _number(value: Any, key: str, low: float, strict: bool) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or (value <= low if strict else value < low):
        raise ConfigError(f"{key}: expected a number {'>' if strict else '>='} {low:g}, got {value!r}")
    return float(value)


def check_param_groups(spec: dict[str, Any] | None) -> list[ParamGroupRule]:
    """The ``param_groups`` rules of an ``optimizer:`` node (and its ``no_decay_norm_bias`` switch), checked.

    Raises:
        ConfigError: one line naming the key (``optimizer.param_groups.1.lr_mult``) and what was expected.
    """
    spec = spec or {}
    switch = spec.get("no_decay_norm_bias", False)
    if not isinstance(switch, bool):
        raise ConfigError(f"optimizer.no_decay_norm_bias: expected true or false, got {switch!r}")
    raw = spec.get("param_groups") or []
    if not isinstance(raw, (list, tuple)):
        raise ConfigError(
            f"optimizer.param_groups: expected a list of {{prefix, lr_mult, weight_decay}} mappings, got {raw!r}"
        )
    fields = ("prefix", "lr_mult", "weight_decay")
    rules: list[ParamGroupRule] = []
    for i, entry in enumerate(raw):
        key = f"optimizer.param_groups.{i}"
        if not isinstance(entry, dict):
            raise ConfigError(f"{key}: expected a mapping {{prefix, lr_mult, weight_decay}}, got {entry!r}")
        for name in entry:
            if name not in fields:
                hint = closest(str(name), list(fields))
                raise ConfigError(
                    f"{key}.{name}: unknown key{f'; did you mean {hint!r}?' if hint else ''} (keys: {', '.join(fields)})"
                )
        prefix = entry.get("prefix")
        if not isinstance(prefix, str) or not prefix or prefix.startswith(".") or prefix.endswith("."):
            raise ConfigError(f"{key}.prefix: expected a parameter-name prefix such as 'encoder', got {prefix!r}")
        if prefix in (r.prefix for r in rules):
            raise ConfigError(f"{key}.prefix: {prefix!r} is already the prefix of an earlier group")
        decay = entry.get("weight_decay")
        rules.append(
            ParamGroupRule(
                prefix,
                _number(entry.get("lr_mult", 1.0), f"{key}.lr_mult", 0.0, strict=True),
                None if decay is None else _number(decay, f"{key}.weight_decay", 0.0, strict=False),
            )
        )
    optimizer = spec.get("type", "adamw")
    if optimizer in _OPTIMIZERS and _default(_OPTIMIZERS[optimizer], "weight_decay") is None:
        if switch or any(r.weight_decay is not None for r in rules):
            raise ConfigError(f"optimizer: {optimizer!r} has no weight_decay, so no group can set or drop it")
    return rules


#: Module types whose weights ``no_decay_norm_bias`` keeps out of weight decay (every torch normalisation layer).
NORM_LAYERS: tuple[type[nn.Module], ...] = (
    nn.modules.batchnorm._NormBase,  # BatchNorm*d, SyncBatchNorm, InstanceNorm*d
    nn.GroupNorm,
    nn.LayerNorm,
    nn.LocalResponseNorm,
    *((nn.RMSNorm,) if hasattr(nn, "RMSNorm") else ()),
)


def parameter_groups(module: nn.Module, spec: dict[str, Any] | None, lr: float) -> list[dict[str, Any]]:
    """Torch parameter groups of ``module``'s trainable parameters per the ``optimizer:`` node ``spec``.

    A parameter goes to the rule with the longest matching prefix (else to the default group), then, with
    ``no_decay_norm_bias``, to that group's no-decay half when it belongs to a normalisation layer
    (:data:`NORM_LAYERS`) or its name ends in ``bias``. Each group is ``{"name", "params", "lr"}`` (+
    ``"weight_decay"`` for optimizers that have one); empty groups are left out, and every trainable parameter
    is in exactly one group.

    Raises:
        ConfigError: a rule's prefix matches no parameter of ``module`` (with the closest module name).
    """
    spec = dict(spec or _DEFAULT_OPTIMIZER)
    rules = check_param_groups(spec)
    cls = optimizer_class(spec.get("type", "adamw"))
    base_decay = spec.get("weight_decay", _default(cls, "weight_decay"))
    exclude = bool(spec.get("no_decay_norm_bias", False))
    norm_params = {id(p) for m in module.modules() if isinstance(m, NORM_LAYERS) for p in m.parameters(recurse=False)}
    groups: dict[tuple[int, bool], dict[str, Any]] = {}
    names: list[str] = []
    for name, param in module.named_parameters():
        names.append(name)
        if not param.requires_grad:  # frozen (a phase's freeze): in no group
            continue
        matching = [i for i, r in enumerate(rules) if r.matches(name)]
        index = max(matching, key=lambda i: len(rules[i].prefix)) if matching else -1
        no_decay = exclude and (id(param) in norm_params or name.endswith("bias"))
        rule = rules[index] if index >= 0 else ParamGroupRule("", 1.0, None)
        group = groups.get((index, no_decay))
        if group is None:
            label = rule.prefix or "default"
            group = {"name": f"{label} (no decay)" if no_decay else label, "params": [], "lr": lr * rule.lr_mult}
            if base_decay is not None:
                group["weight_decay"] = (
                    0.0 if no_decay else (base_decay if rule.weight_decay is None else rule.weight_decay)
                )
            groups[(index, no_decay)] = group
        group["params"].append(param)
    for i, rule in enumerate(rules):
        if not any(rule.matches(name) for name in names):
            raise ConfigError(
                f"optimizer.param_groups.{i}.prefix: {rule.prefix!r} matches no parameter" + _hint(rule.prefix, names)
            )
    return [groups[k] for k in sorted(groups, key=lambda k: (k[0] < 0, k[0], k[1]))]


def _hint(prefix: str, names: list[str]) -> str:
    """The closest module path of ``names`` to ``prefix``, else the top-level modules."""
    paths = {".".join(n.split(".")[:k]) for n in names for k in range(1, n.count(".") + 1)}
    hint = closest(prefix, sorted(paths))
    tops = sorted({n.split(".", 1)[0] for n in names})
    return f"; did you mean {hint!r}?" if hint else f" (top-level modules: {', '.join(tops)})"


def build_optimizer(
    params: nn.Module | Any, spec: dict[str, Any] | None, batch: EffectiveBatch | None = None
) -> Optimizer:
    """Build the optimizer of a config's ``optimizer:`` node (default: AdamW, lr 1e-3).

    ``params`` is a module (its trainable parameters, grouped by :func:`parameter_groups`) or an iterable of
    parameters (one group; ``param_groups`` and ``no_decay_norm_bias`` need the names, so a module).
    ``lr_scaling`` / ``reference_batch`` are read here (see :func:`scaled_lr`); every other key is an argument
    of the torch optimizer.
    """
    spec = dict(spec or _DEFAULT_OPTIMIZER)
    lr = scaled_lr(spec, batch)
    if isinstance(params, nn.Module):
        params = parameter_groups(params, spec, lr)
    elif spec.get("param_groups") or spec.get("no_decay_norm_bias"):
        raise TypeError("optimizer.param_groups / no_decay_norm_bias group parameters by name: pass the module")
    for key in OPTIMIZER_EXTRAS:
        spec.pop(key, None)
    spec["lr"] = lr
    return optimizer_class(spec.pop("type", "adamw"))(params, **spec)


def build_scheduler(optimizer: Optimizer, spec: dict[str, Any] | None, total_steps: int) -> LRScheduler | None:
    """Build the schedule of a config's ``scheduler:`` node, stepped every optimizer step."""
    spec = dict(spec or {"type": "none"})
    return scheduler_factory(spec.pop("type", "none"))(optimizer, total_steps=total_steps, **spec)
