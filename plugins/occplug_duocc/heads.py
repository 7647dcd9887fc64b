"""DuOcc's occupancy decoder (paper §3.3, suppl. A.3): a 3D deconvolution to the label grid, then a per-voxel MLP."""

from __future__ import annotations

from typing import Annotated, Any

import torch
from torch import Tensor, nn

from occplug.constraints import Positive
from occplug.data import Batch
from occplug.geometry import GridSpec, sample_volume
from occplug.interfaces import DEFAULT_QUERY_CHUNK, DenseVoxelScene, OccupancyHead, QueryResult, Scene

__all__ = ["DuOccDecoder"]


class DuOccDecoder(OccupancyHead):
    """``V_up = ReLU(BN(ConvTranspose3d(V_fin)))`` on the label grid, then ``Linear -> ReLU -> Linear`` per voxel.

    The public code's main head: ``ConvTranspose3d(C -> hidden, k = s, stride = s)``, BN, ReLU, then pointwise
    ``hidden -> mlp_hidden`` (ReLU) ``-> K`` (inside its DQA; the paper's "MLP" are these pointwise
    convolutions). Queryable: a point reads ``V_up`` trilinearly and goes through the same MLP, so queries at
    label-voxel centres equal the voxel logits (and any query supervision can train it). Not temporal.

    Both the output grid and the upsampling factor come from the run, once: the label grid is the run's ``grid``
    (the run context's, ego frame) and ``s`` is the scene's declared ``downsample`` (the model gives it as
    ``scene_downsample``), so they cannot disagree with the scene's own setting.

    Args:
        in_channels: ``C`` of ``V_fin``.
        grid: the label grid ``(X, Y, Z)`` ``V_up`` lies on (the run's; given by the model).
        scene_downsample: the upsampling factor ``s``, the scene's ``downsample`` (given by the model; DuOcc: 2;
            1: a 1x1x1 conv instead).
        num_classes: ``K`` (free included; given by the model).
        hidden: channels of ``V_up`` (code: 64).
        mlp_hidden: hidden width of the per-voxel MLP (code: 256).

    Forward: a scene with ``features`` ``V_fin`` ``(B, C, x, y, z)`` -> ``{"logits": (B, K, X, Y, Z)}`` on the
    label grid.
    """

    queryable = True
    temporal = False
    #: besides a head's given arguments, the scene's declared downsampling of the run grid
    given = (*OccupancyHead.given, "scene_downsample")

    def __init__(
        self,
        in_channels: int,
        grid: GridSpec,
        scene_downsample: int,
        num_classes: Annotated[int, Positive],
        hidden: Annotated[int, Positive] = 32,
        mlp_hidden: Annotated[int, Positive] = 64,
    ) -> None:
        super().__init__()
        if scene_downsample not in (1, 2):
            raise ValueError(
                f"duocc_decoder: the scene downsamples the grid by {scene_downsample}; the decoder upsamples by 1 or 2"
            )
        self.grid = grid
        self.num_classes = int(num_classes)
        self.scale = int(scene_downsample)
        up = (
            nn.ConvTranspose3d(in_channels, hidden, self.scale, stride=self.scale, bias=False)
            if self.scale > 1
            else nn.Conv3d(in_channels, hidden, 1, bias=False)
        )
        self.up = nn.Sequential(up, nn.BatchNorm3d(hidden), nn.ReLU(inplace=True))
        self.mlp = nn.Sequential(
            nn.Linear(hidden, mlp_hidden), nn.ReLU(inplace=True), nn.Linear(mlp_hidden, self.num_classes)
        )

    def label_grid(self, scene: Scene) -> GridSpec:
        """The grid ``V_up`` lies on (ego frame): the run's grid, whatever the scene."""
        return self.grid

    def upsampled(self, scene: Scene) -> Tensor:
        """``V_up`` ``(B, hidden, X, Y, Z)`` on :meth:`label_grid`, memoised in the scene's ``cache`` when it has one."""
        cache: dict[Any, Tensor] | None = getattr(scene, "cache", None)
        key = (id(self), self.training, torch.is_grad_enabled())
        if cache is not None and key in cache:
            return cache[key]
        up = self.up(scene.features)
        grid = self.label_grid(scene)
        if tuple(up.shape[2:]) != grid.shape:
            raise ValueError(
                f"duocc_decoder: upsampling by the scene's downsample {self.scale} turns its "
                f"{tuple(scene.features.shape[2:])} voxels into {tuple(up.shape[2:])}, not the label grid {grid.shape}"
            )
        if cache is not None:
            cache[key] = up
        return up

    def forward(self, scene: Scene, batch: Batch) -> dict[str, Tensor]:
        """``{"logits": (B, K, X, Y, Z)}`` on the label grid."""
        return {"logits": self.occupancy_logits(scene, self.label_grid(scene))}

    def occupancy_logits(self, scene: Scene, grid: GridSpec, chunk_size: int = DEFAULT_QUERY_CHUNK) -> Tensor:
        """``(B, K, X, Y, Z)`` logits at ``grid``'s voxel centres: the dense path on the label grid, else queries."""
        if grid == self.label_grid(scene):
            return self.mlp(self.upsampled(scene).movedim(1, -1)).movedim(-1, 1)
        return super().occupancy_logits(scene, grid, chunk_size)

    def query(self, scene: Scene, points: Tensor, times: Tensor | None = None) -> QueryResult:
        """Class logits ``(B, P, K)`` at ``(B, P, 3)`` ego-frame points (``V_up`` read trilinearly; ``times``: 0 only)."""
        self.check_query(points, times)
        features = sample_volume(self.upsampled(scene), self.label_grid(scene), points)
        return QueryResult(class_logits=self.mlp(features))

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple[Any, ...]:
        """A random ``V_fin`` on ``grid`` at twice its voxel size (the label grid is ``grid``), and the batch."""
        coarse = GridSpec(grid.range, tuple(2 * v for v in grid.voxel_size))
        gen = torch.Generator().manual_seed(0)
        volume = torch.randn(len(batch), channels, *coarse.shape, generator=gen)
        return (DenseVoxelScene(volume, coarse), batch)
