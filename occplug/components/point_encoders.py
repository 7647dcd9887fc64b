"""Point encoders: ``voxel_points`` (LiDAR points -> a per-voxel feature volume, plain PyTorch)."""

from __future__ import annotations

from typing import Annotated

import torch
from torch import Tensor, nn

from occplug.constraints import Positive
from occplug.data.frame import Batch
from occplug.geometry import GridSpec, transform_points
from occplug.interfaces import PointEncoder

__all__ = ["VoxelPoints", "voxel_point_statistics"]

#: Per-voxel statistics :func:`voxel_point_statistics` returns, in channel order.
STATISTICS = ("count", "mean_dx", "mean_dy", "mean_dz", "mean_intensity")


def voxel_point_statistics(points: Tensor, intensity: Tensor, grid: GridSpec) -> Tensor:
    """Per-voxel point statistics of one sample, dense on ``grid``.

    Args:
        points: ``(P, 3)`` ego-frame points, metres (non-finite rows, e.g. the padding of an exported graph's
            point input, count as no point).
        intensity: ``(P,)`` intensities in [0, 1].
        grid: the target grid (points outside it are dropped).

    Returns:
        ``(5, X, Y, Z)`` float32: ``log1p(count)``, then the mean offset of the voxel's points from
        its centre in voxel units (each in [-0.5, 0.5]), then their mean intensity; zeros where a
        voxel holds no point.
    """
    shape = grid.shape
    n = shape[0] * shape[1] * shape[2]
    # dropped points are pooled into one extra row, not indexed away: fixed shapes, so this traces for export
    idx = grid.coord_to_index(points)
    inside = grid.contains(points) & grid.index_in_bounds(idx) & torch.isfinite(intensity)
    idx = torch.where(inside[:, None], idx, torch.zeros_like(idx))
    flat = torch.where(inside, (idx[:, 0] * shape[1] + idx[:, 1]) * shape[2] + idx[:, 2], n)
    size = torch.tensor(grid.voxel_size, dtype=points.dtype, device=points.device)
    offset = (points - grid.index_to_coord(idx).to(points.dtype)) / size
    values = torch.cat([torch.ones_like(intensity)[:, None], offset, intensity[:, None]], dim=1).float()
    values = torch.where(inside[:, None], values, torch.zeros_like(values))
    sums = torch.zeros(n + 1, values.shape[1], dtype=torch.float32, device=points.device).index_add_(0, flat, values)
    count = sums[:n, :1]
    means = sums[:n, 1:] / count.clamp(min=1.0)
    out = torch.cat([torch.log1p(count), means], dim=1)
    return out.t().reshape(len(STATISTICS), *shape)


class VoxelPoints(PointEncoder):
    """LiDAR points -> per-voxel statistics -> a small 3D conv net (a cheap, dense LiDAR branch).

    Each voxel of ``grid`` gets :func:`voxel_point_statistics` (log count, mean offset from its
    centre, mean intensity) of the points inside it, then ``num_layers`` 3x3x3 conv + BatchNorm +
    ReLU layers map them to ``out_channels``.

    Args:
        grid: the grid of the output volume (filled with the evaluation grid when left out).
        out_channels: ``C`` of the output.
        num_layers: 3D conv layers (>= 1).

    Shapes:
        reads ``batch.points`` (per sample ``(P, 4)`` lidar-frame x, y, z, intensity; non-finite rows are
        padding) and
        ``batch.lidar_to_ego`` ``(B, 4, 4)``; returns ``(B, out_channels, X, Y, Z)`` in the ego frame.
    """

    requires = frozenset({"points"})

    def __init__(
        self,
        grid: GridSpec,
        out_channels: Annotated[int, Positive] = 16,
        num_layers: Annotated[int, Positive] = 2,
    ) -> None:
        super().__init__()
        if num_layers < 1:
            raise ValueError(f"voxel_points num_layers must be >= 1, got {num_layers}")
        self.grid = grid
        self.out_channels = int(out_channels)
        layers: list[nn.Module] = []
        channels = len(STATISTICS)
        for _ in range(num_layers):
            layers += [nn.Conv3d(channels, self.out_channels, 3, padding=1, bias=False),
                       nn.BatchNorm3d(self.out_channels), nn.ReLU(inplace=True)]
            channels = self.out_channels
        self.net = nn.Sequential(*layers)

    def forward(self, batch: Batch) -> Tensor:
        batch.require("points", "lidar_to_ego", by="the voxel_points point encoder")
        stats = []
        for points, pose in zip(batch.points, batch.lidar_to_ego, strict=True):
            ego = transform_points(pose.to(points.dtype), points[:, :3])
            stats.append(voxel_point_statistics(ego, points[:, 3], self.grid))
        return self.net(torch.stack(stats))
