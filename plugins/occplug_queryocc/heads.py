"""Head ``queryocc_decoder``: QueryOcc's unified query decoder, answering at any 4D point ``(x, y, z, t)``.

Per query (QueryOcc §3.3): contract ``(x, y)`` into the scene grid's coordinates (the grid's own
:meth:`~occplug.geometry.GridSpec.normalize`, so a contracted plane is read where the splat put the
point), encode ``(x, y, z, t)`` with a small MLP, read the scene there (:meth:`Scene.sample`: bilinear on a
BEV plane, trilinear on dense voxels), predict ``K`` offsets in the grid's (contracted) x-y coordinates
and read the scene at those neighbours too (a softmax-weighted sum), then refine with shallow
residual MLP blocks. Shared parameters predict the occupancy logit ``o``, the class logits ``s`` and,
with ``feature_dim > 0``, a foundation-model feature ``v``. Any scene with a grid works: QueryOcc's
BEV plane, or the core's dense voxels (so query supervision mixes with the baseline's scene).
"""

from __future__ import annotations

from typing import Annotated

import torch
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from occplug.constraints import NonNegative, Positive, Range
from occplug.data import Batch
from occplug.interfaces import OccupancyHead, QueryResult, Scene

__all__ = ["QueryDecoder"]

#: a probability strictly between 0 and 1
OpenUnit = Range(low=0, high=1, low_open=True, high_open=True)


