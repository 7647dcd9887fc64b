"""OccLE's losses (§3.5.1, Eq. 6): class-weighted cross-entropy and the composite occupancy loss.

``l_ce`` is "the weighted cross-entropy loss, with weights computed from class frequencies" and ``l_occ`` "a
comprehensive occupancy loss, following prior work" (VoxFormer, Symphonies, SGN). Those all use MonoScene's
semantic scene completion losses, reproduced here: class-weighted CE with ``w_c = 1 / log(f_c + 0.001)``, plus
the scene-class affinity losses ``sem_scal`` and ``geo_scal``. ``l_occ(S, S̄)`` of the semantic branch is applied
"only to voxels containing more than one point" (:func:`lidar_count_mask`); every loss takes a ``mask`` for that
and for camera-visibility masks.

All functions take logits ``(B, K, *spatial)`` (3D grids ``(B, K, X, Y, Z)`` or images ``(B, K, H, W)``) and
integer labels ``(B, *spatial)``. A cell counts when its label is not ``ignore_index`` and ``mask`` (if given) is
True there. Softmax probabilities and counts are pooled over the whole batch, as MonoScene does. With no counted
cell a loss is an exact zero that still depends on the logits (every rank of a distributed run reaches the same
backward).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occplug.data import inverse_log_weights
from occplug.geometry import GridSpec

__all__ = [
    "OccupancyLoss",
    "class_weights_from_frequencies",
    "geo_scal_loss",
    "lidar_count_mask",
    "sem_scal_loss",
    "weighted_cross_entropy",
]

#: SemanticKITTI's (and MonoScene's) "unknown" label.
IGNORE_INDEX = 255


def class_weights_from_frequencies(frequencies: Tensor | Sequence[float], eps: float = 0.001) -> Tensor:
    """MonoScene's class weights ``w_c = 1 / log(f_c + eps)`` (§3.5.1 says only "computed from class frequencies").

    Args:
        frequencies: ``(K,)`` **raw counts** of each class over the training set (voxels, or pixels for the image
            loss), as MonoScene's ``semantic_kitti_class_frequencies``; normalised frequencies would make the
            logarithm negative.
        eps: the ``0.001`` of MonoScene.

    Returns:
        ``(K,)`` float32 weights, larger for rarer classes.
    """
    return inverse_log_weights(frequencies, scale=1.0, eps=eps)


def _counted(labels: Tensor, mask: Tensor | None, ignore_index: int) -> Tensor:
    keep = labels != ignore_index
    if mask is not None:
        if mask.shape != labels.shape:
            raise ValueError(f"loss mask {tuple(mask.shape)} must match the labels {tuple(labels.shape)}")
        keep = keep & mask.to(device=labels.device, dtype=torch.bool)
    return keep


def _check(logits: Tensor, labels: Tensor, name: str) -> None:
    if logits.dim() < 2 or logits.shape[0] != labels.shape[0] or logits.shape[2:] != labels.shape[1:]:
        raise ValueError(
            f"{name}: logits {tuple(logits.shape)} (B, K, *spatial) do not match labels {tuple(labels.shape)} "
            "(B, *spatial)"
        )


def _probabilities(logits: Tensor, keep: Tensor) -> Tensor:
    """``(M, K)`` softmax probabilities of the counted cells, computed in float32 at least."""
    k = logits.shape[1]
    probs = F.softmax(logits.float() if logits.dtype in (torch.float16, torch.bfloat16) else logits, dim=1)
    return probs.movedim(1, -1).reshape(-1, k)[keep.reshape(-1)]


def _bce_to_one(x: Tensor) -> Tensor:
    # BCE against a target of 1 is -log(x); F.binary_cross_entropy clamps the log at -100 like MonoScene's.
    # The clamp keeps round-off above 1 (a ratio of sums) inside BCE's domain.
    x = x.clamp(0.0, 1.0)
    return F.binary_cross_entropy(x, torch.ones_like(x), reduction="none")


def weighted_cross_entropy(
    logits: Tensor,
    labels: Tensor,
    class_weights: Tensor | None = None,
    mask: Tensor | None = None,
    ignore_index: int = IGNORE_INDEX,
) -> Tensor:
    """Class-weighted cross-entropy ``l_ce`` (OccLE Eq. 6; MonoScene's ``CE_ssc_loss``).

    Exactly ``F.cross_entropy(logits, labels, weight=class_weights, ignore_index=ignore_index)`` over the counted
    cells: the weighted mean, divided by the summed weights of the counted labels.

    Args:
        logits: ``(B, K, *spatial)``.
        labels: ``(B, *spatial)`` integer class ids in ``[0, K)`` or ``ignore_index``.
        class_weights: ``(K,)`` (e.g. :func:`class_weights_from_frequencies`) or None for uniform.
        mask: ``(B, *spatial)`` bool, cells to count (e.g. a camera mask or :func:`lidar_count_mask`), or None.
        ignore_index: label never counted.

    Returns:
        Scalar loss.
    """
    _check(logits, labels, "weighted_cross_entropy")
    keep = _counted(labels, mask, ignore_index)
    if not bool(keep.any()):
        return logits.sum() * 0.0
    target = labels.long().masked_fill(~keep, ignore_index)
    weight = None if class_weights is None else class_weights.to(device=logits.device, dtype=logits.dtype)
    return F.cross_entropy(logits, target, weight=weight, ignore_index=ignore_index)


def sem_scal_loss(
    logits: Tensor, labels: Tensor, mask: Tensor | None = None, ignore_index: int = IGNORE_INDEX
) -> Tensor:
    """MonoScene's semantic scene-class affinity loss (``sem_scal_loss``), vectorised over classes.

    With ``p_c`` the softmax probability of class ``c`` and ``y_c = [label == c]`` over the counted cells, per class
    present in the labels (``sum y_c > 0``; MonoScene includes the free class)::

        precision_c   = sum p_c y_c / sum p_c                      (term dropped if sum p_c == 0)
        recall_c      = sum p_c y_c / sum y_c
        specificity_c = sum (1 - p_c)(1 - y_c) / sum (1 - y_c)      (term dropped if every cell is class c)
        loss = mean over present classes of [BCE(precision_c, 1) + BCE(recall_c, 1) + BCE(specificity_c, 1)]

    Args:
        logits: ``(B, K, *spatial)``.
        labels: ``(B, *spatial)`` integer class ids in ``[0, K)`` or ``ignore_index``.
        mask: ``(B, *spatial)`` bool cells to count, or None.
        ignore_index: label never counted.

    Returns:
        Scalar loss (0 at a perfect prediction, ``BCE(x, 1) = -log x``).
    """
    _check(logits, labels, "sem_scal_loss")
    keep = _counted(labels, mask, ignore_index)
    if not bool(keep.any()):
        return logits.sum() * 0.0
    p = _probabilities(logits, keep)  # (M, K)
    y = F.one_hot(labels[keep].long(), p.shape[1]).to(p.dtype)  # (M, K)
    hit = (p * y).sum(0)
    p_sum, y_sum = p.sum(0), y.sum(0)
    neg_sum = (1.0 - y).sum(0)
    tiny = torch.finfo(p.dtype).tiny  # safe denominators: a 0/0 would poison the gradient even when masked
    precision = _bce_to_one(hit / p_sum.clamp_min(tiny)) * (p_sum > 0)
    recall = _bce_to_one(hit / y_sum.clamp_min(tiny))
    specificity = _bce_to_one(((1.0 - p) * (1.0 - y)).sum(0) / neg_sum.clamp_min(tiny)) * (neg_sum > 0)
    present = y_sum > 0
    return ((precision + recall + specificity) * present).sum() / present.sum()


def geo_scal_loss(
    logits: Tensor,
    labels: Tensor,
    mask: Tensor | None = None,
    ignore_index: int = IGNORE_INDEX,
    free_label: int = 0,
) -> Tensor:
    """MonoScene's geometric scene-class affinity loss (``geo_scal_loss``): the same terms for empty vs. occupied.

    With ``q = 1 - p_free`` (probability of "occupied") and ``o = [label != free_label]`` over the counted cells::

        precision   = sum q o / sum q
        recall      = sum q o / sum o
        specificity = sum (1 - q)(1 - o) / sum (1 - o)
        loss = BCE(precision, 1) + BCE(recall, 1) + BCE(specificity, 1)

    A term whose denominator is zero (no occupied or no free counted cell) is dropped; MonoScene's would be NaN.

    Args:
        logits: ``(B, K, *spatial)``.
        labels: ``(B, *spatial)`` integer class ids or ``ignore_index``.
        mask: ``(B, *spatial)`` bool cells to count, or None.
        ignore_index: label never counted.
        free_label: id of the free/empty class (0 in SemanticKITTI and MonoScene; 17 in Occ3D-nuScenes).

    Returns:
        Scalar loss.
    """
    _check(logits, labels, "geo_scal_loss")
    keep = _counted(labels, mask, ignore_index)
    if not bool(keep.any()):
        return logits.sum() * 0.0
    q = 1.0 - _probabilities(logits, keep)[:, free_label]  # (M,)
    o = (labels[keep] != free_label).to(q.dtype)
    hit = (q * o).sum()
    q_sum, o_sum, free_sum = q.sum(), o.sum(), (1.0 - o).sum()
    tiny = torch.finfo(q.dtype).tiny
    precision = _bce_to_one(hit / q_sum.clamp_min(tiny)) * (q_sum > 0)
    recall = _bce_to_one(hit / o_sum.clamp_min(tiny)) * (o_sum > 0)
    specificity = _bce_to_one(((1.0 - q) * (1.0 - o)).sum() / free_sum.clamp_min(tiny)) * (free_sum > 0)
    return precision + recall + specificity


def lidar_count_mask(points: Sequence[Tensor], grid: GridSpec, min_points: int = 2) -> Tensor:
    """Voxels holding at least ``min_points`` LiDAR points: where OccLE applies ``l_occ(S, S̄)`` (§3.5.1).

    The paper's "voxels containing more than one point" reads literally as ``min_points = 2`` (the default);
    pass 1 for "any point".

    Args:
        points: ``B`` tensors ``(P_b, >=3)`` whose first three columns are **ego-frame** x, y, z in metres (the
            core's ``Batch.points`` are in the LiDAR frame: transform them with ``Batch.lidar_to_ego`` first).
        grid: the label grid.
        min_points: threshold on the per-voxel point count.

    Returns:
        ``(B, X, Y, Z)`` bool.
    """
    x, y, z = grid.shape
    masks = []
    for pts in points:  # one sample at a time: the point counts differ
        idx = grid.coord_to_index(pts[:, :3])
        idx = idx[grid.contains(pts[:, :3]) & grid.index_in_bounds(idx)]
        flat = (idx[:, 0] * y + idx[:, 1]) * z + idx[:, 2]
        counts = torch.bincount(flat, minlength=x * y * z)
        masks.append((counts >= min_points).reshape(x, y, z))
    return torch.stack(masks) if masks else torch.zeros(0, x, y, z, dtype=torch.bool)


class OccupancyLoss(nn.Module):
    """The composite occupancy loss ``l_occ`` of OccLE Eq. 6: class-weighted CE + ``sem_scal`` + ``geo_scal``.

    Args:
        class_weights: ``K`` CE class weights (e.g. :func:`class_weights_from_frequencies`), or None for uniform.
        free_label: id of the free/empty class, for ``geo_scal`` (0 in SemanticKITTI).
        ignore_index: label never counted (255 in SemanticKITTI).
        ce_weight, sem_scal_weight, geo_scal_weight: scale of each term (1 in MonoScene and its followers).

    Forward: ``logits`` ``(B, K, *spatial)``, ``labels`` ``(B, *spatial)``, optional ``mask`` ``(B, *spatial)`` bool
    -> ``{"ce", "sem_scal", "geo_scal"}`` scalar losses, already scaled; ``l_occ`` is their sum.
    """

    def __init__(
        self,
        class_weights: Sequence[float] | Tensor | None = None,
        free_label: int = 0,
        ignore_index: int = IGNORE_INDEX,
        ce_weight: float = 1.0,
        sem_scal_weight: float = 1.0,
        geo_scal_weight: float = 1.0,
    ) -> None:
        super().__init__()
        cw = None if class_weights is None else torch.as_tensor(class_weights, dtype=torch.float32).clone()
        self.register_buffer("class_weights", cw, persistent=False)
        self.free_label = int(free_label)
        self.ignore_index = int(ignore_index)
        self.ce_weight = float(ce_weight)
        self.sem_scal_weight = float(sem_scal_weight)
        self.geo_scal_weight = float(geo_scal_weight)

    def forward(self, logits: Tensor, labels: Tensor, mask: Tensor | None = None) -> dict[str, Tensor]:
        """The three scaled terms; see the class docstring."""
        k = logits.shape[1]
        if self.class_weights is not None and self.class_weights.numel() != k:
            raise ValueError(f"OccupancyLoss: {self.class_weights.numel()} class weights for {k} classes")
        if not 0 <= self.free_label < k:
            raise ValueError(f"OccupancyLoss: free_label {self.free_label} is not a class of {k}-class logits")
        return {
            "ce": self.ce_weight * weighted_cross_entropy(logits, labels, self.class_weights, mask, self.ignore_index),
            "sem_scal": self.sem_scal_weight * sem_scal_loss(logits, labels, mask, self.ignore_index),
            "geo_scal": self.geo_scal_weight
            * geo_scal_loss(logits, labels, mask, self.ignore_index, free_label=self.free_label),
        }
