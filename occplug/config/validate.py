"""Validating a composed config against the registered components, before anything is built.

Every component node is checked against its factory's constructor signature: an unknown key
(with the closest valid key), a missing required key, or a value of the wrong type is one
:class:`ConfigError` line naming the full key path. An argument annotated with a group of settings
(:func:`occplug.config.settings`) is checked the same way, field by field, down to any depth.

Numbers are in range by default, wherever they sit (component arguments, settings, the optimizer,
scheduler, trainer and checkpoint sections): a float is finite (``optimizer.lr=.inf`` is refused, not
trained into NaN weights), an int fits in 64 bits, and the top-level ``seed`` is what NumPy and
Lightning accept (``0 .. 2**32 - 1``).
"""

from __future__ import annotations

import collections.abc as cabc
import inspect
import math
import typing
from dataclasses import dataclass
from typing import Any

from occplug.constraints import (
    LabelIds,
    NonNegative,
    Positive,
    Range,
    UnitInterval,
    choices_of,
    constraints_of,
    violated,
)
from occplug.context import parse_grid
from occplug.geometry import GridSpec
from occplug.kinds import given_arguments
from occplug.registry import Registry, closest
from occplug.settings import is_settings, settings_type
from occplug.slots import TOP_LEVEL, Slot, component_params, slot_of

from .errors import ConfigError
from .loggers import check_loggers

__all__ = [
    "RUN_CONSTRAINTS",
    "SEED_RANGE",
    "SCHEDULERS",
    "UsedComponent",
    "check_type",
    "out_of_range",
    "validate",
    "validate_component",
]

#: Learning-rate schedules (``scheduler.type``).
SCHEDULERS = ("none", "cosine", "constant", "step")


#: The seeds ``lightning.seed_everything`` (and NumPy's legacy seeding) accept.
SEED_RANGE = (0, 2**32 - 1)
_INT64 = (-(2**63), 2**63 - 1)


def out_of_range(value: Any) -> str | None:
    """What is wrong with a number anywhere in ``value`` (lists and mappings searched), or None.

    A float must be finite; an int must fit in a signed 64-bit integer (what every tensor and
    generator takes).
    """
    if isinstance(value, float) and not math.isfinite(value):
        return "a finite number"
    if isinstance(value, int) and not isinstance(value, bool) and not _INT64[0] <= value <= _INT64[1]:
        return "an int that fits in 64 bits"
    items = value.values() if isinstance(value, dict) else value if isinstance(value, (list, tuple)) else ()
    for item in items:
        problem = out_of_range(item)
        if problem is not None:
            return ("every element " if isinstance(value, (list, tuple)) else "") + problem
    return None


def _describe(value: Any) -> str:
    text = repr(value)
    return f"{type(value).__name__} {text if len(text) < 40 else text[:37] + '...'}"


def _type_name(annotation: Any) -> str:
    if annotation is type(None):
        return "null"
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _type_name(typing.get_args(annotation)[0])
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        return " or ".join(_type_name(a) for a in typing.get_args(annotation))
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(annotation))
    if origin is not None:
        args = typing.get_args(annotation)
        base = getattr(origin, "__name__", str(origin))
        base = {"Sequence": "list", "tuple": "list", "Mapping": "mapping", "dict": "mapping"}.get(base, base)
        return f"{base}[{', '.join(_type_name(a) for a in args)}]" if args and base == "list" else base
    if annotation is GridSpec:
        return "grid mapping {range, voxel_size}"
    if is_settings(annotation):
        return f"a mapping of {annotation.__name__}"
    return getattr(annotation, "__name__", str(annotation))


def _near(value: Any, annotation: Any) -> str:
    """``"; did you mean 'x'?"`` for a string close to one of ``annotation``'s ``Literal`` choices, else ``""``."""
    hint = closest(value, [c for c in choices_of(annotation) if isinstance(c, str)]) if isinstance(value, str) else None
    return f"; did you mean {hint!r}?" if hint else ""


