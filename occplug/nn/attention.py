"""Attention blocks on dense 2D maps ``(B, C, H, W)`` and 3D grids ``(B, C, X, Y, Z)``: deformable attention and CBAM.

Both work on the cells of whatever grid they are given (an image feature map, a BEV plane, a voxel grid in the ego
frame): offsets and kernels are in cells, never in metres, so the blocks need no geometry.

* Deformable attention (Deformable DETR's single-scale sampling, pure PyTorch): :func:`deformable_sample` reads a
  value map at ``K`` learned offsets around every cell and sums them with weights; :class:`DeformableAttention`
  is the self-attention layer built on it (every cell a query at its own centre).
* CBAM (Woo et al., ECCV 2018): channel attention ``M_c`` from pooled descriptors, then spatial attention ``M_s``
  from channel-pooled maps; :class:`ChannelAttention`, :class:`SpatialAttention2d` / :class:`SpatialAttention3d`,
  the function :func:`cbam` that chains them (also for a module that keeps them as its own attributes) and the
  module :class:`CBAM`.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occplug.constraints import check_choices

__all__ = [
    "CBAM",
    "ChannelAttention",
    "DeformableAttention",
    "SpatialAttention2d",
    "SpatialAttention3d",
    "cbam",
    "deformable_sample",
    "spread_directions",
]


# ---------------------------------------------------------------------------------------------- deformable attention


def deformable_sample(value: Tensor, offsets: Tensor, weights: Tensor) -> Tensor:
    """Deformable sampling of a 2D map or 3D grid: each cell reads ``K`` (bi/tri)linear samples near itself and sums.

    Cell ``i``'s reference point is its centre; sample ``n`` lies at that centre + ``offsets[..., n, :]`` cells
    along the grid's axes (so zero offsets read every cell's own value exactly, and integer offsets read the
    neighbouring cells' values). Samples outside the grid read zero.

    Args:
        value: ``(B, M, D, *S)``: ``M`` heads of ``D`` channels on a grid of ``S = (H, W)`` or ``(X, Y, Z)`` cells.
        offsets: ``(B, M, K, len(S), *S)``: per head and sample, the offset in cells along each axis of ``S``,
            in axis order (``(dh, dw)`` or ``(dx, dy, dz)``).
        weights: ``(B, M, K, *S)``: per head and sample (e.g. a softmax over ``K``).

    Returns:
        ``(B, M * D, *S)``: ``sum_n weights[n] * value(centre + offsets[n])`` per head, heads concatenated.
    """
    b, m, d, *size = value.shape
    n, k = len(size), offsets.shape[2]
    if n not in (2, 3) or offsets.shape[3] != n:
        raise ValueError(
            f"deformable_sample: value {tuple(value.shape)} needs 2 or 3 grid axes and offsets with as many "
            f"components, got offsets {tuple(offsets.shape)}"
        )
    dev, dt = value.device, value.dtype
    axes = [(torch.arange(s, device=dev, dtype=dt) + 0.5) / s * 2 - 1 for s in size]
    ref = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)  # (*S, n) normalised, axis order
    scale = torch.tensor([2.0 / s for s in size], device=dev, dtype=dt)
    grid_axes = tuple(range(4, 4 + n))
    loc = ref.view(1, 1, 1, *size, n) + offsets.permute(0, 1, 2, *grid_axes, 3) * scale  # (B, M, K, *S, n)
    # grid_sample reads (N, C, *S) at coordinates ordered last axis first; the samples run along the output's
    # last axis (cell-major, then sample), which the CPU kernel vectorises over.
    cells = math.prod(size)
    loc = loc.flip(-1).permute(0, 1, *(a - 1 for a in grid_axes), 2, 3 + n)
    loc = loc.reshape(b * m, *([1] * (n - 1)), cells * k, n)
    sampled = F.grid_sample(
        value.reshape(b * m, d, *size), loc, mode="bilinear", padding_mode="zeros", align_corners=False
    ).view(b, m, d, *size, k)
    out = (sampled * weights.permute(0, 1, *(a - 1 for a in grid_axes), 2).unsqueeze(2)).sum(-1)
    return out.reshape(b, m * d, *size)


def spread_directions(n: int, dims: int) -> Tensor:
    """``(n, dims)`` float32 unit vectors spread evenly: a ring in 2D (angles ``2 pi i / n``), a Fibonacci sphere in 3D.

    :class:`DeformableAttention` starts its ``heads * points`` offsets on them (Deformable DETR starts on a ring),
    so the samples begin one cell away in distinct directions rather than all at the centre.
    """
    if dims == 2:
        angle = torch.arange(n, dtype=torch.float32) * (2 * torch.pi / n)
        return torch.stack([angle.cos(), angle.sin()], -1)
    if dims == 3:
        i = torch.arange(n, dtype=torch.float32) + 0.5
        z = 1 - 2 * i / n
        r = (1 - z * z).clamp_min(0).sqrt()
        phi = i * math.pi * (3 - math.sqrt(5))
        return torch.stack([r * phi.cos(), r * phi.sin(), z], dim=-1)
    raise ValueError(f"spread_directions: dims must be 2 or 3, got {dims}")


class DeformableAttention(nn.Module):
    """Single-scale deformable self-attention over a 2D map or a 3D grid (Deformable DETR's sampling, pure PyTorch).

    Every cell is a query at its own centre: per head it predicts ``K`` offsets (in cells, 1x1 convolution) and
    ``K`` softmax weights, reads the value map there (:func:`deformable_sample`) and sums; an output projection,
    a residual connection, BatchNorm and ReLU follow. The offset convolution starts at zero weight with its bias on
    :func:`spread_directions` (one cell away from the centre, in ``heads * points`` directions).

    Args:
        channels: ``C`` (divisible by ``heads``).
        heads: attention heads; points: ``K`` samples per head.
        dims: 2 for ``(B, C, H, W)`` maps, 3 for ``(B, C, X, Y, Z)`` grids.
        offset_order: the order of each offset's components in the offset convolution's output channels:
            ``"axes"``, the input's axis order (``(dh, dw)``, ``(dx, dy, dz)``); ``"grid_sample"``, last axis first
            (``grid_sample``'s, an image's ``(x, y)`` = (column, row)). Fixed by a trained model's weights.

    Forward: ``(B, C, *S)`` -> ``(B, C, *S)``.
    """

    def __init__(
        self,
        channels: int,
        heads: int = 4,
        points: int = 4,
        dims: int = 2,
        offset_order: Literal["axes", "grid_sample"] = "axes",
    ) -> None:
        super().__init__()
        if dims not in (2, 3):
            raise ValueError(f"deformable attention: dims must be 2 or 3, got {dims}")
        check_choices(DeformableAttention.__init__, "deformable attention:", offset_order=offset_order)
        if channels % heads:
            raise ValueError(f"{dims}D deformable attention: channels {channels} not divisible by heads {heads}")
        self.heads, self.points, self.dims = int(heads), int(points), int(dims)
        self.offset_order = offset_order
        conv = nn.Conv2d if dims == 2 else nn.Conv3d
        self.offsets = conv(channels, heads * points * dims, 1)
        self.weights = conv(channels, heads * points, 1)
        self.value = conv(channels, channels, 1)
        self.out = conv(channels, channels, 1)
        self.norm = nn.BatchNorm2d(channels) if dims == 2 else nn.BatchNorm3d(channels)
        nn.init.zeros_(self.offsets.weight)
        with torch.no_grad():
            self.offsets.bias.copy_(spread_directions(heads * points, dims).reshape(-1))

    def attend(self, x: Tensor) -> Tensor:
        """The attention read before the output projection: ``(B, C, *S)`` -> ``(B, C, *S)``."""
        b, c, *size = x.shape
        m, k = self.heads, self.points
        offsets = self.offsets(x).view(b, m, k, self.dims, *size)
        if self.offset_order == "grid_sample":
            offsets = offsets.flip(3)  # to axis order
        weights = self.weights(x).view(b, m, k, *size).softmax(dim=2)
        value = self.value(x).view(b, m, c // m, *size)
        return deformable_sample(value, offsets, weights)

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.norm(x + self.out(self.attend(x))))


# ---------------------------------------------------------------------------------------------- CBAM


class ChannelAttention(nn.Sequential):
    """CBAM's channel attention ``M_c = sigmoid(MLP(AvgPool(x)) + MLP(MaxPool(x)))``, one MLP for both descriptors.

    The MLP is ``1x1 conv (C -> max(1, C // reduction), no bias) -> ReLU -> 1x1 conv (-> C, no bias)``; this
    module *is* that MLP (a ``Sequential``: its parameters are ``0.weight`` and ``2.weight``).

    Args:
        channels: ``C``; reduction: hidden width ``max(1, C // reduction)``; dims: 2 or 3 spatial axes.

    Forward: ``(B, C, *S)`` -> ``M_c`` ``(B, C, 1, ...)`` in ``(0, 1)`` (pooled over every spatial axis).
    """

    def __init__(self, channels: int, reduction: int = 16, dims: int = 3) -> None:
        if dims not in (2, 3):
            raise ValueError(f"ChannelAttention: dims must be 2 or 3, got {dims}")
        conv = nn.Conv2d if dims == 2 else nn.Conv3d
        hidden = max(1, channels // reduction)
        super().__init__(
            conv(channels, hidden, 1, bias=False),
            nn.ReLU(inplace=True),
            conv(hidden, channels, 1, bias=False),
        )

    def forward(self, x: Tensor) -> Tensor:
        spatial = tuple(range(2, x.dim()))
        avg = x.mean(dim=spatial, keepdim=True)
        mx = x.amax(dim=spatial, keepdim=True)
        return torch.sigmoid(super().forward(avg) + super().forward(mx))


class _SpatialAttention:
    """CBAM's spatial attention: a convolution of ``[mean over channels; max over channels]`` to one logit map."""

    def __init__(self, kernel: int = 7) -> None:
        if kernel % 2 == 0:
            raise ValueError(f"spatial attention: kernel must be odd (same-size output), got {kernel}")
        super().__init__(2, 1, kernel, padding=kernel // 2, bias=False)  # type: ignore[call-arg]

    def forward(self, x: Tensor) -> Tensor:
        pooled = torch.cat([x.mean(dim=1, keepdim=True), x.amax(dim=1, keepdim=True)], dim=1)
        return super().forward(pooled)  # type: ignore[misc]


class SpatialAttention2d(_SpatialAttention, nn.Conv2d):
    """CBAM's spatial attention on ``(B, C, H, W)``: the ``M_s`` **logits** ``(B, 1, H, W)`` (apply a sigmoid).

    The module *is* the ``2 -> 1`` convolution (odd ``kernel``, same size, no bias; its parameter is ``weight``).
    """


class SpatialAttention3d(_SpatialAttention, nn.Conv3d):
    """CBAM's spatial attention on ``(B, C, X, Y, Z)``: the ``M_s`` **logits** ``(B, 1, X, Y, Z)`` (apply a sigmoid).

    The module *is* the ``2 -> 1`` convolution (odd ``kernel``, same size, no bias; its parameter is ``weight``).
    """


def cbam(x: Tensor, channel: ChannelAttention, spatial: nn.Module) -> tuple[Tensor, Tensor, Tensor]:
    """CBAM's two steps on ``x`` ``(B, C, *S)``: ``x' = M_c * x``, then ``M_s`` from ``x'``.

    Args:
        x: the features.
        channel: a :class:`ChannelAttention`; spatial: a :class:`SpatialAttention2d` / ``3d`` (its logits).

    Returns:
        ``(x', M_c, M_s logits)``: ``(B, C, *S)``, ``(B, C, 1, ...)`` and ``(B, 1, *S)``; the refined features are
        ``sigmoid(M_s) * x'``.
    """
    channel_map = channel(x)
    attended = channel_map * x
    return attended, channel_map, spatial(attended)


class CBAM(nn.Module):
    """Convolutional block attention module: ``sigmoid(M_s(x')) * x'`` with ``x' = M_c(x) * x`` (Woo et al.).

    Args:
        channels: ``C``; reduction: of the channel MLP (hidden ``max(1, C // reduction)``);
        spatial_kernel: odd kernel of the spatial convolution; dims: 2 or 3 spatial axes.

    Parameters: ``channel_mlp`` (:class:`ChannelAttention`) and ``spatial_conv`` (:class:`SpatialAttention2d` /
    ``3d``), created in that order.

    Forward: ``(B, C, *S)`` -> ``(B, C, *S)``; :meth:`maps` also returns ``M_c`` and the ``M_s`` logits.
    """

    def __init__(self, channels: int, reduction: int = 16, spatial_kernel: int = 7, dims: int = 3) -> None:
        super().__init__()
        self.channel_mlp = ChannelAttention(channels, reduction, dims)
        self.spatial_conv = (SpatialAttention2d if dims == 2 else SpatialAttention3d)(spatial_kernel)

    def maps(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(refined, M_c, M_s logits)``; see :func:`cbam`."""
        attended, channel_map, spatial_logits = cbam(x, self.channel_mlp, self.spatial_conv)
        return torch.sigmoid(spatial_logits) * attended, channel_map, spatial_logits

    def forward(self, x: Tensor) -> Tensor:
        return self.maps(x)[0]
