"""Small dense UNets on 2D maps ``(B, C, H, W)`` and 3D grids ``(B, C, X, Y, Z)``, with a 1x1 per-cell header.

Each level is a ResNet basic block (:class:`~occplug.nn.BasicBlock2d` / ``BasicBlock3d``); downsampling is a 2x
max-pool (as the original UNet, Ronneberger et al.) and upsampling a nearest resize to the skip's size followed by a
block on the concatenation. Small enough for CPU tests.

Downsampling is anisotropic (:func:`halving_stride`): at every level an axis is halved only while it keeps at least
``min_size`` cells (length ``>= 2 * min_size``), otherwise it keeps stride 1. So a flat driving grid such as
``(64, 64, 8)`` shrinks in x and y for longer than in z, and odd lengths are fine (pooling rounds up, upsampling
restores the skip's exact size).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .layers import BasicBlock2d, BasicBlock3d

__all__ = ["UNet2d", "UNet3d", "halving_stride"]


def halving_stride(size: Sequence[int], min_size: int) -> tuple[int, ...]:
    """Per axis of a grid of ``size`` cells: 2 while the axis is at least ``2 * min_size`` long, else 1.

    The stride (or pooling kernel) of an anisotropic downsampling that halves an axis only while it keeps
    ``min_size`` cells, so a short axis (a driving grid's z) stops shrinking before the long ones.
    """
    return tuple(2 if s >= 2 * min_size else 1 for s in size)


class _UNet(nn.Module):
    """Shared body of :class:`UNet2d` and :class:`UNet3d`; ``dims`` is 2 or 3."""

    def __init__(
        self, in_channels: int, num_classes: int, base_channels: int, depth: int, min_size: int, norm: str, dims: int
    ) -> None:
        super().__init__()
        if in_channels < 1 or num_classes < 1 or base_channels < 1:
            raise ValueError(
                f"UNet: in_channels, num_classes and base_channels must be >= 1, got {in_channels}, {num_classes}, "
                f"{base_channels}"
            )
        if depth < 0 or min_size < 1:
            raise ValueError(f"UNet: depth must be >= 0 and min_size >= 1, got {depth} and {min_size}")
        block = BasicBlock2d if dims == 2 else BasicBlock3d
        widths = [base_channels * 2**i for i in range(depth + 1)]
        self.dims = dims
        self.min_size = min_size
        self.out_channels = base_channels
        self.stem = block(in_channels, widths[0], norm=norm)
        self.down = nn.ModuleList([block(widths[i], widths[i + 1], norm=norm) for i in range(depth)])
        self.up = nn.ModuleList(
            [block(widths[i + 1] + widths[i], widths[i], norm=norm) for i in reversed(range(depth))]
        )
        conv = nn.Conv2d if dims == 2 else nn.Conv3d
        self.head = conv(widths[0], num_classes, 1)

    def _pool(self, x: Tensor) -> Tensor:
        kernel = halving_stride(x.shape[2:], self.min_size)
        if all(k == 1 for k in kernel):
            return x
        pool = F.max_pool2d if self.dims == 2 else F.max_pool3d
        return pool(x, kernel_size=kernel, stride=kernel, ceil_mode=True)

    def features(self, x: Tensor) -> Tensor:
        """The last decoder level's features, ``(B, base_channels, *spatial)`` at the input resolution."""
        if x.dim() != self.dims + 2:
            raise ValueError(f"UNet{self.dims}d expects a {self.dims + 2}-D input, got shape {tuple(x.shape)}")
        x = self.stem(x)
        skips = []
        for down in self.down:
            skips.append(x)
            x = down(self._pool(x))
        for up, skip in zip(self.up, reversed(skips), strict=True):
            x = F.interpolate(x, size=skip.shape[2:], mode="nearest")
            x = up(torch.cat([x, skip], dim=1))
        return x

    def forward(self, x: Tensor) -> Tensor:
        """Per-cell class logits, ``(B, num_classes, *spatial)``."""
        return self.head(self.features(x))


class UNet2d(_UNet):
    """2D UNet with a 1x1 segmentation header: images or feature maps -> per-pixel logits.

    Args:
        in_channels: input channels (3 for RGB).
        num_classes: ``K`` output channels (classes).
        base_channels: width of the first level; level ``i`` has ``base_channels * 2**i``.
        depth: number of 2x downsamplings (0: no downsampling).
        min_size: an axis is halved only while it keeps at least this many cells.
        norm: ``"group"`` (default: independent of the batch size, so safe for batches of one) or ``"batch"``.

    Forward: ``(B, in_channels, H, W)`` -> ``(B, num_classes, H, W)`` logits, any ``H``, ``W``.
    :meth:`features` gives the ``(B, base_channels, H, W)`` feature map under the header.
    """

    def __init__(
        self,
        in_channels: int = 3,
        num_classes: int = 20,
        base_channels: int = 16,
        depth: int = 3,
        min_size: int = 2,
        norm: str = "group",
    ) -> None:
        super().__init__(in_channels, num_classes, base_channels, depth, min_size, norm, dims=2)


class UNet3d(_UNet):
    """Dense 3D UNet with a 1x1x1 header: voxel features -> per-voxel logits.

    Args:
        in_channels: ``C`` of the input grid.
        num_classes: ``K`` classes.
        base_channels: width of the first level; level ``i`` has ``base_channels * 2**i``.
        depth: number of downsampling levels; an axis shorter than ``2 * min_size`` keeps stride 1.
        min_size: an axis is halved only while it keeps at least this many cells.
        norm: ``"group"`` (default, batch-size independent) or ``"batch"``.

    Forward: ``(B, in_channels, X, Y, Z)`` -> ``(B, num_classes, X, Y, Z)`` logits, any ``X, Y, Z`` (e.g.
    ``(64, 64, 8)`` or ``(32, 32, 4)``). :meth:`features` gives ``(B, base_channels, X, Y, Z)``.
    """

    def __init__(
        self,
        in_channels: int,
        num_classes: int = 20,
        base_channels: int = 8,
        depth: int = 3,
        min_size: int = 2,
        norm: str = "group",
    ) -> None:
        super().__init__(in_channels, num_classes, base_channels, depth, min_size, norm, dims=3)
