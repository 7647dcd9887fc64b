"""Labels of a synthetic frame: Occ3D-style semantic voxels, visibility masks and 3D boxes.

Voxel classes
-------------
A voxel is **occupied** when a solid meets it (exact closed-set overlap, so every surface point a
sensor can hit lies in an occupied voxel) or when it holds the ground surface. The ground is a
surface, not a volume: only the voxel layer containing ``z = 0`` (half-open voxels: the upper voxel
if 0 falls on a boundary) is ground, so voxels below the surface are free, as in Occ3D where nothing
below the surface is observed.

Where several classes meet a voxel, each candidate scores and the best wins:

* a solid scores ``2 * (f + 0.5 / k**3)``, with ``f`` the fraction of the voxel's ``k**3``
  sub-samples inside it (the ``0.5 / k**3`` keeps a solid that only grazes the voxel in the race),
* the ground scores 0.15, with its class voted by ``k x k`` samples of the ground map,

so an object filling ~7 % of a ground-level voxel takes it (small objects are not swamped by the
ground), while a sliver of a neighbour does not. Ties go to the solid generated later (agents come
after static structures).
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import torch
from torch import Tensor

from occplug.data.classes import OCC3D_FREE
from occplug.geometry import GridSpec, camera_rays, observed_mask, traversed_mask

from .primitives import BOX, CYLINDER, Primitives, overlaps_voxels
from .world import Agents, GroundMap

__all__ = [
    "GROUND_SCORE",
    "SOLID_WEIGHT",
    "agent_boxes",
    "camera_mask",
    "inside_solid",
    "lidar_mask",
    "solid_blocks",
    "voxel_labels",
]

#: Score of the ground's class in its voxel layer.
GROUND_SCORE = 0.15
#: Weight of a solid's sub-sample fraction.
SOLID_WEIGHT = 2.0


def _axis_samples(grid: GridSpec, k: int) -> list[Tensor]:
    """Per axis ``(n, k)`` float64 coordinates of the sub-samples of each voxel (cell centres)."""
    out = []
    for a, n in enumerate(grid.shape):
        offsets = (torch.arange(k, dtype=torch.float64) + 0.5) / k
        out.append(grid.lower[a] + (torch.arange(n, dtype=torch.float64)[:, None] + offsets) * grid.voxel_size[a])
    return out


def _ground_layer(grid: GridSpec, ground: GroundMap, ego_to_world: Tensor, k: int) -> tuple[int, Tensor] | None:
    """The voxel layer holding the ground surface and the ``(X, Y)`` majority ground class there."""
    layer = math.floor((0.0 - grid.lower[2]) / grid.voxel_size[2])
    if not 0 <= layer < grid.shape[2]:
        return None
    xs, ys, _ = _axis_samples(grid, k)
    nx, ny = grid.shape[:2]
    px = xs[:, None, :, None].expand(nx, ny, k, k)
    py = ys[None, :, None, :].expand(nx, ny, k, k)
    pts = torch.stack([px, py, torch.zeros_like(px)], -1).reshape(-1, 3)
    world = (pts @ ego_to_world[:3, :3].T + ego_to_world[:3, 3])[:, :2]
    classes = ground.classes_at(world).reshape(nx * ny, k * k)
    counts = torch.zeros(nx * ny, OCC3D_FREE + 1, dtype=torch.int64)
    counts.scatter_add_(1, classes, torch.ones_like(classes))
    return layer, counts.argmax(-1).reshape(nx, ny)


def inside_solid(prims: Primitives, p: int, points: Tensor) -> Tensor:
    """``(...)`` bool: points ``(..., 3)`` (float64) inside solid ``p``."""
    c, h = prims.center[p].double(), prims.half[p].double()
    yaw = float(prims.yaw[p])
    d = points - c
    cy, sy = math.cos(yaw), math.sin(yaw)
    u = torch.stack(
        [(cy * d[..., 0] + sy * d[..., 1]) / h[0], (-sy * d[..., 0] + cy * d[..., 1]) / h[1], d[..., 2] / h[2]], -1
    )
    kind = int(prims.shape[p])
    if kind == BOX:
        return u.abs().amax(-1) <= 1
    if kind == CYLINDER:
        return (u[..., :2].square().sum(-1) <= 1) & (u[..., 2].abs() <= 1)
    return u.square().sum(-1) <= 1


def solid_blocks(
    prims: Primitives, grid: GridSpec, k: int, touching: bool = True
) -> Iterator[tuple[int, tuple[slice, slice, slice], Tensor, Tensor]]:
    """The voxel block of each solid that may meet the grid, in the solids' order.

    Yields ``(p, block, touch, points)``: ``p`` the solid's row, ``block`` the ``(X, Y, Z)`` slices
    of the voxels its bounding box covers, ``touch`` ``(x, y, z)`` bool: voxels of the block the
    solid meets (exact; all True with ``touching=False``), and ``points`` ``(x, y, z, k, k, k, 3)``
    float64 sub-sample centres of the block's voxels. Solids meeting no voxel are skipped.
    """
    lo, hi = prims.aabb()
    lower = torch.tensor(grid.lower)
    upper = torch.tensor(grid.upper)
    size = torch.tensor(grid.voxel_size, dtype=torch.float64)
    shape = torch.tensor(grid.shape)
    relevant = ((lo <= upper) & (hi >= lower)).all(-1)
    samples = _axis_samples(grid, k)
    for p in torch.nonzero(relevant).squeeze(1).tolist():
        i0 = torch.floor((lo[p].double() - lower.double()) / size).long().clamp(min=0)
        i1 = torch.minimum(torch.floor((hi[p].double() - lower.double()) / size).long(), shape - 1)
        if (i1 < i0).any():
            continue
        sl = tuple(slice(int(a), int(b) + 1) for a, b in zip(i0, i1, strict=True))
        if touching:
            axes = [lower.double()[a] + torch.arange(int(i0[a]), int(i1[a]) + 1) * size[a] for a in range(3)]
            v_lo = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)  # lower corners of the block's voxels
            touch = overlaps_voxels(prims, p, v_lo.float(), (v_lo + size).float())
            if not touch.any():
                continue
        else:
            touch = torch.ones(tuple(int(b - a) + 1 for a, b in zip(i0, i1, strict=True)), dtype=torch.bool)
        xs, ys, zs = (samples[a][sl[a]] for a in range(3))
        pts = torch.stack(
            torch.broadcast_tensors(
                xs[:, None, None, :, None, None], ys[None, :, None, None, :, None], zs[None, None, :, None, None, :]
            ),
            -1,
        )
        yield p, sl, touch, pts


def voxel_labels(prims: Primitives, ground: GroundMap, ego_to_world: Tensor, grid: GridSpec, subsamples: int) -> Tensor:
    """Occ3D semantic occupancy of one frame (see the module docstring for the rules).

    Args:
        prims: every solid, **ego** frame.
        ground: the scene's ground map (world frame).
        ego_to_world: ``(4, 4)`` float64 pose of the frame.
        grid: the label grid (ego frame).
        subsamples: ``k``; ``k**3`` sub-samples per voxel vote.

    Returns:
        ``(X, Y, Z)`` uint8 class ids, 17 = free.
    """
    k = subsamples
    labels = torch.full(grid.shape, OCC3D_FREE, dtype=torch.uint8)
    score = torch.zeros(grid.shape)
    found = _ground_layer(grid, ground, ego_to_world, k)
    if found is not None:
        layer, classes = found
        labels[:, :, layer] = classes.to(torch.uint8)
        score[:, :, layer] = GROUND_SCORE
    for p, sl, touch, pts in solid_blocks(prims, grid, k):
        fraction = inside_solid(prims, p, pts).flatten(3).float().mean(-1)
        mine = SOLID_WEIGHT * (fraction + 0.5 / k**3)
        win = touch & (mine >= score[sl])
        score[sl] = torch.where(win, mine, score[sl])
        labels[sl] = torch.where(win, prims.label[p].to(torch.uint8), labels[sl])
    return labels


def lidar_mask(grid: GridSpec, origin: Tensor, points_ego: Tensor) -> Tensor:
    """``mask_lidar`` ``(X, Y, Z)`` bool: every voxel a LiDAR ray passes through on its way from the
    sensor ``origin`` ``(3,)`` to its return ``points_ego`` ``(P, 3)``, the return's voxel included
    (Occ3D's LiDAR visibility; ego frame)."""
    return traversed_mask(grid, origin.expand_as(points_ego), points_ego)


def camera_mask(occupied: Tensor, grid: GridSpec, intrinsics: Tensor, cam_to_ego: Tensor,
                image_size: tuple[int, int], scale: float = 1.0) -> Tensor:
    """``mask_camera`` ``(X, Y, Z)`` bool: voxels some camera ray traverses up to and including the
    first occupied voxel it meets (Occ3D's camera visibility).

    Rays go through the pixel centres of each image resampled by ``scale`` (2.0: four rays per
    pixel, for small images whose pixels are coarser than the voxels; 0.5: every other pixel row
    and column). A ray needs no range limit: the voxel holding the surface it sees is occupied, so
    it stops there.

    Args:
        occupied: ``(X, Y, Z)`` bool.
        grid: the label grid.
        intrinsics: ``(N, 3, 3)``; cam_to_ego: ``(N, 4, 4)``; image_size: ``(H, W)`` of the images.
        scale: ray density relative to the image resolution.
    """
    h, w = image_size
    hs, ws = max(1, round(h * scale)), max(1, round(w * scale))
    # the same field of view sampled on an (hs, ws) pixel grid: pixel-centre convention
    resample = torch.tensor([[ws / w, 0.0, (ws / w - 1) / 2], [0.0, hs / h, (hs / h - 1) / 2], [0.0, 0.0, 1.0]])
    origins, directions, _ = camera_rays(resample @ intrinsics, cam_to_ego, hs, ws)
    o = origins[:, None, None, :].expand_as(directions)
    return observed_mask(occupied, grid, o.reshape(-1, 3), directions.reshape(-1, 3), torch.inf)


def agent_boxes(agents: Agents, t: float, ego_to_world: Tensor, grid: GridSpec, margin: float = 2.0
                ) -> tuple[Tensor, Tensor, Tensor]:
    """3D boxes of the agents at time ``t`` in the ego frame.

    Only agents whose box centre lies within the grid's x/y range grown by ``margin`` metres are kept.

    Returns:
        ``boxes`` ``(M, 9)`` float32: centre x, y, z, length, width, height, yaw (wrapped to
        ``[-pi, pi)``), vx, vy (world velocity expressed in the ego axes, m/s); ``labels`` ``(M,)``
        int64; ``track_ids`` ``(M,)`` int64.
    """
    rot = ego_to_world[:2, :2]
    xy = (agents.position(t) - ego_to_world[:2, 3]) @ rot  # R^T (p - t), row form
    vel = agents.velocity() @ rot
    ego_yaw = math.atan2(float(ego_to_world[1, 0]), float(ego_to_world[0, 0]))
    yaw = agents.heading - ego_yaw
    yaw = yaw - 2 * math.pi * torch.floor((yaw + math.pi) / (2 * math.pi))
    keep = (
        (xy[:, 0] >= grid.lower[0] - margin) & (xy[:, 0] <= grid.upper[0] + margin)
        & (xy[:, 1] >= grid.lower[1] - margin) & (xy[:, 1] <= grid.upper[1] + margin)
    )
    size = agents.size.double()
    boxes = torch.cat([xy, size[:, 2:3] / 2, size, yaw[:, None], vel], -1)[keep]
    return boxes.float(), agents.label[keep], agents.track_id[keep]
