"""Optimizers and learning-rate schedules, named in configs: :mod:`occplug.optim`, re-exported here for scripts
(``occplug.run.training`` is the public module; the code lives below ``config/`` and the model, which use it).
"""

from __future__ import annotations

from occplug.optim import (
    OPTIMIZER_EXTRAS,
    EffectiveBatch,
    ParamGroupRule,
    base_lr,
    batch_notice,
    build_optimizer,
    build_scheduler,
    check_param_groups,
    optimizer_class,
    optimizer_names,
    parameter_groups,
    scaled_lr,
    scheduler_factory,
)

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
