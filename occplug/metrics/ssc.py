"""SemanticKITTI semantic scene completion: completion IoU and semantic mIoU.

Definition followed: the SemanticKITTI SSC benchmark, ``evaluate_completion.py`` and
``auxiliary/np_ioueval.py`` of github.com/PRBonn/semantic-kitti-api (the Codalab scorer):

* evaluated voxels: ground truth not 255 and not flagged in ``.invalid`` (``batch.voxel_invalid``);
* one ``K x K`` confusion matrix over every evaluated voxel of the data set;
* per-class IoU = TP / (TP + FP + FN) with the scorer's epsilon, so a class absent from both ground
  truth and prediction scores **0** (not NaN) and still counts in the mean;
* ``mIoU`` = plain mean over the semantic classes (every id except ``free_label``: 1..19);
* completion ``IoU`` = occupied-in-both / (all evaluated - empty-in-both), occupied = label != free
  (``acc_cmpltn``); ``Precision`` = occupied-in-both / predicted occupied, ``Recall`` =
  occupied-in-both / ground-truth occupied.

Values are in percent (the scorer prints ``* 100`` too). Predictions must be SSC class ids; the
benchmark's remapping of raw label files happens in :mod:`occplug.data.semantickitti.format`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated

import torch
from torch import Tensor

from occplug.constraints import NonNegative, Positive
from occplug.data.classes import SEMANTIC_KITTI_CLASSES, class_groups
from occplug.data.frame import Batch

from .base import OccMetric, excluded_class_ids
from .miou import confusion_matrix

__all__ = ["SSCMetrics", "ssc_scores"]

_EPS = 1e-15  # np_ioueval's union epsilon


def ssc_scores(confmat: Tensor, free_label: int) -> dict[str, Tensor]:
    """Benchmark scores (fractions) of a ``(K, K)`` confusion matrix, rows = ground truth.

    Returns:
        ``iou`` ``(K,)`` per class, ``mIoU``, ``IoU`` (completion), ``Precision``, ``Recall`` (float64).
    """
    cm = confmat.to(torch.float64)
    tp = cm.diagonal()
    iou = tp / (cm.sum(0) + cm.sum(1) - tp + _EPS)
    semantic = [c for c in range(cm.shape[0]) if c != free_label]
    occ = torch.ones(cm.shape[0], dtype=torch.bool, device=cm.device)
    occ[free_label] = False
    both = cm[occ][:, occ].sum()
    completion = both / (cm.sum() - cm[free_label, free_label])  # NaN when nothing is occupied in either
    return {
        "iou": iou,
        "mIoU": iou[semantic].mean(),
        "IoU": completion,
        "Precision": both / (cm[:, occ].sum() + _EPS),
        "Recall": both / (cm[occ].sum() + _EPS),
    }


class SSCMetrics(OccMetric):
    """SemanticKITTI SSC completion IoU and semantic mIoU (registered as metric ``ssc``).

    ``compute()`` returns ``IoU`` (completion), ``mIoU``, ``Precision``, ``Recall`` and
    ``IoU_<class>`` for every semantic class, in percent; see the module docstring for the exact
    definition. The state is the confusion matrix ``confmat`` ``(K, K)`` (rows = ground truth),
    summed over ranks.

    ``exclude_classes`` adds ``mIoU_excl`` (and ``mIoU_dynamic_excl`` / ``mIoU_static_excl`` where the
    groups are known): the same plain means (the scorer's) leaving those classes out. The benchmark's
    own keys are unchanged.

    Args:
        num_classes: ``K`` (SemanticKITTI: 20, ids 0..19 with 0 = empty).
        class_names: names for the per-class keys (default: SemanticKITTI's when ``K = 20``).
        free_label: the empty id (SemanticKITTI: 0).
        ignore_label: ground-truth id that is never evaluated (SemanticKITTI: 255).
        exclude_classes: semantic class names the ``*_excl`` keys leave out (none: no such keys).
    """

    def __init__(
        self,
        num_classes: Annotated[int, Positive] = 20,
        class_names: Sequence[str] | None = None,
        free_label: Annotated[int, NonNegative] = 0,
        ignore_label: int | None = 255,
        exclude_classes: Sequence[str] = (),
    ) -> None:
        super().__init__()
        if class_names:
            names = list(class_names)
        elif num_classes == len(SEMANTIC_KITTI_CLASSES):
            names = list(SEMANTIC_KITTI_CLASSES)
        else:
            names = [f"class_{i}" for i in range(num_classes)]
        if len(names) != num_classes:
            raise ValueError(f"class_names has {len(names)} names for {num_classes} classes")
        if not 0 <= free_label < num_classes:
            raise ValueError(f"free_label {free_label} is not a class id 0..{num_classes - 1}")
        self.num_classes = num_classes
        self.class_names = names
        self.free_label = free_label
        self.ignore_label = ignore_label
        self.groups = {k: list(v) for k, v in (class_groups(self.class_names) or {}).items()}
        self.excluded = excluded_class_ids(self.class_names, exclude_classes, free_label, "ssc")
        self.add_state("confmat", torch.zeros(num_classes, num_classes, dtype=torch.int64), dist_reduce_fx="sum")

    def update(self, pred: Tensor, batch: Batch) -> None:  # type: ignore[override]
        """Add ``pred`` ``(B, X, Y, Z)`` against ``batch.voxel_labels``, skipping ignored and invalid voxels."""
        batch.require("voxel_labels", by="ssc")
        target = batch.voxel_labels
        if pred.shape != target.shape:
            raise ValueError(f"prediction shape {tuple(pred.shape)} differs from label shape {tuple(target.shape)}")
        valid = torch.ones_like(target, dtype=torch.bool)
        if self.ignore_label is not None:
            valid &= target != self.ignore_label
        if batch.voxel_invalid is not None:
            valid &= ~batch.voxel_invalid.bool()
        self.confmat += confusion_matrix(pred, target, self.num_classes, valid)

    def compute(self) -> dict[str, Tensor]:
        """``IoU`` (completion), ``mIoU``, ``Precision``, ``Recall``, ``IoU_<class>`` and, for a taxonomy with
        dynamic / static groups (SemanticKITTI's, :mod:`occplug.data.classes`), ``mIoU_dynamic`` / ``mIoU_static``
        (the scorer's plain mean over each group) and, with ``exclude_classes``, each mean again without those
        classes as ``<key>_excl``; in percent."""
        scores = ssc_scores(self.confmat, self.free_label)
        out = {key: scores[key] * 100 for key in ("IoU", "mIoU", "Precision", "Recall")}
        for key, ids in self.groups.items():
            out[f"mIoU_{key}"] = scores["iou"][ids].mean() * 100
        if self.excluded:
            for key, ids in self._means().items():
                out[f"{key}_excl"] = scores["iou"][[c for c in ids if c not in self.excluded]].mean() * 100
        for c in range(self.num_classes):
            if c != self.free_label:
                out[f"IoU_{self.class_names[c]}"] = scores["iou"][c] * 100
        return {k: v.to(torch.float32) for k, v in out.items()}

    def _means(self) -> dict[str, list[int]]:
        """The class-mean keys and their class ids: ``mIoU`` and the group means."""
        semantic = [c for c in range(self.num_classes) if c != self.free_label]
        return {"mIoU": semantic, **{f"mIoU_{key}": ids for key, ids in self.groups.items()}}

    def table(self) -> str:
        """The benchmark's per-class table (percent), headed by the settings."""
        res = self.compute()
        ignored = "ignore label none" if self.ignore_label is None else f"ignore label {self.ignore_label}"
        lines = [
            f"SemanticKITTI SSC (semantic-kitti-api scorer; empty = {self.class_names[self.free_label]} ({self.free_label}), "
            f"{ignored} and invalid voxels skipped)",
            f"{'class':<24}{'IoU':>8}",
        ]
        for c in range(self.num_classes):
            if c != self.free_label:
                lines.append(f"{self.class_names[c]:<24}{res[f'IoU_{self.class_names[c]}'].item():>8.2f}")
        for key, label in (
            ("mIoU", "mIoU (SSC)"),
            ("IoU", "IoU (completion)"),
            ("Precision", "Precision"),
            ("Recall", "Recall"),
            *((f"mIoU_{g}", f"mIoU {g}") for g in self.groups),  # after the benchmark's own lines
        ):
            lines.append(f"{label:<24}{res[key].item():>8.2f}")
        if self.excluded:
            lines.append(f"without {', '.join(self.class_names[c] for c in self.excluded)}:")
            for key in self._means():
                lines.append(f"{key.replace('_', ' ') + ' excl.':<24}{res[f'{key}_excl'].item():>8.2f}")
        return "\n".join(lines)
