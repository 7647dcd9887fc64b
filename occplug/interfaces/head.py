"""Kind ``head``: read a :class:`~occplug.interfaces.Scene` and predict."""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.geometry import GridSpec

from .scene import Scene

__all__ = ["Head", "OccupancyHead"]


class Head(nn.Module, ABC):
    """Any prediction head. Constructors take ``in_channels`` (filled in from the scene).

    .. versionadded:: 0.1
    """

    #: Optional :class:`~occplug.data.Frame` fields this component reads (e.g. ``{"points"}``):
    #: data modules skip loading what no component requires (a camera-only model opens no LiDAR file).
    requires: frozenset[str] = frozenset()

    @abstractmethod
    def forward(self, scene: Scene, batch: Batch) -> dict[str, Tensor]:
        """Named predictions for the batch (training and validation outputs)."""


class OccupancyHead(Head):
    """A head that predicts semantic occupancy; the model evaluates through one of these.

    Attributes:
        num_classes: ``K``, logits per voxel / point (Occ3D: 18 with ``free`` = 17).

    ``forward`` returns at least ``{"logits": (B, K, X, Y, Z)}`` on the scene's grid.
    """

    num_classes: int

    @abstractmethod
    def occupancy_logits(self, scene: Scene, grid: GridSpec) -> Tensor:
        """``(B, K, X, Y, Z)`` logits at the centres of ``grid``'s voxels (the evaluation grid)."""

    def query(self, scene: Scene, points: Tensor) -> Tensor:
        """``(B, P, K)`` logits at continuous ego-frame points ``(B, P, 3)``.

        The default reads the scene at the points and classifies them; heads that cannot
        answer arbitrary points raise ``TypeError``.
        """
        raise TypeError(f"{type(self).__name__} cannot be queried at arbitrary points")
