"""The synthetic driving world: occplug's embedded default data set and the fixture of its tests.

A procedural town (roads with lanes, sidewalks, buildings, trees, barriers, moving traffic and
pedestrians) is generated per scene from a seed, and each frame is rendered by exact ray casting:
six surround cameras (images, depth, 2D semantics), a spinning LiDAR, Occ3D-style voxel labels with
camera/LiDAR visibility masks, and 3D boxes with velocities. No downloads; CPU friendly.

Modules: :mod:`.config` (knobs, presets), :mod:`.world` (scenes), :mod:`.primitives` (solids),
:mod:`.appearance` (textures, shading), :mod:`.render` (sensors), :mod:`.labels` (voxels, masks,
boxes), :mod:`.frames` (one frame), :mod:`.dataset` (cached dataset), :mod:`.datamodule`,
:mod:`.writer` (files on disk).
"""

import importlib
from typing import Any

from .config import CODE_VERSION, PRESETS, SyntheticWorldConfig, preset
from .datamodule import SyntheticDataModule
from .dataset import SyntheticDataset, default_cache_dir
from .frames import generate_frame
from .render import CAMERA_RIG, LIDAR_TO_EGO, NO_SURFACE
from .world import Scene, build_scene
from .writer import read_frame, save_frame, write_dataset

#: the writers of real-format trees and the label and rig helpers, loaded on first attribute access
_LAZY = {
    "write_occ3d_nuscenes": "occplug.data.synthetic.export_occ3d",
    "write_semantickitti": "occplug.data.synthetic.export_semantickitti",
    "lidar_grid": "occplug.data.synthetic.export_semantickitti",
    "voxel_labels": "occplug.data.synthetic.labels",
    "camera_rig": "occplug.data.synthetic.render",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'occplug.data.synthetic' has no attribute {name!r}")


__all__ = [
    *_LAZY,
    "CAMERA_RIG",
    "CODE_VERSION",
    "LIDAR_TO_EGO",
    "NO_SURFACE",
    "PRESETS",
    "Scene",
    "SyntheticDataModule",
    "SyntheticDataset",
    "SyntheticWorldConfig",
    "build_scene",
    "default_cache_dir",
    "generate_frame",
    "preset",
    "read_frame",
    "save_frame",
    "write_dataset",
]
