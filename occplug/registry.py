"""The component registry, keyed by ``(kind, name)``."""

from __future__ import annotations

import difflib
import fnmatch
import inspect
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from .kinds import KINDS
from .settings import settings_arguments

__all__ = ["KINDS", "ComponentClashError", "Entry", "Registry", "UnknownComponentError"]

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


def closest(name: str, choices: list[str]) -> str | None:
    """The closest of ``choices`` to ``name`` (difflib), or None if nothing is close."""
    match = difflib.get_close_matches(name, choices, n=1, cutoff=0.6)
    return match[0] if match else None


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

    def build(self, kind: str, spec: Mapping[str, Any], **defaults: Any) -> Any:
        """Build a component from a config node ``{type: name, **kwargs}``.

        ``defaults`` are passed for parameters the factory accepts and the node does not set
        (the model uses this to fill ``in_channels`` from the previous component). The node is
        assumed validated (:mod:`occplug.config.validate`); this does no type checking. A mapping given to
        an argument annotated with a settings class (:func:`occplug.config.settings`) becomes that class.
        """
        spec = dict(spec)
        name = spec.pop("type", None)
        if name is None:
            raise ValueError(f"a {kind} node needs a 'type:' naming a registered {kind}")
        entry = self.get(kind, name)
        params = inspect.signature(entry.factory).parameters
        accepts_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
        for key, value in defaults.items():
            if key not in spec and (key in params or accepts_any):
                spec[key] = value
        return entry.factory(**settings_arguments(entry.factory, spec))


def _dist(distribution: str | None) -> str:
    return f" (distribution {distribution})" if distribution else ""
