"""DuOcc's auxiliary mask decoder (paper §3.3 "Auxiliary Mask Decoder", suppl. A.3 / A.4; training only).

A Mask2Former-style decoder with group-wise one-to-many assignment (Co-DETR; COTR's semantic-aware group decoder)
that reads ``V_fin`` and is dropped at inference: it adds a loss, never changes a voxel feature. It is therefore
a supervision source (``duocc_mask``) that owns its decoder's parameters; the prediction path (scene, heads,
export) does not contain it, and it returns no loss outside training.

What it does (the public code's ``projects/mmdet3d_plugin/models/heads/mask_head/``; the paper gives the idea only):

* ``G`` groups of ``Q`` learnable queries (code: 6 x 100). Group 0 classifies the full class set (every label id
  but ``free``); group ``g >= 1`` classifies the coarse relabelling ``group_split[g - 1]``: a list of coarse
  classes, each a list of label ids merged into it (every non-free id exactly once). ``free`` is the no-object
  class of every group, and is itself a ground-truth mask (its label is the no-object index).
* ``num_layers`` decoder layers (code: 1), each: 3D deformable cross-attention of the queries into ``V_fin``
  (:class:`~occplug_duocc.blocks.v2q.VoxelToQuery`, the plugin's V2Q block, reused: each query samples
  ``heads x points`` points around its reference point ``sigmoid(Linear(query_pos))`` in the scene's range,
  within a box of ``sampling_extent`` times the range's extent), LayerNorm; self-attention within each group
  (the queries are attended per group, so no group reads another), LayerNorm; FFN, LayerNorm.
* Masks: ``mask_embed(q) . voxel_embed(V_fin)`` per voxel, with a 3-layer MLP ``mask_embed`` and
  ``voxel_embed = Linear -> Softplus -> Linear``; each group has its own class head (its classes + no-object).
* Losses per group and layer, on the labelled, camera-visible voxels (the core's ``mask_camera``): Hungarian
  matching (:func:`occplug.nn.linear_assignment`) with the costs ``1 x (-p_class) + 20 x focal + 1
  x dice``, then CE over every query (no-object weight 0.1), sigmoid focal (alpha 0.25, gamma 2) on the matched
  masks x 20 and dice (eps 1) x 1. Every group is matched independently against the same ground truth
  (group-wise one-to-many); group 0 weighs 1, the others ``coarse_group_weight`` (code: ``1 / (G - 1)``, 1/5 at
  its 6 groups).

Where the notes are silent (or the data flow here differs), the choices are:

* the voxel features are ``V_fin`` on the scene's coarse grid through ``voxel_embed`` (the code embeds DQA's
  upsampled map; here that map lives inside the ``duocc_decoder`` head, which a supervision source cannot
  read); the mask logits are upsampled trilinearly (``align_corners=False``, voxel centres) to the label grid,
  where the losses are taken;
* the cross-attention is VoxelToQuery's: offsets bounded to a box around the reference point (yaw 0) rather
  than Deformable DETR's unbounded voxel offsets, and it starts on VoxelToQuery's spread pattern;
* every layer's output is supervised (sum over layers); there is no prediction from the queries before the
  first layer;
* normalisation (as Mask2Former's): CE is the class-weighted mean over the queries of the samples with visible
  voxels; focal is averaged over visible voxels per mask, focal and dice are summed over matched masks and
  divided by the number of matched masks of the group in the batch (at least 1), where the code normalises each
  sample on its own and divides the sum by the batch size; matching and losses use every visible voxel (no point
  sampling);
* a sample's ground-truth classes are those of its counted (camera-visible) voxels only; the code builds them over
  the whole grid, so a class seen only outside the camera mask becomes an empty matched mask there;
* the losses and the matching costs are computed in float32 with autocast off (under ``bf16-mixed`` the mask
  logits arrive in bfloat16, and sums over ~1e5 voxels would lose precision).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occplug.constraints import Length, NonNegative, Positive, Range, UnitInterval
from occplug.data import Batch
from occplug.geometry import GridSpec
from occplug.interfaces import ModelOutputs
from occplug.nn import (
    dice_loss,
    linear_assignment,
    pairwise_dice_loss,
    pairwise_sigmoid_focal_loss,
    sigmoid_focal_loss,
)

from ..blocks.v2q import VoxelToQuery
from ..scene import StreamVoxelScene, coarse_grid
from .auxiliary import _AuxLoss

__all__ = [
    "OCC3D_GROUP_SPLIT",
    "DuOccMask",
    "MaskDecoder",
    "MaskDecoderOutput",
    "group_lookup",
    "match_masks",
]

#: The public code's five coarse relabellings of Occ3D-nuScenes (cfg ``group_split``, 2 / 6 / 6 / 4 / 4 classes),
#: as lists of merged label ids (``free``, 17, is each group's no-object class):
#:
#: 1. objects (others, barrier ... truck) | surfaces and structure (driveable ... vegetation);
#: 2. the rest | bicycle | bus | construction vehicle | motorcycle | trailer;
#: 3. the rest | barrier | car | pedestrian | traffic cone | truck;
#: 4. the rest | other flat | sidewalk | terrain;
#: 5. the rest | driveable surface | manmade | vegetation.
OCC3D_GROUP_SPLIT: tuple[tuple[tuple[int, ...], ...], ...] = (
    (tuple(range(11)), tuple(range(11, 17))),
    ((0, 1, 4, 7, 8, 10, *range(11, 17)), (2,), (3,), (5,), (6,), (9,)),
    ((0, 2, 3, 5, 6, 9, *range(11, 17)), (1,), (4,), (7,), (8,), (10,)),
    ((*range(12), 15, 16), (12,), (13,), (14,)),
    ((*range(11), 12, 13, 14), (11,), (15,), (16,)),
)


def group_lookup(num_classes: int, free_label: int, split: Sequence[Sequence[int]] | None) -> Tensor:
    """The label id -> coarse class table of one group.

    Args:
        num_classes: label ids ``0 .. num_classes - 1`` (``free`` included).
        free_label: the id of empty space; it maps to the group's no-object index ``K``.
        split: ``K`` lists of label ids, one per coarse class (each non-free id exactly once); None: the full class
            set (group 0), the non-free ids in ascending order.

    Returns:
        ``(num_classes,)`` int64: coarse class in ``[0, K)``, ``K`` for ``free``.

    Raises:
        ValueError: ``split`` is not a partition of the non-free ids (one line).
    """
    objects = [i for i in range(num_classes) if i != free_label]
    if split is None:
        split = [[i] for i in objects]
    ids = [int(i) for members in split for i in members]
    if sorted(ids) != objects or any(not members for members in split):
        raise ValueError(
            f"duocc_mask: a group_split entry must list every label id but free ({free_label}) exactly once in "
            f"non-empty coarse classes; got {[list(m) for m in split]}"
        )
    table = torch.full((num_classes,), len(split), dtype=torch.int64)
    for k, members in enumerate(split):
        table[torch.as_tensor(list(members), dtype=torch.int64)] = k
    return table


# ---------------------------------------------------------------------------------------------- matching


@torch.no_grad()
def match_masks(
    cls_logits: Tensor,
    mask_logits: Tensor,
    gt_labels: Tensor,
    gt_masks: Tensor,
    cls_weight: float = 1.0,
    focal_weight: float = 20.0,
    dice_weight: float = 1.0,
    dice_eps: float = 1.0,
) -> tuple[Tensor, Tensor]:
    """One-to-one Hungarian assignment of one group's queries to one sample's ground-truth masks (Mask2Former).

    Cost ``cls_weight * (-softmax(cls)[gt label]) + focal_weight * focal + dice_weight * dice`` (code 1 / 20 / 1).

    Args:
        cls_logits: ``(Q, K + 1)`` class logits (last: no-object).
        mask_logits: ``(Q, V)`` at the counted voxels.
        gt_labels: ``(M,)`` int64 coarse classes in ``[0, K]`` (``K``: the free mask).
        gt_masks: ``(M, V)`` binary.

    Returns:
        ``(query_idx, gt_idx)``, each ``(min(Q, M),)`` int64.
    """
    cost = (
        -cls_weight * cls_logits.float().softmax(-1)[:, gt_labels]
        + focal_weight * pairwise_sigmoid_focal_loss(mask_logits.float(), gt_masks.float())
        + dice_weight * pairwise_dice_loss(mask_logits.float(), gt_masks.float(), dice_eps)
    )
    return linear_assignment(cost)


# ---------------------------------------------------------------------------------------------- decoder


@dataclass
class MaskDecoderOutput:
    """One decoder layer's predictions.

    Attributes:
        cls_logits: ``G`` tensors ``(B, Q, K_g + 1)`` (last column: no-object).
        mask_logits: ``(B, G * Q, x, y, z)`` on the decoder's grid, queries ordered group by group.
    """

    cls_logits: list[Tensor]
    mask_logits: Tensor


class _MaskDecoderLayer(nn.Module):
    """Cross-attention into the voxels, LN, per-group self-attention, LN, FFN, LN (the code's operation order)."""

    def __init__(
        self, channels: int, volume_channels: int, grid: GridSpec, heads: int, points: int, ffn_hidden: int,
        dropout: float,
    ) -> None:  # fmt: skip
        super().__init__()
        self.cross = VoxelToQuery(channels, grid, volume_channels, heads=heads, points=points, dropout=dropout)
        self.self_attn = nn.MultiheadAttention(channels, heads, dropout=dropout, batch_first=True)
        self.ffn = nn.Sequential(
            nn.Linear(channels, ffn_hidden), nn.ReLU(inplace=True), nn.Dropout(dropout), nn.Linear(ffn_hidden, channels)
        )
        self.drop = nn.Dropout(dropout)
        self.norms = nn.ModuleList(nn.LayerNorm(channels) for _ in range(3))

    def forward(self, volume: Tensor, queries: Tensor, pos: Tensor, boxes: Tensor, groups: int) -> Tensor:
        """``(B, G * Q, C)`` queries (``pos`` the same shape, ``boxes`` ``(B, G * Q, 7)``) -> refined queries."""
        b, n, c = queries.shape
        x = self.norms[0](self.cross(volume, queries, boxes, pos))  # VoxelToQuery adds its own residual
        # queries of a group attend only to each other: groups become batch entries
        xg, pg = x.reshape(b * groups, n // groups, c), pos.reshape(b * groups, n // groups, c)
        attended, _ = self.self_attn(xg + pg, xg + pg, xg, need_weights=False)
        x = self.norms[1](x + self.drop(attended).reshape(b, n, c))
        return self.norms[2](x + self.drop(self.ffn(x)))


class MaskDecoder(nn.Module):
    """DuOcc's Mask2Former-style group decoder over ``V_fin`` (see the module docstring).

    Args:
        in_channels: ``C_v`` of ``V_fin``.
        grid: the grid ``V_fin`` lies on (ego frame).
        group_classes: ``K_g`` (classes without no-object) of each of the ``G`` groups.
        num_queries: ``Q`` per group (code: 100).
        channels: query width ``C`` (code: 256; divisible by ``heads``).
        num_layers: decoder layers (code: 1).
        heads, points: attention heads and sampling points per head of the cross-attention (code: 8, 4).
        ffn_hidden: FFN width (code: 512).
        mask_hidden: hidden width of ``mask_embed`` and ``voxel_embed`` (code: 512).
        sampling_extent: the cross-attention's sampling box around each reference point, as a fraction of the
            grid's extent per axis.
        dropout: of attention, FFN and cross-attention output (code: 0.1).

    Forward: ``V_fin`` ``(B, C_v, x, y, z)`` on ``grid`` -> one :class:`MaskDecoderOutput` per layer.
    """

    def __init__(
        self,
        in_channels: int,
        grid: GridSpec,
        group_classes: Sequence[int],
        num_queries: int = 100,
        channels: int = 256,
        num_layers: int = 1,
        heads: int = 8,
        points: int = 4,
        ffn_hidden: int = 512,
        mask_hidden: int = 512,
        sampling_extent: float = 0.5,
        dropout: float = 0.1,
    ) -> None:
        super().__init__()
        self.grid = grid
        self.group_classes = tuple(int(k) for k in group_classes)
        self.groups, self.num_queries = len(self.group_classes), int(num_queries)
        self.sampling_extent = float(sampling_extent)
        n = self.groups * self.num_queries
        self.query_feat = nn.Embedding(n, channels)
        self.query_pos = nn.Embedding(n, channels)
        self.reference = nn.Linear(channels, 3)
        self.layers = nn.ModuleList(
            _MaskDecoderLayer(channels, in_channels, grid, heads, points, ffn_hidden, dropout)
            for _ in range(num_layers)
        )
        self.mask_embed = nn.Sequential(
            nn.Linear(channels, mask_hidden), nn.ReLU(inplace=True),
            nn.Linear(mask_hidden, mask_hidden), nn.ReLU(inplace=True),
            nn.Linear(mask_hidden, channels),
        )  # fmt: skip
        self.voxel_embed = nn.Sequential(
            nn.Linear(in_channels, mask_hidden), nn.Softplus(), nn.Linear(mask_hidden, channels)
        )
        self.class_heads = nn.ModuleList(nn.Linear(channels, k + 1) for k in self.group_classes)

    def reference_boxes(self, pos: Tensor) -> Tensor:
        """``(B, N, 7)`` ego-frame sampling boxes ``[centre, size, yaw = 0]`` of ``(B, N, C)`` query positions."""
        lo, hi = pos.new_tensor(self.grid.range[:3]), pos.new_tensor(self.grid.range[3:])
        centre = lo + self.reference(pos).sigmoid() * (hi - lo)
        size = (self.sampling_extent * (hi - lo)).expand_as(centre)
        return torch.cat([centre, size, centre.new_zeros(*centre.shape[:-1], 1)], dim=-1)

    def predict(self, queries: Tensor, voxels: Tensor) -> MaskDecoderOutput:
        """Class logits per group and mask logits from ``(B, G * Q, C)`` queries and ``(B, x, y, z, C)`` voxel embeddings."""
        masks = torch.einsum("bnc,bxyzc->bnxyz", self.mask_embed(queries), voxels)
        per_group = queries.split(self.num_queries, dim=1)
        return MaskDecoderOutput([head(q) for head, q in zip(self.class_heads, per_group, strict=True)], masks)

    def forward(self, volume: Tensor) -> list[MaskDecoderOutput]:
        """One :class:`MaskDecoderOutput` per layer for ``V_fin`` ``(B, C_v, x, y, z)``."""
        b = volume.shape[0]
        queries = self.query_feat.weight[None].expand(b, -1, -1)
        pos = self.query_pos.weight[None].expand(b, -1, -1)
        boxes = self.reference_boxes(pos)
        voxels = self.voxel_embed(volume.movedim(1, -1))
        out = []
        for layer in self.layers:
            queries = layer(volume, queries, pos, boxes, self.groups)
            out.append(self.predict(queries, voxels))
        return out


# ---------------------------------------------------------------------------------------------- supervision


class DuOccMask(_AuxLoss):
    """``L_mask``: DuOcc's auxiliary Mask2Former-style group decoder on ``V_fin`` (training only; module docstring).

    Reads ``outputs.scene`` (a :class:`~occplug_duocc.scene.StreamVoxelScene`: ``V_fin`` ``(B, C, x, y, z)`` on
    the coarse grid, ego frame) and ``batch.voxel_labels`` ``(B, X, Y, Z)`` on the label grid (with
    ``batch.mask_camera`` when ``camera_mask``). Returns ``{"mask_cls", "mask_focal", "mask_dice"}`` (each already
    scaled by its coefficient, summed over layers and weighted groups) in training, ``{}`` otherwise: the decoder
    never runs at inference.

    Args:
        grid: the label (evaluation) grid, ego frame (the run's, given by the model).
        in_channels: ``C`` of ``V_fin`` (the scene's ``out_channels``, given by the model).
        scene_downsample: the scene's ``downsample``, given by the model (``V_fin`` lies on ``grid`` at that factor
            of its voxel size), so it cannot disagree with the scene's own setting.
        num_queries: ``Q`` per group (code: 100).
        num_groups: ``G`` (code: 6); None: ``1 + len(group_split)``; a smaller ``G`` uses the first ``G - 1``
            coarse groups of ``group_split``.
        group_split: the coarse groups, each a list of coarse classes, each a list of label ids (every non-free id
            exactly once per group); None: :data:`OCC3D_GROUP_SPLIT` (the code's, for the Occ3D taxonomy).
        num_classes: label ids (``free`` included; Occ3D: 18).
        channels, num_layers, heads, points, ffn_hidden, mask_hidden, sampling_extent, dropout: the decoder's
            (:class:`MaskDecoder`).
        cls_weight, focal_weight, dice_weight: loss and matching-cost coefficients (code: 1, 20, 1).
        no_object_weight: CE weight of the no-object class (code: 0.1).
        coarse_group_weight: weight of groups 1 .. G-1 (group 0 weighs 1); None: ``1 / (G - 1)``, the code's rule
            (1/5 at its 6 groups).
        dice_eps: dice smoothing (code: 1).
        weight: ``lambda_mask`` (paper suppl. A.4: 1).
        camera_mask: count only ``batch.mask_camera`` voxels (code: yes).
        free_label, ignore_label: the data set's (filled in by the model).
    """

    #: besides a source's given arguments, the scene's declared downsampling of the run grid
    given = (*_AuxLoss.given, "scene_downsample")

    def __init__(
        self,
        grid: GridSpec,
        num_classes: Annotated[int, Positive],
        scene_downsample: Annotated[int, Range(low=1, high=2)],
        in_channels: Annotated[int, Positive] = 32,
        num_queries: Annotated[int, Positive] = 100,
        num_groups: Annotated[int, Positive] | None = None,
        group_split: list[Annotated[list[list[Annotated[int, NonNegative]]], Length(min=1)]] | None = None,
        channels: Annotated[int, Positive] = 256,
        num_layers: Annotated[int, Positive] = 1,
        heads: Annotated[int, Positive] = 8,
        points: Annotated[int, Positive] = 4,
        ffn_hidden: Annotated[int, Positive] = 512,
        mask_hidden: Annotated[int, Positive] = 512,
        sampling_extent: Annotated[float, Positive] = 0.5,
        dropout: Annotated[float, UnitInterval] = 0.1,
        cls_weight: Annotated[float, NonNegative] = 1.0,
        focal_weight: Annotated[float, NonNegative] = 20.0,
        dice_weight: Annotated[float, NonNegative] = 1.0,
        no_object_weight: Annotated[float, NonNegative] = 0.1,
        coarse_group_weight: Annotated[float, NonNegative] | None = None,
        dice_eps: Annotated[float, Positive] = 1.0,
        weight: Annotated[float, NonNegative] = 1.0,
        camera_mask: bool = True,
        free_label: int = 17,
        ignore_label: int | None = 255,
    ) -> None:
        super().__init__(weight, camera_mask, free_label, ignore_label)
        self.label_grid = grid
        self.downsample = int(scene_downsample)
        self.grid = coarse_grid(self.label_grid, self.downsample)
        split = [list(map(list, g)) for g in (OCC3D_GROUP_SPLIT if group_split is None else group_split)]
        groups = 1 + len(split) if num_groups is None else int(num_groups)
        if groups > 1 + len(split):
            raise ValueError(
                f"duocc_mask: num_groups {groups} needs {groups - 1} group_split entries, got {len(split)}"
            )
        self.num_classes = int(num_classes)
        tables = [group_lookup(self.num_classes, self.free_label, s) for s in [None, *split[: groups - 1]]]
        self.register_buffer("lookup", torch.stack(tables), persistent=False)  # (G, num_classes)
        self.cls_weight, self.focal_weight, self.dice_weight = (
            float(cls_weight),
            float(focal_weight),
            float(dice_weight),
        )
        if coarse_group_weight is None:  # the public code: 1 / (num_groups - 1); nothing to weigh at G = 1
            coarse_group_weight = 1.0 / (groups - 1) if groups > 1 else 0.0
        self.no_object_weight, self.coarse_group_weight = float(no_object_weight), float(coarse_group_weight)
        self.dice_eps = float(dice_eps)
        self.decoder = MaskDecoder(
            int(in_channels),
            self.grid,
            [int(t.max()) for t in tables],  # the no-object index is K_g
            num_queries=num_queries,
            channels=channels,
            num_layers=num_layers,
            heads=heads,
            points=points,
            ffn_hidden=ffn_hidden,
            mask_hidden=mask_hidden,
            sampling_extent=sampling_extent,
            dropout=dropout,
        )

    def counted(self, batch: Batch, labels: Tensor) -> Tensor:
        """``(B, X, Y, Z)`` bool: the voxels the loss sees (labelled, valid, camera-visible, not ignored)."""
        return self.mask(batch, labels) & (labels != self.ignore_label)

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        """``{"mask_cls", "mask_focal", "mask_dice"}`` in training, ``{}`` otherwise."""
        if not self.training:
            return {}
        scene = outputs.scene
        features = getattr(scene, "features", None)
        if not isinstance(scene, StreamVoxelScene) or features is None:
            raise ValueError(f"duocc_mask: needs V_fin of model.scene.type=duocc_stream; got {type(scene).__name__}")
        if scene.grid != self.grid:
            raise ValueError(
                f"duocc_mask: reads V_fin at scene_downsample {self.downsample} (grid {self.grid.shape}) but the "
                f"scene's V_fin is on {scene.grid.shape}; leave scene_downsample to the model (the scene's downsample)"
            )
        batch.require("voxel_labels", by="duocc_mask")
        labels = batch.voxel_labels.to(features.device).long()
        if tuple(labels.shape[1:]) != self.label_grid.shape:
            raise ValueError(
                f"duocc_mask: voxel_labels {tuple(labels.shape[1:])} are not on grid {self.label_grid.shape}"
            )
        counted = self.counted(batch, labels)
        if bool((labels[counted] >= self.num_classes).any()) or bool((labels[counted] < 0).any()):
            raise ValueError(f"duocc_mask: a counted label lies outside 0 .. {self.num_classes - 1} (num_classes)")
        return self.loss(self.decoder(features), labels, counted)

    def loss(self, layers: Sequence[MaskDecoderOutput], labels: Tensor, counted: Tensor) -> dict[str, Tensor]:
        """The weighted terms for the decoder's ``layers`` against ``(B, X, Y, Z)`` labels at ``counted`` voxels.

        Computed in float32 with autocast off, whatever the logits' dtype (``bf16-mixed``: sums over ~1e5 voxels).
        """
        with torch.autocast(labels.device.type, enabled=False):
            return self._loss(layers, labels, counted)

    def _loss(self, layers: Sequence[MaskDecoderOutput], labels: Tensor, counted: Tensor) -> dict[str, Tensor]:
        safe = torch.where(counted, labels, torch.full_like(labels, self.free_label))
        terms = {"mask_cls": [], "mask_focal": [], "mask_dice": []}
        for out in layers:
            masks = out.mask_logits.float()
            if tuple(masks.shape[2:]) != tuple(labels.shape[1:]):  # V_fin's grid -> the label grid, voxel centres
                masks = F.interpolate(masks, size=labels.shape[1:], mode="trilinear", align_corners=False)
            per_group = masks.split(self.decoder.num_queries, dim=1)
            for g, (cls_logits, group_masks) in enumerate(zip(out.cls_logits, per_group, strict=True)):
                w = 1.0 if g == 0 else self.coarse_group_weight
                ce, focal, dice = self.group_loss(cls_logits.float(), group_masks, self.lookup[g][safe], counted)
                terms["mask_cls"].append(w * self.cls_weight * ce)
                terms["mask_focal"].append(w * self.focal_weight * focal)
                terms["mask_dice"].append(w * self.dice_weight * dice)
        return {k: torch.stack(v).sum() for k, v in terms.items()}

    def group_loss(self, cls_logits: Tensor, masks: Tensor, coarse: Tensor, counted: Tensor) -> tuple[Tensor, ...]:
        """CE, focal and dice of one group (unweighted).

        Args:
            cls_logits: ``(B, Q, K + 1)``.
            masks: ``(B, Q, X, Y, Z)`` mask logits on the label grid.
            coarse: ``(B, X, Y, Z)`` int64 coarse labels (``K`` = free).
            counted: ``(B, X, Y, Z)`` bool.

        Returns:
            ``(ce, focal, dice)`` scalars.
        """
        b, q, k1 = cls_logits.shape
        cls_logits = cls_logits.float()
        target = torch.full((b, q), k1 - 1, dtype=torch.int64, device=cls_logits.device)
        focal, dice = cls_logits.new_zeros(()), cls_logits.new_zeros(())
        matched, seen = 0, []
        for i in range(b):
            keep = counted[i]
            if not bool(keep.any()):
                continue  # nothing visible: no targets, not even "no object"
            seen.append(i)
            pred = masks[i][:, keep].float()  # (Q, V), float32 (the sums below run over every visible voxel)
            gt_coarse = coarse[i][keep]
            gt_labels = gt_coarse.unique()
            gt_masks = (gt_coarse[None] == gt_labels[:, None]).to(pred.dtype)  # (M, V); free is a mask too
            qi, gi = match_masks(
                cls_logits[i], pred, gt_labels, gt_masks, self.cls_weight, self.focal_weight, self.dice_weight,
                self.dice_eps,
            )  # fmt: skip
            target[i, qi] = gt_labels[gi]
            focal = focal + sigmoid_focal_loss(pred[qi], gt_masks[gi], 0.25, 2.0) / pred.shape[1]
            dice = dice + dice_loss(pred[qi], gt_masks[gi], self.dice_eps).sum()
            matched += int(qi.numel())
        if not seen:
            zero = (cls_logits.sum() + masks.sum()) * 0.0  # keeps the graph: every parameter gets a (zero) gradient
            return zero, zero, zero
        class_weight = cls_logits.new_ones(k1)
        class_weight[-1] = self.no_object_weight
        rows = torch.as_tensor(seen, device=cls_logits.device)
        ce = F.cross_entropy(cls_logits[rows].flatten(0, 1), target[rows].flatten(), weight=class_weight)
        norm = max(matched, 1)
        return ce, focal / norm, dice / norm

    @classmethod
    def conformance_outputs(cls, batch: Batch, grid: Any, channels: int) -> ModelOutputs:
        """A random ``V_fin`` (``channels`` channels, the ``in_channels`` the check gives; requires grad) on ``grid``
        at twice its voxel size."""
        coarse = coarse_grid(grid, 2)
        gen = torch.Generator().manual_seed(0)
        volume = torch.randn(len(batch), channels, *coarse.shape, generator=gen).requires_grad_(True)
        return ModelOutputs(None, None, StreamVoxelScene(volume, coarse, grid), {}, lambda *a, **k: None)
