"""Occupancy head ``voxel_classifier``: a per-voxel (per-point) MLP classifier."""

from __future__ import annotations

from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.geometry import GridSpec
from occplug.interfaces import OccupancyHead, Scene

__all__ = ["VoxelClassifier"]


class VoxelClassifier(OccupancyHead):
    """Classify scene features with an MLP ``Linear -> ReLU -> Linear``, per voxel or per point.

    The same MLP serves the dense path (a 1x1x1 conv over ``scene.features``) and
    :meth:`query` (over ``scene.sample(points)``), so the two agree exactly at voxel centres.

    Args:
        in_channels: ``C`` of the scene features.
        num_classes: ``K`` (Occ3D: 18 with ``free`` = 17).
        hidden: width of the hidden layer (0: a linear classifier).
    """

    def __init__(self, in_channels: int, num_classes: int = 18, hidden: int = 64) -> None:
        super().__init__()
        if hidden < 0:
            raise ValueError(f"voxel_classifier hidden must be >= 0, got {hidden}")
        self.num_classes = int(num_classes)
        if hidden > 0:
            self.mlp: nn.Module = nn.Sequential(nn.Linear(in_channels, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, self.num_classes))
        else:
            self.mlp = nn.Linear(in_channels, self.num_classes)

    def classify(self, features: Tensor) -> Tensor:
        """``(..., C)`` channels-last features -> ``(..., K)`` logits."""
        return self.mlp(features)

    def forward(self, scene: Scene, batch: Batch) -> dict[str, Tensor]:
        """``{"logits": (B, K, X, Y, Z)}`` on ``scene.grid``."""
        return {"logits": self.occupancy_logits(scene, scene.grid)}

    def occupancy_logits(self, scene: Scene, grid: GridSpec) -> Tensor:
        """``(B, K, X, Y, Z)`` logits at the centres of ``grid``'s voxels.

        On the scene's own dense grid this classifies ``scene.features`` directly; on any other
        grid (or a non-dense scene) it queries the scene at ``grid.centers()``.
        """
        feats = scene.features
        if grid == scene.grid and feats.dim() == 5 and tuple(feats.shape[2:]) == grid.shape:
            return self.classify(feats.movedim(1, -1)).movedim(-1, 1)
        b = feats.shape[0]
        centers = grid.centers(device=feats.device).to(feats.dtype).reshape(1, -1, 3).expand(b, -1, -1)
        return self.query(scene, centers).transpose(1, 2).reshape(b, self.num_classes, *grid.shape)

    def query(self, scene: Scene, points: Tensor) -> Tensor:
        """``(B, P, K)`` logits at ``(B, P, 3)`` ego-frame points (classifies ``scene.sample(points)``)."""
        return self.classify(scene.sample(points))
