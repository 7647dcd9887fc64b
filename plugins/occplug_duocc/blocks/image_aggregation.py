"""Sparse4D v3's deformable image aggregation, the image side of DuOcc's detector (:mod:`.detector`, §3.2 I2Q).

Pure PyTorch, no custom ops. Each anchor's key points (:data:`FIXED_KEY_POINTS` plus learned ones, placed by
:func:`~.boxes.box_points`) are projected into every camera and read bilinearly on every image feature level
(:func:`sample_image_features`, ``grid_sample``); :class:`DeformableImageAggregation` weights the samples over
cameras x levels x points per channel group and sums them.

Pixels follow :mod:`occplug.geometry.cameras`: pixel ``[row, col]`` has its centre at ``(u, v) = (col, row)``
of the augmented image (``img_aug @ intrinsics``); a feature level of stride ``s`` covers the image exactly, so
``grid_sample(..., align_corners=False)`` at ``((u + 0.5) / W, (v + 0.5) / H)`` reads every level at the point.

Assumptions (where the paper, §3.2 "I2Q" and suppl. A.4, is silent; the public code's choices, from
its Sparse4D v3 detector in ``models/heads/queryagg/``, are these):

* Key points: the code's 7 fixed (centre, +-0.45 x size along each box axis) plus ``num_learnable_points``
  predicted from the instance feature within +-0.5 x size; rotated by the anchor's yaw (sin/cos normalised).
  The camera embedding is an MLP of ``cam_to_ego[:3, :4]`` (the code embeds the 3x4 ego-to-image matrix,
  whose pixel-unit entries need normalising); a key point behind a camera (depth <= 1e-5 m) reads zeros.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
import torch.utils.checkpoint
from torch import Tensor, nn

from occplug.geometry import project_to_image

from .boxes import box_points

__all__ = ["DeformableImageAggregation", "FIXED_KEY_POINTS", "sample_image_features"]

#: The 7 fixed key points of a box, as fractions of ``(l, w, h)`` in the box frame (Sparse4D ``fix_scale``).
FIXED_KEY_POINTS = (
    (0.0, 0.0, 0.0),
    (0.45, 0.0, 0.0),
    (-0.45, 0.0, 0.0),
    (0.0, 0.45, 0.0),
    (0.0, -0.45, 0.0),
    (0.0, 0.0, 0.45),
    (0.0, 0.0, -0.45),
)


def sample_image_features(
    levels: Sequence[Tensor],
    points: Tensor,
    image_size: tuple[int, int],
    intrinsics: Tensor,
    cam_to_ego: Tensor,
    img_aug: Tensor | None = None,
    eps: float = 1e-5,
) -> tuple[list[Tensor], Tensor, Tensor]:
    """Bilinearly read every camera's feature levels at ego-frame points.

    Args:
        levels: ``L`` tensors ``(B, N, C_l, H_l, W_l)``, each covering the whole (augmented) image.
        points: ``(B, Q, P, 3)`` ego-frame points.
        image_size: ``(H, W)`` of the (augmented) images, pixels.
        intrinsics: ``(B, N, 3, 3)`` original-image intrinsics.
        cam_to_ego: ``(B, N, 4, 4)``.
        img_aug: ``(B, N, 3, 3)`` original -> augmented pixels, or None (identity).
        eps: points with camera depth at or below this read zeros.

    Returns:
        ``features``: ``L`` tensors ``(B, Q, P, N, C_l)`` (zeros outside an image or behind its camera);
        ``uv``: ``(B, N, Q, P, 2)`` pixel coordinates in the augmented images (:func:`~occplug.geometry.project_to_image`);
        ``valid``: ``(B, N, Q, P)`` bool, depth > ``eps``.
    """
    b, q, p = points.shape[:3]
    n = cam_to_ego.shape[1]
    pts = points.reshape(b, 1, q * p, 3).expand(b, n, q * p, 3).to(cam_to_ego.dtype)
    uv, depth = project_to_image(pts, intrinsics, cam_to_ego, img_aug)
    valid = depth > eps
    h, w = image_size
    scale = uv.new_tensor([w, h])
    grid = (uv + 0.5) / scale * 2.0 - 1.0
    grid = torch.where(valid[..., None], grid, torch.full_like(grid, -2.0))  # behind the camera: outside
    grid = grid.reshape(b * n, 1, q * p, 2)
    out = []
    for level in levels:
        c = level.shape[2]
        s = F.grid_sample(
            level.reshape(b * n, c, *level.shape[-2:]), grid.to(level.dtype), align_corners=False, padding_mode="zeros"
        )
        out.append(s.view(b, n, c, q, p).permute(0, 3, 4, 1, 2))
    return out, uv.view(b, n, q, p, 2), valid.view(b, n, q, p)


def _mlp_block(cin: int, cout: int, repeats: int = 2) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(repeats):
        layers += [nn.Linear(cin if i == 0 else cout, cout), nn.ReLU(inplace=True), nn.LayerNorm(cout)]
    return nn.Sequential(*layers)


class DeformableImageAggregation(nn.Module):
    """Sparse4D's deformable aggregation: each anchor reads the images at its key points.

    ``P = 7 + num_learnable_points`` key points per anchor (:data:`FIXED_KEY_POINTS` plus learnable ones) are
    projected into every camera and sampled bilinearly on every level; per group of ``C / groups`` channels,
    weights predicted from ``feature + anchor embedding + camera embedding`` are softmaxed over
    cameras x levels x points, and the weighted sum goes through an output projection.

    Args:
        channels: ``C``.
        level_channels: channels of each image level (a bias-free Linear maps a level to ``C`` where they differ).
        num_learnable_points: learnable key points per anchor (code 6).
        groups: weight groups (code 8).
        dropout: on the output.
        checkpoint: with gradients on, keep none of the sampled ``(B, Q, P, N, L, C)`` features for the backward
            pass and sample again there (``torch.utils.checkpoint``). The public code's fused CUDA aggregation
            keeps none either; in plain PyTorch they are most of the detector's training memory at the paper's
            size (1,685 of 6,781 MiB saved per sample at 900 queries, 13 points, 6 cameras, 256 channels,
            ``scripts/real_size.py``). Values and gradients are unchanged (tested).
    """

    def __init__(
        self,
        channels: int,
        level_channels: Sequence[int],
        num_learnable_points: int = 6,
        groups: int = 8,
        dropout: float = 0.1,
        checkpoint: bool = False,
    ) -> None:
        super().__init__()
        self.checkpoint = bool(checkpoint)
        if channels % groups:
            raise ValueError(f"DeformableImageAggregation: channels {channels} not divisible by groups {groups}")
        self.channels, self.groups, self.num_levels = int(channels), int(groups), len(level_channels)
        self.num_learnable = int(num_learnable_points)
        self.num_points = len(FIXED_KEY_POINTS) + self.num_learnable
        self.register_buffer("fixed_scale", torch.tensor(FIXED_KEY_POINTS), persistent=False)
        self.learnable = nn.Linear(channels, self.num_learnable * 3) if self.num_learnable else None
        self.level_proj = nn.ModuleList(
            nn.Identity() if c == channels else nn.Linear(c, channels, bias=False) for c in level_channels
        )
        self.camera_embed = _mlp_block(12, channels)
        self.weights = nn.Linear(channels, groups * self.num_levels * self.num_points)
        self.output_proj = nn.Linear(channels, channels)
        self.drop = nn.Dropout(dropout)
        nn.init.zeros_(self.weights.weight)
        nn.init.zeros_(self.weights.bias)

    def key_points(self, anchors: Tensor, query: Tensor) -> Tensor:
        """``(B, Q, P, 3)`` ego-frame key points of ``(B, Q, 10)`` anchors given ``(B, Q, C)`` feature + embedding.

        Point 0 is the box centre; points 1-6 are at +-0.45 x (l, w, h) along the box axes; the rest are learned.
        """
        b, q = anchors.shape[:2]
        scale = self.fixed_scale.to(anchors.dtype).expand(b, q, -1, 3)
        if self.learnable is not None:
            learned = self.learnable(query).view(b, q, self.num_learnable, 3).sigmoid() - 0.5
            scale = torch.cat([scale, learned], dim=2)
        return box_points(anchors, scale)

    def forward(
        self,
        feature: Tensor,
        anchor_embed: Tensor,
        anchors: Tensor,
        levels: Sequence[Tensor],
        image_size: tuple[int, int],
        intrinsics: Tensor,
        cam_to_ego: Tensor,
        img_aug: Tensor | None = None,
    ) -> Tensor:
        """Aggregate image features per anchor.

        Args:
            feature: ``(B, Q, C)`` instance features.
            anchor_embed: ``(B, Q, C)`` their anchor embedding.
            anchors: ``(B, Q, 10)`` encoded anchors, ego frame.
            levels, image_size, intrinsics, cam_to_ego, img_aug: see :func:`sample_image_features`.

        Returns:
            ``(B, Q, C)`` aggregated features (after the output projection and dropout).
        """
        query = feature + anchor_embed
        args = (query, anchors, tuple(levels), image_size, intrinsics, cam_to_ego, img_aug)
        if self.checkpoint and torch.is_grad_enabled():
            agg = torch.utils.checkpoint.checkpoint(self._aggregate, *args, use_reentrant=False)
        else:
            agg = self._aggregate(*args)
        return self.drop(self.output_proj(agg))

    def _aggregate(
        self,
        query: Tensor,
        anchors: Tensor,
        levels: Sequence[Tensor],
        image_size: tuple[int, int],
        intrinsics: Tensor,
        cam_to_ego: Tensor,
        img_aug: Tensor | None,
    ) -> Tensor:
        """``(B, Q, C)`` weighted sum of the samples (before the output projection); see :meth:`forward`."""
        b, q, c = query.shape
        points = self.key_points(anchors, query)
        sampled, _, _ = sample_image_features(levels, points, image_size, intrinsics, cam_to_ego, img_aug)
        feats = torch.stack([proj(s) for proj, s in zip(self.level_proj, sampled, strict=True)], dim=4)  # B Q P N L C
        n = feats.shape[3]
        cam = self.camera_embed(cam_to_ego[..., :3, :4].reshape(b, n, 12).to(query.dtype))  # (B, N, C)
        logits = self.weights(query[:, :, None] + cam[:, None])  # (B, Q, N, L*P*G)
        g, lv, p = self.groups, self.num_levels, self.num_points
        w = logits.view(b, q, n, lv, p, g).permute(0, 1, 5, 2, 3, 4).reshape(b, q, g, n * lv * p).softmax(-1)
        w = w.view(b, q, g, n, lv, p).permute(0, 1, 5, 3, 4, 2)[..., None]  # (B, Q, P, N, L, G, 1)
        return (feats.view(b, q, p, n, lv, g, c // g) * w).sum(dim=(2, 3, 4)).reshape(b, q, c)
