"""DuOcc's lightweight 3D-FPN (paper §3.1, suppl. A.1): ``V_init`` on the lifted grid -> ``V_curr`` at half size.

Three residual 3D stages (strides 1, 2, 2 after one another, so the levels lie at ``X x Y x Z``, ``X/2`` and
``X/4``), every level resampled trilinearly to the output size, concatenated, and compressed by a
``1x1x1 conv -> BatchNorm -> ReLU`` to ``C`` channels (the public code's ``CustomResNet3D`` +
``LSSFPN3D_small`` in ``projects/configs/DuOcc.py``, with fewer channels and blocks for a CPU).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occplug.constraints import Length, Positive
from occplug.nn import BasicBlock3d, ConvNormAct3d

__all__ = ["VoxelFPN3D"]


class VoxelFPN3D(nn.Module):
    """Multi-level 3D residual encoder fused at one output size.

    Args:
        in_channels: ``C_init`` of ``V_init``.
        out_channels: ``C`` of ``V_curr``.
        stage_channels: widths of the three stages (the code: 64, 128, 128).
        stage_blocks: residual blocks per stage (the code: 1, 2, 2); the first block of stages 2 and 3 has stride 2.

    Forward: ``V_init (B, C_init, X, Y, Z)`` and ``size = (x, y, z)`` -> ``V_curr (B, C, x, y, z)``, same frame
    (the ego frame of the frame it was lifted from).
    """

    def __init__(
        self,
        in_channels: Annotated[int, Positive],
        out_channels: Annotated[int, Positive],
        stage_channels: Annotated[Sequence[Annotated[int, Positive]], Length(exact=3)] = (16, 32, 32),
        stage_blocks: Annotated[Sequence[Annotated[int, Positive]], Length(exact=3)] = (1, 1, 1),
    ) -> None:
        super().__init__()
        if len(stage_channels) != 3 or len(stage_blocks) != 3 or min(stage_blocks) < 1:
            raise ValueError(
                f"VoxelFPN3D needs 3 stage widths and 3 block counts >= 1, got {list(stage_channels)}, "
                f"{list(stage_blocks)}"
            )
        stages = []
        c_in = in_channels
        for i, (c, n) in enumerate(zip(stage_channels, stage_blocks, strict=True)):
            blocks = [BasicBlock3d(c_in, int(c), stride=1 if i == 0 else 2)]
            blocks += [BasicBlock3d(int(c), int(c)) for _ in range(int(n) - 1)]
            stages.append(nn.Sequential(*blocks))
            c_in = int(c)
        self.stages = nn.ModuleList(stages)
        self.compress = ConvNormAct3d(sum(int(c) for c in stage_channels), out_channels, 1)
        self.out_channels = int(out_channels)

    def forward(self, volume: Tensor, size: tuple[int, int, int]) -> Tensor:
        """``(B, C_init, X, Y, Z)`` -> ``(B, C, *size)``; see the class docstring."""
        levels = []
        x = volume
        for stage in self.stages:
            x = stage(x)
            levels.append(x if tuple(x.shape[2:]) == tuple(size) else F.interpolate(x, size=size, mode="trilinear"))
        return self.compress(torch.cat(levels, dim=1))
