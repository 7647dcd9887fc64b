"""Occ3D-nuScenes semantic mIoU and geometric IoU."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated

import torch
from torch import Tensor

from occplug.constraints import NonNegative, Positive
from occplug.data.frame import Batch

from .base import EvalMask, OccMetric, check_class_ids, evaluation_mask, excluded_class_ids, group_class_ids

__all__ = ["Occ3DMIoU", "confusion_matrix", "iou_from_confusion"]


def confusion_matrix(pred: Tensor, target: Tensor, num_classes: int, valid: Tensor | None = None) -> Tensor:
    """``(K, K)`` int64 counts, rows = ground truth, columns = prediction.

    Voxels whose target is outside ``[0, K)`` (e.g. 255 = ignore) or where ``valid`` is False
    are not counted. A predicted id outside ``[0, K)`` is an error.
    """
    check_class_ids(pred, num_classes, "confusion matrix")
    target = target.long().reshape(-1)
    pred = pred.long().reshape(-1)
    keep = (target >= 0) & (target < num_classes)
    if valid is not None:
        keep &= valid.reshape(-1).bool()
    idx = target[keep] * num_classes + pred[keep]
    return torch.bincount(idx, minlength=num_classes * num_classes).reshape(num_classes, num_classes)


def iou_from_confusion(confmat: Tensor) -> Tensor:
    """``(K,)`` float64 per-class IoU = TP / (TP + FP + FN); NaN where the class is absent in both."""
    cm = confmat.to(torch.float64)
    tp = cm.diagonal()
    denom = cm.sum(0) + cm.sum(1) - tp
    return torch.where(denom > 0, tp / denom.clamp_min(1), torch.full_like(tp, float("nan")))


class Occ3DMIoU(OccMetric):
    """Semantic mIoU and geometric IoU as the Occ3D-nuScenes benchmark defines them.

    Follows the official Occ3D evaluation (``Metric_mIoU`` of the Occ3D / CVPR 2023 occupancy
    challenge code): one confusion matrix over all evaluated voxels of the data set; per-class
    IoU = TP / (TP + FP + FN) for the semantic classes (every id except ``free_label``: ids 0-16
    of Occ3D-nuScenes); mIoU is the mean over classes with a defined IoU (NaN-mean: a class absent
    from both ground truth and prediction is skipped). Geometric ``IoU`` is occupied (≠ free) vs
    free over the same voxels. Only voxels inside the evaluation mask count; the Occ3D default is
    the camera mask. Values are reported in percent, as the benchmark prints them.

    ``mIoU_dynamic`` / ``mIoU_static`` are the same NaN-mean over the dynamic (object) and static
    (surface / structure) classes, as :func:`occplug.data.classes.class_groups` defines them for the
    Occ3D-nuScenes and SemanticKITTI taxonomies (Occ3D: ``others`` is in neither); other taxonomies
    report them only when ``dynamic_classes`` / ``static_classes`` are given.

    ``exclude_classes`` adds ``mIoU_excl`` (and ``mIoU_dynamic_excl`` / ``mIoU_static_excl`` where the
    groups are known): the same NaN-means leaving those classes out, e.g. the classes a method's
    pseudo-label taxonomy cannot express. The per-class keys and geometric ``IoU`` are unchanged.

    Args:
        num_classes: ``K``, ids ``0..K-1`` including ``free_label``.
        class_names: names for the per-class keys ``IoU_<name>`` (defaults to ``class_<id>``).
        free_label: the id of empty space (Occ3D: 17).
        mask: which voxels are evaluated: ``none``, ``camera`` (Occ3D default), ``lidar`` or
            ``camera_and_lidar``.
        dynamic_classes, static_classes: class names of the two groups, replacing the taxonomy's
            (both or neither).
        exclude_classes: semantic class names the ``*_excl`` keys leave out (none: no such keys).
    """

    def __init__(
        self,
        num_classes: Annotated[int, Positive] = 18,
        class_names: Sequence[str] | None = None,
        free_label: Annotated[int, NonNegative] = 17,
        mask: EvalMask = "camera",
        ignore_label: int | None = 255,
        dynamic_classes: Sequence[str] | None = None,
        static_classes: Sequence[str] | None = None,
        exclude_classes: Sequence[str] = (),
    ) -> None:
        super().__init__()
        self.num_classes = num_classes
        self.class_names = list(class_names) if class_names else [f"class_{i}" for i in range(num_classes)]
        if len(self.class_names) != num_classes:
            raise ValueError(f"class_names has {len(self.class_names)} names for {num_classes} classes")
        self.free_label = free_label
        self.mask = mask
        self.groups = group_class_ids(self.class_names, dynamic_classes, static_classes, "occ3d_miou")
        self.excluded = excluded_class_ids(self.class_names, exclude_classes, free_label, "occ3d_miou")
        self.add_state("confmat", torch.zeros(num_classes, num_classes, dtype=torch.int64), dist_reduce_fx="sum")

    def update(self, pred: Tensor, batch: Batch) -> None:  # type: ignore[override]
        """Add ``pred`` ``(B, X, Y, Z)`` against ``batch.voxel_labels`` inside the evaluation mask."""
        batch.require("voxel_labels", by="occ3d_miou")
        target = batch.voxel_labels
        if pred.shape != target.shape:
            raise ValueError(f"prediction shape {tuple(pred.shape)} differs from label shape {tuple(target.shape)}")
        self.confmat += confusion_matrix(pred, target, self.num_classes, evaluation_mask(batch, self.mask))

    def per_class_iou(self) -> Tensor:
        """``(K,)`` per-class IoU in [0, 1] (NaN where undefined), ``free`` included."""
        return iou_from_confusion(self.confmat)

    def compute(self) -> dict[str, Tensor]:
        """``mIoU``, ``IoU`` (geometric), ``IoU_<class>`` for each semantic class and, where the taxonomy
        has groups, ``mIoU_dynamic`` / ``mIoU_static``; with ``exclude_classes``, each mean again without
        those classes as ``<key>_excl``; in percent."""
        iou = self.per_class_iou()
        semantic = [c for c in range(self.num_classes) if c != self.free_label]
        means = {"mIoU": semantic, **{f"mIoU_{key}": ids for key, ids in self.groups.items()}}
        out = {key: torch.nanmean(iou[ids]) * 100 for key, ids in means.items()}
        if self.excluded:
            for key, ids in means.items():
                out[f"{key}_excl"] = torch.nanmean(iou[[c for c in ids if c not in self.excluded]]) * 100
        cm = self.confmat.to(torch.float64)
        occ = torch.ones(self.num_classes, dtype=torch.bool, device=cm.device)
        occ[self.free_label] = False
        tp = cm[occ][:, occ].sum()
        fp = cm[~occ][:, occ].sum()
        fn = cm[occ][:, ~occ].sum()
        denom = tp + fp + fn
        out["IoU"] = torch.where(denom > 0, tp / denom.clamp_min(1), torch.full_like(tp, float("nan"))) * 100
        for c in semantic:
            out[f"IoU_{self.class_names[c]}"] = iou[c] * 100
        return {k: v.to(torch.float32) for k, v in out.items()}

    def table(self) -> str:
        """Per-class IoU table (percent) headed by the mask setting."""
        res = self.compute()
        lines = [f"Occ3D mIoU (evaluation mask: {self.mask})", f"{'class':<24}{'IoU':>8}"]
        for c in range(self.num_classes):
            if c == self.free_label:
                continue
            lines.append(f"{self.class_names[c]:<24}{res[f'IoU_{self.class_names[c]}'].item():>8.2f}")
        lines.append(f"{'mIoU':<24}{res['mIoU'].item():>8.2f}")
        for key in self.groups:
            lines.append(f"{'mIoU ' + key:<24}{res[f'mIoU_{key}'].item():>8.2f}")
        lines.append(f"{'IoU (geometry)':<24}{res['IoU'].item():>8.2f}")
        if self.excluded:
            lines.append(f"without {', '.join(self.class_names[c] for c in self.excluded)}:")
            for key in ("mIoU", *(f"mIoU_{g}" for g in self.groups)):
                lines.append(f"{key.replace('_', ' ') + ' excl.':<24}{res[f'{key}_excl'].item():>8.2f}")
        return "\n".join(lines)
