"""Sigmoid focal and dice losses of binary predictions (detection classes, instance / semantic masks).

Every function takes **logits** (``p = sigmoid(logits)``) and same-width float targets in ``[0, 1]`` (usually 0 or
1). The element-wise forms compare a prediction with its own target; the ``pairwise_`` forms compare every one of
``Q`` predictions with every one of ``M`` targets, the cost matrix of a Hungarian matching
(:func:`~occplug.nn.linear_assignment`) between predicted and ground-truth masks (Mask2Former's matcher), and their
diagonal equals the element-wise loss of matching rows.
"""

from __future__ import annotations

from typing import Literal

import torch.nn.functional as F
from torch import Tensor

__all__ = ["dice_loss", "pairwise_dice_loss", "pairwise_sigmoid_focal_loss", "sigmoid_focal_loss"]


def sigmoid_focal_loss(
    logits: Tensor,
    targets: Tensor,
    alpha: float = 0.25,
    gamma: float = 2.0,
    reduction: Literal["sum", "mean", "none"] = "sum",
) -> Tensor:
    """Sigmoid focal loss (Lin et al., RetinaNet): ``a_t (1 - p_t)^gamma BCE(logits, targets)`` per element.

    ``p_t = p t + (1 - p)(1 - t)`` and ``a_t = alpha t + (1 - alpha)(1 - t)``; the cross-entropy is
    ``binary_cross_entropy_with_logits`` (stable for large logits).

    Args:
        logits: any shape.
        targets: the shape of ``logits``, floats in ``[0, 1]``.
        alpha: weight of the positives (``1 - alpha`` of the negatives).
        gamma: focusing exponent (0: plain weighted BCE).
        reduction: ``"sum"`` over every element (the detection losses then divide by their number of matched
            objects), ``"mean"``, or ``"none"`` (the per-element losses, shape of ``logits``).

    Returns:
        A scalar, or the per-element losses for ``"none"``.
    """
    if reduction not in ("sum", "mean", "none"):
        raise ValueError(f"sigmoid_focal_loss: reduction must be 'sum', 'mean' or 'none', got {reduction!r}")
    p = logits.sigmoid()
    ce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    p_t = p * targets + (1 - p) * (1 - targets)
    a_t = alpha * targets + (1 - alpha) * (1 - targets)
    loss = a_t * (1 - p_t).pow(gamma) * ce
    if reduction == "none":
        return loss
    return loss.sum() if reduction == "sum" else loss.mean()


def pairwise_sigmoid_focal_loss(logits: Tensor, targets: Tensor, alpha: float = 0.25, gamma: float = 2.0) -> Tensor:
    """The sigmoid focal loss of every prediction row against every target row, averaged over the columns.

    Computed as two matrix products (``-log p`` and ``-log(1 - p)`` as softplus, stable), without the ``(Q, M, V)``
    intermediate; for binary targets it equals :func:`sigmoid_focal_loss` of each pair up to round-off.

    Args:
        logits: ``(Q, V)``, e.g. mask logits of ``Q`` queries at ``V`` voxels.
        targets: ``(M, V)`` binary target rows (float).
        alpha, gamma: as :func:`sigmoid_focal_loss`.

    Returns:
        ``(Q, M)``; entry ``[q, m]`` is ``sigmoid_focal_loss(logits[q], targets[m]) / V``.
    """
    p = logits.sigmoid()
    pos = alpha * (1 - p).pow(gamma) * F.softplus(-logits)  # -log p, stably
    neg = (1 - alpha) * p.pow(gamma) * F.softplus(logits)  # -log(1 - p)
    return (pos @ targets.T + neg @ (1 - targets).T) / max(logits.shape[-1], 1)


def dice_loss(logits: Tensor, targets: Tensor, eps: float = 1.0) -> Tensor:
    """Dice loss ``1 - (2 sum p t + eps) / (sum p + sum t + eps)`` of paired rows, summed over the last axis.

    Args:
        logits: ``(..., V)`` (``p = sigmoid(logits)``).
        targets: the shape of ``logits``, in ``[0, 1]``.
        eps: smoothing; it keeps two empty masks at loss 0 rather than 0 / 0.

    Returns:
        ``(...)``: one loss per row, in ``[0, 1)``.
    """
    p = logits.sigmoid()
    return 1 - (2 * (p * targets).sum(-1) + eps) / (p.sum(-1) + targets.sum(-1) + eps)


def pairwise_dice_loss(logits: Tensor, targets: Tensor, eps: float = 1.0) -> Tensor:
    """:func:`dice_loss` of every prediction row against every target row.

    Args:
        logits: ``(Q, V)``.
        targets: ``(M, V)``.
        eps: smoothing, as :func:`dice_loss`.

    Returns:
        ``(Q, M)``; its diagonal (for ``Q = M``) is ``dice_loss(logits, targets, eps)`` up to round-off.
    """
    p = logits.sigmoid()
    return 1 - (2 * p @ targets.T + eps) / (p.sum(-1)[:, None] + targets.sum(-1)[None] + eps)
