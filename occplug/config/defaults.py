"""Every argument with its default: the run's fully resolved config, ``config show --defaults``, ``plugins --kind``.

:func:`with_defaults` fills every argument a component node leaves out with its constructor's default, down
through nested components (slots) and groups of settings, so a run's ``config.yaml`` says what was run even
after a default changes. Arguments the parent gives (a kind's ``given``: ``in_channels``, ``grid``,
``num_classes``, ...) are left out: the parent fills them at build time, and writing their defaults would
override what it passes. An optional nested component whose default is ``None`` is left out too (the
component decides what ``None`` means), and so is a default that is not plain data.

:func:`arguments` lists a factory's arguments (name, type, default, rule) for ``occplug plugins --kind`` and
:func:`annotated_yaml` prints a config with one comment per argument for ``occplug config show --defaults``.
"""

from __future__ import annotations

import copy
import dataclasses
import enum
import inspect
import json
from dataclasses import dataclass
from typing import Any

from occplug.constraints import describe_rules
from occplug.kinds import given_arguments
from occplug.registry import Registry
from occplug.settings import is_settings, settings_type
from occplug.slots import TOP_LEVEL, Slot, component_params, slot_of

from .yamlio import dump_yaml, styled

__all__ = ["Argument", "annotated_yaml", "arguments", "run_config_text", "with_defaults"]


class _Missing(enum.Enum):
    REQUIRED = "required"
    UNREPRESENTABLE = "not plain data"


@dataclass(frozen=True)
class Argument:
    """One constructor argument (or setting) as a config sees it.

    Attributes:
        name: the config key.
        type: the type in words, as validation names it (``int``, ``float or null``, ``an encoder node``).
        default: the default as plain data; :attr:`required` / :attr:`representable` tell the other cases.
        rule: the declared constraints in words (``> 0``, ``every element in [0, 1]``), or ``""``.
        given: the parent passes it (a kind's ``given``); a config need not set it.
        slot: the nested component kind's slot, or None.
        group: the settings class of a group of settings, or None.
    """

    name: str
    type: str
    default: Any
    rule: str
    given: bool
    slot: Slot | None
    group: type | None

    @property
    def required(self) -> bool:
        return self.default is _Missing.REQUIRED

    @property
    def representable(self) -> bool:
        return not isinstance(self.default, _Missing)

    def describe(self) -> str:
        """``int > 0; default 32`` (or ``; required``, ``; given by its parent``)."""
        joint = " " if self.rule[:1] in "<>" or self.rule.startswith("in ") else ", "
        what = f"{self.type}{joint}{self.rule}" if self.rule else self.type
        if self.given:
            return f"{what}; given by its parent"
        if self.required:
            return f"{what}; required"
        if not self.representable:
            return f"{what}; default not plain data"
        return f"{what}; default {_show(self.default)}"


def _show(value: Any) -> str:
    """A default as a config would write it: ``null``, ``true``, ``0.001``, ``fast``, ``[1.0, 45.0, 1.0]``."""
    if isinstance(value, str):
        return value if value and value.strip() == value else repr(value)
    return json.dumps(value)


def _plain_default(value: Any) -> Any:
    """A default as plain config data, or ``_Missing.UNREPRESENTABLE``."""
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else _Missing.UNREPRESENTABLE
    if isinstance(value, (list, tuple)):
        items = [_plain_default(v) for v in value]
        return _Missing.UNREPRESENTABLE if any(isinstance(i, _Missing) for i in items) else items
    if isinstance(value, dict) and all(isinstance(k, str) for k in value):
        items = {k: _plain_default(v) for k, v in value.items()}
        return _Missing.UNREPRESENTABLE if any(isinstance(i, _Missing) for i in items.values()) else items
    if dataclasses.is_dataclass(value) and not isinstance(value, type) and is_settings(type(value)):
        return _plain_default({f.name: getattr(value, f.name) for f in dataclasses.fields(value)})
    return _Missing.UNREPRESENTABLE


def _default(owner: Any, name: str, param: inspect.Parameter) -> Any:
    if is_settings(owner):  # a dataclass field may hold a default_factory
        field = {f.name: f for f in dataclasses.fields(owner)}.get(name)
        if field is not None and field.default_factory is not dataclasses.MISSING:
            return _plain_default(field.default_factory())
    if param.default is inspect.Parameter.empty:
        return _Missing.REQUIRED
    return _plain_default(param.default)


def arguments(factory: Any, kind: str | None = None) -> list[Argument]:
    """The arguments of a component factory (or a settings class), in signature order."""
    from .validate import _type_name

    given = given_arguments(kind, factory) if kind is not None else set()
    out = []
    for name, (param, annotation) in component_params(factory).items():
        slot = slot_of(annotation)
        if slot is None:
            type_name = _type_name(annotation)
        else:
            type_name = f"{slot.kind} node" + (" mapping" if slot.mapping else "s" if slot.sequence else "")
        out.append(
            Argument(
                name=name,
                type=type_name,
                default=_default(factory, name, param),
                rule=describe_rules(annotation),
                given=name in given,
                slot=slot,
                group=settings_type(annotation),
            )
        )
    return out


