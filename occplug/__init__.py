"""occplug: a plugin-style toolkit on Lightning for 3D semantic occupancy prediction.

This module is the public facade: plugins import from here (and from ``occplug.testing``).
"""

from __future__ import annotations

from typing import Any

from .data.frame import Batch, Frame
from .errors import UserError
from .geometry import GridSpec
from .hookspecs import hookimpl
from .interfaces import (
    Head,
    ImageEncoder,
    Lifted,
    ModelOutputs,
    OccupancyHead,
    PointEncoder,
    QueryResult,
    Scene,
    SceneRepresentation,
    SupervisionSource,
    ViewTransform,
)
from .kinds import KINDS
from .registry import Registry

__version__ = "0.1.0"

__all__ = [
    "KINDS",
    "Batch",
    "Frame",
    "GridSpec",
    "Head",
    "ImageEncoder",
    "Lifted",
    "ModelOutputs",
    "OccDataModule",
    "OccMetric",
    "OccModel",
    "OccupancyHead",
    "OccupancyModel",
    "PointEncoder",
    "QueryResult",
    "Registry",
    "Scene",
    "SceneRepresentation",
    "Slot",
    "SupervisionSource",
    "UserError",
    "ViewTransform",
    "__version__",
    "hookimpl",
]

_LAZY = {
    "OccModel": ("occplug.model", "OccModel"),
    "OccupancyModel": ("occplug.interfaces.model", "OccupancyModel"),
    "OccDataModule": ("occplug.data.datamodule", "OccDataModule"),
    "OccMetric": ("occplug.metrics.base", "OccMetric"),
    "Slot": ("occplug.config.slots", "Slot"),
}


def __getattr__(name: str) -> Any:  # lazy: keeps `import occplug` free of Lightning
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'occplug' has no attribute {name!r}")
