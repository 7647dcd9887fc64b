"""The synthetic world's exact semantic field, sampled on a voxel grid: what a perfect model would answer.

The *ideal field* gives every point in the ego frame the class of the solid that contains it (the
solid generated last wins, as in :func:`~.labels.voxel_labels`), else the ground's class where
``-ground_shell <= z <= 0`` (the ground as a slab of that thickness below its surface: what a
model taught by perfect depth, which places ground points on the surface and free space above,
learns; the surface ``z = 0`` itself included), else free. It is read at the ``k**3`` sub-sample centres of every voxel of a grid
(``k = 1``: the voxel centres, the points a query decoder is read at); :func:`occplug.ceilings.read_voxels`
turns those samples into one class per voxel.
"""

from __future__ import annotations

import torch
from torch import Tensor

from occplug.data.classes import OCC3D_FREE
from occplug.geometry import GridSpec, invert_pose

from .config import SyntheticWorldConfig
from .labels import _axis_samples, inside_solid, solid_blocks
from .primitives import Primitives
from .world import GroundMap, Scene

__all__ = ["DEFAULT_GROUND_SHELL", "field_samples", "scene_field_samples"]

#: Metres of ground below its surface that the ideal field counts as ground.
DEFAULT_GROUND_SHELL = 0.5
# Samples up to this far above z = 0 count as on the ground surface: a voxel centre placed at z = 0 by the
# grid (e.g. z from -1.2 at 0.8 m) is computed as 2e-16, and the surface itself is occupied.
_ON_SURFACE = 1e-6


def field_samples(
    prims: Primitives,
    ground: GroundMap,
    ego_to_world: Tensor,
    grid: GridSpec,
    k: int,
    ground_shell: float = DEFAULT_GROUND_SHELL,
) -> Tensor:
    """The ideal field at the ``k**3`` sub-sample centres of every voxel.

    Args:
        prims: every solid, **ego** frame.
        ground: the scene's ground map (world frame).
        ego_to_world: ``(4, 4)`` float64 pose of the frame.
        grid: the grid read (ego frame).
        k: sub-samples per voxel edge (1: the voxel centre).
        ground_shell: metres below the ground surface that count as ground (0: none).

    Returns:
        ``(X, Y, Z, k, k, k)`` uint8 class ids (17 = free); sample ``[i, j, l, a, b, c]`` lies at
        ``lower + (index + (offset + 0.5) / k) * voxel_size`` per axis.
    """
    if k < 1:
        raise ValueError(f"field_samples: k must be >= 1, got {k}")
    nx, ny, nz = grid.shape
    xs, ys, zs = _axis_samples(grid, k)
    out = torch.full((nx, ny, nz, k, k, k), OCC3D_FREE, dtype=torch.uint8)
    in_shell = (zs <= _ON_SURFACE) & (zs >= -ground_shell)  # (Z, k); a sample on the surface is ground
    if ground_shell > 0 and bool(in_shell.any()):
        px = xs[:, None, :, None].expand(nx, ny, k, k)
        py = ys[None, :, None, :].expand(nx, ny, k, k)
        pts = torch.stack([px, py, torch.zeros_like(px)], -1).reshape(-1, 3)
        world = (pts @ ego_to_world[:3, :3].T + ego_to_world[:3, 3])[:, :2]
        classes = ground.classes_at(world).reshape(nx, ny, k, k).to(torch.uint8)  # (X, Y, kx, ky)
        g = classes[:, :, None, :, :, None].expand(nx, ny, nz, k, k, k)
        shell = in_shell[None, None, :, None, None, :].expand(nx, ny, nz, k, k, k)
        out = torch.where(shell, g, out)
    for p, sl, _, pts in solid_blocks(prims, grid, k, touching=False):
        inside = inside_solid(prims, p, pts)
        block = out[sl]
        block[inside] = int(prims.label[p])
    return out


def scene_field_samples(
    config: SyntheticWorldConfig,
    scene: Scene,
    frame_index: int,
    k: int,
    grid: GridSpec | None = None,
    ground_shell: float = DEFAULT_GROUND_SHELL,
) -> Tensor:
    """:func:`field_samples` of frame ``frame_index`` of a generated ``scene`` (on ``grid``, default the
    config's label grid)."""
    t = frame_index / config.fps
    ego_to_world = scene.ego_to_world(t)
    prims = scene.primitives_at(t).transformed(invert_pose(ego_to_world))
    return field_samples(prims, scene.ground, ego_to_world, grid or config.grid, k, ground_shell)
