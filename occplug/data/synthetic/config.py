"""Every size knob of the synthetic world, and the named presets.

A :class:`SyntheticWorldConfig` plus ``(split, scene, frame)`` determines a frame completely, so
generated frames are cached under :meth:`SyntheticWorldConfig.cache_key`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from typing import Any

from occplug.context import parse_grid
from occplug.geometry import GridSpec

__all__ = ["CODE_VERSION", "PRESETS", "SPLITS", "SyntheticWorldConfig", "preset"]

#: Bump whenever generation changes what a frame contains: it is part of every cache key.
CODE_VERSION = "synthetic-world-3"

#: The splits a world has; ``predict`` reads the ``val`` scenes.
SPLITS = ("train", "val", "test")

# Knobs that choose *which* frames a data set holds, not what any frame contains: left out of the
# cache key so that, e.g., adding scenes reuses the frames already generated.
_SELECTION_KNOBS = ("train_scenes", "val_scenes", "test_scenes", "adjacent_offsets")

# Knobs added after worlds were cached, with the value that reproduces the world from before them:
# left out of the cache key at that value, so caches of the earlier worlds stay valid.
_LATER_KNOBS: dict[str, Any] = {"lidar_range_noise": 0.0, "lidar_dropout": 0.0, "ego_lane_speed_offset": [0.0, 0.0]}


@dataclass(frozen=True)
class SyntheticWorldConfig:
    """The synthetic driving world's knobs (see the presets in :data:`PRESETS`).

    Attributes:
        seed: world seed; scenes of different splits use disjoint derived seeds.
        train_scenes, val_scenes, test_scenes: scenes per split.
        frames_per_scene: frames of each training scene.
        eval_frames_per_scene: frames of each val/test scene.
        fps: frame rate, Hz (frames are ``1 / fps`` seconds apart; nuScenes keyframes: 2 Hz).
        image_size: ``(H, W)`` of every camera image, pixels.
        num_cameras: 1..6; the first ``n`` of the nuScenes-like rig (front, front-right,
            front-left, back, back-left, back-right).
        lidar_beams: rings of the spinning LiDAR.
        lidar_elevation_deg: ``(lowest, highest)`` beam elevation, degrees (nuScenes: -30, +10).
        lidar_azimuth_steps: firings per revolution.
        lidar_max_range: metres; returns beyond it are dropped.
        lidar_range_noise: standard deviation of each return's range error, metres (0: exact;
            nuScenes' HDL-32E: about 0.02).
        lidar_dropout: probability that a return is lost (0: none; the ``nuscenes_lidar``
            preset: 0.1). Labels come from the exact solids either way; ``mask_lidar`` from the
            corrupted returns, as Occ3D's from the real ones.
        grid: the label grid in the ego frame.
        label_subsamples: ``k``: voxel classes are voted by ``k**3`` sub-samples per voxel.
        camera_mask_scale: ray density of ``mask_camera`` relative to the image resolution
            (2.0: 2 x 2 rays per pixel; 0.5: every other pixel row and column).
        adjacent_offsets: frame offsets loaded into ``Frame.adjacent`` (e.g. ``(-1, 1)``).
        vehicle_density: moving vehicles per 100 m of each traffic lane.
        ego_lane_speed_offset: ``(lo, hi)`` m/s: the ego lane's traffic drives ``d ~ U(lo, hi)``
            faster than the ego ahead of it and ``d`` slower behind it (one ``d`` per scene);
            ``(0, 0)``: at the ego's own speed, so it keeps its place in the ego frame.
        parked_density: parked vehicles per 100 m of each parking strip.
        pedestrian_density: pedestrians per 100 m of each sidewalk.
        cyclist_density: bicycles per 100 m of each bike lane.
        structure_density: multiplier on trees, poles, hedges, barriers and cones.
        world_margin: metres of world built around the ego's path (beyond it: bare terrain).
        image_noise: standard deviation of the per-pixel sensor noise added to images.
    """

    seed: int = 0
    train_scenes: int = 16
    val_scenes: int = 4
    test_scenes: int = 4
    frames_per_scene: int = 12
    eval_frames_per_scene: int = 6
    fps: float = 2.0
    image_size: tuple[int, int] = (96, 176)
    num_cameras: int = 6
    lidar_beams: int = 32
    lidar_elevation_deg: tuple[float, float] = (-30.0, 10.0)
    lidar_azimuth_steps: int = 720
    lidar_max_range: float = 60.0
    lidar_range_noise: float = 0.0
    lidar_dropout: float = 0.0
    grid: GridSpec = field(default_factory=lambda: GridSpec((-24.0, -24.0, -1.0, 24.0, 24.0, 5.4), 0.8))
    label_subsamples: int = 4
    camera_mask_scale: float = 1.0
    adjacent_offsets: tuple[int, ...] = ()
    vehicle_density: float = 4.0
    ego_lane_speed_offset: tuple[float, float] = (0.0, 0.0)
    parked_density: float = 7.0
    pedestrian_density: float = 6.0
    cyclist_density: float = 2.0
    structure_density: float = 1.0
    world_margin: float = 70.0
    image_noise: float = 0.01

    def __post_init__(self) -> None:
        if not 1 <= self.num_cameras <= 6:
            raise ValueError(f"num_cameras must be 1..6, got {self.num_cameras}")
        if len(self.image_size) != 2 or min(self.image_size) < 4:
            raise ValueError(f"image_size must be (H, W) with H, W >= 4, got {self.image_size}")
        if self.fps <= 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        for name in ("train_scenes", "val_scenes", "test_scenes"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("frames_per_scene", "eval_frames_per_scene", "lidar_beams", "lidar_azimuth_steps",
                     "label_subsamples"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.image_noise < 0:
            raise ValueError(f"image_noise must be >= 0, got {self.image_noise}")
        if self.lidar_range_noise < 0:
            raise ValueError(f"lidar_range_noise must be >= 0, got {self.lidar_range_noise}")
        if not 0 <= self.lidar_dropout < 1:
            raise ValueError(f"lidar_dropout must be in [0, 1), got {self.lidar_dropout}")
        lo, hi = self.ego_lane_speed_offset
        if not 0 <= lo <= hi:
            raise ValueError(
                f"ego_lane_speed_offset must be (lo, hi) with 0 <= lo <= hi, got {self.ego_lane_speed_offset}"
            )
        if self.camera_mask_scale <= 0:
            raise ValueError(f"camera_mask_scale must be positive, got {self.camera_mask_scale}")

    def scenes(self, split: str) -> int:
        """Number of scenes of ``split`` (``train``, ``val``, ``test``)."""
        return {"train": self.train_scenes, "val": self.val_scenes, "test": self.test_scenes}[_check_split(split)]

    def frames(self, split: str) -> int:
        """Frames per scene of ``split``."""
        return self.frames_per_scene if _check_split(split) == "train" else self.eval_frames_per_scene

    def replace(self, **changes: Any) -> SyntheticWorldConfig:
        """A copy with some knobs changed (sequences are converted to tuples, grids to GridSpec)."""
        if "grid" in changes and not isinstance(changes["grid"], GridSpec):
            changes["grid"] = parse_grid(changes["grid"])
        for name in ("image_size", "lidar_elevation_deg", "adjacent_offsets", "ego_lane_speed_offset"):
            if name in changes:
                changes[name] = tuple(changes[name])
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready mapping of every knob (the grid as ``{range, voxel_size}``)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["grid"] = self.grid.to_dict()
        return {k: list(v) if isinstance(v, tuple) else v for k, v in out.items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SyntheticWorldConfig:
        """Inverse of :meth:`to_dict`."""
        return cls().replace(**data)

    def cache_key(self) -> str:
        """A short hash of everything that changes a frame's content, plus :data:`CODE_VERSION`."""
        content = {
            k: v
            for k, v in self.to_dict().items()
            if k not in _SELECTION_KNOBS and not (k in _LATER_KNOBS and v == _LATER_KNOBS[k])
        }
        text = json.dumps({"code": CODE_VERSION, "world": content}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def _check_split(split: str) -> str:
    if split not in SPLITS:
        raise ValueError(f"unknown split '{split}' (valid: {', '.join(SPLITS)})")
    return split


# The default grid moved down by 0.2 m: z = 0 (the ground surface) is the centre of a voxel layer, as in
# Occ3D (0.4 m voxels from z = -1.0: ground layer [-0.2, 0.2)); the default grid puts it 0.2 m below the
# centre of [-0.2, 0.6).
_ALIGNED_GRID = GridSpec((-24.0, -24.0, -1.2, 24.0, 24.0, 5.2), 0.8)

#: The named worlds: ``tiny`` (tests, seconds), ``default`` (a CPU run of minutes), ``aligned`` (the default
#: world on a grid whose ground surface lies on voxel centres), ``testbed`` (``aligned`` plus nuScenes-like
#: LiDAR noise and dropout, ego-lane traffic at its own speeds, 16-frame evaluation scenes and 192 x 352
#: images: the calibrated test bed of issue 52), ``occ3d``
#: (Occ3D-nuScenes size: 200 x 200 x 16 voxels at 0.4 m, 256 x 704 images; for GPUs), ``long_range``
#: (range experiments: the town reaches 260 m beyond the ego's path, the LiDAR 250 m with beams up
#: to +5 degrees, and the synthetic pseudo depth is kept to the LiDAR range; labels on a
#: 102.4 m x 102.4 m grid; about 25 s of generation per frame on one CPU core).
PRESETS: dict[str, SyntheticWorldConfig] = {
    "tiny": SyntheticWorldConfig(
        train_scenes=2,
        val_scenes=1,
        test_scenes=1,
        frames_per_scene=3,
        eval_frames_per_scene=2,
        image_size=(32, 64),
        lidar_beams=16,
        lidar_azimuth_steps=360,
        lidar_max_range=40.0,
        grid=GridSpec((-16.0, -16.0, -1.0, 16.0, 16.0, 5.4), 0.8),
        camera_mask_scale=2.0,
        world_margin=50.0,
    ),
    "default": SyntheticWorldConfig(),
    "occ3d": SyntheticWorldConfig(
        train_scenes=64,
        val_scenes=16,
        test_scenes=16,
        frames_per_scene=20,
        eval_frames_per_scene=20,
        image_size=(256, 704),
        lidar_azimuth_steps=1080,
        grid=GridSpec((-40.0, -40.0, -1.0, 40.0, 40.0, 5.4), 0.4),
        label_subsamples=3,
        camera_mask_scale=0.5,
        world_margin=80.0,
    ),
    "long_range": SyntheticWorldConfig(
        train_scenes=6,
        val_scenes=2,
        test_scenes=2,
        frames_per_scene=6,
        eval_frames_per_scene=4,
        image_size=(64, 176),
        lidar_elevation_deg=(-25.0, 5.0),
        lidar_max_range=250.0,
        grid=GridSpec((-51.2, -51.2, -1.0, 51.2, 51.2, 5.4), 0.8),
        label_subsamples=2,
        camera_mask_scale=0.5,
        world_margin=260.0,
    ),
    "aligned": SyntheticWorldConfig(grid=_ALIGNED_GRID),
    "testbed": SyntheticWorldConfig(
        grid=_ALIGNED_GRID,
        eval_frames_per_scene=16,
        image_size=(192, 352),
        lidar_range_noise=0.02,
        lidar_dropout=0.1,
        ego_lane_speed_offset=(1.0, 4.0),
    ),
}


def preset(name: str) -> SyntheticWorldConfig:
    """The preset called ``name``; a ``ValueError`` names the valid ones."""
    if name not in PRESETS:
        raise ValueError(f"unknown synthetic world preset '{name}' (valid: {', '.join(PRESETS)})")
    return PRESETS[name]
