"""Sparse4D v3's detection loss for DuOcc's image-to-query detector (:mod:`.detector`), suppl. A.4 ``L_det``.

:func:`detection_loss`: per decoder layer, Hungarian matching (:func:`~.matching.hungarian_match`), sigmoid focal
classification (:func:`occplug.nn.sigmoid_focal_loss`) and weighted L1 regression on
:func:`~.matching.encode_boxes`; with the detector's denoising queries, their loss too (:func:`~.denoising.denoising_loss`).

Assumptions (where the paper is silent; the public code's choices, from its config, are these):

* Suppl. A.4 / code loss: focal (alpha 0.25, gamma 2) x 2.0 and L1 x 0.25 with per-dimension weights
  ``[2, 2, 2, 1, 1, 1, 1, 1, 1, 1]``, both divided by the number of matched ground truths in the batch (at least
  1), summed over layers; the box loss counts only matches whose score exceeds ``reg_score_threshold`` (0.05,
  Sparse4D's ``cls_threshold_to_reg``). DuOcc's overall weight 0.2 is the caller's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from occplug.nn import sigmoid_focal_loss

from .boxes import BOX_DIM
from .denoising import denoising_loss
from .detector import DetectorOutput
from .matching import SPARSE4D_REG_WEIGHTS, encode_boxes, hungarian_match

__all__ = ["SPARSE4D_LOSS_REG_WEIGHTS", "detection_loss"]

#: Sparse4D v3's per-dimension weights of the L1 box loss on the encoded box.
SPARSE4D_LOSS_REG_WEIGHTS = (2.0, 2.0, 2.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0)


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
