"""Which supervision can query which head: the check behind one-line config errors.

Heads declare :attr:`~occplug.interfaces.Head.queryable` and :attr:`~occplug.interfaces.Head.temporal`;
supervision sources declare :attr:`~occplug.interfaces.SupervisionSource.query_head` and
:attr:`~occplug.interfaces.SupervisionSource.needs_temporal_queries`. An impossible pairing (queries on a
head that cannot answer them, or at ``t != 0`` on a head that is not temporal) is a
:class:`~occplug.config.errors.ConfigError` naming both config keys, raised before anything is written:
from the config alone (:func:`check_query_config`, part of config validation) and again from the built
components (:func:`check_query_support`, at the end of building the model).
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any

from occplug.errors import ConfigError

__all__ = ["check_query_config", "check_query_support", "registered_types"]


def check_query_support(
    heads: Mapping[str, Any], supervision: Mapping[str, Any], types: Mapping[str, str] | None = None
) -> None:
    """Raise :class:`ConfigError` (one line) if a supervision source queries a head that cannot answer.

    The message names both components by their registered ``type:`` where ``types`` gives it (a mix of two
    plugins' components reads as the config that wrote it), else by class.

    Args:
        heads: ``{config name: head}`` (instances, or classes when checking a config before building).
        supervision: ``{config name: source}`` (instances or classes; read: ``query_head``,
            ``needs_temporal_queries``).
        types: ``{"heads.<name>" | "supervision.<name>": registered type}`` of the components, where known.
    """
    types = types or {}

    def label(key: str, component: Any) -> str:
        return types.get(key) or _name(component)

    for name, source in supervision.items():
        target = getattr(source, "query_head", None)
        if target is None:
            continue
        what = f"model.supervision.{name} ({label(f'supervision.{name}', source)})"
        if target not in heads:
            raise ConfigError(
                f"{what}: queries head '{target}' but model.heads has no such head (heads: {', '.join(heads) or '(none)'})"
            )
        head = heads[target]
        if not getattr(head, "queryable", False):
            raise ConfigError(
                f"{what}: queries model.heads.{target}, but {label(f'heads.{target}', head)} cannot be queried at "
                "points (queryable = False)"
            )
        if getattr(source, "needs_temporal_queries", False) and not getattr(head, "temporal", False):
            raise ConfigError(
                f"{what}: queries at times t != 0, but model.heads.{target} ({label(f'heads.{target}', head)}) is not "
                "temporal "
                f"(it answers the current frame only)"
            )


def check_query_config(model: Mapping[str, Any], registry: Any) -> None:
    """:func:`check_query_support` on a validated ``model`` config node, without building anything.

    Heads are checked through their registered classes' attributes; a source's ``query_head`` is its
    node's ``query_head`` argument (else the constructor's default) and ``needs_temporal_queries`` its
    class attribute. Components registered as plain functions are left to the build-time check.
    """
    heads_node, sup_node = model.get("heads"), model.get("supervision")
    if not isinstance(heads_node, Mapping) or not isinstance(sup_node, Mapping):
        return
    heads = {name: _factory(registry, "head", node) for name, node in heads_node.items() if node is not None}
    sources: dict[str, Any] = {}
    for name, node in sup_node.items():
        factory = None if node is None else _factory(registry, "supervision", node)
        if factory is None:
            continue
        target = node.get("query_head", _default(factory, "query_head", getattr(factory, "query_head", None)))
        sources[name] = _Declared(factory.__name__, target, bool(getattr(factory, "needs_temporal_queries", False)))
    if any(h is None for h in heads.values()):  # a head we cannot inspect: only check the names it answers to
        heads = {n: h if h is not None else _Declared("?", None, True, queryable=True) for n, h in heads.items()}
    check_query_support(heads, sources, registered_types(model))


def registered_types(model: Mapping[str, Any]) -> dict[str, str]:
    """``{"heads.<name>" | "supervision.<name>": type}`` of a ``model`` config node's heads and supervision sources."""
    out: dict[str, str] = {}
    for section in ("heads", "supervision"):
        node = model.get(section)
        if isinstance(node, Mapping):
            for name, spec in node.items():
                if isinstance(spec, Mapping) and "type" in spec:
                    out[f"{section}.{name}"] = str(spec["type"])
    return out


class _Declared:
    """A component's declarations read from its class and config node."""

    def __init__(self, name: str, query_head: str | None, needs_temporal: bool, queryable: bool = False) -> None:
        self.name, self.query_head, self.needs_temporal_queries = name, query_head, needs_temporal
        self.queryable = self.temporal = queryable


def _name(component: Any) -> str:
    if isinstance(component, _Declared):
        return component.name
    return component.__name__ if inspect.isclass(component) else type(component).__name__


def _factory(registry: Any, kind: str, node: Any) -> Any:
    if not isinstance(node, Mapping) or "type" not in node:
        return None
    factory = registry.get(kind, str(node["type"])).factory
    return factory if inspect.isclass(factory) else None


def _default(factory: Any, param: str, fallback: Any) -> Any:
    try:
        p = inspect.signature(factory).parameters.get(param)
    except (TypeError, ValueError):
        return fallback
    return fallback if p is None or p.default is inspect.Parameter.empty else p.default
