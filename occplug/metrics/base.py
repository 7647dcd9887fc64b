"""The metric kind: torchmetrics Metrics fed with predicted class grids and the batch."""

from __future__ import annotations

from abc import abstractmethod
from typing import Literal

import torch
from torch import Tensor
from torchmetrics import Metric

from occplug.data.frame import Batch

__all__ = ["EvalMask", "OccMetric", "evaluation_mask"]

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
    parts = {"camera": ["mask_camera"], "lidar": ["mask_lidar"], "camera_and_lidar": ["mask_camera", "mask_lidar"]}[mask]
    batch.require(*parts, by=f"evaluation mask '{mask}'")
    out = torch.ones_like(getattr(batch, parts[0]), dtype=torch.bool)
    for name in parts:
        out &= getattr(batch, name).bool()
    return out
