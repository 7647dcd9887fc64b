"""Where components sit in a config: the top-level schema and ``Slot`` annotations.

A component's constructor declares a nested component with
``encoder: Annotated[dict, Slot("encoder")]`` (one node) or
``heads: Annotated[dict, Slot("head", mapping=True)]`` (a named mapping of nodes), so the
validator and the builder know which kind to look a nested ``type:`` up in.
"""

from __future__ import annotations

import inspect
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["BUILDER_ARGUMENTS", "TOP_LEVEL", "Slot", "component_params", "slot_of", "slot_at"]

#: Constructor parameters the builder hands in and a config never sets: the run context
#: (:class:`occplug.context.RunContext`) and, for a data module, the registry its nested nodes are built from.
BUILDER_ARGUMENTS: tuple[str, ...] = ("context", "registry")


@dataclass(frozen=True)
class Slot:
    """Marks a constructor parameter as a nested component node (or mapping/list of nodes)."""

    kind: str
    mapping: bool = False
    sequence: bool = False


#: Top-level sections: name -> Slot for component sections, or a description for plain ones.
TOP_LEVEL: dict[str, Slot | str] = {
    "seed": "int: global random seed",
    "grid": "mapping {range, voxel_size}: the label/evaluation grid, given to every component that takes a grid",
    "data": Slot("data"),
    "model": Slot("model"),
    "optimizer": "mapping {type: adamw|adam|sgd, lr, ..., reference_batch, lr_scaling: none|linear}",
    "scheduler": "mapping {type: none|cosine|step, ...}",
    "trainer": "mapping of lightning.Trainer arguments",
    "metrics": Slot("metric", sequence=True),
    "eval_mask": "none|camera|lidar|camera_and_lidar: voxels every masked metric evaluates (default: the data set's)",
    "checkpoint": "mapping of lightning ModelCheckpoint arguments",
    "callbacks": Slot("callback", mapping=True),
    "init_from": "list of {file, map, strict}: weights loaded from state-dict files before fit; occplug.run.weights",
    "phases": "mapping phase name -> overlay of this config (+ freeze, init_from, pseudo_labels_from); occplug.config.phases",
}


_STARRED = (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)


def _hints(factory: Callable[..., Any]) -> dict[str, Any]:
    target = factory.__init__ if inspect.isclass(factory) else factory
    try:
        return typing.get_type_hints(target, include_extras=True)
    except Exception:
        return {}


def component_params(factory: Callable[..., Any]) -> dict[str, tuple[inspect.Parameter, Any]]:
    """Constructor parameters of a factory (minus ``self``/``*args``/``**kwargs``) with resolved annotations.

    A class whose ``__init__`` takes ``**kwargs`` and hands them to its base (a plugin's subclass of
    ``occ_model`` adding one argument) also accepts the base's parameters, found along the MRO. The
    :data:`BUILDER_ARGUMENTS` are left out: no config sets them.
    """
    out: dict[str, tuple[inspect.Parameter, Any]] = {}
    owners = [c for c in factory.__mro__ if "__init__" in vars(c)] if inspect.isclass(factory) else [factory]
    for owner in owners:
        target = owner.__init__ if inspect.isclass(owner) else owner
        try:
            params = inspect.signature(target).parameters
        except (TypeError, ValueError):
            break
        hints = _hints(owner)
        for name, p in params.items():
            if name == "self" or name in BUILDER_ARGUMENTS or p.kind in _STARRED:
                continue
            out.setdefault(name, (p, hints.get(name, p.annotation)))
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            break
    return out


def slot_of(annotation: Any) -> Slot | None:
    """The :class:`Slot` in an ``Annotated[...]`` annotation, if any (also inside ``X | None``)."""
    if typing.get_origin(annotation) is typing.Annotated:
        for meta in annotation.__metadata__:
            if isinstance(meta, Slot):
                return meta
    for arg in typing.get_args(annotation):
        found = slot_of(arg) if arg is not type(None) else None
        if found is not None:
            return found
    return None


def slot_at(root: dict, path: Sequence[str], registry: Any) -> Slot | None:
    """The slot of the component node at ``path`` in a plain-dict config, or None if it is not one.

    ``path`` addresses one component node, e.g. ``("model", "heads", "occupancy")``.
    """
    if not path:
        return None
    top = TOP_LEVEL.get(path[0])
    if not isinstance(top, Slot):
        return None

    def walk(node: Any, slot: Slot, rest: Sequence[str]) -> Slot | None:
        if slot.mapping or slot.sequence:
            if not rest:
                return None
            node, rest = _child(node, rest[0]), rest[1:]
        if not rest:
            return slot
        if not isinstance(node, dict) or "type" not in node:
            return None
        try:
            entry = registry.get(slot.kind, node["type"])
        except LookupError:
            return None
        params = component_params(entry.factory)
        if rest[0] not in params:
            return None
        nested = slot_of(params[rest[0]][1])
        return None if nested is None else walk(node.get(rest[0]), nested, rest[1:])

    return walk(root.get(path[0]), top, list(path[1:]))


def _child(node: Any, key: str) -> Any:
    if isinstance(node, dict):
        return node.get(key)
    if isinstance(node, list) and key.isdigit() and int(key) < len(node):
        return node[int(key)]
    return None
