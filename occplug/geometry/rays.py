"""Rays from cameras and LiDARs, in the ego frame."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .cameras import effective_intrinsics, pixel_centers

__all__ = ["camera_rays", "lidar_ray_directions"]


def camera_rays(
    intrinsics: Tensor, cam_to_ego: Tensor, height: int, width: int, img_aug: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """One ray per pixel centre of each camera.

    Args:
        intrinsics: ``(..., 3, 3)``; cam_to_ego: ``(..., 4, 4)``; img_aug: ``(..., 3, 3)`` or None.
        height, width: size of the (augmented) image, pixels.

    Returns:
        ``origins`` ``(..., 3)`` camera centres in the ego frame;
        ``directions`` ``(..., H, W, 3)`` unit ray directions in the ego frame;
        ``z_per_metre`` ``(..., H, W)``: camera-frame depth gained per metre along the ray, so a
        hit at range ``r`` has depth ``r * z_per_metre``.
    """
    k = effective_intrinsics(intrinsics, img_aug)
    uv = pixel_centers(height, width, device=k.device).to(k.dtype)
    uv1 = torch.cat([uv, torch.ones_like(uv[..., :1])], dim=-1)  # (H, W, 3)
    k_inv = torch.linalg.inv(k)  # (..., 3, 3)
    d_cam = torch.einsum("...ij,hwj->...hwi", k_inv, uv1)
    d_cam = F.normalize(d_cam, dim=-1)
    rot = cam_to_ego[..., :3, :3]
    d_ego = torch.einsum("...ij,...hwj->...hwi", rot, d_cam)
    return cam_to_ego[..., :3, 3], d_ego, d_cam[..., 2]


def lidar_ray_directions(elevations_deg: Tensor, azimuth_steps: int) -> Tensor:
    """Unit directions of a spinning LiDAR in its own frame (x forward, y left, z up).

    Args:
        elevations_deg: ``(R,)`` beam elevation angles, degrees (positive up).
        azimuth_steps: number of firings per revolution, evenly spaced from azimuth 0.

    Returns:
        ``(R, A, 3)`` float32 directions; beam ``r``, firing ``a`` points at azimuth ``2*pi*a/A``
        counter-clockwise from +x.
    """
    el = torch.deg2rad(elevations_deg.to(torch.float32))[:, None]
    az = torch.arange(azimuth_steps, dtype=torch.float32)[None, :] * (2 * torch.pi / azimuth_steps)
    el, az = torch.broadcast_tensors(el, az)
    return torch.stack([torch.cos(el) * torch.cos(az), torch.cos(el) * torch.sin(az), torch.sin(el)], -1)
