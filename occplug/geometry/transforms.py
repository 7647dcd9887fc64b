"""Rigid transforms as 4x4 homogeneous matrices.

A pose named ``a_to_b`` maps points expressed in frame ``a`` into frame ``b``:
``p_b = a_to_b @ p_a``. Composition reads right to left:
``a_to_c = b_to_c @ a_to_b``. Every function accepts arbitrary leading batch dimensions.
"""

from __future__ import annotations

import math

import torch
from kornia.geometry.linalg import transform_points as _kornia_transform_points
from torch import Tensor

__all__ = [
    "invert_pose",
    "make_pose",
    "relative_pose",
    "rotation_z",
    "transform_points",
    "yaw_of",
]


def make_pose(rotation: Tensor, translation: Tensor) -> Tensor:
    """Build ``(..., 4, 4)`` poses from ``(..., 3, 3)`` rotations and ``(..., 3)`` translations."""
    batch = rotation.shape[:-2]
    pose = torch.zeros(*batch, 4, 4, dtype=rotation.dtype, device=rotation.device)
    pose[..., :3, :3] = rotation
    pose[..., :3, 3] = translation
    pose[..., 3, 3] = 1.0
    return pose


def invert_pose(pose: Tensor) -> Tensor:
    """Exact inverse of rigid ``(..., 4, 4)`` poses (``R^T``, ``-R^T t``), no general matrix inverse."""
    rot_t = pose[..., :3, :3].transpose(-1, -2)
    return make_pose(rot_t, -(rot_t @ pose[..., :3, 3:4]).squeeze(-1))


def relative_pose(src_to_global: Tensor, dst_to_global: Tensor) -> Tensor:
    """The pose mapping frame ``src`` into frame ``dst`` given both frames' poses in a common frame.

    With ``ego_to_global`` of two frames this is the ego-motion transform
    ``T_{g->e}^{dst} T_{e->g}^{src}`` (DuOcc Eq. 1).

    Args:
        src_to_global: ``(..., 4, 4)``.
        dst_to_global: ``(..., 4, 4)``.

    Returns:
        ``(..., 4, 4)`` ``src_to_dst``.
    """
    return invert_pose(dst_to_global) @ src_to_global


def transform_points(pose: Tensor, points: Tensor) -> Tensor:
    """Apply ``(B, 4, 4)`` (or ``(4, 4)``) poses to ``(B, N, 3)`` (or ``(N, 3)``) points."""
    if pose.dim() == 2 and points.dim() == 2:
        return _kornia_transform_points(pose[None], points[None])[0]
    if pose.dim() == 2:
        pose = pose.expand(points.shape[0], 4, 4)
    return _kornia_transform_points(pose, points)


def rotation_z(yaw: Tensor | float) -> Tensor:
    """``(..., 3, 3)`` rotation about +z by ``yaw`` radians (counter-clockwise seen from above)."""
    yaw = torch.as_tensor(yaw, dtype=torch.float32) if not isinstance(yaw, Tensor) else yaw
    c, s = torch.cos(yaw), torch.sin(yaw)
    zero, one = torch.zeros_like(yaw), torch.ones_like(yaw)
    return torch.stack(
        [torch.stack([c, -s, zero], -1), torch.stack([s, c, zero], -1), torch.stack([zero, zero, one], -1)], -2
    )


def yaw_of(pose: Tensor) -> Tensor:
    """Heading (rotation about z) of ``(..., 4, 4)`` or ``(..., 3, 3)`` transforms, radians in (-pi, pi]."""
    return torch.atan2(pose[..., 1, 0], pose[..., 0, 0])


def wrap_angle(angle: Tensor) -> Tensor:
    """Wrap angles to ``[-pi, pi)``."""
    return angle - 2 * math.pi * torch.floor((angle + math.pi) / (2 * math.pi))