def check_type(value: Any, annotation: Any) -> bool:
    """Whether a config value fits a (resolved) annotation; unknown annotations accept anything."""
    if annotation is inspect.Parameter.empty or annotation is Any or isinstance(annotation, str):
        return True
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Annotated:
        return check_type(value, args[0])
    if origin is typing.Union or (origin is not None and type(annotation).__name__ == "UnionType"):
        return any(check_type(value, a) for a in args)
    if annotation is type(None):
        return value is None
    if origin is typing.Literal:
        return value in args
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if annotation is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if annotation is str:
        return isinstance(value, str)
    if annotation is GridSpec:
        return isinstance(value, (dict, GridSpec))
    if is_settings(annotation):  # a nested group of settings: a mapping (checked key by key) or the object
        return isinstance(value, (dict, annotation))
    if origin in (list, tuple, cabc.Sequence) or annotation in (list, tuple, cabc.Sequence):
        if not isinstance(value, (list, tuple)):
            return False
        if origin is tuple and args and args[-1] is not Ellipsis:
            return len(args) == len(value) and all(check_type(v, a) for v, a in zip(value, args, strict=True))
        return not args or all(check_type(v, args[0]) for v in value)
    if origin in (dict, cabc.Mapping) or annotation in (dict, cabc.Mapping):
        if not isinstance(value, dict):
            return False
        return len(args) != 2 or all(check_type(v, args[1]) for v in value.values())
    if inspect.isclass(annotation):
        return isinstance(value, annotation)
    return True


@dataclass(frozen=True)
class UsedComponent:
    """A component node of a config: where it sits, its kind and registered name, who provides it."""

    path: str
    kind: str
    type: str
    plugin: str
    distribution: str | None


class _Validator:
    def __init__(self, registry: Registry, class_count: int | None = None) -> None:
        self.registry = registry
        self.used: list[UsedComponent] = []
        #: how many classes the run's data module has, where it declares them (checks :class:`LabelIds`)
        self.class_count = class_count

    def node(self, node: Any, kind: str, path: str) -> None:
        if isinstance(node, str) and kind == "metric":
            node = {"type": node}
        if not isinstance(node, dict):
            raise ConfigError(f"{path}: expected a {kind} node (a mapping with 'type:'), got {_describe(node)}")
        if "type" not in node:
            names = ", ".join(self.registry.names(kind)) or "(none)"
            raise ConfigError(f"{path}: missing 'type:' naming a registered {kind} (available: {names})")
        name = node["type"]
        try:
            entry = self.registry.get(kind, str(name))
        except LookupError as exc:
            raise ConfigError(f"{path}.type: {exc}") from None
        self.used.append(UsedComponent(path, kind, entry.name, entry.plugin, entry.distribution))
        label = f"{entry.name} ({kind}{', plugin ' + entry.plugin if entry.plugin != 'occplug' else ''})"
        given = given_arguments(kind, entry.factory)
        self.arguments(node, component_params(entry.factory), path, label, "parameter", given)

    def arguments(
        self,
        node: dict[str, Any],
        params: dict[str, tuple[inspect.Parameter, Any]],
        path: str,
        label: str,
        noun: str,
        given: set[str] | frozenset[str] = frozenset(),
    ) -> None:
        """Check a component node's arguments, or a settings group's values, against ``params``."""
        for key, value in node.items():
            if key == "type" and noun == "parameter":
                continue
            if key not in params:
                hint = closest(str(key), list(params))
                suggestion = f"; did you mean '{hint}'?" if hint else f"; valid keys: {', '.join(params) or '(none)'}"
                raise ConfigError(f"{path}.{key}: {label} has no {noun} '{key}'{suggestion}")
            param, annotation = params[key]
            slot = slot_of(annotation)
            group = settings_type(annotation)
            if slot is not None:
                self.slot(value, slot, f"{path}.{key}")
            elif not check_type(value, annotation):
                raise ConfigError(
                    f"{path}.{key}: expected {_type_name(annotation)}, got {_describe(value)}{_near(value, annotation)}"
                )
            elif (problem := violated(value, self.with_classes(annotation))) is not None:
                raise ConfigError(f"{path}.{key}: expected {problem}, got {_describe(value)}")
            elif group is not None and isinstance(value, dict):
                self.arguments(value, component_params(group), f"{path}.{key}", group.__name__, "setting")
            elif (problem := out_of_range(value)) is not None:  # any float finite, any int within 64 bits
                raise ConfigError(f"{path}.{key}: expected {problem}, got {_describe(value)}")
        missing = [k for k, (p, _) in params.items() if p.default is inspect.Parameter.empty and k not in node]
        missing = [k for k in missing if k not in given]
        if missing:
            what = "argument" if noun == "parameter" else noun
            raise ConfigError(f"{path}: {label} is missing required {what}(s): {', '.join(missing)}")

    def with_classes(self, annotation: Any) -> Any:
        """``annotation`` with its :class:`LabelIds` rule bounded by the run's class count, where both are known."""
        if self.class_count is None or LabelIds() not in constraints_of(annotation):
            return annotation
        return typing.Annotated[annotation, LabelIds(self.class_count)]

    def slot(self, value: Any, slot: Slot, path: str) -> None:
        if slot.mapping:
            if value is None:
                return
            if not isinstance(value, dict):
                raise ConfigError(f"{path}: expected a mapping of name -> {slot.kind} node, got {_describe(value)}")
            for name, sub in value.items():
                if sub is None:  # `name: null` switches an entry off
                    continue
                self.node(sub, slot.kind, f"{path}.{name}")
        elif slot.sequence:
            if value is None:
                return
            if not isinstance(value, list):
                raise ConfigError(f"{path}: expected a list of {slot.kind} nodes, got {_describe(value)}")
            for i, sub in enumerate(value):
                self.node(sub, slot.kind, f"{path}.{i}")
        else:
            self.node(value, slot.kind, path)