class _Residual(nn.Module):
    """``h + Linear(ReLU(Linear(LayerNorm(h))))``."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.LayerNorm(width), nn.Linear(width, width), nn.ReLU(inplace=True), nn.Linear(width, width)
        )

    def forward(self, h: Tensor) -> Tensor:
        return h + self.net(h)


class QueryDecoder(OccupancyHead):
    """Unified query decoder over a BEV scene (queryable, temporal).

    Args:
        in_channels: ``C`` of the scene plane; num_classes: ``K`` (``free`` included; its column is
            never trained -- ``free`` comes from the occupancy logit); free_label: the data set's.
        hidden: width of the query features.
        offsets: neighbour samples per query (0: none); offset_range: how far they may reach, in plane cells.
        num_blocks: residual refinement blocks.
        feature_dim: size of the distilled feature ``v`` (0: none).
        time_scale: seconds that map to 1 in the query encoding (adjacent keyframes are 0.5 s apart).
        occupancy_threshold: ``sigmoid(o)`` below which a point is predicted ``free`` (default 0.5).
        voxel_samples: points per axis at which each evaluation voxel is queried (1, the paper's: its centre;
            ``s > 1``: the most occupied of its ``s^3`` sub-cell centres; the core's
            :attr:`~occplug.interfaces.OccupancyHead.voxel_samples`). Evaluation only: training is unchanged.
        checkpoint_queries: with gradients on, decode the queries in chunks of this many per sample and keep
            none of a chunk's activations for the backward pass (``torch.utils.checkpoint``: each chunk's forward
            runs again in the backward). The values and gradients are those of one pass (tested); the memory of
            the decoder's activations stops growing with the query count (at the paper's 800k queries per sample
            they are about 10 GB). 0: off.

    Forward returns ``{"logits": (B, K, X, Y, Z)}`` at the centres of the scene's own grid's cells (a BEV
    grid has few z cells: this is cheap); the model evaluates through :meth:`occupancy_logits` at the
    evaluation grid's voxel centres (the core's chunked query).
    """

    queryable = True
    temporal = True

    def __init__(
        self,
        in_channels: int,
        num_classes: Annotated[int, Positive],
        free_label: int | None = 17,
        hidden: Annotated[int, Positive] = 64,
        offsets: Annotated[int, NonNegative] = 4,
        offset_range: Annotated[float, Positive] = 2.0,
        num_blocks: Annotated[int, NonNegative] = 2,
        feature_dim: Annotated[int, NonNegative] = 0,
        time_scale: Annotated[float, Positive] = 0.5,
        occupancy_threshold: Annotated[float, OpenUnit] = 0.5,
        voxel_samples: Annotated[int, Positive] = 1,
        checkpoint_queries: Annotated[int, NonNegative] = 0,
    ) -> None:
        super().__init__()
        if not 0.0 < occupancy_threshold < 1.0:
            raise ValueError(f"queryocc_decoder occupancy_threshold must lie in (0, 1), got {occupancy_threshold}")
        self.num_classes, self.free_label = int(num_classes), free_label
        self.occupancy_threshold = float(occupancy_threshold)
        self.voxel_samples = int(voxel_samples)
        self.checkpoint_queries = int(checkpoint_queries)
        self.num_offsets, self.offset_range, self.time_scale = int(offsets), float(offset_range), float(time_scale)
        self.encode_query = nn.Sequential(nn.Linear(4, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, hidden))
        self.read = nn.Linear(in_channels, hidden)
        if self.num_offsets:
            self.offset = nn.Linear(hidden, self.num_offsets * 2)
            self.offset_weight = nn.Linear(hidden, self.num_offsets)
            self.read_neighbours = nn.Linear(in_channels, hidden)
        self.blocks = nn.Sequential(*(_Residual(hidden) for _ in range(num_blocks)))
        self.occupancy = nn.Linear(hidden, 1)
        self.classes = nn.Linear(hidden, self.num_classes)
        self.features = nn.Linear(hidden, feature_dim) if feature_dim else None

    def forward(self, scene: Scene, batch: Batch) -> dict[str, Tensor]:
        """``{"logits"}`` at the scene grid's cell centres (a model whose scene lies on the evaluation grid is evaluated
        from them; in training they cost a query per scene cell, which the conformance contract's gradient check reads)."""
        return {"logits": self.occupancy_logits(scene, scene.grid)}

    def query(self, scene: Scene, points: Tensor, times: Tensor | None = None) -> QueryResult:
        """Occupancy logit ``(B, P)``, class logits ``(B, P, K)`` (and features ``(B, P, F)``) at ``(B, P, 3)``
        ego-frame points of the current frame, at ``(B, P)`` seconds relative to it."""
        self.check_query(points, times)
        chunk = self.checkpoint_queries
        if chunk and torch.is_grad_enabled() and points.shape[1] > chunk:
            parts = [
                checkpoint(self._decode, scene, points[:, i : i + chunk], None if times is None else times[:, i : i + chunk],
                           use_reentrant=False)
                for i in range(0, points.shape[1], chunk)
            ]  # fmt: skip
            return QueryResult(
                class_logits=torch.cat([r.class_logits for r in parts], 1),
                occupancy_logit=torch.cat([r.occupancy_logit for r in parts], 1),
                features=None if self.features is None else torch.cat([r.features for r in parts], 1),
            )
        return self._decode(scene, points, times)

    def _decode(self, scene: Scene, points: Tensor, times: Tensor | None) -> QueryResult:
        """:meth:`query` in one pass."""
        b, p = points.shape[:2]
        grid = scene.grid
        norm = grid.normalize(points.float())  # (B, P, 3) in [-1, 1] (x, y contracted on a contracted grid)
        t = torch.zeros_like(norm[..., :1]) if times is None else (times.to(norm.dtype) / self.time_scale).unsqueeze(-1)
        h = self.encode_query(torch.cat([norm, t], -1)) + self.read(scene.sample(points))
        if self.num_offsets:
            k = self.num_offsets
            cells = torch.tensor([2.0 / n for n in grid.shape[:2]], dtype=norm.dtype, device=norm.device)
            delta = torch.tanh(self.offset(h)).view(b, p, k, 2) * (self.offset_range * cells)
            moved = torch.cat(
                [(norm[..., None, :2] + delta).clamp(-1 + 1e-4, 1 - 1e-4), norm[..., None, 2:].expand(b, p, k, 1)], -1
            )
            neighbours = scene.sample(grid.denormalize(moved).view(b, p * k, 3)).view(b, p, k, -1)
            weights = self.offset_weight(h).softmax(-1).unsqueeze(-1)  # (B, P, K, 1)
            h = h + self.read_neighbours((neighbours * weights).sum(2))
        h = self.blocks(h)
        return QueryResult(
            class_logits=self.classes(h),
            occupancy_logit=self.occupancy(h).squeeze(-1),
            features=None if self.features is None else self.features(h),
        )
