"""Small building blocks shared by the built-in components (plain PyTorch, CPU-friendly)."""

from __future__ import annotations

import math
from typing import Literal

from torch import Tensor, nn

from occplug.constraints import check_choices

__all__ = ["BasicBlock2d", "BasicBlock3d", "ConvNormAct2d", "ConvNormAct3d", "PixelNet", "norm_layer"]


def norm_layer(kind: str, channels: int, dims: int = 2) -> nn.Module:
    """A normalisation layer for ``channels`` feature maps.

    Args:
        kind: ``"batch"`` (BatchNorm) or ``"group"`` (GroupNorm with up to 8 groups, a divisor
            of ``channels``; independent of the batch size, so safe for batches of one).
        channels: number of channels.
        dims: 2 for images ``(B, C, H, W)``, 3 for volumes ``(B, C, X, Y, Z)``.
    """
    if kind == "batch":
        return nn.BatchNorm2d(channels) if dims == 2 else nn.BatchNorm3d(channels)
    if kind == "group":
        return nn.GroupNorm(math.gcd(8, channels), channels)
    raise ValueError(f"norm must be 'batch' or 'group', got {kind!r}")


class _ConvNormAct(nn.Sequential):
    """``conv (no bias) -> norm -> activation`` in 2D or 3D; its parameters are ``0.*`` (conv) and ``1.*`` (norm)."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel: int,
        stride: int,
        norm: str,
        act: Literal["relu", "silu"],
        dims: int,
    ) -> None:
        check_choices(_ConvNormAct.__init__, "_ConvNormAct", act=act)
        conv = nn.Conv2d if dims == 2 else nn.Conv3d
        super().__init__(
            conv(in_channels, out_channels, kernel, stride=stride, padding=kernel // 2, bias=False),
            norm_layer(norm, out_channels, dims),
            nn.ReLU(inplace=True) if act == "relu" else nn.SiLU(),
        )


class ConvNormAct2d(_ConvNormAct):
    """``Conv2d (no bias) -> norm -> ReLU`` (or SiLU) on ``(B, C, H, W)``; ``kernel`` odd, "same" padding, optional stride.

    Args:
        in_channels, out_channels: channels; kernel: odd kernel size; stride: of the convolution;
        norm: ``"batch"`` or ``"group"`` (:func:`norm_layer`); act: ``"relu"`` or ``"silu"``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel: int = 3,
        stride: int = 1,
        norm: str = "batch",
        act: str = "relu",
    ) -> None:
        super().__init__(in_channels, out_channels, kernel, stride, norm, act, dims=2)


class ConvNormAct3d(_ConvNormAct):
    """``Conv3d (no bias) -> norm -> ReLU`` (or SiLU) on ``(B, C, X, Y, Z)``; arguments as :class:`ConvNormAct2d`."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel: int = 3,
        stride: int = 1,
        norm: str = "batch",
        act: str = "relu",
    ) -> None:
        super().__init__(in_channels, out_channels, kernel, stride, norm, act, dims=3)


class _BasicBlock(nn.Module):
    """ResNet basic block: two 3x3(x3) convs with a residual connection (projected when the shape changes)."""

    def __init__(self, in_channels: int, out_channels: int, stride: int, norm: str, dims: int) -> None:
        super().__init__()
        conv = nn.Conv2d if dims == 2 else nn.Conv3d
        self.conv1 = conv(in_channels, out_channels, 3, stride=stride, padding=1, bias=False)
        self.norm1 = norm_layer(norm, out_channels, dims)
        self.conv2 = conv(out_channels, out_channels, 3, padding=1, bias=False)
        self.norm2 = norm_layer(norm, out_channels, dims)
        self.relu = nn.ReLU(inplace=True)
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or in_channels != out_channels:
            self.shortcut = nn.Sequential(
                conv(in_channels, out_channels, 1, stride=stride, bias=False), norm_layer(norm, out_channels, dims)
            )

    def forward(self, x: Tensor) -> Tensor:
        out = self.relu(self.norm1(self.conv1(x)))
        out = self.norm2(self.conv2(out))
        return self.relu(out + self.shortcut(x))


class BasicBlock2d(_BasicBlock):
    """2D ResNet basic block on ``(B, C, H, W)``; ``stride`` 2 halves ``H`` and ``W`` (rounding up)."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1, norm: str = "batch") -> None:
        super().__init__(in_channels, out_channels, stride, norm, dims=2)


class BasicBlock3d(_BasicBlock):
    """3D ResNet basic block on ``(B, C, X, Y, Z)``, shape-preserving when ``stride`` is 1."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1, norm: str = "batch") -> None:
        super().__init__(in_channels, out_channels, stride, norm, dims=3)


class PixelNet(nn.Sequential):
    """Per-feature-cell image head of the view transforms: ``3x3 conv -> norm -> ReLU -> 1x1 conv``.

    Maps ``(B*N, in_channels, h, w)`` to ``(B*N, out_channels, h, w)`` (same resolution).
    With ``hidden == 0`` it is a single 1x1 convolution.
    """

    def __init__(self, in_channels: int, hidden: int, out_channels: int) -> None:
        if hidden < 0:
            raise ValueError(f"hidden must be >= 0, got {hidden}")
        layers: list[nn.Module] = []
        if hidden > 0:
            layers.append(ConvNormAct2d(in_channels, hidden, 3))
            in_channels = hidden
        layers.append(nn.Conv2d(in_channels, out_channels, 1))
        super().__init__(*layers)