def _validate_grid(value: Any) -> None:
    if not isinstance(value, dict):
        raise ConfigError(f"grid: expected a mapping {{range, voxel_size}}, got {_describe(value)}")
    for key in value:
        if key not in ("range", "voxel_size"):
            hint = closest(str(key), ["range", "voxel_size"])
            raise ConfigError(
                f"grid.{key}: unknown key{f'; did you mean {hint!r}?' if hint else ''} (grid has range, voxel_size)"
            )
    for key in ("range", "voxel_size"):
        if key not in value:
            raise ConfigError(f"grid: missing '{key}'")
    try:
        parse_grid(value)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"grid: {exc}") from None


#: Rules on the run's own numbers (optimizer, scheduler, trainer, checkpoint arguments), whose
#: signatures belong to PyTorch and Lightning and declare none. Keys not listed are type-checked only.
RUN_CONSTRAINTS: dict[str, Any] = {
    "optimizer.lr": Positive,
    "optimizer.weight_decay": NonNegative,
    "optimizer.momentum": UnitInterval,
    "optimizer.dampening": UnitInterval,
    "optimizer.eps": Positive,
    "optimizer.betas": UnitInterval,  # each of the two
    "scheduler.warmup_steps": NonNegative,
    "scheduler.min_lr_ratio": UnitInterval,
    "scheduler.warmup_start": UnitInterval,
    "scheduler.step_size": Positive,
    "scheduler.gamma": Positive,
    "trainer.max_epochs": Range(low=-1),
    "trainer.min_epochs": NonNegative,
    "trainer.max_steps": Range(low=-1),
    "trainer.min_steps": NonNegative,
    "trainer.accumulate_grad_batches": Range(low=1),
    "trainer.gradient_clip_val": NonNegative,
    "trainer.log_every_n_steps": Range(low=1),
    "trainer.check_val_every_n_epoch": Range(low=1),
    "trainer.val_check_interval": Positive,
    "trainer.num_sanity_val_steps": Range(low=-1),
    "trainer.limit_train_batches": NonNegative,
    "trainer.limit_val_batches": NonNegative,
    "trainer.limit_test_batches": NonNegative,
    "trainer.limit_predict_batches": NonNegative,
    "trainer.num_nodes": Range(low=1),
    "trainer.checkpoint_every_n_steps": Range(low=1),
    "checkpoint.save_top_k": Range(low=-1),
    "checkpoint.every_n_epochs": NonNegative,
    "checkpoint.every_n_train_steps": NonNegative,
}


#: occplug's own ``trainer.*`` keys, which are not ``lightning.Trainer`` arguments (the runner takes them out
#: before building the Trainer): name -> annotation.
TRAINER_EXTRAS: dict[str, Any] = {"checkpoint_every_n_steps": int | None}


