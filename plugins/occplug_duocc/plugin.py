"""DuOcc's hook implementations (the only module that uses ``@occplug.hookimpl``)."""

from __future__ import annotations

from importlib.resources import files
from importlib.resources.abc import Traversable

import occplug


@occplug.hookimpl
def occplug_register_components(registry: occplug.Registry) -> None:
    from .heads import DuOccDecoder
    from .scene import DuOccStacking, DuOccStream
    from .supervision import DuOccDetection, DuOccForecast, DuOccMask, DuOccOccupied

    registry.add("scene", "duocc_stream", DuOccStream)
    registry.add("scene", "duocc_stacking", DuOccStacking)
    registry.add("head", "duocc_decoder", DuOccDecoder)
    registry.add("supervision", "duocc_occupied", DuOccOccupied)
    registry.add("supervision", "duocc_forecast", DuOccForecast)
    registry.add("supervision", "duocc_detection", DuOccDetection)
    registry.add("supervision", "duocc_mask", DuOccMask)


@occplug.hookimpl
def occplug_config_dir() -> Traversable:
    return files("occplug_duocc") / "configs"
