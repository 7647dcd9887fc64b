"""Point encoder ``occle_lidar_voxels``: OccLE's VoxelNet LiDAR input (§3.2) as an occplug point encoder."""

from __future__ import annotations

from typing import Annotated

import torch
from torch import Tensor

from occplug.constraints import NonNegative, Positive
from occplug.data import Batch
from occplug.geometry import GridSpec, transform_points
from occplug.interfaces import PointEncoder

from .blocks.geometry_branch import LidarVoxelEncoder, PointSampling

__all__ = ["OccleLidarVoxels"]


class OccleLidarVoxels(PointEncoder):
    """LiDAR points -> VoxelNet voxel features on the grid (:class:`~.geometry_branch.LidarVoxelEncoder`).

    The batch's points are in the LiDAR frame; they are moved into the ego frame with ``batch.lidar_to_ego``
    before voxelisation, so the volume lies on the ego-frame ``grid`` like every other grid of the model. Each
    point keeps ``point_features`` columns after ``x, y, z`` (1: intensity).

    Args:
        grid: the output grid (the evaluation grid when left out).
        out_channels: ``C`` of the output volume.
        hidden: width of the first point layer.
        max_points: points kept per voxel (§3.2: 35).
        point_features: feature columns per point after ``x, y, z`` (1: intensity).
        sampling: which points a fuller voxel keeps: ``random`` (§3.2; a fresh subset every training step, a
            fixed pseudo-random one in eval and export) or ``first`` (input order).

    Forward:
        ``batch.points`` (per sample ``(P, 3 + F)`` lidar frame; non-finite rows are padding, no point) and
        ``batch.lidar_to_ego`` ``(B, 4, 4)`` -> ``(B, out_channels, X, Y, Z)`` ego frame, zero in voxels without
        a point.
    """

    requires = frozenset({"points"})

    def __init__(
        self,
        grid: GridSpec,
        out_channels: Annotated[int, Positive] = 32,
        hidden: Annotated[int, Positive] = 32,
        max_points: Annotated[int, Positive] = 35,
        point_features: Annotated[int, NonNegative] = 1,
        sampling: PointSampling = "random",
    ) -> None:
        super().__init__()
        self.encoder = LidarVoxelEncoder(grid, point_features, out_channels, hidden, max_points, sampling)
        self.grid = self.encoder.grid
        self.out_channels = int(out_channels)
        self.point_features = int(point_features)

    def forward(self, batch: Batch) -> Tensor:
        batch.require("points", "lidar_to_ego", by="the occle_lidar_voxels point encoder")
        ego = []
        for points, pose in zip(batch.points, batch.lidar_to_ego, strict=True):
            xyz = transform_points(pose.to(points.dtype), points[:, :3])
            ego.append(torch.cat([xyz, points[:, 3 : 3 + self.point_features]], dim=1).float())
        return self.encoder(ego)
