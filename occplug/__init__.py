"""occplug: a plugin-style toolkit on Lightning for 3D semantic occupancy prediction.

This module is the public facade: the hook marker, the registry, the kinds' interfaces and the data contract.
A plugin (and a script) imports from here and from the other modules in :data:`PUBLIC_MODULES`, each by a name
in its ``__all__``; every other module under ``occplug`` is internal. ``tests/test_import_boundary.py`` holds
the tree to that rule. Importing this module does not import Lightning.
"""

from __future__ import annotations

from typing import Any

from .context import RunContext, parse_grid
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

#: The plugin API: the modules a plugin or a script may import from, by the names in their ``__all__``
#: (docs/plugins.md, "What a plugin may import", says what each holds).
PUBLIC_MODULES: tuple[str, ...] = (
    "occplug",  # this facade: hookimpl, Registry, KINDS, interfaces, Batch / Frame, GridSpec, RunContext, parse_grid
    "occplug.interfaces",  # the kinds' interfaces and the scene / query types they exchange
    "occplug.constraints",  # Annotated[...] rules on component arguments (Positive, Range, ...)
    "occplug.config",  # Slot, ConfigError, compose / validate, phase_specs
    "occplug.geometry",  # poses, cameras, rays, grids, contraction, volume sampling and warping
    "occplug.ops",  # the lift-splat operators (FrustumSplatter, splat, ...)
    "occplug.nn",  # shared building blocks: residual blocks, attention, losses, matching
    "occplug.components",  # the core's registered generic components (to reuse or subclass)
    "occplug.streams",  # StreamState: per-sequence memory of a streaming component
    "occplug.data",  # classes, labelled points, class statistics, the data modules
    "occplug.data.synthetic",  # the synthetic world and its writers of real-format trees
    "occplug.metrics",  # mIoU, RayIoU, SSC metrics and their building blocks
    "occplug.ceilings",  # floors and ceilings of a protocol: readouts, perfect-depth lift, history headroom
    "occplug.data.synthetic.testbed",  # scripts: the synthetic world's floors, ceilings, headroom, pixel heights
    "occplug.testing",  # fixtures, conformance check, run_config
    "occplug.run.runner",  # scripts: load_config, build_run, fit, evaluate, load_checkpoint
    "occplug.run.training",  # scripts: the optimiser and schedule a config builds
    "occplug.run.bench",  # scripts: the cost / accuracy benchmark, mean_std
    "occplug.run.phases",  # scripts: fit_phases (a config with phases:, with the caller's callbacks)
    "occplug.run.memory",  # scripts: SavedTensorProfile (activations saved for backward, per module)
    "occplug.plugins",  # scripts: the plugin manager and the registry (get_registry)
    "occplug.viz",  # scripts: pictures (palette, camera ray casts, 3D view)
    "occplug.cli",  # scripts: the command line (main)
)

__all__ = [
    "KINDS",
    "PUBLIC_MODULES",
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
    "RunContext",
    "Scene",
    "SceneRepresentation",
    "Slot",
    "SupervisionSource",
    "UserError",
    "ViewTransform",
    "__version__",
    "hookimpl",
    "parse_grid",
]

_LAZY = {
    "OccModel": ("occplug.model", "OccModel"),
    "OccupancyModel": ("occplug.interfaces.model", "OccupancyModel"),
    "OccDataModule": ("occplug.data.datamodule", "OccDataModule"),
    "OccMetric": ("occplug.metrics.base", "OccMetric"),
    "Slot": ("occplug.slots", "Slot"),
}


def __getattr__(name: str) -> Any:  # lazy: keeps `import occplug` free of Lightning
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'occplug' has no attribute {name!r}")
