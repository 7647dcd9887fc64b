"""Kind ``head``: read a :class:`~occplug.interfaces.Scene` and predict."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.geometry import GridSpec

from .scene import Scene

__all__ = ["Head", "OccupancyHead"]


class Head(nn.Module, ABC):
    """Any prediction head.

    Contract:
        given: ``in_channels`` (the scene's ``out_channels``) and ``num_classes`` (the data set's).
        declares: ``reads`` -- the config names of other heads whose outputs this head consumes.
        The model runs heads in an order where every head comes after the heads it reads (a
        cycle or an unknown name is a config error) and calls a head that reads anything, or
        that sets ``reads_outputs = True``, as ``forward(scene, batch, outputs)`` with the
        :class:`~occplug.interfaces.ModelOutputs` so far (earlier heads in ``outputs.heads``,
        every image level, point-encoder volumes; it may add to ``outputs.extras``).
        conformance: :meth:`conformance_inputs` gives a dense voxel scene; a head that needs
        another scene (a BEV plane, a query set) overrides it.

    .. versionadded:: 0.1
    .. versionchanged:: 0.2 ``reads`` / ``reads_outputs``: heads that consume other heads.
    """

    #: Constructor arguments the model fills in when the config leaves them out.
    given: ClassVar[tuple[str, ...]] = ("in_channels", "num_classes")
    #: Config names of the heads whose outputs this head reads (an instance may set its own).
    reads: tuple[str, ...] = ()
    #: Whether ``forward`` takes a third argument, the :class:`~occplug.interfaces.ModelOutputs` so far.
    reads_outputs: ClassVar[bool] = False

    #: Optional :class:`~occplug.data.Frame` fields this component reads (e.g. ``{"points"}``):
    #: data modules skip loading what no component requires (a camera-only model opens no LiDAR file).
    requires: frozenset[str] = frozenset()

    @abstractmethod
    def forward(self, scene: Scene, batch: Batch) -> dict[str, Tensor]:
        """Named predictions for the batch (training and validation outputs).

        A head with ``reads`` (or ``reads_outputs``) is called with a third argument ``outputs``.
        """

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple[Any, ...]:
        """Positional ``forward`` inputs for the conformance check: a random dense voxel scene on
        ``grid`` and the batch."""
        from occplug.components.scenes import DenseVoxelScene

        gen = torch.Generator().manual_seed(0)
        volume = torch.randn(len(batch), channels, *grid.shape, generator=gen)
        return (DenseVoxelScene(volume, grid), batch)


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
