"""Pinhole cameras: projection and unprojection between the ego frame and image pixels.

Conventions
-----------
* Camera frame: OpenCV (x right, y down, z forward), metres.
* Pixels: ``(u, v)`` = (column, row); the centre of pixel ``[row, col]`` is at ``u = col``,
  ``v = row`` (OpenCV / nuScenes intrinsics). Depth is the camera-frame ``z``, not the range.
* ``intrinsics`` ``K`` is the 3x3 matrix of the camera as calibrated (original image).
* ``img_aug`` ``A`` is a 3x3 matrix recording every image-plane augmentation (resize, crop,
  flip, rotation) applied to the original image: an original pixel ``(u, v, 1)`` lands at
  ``A @ (u, v, 1)`` in the image the network sees. The effective intrinsics are ``A @ K``,
  which keeps projection exact under augmentation.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .transforms import invert_pose, transform_points

__all__ = ["effective_intrinsics", "pixel_centers", "project_to_image", "unproject_from_image"]


def effective_intrinsics(intrinsics: Tensor, img_aug: Tensor | None = None) -> Tensor:
    """``A @ K``: the ``(..., 3, 3)`` intrinsics of the augmented image."""
    return intrinsics if img_aug is None else img_aug @ intrinsics


def _flatten_points(points: Tensor, batch_shape: torch.Size) -> tuple[Tensor, int]:
    lead = math.prod(batch_shape)  # plain ints: traceable by torch.export
    return points.reshape(lead, -1, 3), lead


def project_to_image(
    points_ego: Tensor, intrinsics: Tensor, cam_to_ego: Tensor, img_aug: Tensor | None = None, eps: float = 1e-6
) -> tuple[Tensor, Tensor]:
    """Project ego-frame points into (augmented) images.

    Args:
        points_ego: ``(..., P, 3)`` points in the ego frame; the leading dims ``...`` match the
            cameras' (e.g. ``(B, N, P, 3)`` for ``B`` samples and ``N`` cameras).
        intrinsics: ``(..., 3, 3)``.
        cam_to_ego: ``(..., 4, 4)``.
        img_aug: ``(..., 3, 3)`` or None for the identity.
        eps: points with depth below this are returned with ``uv`` = NaN-free garbage; mask them
            with ``depth > eps``.

    Returns:
        ``uv``: ``(..., P, 2)`` pixel coordinates; ``depth``: ``(..., P)`` camera-frame z, metres.
    """
    batch = cam_to_ego.shape[:-2]
    pts, lead = _flatten_points(points_ego, batch)
    ego_to_cam = invert_pose(cam_to_ego).reshape(lead, 4, 4)
    cam = transform_points(ego_to_cam, pts)
    depth = cam[..., 2]
    safe = torch.where(depth.abs() < eps, torch.full_like(depth, eps), depth)
    # the full matrix, not kornia's project_points: that reads only fx, fy, cx, cy, and an img_aug with
    # a rotation puts off-diagonal terms into A @ K
    k = effective_intrinsics(intrinsics, img_aug).reshape(lead, 3, 3).to(cam.dtype)
    xy1 = torch.cat([cam[..., :2] / safe[..., None], torch.ones_like(safe[..., None])], -1)
    uv = (xy1 @ k.transpose(-1, -2))[..., :2]
    out_shape = points_ego.shape[:-1]
    return uv.reshape(*out_shape, 2), depth.reshape(out_shape)


def unproject_from_image(
    uv: Tensor, depth: Tensor, intrinsics: Tensor, cam_to_ego: Tensor, img_aug: Tensor | None = None
) -> Tensor:
    """Inverse of :func:`project_to_image`: pixels with depth back to ego-frame points.

    Args:
        uv: ``(..., P, 2)`` pixel coordinates in the (augmented) image.
        depth: ``(..., P)`` camera-frame z, metres.
        intrinsics, cam_to_ego, img_aug: as in :func:`project_to_image`, leading dims ``...``.

    Returns:
        ``(..., P, 3)`` ego-frame points.
    """
    batch = cam_to_ego.shape[:-2]
    lead = math.prod(batch)  # plain ints: traceable by torch.export
    p = uv.shape[-2]
    k = effective_intrinsics(intrinsics, img_aug).reshape(lead, 3, 3)
    uv1 = torch.cat([uv.reshape(lead, p, 2), torch.ones_like(uv.reshape(lead, p, 2)[..., :1])], -1)
    rays = uv1 @ torch.linalg.inv(k.to(uv1.dtype)).transpose(-1, -2)  # (x/z, y/z, 1): full inverse (see above)
    cam = rays / rays[..., 2:3] * depth.reshape(lead, p, 1)
    ego = transform_points(cam_to_ego.reshape(lead, 4, 4), cam)
    return ego.reshape(*uv.shape[:-1], 3)


def pixel_centers(height: int, width: int, device: torch.device | str | None = None) -> Tensor:
    """``(H, W, 2)`` float32 ``(u, v)`` of every pixel centre (``u = col``, ``v = row``)."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=torch.float32),
        torch.arange(width, device=device, dtype=torch.float32),
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1)
