"""Hungarian matching of DuOcc's instance queries to ground-truth boxes (Sparse4D v3's assigner).

DuOcc's image-to-query detector is Sparse4D v3 (paper §3.2, "I2Q") trained with its detection loss
(suppl. A.4), whose one-to-one assignment minimises, per sample, the cost (Sparse4D v3
``SparseBox3DTarget``; values of DuOcc's config, ``projects/configs/DuOcc.py``)

``C[q, g] = cls_weight * (pos(p_q,c_g) - neg(p_q,c_g)) + box_weight * sum_d w_g,d * r_d * |b_q,d - b_g,d|``

with ``p = sigmoid(logit)``, ``pos(p) = -alpha (1 - p)^gamma log(p + eps)``,
``neg(p) = -(1 - alpha) p^gamma log(1 - p + eps)`` (the focal-loss-style class cost of Deformable DETR),
``cls_weight = 2``, ``alpha = 0.25``, ``gamma = 2``, ``box_weight = 0.25`` and the per-dimension
regression weights ``r = [2, 2, 2, 0.5, 0.5, 0.5, 0, 0, 0, 0]`` on Sparse4D's box encoding
(:func:`encode_boxes`); ``w_g`` is 1 except for the classes given in ``class_reg_weights`` (DuOcc: the
traffic cone's ``[2, 2, 2, 1, 1, 1, 0, 0, 1, 1]``) and 0 where a target is NaN.

The core's :func:`occplug.nn.linear_assignment` (scipy's ``linear_sum_assignment``) solves the assignment; scipy
is imported only when a match runs (install ``occplug[duocc]``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from occplug.nn import linear_assignment

__all__ = ["SPARSE4D_REG_WEIGHTS", "encode_boxes", "hungarian_match", "matching_cost"]

#: Sparse4D v3 / DuOcc regression weights of the matching cost on ``encode_boxes`` of a 9-column box.
SPARSE4D_REG_WEIGHTS = (2.0, 2.0, 2.0, 0.5, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0)


def encode_boxes(boxes: Tensor) -> Tensor:
    """Sparse4D's regression encoding of ego-frame boxes.

    Args:
        boxes: ``(..., 7)`` ``[x, y, z, l, w, h, yaw]`` or ``(..., 9)`` with ``vx, vy`` (the
            :class:`~occplug.Frame` ``boxes`` layout; ``l`` along the heading, metres, radians).

    Returns:
        ``(..., 8)`` ``[x, y, z, log l, log w, log h, sin yaw, cos yaw]`` or ``(..., 10)`` with ``vx, vy``.
    """
    if boxes.shape[-1] not in (7, 9):
        raise ValueError(f"encode_boxes: expected 7 or 9 columns (x, y, z, l, w, h, yaw[, vx, vy]), got {boxes.shape}")
    yaw = boxes[..., 6:7]
    return torch.cat([boxes[..., :3], boxes[..., 3:6].log(), yaw.sin(), yaw.cos(), boxes[..., 7:]], dim=-1)


def matching_cost(
    cls_logits: Tensor,
    box_pred: Tensor,
    gt_labels: Tensor,
    gt_boxes: Tensor,
    cls_weight: float = 2.0,
    box_weight: float = 0.25,
    alpha: float = 0.25,
    gamma: float = 2.0,
    reg_weights: Sequence[float] | None = SPARSE4D_REG_WEIGHTS,
    class_reg_weights: Mapping[int, Sequence[float]] | None = None,
    eps: float = 1e-12,
) -> Tensor:
    """The matching cost of one sample (module docstring).

    Args:
        cls_logits: ``(Q, K)`` class logits (sigmoid classification, no background column).
        box_pred: ``(Q, D)`` predicted boxes, encoded (e.g. :func:`encode_boxes`).
        gt_labels: ``(G,)`` int64 class ids in ``[0, K)``.
        gt_boxes: ``(G, D)`` ground-truth boxes in the same encoding; NaN entries are not compared.
        cls_weight, box_weight, alpha, gamma, eps: as in the module docstring.
        reg_weights: ``(D,)`` per-dimension weights ``r``; None: all ones.
        class_reg_weights: ``{class id: (D,) weights}`` replacing ``w_g`` for ground truths of that class.

    Returns:
        ``(Q, G)`` cost, ``dtype`` of ``cls_logits``.
    """
    q, d = box_pred.shape
    if gt_boxes.shape[-1] != d:
        raise ValueError(f"matching_cost: predicted boxes have {d} columns, ground truth {gt_boxes.shape[-1]}")
    p = cls_logits.sigmoid()
    neg = -(1 - p + eps).log() * (1 - alpha) * p.pow(gamma)
    pos = -(p + eps).log() * alpha * (1 - p).pow(gamma)
    cls_cost = (pos - neg)[:, gt_labels.long()] * cls_weight  # (Q, G)
    weights = (~gt_boxes.isnan()).to(box_pred.dtype)  # (G, D) w_g
    if class_reg_weights:
        for cls, w in class_reg_weights.items():
            weights = torch.where((gt_labels == cls)[:, None], weights.new_tensor(w), weights)
    if reg_weights is not None:
        if len(reg_weights) != d:
            raise ValueError(f"matching_cost: {len(reg_weights)} reg_weights for {d} box columns")
        weights = weights * weights.new_tensor(reg_weights)
    # a NaN target has weight 0: compare against 0 instead, so 0 * |delta| stays finite
    target = torch.nan_to_num(gt_boxes.to(box_pred.dtype), nan=0.0)
    box_cost = ((box_pred[:, None] - target[None]).abs() * weights[None]).sum(-1) * box_weight
    return cls_cost + box_cost.to(cls_cost.dtype)


@torch.no_grad()
def hungarian_match(
    cls_logits: Tensor,
    box_pred: Tensor,
    gt_labels: Sequence[Tensor],
    gt_boxes: Sequence[Tensor],
    cls_weight: float = 2.0,
    box_weight: float = 0.25,
    alpha: float = 0.25,
    gamma: float = 2.0,
    reg_weights: Sequence[float] | None = SPARSE4D_REG_WEIGHTS,
    class_reg_weights: Mapping[int, Sequence[float]] | None = None,
) -> list[tuple[Tensor, Tensor]]:
    """One-to-one assignment of queries to ground truth per sample (Sparse4D v3, as DuOcc trains it).

    Args:
        cls_logits: ``(B, Q, K)`` class logits.
        box_pred: ``(B, Q, D)`` encoded predicted boxes (:func:`encode_boxes`).
        gt_labels: ``B`` tensors ``(G_b,)`` int64 class ids.
        gt_boxes: ``B`` tensors ``(G_b, D)`` in the same encoding.
        cls_weight, box_weight, alpha, gamma, reg_weights, class_reg_weights: see :func:`matching_cost`.

    Returns:
        ``B`` pairs ``(pred_idx, gt_idx)``, each ``(min(Q, G_b),)`` int64 (empty where ``G_b = 0``):
        query ``pred_idx[i]`` is matched to ground truth ``gt_idx[i]``; other queries are background.
    """
    if not len(gt_labels) == len(gt_boxes) == cls_logits.shape[0] == box_pred.shape[0]:
        raise ValueError("hungarian_match: cls_logits, box_pred, gt_labels and gt_boxes need one entry per sample")
    out = []
    for b in range(cls_logits.shape[0]):
        cost = matching_cost(
            cls_logits[b],
            box_pred[b],
            gt_labels[b],
            gt_boxes[b],
            cls_weight=cls_weight,
            box_weight=box_weight,
            alpha=alpha,
            gamma=gamma,
            reg_weights=reg_weights,
            class_reg_weights=class_reg_weights,
        )
        out.append(linear_assignment(cost))
    return out