def _fill_slot(value: Any, slot: Slot, registry: Registry) -> Any:
    if slot.mapping and isinstance(value, dict):
        return {k: None if v is None else _fill_node(v, slot.kind, registry) for k, v in value.items()}
    if slot.sequence and isinstance(value, list):
        return [_fill_node(v, slot.kind, registry) for v in value]
    return value if slot.mapping or slot.sequence else _fill_node(value, slot.kind, registry)


def _fill_node(node: Any, kind: str, registry: Registry) -> Any:
    if isinstance(node, str) and kind == "metric":  # the metric shorthand `- occ3d_miou`
        node = {"type": node}
    if not isinstance(node, dict) or "type" not in node:
        return node
    try:
        factory = registry.get(kind, str(node["type"])).factory
    except LookupError:
        return node
    return {"type": node["type"], **_fill_arguments(node, factory, kind, registry)}


def _fill_arguments(node: dict[str, Any], factory: Any, kind: str | None, registry: Registry) -> dict[str, Any]:
    out: dict[str, Any] = {}
    args = arguments(factory, kind)
    for arg in args:
        if arg.name in node:
            value = node[arg.name]
            if arg.slot is not None:
                value = _fill_slot(value, arg.slot, registry)
            elif arg.group is not None and isinstance(value, dict):
                value = _fill_arguments(value, arg.group, None, registry)
            out[arg.name] = value
        elif not arg.given and arg.representable and not arg.required:
            if arg.slot is not None and arg.default is None:
                continue  # an optional nested component left unset: its owner decides what None means
            value = copy.deepcopy(arg.default)
            if arg.slot is not None:
                value = _fill_slot(value, arg.slot, registry)
            elif arg.group is not None and isinstance(value, dict):
                value = _fill_arguments(value, arg.group, None, registry)
            out[arg.name] = value
    out.update({k: v for k, v in node.items() if k != "type" and k not in out})  # unknown keys: validation names them
    return out


def with_defaults(config: dict[str, Any], registry: Registry) -> dict[str, Any]:
    """``config`` (resolved, validated) with every component's omitted arguments set to their defaults; a new
    dict, key order: each node's ``type``, then its arguments in signature order.

    A config with ``phases`` is returned as it is: a phase's overlay may change a component's ``type``, and
    the old type's defaults would not fit the new one (each phase's own ``config.yaml`` holds its defaults).
    """
    if config.get("phases") is not None:
        return copy.deepcopy(config)
    out = copy.deepcopy(config)
    for section, slot in TOP_LEVEL.items():
        if isinstance(slot, Slot) and section in out:
            out[section] = _fill_slot(out[section], slot, registry)
    return out


def run_config_text(config: dict[str, Any], registry: Registry | None = None) -> str:
    """The text of a run's ``config.yaml``: a header line, then :func:`with_defaults` as YAML 1.2."""
    from occplug.plugins import get_registry

    header = (
        "# resolved occplug config, every component argument with its default; plugins and versions in plugins.json\n"
    )
    return header + dump_yaml(with_defaults(config, registry or get_registry()))


def annotated_yaml(config: dict[str, Any], registry: Registry) -> str:
    """:func:`with_defaults` as YAML with a comment on every component argument: its type, rule and default
    (``out_channels: 64  # int > 0; default 32``), and on each node's ``type`` line the arguments its parent
    gives."""

    def annotate(node: Any, kind: str | None, factory: Any) -> None:
        args = {a.name: a for a in arguments(factory, kind)}
        if kind is not None:
            given = [a.name for a in args.values() if a.given and a.name not in node]
            note = f"{kind}" + (f"; given by its parent: {', '.join(given)}" if given else "")
            node.yaml_add_eol_comment(note, "type")
        for key, arg in args.items():
            if key not in node:
                continue
            node.yaml_add_eol_comment(arg.describe(), key)
            value = node[key]
            if arg.slot is not None:
                walk_slot(value, arg.slot)
            elif arg.group is not None and isinstance(value, dict):
                annotate(value, None, arg.group)

    def walk_slot(value: Any, slot: Slot) -> None:
        nodes = (
            list(value.values())
            if slot.mapping and isinstance(value, dict)
            else list(value)
            if slot.sequence and isinstance(value, list)
            else [value]
        )
        for sub in nodes:
            if isinstance(sub, dict) and "type" in sub:
                try:
                    factory = registry.get(slot.kind, str(sub["type"])).factory
                except LookupError:
                    continue
                annotate(sub, slot.kind, factory)

    data = styled(with_defaults(config, registry))
    for section, slot in TOP_LEVEL.items():
        if isinstance(slot, Slot) and section in data:
            walk_slot(data[section], slot)
    return dump_yaml(data)
