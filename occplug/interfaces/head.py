"""Kind ``head``: read a :class:`~occplug.interfaces.Scene` and predict."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.geometry import GridSpec

from .checks import CHECK_CHANNELS, assert_finite, assert_gradient, eval_twice
from .query import QueryResult
from .scene import DenseVoxelScene, Scene

__all__ = ["DEFAULT_QUERY_CHUNK", "Head", "OccupancyHead"]

#: Points per :meth:`OccupancyHead.query` call in the default :meth:`OccupancyHead.occupancy_logits`
#: (Occ3D's 640k voxel centres: 10 calls per sample).
DEFAULT_QUERY_CHUNK = 65536


class Head(nn.Module, ABC):
    """Any prediction head.

    Contract:
        given: ``in_channels`` (the scene's ``out_channels``), ``num_classes`` and ``free_label``
        (the data set's), and, to a head that takes it, ``image_channels`` (the image encoder's
        ``out_channels``, the width of ``outputs.image_features``).
        declares: ``reads`` -- the config names of other heads whose outputs this head consumes.
        The model runs heads in an order where every head comes after the heads it reads (a
        cycle or an unknown name is a config error) and calls a head that reads anything, or
        that sets ``reads_outputs = True``, as ``forward(scene, batch, outputs)`` with the
        :class:`~occplug.interfaces.ModelOutputs` so far (earlier heads in ``outputs.heads``,
        every image level, point-encoder volumes; it may add to ``outputs.extras``).
        conformance: :meth:`conformance_inputs` gives a dense voxel scene; a head that needs
        another scene (a BEV plane, a query set) overrides it, and a head that reads outputs returns
        ``(scene, batch, outputs)`` with the outputs it reads.

    .. versionadded:: 0.1
    .. versionchanged:: 0.2 ``reads`` / ``reads_outputs``: heads that consume other heads.
    """

    #: Constructor arguments the model fills in when the config leaves them out.
    given: ClassVar[tuple[str, ...]] = ("in_channels", "num_classes", "free_label", "grid", "image_channels")
    #: Config names of the heads whose outputs this head reads (an instance may set its own).
    reads: tuple[str, ...] = ()
    #: Whether ``forward`` takes a third argument, the :class:`~occplug.interfaces.ModelOutputs` so far.
    reads_outputs: ClassVar[bool] = False
    #: Whether it carries state from frame to frame (a :class:`~occplug.streams.StreamState`); a stateful model
    #: needs ``data.sequential``.
    stateful: ClassVar[bool] = False

    #: Optional :class:`~occplug.data.Frame` fields this component reads (e.g. ``{"points"}``):
    #: data modules skip loading what no component requires (a camera-only model opens no LiDAR file).
    requires: frozenset[str] = frozenset()

    #: Whether :meth:`OccupancyHead.query` answers at arbitrary continuous points (query supervision needs it).
    queryable: bool = False
    #: Whether its queries may ask about other time steps (``times != 0``); only a queryable head can be.
    temporal: bool = False

    @abstractmethod
    def forward(self, scene: Scene, batch: Batch) -> dict[str, Tensor]:
        """Named predictions for the batch (training and validation outputs).

        A head with ``reads`` (or ``reads_outputs``) is called with a third argument ``outputs``.
        """

    @classmethod
    def check_conformance(cls, component: Head, batch: Batch, grid: GridSpec) -> None:
        """The kind's contract, checked: named tensors, deterministic in eval; an occupancy head's
        ``occupancy_logits`` equal its forward logits and its queries at voxel centres equal them; gradients.

        :func:`occplug.testing.check_component` runs it on every registered component of this kind.
        """
        head = component
        inputs = type(head).conformance_inputs(batch, grid, CHECK_CHANNELS)
        scene = inputs[0]
        first, second = eval_twice(head, lambda m: m(*inputs))
        assert isinstance(first, dict) and all(isinstance(v, Tensor) for v in first.values()), (
            "a head returns dict[str, Tensor]"
        )
        for key in first:
            assert torch.equal(first[key], second[key]), f"head output '{key}' is not deterministic in eval mode"
        assert_finite(first, "head output")
        reads = bool(getattr(head, "reads", ())) or head.reads_outputs
        if isinstance(head, OccupancyHead) and not reads:  # a reading head is evaluated from its forward logits
            head.eval()
            logits = head.occupancy_logits(scene, grid)
            assert logits.shape == (len(batch), head.num_classes, *grid.shape), (
                f"occupancy_logits {tuple(logits.shape)}"
            )
            assert torch.allclose(logits, head(*inputs)["logits"], atol=1e-5), "occupancy_logits != forward logits"
            if head.queryable:  # queries at voxel centres agree with the voxel logits; t != 0 only for temporal heads
                idx = torch.tensor([[1, 2, 3], [5, 0, 1]])
                pts = grid.index_to_coord(idx)[None].expand(len(batch), -1, -1)
                result = head.query(scene, pts)
                assert isinstance(result, QueryResult), f"query returned a {type(result).__name__}, not a QueryResult"
                expected = logits[:, :, idx[:, 0], idx[:, 1], idx[:, 2]].transpose(1, 2)
                queried = result.logits(head.free_label)
                assert torch.allclose(queried, expected, atol=1e-4), "query at voxel centres != occupancy logits"
                if not head.temporal:
                    try:
                        head.query(scene, pts, torch.full(pts.shape[:2], 0.5))
                    except ValueError:
                        pass
                    else:
                        raise AssertionError("a head that is not temporal must reject queries at t != 0 (ValueError)")
            head.train()
        out = head(*inputs)
        torch.stack([v.float().square().mean() for v in out.values() if v.is_floating_point()]).sum().backward()
        assert_gradient(head, "head")

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple[Any, ...]:
        """Positional ``forward`` inputs for the conformance check: a random dense voxel scene on
        ``grid`` and the batch."""
        gen = torch.Generator().manual_seed(0)
        volume = torch.randn(len(batch), channels, *grid.shape, generator=gen)
        return (DenseVoxelScene(volume, grid), batch)


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
    #: Occupancy probability below which a query with an occupancy logit predicts ``free``
    #: (:meth:`QueryResult.logits`); a head may take it as a constructor argument.
    occupancy_threshold: float = 0.5
    #: Points per axis at which :meth:`occupancy_logits` queries each voxel: 1, the centre; ``s > 1``, the centres of
    #: its ``s x s x s`` sub-cells, the voxel taking the answer of the most occupied one (a voxel label marks a voxel
    #: occupied when any surface lies in it; a continuous field can be free at the centre of a voxel its surface
    #: only clips). Needs an occupancy logit; a head may take it as a constructor argument.
    voxel_samples: int = 1

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
            raise ValueError(
                f"{name}.query: times must be (B, P) = {tuple(points.shape[:2])}, got {tuple(times.shape)}"
            )
        if not self.temporal and times.numel() and bool((times != 0).any()):
            lo, hi = float(times.min()), float(times.max())
            raise ValueError(
                f"{name} is not temporal: it answers queries at t = 0 (the current frame) only, got times in [{lo:g}, {hi:g}] s"
            )

    def occupancy_logits(self, scene: Scene, grid: GridSpec, chunk_size: int = DEFAULT_QUERY_CHUNK) -> Tensor:
        """``(B, K, X, Y, Z)`` logits at the centres of ``grid``'s voxels (the evaluation grid).

        The default queries the centres at ``t = 0`` (or :attr:`voxel_samples` ``> 1`` sub-cell centres per voxel
        axis, the voxel taking the answer with the largest occupancy logit), ``chunk_size`` points at a time, and
        writes each
        chunk's :meth:`QueryResult.logits` (``free``'s logit from the occupancy logit and
        :attr:`occupancy_threshold` where the head returns one) into the output, so the memory beyond
        the output is bounded by the chunk, not the grid. ``argmax`` over ``K`` gives the class ids (:meth:`OccModel.predict_occupancy`).

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
        s = int(self.voxel_samples)
        sub = _sub_offsets(grid, s).to(device)  # (S, 3) metres from the voxel centre, S = s^3
        chunk_size = max(1, chunk_size // len(sub))
        out: Tensor | None = None
        for start in range(0, n, chunk_size):
            flat = torch.arange(start, min(start + chunk_size, n), device=device)
            index = torch.stack((flat // (ny * nz), flat // nz % ny, flat % nz), dim=-1)
            centres = grid.index_to_coord(index).to(device)  # (p, 3)
            points = (centres[:, None] + sub).reshape(-1, 3).unsqueeze(0).expand(b, -1, -1)  # (B, p * S, 3)
            result = self.query(scene, points)
            logits = result.logits(self.free_label, self.occupancy_threshold)  # (B, p * S, K)
            if len(sub) > 1:
                if result.occupancy_logit is None:
                    raise ValueError(f"{type(self).__name__}: voxel_samples > 1 needs a query occupancy logit")
                most = result.occupancy_logit.view(b, len(flat), len(sub)).argmax(-1)  # (B, p)
                logits = logits.view(b, len(flat), len(sub), -1)
                logits = logits.gather(2, most[..., None, None].expand(-1, -1, 1, logits.shape[-1])).squeeze(2)
            if out is None:
                out = logits.new_empty(b, logits.shape[-1], n)
            out[:, :, start : start + len(flat)] = logits.transpose(1, 2)
        assert out is not None  # a grid has at least one voxel
        return out.view(b, -1, nx, ny, nz)


def _sub_offsets(grid: GridSpec, samples: int) -> Tensor:
    """``(samples^3, 3)`` offsets (metres) from a voxel's centre to the centres of its ``samples^3`` equal sub-cells."""
    if samples < 1:
        raise ValueError(f"voxel_samples must be >= 1, got {samples}")
    steps = (torch.arange(samples, dtype=torch.float32) + 0.5) / samples - 0.5  # (s,) in (-0.5, 0.5)
    size = torch.tensor(grid.voxel_size, dtype=torch.float32)
    ox, oy, oz = torch.meshgrid(steps * size[0], steps * size[1], steps * size[2], indexing="ij")
    return torch.stack([ox, oy, oz], -1).reshape(-1, 3)