def _check_run_number(key: str, value: Any) -> None:
    rule = RUN_CONSTRAINTS.get(key)
    if rule is None or value is None or isinstance(value, bool):
        return
    values = value if isinstance(value, (list, tuple)) else [value]
    for item in values:
        if isinstance(item, (int, float)) and not rule.holds(item):
            kind = "an int" if isinstance(item, int) else "a number"
            every = "every element " if isinstance(value, (list, tuple)) else ""
            raise ConfigError(f"{key}: expected {every}{kind} {rule.describe()}, got {_describe(value)}")


def _validate_kwargs(
    value: Any, section: str, target: Any, skip: set[str], extras: dict[str, Any] | None = None
) -> None:
    if not isinstance(value, dict):
        raise ConfigError(f"{section}: expected a mapping, got {_describe(value)}")
    params = {k: v for k, v in component_params(target).items() if k not in skip}
    params.update({k: (None, annotation) for k, annotation in (extras or {}).items()})
    for key, val in value.items():
        if key not in params:
            hint = closest(str(key), list(params))
            raise ConfigError(
                f"{section}.{key}: unknown {section} argument{f'; did you mean {hint!r}?' if hint else ''}"
            )
        if not check_type(val, params[key][1]):
            raise ConfigError(f"{section}.{key}: expected {_type_name(params[key][1])}, got {_describe(val)}")
        if (problem := out_of_range(val)) is not None:
            raise ConfigError(f"{section}.{key}: expected {problem}, got {_describe(val)}")
        _check_run_number(f"{section}.{key}", val)


def _validate_named_choice(value: Any, section: str, choices: tuple[str, ...]) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ConfigError(f"{section}: expected a mapping with 'type:', got {_describe(value)}")
    kind = value.get("type")
    if kind not in choices:
        hint = closest(str(kind), list(choices))
        raise ConfigError(
            f"{section}.type: unknown {section} {kind!r}{f'; did you mean {hint!r}?' if hint else ''}; available: {', '.join(choices)}"
        )
    return {k: v for k, v in value.items() if k != "type"}


def validate(config: dict[str, Any], registry: Registry) -> list[UsedComponent]:
    """Validate a resolved config; raise :class:`ConfigError` at the first problem.

    Required top-level sections: ``data`` and ``model``.

    Returns:
        every component node of the config, in the order met (checkpoints record them, so a
        missing plugin is named before anything is rebuilt).
    """
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint

    from occplug.metrics.base import EvalMask
    from occplug.optim import (
        OPTIMIZER_EXTRAS,
        check_param_groups,
        optimizer_class,
        optimizer_names,
        scheduler_factory,
    )

    eval_masks = typing.get_args(EvalMask)

    if not isinstance(config, dict):
        raise ConfigError("a config must be a mapping")
    if config.get("phases") is not None:
        return _validate_phases(config, registry)
    for key in config:
        if key not in TOP_LEVEL:
            hint = closest(str(key), list(TOP_LEVEL))
            raise ConfigError(
                f"{key}: unknown top-level section{f'; did you mean {hint!r}?' if hint else ''} "
                f"(sections: {', '.join(TOP_LEVEL)})"
            )
    for required in ("data", "model"):
        if required not in config:
            raise ConfigError(f"{required}: missing section (every config needs 'data:' and 'model:')")
    v = _Validator(registry, _class_count(config.get("data"), registry))
    if "seed" in config and not check_type(config["seed"], int):
        raise ConfigError(f"seed: expected int, got {_describe(config['seed'])}")
    if "seed" in config and not SEED_RANGE[0] <= config["seed"] <= SEED_RANGE[1]:
        raise ConfigError(
            f"seed: expected an int in [0, 2**32 - 1] (what NumPy seeds), got {_describe(config['seed'])}"
        )
    if "grid" in config:
        _validate_grid(config["grid"])
    if config.get("init_from") is not None:
        from .phases import parse_init_from

        parse_init_from(config["init_from"], None, "init_from")
    for section, slot in TOP_LEVEL.items():
        if isinstance(slot, Slot) and section in config:
            v.slot(config[section], slot, section)
    if config.get("eval_mask") is not None and config["eval_mask"] not in eval_masks:
        hint = closest(str(config["eval_mask"]), list(eval_masks))
        raise ConfigError(
            f"eval_mask: unknown mask {config['eval_mask']!r}{f'; did you mean {hint!r}?' if hint else ''} "
            f"(one of: {', '.join(eval_masks)})"
        )
    if config.get("optimizer") is not None:
        args = _validate_named_choice(config["optimizer"], "optimizer", optimizer_names())
        _validate_lr_scaling(args)
        check_param_groups(config["optimizer"])
        args = {k: v for k, v in args.items() if k not in OPTIMIZER_EXTRAS}
        _validate_kwargs(args, "optimizer", optimizer_class(config["optimizer"]["type"]), {"params"})
    if config.get("scheduler") is not None:
        args = _validate_named_choice(config["scheduler"], "scheduler", SCHEDULERS)
        _validate_kwargs(
            args, "scheduler", scheduler_factory(config["scheduler"]["type"]), {"optimizer", "total_steps"}
        )
    if config.get("trainer") is not None:
        trainer = config["trainer"]
        if isinstance(trainer, dict) and "loggers" in trainer:  # occplug's own key, not a Trainer argument
            check_loggers(trainer["loggers"], check_type=check_type)
            trainer = {k: v for k, v in trainer.items() if k != "loggers"}
        _validate_kwargs(trainer, "trainer", L.Trainer, {"callbacks", "logger", "default_root_dir"}, TRAINER_EXTRAS)
    if config.get("checkpoint") is not None:
        _validate_kwargs(config["checkpoint"], "checkpoint", ModelCheckpoint, {"dirpath"})
    if isinstance(config["model"], dict):  # query supervision on a head that cannot answer it
        from occplug.queries import check_query_config

        check_query_config(config["model"], registry)
    _check_stateful_needs_sequential(config, v.used, registry)
    return v.used


