"""View transforms: ``lss`` (forward splat of a per-cell depth distribution) and ``backward_projection``.

Feature cells and pixels
------------------------
An encoder of stride ``s`` turns an ``H x W`` (augmented) image into an ``h x w`` feature map
whose cell ``(r, c)`` covers pixels ``[s*r, s*r + s) x [s*c, s*c + s)``. With the pixel-centre
convention of :mod:`occplug.geometry.cameras` (centre of pixel ``[row, col]`` at ``u = col``,
``v = row``) the cell's centre is at::

    u = s*c + (s - 1) / 2,    v = s*r + (s - 1) / 2

and conversely a pixel position ``(u, v)`` lies at fractional cell ``c = (u - (s-1)/2) / s``.
Both transforms use exactly this map (:func:`feature_cell_centers`), through the effective
intrinsics ``img_aug @ intrinsics`` of the augmented image, so they agree with each other and
with any depth or semantic supervision that reads pixels.

Both transforms take the same arguments, so a config swaps ``lss`` <-> ``backward_projection``
by changing only ``type``. The frustum geometry and the splat itself are public
(:class:`occplug.ops.FrustumSplatter`); ``lss`` is a thin component on top of it
(``feature_cell_centers``, ``frustum_points`` and ``splat`` are re-exported here from there).
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from typing import Annotated, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from occplug.constraints import Length, NonNegative, Positive, check_choices
from occplug.context import RunContext
from occplug.data.frame import Batch
from occplug.geometry import GridSpec, project_to_image
from occplug.interfaces import Lifted, ViewTransform
from occplug.nn import PixelNet
from occplug.ops.splat import (
    FrustumSplatter,
    SplatPlan,
    SplatPlanCache,
    feature_cell_centers,
    frustum_points,
    splat,
)
from occplug.slots import Slot

from .depth_nets import DepthNet, PlainDepthNet

__all__ = [
    "BackwardProjection",
    "LSSViewTransform",
    "build_depth_net",
    "depth_bin_centers",
    "feature_cell_centers",
    "frustum_points",
    "splat",
    "voxel_flat_index",
]

#: ``[start, stop, step]`` metres, each >= 0 (:func:`depth_bin_centers` checks start < stop, step > 0).
DepthBins = Annotated[list[Annotated[float, NonNegative]], Length(exact=3)]


# ----------------------------------------------------------------------------- shared geometry
def depth_bin_centers(depth_bins: list[float] | tuple[float, ...]) -> Tensor:
    """Centres of the depth bins ``[start, stop, step]`` (metres of camera-frame z).

    The ``D = (stop - start) / step`` bins (an integer, else ``ValueError``) are
    ``[start + d*step, start + (d+1)*step)``; bin ``d``'s centre is ``start + (d + 0.5) * step``.
    E.g. ``[1.0, 45.0, 1.0]`` gives 44 bins with centres 1.5, 2.5, ..., 44.5.

    Returns:
        ``(D,)`` float32 bin centres.
    """
    if len(depth_bins) != 3:
        raise ValueError(f"depth_bins must be [start, stop, step] in metres, got {list(depth_bins)}")
    start, stop, step = (float(v) for v in depth_bins)
    if step <= 0 or stop <= start or start < 0:
        raise ValueError(f"depth_bins [start, stop, step] needs 0 <= start < stop and step > 0, got {list(depth_bins)}")
    count = (stop - start) / step
    d = round(count)
    if abs(count - d) > 1e-6 * max(1.0, count):
        raise ValueError(f"depth_bins: (stop - start) / step must be a whole number of bins, got {count:g}")
    return start + (torch.arange(d, dtype=torch.float64) + 0.5).mul(step).to(torch.float32)


def voxel_flat_index(points: Tensor, grid: GridSpec) -> Tensor:
    """Flat index of the voxel holding each point, over a batch of volumes; ``-1`` outside the grid.

    Args:
        points: ``(B, ..., 3)`` ego-frame points, metres (sample ``b``'s points in ``points[b]``).
        grid: the volume's grid ``(X, Y, Z)``.

    Returns:
        ``(B, ...)`` int64: ``((b*X + i)*Y + j)*Z + k`` for voxel ``(i, j, k)`` of sample ``b``
        (the row of a ``(B*X*Y*Z, C)`` view of a channels-last volume), or ``-1``.
    """
    x, y, z = grid.shape
    idx = grid.coord_to_index(points)
    inside = grid.index_in_bounds(idx)
    b = torch.arange(points.shape[0], device=points.device).view(-1, *([1] * (points.dim() - 2)))
    flat = ((b * x + idx[..., 0]) * y + idx[..., 1]) * z + idx[..., 2]
    return torch.where(inside, flat, torch.full_like(flat, -1))


def _no_autocast(device: torch.device) -> AbstractContextManager:
    """Geometry runs in float32 even under mixed precision (bf16 would move points by centimetres)."""
    return torch.autocast(device_type=device.type, enabled=False)


def _check_feature_size(features: Tensor, batch: Batch, stride: int, who: str) -> None:
    if features.dim() != 5:
        raise ValueError(f"{who}: expected features (B, N, C, h, w), got shape {tuple(features.shape)}")
    h, w = features.shape[-2:]
    big_h, big_w = batch.images.shape[-2:]
    if abs(h * stride - big_h) >= stride or abs(w * stride - big_w) >= stride:
        raise ValueError(
            f"{who}: a {h}x{w} feature map at image_stride {stride} does not match the {big_h}x{big_w} images; "
            f"image_stride must be the encoder's stride"
        )


# ----------------------------------------------------------------------------- LSS
class LSSViewTransform(ViewTransform):
    """Lift-Splat-Shoot: a categorical depth distribution per feature cell, splatted into voxels.

    A depth net (kind ``depth_net``, default ``plain``: a per-cell conv head) predicts ``D`` depth
    logits and ``C`` context features for every feature cell from the image features and the
    batch's calibration; the softmax over depth times the context gives ``D`` weighted copies of
    the context, placed at the cell centre (see the module docstring) unprojected to each depth
    bin's centre through ``img_aug @ intrinsics`` and ``cam_to_ego``. Copies outside the grid are
    dropped (on a contracted grid only those outside its z range); the rest are summed into the
    voxel that contains them.

    The sum runs through the public :class:`occplug.ops.FrustumSplatter` (:attr:`splatter`), which
    never builds the ``D x C`` products: the (camera, depth bin, cell) -> voxel structure is
    prepared once per sample geometry and kept in :attr:`plan_cache`, so a fixed camera rig
    computes its frustum geometry once. ``splat="reference"`` runs the naive :func:`splat`
    (``index_add_`` over all frustum points) instead; both give the same volume.

    Args:
        in_channels: ``C_in`` of the image features (the encoder's ``out_channels``).
        image_stride: pixels per feature cell (the encoder's ``stride``).
        grid: the output grid, a :class:`GridSpec` or ``{range, voxel_size[, contraction]}`` mapping.
        out_channels: ``C`` of the lifted volume.
        depth_bins: ``[start, stop, step]`` metres of camera-frame z; see :func:`depth_bin_centers`.
        hidden: width of the depth net's 3x3 conv (0: a single 1x1 conv), passed to the depth net
            unless its node sets ``hidden`` itself.
        splat: ``fast`` (cached plans, :func:`occplug.ops.splat_outer`) or ``reference``
            (the naive :func:`splat`; for checking and benchmarking).
        depth_net: a ``depth_net`` node (default ``{type: plain}``) or a built :class:`DepthNet`;
            its ``in_channels``, ``num_bins`` and ``out_channels`` are filled in.
        context: the run context (handed in by the builder); a ``depth_net`` node is built through it.

    Forward:
        ``features`` ``(B, N, C_in, h, w)`` and a batch with ``intrinsics``, ``cam_to_ego``,
        ``img_aug`` -> :class:`Lifted` with ``volume`` ``(B, C, X, Y, Z)`` (ego frame, on ``grid``;
        float32 under mixed precision too), ``depth_probs`` ``(B, N, D, h, w)`` (softmax over ``D``)
        and ``depth_bins`` ``(D,)`` centres.
    """

    def __init__(
        self,
        in_channels: int,
        image_stride: int,
        grid: GridSpec,
        out_channels: Annotated[int, Positive] = 64,
        depth_bins: DepthBins = [1.0, 45.0, 1.0],  # noqa: B006 - read only, never mutated
        hidden: Annotated[int, NonNegative] = 64,
        splat: Literal["fast", "reference"] = "fast",
        depth_net: Annotated[dict | DepthNet | None, Slot("depth_net")] = None,
        context: RunContext | None = None,
    ) -> None:
        super().__init__()
        check_choices(LSSViewTransform.__init__, "lss", splat=splat)
        self.grid = grid
        self.image_stride = int(image_stride)
        self.out_channels = int(out_channels)
        self.splat_mode = splat
        self.register_buffer("depth_centers", depth_bin_centers(depth_bins), persistent=False)
        self.num_depth_bins = int(self.depth_centers.shape[0])
        self.depth_net = build_depth_net(
            depth_net,
            in_channels,
            self.num_depth_bins,
            self.out_channels,
            context=context,
            hidden=hidden,
            depth_centers=self.depth_centers,
        )
        #: the public splatter doing the frustum geometry, the plans and the pooling.
        self.splatter = FrustumSplatter(self.grid, self.image_stride, mode=splat)

    @property
    def plan_cache(self) -> SplatPlanCache:
        """Geometry key -> :class:`~occplug.ops.SplatPlan` of one sample (the splatter's; not in the state dict)."""
        return self.splatter.plan_cache

    def voxel_index(self, batch: Batch, h: int, w: int) -> Tensor:
        """``(B, N, D, h, w)`` int64 flat voxel index (:func:`voxel_flat_index`) of every frustum point, -1 outside."""
        with _no_autocast(self.depth_centers.device):
            points = frustum_points(batch, h, w, self.image_stride, self.depth_centers, dtype=torch.float64)
            return voxel_flat_index(points, self.grid)

    def splat_plans(self, batch: Batch, h: int, w: int) -> list[SplatPlan]:
        """The :class:`~occplug.ops.SplatPlan` of every batch item (:meth:`occplug.ops.FrustumSplatter.plans`)."""
        return self.splatter.plans(batch, h, w, self.depth_centers)

    def forward(self, features: Tensor, batch: Batch) -> Lifted:
        """Lift ``(B, N, C_in, h, w)`` features into a ``(B, C, X, Y, Z)`` volume; see the class docstring."""
        _check_feature_size(features, batch, self.image_stride, "lss")
        logits, context = self.depth_net(features, batch)
        probs = logits.softmax(dim=2)  # (B, N, D, h, w)
        volume = self.splatter.splat_outer(probs, context, batch, self.depth_centers)
        return Lifted(
            volume=volume.contiguous(),
            grid=self.grid,
            depth_probs=probs,
            depth_bins=self.depth_centers,
            image_stride=self.image_stride,
        )


def build_depth_net(
    node: dict | DepthNet | None,
    in_channels: int,
    num_bins: int,
    out_channels: int,
    *,
    context: RunContext | None = None,
    **defaults: object,
) -> DepthNet:
    """A :class:`DepthNet` from a ``depth_net`` node (``None``: the plain depth net) or passed through.

    A node is built through the run ``context`` (:meth:`~occplug.context.RunContext.build`, which the view
    transform was handed); ``in_channels``, ``num_bins``, ``out_channels`` and ``defaults`` fill the parameters the
    node leaves out (where the registered factory accepts them). Without a node no context is needed: the plain
    depth net is built directly (a view transform constructed in Python, outside a run).

    Raises:
        ValueError: a node but no context, or a depth net whose bins / channels differ from the view transform's.
    """
    if isinstance(node, DepthNet):
        net = node
    elif node is None and context is None:
        hidden = defaults.get("hidden")
        net = PlainDepthNet(in_channels, num_bins, out_channels, **({} if hidden is None else {"hidden": hidden}))
    else:
        if context is None:
            raise ValueError(
                f"depth_net {node!r}: a depth_net node is built through the run context; build the view transform "
                "with the registry (RunContext.build) or pass a built DepthNet"
            )
        spec = {"type": "plain"} if node is None else node
        net = context.build(
            "depth_net", spec, in_channels=in_channels, num_bins=num_bins, out_channels=out_channels, **defaults
        )
    if net.num_bins != num_bins or net.out_channels != out_channels:
        raise ValueError(
            f"depth_net gives {net.num_bins} depth bins and {net.out_channels} context channels; "
            f"the view transform needs {num_bins} and {out_channels}"
        )
    return net


# ----------------------------------------------------------------------------- backward projection
class BackwardProjection(ViewTransform):
    """Backward projection: each voxel reads the image features where it projects.

    Every voxel holds ``points_per_voxel`` sample points, spread evenly along z inside it
    (at ``z_centre + ((m + 0.5) / points_per_voxel - 0.5) * dz``; one point = the voxel centre).
    Each point is projected through ``img_aug @ intrinsics`` into every camera and reads the
    projected image features there by bilinear interpolation on the feature map, using the
    cell <-> pixel map of the module docstring (a point projecting onto cell ``(r, c)``'s centre
    reads exactly that cell). A projection counts where its camera-frame depth lies in
    ``[start, stop)`` of ``depth_bins`` (the depth range LSS lifts to) and it falls inside the
    image (``-0.5 <= u < W - 0.5``, ``-0.5 <= v < H - 0.5``). A voxel's feature is the mean over
    its counted (camera, point) pairs; zero where none counts.

    Args:
        in_channels: ``C_in`` of the image features (the encoder's ``out_channels``).
        image_stride: pixels per feature cell (the encoder's ``stride``).
        grid: the output grid, a :class:`GridSpec` or ``{range, voxel_size}`` mapping.
        out_channels: ``C`` of the lifted volume.
        depth_bins: ``[start, stop, step]``, as for ``lss``; only the range ``[start, stop)`` is used.
        hidden: width of the per-cell net's 3x3 conv before the 1x1 projection to ``C``
            (0: the 1x1 projection alone).
        points_per_voxel: sample points per voxel along z (>= 1).

    Forward:
        ``features`` ``(B, N, C_in, h, w)`` and a batch with ``images`` (for ``H, W``),
        ``intrinsics``, ``cam_to_ego``, ``img_aug`` -> :class:`Lifted` with ``volume``
        ``(B, C, X, Y, Z)`` in the ego frame on ``grid``.
    """

    def __init__(
        self,
        in_channels: int,
        image_stride: int,
        grid: GridSpec,
        out_channels: Annotated[int, Positive] = 64,
        depth_bins: DepthBins = [1.0, 45.0, 1.0],  # noqa: B006 - read only, never mutated
        hidden: Annotated[int, NonNegative] = 64,
        points_per_voxel: Annotated[int, Positive] = 1,
    ) -> None:
        super().__init__()
        if points_per_voxel < 1:
            raise ValueError(f"backward_projection points_per_voxel must be >= 1, got {points_per_voxel}")
        depth_bin_centers(depth_bins)  # validates
        self.grid = grid
        self.image_stride = int(image_stride)
        self.out_channels = int(out_channels)
        self.depth_range = (float(depth_bins[0]), float(depth_bins[1]))
        self.points_per_voxel = int(points_per_voxel)
        self.image_net = PixelNet(in_channels, hidden, self.out_channels)
        self.register_buffer("points", self._sample_points(), persistent=False)

    def _sample_points(self) -> Tensor:
        """``(X*Y*Z*p, 3)`` float32 ego-frame sample points, voxel-major then point."""
        p = self.points_per_voxel
        offsets = torch.zeros(p, 3)
        offsets[:, 2] = ((torch.arange(p, dtype=torch.float32) + 0.5) / p - 0.5) * self.grid.voxel_size[2]
        return (self.grid.centers()[..., None, :] + offsets).reshape(-1, 3)

    def forward(self, features: Tensor, batch: Batch) -> Lifted:
        """Lift ``(B, N, C_in, h, w)`` features into a ``(B, C, X, Y, Z)`` volume; see the class docstring."""
        _check_feature_size(features, batch, self.image_stride, "backward_projection")
        b, n, _, h, w = features.shape
        s, c = self.image_stride, self.out_channels
        big_h, big_w = batch.images.shape[-2:]
        feats = self.image_net(features.flatten(0, 1))  # (B*N, C, h, w)
        with _no_autocast(feats.device):
            q = self.points.shape[0]
            uv, depth = project_to_image(
                self.points.view(1, 1, q, 3).expand(b, n, q, 3),
                batch.intrinsics.float(),
                batch.cam_to_ego.float(),
                batch.img_aug.float(),
            )  # (B, N, Q, 2), (B, N, Q)
            u, v = uv.unbind(-1)
            valid = (
                (depth >= self.depth_range[0])
                & (depth < self.depth_range[1])
                & (u >= -0.5)
                & (u < big_w - 0.5)
                & (v >= -0.5)
                & (v < big_h - 0.5)
            )
            # Pixel (u, v) -> grid_sample coordinates of the h x w feature map (align_corners=False):
            # fractional cell c = (u - (s-1)/2) / s sits at (2c + 1) / w - 1 = (2u + 1) / (s*w) - 1.
            norm = torch.stack([(2 * u + 1) / (s * w) - 1, (2 * v + 1) / (s * h) - 1], dim=-1)
            norm = torch.where(valid[..., None], norm, torch.zeros_like(norm))
        # Sampled in float32: bf16 sampling coordinates would be off by a fraction of a cell.
        sampled = F.grid_sample(
            feats.float(), norm.view(b * n, q, 1, 2), mode="bilinear", padding_mode="border", align_corners=False
        )  # (B*N, C, Q, 1)
        p = self.points_per_voxel
        sampled = sampled.view(b, n, c, q // p, p)
        weight = valid.view(b, n, 1, q // p, p).to(sampled.dtype)
        total = (sampled * weight).sum(dim=(1, 4))  # (B, C, X*Y*Z)
        count = weight.sum(dim=(1, 4)).clamp_min(1.0)
        volume = (total / count).view(b, c, *self.grid.shape)
        return Lifted(volume=volume, grid=self.grid)
