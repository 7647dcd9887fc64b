"""A tiny per-point MLP occupancy head."""

from __future__ import annotations

from typing import Annotated

from torch import Tensor, nn

import occplug
from occplug.constraints import Positive


class TinyMLPHead(occplug.OccupancyHead):
    """A two-layer MLP with a GELU over the scene's features at each query point: the example plugin's head.

    It only implements :meth:`query`; the voxel logits (``forward``, evaluation) come from the core's
    chunked :meth:`~occplug.OccupancyHead.occupancy_logits`, which queries the voxel centres.

    Args:
        in_channels: scene feature size (filled in by the model).
        num_classes: logits per point (filled in from the data set's classes).
        hidden: hidden width of the MLP.
    """

    queryable = True  # any scene that can be sampled at points; current frame only (temporal = False)

    def __init__(
        self, in_channels: int, num_classes: Annotated[int, Positive], hidden: Annotated[int, Positive] = 16
    ) -> None:
        super().__init__()
        self.num_classes = num_classes
        self.mlp = nn.Sequential(nn.Linear(in_channels, hidden), nn.GELU(), nn.Linear(hidden, num_classes))

    def forward(self, scene: occplug.Scene, batch: occplug.Batch) -> dict[str, Tensor]:
        """``{"logits": (B, K, X, Y, Z)}`` on the scene's grid."""
        return {"logits": self.occupancy_logits(scene, scene.grid)}

    def query(self, scene: occplug.Scene, points: Tensor, times: Tensor | None = None) -> occplug.QueryResult:
        """``(B, P, K)`` class logits at ``(B, P, 3)`` ego-frame points of the current frame."""
        self.check_query(points, times)
        return occplug.QueryResult(class_logits=self.mlp(scene.sample(points)))


__all__ = ["TinyMLPHead"]
