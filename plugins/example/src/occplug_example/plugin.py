"""The plugin's hook implementations (the only module that uses ``@occplug.hookimpl``)."""

from __future__ import annotations

from importlib.resources import files
from importlib.resources.abc import Traversable

import occplug

from .heads import TinyMLPHead


@occplug.hookimpl
def occplug_register_components(registry: occplug.Registry) -> None:
    registry.add("head", "tiny_mlp", TinyMLPHead)


@occplug.hookimpl
def occplug_config_dir() -> Traversable:
    return files("occplug_example") / "configs"
