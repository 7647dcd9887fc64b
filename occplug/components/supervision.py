"""Supervision source ``voxel_ce``: cross-entropy of voxel logits against ``batch.voxel_labels``."""

from __future__ import annotations

from typing import Annotated, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from occplug.constraints import NonNegative, UnitInterval, check_choices
from occplug.data.frame import Batch
from occplug.interfaces import ModelOutputs, SupervisionSource

__all__ = ["VoxelCrossEntropy"]

_IGNORE = -100  # internal ignore value handed to F.cross_entropy


class VoxelCrossEntropy(SupervisionSource):
    """Cross-entropy of an occupancy head's ``(B, K, X, Y, Z)`` logits against the voxel labels.

    A voxel counts when its sample has ``batch.has_voxel_labels``, its label is not
    ``ignore_label``, it is not flagged in ``batch.voxel_invalid`` (SemanticKITTI's ``.invalid``
    voxels, which the benchmark ignores too), and (if asked) ``batch.mask_camera`` /
    ``batch.mask_lidar`` is set there.
    The loss is the mean over counted voxels, exactly ``F.cross_entropy(logits[counted],
    labels[counted], weight=class_weights, label_smoothing=label_smoothing)`` (with class weights,
    normalised by the summed weights of the counted labels, as PyTorch does; ``normalize: count`` divides the
    weighted sum by the number of counted voxels instead, as e.g. the public DuOcc and FlashOcc code do). A batch with no
    counted voxel gives a zero loss that still depends on the logits, so every rank of a
    distributed run reaches the same backward.

    Args:
        weight: scale applied by the model to the returned loss.
        head: which head's outputs to read: ``outputs.heads[head]["logits"]``.
        camera_mask: count only voxels with ``batch.mask_camera`` (Occ3D's camera-visible mask).
        lidar_mask: count only voxels with ``batch.mask_lidar``.
        ignore_label: label id never counted (filled from the data module when left out); None: none.
        class_weights: ``K`` per-class weights, or None for uniform.
        label_smoothing: as in :func:`torch.nn.functional.cross_entropy`.
        normalize: ``weights`` (the summed class weight of the counted voxels, PyTorch's ``mean``) or ``count``
            (the number of counted voxels); the two agree without class weights.

    Needs batch fields: ``voxel_labels`` ``(B, X, Y, Z)`` (integer class ids, same shape as the
    logits' grid), ``has_voxel_labels`` ``(B,)``, and ``mask_camera`` / ``mask_lidar`` when asked.

    Returns:
        ``{"voxel_ce": scalar loss}`` (unweighted).
    """

    def __init__(
        self,
        weight: Annotated[float, NonNegative] = 1.0,
        head: str = "occupancy",
        camera_mask: bool = False,
        lidar_mask: bool = False,
        ignore_label: int | None = 255,
        class_weights: list[Annotated[float, NonNegative]] | None = None,
        label_smoothing: Annotated[float, UnitInterval] = 0.0,
        normalize: Literal["weights", "count"] = "weights",
    ) -> None:
        super().__init__()
        if not 0.0 <= label_smoothing <= 1.0:
            raise ValueError(f"voxel_ce label_smoothing must lie in [0, 1], got {label_smoothing}")
        self.weight = float(weight)
        self.head = head
        self.camera_mask = bool(camera_mask)
        self.lidar_mask = bool(lidar_mask)
        self.ignore_label = ignore_label
        self.label_smoothing = float(label_smoothing)
        check_choices(VoxelCrossEntropy.__init__, "voxel_ce", normalize=normalize)
        self.normalize = normalize
        cw = None if class_weights is None else torch.tensor([float(v) for v in class_weights], dtype=torch.float32)
        self.register_buffer("class_weights", cw, persistent=False)

    def _logits(self, outputs: ModelOutputs) -> Tensor:
        if self.head not in outputs.heads:
            raise ValueError(
                f"voxel_ce reads head '{self.head}', but the model's heads are: {', '.join(outputs.heads) or '(none)'}"
            )
        head_out = outputs.heads[self.head]
        if "logits" not in head_out:
            raise ValueError(f"voxel_ce needs head '{self.head}' to output 'logits'; it outputs: {', '.join(head_out)}")
        return head_out["logits"]

    @property
    def training_mask(self) -> str:
        """``camera``, ``lidar``, ``camera_and_lidar`` or ``none``, from ``camera_mask`` / ``lidar_mask``."""
        return {
            (False, False): "none",
            (True, False): "camera",
            (False, True): "lidar",
            (True, True): "camera_and_lidar",
        }[(self.camera_mask, self.lidar_mask)]

    def counted(self, batch: Batch, labels: Tensor) -> Tensor:
        """``(B, X, Y, Z)`` bool: the voxels that count toward the loss."""
        keep = batch.has_voxel_labels.to(labels.device).view(-1, 1, 1, 1).expand_as(labels)
        if self.ignore_label is not None:
            keep = keep & (labels != self.ignore_label)
        if batch.voxel_invalid is not None:
            keep = keep & ~batch.voxel_invalid.bool()
        if self.camera_mask:
            batch.require("mask_camera", by="voxel_ce with camera_mask")
            keep = keep & batch.mask_camera.bool()
        if self.lidar_mask:
            batch.require("mask_lidar", by="voxel_ce with lidar_mask")
            keep = keep & batch.mask_lidar.bool()
        return keep

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        """``{"voxel_ce": loss}``; see the class docstring."""
        batch.require("voxel_labels", by="voxel_ce")
        logits = self._logits(outputs)
        labels = batch.voxel_labels.long()
        if logits.dim() != 5 or logits.shape[0] != labels.shape[0] or logits.shape[2:] != labels.shape[1:]:
            raise ValueError(
                f"voxel_ce: head '{self.head}' logits {tuple(logits.shape)} (B, K, X, Y, Z) do not match the voxel "
                f"labels {tuple(labels.shape)} (B, X, Y, Z); the head's grid must be the label grid"
            )
        k = logits.shape[1]
        if self.class_weights is not None and self.class_weights.numel() != k:
            raise ValueError(
                f"voxel_ce: class_weights has {self.class_weights.numel()} entries but the logits have {k} classes"
            )
        keep = self.counted(batch, labels)
        target = labels.masked_fill(~keep, _IGNORE)
        weights = None if self.class_weights is None else self.class_weights.to(logits.dtype)
        per_voxel = F.cross_entropy(
            logits, target, weight=weights, ignore_index=_IGNORE, label_smoothing=self.label_smoothing, reduction="none"
        )
        # "weights" is PyTorch's mean: the summed weight of the counted targets; "count": how many there are.
        if weights is None or self.normalize == "count":
            denom = keep.sum().to(per_voxel.dtype)
        else:
            denom = (weights[target.clamp_min(0)] * keep).sum()
        loss = per_voxel.sum() / denom.clamp_min(torch.finfo(per_voxel.dtype).tiny)
        return {"voxel_ce": loss}
