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

from .config import CODE_VERSION, PRESETS, SyntheticWorldConfig, preset
from .datamodule import SyntheticDataModule
from .dataset import SyntheticDataset, default_cache_dir
from .frames import generate_frame
from .render import CAMERA_RIG, LIDAR_TO_EGO, NO_SURFACE
from .world import Scene, build_scene
from .writer import read_frame, save_frame, write_dataset

__all__ = [
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
