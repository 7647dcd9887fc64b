"""Plugin discovery: the built-in plugin plus every ``occplug`` entry point.

The built-in plugin is named, not imported (:data:`BUILTIN_MODULE`, as pytest's ``default_plugins``): it imports
the components it registers and those read the registry built here, so importing it from this module would close
a circle (plugins -> builtin -> model -> plugins).

Switches (environment variables, read when the plugin manager is first built):

* ``OCCPLUG_DISABLE_PLUGINS=a,b``: do not load these entry points.
* ``OCCPLUG_LOAD_PLUGINS=a,b``: load only these entry points (empty string: none).
* ``OCCPLUG_TRACE_PLUGINS=1``: print each hook call and its result to stderr.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import sys
import traceback
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import pluggy

from . import hookspecs
from .registry import ComponentClashError, Registry

__all__ = [
    "ENTRY_POINT_GROUP",
    "PluginLoadError",
    "PluginReport",
    "broken_plugins_warning",
    "config_dirs",
    "get_plugin_manager",
    "get_registry",
    "isolated",
    "plugin_reports",
    "reset",
]

ENTRY_POINT_GROUP = "occplug"
BUILTIN_NAME = "occplug"
#: The module of the core's own plugin, registered as :data:`BUILTIN_NAME` before any entry point.
BUILTIN_MODULE = "occplug.builtin"


@dataclass
class PluginReport:
    """What ``occplug plugins`` shows for one plugin."""

    name: str
    distribution: str | None
    version: str | None
    module: str | None
    error: str | None = None
    components: dict[str, list[str]] = field(default_factory=dict)
    #: What the plugin failed to do when :attr:`error` is set: ``import``, ``register`` (its hook raised), ...
    failed_to: str | None = None

    @property
    def problem(self) -> str | None:
        """One line, e.g. ``failed to import: ImportError: needs torch_scatter``; None for a working plugin."""
        if self.error is None:
            return None
        first = self.error.strip().splitlines()[0] if self.error.strip() else "unknown error"
        for prefix in ("registration failed: ", "occplug_config_dir failed: "):  # said by failed_to already
            first = first.removeprefix(prefix)
        return f"failed to {self.failed_to or 'load'}: {first}"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "name": self.name,
            "distribution": self.distribution,
            "version": self.version,
            "module": self.module,
            "error": self.error,
            "components": self.components,
        }


class PluginLoadError(RuntimeError):
    """A plugin could not be loaded (raised only where the plugin is actually needed)."""


@dataclass
class _State:
    pm: pluggy.PluginManager
    reports: dict[str, PluginReport]
    registry: Registry | None = None


_state: _State | None = None


def _env_list(name: str) -> list[str] | None:
    raw = os.environ.get(name)
    if raw is None:
        return None
    return [p.strip() for p in raw.split(",") if p.strip()]


def _entry_points() -> list[metadata.EntryPoint]:
    return sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda ep: ep.name)


def _build_manager(
    only: list[str] | None = None, extra: tuple[tuple[str, object], ...] = (), autoload: bool = True
) -> _State:
    pm = pluggy.PluginManager("occplug")
    pm.add_hookspecs(hookspecs)
    pm.register(importlib.import_module(BUILTIN_MODULE), name=BUILTIN_NAME)
    version = metadata.version("occplug") if _installed("occplug") else None
    reports = {BUILTIN_NAME: PluginReport(BUILTIN_NAME, "occplug", version, BUILTIN_MODULE)}
    disabled = set(_env_list("OCCPLUG_DISABLE_PLUGINS") or []) if autoload else set()
    if autoload:
        only = _env_list("OCCPLUG_LOAD_PLUGINS")
    for ep in _entry_points():
        if ep.name in disabled or (only is not None and ep.name not in only):
            continue
        dist = ep.dist.name if ep.dist is not None else None
        dist_version = ep.dist.version if ep.dist is not None else None
        report = PluginReport(ep.name, dist, dist_version, ep.value)
        reports[ep.name] = report
        if ep.name in pm.list_name_plugin() and pm.get_plugin(ep.name) is not None:
            report.error = f"the plugin name '{ep.name}' is already taken"
            report.failed_to = "load"
            continue
        try:
            module = ep.load()
            pm.register(module, name=ep.name)
        except Exception as exc:  # a broken plugin must not break the others
            report.error = f"{type(exc).__name__}: {exc}"
            report.failed_to = "import"
            if os.environ.get("OCCPLUG_TRACE_PLUGINS"):
                traceback.print_exc()
    if only is not None:
        missing = [n for n in only if n not in reports and not autoload]
        if missing:
            raise PluginLoadError(f"no installed entry point named {', '.join(missing)} in group '{ENTRY_POINT_GROUP}'")
    for name, obj in extra:
        pm.register(obj, name=name)
        reports[name] = PluginReport(name, None, None, getattr(obj, "__name__", type(obj).__name__))
    pm.check_pending()
    if os.environ.get("OCCPLUG_TRACE_PLUGINS"):
        pm.trace.root.setwriter(lambda msg: print(msg, end="", file=sys.stderr))
        pm.enable_tracing()
    return _State(pm, reports)


def _installed(dist: str) -> bool:
    try:
        metadata.distribution(dist)
    except metadata.PackageNotFoundError:
        return False
    return True


def _get_state() -> _State:
    global _state
    if _state is None:
        _state = _build_manager()
    return _state


def get_plugin_manager() -> pluggy.PluginManager:
    """The process-wide plugin manager (built on first use)."""
    return _get_state().pm


def get_registry() -> Registry:
    """The process-wide registry, filled by calling each plugin's hook in turn.

    A plugin whose registration hook raises is reported (``occplug plugins``) and skipped;
    a name clash between two plugins is an error (:class:`~occplug.registry.ComponentClashError`).
    """
    state = _get_state()
    if state.registry is None:
        state.registry = fill_registry(state.pm, state.reports)
    return state.registry


def fill_registry(pm: pluggy.PluginManager, reports: dict[str, PluginReport] | None = None) -> Registry:
    """Build a registry from every ``occplug_register_components`` implementation of ``pm``."""
    reports = reports if reports is not None else {}
    registry = Registry()
    for impl in pm.hook.occplug_register_components.get_hookimpls():  # registration order: built-ins first
        report = reports.get(impl.plugin_name)
        registry.current_plugin = impl.plugin_name
        registry.current_distribution = report.distribution if report else None
        try:
            impl.function(registry=registry)
        except ComponentClashError:
            raise
        except Exception as exc:
            if report is not None:
                report.error = f"registration failed: {type(exc).__name__}: {exc}"
                report.failed_to = "register"
            _drop_partial(registry, impl.plugin_name)
    registry.current_plugin = BUILTIN_NAME
    registry.current_distribution = None
    registry.broken_plugins = {r.name: r.problem for r in reports.values() if r.problem is not None}
    for entry in registry.entries():
        rep = reports.get(entry.plugin)
        if rep is not None:
            rep.components.setdefault(entry.kind, []).append(entry.name)
    return registry


def _drop_partial(registry: Registry, plugin: str) -> None:
    for key in [k for k, e in registry._entries.items() if e.plugin == plugin]:
        del registry._entries[key]


def plugin_reports() -> list[PluginReport]:
    """One report per plugin (built-in first), with its components or its load error."""
    get_registry()
    return list(_get_state().reports.values())


def broken_plugins_warning() -> str | None:
    """One ``warning:`` line naming every plugin that failed to load, or None when all loaded."""
    broken = [f"plugin '{r.name}' {r.problem}" for r in plugin_reports() if r.problem is not None]
    if not broken:
        return None
    return f"warning: {'; '.join(broken)} (its components are unavailable; `occplug plugins` shows details)"


def config_dirs() -> dict[str, Path]:
    """Config folders by plugin name (``occplug`` is the core's own ``occplug/configs``)."""
    pm = get_plugin_manager()
    dirs: dict[str, Path] = {}
    for impl in pm.hook.occplug_config_dir.get_hookimpls():
        try:
            folder = impl.function()
        except Exception as exc:  # reported like a load failure
            report = _get_state().reports.get(impl.plugin_name)
            if report is not None:
                report.error = f"occplug_config_dir failed: {type(exc).__name__}: {exc}"
                report.failed_to = "give its config folder"
            continue
        if folder is not None:
            dirs[impl.plugin_name] = Path(str(folder))
    return dirs


@contextlib.contextmanager
def isolated(entry_points: Sequence[str] = (), plugins: Sequence[tuple[str, object]] = ()) -> Iterator[Registry]:
    """Use only the built-ins, the named installed entry points and the given plugin objects.

    Inside the block the process-wide registry is the isolated one (so configs validate and
    build against it); the previous state comes back afterwards. Naming an entry point that is
    not installed raises :class:`PluginLoadError` (so a test also proves the entry point exists).
    """
    global _state
    saved = _state
    _state = _build_manager(only=list(entry_points), extra=tuple(plugins), autoload=False)
    try:
        yield get_registry()
    finally:
        _state = saved


def reset() -> None:
    """Forget the plugin manager and registry (tests; after installing a plugin in-process)."""
    global _state
    _state = None
