"""DuOcc's image-to-query detector (I2Q, a small Sparse4D v3) and voxel-to-query aggregation (V2Q), paper §3.2.

Pure PyTorch, no custom ops. The pieces:

* :class:`SparseDetector` — anchor-based instance queries refined layer by layer from multi-view, multi-level
  image features (Sparse4D v3's deformable aggregation, done with ``grid_sample``), with temporal propagation of
  the top-k instances of the previous frame through an explicit :class:`DetectorState` (no hidden state).
* :func:`detection_loss` — Sparse4D v3's loss: Hungarian matching per layer (:func:`~.matching.hungarian_match`),
  sigmoid focal classification (:func:`occplug.nn.sigmoid_focal_loss`) and weighted L1 regression on
  :func:`~.matching.encode_boxes`.
* :class:`VoxelToQuery` — Eq. 6: 3D deformable attention of each query into the stream-aggregated volume.
* :func:`detection_map` — nuScenes-style mAP by BEV centre distance (the detector's metric on the synthetic world).
* :func:`select_detections` — Sparse4D's post-processing (top-k over queries x classes, score threshold).

Boxes. Decoded boxes use the :class:`~occplug.Frame` ``boxes`` layout, ``(..., 9)``
``[cx, cy, cz, l, w, h, yaw, vx, vy]`` in the **ego** frame of the current sample (metres, radians about +z from
+x, m/s), ``l`` along the heading. Anchors and regression live in Sparse4D's encoding (:func:`~.matching.encode_boxes`),
``(..., 10)`` ``[cx, cy, cz, log l, log w, log h, sin yaw, cos yaw, vx, vy]`` (:data:`BOX_DIM`).

Pixels follow :mod:`occplug.geometry.cameras`: pixel ``[row, col]`` has its centre at ``(u, v) = (col, row)``
of the augmented image (``img_aug @ intrinsics``); a feature level of stride ``s`` covers the image exactly, so
``grid_sample(..., align_corners=False)`` at ``((u + 0.5) / W, (v + 0.5) / H)`` reads every level at the point.

Assumptions (where the paper, §3.2 "I2Q"/"V2Q" and suppl. A.4, is silent; the public code's choices are in
``duocc-code-notes.md`` §3):

* §3.2 I2Q, anchors: 900 k-means anchors of the training boxes in the code; here ``anchor_centres`` when given
  (``python -m occplug_duocc.fit_anchors`` makes them as the code does, :mod:`.anchors`), else ``num_queries`` centres drawn
  uniformly (fixed seed) in ``anchor_range``; size ``anchor_size``, yaw 0, all learnable. The
  instance features start at zero (code) and are learnable unless ``learn_instance_feature=False`` (the code
  freezes them).
* §3.2 I2Q, layer order (code ``operation_order``): layer 1 = image deformable aggregation, FFN, LN, refine;
  later layers = temporal cross-attention (only with a valid state), self-attention, LN, image deformable
  aggregation, FFN, LN, refine. No quality (centerness / yawness) head, no point drop. Sparse4D v3's instance
  denoising (the code's 5 groups) is ``num_dn_groups`` (:mod:`.denoising`; 0, off, by default), without its
  temporal groups.
* Attention uses DETR's ``q = k = feature + anchor embedding, v = feature`` (the code concatenates the two
  into a 2C-wide attention); the anchor encoder is the code's four MLPs (position, size, yaw, velocity) with
  two (Linear, ReLU, LN) blocks each instead of four, channel split 1/2, 1/8, 1/8, 1/4.
* Key points: the code's 7 fixed (centre, +-0.45 x size along each box axis) plus ``num_learnable_points``
  predicted from the instance feature within +-0.5 x size; rotated by the anchor's yaw (sin/cos normalised).
  The camera embedding is an MLP of ``cam_to_ego[:3, :4]`` (the code embeds the 3x4 ego-to-image matrix,
  whose pixel-unit entries need normalising); a key point behind a camera (depth <= 1e-5 m) reads zeros.
* Refinement: residual deltas on every encoded dimension (centre, log size, sin/cos, velocity in m/s); the code
  predicts sin/cos absolutely and velocity as a displacement over ``dt``. The anchor is not detached between
  layers (Sparse4D).
* Temporal propagation (Sparse4D v3 ``InstanceBank``): the cache keeps the top-``num_temporal`` instances by
  confidence, with the cached ones' confidence decayed by ``confidence_decay`` (0.6) and maxed with the new
  one; after layer 1 (before it in a one-layer detector) the cached instances (moved into the current ego frame
  by the relative ego pose and, when ``use_velocity``, by constant velocity over ``dt``) are prepended to the top
  ``Q - k`` current queries, so ``Q`` stays ``num_queries``. A sample's cache is dropped when ``reset`` is set
  or ``|dt| > max_time_interval`` (2 s); later layers also cross-attend to the cached instances.
* Suppl. A.4 / code loss: focal (alpha 0.25, gamma 2) x 2.0 and L1 x 0.25 with per-dimension weights
  ``[2, 2, 2, 1, 1, 1, 1, 1, 1, 1]``, both divided by the number of matched ground truths in the batch (at least
  1), summed over layers; the box loss counts only matches whose score exceeds ``reg_score_threshold`` (0.05,
  Sparse4D's ``cls_threshold_to_reg``). DuOcc's overall weight 0.2 is the caller's.
* §3.2 V2Q (Eq. 6): ``heads x points`` learnable offsets per query within +-0.5 x box size, rotated by yaw
  (the code adds the 7 fixed key points; here the offset bias starts on a spread pattern instead); weights are
  a zero-initialised Linear, softmax over each head's points; ``W'_h`` is a bias-free projection applied after
  sampling (identical to projecting the volume first, since trilinear sampling is linear) and ``W_h`` the output
  projection over the concatenated heads.
* :func:`detection_map` follows the nuScenes devkit (greedy matching by score within each class, 101-point
  precision interpolation without an envelope, ``min_recall = min_precision = 0.1``); classes are those present
  in the ground truth.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Annotated

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occplug.constraints import NonNegative, Positive
from occplug.geometry import GridSpec, project_to_image, relative_pose, sample_volume, transform_points
from occplug.nn import sigmoid_focal_loss

from .denoising import DN_NOISE_SCALE, DenoisingQueries, denoising_loss, make_denoising_queries
from .matching import SPARSE4D_REG_WEIGHTS, encode_boxes, hungarian_match

if TYPE_CHECKING:
    from occplug.data import Batch

__all__ = [
    "BOX_DIM",
    "AnchorEncoder",
    "AsymmetricFFN",
    "DeformableImageAggregation",
    "box_points",
    "FIXED_KEY_POINTS",
    "SPARSE4D_LOSS_REG_WEIGHTS",
    "DetectorOutput",
    "DetectorState",
    "SparseDetector",
    "VoxelToQuery",
    "decode_boxes",
    "detection_loss",
    "detection_map",
    "propagate_state",
    "sample_image_features",
    "select_detections",
]

#: Width of the encoded box / anchor: ``[cx, cy, cz, log l, log w, log h, sin, cos, vx, vy]``.
BOX_DIM = 10
#: Sparse4D v3's per-dimension weights of the L1 box loss on the encoded box.
SPARSE4D_LOSS_REG_WEIGHTS = (2.0, 2.0, 2.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0)
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


# ---------------------------------------------------------------------------------------------- boxes


def decode_boxes(encoded: Tensor) -> Tensor:
    """Inverse of :func:`~.matching.encode_boxes`.

    Args:
        encoded: ``(..., 8)`` ``[x, y, z, log l, log w, log h, sin, cos]`` or ``(..., 10)`` with ``vx, vy``.

    Returns:
        ``(..., 7)`` ``[x, y, z, l, w, h, yaw]`` or ``(..., 9)`` with ``vx, vy`` (yaw from ``atan2(sin, cos)``).
    """
    yaw = torch.atan2(encoded[..., 6], encoded[..., 7])[..., None]
    return torch.cat([encoded[..., :3], encoded[..., 3:6].exp(), yaw, encoded[..., 8:]], dim=-1)


def _yaw_rotate(local: Tensor, sin_cos: Tensor) -> Tensor:
    """Rotate ``(..., P, 3)`` box-frame offsets about +z by the (normalised) ``(..., 1, 2)`` ``[sin, cos]``."""
    norm = sin_cos.norm(dim=-1, keepdim=True).clamp(min=1e-6)
    s, c = (sin_cos / norm).unbind(-1)  # broadcast against the point axis of ``local``
    x, y, z = local.unbind(-1)
    return torch.stack([c * x - s * y, s * x + c * y, z], dim=-1)


def box_points(anchors: Tensor, scales: Tensor) -> Tensor:
    """Ego-frame points of boxes at box-frame fractions of their size.

    Args:
        anchors: ``(B, Q, >=8)`` encoded boxes (:data:`BOX_DIM` layout), ego frame.
        scales: ``(B, Q, P, 3)`` fractions of ``(l, w, h)`` along the box's own axes (0 = centre).

    Returns:
        ``(B, Q, P, 3)`` ego-frame points.
    """
    local = scales * anchors[..., None, 3:6].exp()
    return anchors[..., None, :3] + _yaw_rotate(local, anchors[..., None, 6:8])


# ---------------------------------------------------------------------------------------------- image sampling


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


class AnchorEncoder(nn.Module):
    """Anchor embedding: MLPs of position, log size, (sin, cos) and velocity, concatenated to ``C`` channels.

    Forward: ``(B, Q, 10)`` encoded anchors -> ``(B, Q, C)``.
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        if channels < 16:
            raise ValueError(f"AnchorEncoder needs at least 16 channels, got {channels}")
        pos, size, yaw = channels // 2, channels // 8, channels // 8
        self.pos, self.size, self.yaw = _mlp_block(3, pos), _mlp_block(3, size), _mlp_block(2, yaw)
        self.vel = _mlp_block(2, channels - pos - size - yaw)

    def forward(self, anchors: Tensor) -> Tensor:
        return torch.cat(
            [
                self.pos(anchors[..., :3]),
                self.size(anchors[..., 3:6]),
                self.yaw(anchors[..., 6:8]),
                self.vel(anchors[..., 8:10]),
            ],
            dim=-1,
        )


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
    """

    def __init__(
        self,
        channels: int,
        level_channels: Sequence[int],
        num_learnable_points: int = 6,
        groups: int = 8,
        dropout: float = 0.1,
    ) -> None:
        super().__init__()
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
        b, q, c = feature.shape
        query = feature + anchor_embed
        points = self.key_points(anchors, query)
        sampled, _, _ = sample_image_features(levels, points, image_size, intrinsics, cam_to_ego, img_aug)
        feats = torch.stack([proj(s) for proj, s in zip(self.level_proj, sampled, strict=True)], dim=4)  # B Q P N L C
        n = feats.shape[3]
        cam = self.camera_embed(cam_to_ego[..., :3, :4].reshape(b, n, 12).to(feature.dtype))  # (B, N, C)
        logits = self.weights(query[:, :, None] + cam[:, None])  # (B, Q, N, L*P*G)
        g, lv, p = self.groups, self.num_levels, self.num_points
        w = logits.view(b, q, n, lv, p, g).permute(0, 1, 5, 2, 3, 4).reshape(b, q, g, n * lv * p).softmax(-1)
        w = w.view(b, q, g, n, lv, p).permute(0, 1, 5, 3, 4, 2)[..., None]  # (B, Q, P, N, L, G, 1)
        agg = (feats.view(b, q, p, n, lv, g, c // g) * w).sum(dim=(2, 3, 4)).reshape(b, q, c)
        return self.drop(self.output_proj(agg))


class AsymmetricFFN(nn.Module):
    """Sparse4D's FFN on ``[feature, aggregated]``: ``Linear(2C -> C)(x) + MLP(LN(x))`` (pre-norm, identity branch)."""

    def __init__(self, in_channels: int, channels: int, hidden: int, dropout: float = 0.1) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(in_channels)
        self.identity = nn.Linear(in_channels, channels) if in_channels != channels else nn.Identity()
        self.mlp = nn.Sequential(
            nn.Linear(in_channels, hidden),
            nn.ReLU(inplace=True),
            nn.Dropout(dropout),
            nn.Linear(hidden, channels),
            nn.Dropout(dropout),
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.identity(x) + self.mlp(self.norm(x))


class _DecoderLayer(nn.Module):
    """One Sparse4D v3 decoder layer (see the module docstring for the order of operations)."""

    def __init__(
        self,
        channels: int,
        num_classes: int,
        level_channels: Sequence[int],
        heads: int,
        num_learnable_points: int,
        groups: int,
        dropout: float,
        interaction: bool,
    ) -> None:
        super().__init__()
        self.interaction = interaction
        if interaction:
            self.temporal_attn = nn.MultiheadAttention(channels, heads, dropout=dropout, batch_first=True)
            self.self_attn = nn.MultiheadAttention(channels, heads, dropout=dropout, batch_first=True)
            self.norm_attn = nn.LayerNorm(channels)
        self.deformable = DeformableImageAggregation(channels, level_channels, num_learnable_points, groups, dropout)
        self.ffn = AsymmetricFFN(2 * channels, channels, 4 * channels, dropout)
        self.norm_ffn = nn.LayerNorm(channels)
        self.refine = nn.Sequential(_mlp_block(channels, channels), nn.Linear(channels, BOX_DIM))
        self.cls = nn.Sequential(_mlp_block(channels, channels, repeats=1), nn.Linear(channels, num_classes))
        nn.init.zeros_(self.refine[-1].weight)
        nn.init.zeros_(self.refine[-1].bias)
        nn.init.constant_(self.cls[-1].bias, -math.log((1 - 0.01) / 0.01))  # prior probability 0.01

    def forward(
        self,
        x: Tensor,
        anchors: Tensor,
        anchor_embed: Tensor,
        cams: tuple,
        temporal: tuple[Tensor, Tensor, Tensor] | None,
        attn_mask: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        if self.interaction:
            if temporal is not None:
                t_feat, t_embed, t_valid = temporal
                att = self.temporal_attn(x + anchor_embed, t_feat + t_embed, t_feat, need_weights=False)[0]
                x = x + att * t_valid[:, None, None].to(x.dtype)
            q = x + anchor_embed
            x = self.norm_attn(x + self.self_attn(q, q, x, attn_mask=attn_mask, need_weights=False)[0])
        agg = self.deformable(x, anchor_embed, anchors, *cams)
        x = self.norm_ffn(self.ffn(torch.cat([x, agg], dim=-1)))
        anchors = anchors + self.refine(x + anchor_embed)
        return x, anchors, self.cls(x)


# ---------------------------------------------------------------------------------------------- state


@dataclass
class DetectorState:
    """The detector's memory between frames: the top-k instances of one frame.

    Attributes:
        anchors: ``(B, k, 10)`` encoded anchors in the ego frame of the frame they come from.
        features: ``(B, k, C)`` instance features (detached).
        confidence: ``(B, k)`` their (decayed) confidence in [0, 1].
        ego_to_global: ``(B, 4, 4)`` float64 pose of that frame, or None (then the next frame is assumed to
            share its ego frame).
        timestamp: ``(B,)`` float64 seconds of that frame, or None.
    """

    anchors: Tensor
    features: Tensor
    confidence: Tensor
    ego_to_global: Tensor | None = None
    timestamp: Tensor | None = None

    def detach(self) -> DetectorState:
        """A copy cut from the autograd graph."""
        return replace(
            self, anchors=self.anchors.detach(), features=self.features.detach(), confidence=self.confidence.detach()
        )


def propagate_state(
    state: DetectorState,
    ego_to_global: Tensor | None = None,
    timestamp: Tensor | None = None,
    use_velocity: bool = False,
    max_time_interval: float = 2.0,
) -> tuple[DetectorState, Tensor]:
    """Move a state's anchors into the current ego frame (Sparse4D ``anchor_projection``).

    Centres move by the relative ego pose ``T_{g->e}^t T_{e->g}^{t-1}`` (:func:`~occplug.geometry.relative_pose`),
    after a constant-velocity step ``v * dt`` when ``use_velocity``; yaw (sin, cos) and velocity rotate with it;
    sizes are unchanged.

    Args:
        state: the previous frame's state.
        ego_to_global: ``(B, 4, 4)`` pose of the current frame, or None (only if the state has none either:
            the frames share the ego frame).
        timestamp: ``(B,)`` seconds of the current frame, or None (no velocity step, no time check).
        use_velocity: apply the constant-velocity step (needs both timestamps).
        max_time_interval: a sample whose ``|dt|`` exceeds this (seconds) is marked invalid.

    Returns:
        The state in the current ego frame (its pose and timestamp replaced by the current ones) and ``(B,)``
        bool: whether each sample's state may be used.
    """
    anchors = state.anchors
    b = anchors.shape[0]
    valid = torch.ones(b, dtype=torch.bool, device=anchors.device)
    dt = None
    if timestamp is not None and state.timestamp is not None:
        dt = (timestamp.to(torch.float64) - state.timestamp.to(torch.float64)).to(anchors.device)
        valid = dt.abs() <= max_time_interval
    if (ego_to_global is None) != (state.ego_to_global is None):
        raise ValueError("propagate_state: give ego_to_global for both frames or for neither")
    a = anchors.to(torch.float64)
    centre = a[..., :3]
    if use_velocity and dt is not None:
        centre = centre + torch.cat([a[..., 8:10], torch.zeros_like(a[..., :1])], -1) * dt[:, None, None]
    if ego_to_global is not None:
        assert state.ego_to_global is not None
        prev_to_curr = relative_pose(state.ego_to_global.to(torch.float64), ego_to_global.to(torch.float64))
        rot = prev_to_curr[:, :2, :2].to(anchors.device)  # yaw part: rotation about z only matters for boxes
        centre = transform_points(prev_to_curr.to(anchors.device), centre)
        cos_sin = torch.einsum("bij,bqj->bqi", rot, a[..., [7, 6]])
        vel = torch.einsum("bij,bqj->bqi", rot, a[..., 8:10])
        a = torch.cat([centre, a[..., 3:6], cos_sin[..., 1:2], cos_sin[..., 0:1], vel], dim=-1)
    else:
        a = torch.cat([centre, a[..., 3:]], dim=-1)
    moved = DetectorState(
        anchors=a.to(anchors.dtype),
        features=state.features,
        confidence=state.confidence,
        ego_to_global=ego_to_global,
        timestamp=timestamp,
    )
    return moved, valid


# ---------------------------------------------------------------------------------------------- detector


@dataclass
class DetectorOutput:
    """What :class:`SparseDetector` returns.

    Attributes:
        cls_logits: per layer ``(B, Q, K)`` class logits (sigmoid classification, no background class).
        encoded_boxes: per layer ``(B, Q, 10)`` encoded boxes (:data:`BOX_DIM` layout), ego frame.
        features: ``(B, Q, C)`` instance features after the last layer (``q_img`` of Eq. 6).
        anchor_embed: ``(B, Q, C)`` embedding of the final boxes (a positional term for V2Q / DQA), or None.
        state: the state to pass to the next frame (detached), or None.
        denoising: the step's denoising queries (training only, :mod:`.denoising`), or None.
        dn_cls_logits: per layer ``(B, M, K)`` the denoising queries' class logits (with ``denoising``).
        dn_encoded_boxes: per layer ``(B, M, 10)`` their encoded boxes (with ``denoising``).
    """

    cls_logits: list[Tensor]
    encoded_boxes: list[Tensor]
    features: Tensor | None = None
    anchor_embed: Tensor | None = None
    state: DetectorState | None = None
    denoising: DenoisingQueries | None = None
    dn_cls_logits: list[Tensor] | None = None
    dn_encoded_boxes: list[Tensor] | None = None

    @property
    def boxes(self) -> list[Tensor]:
        """Per layer ``(B, Q, 9)`` decoded boxes ``[cx, cy, cz, l, w, h, yaw, vx, vy]``, ego frame."""
        return [decode_boxes(e) for e in self.encoded_boxes]

    @property
    def scores(self) -> Tensor:
        """``(B, Q)`` the last layer's confidence (largest class sigmoid)."""
        return self.cls_logits[-1].sigmoid().amax(-1)


class SparseDetector(nn.Module):
    """DuOcc's image-to-query detector (§3.2 I2Q): a small Sparse4D v3 in plain PyTorch.

    Args:
        num_classes: ``K`` detection classes.
        channels: ``C`` of the instance features (divisible by ``heads`` and ``groups``; >= 16).
        level_channels: channels of the image feature levels, finest first (the encoder's ``level_channels``).
        num_queries: ``Q`` anchors / instance queries (paper 900).
        num_layers: decoder layers (paper 6).
        num_temporal: ``k`` instances propagated to the next frame (code 600 of 900; 0 disables propagation).
        heads: attention heads; groups: deformable-aggregation weight groups; num_learnable_points: learnable
            key points per anchor (code 8 / 8 / 6).
        anchor_range: ``(x_min, y_min, z_min, x_max, y_max, z_max)`` ego-frame box in which anchor centres start.
        anchor_size: initial ``(l, w, h)`` of every anchor, metres.
        anchor_centres: ``num_queries`` ego-frame ``(x, y, z)`` starting centres (the code's k-means anchors;
            ``python -m occplug_duocc.fit_anchors``), or None to draw them uniformly in ``anchor_range``.
        learn_instance_feature: whether the initial instance features are learned (code: frozen zeros).
        confidence_decay: decay of a cached instance's confidence per frame.
        use_velocity: move cached anchors by constant velocity as well as by ego motion.
        max_time_interval: seconds beyond which a cached state is dropped.
        dropout: attention / FFN / aggregation dropout (code 0.1).
        num_dn_groups: Sparse4D v3's denoising groups in training (code 5; 0: off), :mod:`.denoising`.
        dn_noise_scale: their noise per encoded box dimension (code ``[2.0] * 3 + [0.5] * 7``).
        max_dn_gt: ground truths per sample that get denoising queries (code 32).
        dn_negatives: add a negative (1 to 2 noise scales away) per ground truth (code: on).

    Forward: :meth:`forward` (tensors) or :meth:`forward_batch` (a :class:`~occplug.Batch`).
    """

    def __init__(
        self,
        num_classes: Annotated[int, Positive],
        channels: Annotated[int, Positive] = 64,
        level_channels: Sequence[int] = (64,),
        num_queries: Annotated[int, Positive] = 64,
        num_layers: Annotated[int, Positive] = 2,
        num_temporal: int = 32,
        heads: Annotated[int, Positive] = 4,
        groups: Annotated[int, Positive] = 4,
        num_learnable_points: int = 6,
        anchor_range: Sequence[float] = (-40.0, -40.0, -1.0, 40.0, 40.0, 5.4),
        anchor_size: Sequence[float] = (4.0, 1.8, 1.6),
        anchor_centres: Sequence[Sequence[float]] | None = None,
        learn_instance_feature: bool = True,
        confidence_decay: float = 0.6,
        use_velocity: bool = True,
        max_time_interval: float = 2.0,
        dropout: float = 0.1,
        num_dn_groups: Annotated[int, NonNegative] = 0,
        dn_noise_scale: Sequence[float] = DN_NOISE_SCALE,
        max_dn_gt: Annotated[int, Positive] = 32,
        dn_negatives: bool = True,
    ) -> None:
        super().__init__()
        if len(dn_noise_scale) != BOX_DIM:
            raise ValueError(f"SparseDetector: dn_noise_scale needs {BOX_DIM} values, got {list(dn_noise_scale)}")
        self.num_dn_groups, self.max_dn_gt, self.dn_negatives = int(num_dn_groups), int(max_dn_gt), bool(dn_negatives)
        self.dn_noise_scale = tuple(float(v) for v in dn_noise_scale)
        if not 0 <= num_temporal < num_queries:
            raise ValueError(f"SparseDetector: num_temporal must be in [0, num_queries), got {num_temporal}")
        if channels % heads:
            raise ValueError(f"SparseDetector: channels {channels} not divisible by heads {heads}")
        self.num_classes, self.channels = int(num_classes), int(channels)
        self.num_queries, self.num_temporal = int(num_queries), int(num_temporal)
        self.confidence_decay, self.use_velocity = float(confidence_decay), bool(use_velocity)
        self.max_time_interval = float(max_time_interval)
        rng = torch.tensor([float(v) for v in anchor_range])
        if anchor_centres is None:
            gen = torch.Generator().manual_seed(0)
            centres = rng[:3] + torch.rand(num_queries, 3, generator=gen) * (rng[3:] - rng[:3])
        else:
            if len(anchor_centres) != num_queries:
                raise ValueError(
                    f"SparseDetector: anchor_centres must be num_queries={num_queries} rows of (x, y, z), got "
                    f"{len(anchor_centres)} rows; make them for this query count with python -m occplug_duocc.fit_anchors "
                    "--queries, or set anchor_centres: null"
                )
            bad = [i for i, c in enumerate(anchor_centres) if len(c) != 3]
            if bad:
                raise ValueError(
                    f"SparseDetector: anchor_centres[{bad[0]}] must be (x, y, z), got {anchor_centres[bad[0]]}"
                )
            centres = torch.tensor([[float(v) for v in c] for c in anchor_centres])
        size = torch.tensor([float(v) for v in anchor_size]).log().expand(num_queries, 3)
        yaw = torch.tensor([0.0, 1.0]).expand(num_queries, 2)
        self.anchors = nn.Parameter(torch.cat([centres, size, yaw, torch.zeros(num_queries, 2)], dim=-1))
        self.instance_feature = nn.Parameter(torch.zeros(num_queries, channels), requires_grad=learn_instance_feature)
        self.anchor_encoder = AnchorEncoder(channels)
        self.layers = nn.ModuleList(
            _DecoderLayer(
                channels, num_classes, level_channels, heads, num_learnable_points, groups, dropout, interaction=i > 0
            )
            for i in range(num_layers)
        )

    def forward(
        self,
        levels: Tensor | Sequence[Tensor],
        image_size: tuple[int, int],
        intrinsics: Tensor,
        cam_to_ego: Tensor,
        img_aug: Tensor | None = None,
        state: DetectorState | None = None,
        ego_to_global: Tensor | None = None,
        timestamp: Tensor | None = None,
        reset: Tensor | None = None,
        denoising: DenoisingQueries | None = None,
    ) -> DetectorOutput:
        """Detect boxes in one frame, optionally continuing from the previous frame's state.

        Args:
            levels: image features, one tensor or a list ``(B, N, C_l, H_l, W_l)`` (finest first), each covering
                the whole augmented image.
            image_size: ``(H, W)`` of the augmented images, pixels.
            intrinsics: ``(B, N, 3, 3)`` original-image intrinsics.
            cam_to_ego: ``(B, N, 4, 4)``.
            img_aug: ``(B, N, 3, 3)`` original -> augmented pixels, or None.
            state: the previous frame's :attr:`DetectorOutput.state`, or None (first frame).
            ego_to_global: ``(B, 4, 4)`` float64 pose of this frame (needed with a state that has one).
            timestamp: ``(B,)`` float64 seconds of this frame, or None.
            reset: ``(B,)`` bool: samples that start a new sequence (their state is ignored), or None.
            denoising: :meth:`denoising_queries` of this frame's ground truth (training), or None. They run
                beside the ``Q`` queries, masked from them (module :mod:`.denoising`), and change none of their
                outputs (exactly so without dropout).

        Returns:
            :class:`DetectorOutput` with ``Q = num_queries`` queries per layer and the next state (and the
            denoising queries' outputs with ``denoising``).
        """
        levels = [levels] if isinstance(levels, Tensor) else list(levels)
        b = levels[0].shape[0]
        cams = (levels, image_size, intrinsics, cam_to_ego, img_aug)
        x = self.instance_feature.expand(b, -1, -1)
        anchors = self.anchors.expand(b, -1, -1)
        temporal, valid = None, None
        if state is not None and self.num_temporal > 0:
            state, valid = propagate_state(
                state, ego_to_global, timestamp, self.use_velocity, max_time_interval=self.max_time_interval
            )
            if reset is not None:
                valid = valid & ~reset.to(valid.device)
            # no valid state anywhere: skip its work (an eager shortcut: the masked path below gives the same
            # result, and a traced graph -- export, torch.compile -- cannot branch on data)
            if not torch.compiler.is_compiling() and not bool(valid.any()):
                state, valid = None, None
            else:
                temporal = (state.features, self.anchor_encoder(state.anchors), valid)
        if state is not None and len(self.layers) == 1:  # no later layer: prepend to the first Q - k anchors
            x, anchors = self._merge_cache(x, anchors, None, state, valid)
        cls_out, box_out = [], []
        dn_cls, dn_box, mask = [], [], None
        if denoising is not None:
            q, m = self.num_queries, denoising.anchors.shape[1]
            x_dn, a_dn = x.new_zeros(b, m, self.channels), denoising.anchors.to(anchors)  # zero features (Sparse4D)
            mask = torch.ones(q + m, q + m, dtype=torch.bool, device=x.device)  # True: may not attend
            mask[:q, :q] = False
            mask[q:, q:] = denoising.attn_mask.to(x.device)
        for i, layer in enumerate(self.layers):
            t = temporal if i > 0 else None
            if denoising is None:
                x, anchors, logits = layer(x, anchors, self.anchor_encoder(anchors), cams, t)
            else:
                both = torch.cat([anchors, a_dn], dim=1)
                xs, both, both_logits = layer(torch.cat([x, x_dn], 1), both, self.anchor_encoder(both), cams, t, mask)
                x, x_dn = xs[:, :q], xs[:, q:]
                anchors, a_dn = both[:, :q], both[:, q:]
                logits = both_logits[:, :q]
                dn_cls.append(both_logits[:, q:])
                dn_box.append(a_dn)
            cls_out.append(logits)
            box_out.append(anchors)
            if i == 0 and state is not None and len(self.layers) > 1:
                x, anchors = self._merge_cache(x, anchors, logits, state, valid)
        scores = cls_out[-1].sigmoid().amax(-1)
        new_state = self._cache(x, anchors, scores, state, valid, ego_to_global, timestamp)
        out = DetectorOutput(cls_out, box_out, x, self.anchor_encoder(anchors), new_state)
        if denoising is not None:
            out.denoising, out.dn_cls_logits, out.dn_encoded_boxes = denoising, dn_cls, dn_box
        return out

    def denoising_queries(
        self, gt_labels: Sequence[Tensor], gt_boxes: Sequence[Tensor], generator: torch.Generator | None = None
    ) -> DenoisingQueries | None:
        """This detector's denoising queries for a frame's ground truth (:func:`~.denoising.make_denoising_queries`
        with ``num_dn_groups``, ``dn_noise_scale``, ``max_dn_gt``, ``dn_negatives``); None when off or no box."""
        return make_denoising_queries(
            gt_labels,
            gt_boxes,
            self.num_dn_groups,
            noise_scale=self.dn_noise_scale,
            max_gt=self.max_dn_gt,
            negatives=self.dn_negatives,
            generator=generator,
        )

    def forward_batch(
        self, levels: Tensor | Sequence[Tensor], batch: Batch, state: DetectorState | None = None
    ) -> DetectorOutput:
        """:meth:`forward` with cameras, pose, time and sequence starts read from ``batch``."""
        h, w = batch.images.shape[-2:]
        return self.forward(
            levels,
            (int(h), int(w)),
            batch.intrinsics,
            batch.cam_to_ego,
            batch.img_aug,
            state=state,
            ego_to_global=batch.ego_to_global,
            timestamp=batch.timestamp,
            reset=batch.is_sequence_start,
        )

    def _merge_cache(
        self, x: Tensor, anchors: Tensor, logits: Tensor | None, state: DetectorState, valid: Tensor
    ) -> tuple[Tensor, Tensor]:
        """``[cached k, top Q - k current]`` where the state is valid, the current set elsewhere.

        Runs after layer 1 (``logits`` rank the current queries); a one-layer detector merges before it, keeping
        the first ``Q - k`` anchors (``logits`` None).
        """
        k = self.num_temporal
        if logits is None:
            idx = torch.arange(self.num_queries - k, device=x.device).expand(x.shape[0], -1)
        else:
            idx = logits.detach().sigmoid().amax(-1).topk(self.num_queries - k, dim=1).indices
        top_x = x.gather(1, idx[..., None].expand(-1, -1, x.shape[-1]))
        top_a = anchors.gather(1, idx[..., None].expand(-1, -1, anchors.shape[-1]))
        merged_x = torch.cat([state.features.to(x), top_x], dim=1)
        merged_a = torch.cat([state.anchors.to(anchors), top_a], dim=1)
        keep = valid[:, None, None]
        return torch.where(keep, merged_x, x), torch.where(keep, merged_a, anchors)

    def _cache(
        self,
        x: Tensor,
        anchors: Tensor,
        scores: Tensor,
        state: DetectorState | None,
        valid: Tensor | None,
        ego_to_global: Tensor | None,
        timestamp: Tensor | None,
    ) -> DetectorState | None:
        k = self.num_temporal
        if k == 0:
            return None
        conf = scores.detach()
        if state is not None and valid is not None:
            decayed = torch.maximum(state.confidence.to(conf) * self.confidence_decay, conf[:, :k])
            conf = torch.cat([torch.where(valid[:, None], decayed, conf[:, :k]), conf[:, k:]], dim=1)
        top, idx = conf.topk(k, dim=1)
        return DetectorState(
            anchors=anchors.detach().gather(1, idx[..., None].expand(-1, -1, anchors.shape[-1])),
            features=x.detach().gather(1, idx[..., None].expand(-1, -1, x.shape[-1])),
            confidence=top,
            ego_to_global=ego_to_global,
            timestamp=timestamp,
        )


def select_detections(
    output: DetectorOutput, top_k: int = 300, score_threshold: float = 0.0, layer: int = -1
) -> list[tuple[Tensor, Tensor, Tensor]]:
    """Sparse4D's post-processing: per sample the ``top_k`` (query, class) pairs by sigmoid score.

    Args:
        output: the detector's output.
        top_k: pairs kept per sample (code 300); score_threshold: drop pairs at or below it (DuOcc's eval 0.3).
        layer: which layer's predictions (default the last).

    Returns:
        ``B`` triples ``(boxes (P, 9) ego frame, scores (P,), labels (P,) int64)``, scores descending.
    """
    logits, boxes = output.cls_logits[layer], output.boxes[layer]
    k = logits.shape[-1]
    out = []
    for b in range(logits.shape[0]):
        probs = logits[b].detach().sigmoid().flatten()
        scores, idx = probs.topk(min(top_k, probs.numel()))
        keep = scores > score_threshold
        scores, idx = scores[keep], idx[keep]
        out.append((boxes[b].detach()[idx // k], scores, idx % k))
    return out


# ---------------------------------------------------------------------------------------------- loss


def detection_loss(
    outputs: DetectorOutput,
    gt_labels: Sequence[Tensor],
    gt_boxes: Sequence[Tensor],
    cls_weight: float = 2.0,
    box_weight: float = 0.25,
    alpha: float = 0.25,
    gamma: float = 2.0,
    reg_weights: Sequence[float] = SPARSE4D_LOSS_REG_WEIGHTS,
    match_reg_weights: Sequence[float] = SPARSE4D_REG_WEIGHTS,
    class_reg_weights: Mapping[int, Sequence[float]] | None = None,
    reg_score_threshold: float | None = 0.05,
    layer_weights: Sequence[float] | None = None,
) -> dict[str, Tensor]:
    """Sparse4D v3's detection loss, summed over decoder layers (suppl. A.4 ``L_det``).

    Per layer: one-to-one Hungarian assignment (:func:`~.matching.hungarian_match`, same weights), then
    ``cls_weight * focal(all queries, one-hot targets of the matched ones)`` and
    ``box_weight * sum_matched sum_d w_d |b_pred,d - b_gt,d|`` on the encoded boxes, both divided by the number
    of matched ground truths in the batch (at least 1). A NaN target dimension (e.g. unknown velocity) has weight 0.

    Args:
        outputs: the detector's output (``cls_logits`` and ``encoded_boxes`` per layer).
        gt_labels: ``B`` tensors ``(G_b,)`` int64 class ids in ``[0, K)`` (``G_b`` may be 0).
        gt_boxes: ``B`` tensors ``(G_b, 7)`` or ``(G_b, 9)`` boxes ``[cx, cy, cz, l, w, h, yaw(, vx, vy)]``, ego frame.
        cls_weight, box_weight, alpha, gamma: loss (and matching-cost) weights; Sparse4D 2.0, 0.25, 0.25, 2.
        reg_weights: per-dimension L1 weights (10, truncated to 8 for 7-column ground truth).
        match_reg_weights: per-dimension weights of the matching cost.
        class_reg_weights: ``{class id: weights}`` replacing ``reg_weights`` for that class (loss and matching).
        reg_score_threshold: regress only matches whose score exceeds this (None: all).
        layer_weights: weight of each layer (default 1 each).

    Returns:
        ``{"det_cls": scalar, "det_box": scalar}``, plus ``{"det_dn_cls", "det_dn_box"}`` when ``outputs`` carries
        denoising queries (:func:`~.denoising.denoising_loss`, same weights).
    """
    if len(gt_labels) != len(gt_boxes):
        raise ValueError("detection_loss: gt_labels and gt_boxes need one entry per sample")
    targets = [encode_boxes(g.to(outputs.encoded_boxes[0].dtype)) for g in gt_boxes]
    dims = {t.shape[-1] for t in targets} or {BOX_DIM}
    if len(dims) > 1:
        raise ValueError(f"detection_loss: ground-truth boxes of a batch have different widths {sorted(dims)}")
    d = dims.pop()
    weights = layer_weights or [1.0] * len(outputs.cls_logits)
    total_cls = outputs.cls_logits[0].new_zeros(())
    total_box = outputs.cls_logits[0].new_zeros(())
    for w_layer, logits, enc in zip(weights, outputs.cls_logits, outputs.encoded_boxes, strict=True):
        pred = enc[..., :d]
        matches = hungarian_match(
            logits,
            pred,
            gt_labels,
            targets,
            cls_weight=cls_weight,
            box_weight=box_weight,
            alpha=alpha,
            gamma=gamma,
            reg_weights=list(match_reg_weights)[:d],
            class_reg_weights={c: list(v)[:d] for c, v in (class_reg_weights or {}).items()},
        )
        cls_target = torch.zeros_like(logits)
        box_loss = logits.new_zeros(())
        num_pos = 0
        for b, (qi, gi) in enumerate(matches):
            num_pos += int(qi.numel())
            if qi.numel() == 0:
                continue
            labels = gt_labels[b].to(logits.device).long()[gi]
            cls_target[b, qi, labels] = 1.0
            tgt = targets[b][gi]
            w = pred.new_tensor(list(reg_weights)[:d]).expand(qi.numel(), d)
            if class_reg_weights:
                for c, cw in class_reg_weights.items():
                    w = torch.where((labels == c)[:, None], pred.new_tensor(list(cw)[:d]), w)
            w = w * (~tgt.isnan()).to(w.dtype)
            if reg_score_threshold is not None:
                score = logits[b, qi].detach().sigmoid().amax(-1)
                w = w * (score > reg_score_threshold).to(w.dtype)[:, None]
            diff = (pred[b, qi] - torch.nan_to_num(tgt, nan=0.0)).abs()
            box_loss = box_loss + (diff * w).sum()
        norm = max(num_pos, 1)
        total_cls = total_cls + w_layer * cls_weight * sigmoid_focal_loss(logits, cls_target, alpha, gamma) / norm
        total_box = total_box + w_layer * box_weight * box_loss / norm
    out = {"det_cls": total_cls, "det_box": total_box}
    if outputs.denoising is not None and outputs.dn_cls_logits and outputs.dn_encoded_boxes:
        out.update(
            denoising_loss(
                outputs.denoising,
                outputs.dn_cls_logits,
                outputs.dn_encoded_boxes,
                lambda logits, targets: sigmoid_focal_loss(logits, targets, alpha, gamma),
                cls_weight,
                box_weight,
                reg_weights,
                layer_weights,
            )
        )
    return out


# ---------------------------------------------------------------------------------------------- V2Q


class VoxelToQuery(nn.Module):
    """V2Q (§3.2, Eq. 6): each instance query samples the voxel volume around its box and adds the result.

    ``q_vox = q_img + W [concat_h sum_o alpha_hqo W'_h V(c_q + R(yaw_q) (s_hqo * size_q))]`` with offsets
    ``s = sigmoid(Linear(q)) - 0.5`` (fractions of the box's ``(l, w, h)``, so inside the box), weights
    ``alpha = softmax_o(Linear(q))`` per head, trilinear sampling (:func:`~occplug.geometry.sample_volume`, zeros
    outside the grid).

    Args:
        channels: ``C`` of the queries (divisible by ``heads``).
        grid: the grid the volume lies on (``GridSpec`` or ``{range, voxel_size}``), ego frame.
        volume_channels: channels of the volume (default ``C``).
        heads, points: ``H`` heads with ``O`` points each (code 8 x 6).
        dropout: on the output.
    """

    def __init__(
        self,
        channels: Annotated[int, Positive],
        grid: GridSpec | Mapping,
        volume_channels: int | None = None,
        heads: Annotated[int, Positive] = 8,
        points: Annotated[int, Positive] = 6,
        dropout: float = 0.1,
    ) -> None:
        super().__init__()
        if channels % heads:
            raise ValueError(f"VoxelToQuery: channels {channels} not divisible by heads {heads}")
        self.grid = GridSpec.from_config(grid)
        self.channels, self.heads, self.points = int(channels), int(heads), int(points)
        self.offsets = nn.Linear(channels, heads * points * 3)
        self.attn = nn.Linear(channels, heads * points)
        self.value_proj = nn.Linear(int(volume_channels or channels), channels, bias=False)
        self.out_proj = nn.Linear(channels, channels)
        self.drop = nn.Dropout(dropout)
        nn.init.zeros_(self.offsets.weight)
        nn.init.zeros_(self.attn.weight)
        nn.init.zeros_(self.attn.bias)
        with torch.no_grad():  # start on a spread pattern: head h along direction 2 pi h / H, points at growing radius
            theta = 2 * math.pi * torch.arange(heads, dtype=torch.float64) / heads
            radius = 0.45 * (torch.arange(points, dtype=torch.float64) + 1) / points
            frac = torch.stack(
                [
                    radius[None] * theta.cos()[:, None],
                    radius[None] * theta.sin()[:, None],
                    (0.2 * (torch.arange(heads) % 2 * 2 - 1))[:, None].expand(heads, points).to(torch.float64),
                ],
                dim=-1,
            )
            self.offsets.bias.copy_(torch.logit(frac + 0.5).flatten().float())

    def sample_points(self, queries: Tensor, boxes: Tensor) -> Tensor:
        """``(B, Q, H, O, 3)`` ego-frame sampling points of ``(B, Q, C)`` queries around ``(B, Q, >=7)`` boxes."""
        b, q = queries.shape[:2]
        frac = self.offsets(queries).view(b, q, self.heads * self.points, 3).sigmoid() - 0.5
        yaw = boxes[..., 6]
        enc = torch.cat(
            [boxes[..., :3], boxes[..., 3:6].clamp(min=1e-6).log(), yaw.sin()[..., None], yaw.cos()[..., None]], -1
        )
        return box_points(enc, frac).view(b, q, self.heads, self.points, 3)

    def forward(self, volume: Tensor, queries: Tensor, boxes: Tensor, query_pos: Tensor | None = None) -> Tensor:
        """Refine instance queries with the voxel volume.

        Args:
            volume: ``V_S.A``, ``(B, C_v, X, Y, Z)`` on ``grid``, ego frame.
            queries: ``q_img``, ``(B, Q, C)``.
            boxes: ``(B, Q, >=7)`` their boxes ``[cx, cy, cz, l, w, h, yaw, ...]``, ego frame.
            query_pos: ``(B, Q, C)`` added to the queries for predicting offsets and weights (e.g. the anchor
                embedding), or None.

        Returns:
            ``q_vox``, ``(B, Q, C)``.
        """
        if tuple(volume.shape[2:]) != self.grid.shape:
            raise ValueError(f"VoxelToQuery: volume {tuple(volume.shape)} is not on grid {self.grid.shape}")
        b, q, c = queries.shape
        h, o = self.heads, self.points
        src = queries if query_pos is None else queries + query_pos
        pts = self.sample_points(src, boxes)
        sampled = sample_volume(volume, self.grid, pts.reshape(b, q * h * o, 3).to(volume.dtype))  # (B, QHO, C_v)
        values = self.value_proj(sampled.to(queries.dtype)).view(b, q, h, o, h, c // h)
        values = torch.diagonal(values, dim1=2, dim2=4).movedim(-1, 2)  # head h reads its own channels: (B,Q,H,O,d)
        alpha = self.attn(src).view(b, q, h, o).softmax(-1)
        out = (alpha[..., None] * values).sum(3).reshape(b, q, c)
        return queries + self.drop(self.out_proj(out))


# ---------------------------------------------------------------------------------------------- metric


def _average_precision(tp: np.ndarray, npos: int, min_recall: float, min_precision: float) -> float:
    """nuScenes ``accumulate`` + ``calc_ap`` for one class and threshold (``tp`` in descending-score order)."""
    if tp.size == 0 or tp.sum() == 0:
        return 0.0
    ctp, cfp = np.cumsum(tp), np.cumsum(1 - tp)
    prec = ctp / (ctp + cfp)
    rec = ctp / float(npos)
    prec = np.interp(np.linspace(0, 1, 101), rec, prec, right=0)
    prec = prec[round(100 * min_recall) + 1 :] - min_precision
    prec[prec < 0] = 0
    return float(np.mean(prec)) / (1.0 - min_precision)


def detection_map(
    pred_boxes: Sequence[Tensor],
    pred_scores: Sequence[Tensor],
    pred_labels: Sequence[Tensor],
    gt_boxes: Sequence[Tensor],
    gt_labels: Sequence[Tensor],
    thresholds: Sequence[float] = (0.5, 1.0, 2.0, 4.0),
    min_recall: float = 0.1,
    min_precision: float = 0.1,
) -> dict[str, object]:
    """nuScenes-style mean average precision by BEV centre distance.

    Per class present in the ground truth and per threshold: predictions of that class (all samples) are taken
    by descending score; each is a true positive when the nearest not-yet-matched ground truth of its class in
    its sample lies within the threshold (BEV centre distance, metres, strict ``<``), which it then consumes.
    AP is the devkit's: precision interpolated at 101 recalls, recalls up to ``min_recall`` dropped,
    ``max(p - min_precision, 0)`` averaged and divided by ``1 - min_precision`` (0 and 0 give plain 101-point AP).

    Args:
        pred_boxes: ``B`` tensors ``(P_b, >=2)`` (only the centre ``x, y`` is used), ego frame.
        pred_scores: ``B`` tensors ``(P_b,)``.
        pred_labels: ``B`` tensors ``(P_b,)`` int64.
        gt_boxes: ``B`` tensors ``(G_b, >=2)``, ego frame.
        gt_labels: ``B`` tensors ``(G_b,)`` int64.
        thresholds: centre-distance thresholds, metres (nuScenes 0.5, 1, 2, 4).
        min_recall, min_precision: the devkit's 0.1 and 0.1.

    Returns:
        ``{"mAP": float (0 without ground truth), "AP": {class: AP averaged over thresholds},
        "AP@": {threshold: AP averaged over classes}}``.
    """
    n = len(gt_boxes)
    if not len(pred_boxes) == len(pred_scores) == len(pred_labels) == len(gt_labels) == n:
        raise ValueError("detection_map: every argument needs one entry per sample")

    def np_(t: Tensor) -> np.ndarray:
        return t.detach().cpu().numpy()

    gt_xy = [np_(g[:, :2]).astype(np.float64) for g in gt_boxes]
    gt_cls = [np_(g).astype(np.int64) for g in gt_labels]
    classes = sorted(set(np.concatenate(gt_cls).tolist())) if n else []
    table = np.zeros((len(classes), len(thresholds)))
    for ci, c in enumerate(classes):
        npos = int(sum((g == c).sum() for g in gt_cls))
        preds = []  # (score, sample, xy)
        for s in range(n):
            lab = np_(pred_labels[s]).astype(np.int64)
            sc, xy = np_(pred_scores[s]).astype(np.float64), np_(pred_boxes[s][:, :2]).astype(np.float64)
            preds += [(sc[i], s, xy[i]) for i in np.nonzero(lab == c)[0]]
        order = np.argsort([-p[0] for p in preds], kind="stable")
        for ti, thr in enumerate(thresholds):
            taken = [np.zeros(int((g == c).sum()), dtype=bool) for g in gt_cls]
            tp = np.zeros(len(preds))
            for rank, pi in enumerate(order):
                _, s, xy = preds[pi]
                cand = gt_xy[s][gt_cls[s] == c]
                if cand.shape[0] == 0:
                    continue
                dist = np.linalg.norm(cand - xy, axis=1)
                dist[taken[s]] = np.inf
                j = int(np.argmin(dist))
                if dist[j] < thr:
                    taken[s][j] = True
                    tp[rank] = 1.0
            table[ci, ti] = _average_precision(tp, npos, min_recall, min_precision)
    return {
        "mAP": float(table.mean()) if table.size else 0.0,
        "AP": {int(c): float(table[ci].mean()) for ci, c in enumerate(classes)},
        "AP@": {float(t): float(table[:, ti].mean()) if classes else 0.0 for ti, t in enumerate(thresholds)},
    }
