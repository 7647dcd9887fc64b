"""OccLE's scatter-accumulated projection (§3.4, Eq. 5) and its distance-weighted alternative (Appendix C.1).

The fused feature grid ``F_3d`` is projected onto a camera's image plane by summing, per pixel, the features
of every voxel whose centre projects into that pixel: ``F_2d(u, v) = sum_{p -> (u, v)} F_3d(p)``. A 2D head
(:class:`ProjectionHead`) turns ``F_2d`` into the projected segmentation ``y``, supervised with the aligned
pseudo labels ``s̄`` (``l_ce(y, s̄)`` in Eq. 6), so every voxel along a ray, annotated or not, receives a
semantic signal.

Frames and conventions are the core's (:mod:`occplug.geometry.cameras`): the grid is in the ego frame, cameras
are placed by ``cam_to_ego`` (OpenCV camera axes), and the centre of pixel ``[row, col]`` is at ``u = col``,
``v = row``, so a voxel lands in pixel ``(round(v), round(u))`` of its projected centre.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor, nn

from occplug.constraints import check_choices
from occplug.geometry import GridSpec, project_to_image
from occplug.nn import PixelNet
from occplug.ops import splat

__all__ = ["ProjectionHead", "ScatterProjection", "feature_map_intrinsics", "scatter_project"]

ProjectionMode = Literal["sum", "distance"]
_MODES = ("sum", "distance")
_MIN_DEPTH = 1e-6  # camera-frame z below which a voxel counts as behind the camera (project_to_image's eps)


def feature_map_intrinsics(intrinsics: Tensor, stride: int) -> Tensor:
    """Intrinsics of a feature map downsampled ``stride`` times from the image the intrinsics describe.

    Follows the core's feature-cell convention (:func:`occplug.ops.feature_cell_centers`): cell ``(r, c)`` of
    the feature map is centred on image pixel ``(s*c + (s-1)/2, s*r + (s-1)/2)``, so an image point ``u`` lies
    at feature coordinate ``(u - (s-1)/2) / s``.

    Args:
        intrinsics: ``(..., 3, 3)`` pinhole matrices of the image (already ``img_aug @ K`` if augmented).
        stride: integer downsampling factor ``s >= 1`` of the feature map.

    Returns:
        ``(..., 3, 3)`` intrinsics mapping camera-frame points to feature-map ``(u, v)``.
    """
    if stride < 1:
        raise ValueError(f"feature_map_intrinsics: stride must be >= 1, got {stride}")
    s = float(stride)
    scale = torch.tensor(
        [[1 / s, 0.0, -(s - 1) / (2 * s)], [0.0, 1 / s, -(s - 1) / (2 * s)], [0.0, 0.0, 1.0]],
        dtype=intrinsics.dtype,
        device=intrinsics.device,
    )
    return scale @ intrinsics


def scatter_project(
    volume: Tensor,
    grid: GridSpec,
    intrinsics: Tensor,
    cam_to_ego: Tensor,
    image_size: tuple[int, int],
    mode: ProjectionMode = "sum",
    img_aug: Tensor | None = None,
) -> Tensor:
    """Scatter-accumulate a voxel feature grid onto camera image planes (OccLE Eq. 5).

    Every voxel centre is projected with :func:`occplug.geometry.project_to_image`; its feature is added to the
    pixel it lands in. Voxels behind a camera (camera-frame depth ``<= 1e-6``) or projecting outside the
    ``H x W`` image contribute nothing. Vectorised: one ``index_add_`` (:func:`occplug.ops.splat`) over all
    (camera, voxel) pairs; differentiable with respect to ``volume``.

    Modes:

    * ``"sum"`` (the paper's): ``F_2d(u, v) = sum_{p -> (u, v)} F_3d(p)``.
    * ``"distance"`` (the ablation of Appendix C.1, "weights features by the distance between each voxel and
      the camera"): ``F_2d(u, v) = sum_p w_p F_3d(p)`` with normalised inverse-distance weights
      ``w_p = n_uv * (1 / d_p) / sum_{q -> (u, v)} (1 / d_q)``, where ``d_p`` is the Euclidean distance from the
      camera centre to the voxel centre (clamped below at half the smallest voxel edge) and ``n_uv`` is the
      number of voxels projecting into the pixel. The weights of a pixel average to 1, so the pixel's total
      weight equals the ``"sum"`` mode's and the mode only shifts weight toward near voxels (a voxel ``k``
      times farther than another on the same ray gets ``1/k`` of its weight); with a single voxel, or equal
      distances, both modes agree.

    Args:
        volume: ``(B, C, X, Y, Z)`` features on ``grid`` (ego frame); ``(X, Y, Z) == grid.shape``.
        grid: the voxel grid (metric or contracted; voxel centres are taken uncontracted, in metres).
        intrinsics: ``(B, 3, 3)`` or ``(B, N, 3, 3)`` pinhole matrices **of the output image**: for a feature
            map rather than the full image, scale them first (:func:`feature_map_intrinsics`).
        cam_to_ego: ``(B, 4, 4)`` or ``(B, N, 4, 4)`` camera -> ego poses (the core's ``Batch.cam_to_ego``;
            OpenCV camera axes). Its inverse is the paper's extrinsic ``T`` (ego -> camera).
        image_size: ``(H, W)`` of the output image.
        mode: ``"sum"`` or ``"distance"`` (see above).
        img_aug: optional ``(B, 3, 3)`` / ``(B, N, 3, 3)`` image-plane augmentation, as in ``project_to_image``.

    Returns:
        ``(B, C, H, W)`` (cameras given as ``(B, ...)``) or ``(B, N, C, H, W)`` (cameras ``(B, N, ...)``),
        the volume's dtype; zero at pixels no voxel projects into.
    """
    if mode not in _MODES:
        raise ValueError(f"scatter_project: mode must be one of {_MODES}, got {mode!r}")
    if volume.dim() != 5 or tuple(volume.shape[2:]) != tuple(grid.shape):
        raise ValueError(
            f"scatter_project: volume {tuple(volume.shape)} must be (B, C, X, Y, Z) with (X, Y, Z) = grid.shape "
            f"{tuple(grid.shape)}"
        )
    b, c = volume.shape[:2]
    cam_batch = cam_to_ego.shape[:-2]
    if len(cam_batch) not in (1, 2) or cam_batch[0] != b or intrinsics.shape[:-2] != cam_batch:
        raise ValueError(
            f"scatter_project: cameras must be (B, 4, 4) / (B, 3, 3) or (B, N, 4, 4) / (B, N, 3, 3) with B = {b}, "
            f"got cam_to_ego {tuple(cam_to_ego.shape)} and intrinsics {tuple(intrinsics.shape)}"
        )
    h, w = (int(v) for v in image_size)
    n = math.prod(cam_batch[1:])
    lead = b * n
    device = volume.device

    centers = grid.centers(device=device).reshape(1, -1, 3).to(cam_to_ego.dtype)  # (1, P, 3) ego frame
    num_vox = centers.shape[1]
    aug = None if img_aug is None else img_aug.reshape(lead, 3, 3)
    uv, depth = project_to_image(
        centers.expand(lead, num_vox, 3), intrinsics.reshape(lead, 3, 3), cam_to_ego.reshape(lead, 4, 4), aug
    )
    u, v = uv[..., 0], uv[..., 1]
    # pixel [row, col] covers u in [col - 0.5, col + 0.5): test bounds in float, before any int cast of far-off uv
    valid = (depth > _MIN_DEPTH) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
    cam_idx, vox_idx = valid.nonzero(as_tuple=True)  # (M,), (M,)
    col = torch.floor(u[cam_idx, vox_idx] + 0.5).long()
    row = torch.floor(v[cam_idx, vox_idx] + 0.5).long()
    pixel = cam_idx * (h * w) + row * w + col  # (M,) flat index into (B*N*H*W)

    feats = volume.reshape(b, c, num_vox).transpose(1, 2)[cam_idx // n, vox_idx]  # (M, C)
    if mode == "distance":
        cam_pos = cam_to_ego.reshape(lead, 4, 4)[:, :3, 3]
        floor = min(grid.voxel_size) / 2  # a voxel holding the camera would otherwise get an unbounded weight
        inv = 1.0 / (centers[0, vox_idx] - cam_pos[cam_idx]).norm(dim=-1).clamp_min(floor)
        inv_sum = inv.new_zeros(lead * h * w).index_add_(0, pixel, inv)
        count = torch.bincount(pixel, minlength=lead * h * w).to(inv.dtype)
        weight = inv * count[pixel] / inv_sum[pixel]
        feats = feats * weight.to(feats.dtype).unsqueeze(-1)

    out = splat(feats, pixel, lead * h * w)  # (B*N*H*W, C)
    out = out.reshape(b, n, h, w, c).permute(0, 1, 4, 2, 3)
    return out[:, 0] if len(cam_batch) == 1 else out


class ScatterProjection(nn.Module):
    """Module form of :func:`scatter_project` for a fixed grid and mode (no parameters).

    Args:
        grid: the voxel grid of the volumes it will project (ego frame).
        mode: ``"sum"`` (OccLE's scatter-accumulated projection, §3.4) or ``"distance"`` (the distance-weighted
            ablation, Appendix C.1); see :func:`scatter_project`.

    Forward: ``volume`` ``(B, C, X, Y, Z)``, ``intrinsics`` ``(B, [N,] 3, 3)``, ``cam_to_ego``
    ``(B, [N,] 4, 4)``, ``image_size`` ``(H, W)``, optional ``img_aug`` -> ``(B, [N,] C, H, W)``.
    """

    def __init__(self, grid: GridSpec, mode: ProjectionMode = "sum") -> None:
        super().__init__()
        check_choices(ScatterProjection.__init__, "ScatterProjection:", mode=mode)
        self.grid = grid
        self.mode = mode

    def forward(
        self,
        volume: Tensor,
        intrinsics: Tensor,
        cam_to_ego: Tensor,
        image_size: tuple[int, int],
        img_aug: Tensor | None = None,
    ) -> Tensor:
        """Project ``volume`` into the cameras; see :func:`scatter_project` for shapes and frames."""
        return scatter_project(volume, self.grid, intrinsics, cam_to_ego, image_size, mode=self.mode, img_aug=img_aug)

    def extra_repr(self) -> str:
        return f"grid={self.grid!r}, mode={self.mode!r}"


class ProjectionHead(PixelNet):
    """The 2D header of §3.4: projected feature map ``F_2d`` -> projected segmentation logits ``y``.

    ``3x3 conv -> BatchNorm -> ReLU -> 1x1 conv`` (the core's :class:`~occplug.nn.PixelNet`);
    the norm also absorbs the scale of the accumulated features, which grows with the number of voxels a ray
    crosses. With ``hidden_channels == 0`` it is a single 1x1 convolution.

    Args:
        in_channels: ``C`` of the projected features.
        num_classes: ``K`` classes of the pseudo labels ``s̄``.
        hidden_channels: width of the 3x3 layer (0: none).

    Forward: ``(B, C, H, W)`` -> ``(B, K, H, W)`` logits, same resolution.
    """

    def __init__(self, in_channels: int, num_classes: int, hidden_channels: int = 32) -> None:
        super().__init__(in_channels, hidden_channels, num_classes)
