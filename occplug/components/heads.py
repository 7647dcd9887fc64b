"""Occupancy head ``voxel_classifier``: a per-voxel (per-point) MLP classifier."""

from __future__ import annotations

from typing import Annotated

from torch import Tensor, nn

from occplug.constraints import NonNegative, Positive
from occplug.data.frame import Batch
from occplug.geometry import GridSpec
from occplug.interfaces import DEFAULT_QUERY_CHUNK, OccupancyHead, QueryResult, Scene

__all__ = ["VoxelClassifier"]


class VoxelClassifier(OccupancyHead):
    """Classify scene features with an MLP ``Linear -> ReLU -> Linear``, per voxel or per point.

    Queryable (the scene is read at the points, trilinearly for dense voxels), not temporal. The
    same MLP serves the dense path (over ``scene.features``) and :meth:`query` (over
    ``scene.sample(points)``), so the two agree at voxel centres. It predicts ``free`` as one of its
    ``K`` classes (no occupancy logit).

    Args:
        in_channels: ``C`` of the scene features.
        num_classes: ``K`` (Occ3D: 18 with ``free`` = 17).
        hidden: width of the hidden layer (0: a linear classifier).
    """

    queryable = True
    temporal = False

    def __init__(
        self, in_channels: int, num_classes: Annotated[int, Positive], hidden: Annotated[int, NonNegative] = 64
    ) -> None:
        super().__init__()
        if hidden < 0:
            raise ValueError(f"voxel_classifier hidden must be >= 0, got {hidden}")
        self.num_classes = int(num_classes)
        if hidden > 0:
            self.mlp: nn.Module = nn.Sequential(
                nn.Linear(in_channels, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, self.num_classes)
            )
        else:
            self.mlp = nn.Linear(in_channels, self.num_classes)

    def classify(self, features: Tensor) -> Tensor:
        """``(..., C)`` channels-last features -> ``(..., K)`` logits."""
        return self.mlp(features)

    def forward(self, scene: Scene, batch: Batch) -> dict[str, Tensor]:
        """``{"logits": (B, K, X, Y, Z)}`` on ``scene.grid``."""
        return {"logits": self.occupancy_logits(scene, scene.grid)}

    def occupancy_logits(self, scene: Scene, grid: GridSpec, chunk_size: int = DEFAULT_QUERY_CHUNK) -> Tensor:
        """``(B, K, X, Y, Z)`` logits at the centres of ``grid``'s voxels.

        On the scene's own dense grid this classifies ``scene.features`` directly (the fast path,
        equal to the query default); on any other grid, or a non-dense scene, it is the chunked
        query default of :meth:`OccupancyHead.occupancy_logits`.
        """
        feats = scene.features
        if grid == scene.grid and feats.dim() == 5 and tuple(feats.shape[2:]) == grid.shape:
            return self.classify(feats.movedim(1, -1)).movedim(-1, 1)
        return super().occupancy_logits(scene, grid, chunk_size)

    def query(self, scene: Scene, points: Tensor, times: Tensor | None = None) -> QueryResult:
        """Class logits ``(B, P, K)`` of ``scene.sample(points)`` at ``(B, P, 3)`` ego-frame points (``times``: 0 only)."""
        self.check_query(points, times)
        return QueryResult(class_logits=self.classify(scene.sample(points)))
