"""The metric kind: torchmetrics Metrics fed with predicted class grids and the batch."""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Sequence
from typing import ClassVar, Literal

import torch
from torch import Tensor
from torchmetrics import Metric

from occplug.data.classes import class_groups
from occplug.data.frame import Batch
from occplug.geometry import GridSpec

__all__ = ["EvalMask", "OccMetric", "check_class_ids", "evaluation_mask", "excluded_class_ids", "group_class_ids"]

EvalMask = Literal["none", "camera", "lidar", "camera_and_lidar"]


class OccMetric(Metric):
    """Base of occplug metrics (registered under kind ``metric``).

    ``update(pred, batch)`` takes ``pred`` ``(B, X, Y, Z)`` int64 class ids on the evaluation grid
    (from ``model.predict_occupancy``) and reads ground truth from ``batch``. States are
    sum-reducible, so results are identical in one process or sharded over DDP ranks.
    ``compute()`` returns named scalars.

    .. versionadded:: 0.1
    """

    full_state_update = False
    #: Constructor arguments the model fills in when the config leaves them out (the run's ``grid`` among them, and
    #: ``mask``: the run's evaluation mask, the top-level ``eval_mask``).
    given: ClassVar[tuple[str, ...]] = ("num_classes", "class_names", "free_label", "ignore_label", "grid", "mask")
    #: Optional Frame fields the metric reads beyond the labels (see ``SupervisionSource.requires``).
    requires: frozenset[str] = frozenset()

    @classmethod
    def check_conformance(cls, component: OccMetric, batch: Batch, grid: GridSpec) -> None:
        """The kind's contract, checked: scalar results from ``compute`` after an ``update`` with the truth.

        :func:`occplug.testing.check_component` runs it on every registered component of this kind.
        """
        metric = component
        assert isinstance(metric, OccMetric)
        batch.require("voxel_labels", by="the metric conformance check")
        metric.update(batch.voxel_labels.long(), batch)
        perfect = metric.compute()
        assert isinstance(perfect, dict) and perfect, "compute() returns a non-empty dict"
        for key, value in perfect.items():
            assert value.dim() == 0, f"metric result '{key}' must be a scalar"
        metric.reset()

    @abstractmethod
    def update(self, pred: Tensor, batch: Batch) -> None:  # type: ignore[override]
        """Accumulate one batch."""

    @abstractmethod
    def compute(self) -> dict[str, Tensor]:
        """Named results."""

    def table(self) -> str:
        """A per-class text table of the current results (empty if the metric has none)."""
        return ""


def evaluation_mask(batch: Batch, mask: EvalMask) -> Tensor | None:
    """The ``(B, X, Y, Z)`` bool mask of voxels to evaluate, or None for all.

    Raises:
        ValueError: the batch lacks the mask the setting asks for.
    """
    if mask == "none":
        return None
    parts = {"camera": ["mask_camera"], "lidar": ["mask_lidar"], "camera_and_lidar": ["mask_camera", "mask_lidar"]}[
        mask
    ]
    batch.require(*parts, by=f"evaluation mask '{mask}'")
    out = torch.ones_like(getattr(batch, parts[0]), dtype=torch.bool)
    for name in parts:
        out &= getattr(batch, name).bool()
    return out


def check_class_ids(pred: Tensor, num_classes: int, who: str) -> None:
    """Raise a clear error when a prediction holds an id outside ``0..num_classes-1`` (e.g. 255).

    The confusion-matrix metrics (``occ3d_miou``, ``ssc``) call it: their reference scorers index a
    ``K x K`` matrix with the id, which fails or miscounts, and clamping would silently count it as the
    last class. RayIoU does not: like SparseOcc's scorer it treats such a voxel as occupied with no
    class (:mod:`occplug.metrics.rayiou`).
    """
    if pred.numel() and (int(pred.min()) < 0 or int(pred.max()) >= num_classes):
        bad = int(pred.min()) if int(pred.min()) < 0 else int(pred.max())
        raise ValueError(f"{who}: the prediction holds class id {bad}, outside 0..{num_classes - 1}")


def group_class_ids(
    class_names: Sequence[str], dynamic: Sequence[str] | None, static: Sequence[str] | None, who: str
) -> dict[str, list[int]]:
    """``{"dynamic": ids, "static": ids}``: the class groups a metric reports its ``<mean>_dynamic`` /
    ``<mean>_static`` keys over (``mIoU_dynamic``, ``RayIoU_static``, ...).

    The taxonomy's groups (:func:`occplug.data.classes.class_groups`: Occ3D-nuScenes, SemanticKITTI)
    unless ``dynamic`` / ``static`` name the classes of each group (both or neither); ``{}`` for
    another taxonomy without explicit groups (the metric then reports no group keys).

    Raises:
        ValueError: only one group given, or a name that is not one of ``class_names``.
    """
    if (dynamic is None) != (static is None):
        raise ValueError(f"{who}: give both dynamic_classes and static_classes, or neither")
    if dynamic is None:
        found = class_groups(list(class_names))
        return {k: list(v) for k, v in found.items()} if found else {}
    out: dict[str, list[int]] = {}
    for key, names in (("dynamic", dynamic), ("static", static)):
        for n in names:
            if n not in class_names:
                raise ValueError(f"{who}.{key}_classes: unknown class '{n}' (classes: {', '.join(class_names)})")
        out[key] = [list(class_names).index(n) for n in names]
    return out


def excluded_class_ids(class_names: Sequence[str], exclude: Sequence[str], free_label: int, who: str) -> list[int]:
    """The ids of ``exclude`` (a metric's ``exclude_classes``), which its ``<mean>_excl`` keys leave out.

    Raises:
        ValueError: a name that is not a semantic class (every class but ``free_label``), naming the
            valid ones.
    """
    semantic = [n for i, n in enumerate(class_names) if i != free_label]
    for n in exclude:
        if n not in semantic:
            raise ValueError(f"{who}.exclude_classes: unknown class '{n}' (semantic classes: {', '.join(semantic)})")
    return sorted({list(class_names).index(n) for n in exclude})
