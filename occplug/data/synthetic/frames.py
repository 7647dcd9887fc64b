"""One synthetic frame: the scene at time ``frame_index / fps`` seen by every sensor, with labels."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from occplug.data.classes import OCC3D_FREE
from occplug.data.frame import Frame
from occplug.geometry import invert_pose

from .config import SyntheticWorldConfig
from .labels import agent_boxes, camera_mask, lidar_mask, voxel_labels
from .primitives import Primitives
from .render import LIDAR_TO_EGO, LidarSweep, camera_rig, corrupt_lidar, lidar_generator, render_cameras, render_lidar
from .world import Scene

__all__ = ["FrameLabels", "frame_labels", "frame_token", "generate_frame", "rig_camera_mask"]


def frame_token(config: SyntheticWorldConfig, split: str, scene_index: int, frame_index: int) -> str:
    """The unique sample id of a frame, e.g. ``synth-0-train-0003-007``."""
    return f"synth-{config.seed}-{split}-{scene_index:04d}-{frame_index:03d}"


def generate_frame(config: SyntheticWorldConfig, scene: Scene, split: str, scene_index: int, frame_index: int) -> Frame:
    """Render and label frame ``frame_index`` of ``scene`` (deterministic; no adjacent frames).

    Every field is filled except the pseudo-label fields; ``extras`` holds ``is_sequence_start``
    and ``split``. ``semantics_2d`` is 255 where a pixel sees no surface (sky).
    ``sequence_lidar_origins`` holds the LiDAR position of every frame of the scene (all
    ``config.frames(split)`` of them, in order) in this frame's ego frame.
    """
    t = frame_index / config.fps
    ego_to_world = scene.ego_to_world(t)
    world_to_ego = invert_pose(ego_to_world)
    prims = scene.primitives_at(t).transformed(world_to_ego)
    sun_ego = (world_to_ego[:3, :3] @ scene.sun.double()).float()
    names, intrinsics, cam_to_ego = camera_rig(config.num_cameras, config.image_size)
    noise = torch.Generator().manual_seed((scene.seed * 1_000_003 + frame_index) % (1 << 62))
    cams = render_cameras(
        prims, scene.ground, ego_to_world, sun_ego, intrinsics, cam_to_ego, config.image_size, config.image_noise, noise
    )
    lidar, labels, points_ego = _lidar_and_labels(config, scene, frame_index, prims, ego_to_world)
    grid = config.grid
    boxes, box_labels, track_ids = agent_boxes(scene.agents, t, ego_to_world, grid)
    lidar_origin = LIDAR_TO_EGO[:3, 3].double()
    sequence_origins = torch.stack(
        [
            (world_to_ego @ scene.ego_to_world(k / config.fps))[:3]
            @ torch.cat([lidar_origin, lidar_origin.new_ones(1)])
            for k in range(config.frames(split))
        ]
    ).float()
    n = intrinsics.shape[0]
    return Frame(
        images=cams.images,
        intrinsics=intrinsics,
        cam_to_ego=cam_to_ego,
        img_aug=torch.eye(3).expand(n, 3, 3).clone(),
        ego_to_global=scene.world_to_global @ ego_to_world,
        timestamp=float(t),
        scene=scene.name,
        frame_index=frame_index,
        token=frame_token(config, split, scene_index, frame_index),
        camera_names=names,
        lidar_to_ego=LIDAR_TO_EGO.clone(),
        points=lidar.points,
        point_labels=lidar.labels,
        voxel_labels=labels,
        mask_camera=camera_mask(
            labels != OCC3D_FREE, grid, intrinsics, cam_to_ego, config.image_size, config.camera_mask_scale
        ),
        mask_lidar=lidar_mask(grid, lidar.origin, points_ego),
        boxes=boxes,
        box_labels=box_labels,
        box_track_ids=track_ids,
        depth=cams.depth,
        semantics_2d=cams.semantics,
        sequence_lidar_origins=sequence_origins,
        extras={"is_sequence_start": frame_index == 0, "split": split},
    )


def _lidar_and_labels(
    config: SyntheticWorldConfig, scene: Scene, frame_index: int, prims: Primitives, ego_to_world: Tensor
) -> tuple[LidarSweep, Tensor, Tensor]:
    """The frame's LiDAR sweep (with the config's range noise and dropout), voxel labels and the
    sweep's points in the ego frame ``(P, 3)``."""
    lidar = render_lidar(
        prims,
        scene.ground,
        ego_to_world,
        config.lidar_beams,
        config.lidar_elevation_deg,
        config.lidar_azimuth_steps,
        config.lidar_max_range,
    )
    lidar = corrupt_lidar(lidar, config.lidar_range_noise, config.lidar_dropout, lidar_generator(scene, frame_index))
    labels = voxel_labels(prims, scene.ground, ego_to_world, config.grid, config.label_subsamples)
    points_ego = lidar.points[:, :3] @ LIDAR_TO_EGO[:3, :3].T + LIDAR_TO_EGO[:3, 3]
    return lidar, labels, points_ego


@dataclass
class FrameLabels:
    """What :func:`frame_labels` returns: a frame's labels without its images.

    Attributes:
        voxel_labels: ``(X, Y, Z)`` uint8, as :attr:`Frame.voxel_labels`.
        mask_camera: ``(X, Y, Z)`` bool for the first ``num_cameras`` cameras of the rig.
        mask_lidar: ``(X, Y, Z)`` bool, as :attr:`Frame.mask_lidar`.
        ego_to_world: ``(4, 4)`` float64 pose in the scene's world frame.
        points_ego: ``(P, 3)`` the LiDAR returns in the ego frame; point_labels: ``(P,)`` their classes.
    """

    voxel_labels: Tensor
    mask_camera: Tensor
    mask_lidar: Tensor
    ego_to_world: Tensor
    points_ego: Tensor
    point_labels: Tensor


def frame_labels(
    config: SyntheticWorldConfig, scene: Scene, frame_index: int, num_cameras: int | None = None
) -> FrameLabels:
    """Labels and masks of frame ``frame_index`` of ``scene`` without rendering any image.

    Equal to the fields of :func:`generate_frame` for ``num_cameras = config.num_cameras`` (the
    default); fewer cameras give the camera mask of the first ``num_cameras`` of the rig.
    """
    n = config.num_cameras if num_cameras is None else num_cameras
    ego_to_world = scene.ego_to_world(frame_index / config.fps)
    prims = scene.primitives_at(frame_index / config.fps).transformed(invert_pose(ego_to_world))
    lidar, labels, points_ego = _lidar_and_labels(config, scene, frame_index, prims, ego_to_world)
    mask = rig_camera_mask(config, labels, n)
    return FrameLabels(
        labels, mask, lidar_mask(config.grid, lidar.origin, points_ego), ego_to_world, points_ego, lidar.labels
    )


def rig_camera_mask(config: SyntheticWorldConfig, labels: Tensor, num_cameras: int) -> Tensor:
    """``mask_camera`` ``(X, Y, Z)`` bool of the first ``num_cameras`` cameras of the rig for ``(X, Y, Z)`` labels."""
    _, intrinsics, cam_to_ego = camera_rig(num_cameras, config.image_size)
    return camera_mask(
        labels != OCC3D_FREE, config.grid, intrinsics, cam_to_ego, config.image_size, config.camera_mask_scale
    )
