"""Occupancy and LiDAR seen through the data set's own cameras.

* :func:`occupancy_in_cameras`: per-pixel ray casting through the label grid with each camera's
  rays (:func:`occplug.geometry.camera_rays` of the effective intrinsics ``img_aug @ K`` and
  ``cam_to_ego``, so it is exact under image augmentation): the class of the first occupied voxel
  each pixel sees, ``-1`` where it sees none.
* :func:`blend_overlay`: that class image as a semi-transparent overlay on the camera image.
* :func:`lidar_in_cameras`: LiDAR points projected into each camera with their range.
* :func:`rig_layout`: where each camera goes in a surround-view figure, by its name.

Images are ``(N, 3, H, W)`` float in [0, 1] (the :class:`~occplug.data.Frame` layout); outputs
are numpy ``(H, W, 3)`` uint8 per camera.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from occplug.geometry import GridSpec, camera_rays, project_to_image

from .render3d import coarse_to_fine_first_hit
from .style import Palette

__all__ = ["LidarView", "blend_overlay", "downscale_matrix", "lidar_in_cameras", "occupancy_in_cameras", "rig_layout"]

#: Surround-rig slots ``(row, column)``: front-left, front, front-right above back-left, back,
#: back-right (keys are camera names without a ``CAM_`` prefix, upper case).
RIG_SLOTS: dict[str, tuple[int, int]] = {
    "FRONT_LEFT": (0, 0),
    "FRONT": (0, 1),
    "FRONT_RIGHT": (0, 2),
    "BACK_LEFT": (1, 0),
    "BACK": (1, 1),
    "BACK_RIGHT": (1, 2),
}


def rig_layout(camera_names: Sequence[str], columns: int = 3) -> list[tuple[int, int]]:
    """``(row, column)`` of each camera (in the given order) in a surround-view grid.

    nuScenes-style names (``CAM_FRONT_LEFT``, ``FRONT``, ``cam_back_right`` ...) take their rig
    slot; any other camera (or a second one wanting a taken slot) fills the next free slot in
    reading order, adding rows below as needed.
    """
    taken: set[tuple[int, int]] = set()
    out: list[tuple[int, int] | None] = []
    for name in camera_names:
        key = name.upper().removeprefix("CAM_").strip("_")
        slot = RIG_SLOTS.get(key)
        if slot is not None and slot not in taken and slot[1] < columns:
            taken.add(slot)
            out.append(slot)
        else:
            out.append(None)
    free = (divmod(i, columns) for i in range(10_000))
    for i, slot in enumerate(out):
        if slot is None:
            cell = next(c for c in free if c not in taken)
            taken.add(cell)
            out[i] = cell
    return out  # type: ignore[return-value]


def downscale_matrix(factor: int) -> Tensor:
    """``(3, 3)`` pixel map from an image to the one ``factor`` times smaller in each direction,
    in the pixel-centre convention (pixel ``u'`` covers ``u' * f .. u' * f + f - 1``)."""
    s = 1.0 / factor
    return torch.tensor([[s, 0.0, (s - 1) / 2], [0.0, s, (s - 1) / 2], [0.0, 0.0, 1.0]])


def occupancy_in_cameras(
    labels: Tensor,
    grid: GridSpec,
    palette: Palette,
    intrinsics: Tensor,
    cam_to_ego: Tensor,
    image_size: tuple[int, int],
    img_aug: Tensor | None = None,
    max_rays: int | None = 400_000,
) -> Tensor:
    """The class of the first occupied voxel seen by every pixel of every camera.

    Args:
        labels: ``(X, Y, Z)`` integer class ids on ``grid`` (ego frame).
        grid: the label grid.
        palette: which ids are free / ignored (never hit).
        intrinsics: ``(N, 3, 3)``; cam_to_ego: ``(N, 4, 4)``; img_aug: ``(N, 3, 3)`` or None.
        image_size: ``(H, W)`` of the (augmented) images.
        max_rays: cast at most about this many rays: for larger rigs the pixels are cast at an
            integer stride ``s`` (one ray per ``s x s`` block, through the block's centre) and
            the result repeated over the block; None casts one ray per pixel.

    Returns:
        ``(N, H, W)`` int64 class ids, ``-1`` where the pixel's ray leaves the grid unobstructed.
    """
    n = intrinsics.shape[0]
    h, w = image_size
    stride = 1 if max_rays is None else max(1, math.ceil(math.sqrt(n * h * w / max_rays)))
    hs, ws = math.ceil(h / stride), math.ceil(w / stride)
    aug = torch.eye(3).expand(n, 3, 3) if img_aug is None else img_aug
    aug = downscale_matrix(stride).to(torch.float64) @ aug.to(torch.float64) if stride > 1 else aug.to(torch.float64)
    origins, dirs, _ = camera_rays(intrinsics.to(torch.float64), cam_to_ego.to(torch.float64), hs, ws, aug)
    dirs = dirs.reshape(-1, 3)
    origins = origins[:, None, :].expand(n, hs * ws, 3).reshape(-1, 3)
    labels = labels.long().cpu()
    hit, _ = coarse_to_fine_first_hit(palette.occupied(labels), grid, origins, dirs)
    found = hit[:, 0] >= 0
    cls = torch.full((hit.shape[0],), -1, dtype=torch.int64)
    cls[found] = labels[hit[found, 0], hit[found, 1], hit[found, 2]]
    cls = cls.reshape(n, hs, ws)
    if stride > 1:
        cls = cls.repeat_interleave(stride, dim=1).repeat_interleave(stride, dim=2)[:, :h, :w]
    return cls


def blend_overlay(image: Tensor, classes: Tensor, palette: Palette, alpha: float = 0.5) -> np.ndarray:
    """A camera image with a semantic overlay.

    Args:
        image: ``(3, H, W)`` float RGB in [0, 1].
        classes: ``(H, W)`` int class ids (``-1`` / free / ignored: no overlay).
        palette: class colours.
        alpha: overlay opacity.

    Returns:
        ``(H, W, 3)`` uint8: ``alpha * colour + (1 - alpha) * image`` where a class is seen, the
        image elsewhere.
    """
    rgb = image.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255.0
    colored = palette.occupied(classes.long().cpu()).numpy()
    color = palette.colorize(classes).astype(np.float64)
    out = np.where(colored[..., None], alpha * color + (1 - alpha) * rgb, rgb)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


@dataclass
class LidarView:
    """LiDAR points visible in one camera.

    Attributes:
        uv: ``(P, 2)`` float pixel coordinates (u = column, v = row) in the camera image.
        range: ``(P,)`` float distance from the LiDAR sensor, metres.
        depth: ``(P,)`` float camera-frame depth, metres.
    """

    uv: np.ndarray
    range: np.ndarray
    depth: np.ndarray


def lidar_in_cameras(
    points: Tensor,
    lidar_to_ego: Tensor,
    intrinsics: Tensor,
    cam_to_ego: Tensor,
    image_size: tuple[int, int],
    img_aug: Tensor | None = None,
    min_depth: float = 0.5,
) -> list[LidarView]:
    """Project LiDAR points into every camera.

    Args:
        points: ``(P, >=3)`` points in the **lidar** frame (x, y, z, ...).
        lidar_to_ego: ``(4, 4)``.
        intrinsics: ``(N, 3, 3)``; cam_to_ego: ``(N, 4, 4)``; img_aug: ``(N, 3, 3)`` or None.
        image_size: ``(H, W)`` of the (augmented) images.
        min_depth: points closer than this in front of a camera are dropped.

    Returns:
        One :class:`LidarView` per camera, far points first (draw in order: near points on top).
    """
    from occplug.geometry import transform_points

    xyz = points[:, :3].float()
    rng = xyz.norm(dim=-1)
    ego = transform_points(lidar_to_ego.float(), xyz)
    n = intrinsics.shape[0]
    h, w = image_size
    uv, depth = project_to_image(
        ego[None].expand(n, -1, 3), intrinsics.float(), cam_to_ego.float(), None if img_aug is None else img_aug.float()
    )
    out = []
    for c in range(n):  # one entry per camera (a handful), the points are vectorised
        u, v, d = uv[c, :, 0], uv[c, :, 1], depth[c]
        keep = (d > min_depth) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
        order = torch.argsort(d[keep], descending=True)
        out.append(
            LidarView(uv=uv[c][keep][order].numpy(), range=rng[keep][order].numpy(), depth=d[keep][order].numpy())
        )
    return out
