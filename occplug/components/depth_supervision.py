"""Supervision source ``lidar_depth``: BEVDepth's depth loss from LiDAR points projected into the cameras."""

from __future__ import annotations

from typing import Annotated

import torch
import torch.nn.functional as F
from torch import Tensor

from occplug.constraints import NonNegative
from occplug.data.frame import Batch
from occplug.geometry import project_to_image, transform_points
from occplug.interfaces import ModelOutputs, SupervisionSource

__all__ = ["LidarDepthSupervision", "lidar_depth_targets"]


def _bin_edges(centers: Tensor) -> Tensor:
    """``(D + 1,)`` edges of bins given by their centres (midpoints inside, half a step outside)."""
    mid = (centers[1:] + centers[:-1]) / 2
    first = centers[:1] - (mid[:1] - centers[:1]) if centers.numel() > 1 else centers[:1] - 0.5
    last = centers[-1:] + (centers[-1:] - mid[-1:]) if centers.numel() > 1 else centers[-1:] + 0.5
    return torch.cat([first, mid, last])


def lidar_depth_targets(batch: Batch, feature_hw: tuple[int, int], stride: int, centers: Tensor) -> Tensor:
    """Per feature cell, the depth bin of the nearest LiDAR return, as BEVDepth builds its labels.

    Each LiDAR point (``batch.points`` in the LiDAR frame, through ``lidar_to_ego``) is projected
    into every camera through ``img_aug @ intrinsics`` and ``cam_to_ego``; a point in front of a
    camera lands on pixel ``[round(v), round(u)]`` (pixel centres at integer ``u, v``), i.e. on
    feature cell ``(row // stride, col // stride)``. A cell keeps the smallest camera-frame depth
    of its points (BEVDepth's ``get_downsampled_gt_depth``) and that depth's bin: bin ``d`` spans
    half-way to its neighbours' centres (``[start + d*step, start + (d+1)*step)`` for the uniform
    bins of ``depth_bins``). Cells without a point, or whose depth lies outside the bins, get -1.

    Args:
        batch: ``points`` (list of ``(P, >=3)``), ``lidar_to_ego`` ``(B, 4, 4)``, ``intrinsics``,
            ``cam_to_ego``, ``img_aug`` and ``images`` (for the image size).
        feature_hw: ``(h, w)`` of the depth distribution's feature map.
        stride: image pixels per feature cell.
        centers: ``(D,)`` depth bin centres, metres (ascending).

    Returns:
        ``(B, N, h, w)`` int64 bin index, -1 where there is no target.
    """
    batch.require("points", "lidar_to_ego", by="lidar_depth")
    b, n = batch.cam_to_ego.shape[:2]
    h, w = feature_hw
    big_h, big_w = batch.images.shape[-2:]
    edges = _bin_edges(centers.double())
    out = torch.full((b, n * h * w), -1, dtype=torch.int64, device=batch.cam_to_ego.device)
    for i in range(b):
        xyz = batch.points[i][:, :3].to(batch.cam_to_ego.device, torch.float32)
        ego = transform_points(batch.lidar_to_ego[i].float(), xyz)
        uv, depth = project_to_image(
            ego.expand(n, -1, 3), batch.intrinsics[i].float(), batch.cam_to_ego[i].float(), batch.img_aug[i].float()
        )  # (N, P, 2), (N, P)
        col = torch.floor(uv[..., 0] + 0.5).long()
        row = torch.floor(uv[..., 1] + 0.5).long()
        r, c = row.div(stride, rounding_mode="floor"), col.div(stride, rounding_mode="floor")
        ok = (depth > 1e-3) & (col >= 0) & (col < big_w) & (row >= 0) & (row < big_h) & (r < h) & (c < w)
        cam = torch.arange(n, device=ok.device).view(n, 1).expand_as(ok)
        cell = (cam * h + r) * w + c
        nearest = torch.full((n * h * w,), float("inf"), dtype=torch.float64, device=ok.device)
        nearest.scatter_reduce_(0, cell[ok], depth[ok].double(), reduce="amin")
        hit = torch.isfinite(nearest) & (nearest >= edges[0]) & (nearest < edges[-1])
        bins = (torch.bucketize(nearest.clamp(edges[0].item(), edges[-1].item()), edges, right=True) - 1).clamp(
            0, len(centers) - 1
        )
        out[i] = torch.where(hit, bins, torch.full_like(bins, -1))
    return out.view(b, n, h, w)


class LidarDepthSupervision(SupervisionSource):
    """BEVDepth's depth loss (Li et al., AAAI 2023), as DuOcc uses it for its view transform.

    Targets come from :func:`lidar_depth_targets` (the nearest LiDAR return per feature cell, as a
    depth bin). The loss is BEVDepth's ``get_depth_loss``: binary cross-entropy between the view
    transform's per-cell depth distribution (``lifted.depth_probs``, a softmax over ``D`` bins)
    and the one-hot target, summed over the ``D`` bins and averaged over the cells that have a
    target (``max(1, count)``). BEVDepth scales it by ``depth_loss_factor = 3.0``: set
    ``weight: 3.0`` to match.

    Args:
        weight: scale applied by the model to the returned loss.

    Needs: a view transform that returns ``depth_probs`` and ``depth_bins`` (``lss``); batch
    fields ``points`` and ``lidar_to_ego`` (it declares ``requires = {"points"}``, so the data
    module loads LiDAR files for it).

    Returns:
        ``{"depth": scalar loss}`` (unweighted).
    """

    requires = frozenset({"points"})

    def __init__(self, weight: Annotated[float, NonNegative] = 1.0) -> None:
        super().__init__()
        self.weight = float(weight)

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        """``{"depth": loss}``; see the class docstring."""
        lifted = outputs.lifted
        if lifted.depth_probs is None or lifted.depth_bins is None or lifted.image_stride is None:
            raise ValueError("lidar_depth needs a view transform that predicts depth distributions (e.g. lss)")
        probs = lifted.depth_probs.float()  # (B, N, D, h, w)
        target = lidar_depth_targets(batch, tuple(probs.shape[-2:]), lifted.image_stride, lifted.depth_bins)
        has = target >= 0
        probs = probs.permute(0, 1, 3, 4, 2)[has]  # (M, D)
        onehot = F.one_hot(target[has], probs.shape[-1]).to(probs.dtype)
        loss = F.binary_cross_entropy(probs.clamp(0.0, 1.0), onehot, reduction="sum") / max(1, int(has.sum()))
        if not has.any():  # keep the graph so every rank reaches the same backward
            loss = loss + 0.0 * lifted.depth_probs.sum()
        return {"depth": loss}
