"""OccLE's geometric branch (OccLE §3.3.1, Fig. 3c) and its Tab. 4(a) baseline, plus the LiDAR voxeliser (§3.2).

Every grid here lives on one :class:`~occplug.geometry.GridSpec` in the ego frame (x forward, y left, z up;
the camera faces +x) and is laid out ``(B, C, X, Y, Z)``. A multi-frame input is ``(B, T, C, X, Y, Z)`` or a
list of ``T`` grids ``(B, C, X, Y, Z)``, its frames already brought onto the current ego grid (by the
view transform for images, by the point transform for LiDAR) and given in the same order to every call.

Cross-plane image/LiDAR synergy (:class:`CrossPlaneFusion`), in the paper's words and ours:

1. The ``T`` frames of each modality are fused into one grid by a Conv1D over the frame axis (per voxel).
2. LiDAR is reliable along x (range), so its grid is collapsed by stacking y (resp. z) into channels and a
   Conv2D, giving the planes ``F_xz`` ``(B, C, X, Z)`` and ``F_xy`` ``(B, C, X, Y)``.
3. The image is reliable on the yz plane (the image plane of a +x camera), so its grid is collapsed by stacking
   x into channels and a Conv2D, giving ``F_yz`` ``(B, C, Y, Z)``; then (Eq. 3)
   ``F_yz,y = F_yz + SA_y(F_yz)`` (self-attention among the ``Y`` tokens of each z row) and
   ``F_yz,z = F_yz + SA_z(F_yz^T)^T`` (among the ``Z`` tokens of each y column).
4. Eq. 4: ``F_f1 = F_xz x F_yz,z`` (the planes share z) and ``F_f2 = F_xy x F_yz,y`` (they share y), each a
   ``(B, C, X, Y, Z)`` grid, ``F_f1[c,x,y,z] = F_xz[c,x,z] * F_yz,z[c,y,z]`` and
   ``F_f2[c,x,y,z] = F_xy[c,x,y] * F_yz,y[c,y,z]``; the geometric feature grid is ``F_f = F_f1 + F_f2``
   (:func:`cross_plane_product`).

Assumptions (where the paper is silent or inconsistent):

- §3.3.1 text vs. subscripts: the text gives the LiDAR grid the xz/xy planes and the image grid the yz plane
  (matching the Fig. 3a/b motivation), while Eq. 3-4 label them ``F_I,xz`` / ``F_P,yz``, swapping the
  ``I``/``P`` of §3.2. We follow the text. The stated plane shapes (``F_xy in R^{W1 x Z1}``,
  ``F_yz in R^{H1 x W1}``) are also garbled; we use ``xz: (X, Z)``, ``xy: (X, Y)``, ``yz: (Y, Z)``.
- §3.3.1 "×" in Eq. 4 ("matrix multiplication in the TPV", "multiplicative integration"): the result is
  stated to be a ``H1 x W1 x Z1`` grid, so it cannot contract the shared axis. We read it as the per-channel
  batched outer product over the shared axis, i.e. an elementwise product after broadcasting both planes to
  the grid.
- Eq. 3: ``SA(F)`` attends along the first axis of ``F`` (y), ``SA(F^T)^T`` along z; the subscript of the
  result names the axis attended along, and Eq. 4 pairs each with the plane sharing that axis. ``SA`` is a
  plain multi-head self-attention over the channel vectors (no norm, no positional encoding: the residual and
  the Conv2D carry position); the two axes get separate weights.
- "Stack along an axis": channel ``c * N + n`` of the stacked map holds channel ``c`` at index ``n`` of the
  stacked axis. The Conv2D kernel size is not given (``plane_kernel``, default 3, "same" padding); the
  Conv2Ds map straight to ``channels`` with no norm or activation (the paper names only the Conv2D).
- Conv1D frame fusion: ``Conv1d(C, C, kernel_size=T)`` over each voxel's ``(C, T)`` sequence (no padding),
  so every frame gets its own ``C x C`` mixing; each modality keeps its channel count until its Conv2D.
- §3.5 ``l_geo = ce(G, G_bar)``: ``G`` is the 2-class (free/occupied) logits of a small 3D head
  (:class:`GeometryHead`; its depth is not given: ``3x3x3 conv -> BN -> ReLU`` blocks then a ``1x1x1`` conv).
- Tab. 4(a) baseline ("Conv3D and 3D DA"): frame fusion as above, modalities concatenated, one
  ``3x3x3 conv -> BN -> ReLU``, one single-scale 3D deformable self-attention layer (Deformable DETR's sampling
  with a third offset, the core's :class:`~occplug.nn.DeformableAttention`), the same head.
- §3.2 voxelisation: "randomly samples up to 35 points per voxel"; :func:`voxelize_points` keeps the first
  ``max_points`` in input order (deterministic), so a caller who wants the paper's random subset shuffles the
  points first (that is also where the student's "sampling number" augmentation of Tab. 1 goes). The offset
  from the voxel centre is in metres, like the position.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Literal

import torch
from torch import Tensor, nn

from occplug.constraints import NonNegative, Positive, check_choices
from occplug.geometry import GridSpec
from occplug.nn import ConvNormAct3d, DeformableAttention

__all__ = [
    "Conv3dDeformableBaseline",
    "CrossPlaneFusion",
    "CrossPlaneGeometryBranch",
    "CrossPlanes",
    "FrameFusion",
    "GeometryHead",
    "LidarVoxelEncoder",
    "VoxelizedPoints",
    "cross_plane_product",
    "stack_frames",
    "voxelize_points",
]

Frames = Tensor | Sequence[Tensor]


def stack_frames(grids: Frames, num_frames: int, channels: int, shape: Sequence[int], who: str) -> Tensor:
    """Check and stack a multi-frame grid input.

    Args:
        grids: ``(B, T, C, X, Y, Z)`` or a list of ``T`` tensors ``(B, C, X, Y, Z)``.
        num_frames: expected ``T``; channels: expected ``C``; shape: expected ``(X, Y, Z)``.
        who: the caller, for the error message.

    Returns:
        ``(B, T, C, X, Y, Z)``.
    """
    if not isinstance(grids, Tensor):
        grids = torch.stack(list(grids), dim=1)
    expected = (num_frames, channels, *shape)
    if grids.dim() != 6 or tuple(grids.shape[1:]) != expected:
        raise ValueError(f"{who}: expected grids (B, {', '.join(map(str, expected))}), got {tuple(grids.shape)}")
    return grids


class FrameFusion(nn.Module):
    """Fuse ``T`` frames of a feature grid into one with a Conv1D over the frame axis (OccLE §3.3.1).

    Each voxel's ``(C, T)`` sequence goes through ``Conv1d(C, C, kernel_size=T)``, whose single output
    position is the fused feature. Computed as one contraction over ``(C, T)`` rather than by reshaping every
    voxel into a batch element (same numbers, no ``(B*X*Y*Z, C, T)`` copy).

    Args:
        channels: ``C``; num_frames: ``T``.

    Forward: ``(B, T, C, X, Y, Z)`` -> ``(B, C, X, Y, Z)``.
    """

    def __init__(self, channels: Annotated[int, Positive], num_frames: Annotated[int, Positive]) -> None:
        super().__init__()
        self.num_frames = int(num_frames)
        self.conv = nn.Conv1d(channels, channels, kernel_size=self.num_frames)

    def forward(self, grids: Tensor) -> Tensor:
        out = torch.einsum("oct,btcxyz->boxyz", self.conv.weight, grids)
        return out + self.conv.bias.view(1, -1, 1, 1, 1)


def _stack_axis(grid: Tensor, axis: int) -> Tensor:
    """Stack one spatial axis of ``(B, C, X, Y, Z)`` into channels: ``(B, C * N_axis, <other two axes>)``.

    ``axis`` is 0 (x), 1 (y) or 2 (z); channel ``c * N + n`` holds channel ``c`` at index ``n``.
    """
    b, c = grid.shape[:2]
    moved = grid.movedim(2 + axis, 2)  # (B, C, N, A, B')
    return moved.reshape(b, c * moved.shape[2], *moved.shape[3:])


def cross_plane_product(xz: Tensor, xy: Tensor, yz_y: Tensor, yz_z: Tensor) -> Tensor:
    """Eq. 4 and the sum after it: ``F_f = F_xz x F_yz,z + F_xy x F_yz,y`` as a 3D grid.

    Args:
        xz: ``(B, C, X, Z)`` LiDAR xz plane. xy: ``(B, C, X, Y)`` LiDAR xy plane.
        yz_y: ``(B, C, Y, Z)`` image yz plane after attention along y (pairs with ``xy``: both hold y).
        yz_z: ``(B, C, Y, Z)`` image yz plane after attention along z (pairs with ``xz``: both hold z).

    Returns:
        ``(B, C, X, Y, Z)``: ``out[b,c,x,y,z] = xz[b,c,x,z] * yz_z[b,c,y,z] + xy[b,c,x,y] * yz_y[b,c,y,z]``.
    """
    f1 = xz.unsqueeze(3) * yz_z.unsqueeze(2)
    f2 = xy.unsqueeze(4) * yz_y.unsqueeze(2)
    return f1 + f2


@dataclass
class CrossPlanes:
    """The intermediate grids and planes of :class:`CrossPlaneFusion` (for inspection and tests)."""

    #: ``(B, C_lidar, X, Y, Z)`` LiDAR grid after frame fusion.
    lidar: Tensor
    #: ``(B, C_image, X, Y, Z)`` image grid after frame fusion.
    image: Tensor
    #: ``(B, C, X, Z)`` LiDAR grid with y stacked into channels, after its Conv2D.
    xz: Tensor
    #: ``(B, C, X, Y)`` LiDAR grid with z stacked into channels, after its Conv2D.
    xy: Tensor
    #: ``(B, C, Y, Z)`` image grid with x stacked into channels, after its Conv2D.
    yz: Tensor
    #: ``(B, C, Y, Z)`` ``yz + SA`` along y (within each z row), Eq. 3 ``F_P,yzy``.
    yz_y: Tensor
    #: ``(B, C, Y, Z)`` ``yz + SA`` along z (within each y column), Eq. 3 ``F_P,yzz``.
    yz_z: Tensor


class CrossPlaneFusion(nn.Module):
    """Cross-plane image/LiDAR feature synergy (OccLE §3.3.1, Eq. 3-4); see the module docstring.

    Planes, on a grid of shape ``(X, Y, Z)`` with ``C = channels``:

    - LiDAR: ``xz`` ``(B, C, X, Z)`` (y stacked: ``Conv2d(C_lidar * Y, C)``) and ``xy`` ``(B, C, X, Y)``
      (z stacked: ``Conv2d(C_lidar * Z, C)``);
    - image: ``yz`` ``(B, C, Y, Z)`` (x stacked: ``Conv2d(C_image * X, C)``), then ``yz_y`` and ``yz_z``
      ``(B, C, Y, Z)`` by Eq. 3 (attention costs ``O(Y^2)`` per z row and ``O(Z^2)`` per y column);
    - output ``(B, C, X, Y, Z)`` by Eq. 4 (:func:`cross_plane_product`).

    Args:
        lidar_channels: ``C_lidar`` of the LiDAR feature grids.
        image_channels: ``C_image`` of the lifted image feature grids.
        grid: the grid both live on (a :class:`GridSpec` or ``{range, voxel_size}``); its shape sizes the
            Conv2Ds, which see a whole axis in their input channels.
        channels: ``C`` of the planes and of the output.
        num_frames: ``T``, frames per modality.
        plane_kernel: odd kernel size of the three Conv2Ds ("same" padding).
        heads: attention heads (``channels`` must be divisible by it).

    Forward:
        ``lidar`` ``(B, T, C_lidar, X, Y, Z)`` (or a list of ``T`` ``(B, C_lidar, X, Y, Z)``) and ``image``
        likewise with ``C_image`` -> ``(B, C, X, Y, Z)``, the geometric feature grid ``F_f^g``.
    """

    def __init__(
        self,
        lidar_channels: Annotated[int, Positive],
        image_channels: Annotated[int, Positive],
        grid: GridSpec,
        channels: Annotated[int, Positive] = 32,
        num_frames: Annotated[int, Positive] = 1,
        plane_kernel: Annotated[int, Positive] = 3,
        heads: Annotated[int, Positive] = 4,
    ) -> None:
        super().__init__()
        if plane_kernel % 2 != 1:
            raise ValueError(f"cross-plane fusion: plane_kernel must be odd, got {plane_kernel}")
        if channels % heads:
            raise ValueError(f"cross-plane fusion: channels {channels} not divisible by heads {heads}")
        self.grid = grid
        self.lidar_channels, self.image_channels = int(lidar_channels), int(image_channels)
        self.channels, self.num_frames = int(channels), int(num_frames)
        x, y, z = self.grid.shape
        pad = plane_kernel // 2
        self.lidar_frames = FrameFusion(self.lidar_channels, self.num_frames)
        self.image_frames = FrameFusion(self.image_channels, self.num_frames)
        self.lidar_to_xz = nn.Conv2d(self.lidar_channels * y, self.channels, plane_kernel, padding=pad)
        self.lidar_to_xy = nn.Conv2d(self.lidar_channels * z, self.channels, plane_kernel, padding=pad)
        self.image_to_yz = nn.Conv2d(self.image_channels * x, self.channels, plane_kernel, padding=pad)
        self.attend_y = nn.MultiheadAttention(self.channels, heads, batch_first=True)
        self.attend_z = nn.MultiheadAttention(self.channels, heads, batch_first=True)

    def axial_attention(self, yz: Tensor) -> tuple[Tensor, Tensor]:
        """Eq. 3 on a ``(B, C, Y, Z)`` plane -> ``(yz_y, yz_z)``, both ``(B, C, Y, Z)``.

        ``yz_y = yz + SA`` over the ``Y`` tokens of each z row; ``yz_z = yz + SA`` over the ``Z`` tokens of
        each y column.
        """
        b, c, y, z = yz.shape
        rows = yz.permute(0, 3, 2, 1).reshape(b * z, y, c)  # one sequence per z, running along y
        along_y = self.attend_y(rows, rows, rows, need_weights=False)[0].view(b, z, y, c).permute(0, 3, 2, 1)
        cols = yz.permute(0, 2, 3, 1).reshape(b * y, z, c)  # one sequence per y, running along z
        along_z = self.attend_z(cols, cols, cols, need_weights=False)[0].view(b, y, z, c).permute(0, 3, 1, 2)
        return yz + along_y, yz + along_z

    def planes(self, lidar: Frames, image: Frames) -> CrossPlanes:
        """Everything up to Eq. 4: the fused grids and the five planes (shapes in :class:`CrossPlanes`)."""
        shape = self.grid.shape
        lidar = stack_frames(lidar, self.num_frames, self.lidar_channels, shape, "cross-plane fusion (lidar)")
        image = stack_frames(image, self.num_frames, self.image_channels, shape, "cross-plane fusion (image)")
        lidar_grid = self.lidar_frames(lidar)
        image_grid = self.image_frames(image)
        xz = self.lidar_to_xz(_stack_axis(lidar_grid, 1))
        xy = self.lidar_to_xy(_stack_axis(lidar_grid, 2))
        yz = self.image_to_yz(_stack_axis(image_grid, 0))
        yz_y, yz_z = self.axial_attention(yz)
        return CrossPlanes(lidar=lidar_grid, image=image_grid, xz=xz, xy=xy, yz=yz, yz_y=yz_y, yz_z=yz_z)

    def forward(self, lidar: Frames, image: Frames) -> Tensor:
        p = self.planes(lidar, image)
        return cross_plane_product(p.xz, p.xy, p.yz_y, p.yz_z)


class GeometryHead(nn.Module):
    """The geometric branch's 3D header: ``layers`` x (``3x3x3 conv -> BN -> ReLU``), then a ``1x1x1`` conv.

    Args:
        channels: ``C`` in; num_classes: ``K`` logits per voxel (2: free / occupied for ``l_geo``, §3.5);
        hidden: width of the 3x3x3 layers; layers: how many (0: the 1x1x1 conv alone).

    Forward: ``(B, C, X, Y, Z)`` -> ``(B, K, X, Y, Z)`` logits.
    """

    def __init__(
        self,
        channels: Annotated[int, Positive],
        num_classes: Annotated[int, Positive] = 2,
        hidden: Annotated[int, Positive] = 32,
        layers: Annotated[int, NonNegative] = 1,
    ) -> None:
        super().__init__()
        blocks: list[nn.Module] = []
        width = channels
        for _ in range(layers):
            blocks += ConvNormAct3d(width, hidden)  # its three layers, flattened: the keys stay ``net.<i>.*``
            width = hidden
        blocks.append(nn.Conv3d(width, num_classes, 1))
        self.net = nn.Sequential(*blocks)

    def forward(self, grid: Tensor) -> Tensor:
        return self.net(grid)


class CrossPlaneGeometryBranch(nn.Module):
    """OccLE's geometric branch: :class:`CrossPlaneFusion` then :class:`GeometryHead` (§3.3.1, §3.5).

    Args:
        lidar_channels, image_channels, grid, channels, num_frames, plane_kernel, heads: as for
            :class:`CrossPlaneFusion`.
        num_classes: ``K`` (2 for the free/occupied geometry ``G`` of ``l_geo = ce(G, G_bar)``).
        head_layers: 3x3x3 layers of the head.

    Forward:
        ``lidar`` ``(B, T, C_lidar, X, Y, Z)`` and ``image`` ``(B, T, C_image, X, Y, Z)`` (or lists of ``T``
        grids) -> ``(B, K, X, Y, Z)`` logits. :meth:`encode` returns the feature grid ``F_f^g``
        ``(B, channels, X, Y, Z)`` that §3.4 fuses with the semantic grid.
    """

    def __init__(
        self,
        lidar_channels: Annotated[int, Positive],
        image_channels: Annotated[int, Positive],
        grid: GridSpec,
        channels: Annotated[int, Positive] = 32,
        num_frames: Annotated[int, Positive] = 1,
        num_classes: Annotated[int, Positive] = 2,
        plane_kernel: Annotated[int, Positive] = 3,
        heads: Annotated[int, Positive] = 4,
        head_layers: Annotated[int, NonNegative] = 1,
    ) -> None:
        super().__init__()
        self.fusion = CrossPlaneFusion(
            lidar_channels, image_channels, grid, channels, num_frames, plane_kernel=plane_kernel, heads=heads
        )
        self.grid = self.fusion.grid
        self.head = GeometryHead(channels, num_classes, hidden=channels, layers=head_layers)

    def encode(self, lidar: Frames, image: Frames) -> Tensor:
        """The geometric feature grid ``(B, channels, X, Y, Z)``."""
        return self.fusion(lidar, image)

    def forward(self, lidar: Frames, image: Frames) -> Tensor:
        return self.head(self.encode(lidar, image))


class Conv3dDeformableBaseline(nn.Module):
    """Tab. 4(a)'s geometric-branch baseline: concatenation, Conv3D fusion, 3D deformable attention, head.

    Same arguments and input/output contract as :class:`CrossPlaneGeometryBranch`, so a config swaps the two.

    Args:
        lidar_channels, image_channels, grid, channels, num_frames, num_classes, head_layers: as for
            :class:`CrossPlaneGeometryBranch`.
        heads, points: of the deformable attention.

    Forward:
        ``lidar`` ``(B, T, C_lidar, X, Y, Z)`` and ``image`` ``(B, T, C_image, X, Y, Z)`` (or lists of ``T``
        grids) -> ``(B, K, X, Y, Z)`` logits; :meth:`encode` -> ``(B, channels, X, Y, Z)``.
    """

    def __init__(
        self,
        lidar_channels: Annotated[int, Positive],
        image_channels: Annotated[int, Positive],
        grid: GridSpec,
        channels: Annotated[int, Positive] = 32,
        num_frames: Annotated[int, Positive] = 1,
        num_classes: Annotated[int, Positive] = 2,
        heads: Annotated[int, Positive] = 4,
        points: Annotated[int, Positive] = 4,
        head_layers: Annotated[int, NonNegative] = 1,
    ) -> None:
        super().__init__()
        self.grid = grid
        self.lidar_channels, self.image_channels = int(lidar_channels), int(image_channels)
        self.num_frames = int(num_frames)
        self.lidar_frames = FrameFusion(self.lidar_channels, self.num_frames)
        self.image_frames = FrameFusion(self.image_channels, self.num_frames)
        self.fuse = ConvNormAct3d(self.lidar_channels + self.image_channels, channels)
        self.attention = DeformableAttention(channels, heads, points, dims=3)
        self.head = GeometryHead(channels, num_classes, hidden=channels, layers=head_layers)

    def encode(self, lidar: Frames, image: Frames) -> Tensor:
        """The fused feature grid ``(B, channels, X, Y, Z)``."""
        shape = self.grid.shape
        lidar = stack_frames(lidar, self.num_frames, self.lidar_channels, shape, "conv3d baseline (lidar)")
        image = stack_frames(image, self.num_frames, self.image_channels, shape, "conv3d baseline (image)")
        both = torch.cat([self.lidar_frames(lidar), self.image_frames(image)], dim=1)
        return self.attention(self.fuse(both))

    def forward(self, lidar: Frames, image: Frames) -> Tensor:
        return self.head(self.encode(lidar, image))


@dataclass
class VoxelizedPoints:
    """Points grouped by voxel, VoxelNet style (OccLE §3.2), for a batch of point clouds.

    Voxels are listed in ascending ``(b, i, j, k)`` order; within a voxel the points keep their input order.
    """

    #: ``(V, M, 3 + F + 3)`` per point: ego-frame ``x, y, z`` (metres), its ``F`` extra features (intensity,
    #: ...), then its offset from the voxel centre (metres); rows past ``counts[v]`` are zero.
    features: Tensor
    #: ``(V,)`` int64 points kept in each voxel, in ``[1, M]``.
    counts: Tensor
    #: ``(V, 4)`` int64 ``(b, i, j, k)``: sample and voxel index on ``grid``.
    coords: Tensor
    #: ``B``, the number of point clouds.
    batch_size: int
    #: The grid the voxels index.
    grid: GridSpec

    @property
    def mask(self) -> Tensor:
        """``(V, M)`` bool: which rows of :attr:`features` hold a point."""
        m = self.features.shape[1]
        return torch.arange(m, device=self.counts.device) < self.counts[:, None]


def voxelize_points(points: Sequence[Tensor], grid: GridSpec, max_points: int = 35) -> VoxelizedPoints:
    """Group each sample's points by the voxel of ``grid`` holding them (§3.2's ``V(P)``).

    A point lands in voxel :meth:`GridSpec.coord_to_index` of its position; points outside the grid (and
    non-finite ones) are dropped. A voxel keeps at most ``max_points`` points: the first ones in input order
    (deterministic; shuffle beforehand for the paper's random subset).

    Args:
        points: ``B`` tensors ``(P_b, 3 + F)``: ego-frame ``x, y, z`` in metres, then ``F`` features
            (e.g. intensity), the same ``F`` for all.
        grid: the voxel grid.
        max_points: ``M``, points kept per voxel.

    Returns:
        :class:`VoxelizedPoints` with ``features`` ``(V, M, 3 + F + 3)``, ``counts`` ``(V,)``,
        ``coords`` ``(V, 4)``.
    """
    if max_points < 1:
        raise ValueError(f"voxelize_points: max_points must be >= 1, got {max_points}")
    if not points:
        raise ValueError("voxelize_points: need at least one point cloud")
    x, y, z = grid.shape
    feats, keys = [], []
    for b, pts in enumerate(points):
        if pts.dim() != 2 or pts.shape[1] < 3 or pts.shape[1] != points[0].shape[1]:
            raise ValueError(f"voxelize_points: sample {b}: expected (P, 3 + F) points, got {tuple(pts.shape)}")
        xyz = pts[:, :3]
        idx = grid.coord_to_index(xyz)
        keep = grid.contains(xyz) & grid.index_in_bounds(idx) & torch.isfinite(pts).all(dim=1)
        pts, idx = pts[keep], idx[keep]
        centre = grid.index_to_coord(idx).to(pts.dtype)
        feats.append(torch.cat([pts, pts[:, :3] - centre], dim=1))
        keys.append(((b * x + idx[:, 0]) * y + idx[:, 1]) * z + idx[:, 2])
    feat, key = torch.cat(feats), torch.cat(keys)
    key, order = torch.sort(key, stable=True)  # stable: input order survives within a voxel
    feat = feat[order]
    voxel_keys, inverse, counts = torch.unique_consecutive(key, return_inverse=True, return_counts=True)
    start = torch.cumsum(counts, 0) - counts
    rank = torch.arange(len(key), device=key.device) - start[inverse]
    kept = rank < max_points
    out = feat.new_zeros(len(voxel_keys), max_points, feat.shape[1])
    out[inverse[kept], rank[kept]] = feat[kept]
    k = voxel_keys % z
    j = voxel_keys // z % y
    i = voxel_keys // (y * z) % x
    b = voxel_keys // (x * y * z)
    coords = torch.stack([b, i, j, k], dim=1)
    return VoxelizedPoints(
        features=out, counts=counts.clamp(max=max_points), coords=coords, batch_size=len(points), grid=grid
    )


def _mix32(x: Tensor) -> Tensor:
    """murmur3's 32-bit finaliser on int64 ``x`` in ``[0, 2^32)``: a bijection there, every input bit spread over
    every output bit (a plain multiplicative hash ranks strided indices in long runs). Plain int64 arithmetic, so
    it traces."""
    mask = (1 << 32) - 1
    x = x ^ (x >> 16)
    x = (x * 0x85EBCA6B) & mask
    x = x ^ (x >> 13)
    x = (x * 0xC2B2AE35) & mask
    return x ^ (x >> 16)


#: How a voxel with more than ``max_points`` points picks the ones it keeps (:class:`LidarVoxelEncoder`).
PointSampling = Literal["random", "first"]


class LidarVoxelEncoder(nn.Module):
    """LiDAR points -> a dense feature grid: VoxelNet voxel feature encoding (§3.2's dense 3D input path).

    Every point gets its voxel of ``grid`` (points outside it, and non-finite rows -- the padding of an exported
    graph's point input -- go nowhere); a voxel keeps at most ``max_points`` of its points; the kept points go
    through a shared point MLP (``Linear -> LayerNorm -> ReLU``), get the voxel's max-pooled feature appended
    (VoxelNet's VFE), pass a second ``Linear -> LayerNorm -> ReLU`` and are max-pooled again into the voxel
    feature on a zero grid. A voxel's feature depends only on its own kept points, in any order.

    Which points a voxel keeps (``sampling``): ``"random"`` (§3.2: "randomly samples up to 35 points per
    voxel") -- a fresh random subset every training step, and in eval a fixed pseudo-random one (points ranked
    by a 32-bit mixing hash of their input index, so the subset does not follow the scan order of the sensor,
    and the same points are kept in an exported graph); ``"first"``: the first ones in input order
    (:func:`voxelize_points`'s rule).

    The pooling runs over one slot per voxel of the batch plus one discard slot, with fixed shapes (no
    data-dependent indexing), so the encoder traces for export with any number of points; it equals the
    VoxelNet computation on :func:`voxelize_points` (tested).

    Args:
        grid: the output grid (a :class:`GridSpec` or ``{range, voxel_size}``).
        point_features: ``F``, features per point after ``x, y, z`` (1 for intensity).
        out_channels: ``C`` of the output; hidden: width of the first point layer.
        max_points: points kept per voxel (§3.2: 35).
        sampling: ``"random"`` or ``"first"`` (above).

    Forward: ``B`` tensors ``(P_b, 3 + F)`` of ego-frame points -> ``(B, C, X, Y, Z)`` (zero in empty voxels).
    """

    def __init__(
        self,
        grid: GridSpec,
        point_features: Annotated[int, NonNegative] = 1,
        out_channels: Annotated[int, Positive] = 32,
        hidden: Annotated[int, Positive] = 32,
        max_points: Annotated[int, Positive] = 35,
        sampling: PointSampling = "random",
    ) -> None:
        super().__init__()
        check_choices(LidarVoxelEncoder.__init__, "lidar voxel encoder:", sampling=sampling)
        self.grid = grid
        self.point_features, self.out_channels, self.max_points = int(point_features), int(out_channels), max_points
        self.sampling = sampling
        self.point_net = nn.Sequential(nn.Linear(6 + self.point_features, hidden), nn.LayerNorm(hidden), nn.ReLU())
        self.voxel_net = nn.Sequential(nn.Linear(2 * hidden, out_channels), nn.LayerNorm(out_channels), nn.ReLU())

    def _order_within_voxel(self, count: int, device: torch.device) -> Tensor:
        """``(count,)`` int64 in ``[0, 2^32)``, distinct: the rank key of a sample's points inside their voxel."""
        index = torch.arange(count, device=device, dtype=torch.int64)
        if self.sampling == "first":
            return index
        if self.training:
            return torch.randperm(count, device=device)
        return _mix32(index)

    def slots(self, points: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
        """Each point's features and pooling slot, sorted by voxel (fixed shapes: every point has a row).

        Returns:
            ``features`` ``(N, 6 + F)`` (ego-frame ``x, y, z``, the ``F`` extra features, offset from the voxel
            centre; zero for a point outside the grid or non-finite) and ``slot`` ``(N,)`` int64: ``b * X * Y * Z + flat
            voxel index`` for a kept point, ``B * X * Y * Z`` (the discard slot) for a point outside the grid,
            non-finite, or past its voxel's ``max_points``. ``N = sum P_b``.
        """
        x, y, z = self.grid.shape
        cells = x * y * z
        discard = len(points) * cells
        feats, keys = [], []
        for b, pts in enumerate(points):
            if pts.dim() != 2 or pts.shape[1] != 3 + self.point_features:
                raise ValueError(
                    f"lidar voxel encoder: sample {b}: expected (P, {3 + self.point_features}) points, got "
                    f"{tuple(pts.shape)}"
                )
            xyz = pts[:, :3]
            idx = self.grid.coord_to_index(xyz)
            valid = self.grid.contains(xyz) & self.grid.index_in_bounds(idx) & torch.isfinite(pts).all(dim=1)
            idx = torch.where(valid[:, None], idx, torch.zeros_like(idx))
            centre = self.grid.index_to_coord(idx).to(pts.dtype)
            feat = torch.cat([pts, xyz - centre], dim=1)
            feats.append(torch.where(valid[:, None], feat, torch.zeros_like(feat)))
            flat = b * cells + (idx[:, 0] * y + idx[:, 1]) * z + idx[:, 2]
            voxel = torch.where(valid, flat, torch.full_like(flat, discard))
            keys.append(voxel * (1 << 32) + self._order_within_voxel(pts.shape[0], pts.device))
        feat, key = torch.cat(feats), torch.cat(keys)
        key, order = torch.sort(key)  # voxel-major, then the sampling's rank (distinct within a voxel)
        voxel = key // (1 << 32)
        position = torch.arange(key.shape[0], device=key.device)
        first = torch.full((discard + 1,), key.shape[0], dtype=torch.int64, device=key.device)
        first = first.scatter_reduce(0, voxel, position, reduce="amin")  # each voxel's first sorted position
        kept = (position - first[voxel] < self.max_points) & (voxel < discard)
        return feat[order], torch.where(kept, voxel, torch.full_like(voxel, discard))

    @staticmethod
    def _slot_max(h: Tensor, slot: Tensor, slots: int) -> Tensor:
        """``(N, D)`` point features -> ``(slots, D)``: the max over each slot's points (0 where it has none)."""
        out = h.new_zeros(slots, h.shape[1])
        return out.scatter_reduce(0, slot[:, None].expand_as(h), h, reduce="amax", include_self=False)

    def forward(self, points: Sequence[Tensor]) -> Tensor:
        feat, slot = self.slots(points)
        x, y, z = self.grid.shape
        slots = len(points) * x * y * z + 1
        h = self.point_net(feat)  # (N, hidden)
        pooled = self._slot_max(h, slot, slots)
        h = self.voxel_net(torch.cat([h, pooled[slot]], dim=-1))
        voxel = self._slot_max(h, slot, slots)[:-1]  # (B * X * Y * Z, C): the discard slot dropped
        return voxel.view(len(points), x, y, z, self.out_channels).permute(0, 4, 1, 2, 3)
