"""Kind ``head``: read a :class:`~occplug.interfaces.Scene` and predict."""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.geometry import GridSpec

from .query import QueryResult
from .scene import Scene

__all__ = ["DEFAULT_QUERY_CHUNK", "Head", "OccupancyHead"]

#: Points per :meth:`OccupancyHead.query` call in the default :meth:`OccupancyHead.occupancy_logits`
#: (Occ3D's 640k voxel centres: 10 calls per sample).
DEFAULT_QUERY_CHUNK = 65536


class Head(nn.Module, ABC):
    """Any prediction head. Constructors take ``in_channels`` (filled in from the scene), and may take
    ``num_classes`` and ``free_label`` (filled in from the data set).

    .. versionadded:: 0.1
    """

    #: Optional :class:`~occplug.data.Frame` fields this component reads (e.g. ``{"points"}``):
    #: data modules skip loading what no component requires (a camera-only model opens no LiDAR file).
    requires: frozenset[str] = frozenset()

    #: Whether :meth:`OccupancyHead.query` answers at arbitrary continuous points (query supervision needs it).
    queryable: bool = False
    #: Whether its queries may ask about other time steps (``times != 0``); only a queryable head can be.
    temporal: bool = False

    @abstractmethod
    def forward(self, scene: Scene, batch: Batch) -> dict[str, Tensor]:
        """Named predictions for the batch (training and validation outputs)."""


class OccupancyHead(Head):
    """A head that predicts semantic occupancy; the model evaluates through one of these.

    A queryable head implements :meth:`query` and gets :meth:`occupancy_logits` for free (chunked
    over the voxel centres); it may override that with a faster exact path. A head that cannot be
    queried implements :meth:`occupancy_logits` itself.

    Attributes:
        num_classes: ``K``, logits per voxel / point (Occ3D: 18 with ``free`` = 17).
        free_label: label id of ``free``; a head whose queries return an occupancy logit needs it
            (take ``free_label`` as a constructor argument: the model passes the data set's).

    ``forward`` returns at least ``{"logits": (B, K, X, Y, Z)}`` on the scene's grid.
    """

    num_classes: int
    free_label: int | None = None

    def query(self, scene: Scene, points: Tensor, times: Tensor | None = None) -> QueryResult:
        """The head's answer at continuous 4D points.

        Args:
            scene: the scene of the current frame.
            points: ``(B, P, 3)`` ego-frame points of the current frame, metres.
            times: ``(B, P)`` seconds relative to the current frame (``None``: all 0). A head that is
                not :attr:`temporal` raises ``ValueError`` for any non-zero time
                (:meth:`check_query` does the checks).

        Returns:
            a :class:`QueryResult` with ``(B, P, K)`` class logits (and optionally an occupancy logit
            and features). The default raises ``TypeError``: this head is not queryable.
        """
        raise TypeError(f"{type(self).__name__} cannot be queried at arbitrary points (queryable = False)")

    def check_query(self, points: Tensor, times: Tensor | None = None) -> None:
        """Raise ``ValueError`` unless ``points`` is ``(B, P, 3)``, ``times`` ``None`` or ``(B, P)``, and
        ``times`` all zero for a head that is not :attr:`temporal`. Call it first in :meth:`query`."""
        name = type(self).__name__
        if points.dim() != 3 or points.shape[-1] != 3:
            raise ValueError(f"{name}.query: points must be (B, P, 3) ego-frame metres, got {tuple(points.shape)}")
        if times is None:
            return
        if tuple(times.shape) != tuple(points.shape[:2]):
            raise ValueError(f"{name}.query: times must be (B, P) = {tuple(points.shape[:2])}, got {tuple(times.shape)}")
        if not self.temporal and times.numel() and bool((times != 0).any()):
            lo, hi = float(times.min()), float(times.max())
            raise ValueError(
                f"{name} is not temporal: it answers queries at t = 0 (the current frame) only, got times in [{lo:g}, {hi:g}] s"
            )

    def occupancy_logits(self, scene: Scene, grid: GridSpec, chunk_size: int = DEFAULT_QUERY_CHUNK) -> Tensor:
        """``(B, K, X, Y, Z)`` logits at the centres of ``grid``'s voxels (the evaluation grid).

        The default queries the centres at ``t = 0``, ``chunk_size`` points at a time, and writes each
        chunk's :meth:`QueryResult.logits` (``free``'s logit from the occupancy logit where the head
        returns one) into the output, so the memory beyond the output is bounded by the chunk, not the
        grid. ``argmax`` over ``K`` gives the class ids (:meth:`OccModel.predict_occupancy`).

        Args:
            scene: the scene of the current frame.
            grid: the grid whose voxel centres are queried (ego frame).
            chunk_size: query points per call (per sample).
        """
        if not self.queryable:
            raise TypeError(f"{type(self).__name__} is not queryable: it must implement occupancy_logits itself")
        if chunk_size < 1:
            raise ValueError(f"occupancy_logits: chunk_size must be >= 1, got {chunk_size}")
        b, device = scene.batch_size, scene.device
        nx, ny, nz = grid.shape
        n = nx * ny * nz
        out: Tensor | None = None
        for start in range(0, n, chunk_size):
            flat = torch.arange(start, min(start + chunk_size, n), device=device)
            index = torch.stack((flat // (ny * nz), flat // nz % ny, flat % nz), dim=-1)
            points = grid.index_to_coord(index).to(device).unsqueeze(0).expand(b, -1, -1)
            logits = self.query(scene, points).logits(self.free_label)  # (B, p, K)
            if out is None:
                out = logits.new_empty(b, logits.shape[-1], n)
            out[:, :, start : start + len(flat)] = logits.transpose(1, 2)
        assert out is not None  # a grid has at least one voxel
        return out.view(b, -1, nx, ny, nz)
