"""Kind ``supervision``: turn a batch and the model's outputs into losses."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field

from torch import Tensor, nn

from occplug.data.frame import Batch

from .query import QueryResult
from .scene import Scene
from .view_transform import Lifted

__all__ = ["ModelOutputs", "SupervisionSource"]


@dataclass
class ModelOutputs:
    """Everything a forward pass produced, for supervision sources to read.

    Attributes:
        image_features: ``(B, N, C, h, w)`` encoder output.
        lifted: the view transform's output (volume, optional depth distributions).
        scene: the scene representation.
        heads: each head's named outputs, keyed by the head's config name.
        query: ``query(head_name, points, times=None) -> QueryResult`` asks the queryable head
            ``model.heads.<head_name>`` about ``(B, P, 3)`` ego-frame points of the current frame at
            ``(B, P)`` times in seconds relative to it (``None``: all 0); see
            :meth:`~occplug.interfaces.OccupancyHead.query`. 4D query supervision uses this.
        extras: model-specific additions (e.g. a teacher's predictions).
    """

    image_features: Tensor
    lifted: Lifted
    scene: Scene
    heads: dict[str, dict[str, Tensor]]
    query: Callable[..., QueryResult]
    extras: dict[str, object] = field(default_factory=dict)


class SupervisionSource(nn.Module, ABC):
    """A loss term family. ``weight`` scales every loss it returns.

    .. versionadded:: 0.1
    """

    #: Optional :class:`~occplug.data.Frame` fields this component reads (e.g. ``{"points"}``):
    #: data modules skip loading what no component requires (a camera-only model opens no LiDAR file).
    requires: frozenset[str] = frozenset()

    weight: float

    #: Config name of the head this source asks through :attr:`ModelOutputs.query` (``None``: none).
    #: A source that queries takes it as the constructor argument ``query_head`` and stores it here, so
    #: the model build (and config validation, from the argument) can check the head is queryable.
    query_head: str | None = None
    #: Whether its queries ask about other time steps (``times != 0``): the queried head must be temporal.
    #: Config validation reads the class attribute; a source whose need depends on its arguments sets it
    #: on the instance in its constructor (then the model build catches an impossible mix).
    needs_temporal_queries: bool = False

    @property
    def training_mask(self) -> str:
        """Which visibility mask restricts this source's targets: ``none``, ``camera``, ``lidar`` or
        ``camera_and_lidar`` (recorded in checkpoints and ``metrics.json`` beside the evaluation mask)."""
        return "none"

    @abstractmethod
    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        """Named, unweighted scalar losses (the model multiplies by ``weight`` and sums)."""
