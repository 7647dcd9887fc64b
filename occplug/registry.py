"""The component registry, keyed by ``(kind, name)``."""

from __future__ import annotations

import fnmatch
import inspect
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from .context import parse_grid
from .errors import ComponentArgumentError, closest
from .geometry import GridSpec
from .kinds import KINDS, given_arguments
from .settings import settings_arguments
from .slots import component_params

__all__ = [
    "KINDS",
    "ComponentArgumentError",
    "ComponentClashError",
    "Entry",
    "Registry",
    "UnknownComponentError",
]


class UnknownComponentError(LookupError):
    """No component of that kind has that name."""


class ComponentClashError(RuntimeError):
    """Two plugins registered the same ``(kind, name)``."""


@dataclass(frozen=True)
class Entry:
    """A registered component.

    Attributes:
        kind: one of :data:`KINDS`.
        name: the registry name a config's ``type:`` refers to.
        factory: a class (or function) called with the node's arguments.
        plugin: name of the plugin that registered it (``occplug`` for the core).
        distribution: installed distribution providing that plugin, if known.
    """

    kind: str
    name: str
    factory: Callable[..., Any]
    plugin: str
    distribution: str | None = None

    @property
    def summary(self) -> str:
        """First line of the factory's docstring."""
        doc = inspect.getdoc(self.factory) or ""
        return doc.strip().splitlines()[0] if doc.strip() else ""

    @property
    def source(self) -> str:
        """``module:qualname`` of the factory, so a reader finds its code."""
        return f"{self.factory.__module__}:{getattr(self.factory, '__qualname__', self.factory)}"


class Registry:
    """One registry for every component kind. Plugins fill it through ``occplug_register_components``.

    The plugin manager sets :attr:`current_plugin` while a plugin's hook runs, so each
    :class:`Entry` records who registered it.
    """

    def __init__(self) -> None:
        self._entries: dict[tuple[str, str], Entry] = {}
        self.current_plugin: str = "occplug"
        self.current_distribution: str | None = None
        #: ``{plugin name: what went wrong}`` of the plugins that failed to load (set by :mod:`occplug.plugins`);
        #: an unknown name mentions them, since the missing component may be theirs.
        self.broken_plugins: dict[str, str] = {}

    def add(self, kind: str, name: str, factory: Callable[..., Any]) -> None:
        """Register ``factory`` as ``name`` of ``kind``.

        A class must subclass its kind's interface (:data:`occplug.kinds.KINDS`); a factory
        function is checked when it builds.

        Raises:
            ValueError: unknown kind, a name that is not snake_case, or a class that does not
                subclass its kind's interface.
            ComponentClashError: the name is taken in that kind (the message names both plugins).
        """
        if kind not in KINDS:
            raise ValueError(f"unknown component kind '{kind}'; kinds are: {', '.join(KINDS)}")
        if inspect.isclass(factory):
            base = KINDS[kind].interface()
            if not issubclass(factory, base):
                raise ValueError(
                    f"{kind} '{name}' (plugin {self.current_plugin}): {factory.__module__}.{factory.__qualname__} "
                    f"must subclass {base.__module__}.{base.__qualname__}"
                )
        if not name or not name.replace("_", "a").isalnum() or name.lower() != name:
            raise ValueError(f"component name '{name}' must be snake_case (lowercase letters, digits, _)")
        key = (kind, name)
        if key in self._entries:
            other = self._entries[key]
            raise ComponentClashError(
                f"{kind} '{name}' is registered by both plugin '{other.plugin}'"
                f"{_dist(other.distribution)} and plugin '{self.current_plugin}'"
                f"{_dist(self.current_distribution)}; uninstall one of them or block it with "
                f"OCCPLUG_DISABLE_PLUGINS={self.current_plugin}"
            )
        self._entries[key] = Entry(kind, name, factory, self.current_plugin, self.current_distribution)

    def has(self, kind: str, name: str) -> bool:
        """Whether ``name`` is registered under ``kind``."""
        return (kind, name) in self._entries

    def get(self, kind: str, name: str) -> Entry:
        """The entry of ``(kind, name)``.

        Raises:
            UnknownComponentError: listing the available names of ``kind`` and the closest one.
        """
        entry = self._entries.get((kind, name))
        if entry is not None:
            return entry
        if kind not in KINDS:
            raise UnknownComponentError(f"unknown component kind '{kind}'; kinds are: {', '.join(KINDS)}")
        names = self.names(kind)
        hint = closest(str(name), names)
        broken = "".join(f" (plugin '{p}' {why})" for p, why in self.broken_plugins.items())
        parts = [f"no {kind} named '{name}'{broken}"]
        if hint:
            parts.append(f"did you mean '{hint}'?")
        parts.append(f"available: {', '.join(names) if names else '(none)'}")
        raise UnknownComponentError("; ".join(parts))

    def __contains__(self, key: tuple[str, str]) -> bool:
        return key in self._entries

    def names(self, kind: str, pattern: str = "*") -> list[str]:
        """Sorted names registered under ``kind`` matching the fnmatch ``pattern``."""
        return sorted(n for (k, n) in self._entries if k == kind and fnmatch.fnmatch(n, pattern))

    def entries(self, kind: str | None = None) -> Iterator[Entry]:
        """All entries (of one kind), sorted by kind then name."""
        for key in sorted(self._entries, key=lambda kn: (list(KINDS).index(kn[0]), kn[1])):
            if kind is None or key[0] == kind:
                yield self._entries[key]

    def build(self, kind: str, spec: Mapping[str, Any] | str, /, **given: Any) -> Any:
        """Build a component from its config node ``{type: name, **arguments}`` (or the bare name): the one way
        the core and its plugins build a component.

        ``given`` are the values the parent passes (the kind's ``given``: ``in_channels`` from the previous
        component, the run's ``grid``, ``context``, ...); each fills a constructor parameter the node leaves
        out, where the factory takes it. Before calling the factory the builder turns a mapping given to a
        settings argument (:func:`occplug.config.settings`) into that class and a mapping given to a
        ``GridSpec`` argument into a :class:`~occplug.geometry.GridSpec` (the one place a config's grid is
        parsed, so a component always receives a ``GridSpec``). A factory that declares a ``registry``
        parameter (a data module, which builds its label sources and transforms) receives this registry.
        The node's values are assumed validated
        (:mod:`occplug.config.validate`) and are not type-checked here.

        Raises:
            UnknownComponentError: no ``kind`` named ``type``.
            ComponentArgumentError: the node sets an argument the factory does not take (naming the closest),
                or the factory needs a given argument the parent does not pass.
            TypeError: the factory built an object that is not its kind's interface.
        """
        node = {"type": spec} if isinstance(spec, str) else dict(spec)
        name = node.pop("type", None)
        if name is None:
            raise ValueError(f"a {kind} node needs a 'type:' naming a registered {kind}")
        entry = self.get(kind, name)
        params = component_params(entry.factory)
        if not _takes_any(entry.factory):
            for key in node:
                if key not in params:
                    hint = closest(str(key), list(params))
                    raise ComponentArgumentError(
                        f"unknown argument of {kind} '{name}'{f'; did you mean {hint!r}?' if hint else ''} "
                        f"(valid: {', '.join(params)})",
                        key=str(key),
                    )
        own = inspect.signature(entry.factory).parameters
        accepts_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in own.values())
        if "registry" in own and "registry" not in given:  # a factory that builds nested nodes itself (a data module)
            given = {**given, "registry": self}
        for key, value in given.items():
            if key not in node and (key in own or accepts_any):
                node[key] = value
        not_passed = [
            arg
            for arg, (param, _) in params.items()
            if param.default is inspect.Parameter.empty
            and arg not in node
            and arg in given_arguments(kind, entry.factory)
        ]
        if not_passed:
            raise ComponentArgumentError(
                f"{kind} '{entry.name}' (plugin {entry.plugin}) expects its parent to give '{not_passed[0]}', which "
                f"this model does not pass (it passes: {', '.join(sorted(given)) or 'nothing'}); set it in the config",
                key=not_passed[0],
            )
        obj = entry.factory(**_grid_arguments(params, settings_arguments(entry.factory, node)))
        base = KINDS[kind].interface() if kind in KINDS else None
        if base is not None and not isinstance(obj, base):
            raise TypeError(
                f"{kind} '{entry.name}' (plugin {entry.plugin}) built a {type(obj).__name__}, not a {base.__name__}"
            )
        return obj


