"""A tiny per-voxel MLP occupancy head."""

from __future__ import annotations

from torch import Tensor, nn

import occplug


class TinyMLPHead(occplug.OccupancyHead):
    """A two-layer per-voxel MLP with a GELU: the example plugin's occupancy head.

    Args:
        in_channels: scene feature size (filled in by the model).
        num_classes: logits per voxel (filled in from the data set's classes).
        hidden: hidden width of the MLP.
    """

    def __init__(self, in_channels: int, num_classes: int = 18, hidden: int = 16) -> None:
        super().__init__()
        self.num_classes = num_classes
        self.mlp = nn.Sequential(nn.Linear(in_channels, hidden), nn.GELU(), nn.Linear(hidden, num_classes))

    def _classify_volume(self, features: Tensor) -> Tensor:
        return self.mlp(features.movedim(1, -1)).movedim(-1, 1)

    def forward(self, scene: occplug.Scene, batch: occplug.Batch) -> dict[str, Tensor]:
        """``{"logits": (B, K, X, Y, Z)}`` on the scene's grid."""
        return {"logits": self._classify_volume(scene.features)}

    def occupancy_logits(self, scene: occplug.Scene, grid: occplug.GridSpec) -> Tensor:
        """Logits on ``grid``: the scene's own grid directly, any other grid by querying its centres."""
        if grid == scene.grid:
            return self._classify_volume(scene.features)
        b = scene.features.shape[0]
        centers = grid.centers(device=scene.features.device).reshape(1, -1, 3).expand(b, -1, -1)
        return self.query(scene, centers).transpose(1, 2).reshape(b, self.num_classes, *grid.shape)

    def query(self, scene: occplug.Scene, points: Tensor) -> Tensor:
        """``(B, P, K)`` logits at continuous ego-frame points."""
        return self.mlp(scene.sample(points))


__all__ = ["TinyMLPHead"]
