"""Scene ``queryocc_bev``: QueryOcc's BEV processing -- residual blocks, deformable attention, dynamic convolution.

All three work on the plane's cells whatever the grid (metric or contracted): on a contracted plane a
cell in the border band stands for a longer stretch of road, and the layers do not need to know. The residual
blocks and the deformable attention are the core's (:mod:`occplug.nn`); the dynamic convolution is QueryOcc's.
"""

from __future__ import annotations

from typing import Annotated

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occplug.constraints import NonNegative, Positive
from occplug.data import Batch
from occplug.geometry import GridSpec
from occplug.interfaces import BevScene, Lifted, SceneRepresentation
from occplug.nn import BasicBlock2d, ConvNormAct2d, DeformableAttention

__all__ = ["DynamicConv2d", "QueryOccBev"]


class DynamicConv2d(nn.Module):
    """Dynamic convolution (Chen et al., CVPR 2020): a per-sample 3x3 kernel mixed from ``K`` experts.

    Attention over the experts comes from the globally pooled input (``softmax(MLP(GAP(x)) / T)``);
    the mixed kernel runs as one grouped convolution over the batch. Norm, ReLU and a residual follow.

    Forward: ``(B, C, H, W)`` -> ``(B, C, H, W)``.
    """

    def __init__(self, channels: int, experts: int = 4, reduction: int = 4, temperature: float = 30.0) -> None:
        super().__init__()
        self.experts, self.temperature = experts, temperature
        self.kernels = nn.Parameter(torch.empty(experts, channels, channels, 3, 3))
        for i in range(experts):
            nn.init.kaiming_uniform_(self.kernels.data[i], a=5**0.5)
        hidden = max(4, channels // reduction)
        self.attention = nn.Sequential(nn.Linear(channels, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, experts))
        self.norm = nn.BatchNorm2d(channels)

    def forward(self, x: Tensor) -> Tensor:
        b, c, h, w = x.shape
        pi = (self.attention(x.mean(dim=(2, 3))) / self.temperature).softmax(-1)  # (B, K)
        kernel = torch.einsum("bk,koihw->boihw", pi, self.kernels).reshape(b * c, c, 3, 3)
        out = F.conv2d(x.reshape(1, b * c, h, w), kernel, padding=1, groups=b).view(b, c, h, w)
        return F.relu(x + self.norm(out))


class QueryOccBev(SceneRepresentation):
    """QueryOcc's BEV encoder: ``3x3 conv`` to ``out_channels``, residual blocks, deformable attention, dynamic conv.

    Args:
        in_channels: ``C_in`` of the lifted plane; out_channels: ``C`` of the scene.
        num_blocks: 2D residual blocks (>= 0).
        deformable: add the deformable attention layer; heads, points: its heads and samples per head.
        dynamic: add the dynamic convolution layer; experts: its kernels.

    Forward:
        a :class:`Lifted` with a BEV ``volume`` ``(B, C_in, X, Y)`` -> :class:`BevScene` ``(B, C, X, Y)`` on
        the lifted grid. A 3D volume is a ``ValueError`` (use a BEV view transform such as ``queryocc_lift_contract_splat``).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: Annotated[int, Positive] = 64,
        num_blocks: Annotated[int, NonNegative] = 2,
        deformable: bool = True,
        heads: Annotated[int, Positive] = 4,
        points: Annotated[int, Positive] = 4,
        dynamic: bool = True,
        experts: Annotated[int, Positive] = 4,
    ) -> None:
        super().__init__()
        self.out_channels = int(out_channels)
        c = self.out_channels
        layers: list[nn.Module] = [ConvNormAct2d(in_channels, c)]
        layers += [BasicBlock2d(c, c) for _ in range(num_blocks)]
        if deformable:
            # QueryOcc's offsets list the plane's last axis (Y) first, as grid_sample does: kept for its checkpoints
            layers.append(DeformableAttention(c, heads, points, dims=2, offset_order="grid_sample"))
        if dynamic:
            layers.append(DynamicConv2d(c, experts))
        self.layers = nn.Sequential(*layers)

    def forward(self, lifted: Lifted, batch: Batch) -> BevScene:
        """Process the plane (stateless: ``batch`` is unused)."""
        plane = lifted.volume
        if plane.dim() != 4:
            raise ValueError(
                f"queryocc_bev needs a BEV plane (B, C, X, Y) but got a volume {tuple(plane.shape)}; "
                f"use a BEV view transform such as queryocc_lift_contract_splat"
            )
        return BevScene(self.layers(plane), lifted.grid)

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple:
        """A random BEV plane on ``grid``'s x-y cells."""
        gen = torch.Generator().manual_seed(0)
        plane = torch.randn(len(batch), channels, *grid.shape[:2], generator=gen)
        return (Lifted(volume=plane, grid=grid), batch)
