"""The occplug hook specifications: the whole contract between the core and a plugin.

A plugin is a module (found through the ``occplug`` entry-point group) with functions decorated
``@occplug.hookimpl`` whose names match the specs below. The core's own components register
through the same hooks (``occplug.builtin``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import pluggy

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable
    from pathlib import Path

    from occplug.registry import Registry

hookspec = pluggy.HookspecMarker("occplug")
hookimpl = pluggy.HookimplMarker("occplug")

__all__ = ["hookimpl", "hookspec", "occplug_config_dir", "occplug_register_components"]


@hookspec
def occplug_register_components(registry: Registry) -> None:
    """Add this plugin's components to ``registry``.

    Call ``registry.add(kind, name, factory)`` once per component. ``kind`` is one of
    :data:`occplug.kinds.KINDS`; ``name`` must be unique within its kind across all installed
    plugins: a clash stops start-up with an error naming both plugins.

    Example:
        >>> @occplug.hookimpl
        ... def occplug_register_components(registry):
        ...     registry.add("head", "tiny_mlp", TinyMLPHead)

    .. versionadded:: 0.1
    """


@hookspec
def occplug_config_dir() -> Traversable | Path | None:
    """Return the folder of YAML configs this plugin ships, or None.

    A file ``<dir>/base.yaml`` is addressed in configs and on the command line as
    ``<plugin>/base`` (``.yaml`` optional), where ``<plugin>`` is the entry-point name.

    .. versionadded:: 0.1
    """