def _takes_any(factory: Callable[..., Any]) -> bool:
    """Whether ``factory`` takes any keyword: its ``**kwargs`` reach no constructor that names its arguments."""
    owners = [c for c in factory.__mro__ if "__init__" in vars(c)] if inspect.isclass(factory) else [factory]
    for owner in owners:
        try:
            params = inspect.signature(owner.__init__ if inspect.isclass(owner) else owner).parameters
        except (TypeError, ValueError):
            return True
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
            return False
    return True


def _takes_grid_only(annotation: Any) -> bool:
    """Whether ``annotation`` takes a :class:`GridSpec` and no mapping (``GridSpec``, ``GridSpec | None``): a
    parameter the builder gives a parsed grid. One that also takes a ``dict`` keeps what the config wrote."""
    if isinstance(annotation, str):  # an annotation the type hints could not resolve
        return "GridSpec" in annotation and "dict" not in annotation and "Mapping" not in annotation
    args = typing.get_args(annotation) if typing.get_origin(annotation) in (typing.Union, types.UnionType) else ()
    if args:
        plain = [typing.get_origin(a) or a for a in args]
        return GridSpec in plain and not any(a in (dict, Mapping) for a in plain)
    return annotation is GridSpec


def _grid_arguments(params: Mapping[str, tuple[inspect.Parameter, Any]], arguments: dict[str, Any]) -> dict[str, Any]:
    """``arguments`` with the config form of a grid (``{range, voxel_size}``) given to a ``GridSpec`` parameter
    made into a :class:`GridSpec`."""
    for key, value in arguments.items():
        if key in params and isinstance(value, (Mapping, list, tuple)) and _takes_grid_only(params[key][1]):
            arguments[key] = parse_grid(value)
    return arguments


def _dist(distribution: str | None) -> str:
    return f" (distribution {distribution})" if distribution else ""
