"""DuOcc's image-to-query detector (I2Q, paper §3.2): a small Sparse4D v3 in plain PyTorch, no custom ops.

* :class:`SparseDetector` — anchor-based instance queries refined layer by layer (:class:`_DecoderLayer`) from
  multi-view, multi-level image features (Sparse4D v3's deformable aggregation, :mod:`.image_aggregation`), with
  temporal propagation of the top-k instances of the previous frame through an explicit :class:`DetectorState`
  (:func:`propagate_state`; no hidden state). It returns a :class:`DetectorOutput`.
* :func:`select_detections` — Sparse4D's post-processing (top-k over queries x classes, score threshold).

Beside it: the encoded box (:mod:`.boxes`), the image aggregation (:mod:`.image_aggregation`), the loss
(:mod:`.detection_loss`, with :mod:`.matching` and :mod:`.denoising`), V2Q (:mod:`.v2q`) and the mAP
(:mod:`.detection_eval`). Boxes are decoded in the ego frame, ``(..., 9)``; anchors and regression live in
Sparse4D's encoding, :data:`~.boxes.BOX_DIM` wide (:mod:`.boxes`).

Assumptions (where the paper, §3.2 "I2Q" and suppl. A.4, is silent; the public code's choices, from
its Sparse4D v3 detector in ``models/heads/queryagg/``, are these):

* §3.2 I2Q, anchors: 900 k-means anchors of the training boxes in the code; here ``anchor_centres`` when given
  (``python -m occplug_duocc.tools.fit_anchors`` makes them as the code does, :mod:`.anchors`), else ``num_queries`` centres drawn
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
* Refinement: residual deltas on every encoded dimension (centre, log size, sin/cos, velocity in m/s); the code
  predicts sin/cos absolutely and velocity as a displacement over ``dt``. The anchor is not detached between
  layers (Sparse4D).
* Temporal propagation (Sparse4D v3 ``InstanceBank``): the cache keeps the top-``num_temporal`` instances by
  confidence, with the cached ones' confidence decayed by ``confidence_decay`` (0.6) and maxed with the new
  one; after layer 1 (before it in a one-layer detector) the cached instances (moved into the current ego frame
  by the relative ego pose and, when ``use_velocity``, by constant velocity over ``dt``) are prepended to the top
  ``Q - k`` current queries, so ``Q`` stays ``num_queries``. A sample's cache is dropped when ``reset`` is set
  or ``|dt| > max_time_interval`` (2 s); later layers also cross-attend to the cached instances.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Annotated, Literal

import torch
from torch import Tensor, nn

from occplug.constraints import NonNegative, Positive, check_choices
from occplug.geometry import relative_pose, transform_points

from .boxes import BOX_DIM, decode_boxes
from .denoising import DN_NOISE_SCALE, DenoisingQueries, make_denoising_queries
from .image_aggregation import DeformableImageAggregation, _mlp_block

if TYPE_CHECKING:
    from occplug.data import Batch

__all__ = [
    "AnchorEncoder",
    "AsymmetricFFN",
    "DetectorOutput",
    "DetectorState",
    "SparseDetector",
    "propagate_state",
    "select_detections",
]


# ---------------------------------------------------------------------------------------------- layers


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
        checkpoint: bool = False,
    ) -> None:
        super().__init__()
        self.interaction = interaction
        if interaction:
            self.temporal_attn = nn.MultiheadAttention(channels, heads, dropout=dropout, batch_first=True)
            self.self_attn = nn.MultiheadAttention(channels, heads, dropout=dropout, batch_first=True)
            self.norm_attn = nn.LayerNorm(channels)
        self.deformable = DeformableImageAggregation(
            channels, level_channels, num_learnable_points, groups, dropout, checkpoint=checkpoint
        )
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
        before_refine: Callable[[Tensor, Tensor, Tensor], Tensor] | None = None,
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
        if before_refine is not None:  # V2Q inside the layer (v2q_placement="before_last_refinement")
            x = before_refine(x, anchors, anchor_embed)
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
        encoded_boxes: per layer ``(B, Q, 10)`` encoded boxes (:data:`~.boxes.BOX_DIM` layout), ego frame.
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
            ``python -m occplug_duocc.tools.fit_anchors``), or None to draw them uniformly in ``anchor_range``.
        learn_instance_feature: whether the initial instance features are learned (code: frozen zeros).
        confidence_decay: decay of a cached instance's confidence per frame.
        use_velocity: move cached anchors by constant velocity as well as by ego motion.
        max_time_interval: seconds beyond which a cached state is dropped.
        dropout: attention / FFN / aggregation dropout (code 0.1).
        num_dn_groups: Sparse4D v3's denoising groups in training (code 5; 0: off), :mod:`.denoising`.
        dn_noise_scale: their noise per encoded box dimension (code ``[2.0] * 3 + [0.5] * 7``).
        max_dn_gt: ground truths per sample that get denoising queries (code 32).
        dn_negatives: add a negative (1 to 2 noise scales away) per ground truth (code: on).
        checkpoint_aggregation: recompute each layer's image samples in the backward pass instead of keeping
            them (:class:`~.image_aggregation.DeformableImageAggregation` ``checkpoint``; same values and
            gradients, less training memory).
        v2q_placement: where QueryAgg's V2Q runs: after the last layer (``"after_last_refinement"``: the boxes
            never see the voxels), or, as the public code, inside the last layer before its refinement
            (``"before_last_refinement"``: the last refinement and classification read the V2Q-refined
            features); the latter is the ``v2q`` argument of :meth:`forward`.

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
        checkpoint_aggregation: bool = False,
        v2q_placement: Literal["after_last_refinement", "before_last_refinement"] = "after_last_refinement",
    ) -> None:
        super().__init__()
        check_choices(SparseDetector.__init__, "SparseDetector", v2q_placement=v2q_placement)
        self.v2q_placement = v2q_placement
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
                    f"{len(anchor_centres)} rows; make them for this query count with python -m occplug_duocc.tools.fit_anchors "
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
                channels,
                num_classes,
                level_channels,
                heads,
                num_learnable_points,
                groups,
                dropout,
                interaction=i > 0,
                checkpoint=checkpoint_aggregation,
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
        v2q: Callable[[Tensor, Tensor, Tensor], Tensor] | None = None,
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
            v2q: with ``v2q_placement="before_last_refinement"``, ``v2q(features (B, Q', C), encoded anchors
                (B, Q', 10), anchor embedding (B, Q', C)) -> features`` runs in the last layer before its
                refinement (on the denoising queries too); ignored with ``"after_last_refinement"``.

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
        inside = v2q if self.v2q_placement == "before_last_refinement" else None
        for i, layer in enumerate(self.layers):
            t = temporal if i > 0 else None
            # the layer's call is the plain one unless V2Q runs inside it
            step = {"before_refine": inside} if inside is not None and i == len(self.layers) - 1 else {}
            if denoising is None:
                x, anchors, logits = layer(x, anchors, self.anchor_encoder(anchors), cams, t, **step)
            else:
                both = torch.cat([anchors, a_dn], dim=1)
                xs, both, both_logits = layer(
                    torch.cat([x, x_dn], 1), both, self.anchor_encoder(both), cams, t, mask, **step
                )
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