def _class_count(data: Any, registry: Registry) -> int | None:
    """How many classes the data node's module declares (a ``class_names`` class attribute), or None."""
    if not isinstance(data, dict) or not isinstance(data.get("type"), str):
        return None
    try:
        names = getattr(registry.get("data", data["type"]).factory, "class_names", None)
    except LookupError:
        return None  # named by the walk, with a suggestion
    return len(names) if isinstance(names, tuple) and names else None


def validate_component(node: Any, kind: str, key: str, registry: Registry) -> None:
    """Check one component node (``{type: ..., args...}``) of ``kind`` at config ``key``, as :func:`validate` does.

    Raises :class:`ConfigError` with the one-line message a whole config would get.
    """
    _Validator(registry).node(node, kind, key)


def _check_stateful_needs_sequential(config: dict[str, Any], used: list[UsedComponent], registry: Registry) -> None:
    """A component declaring ``stateful = True`` needs ``data.sequential`` (as ``fit`` checks on the built model)."""
    data = config.get("data")
    if not isinstance(data, dict) or data.get("sequential"):
        return
    for u in used:
        if u.path.startswith("model") and getattr(registry.get(u.kind, u.type).factory, "stateful", False):
            raise ConfigError(
                f"data.sequential: {u.path} ({u.type}) is stateful (it carries features from frame to frame) and needs "
                "data.sequential: true"
            )


def _validate_phases(config: dict[str, Any], registry: Registry) -> list[UsedComponent]:
    """Validate the run's config without its phases, then each phase's config (errors name the phase)."""
    from .phases import phase_specs

    used = validate({k: v for k, v in config.items() if k != "phases"}, registry)
    for spec in phase_specs(config):
        try:
            validate(spec.config, registry)
        except ConfigError as exc:
            raise ConfigError(f"phases.{spec.name}: {exc}") from None
    return used


def _validate_lr_scaling(args: dict[str, Any]) -> None:
    scaling = args.get("lr_scaling", "none")
    if scaling not in ("none", "linear"):
        raise ConfigError(f"optimizer.lr_scaling: expected 'none' or 'linear', got {_describe(scaling)}")
    ref = args.get("reference_batch")
    if ref is not None and (not isinstance(ref, int) or isinstance(ref, bool) or ref < 1):
        raise ConfigError(
            f"optimizer.reference_batch: expected a positive int (the paper's total batch), got {_describe(ref)}"
        )
    if scaling == "linear" and ref is None:
        raise ConfigError(
            "optimizer.lr_scaling: 'linear' needs optimizer.reference_batch (the batch the lr was tuned for)"
        )
