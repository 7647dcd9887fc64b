"""Labelled point clouds with their sensor origins, from a batch's LiDAR or its pseudo depth maps.

Sources that supervise along sensor rays (free space between a sensor and what it saw, occupied
space at and just behind the return) need, per sample, every point with the position it was seen
from, its class and optionally a feature vector. Two ways to get them from a :class:`~occplug.data.Batch`:

* :func:`pseudo_depth_points`: the pixels of ``pseudo_depth`` (an external depth model's map, 0 = none)
  unprojected through ``img_aug @ intrinsics`` and ``cam_to_ego``, seen from the camera centre,
  labelled by ``pseudo_semantics`` at the same pixel and, optionally, ``pseudo_features`` at the
  feature cell holding the pixel;
* :func:`lidar_points`: the LiDAR returns, seen from the LiDAR origin, labelled by projecting each
  into the cameras' ``pseudo_semantics`` (the first camera, in rig order, whose image holds it in
  front of the camera; ``ignore_label`` where none does) -- or by ``point_labels`` when asked.

and one way to get the rays that end at no surface:

* :func:`free_pixel_rays`: the pixels whose ``pseudo_semantics`` is the free class (a segmenter's ``sky``
  mapped to ``free``): rays free of surfaces as far as the camera sees, with no depth of their own.

Everything is in the ego frame of the batch the points come from; :func:`to_frame` moves a set
into another frame of the same scene through the global poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from occplug.geometry import invert_pose, project_to_image, transform_points, unproject_from_image

__all__ = ["LabelledPoints", "free_pixel_rays", "lidar_points", "pseudo_depth_points", "to_frame"]


@dataclass
class LabelledPoints:
    """One sample's labelled points.

    Attributes:
        points: ``(P, 3)`` float32 ego frame, metres.
        origins: ``(P, 3)`` float32 the sensor position each point was seen from (same frame).
        labels: ``(P,)`` int64 class ids (``ignore_label`` where unknown).
        features: ``(P, F)`` float32 feature vectors, or ``None``.
    """

    points: Tensor
    origins: Tensor
    labels: Tensor
    features: Tensor | None = None

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def select(self, index: Tensor) -> LabelledPoints:
        """The points at ``index`` (a ``(P,)`` bool mask or an int64 index)."""
        feats = None if self.features is None else self.features[index]
        return LabelledPoints(self.points[index], self.origins[index], self.labels[index], feats)

    @staticmethod
    def cat(parts: list[LabelledPoints]) -> LabelledPoints:
        """Concatenate sets (features kept only when every part has them)."""
        feats = [p.features for p in parts]
        return LabelledPoints(
            torch.cat([p.points for p in parts]),
            torch.cat([p.origins for p in parts]),
            torch.cat([p.labels for p in parts]),
            None if any(f is None for f in feats) else torch.cat(feats),  # type: ignore[arg-type]
        )


def _strided_pixels(h: int, w: int, stride: int, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
    """Every ``stride``-th row and column of an ``(h, w)`` image, and their ``(Q, 2)`` float32 pixel centres
    ``(u, v) = (col, row)`` in row-major order."""
    rows = torch.arange(0, h, stride, device=device)
    cols = torch.arange(0, w, stride, device=device)
    vv, uu = torch.meshgrid(rows, cols, indexing="ij")
    return rows, cols, torch.stack([uu, vv], -1).reshape(-1, 2).to(torch.float32)


def pseudo_depth_points(
    batch, stride: int = 1, max_depth: float = float("inf"), ignore_label: int = 255, with_features: bool = False
) -> list[LabelledPoints]:
    """Every ``stride``-th pixel (rows and columns) with a pseudo depth in ``(0, max_depth]``, per sample.

    Args:
        batch: with ``pseudo_depth`` ``(B, N, H, W)`` (camera-frame z, 0 = none), ``pseudo_semantics``
            ``(B, N, H, W)`` (or ``None``: every label ``ignore_label``), ``intrinsics``, ``cam_to_ego``,
            ``img_aug``, and ``pseudo_features`` ``(B, N, F, h, w)`` when ``with_features``.
        stride: pixel subsampling (pixel centres ``(stride*c, stride*r)``).
        max_depth: drop pixels deeper than this (metres, camera z).
        ignore_label: label of pixels without a pseudo class.
        with_features: attach the feature of the cell ``(v * h // H, u * w // W)`` holding each pixel.

    Returns:
        ``B`` :class:`LabelledPoints` in the ego frame; origins are the camera centres.
    """
    depth = batch.pseudo_depth
    if depth is None:
        raise ValueError("pseudo_depth_points: the batch has no pseudo_depth (set data.pseudo_labels)")
    b, n, h, w = depth.shape
    rows, cols, uv = _strided_pixels(h, w, stride, depth.device)
    z = depth[:, :, rows][:, :, :, cols].reshape(b, n, -1)  # (B, N, Q)
    ego = unproject_from_image(
        uv.expand(b, n, -1, 2), z, batch.intrinsics.float(), batch.cam_to_ego.float(), batch.img_aug.float()
    )  # (B, N, Q, 3)
    sem = batch.pseudo_semantics
    feats = batch.pseudo_features if with_features else None
    if with_features and feats is None:
        raise ValueError("pseudo_depth_points: with_features needs pseudo_features in the batch")
    out = []
    for i in range(b):
        keep = (z[i] > 0) & (z[i] <= max_depth)  # (N, Q)
        cam, q = torch.nonzero(keep, as_tuple=True)
        points = ego[i][cam, q]
        origins = batch.cam_to_ego[i, :, :3, 3].float()[cam]
        pix = uv[q].long()
        if sem is None:
            labels = torch.full((len(q),), ignore_label, dtype=torch.int64, device=depth.device)
        else:
            labels = sem[i][cam, pix[:, 1], pix[:, 0]].long()
        f = None
        if feats is not None:
            fh, fw = feats.shape[-2:]
            f = feats[i][cam, :, pix[:, 1] * fh // h, pix[:, 0] * fw // w].float()
        out.append(LabelledPoints(points.float(), origins, labels, f))
    return out


def free_pixel_rays(batch, free_label: int, stride: int = 1) -> list[LabelledPoints]:
    """The rays of every ``stride``-th pixel (rows and columns) whose pseudo class is ``free_label``, per sample.

    A pixel a segmenter calls sky (mapped to the free class) sees no surface: its ray is free as far as the
    camera sees, whatever depth a depth model gives it. Each ray is returned as a labelled point one metre
    along it, so ``points - origins`` is its unit direction and :func:`to_frame` moves rays as it moves points.

    Args:
        batch: with ``pseudo_semantics`` ``(B, N, H, W)``, ``intrinsics``, ``cam_to_ego`` and ``img_aug``.
        free_label: the free class id (Occ3D ``free`` = 17).
        stride: pixel subsampling (pixel centres ``(stride*c, stride*r)``).

    Returns:
        ``B`` :class:`LabelledPoints` in the ego frame: ``points`` one metre along each ray, ``origins``
        the camera centres, ``labels`` all ``free_label``.
    """
    sem = batch.pseudo_semantics
    if sem is None:
        raise ValueError("free_pixel_rays: the batch has no pseudo_semantics (set data.pseudo_labels)")
    b, n, h, w = sem.shape
    rows, cols, uv = _strided_pixels(h, w, stride, sem.device)
    cam_z = torch.ones(b, n, uv.shape[0], device=sem.device)
    ego = unproject_from_image(
        uv.expand(b, n, -1, 2), cam_z, batch.intrinsics.float(), batch.cam_to_ego.float(), batch.img_aug.float()
    )  # (B, N, Q, 3): the point at camera depth 1 on each pixel's ray
    centres = batch.cam_to_ego[:, :, :3, 3].float()  # (B, N, 3)
    unit = ego - centres[:, :, None]
    unit = unit / unit.norm(dim=-1, keepdim=True)
    free = sem[:, :, rows][:, :, :, cols].reshape(b, n, -1) == free_label  # (B, N, Q)
    out = []
    for i in range(b):
        cam, q = torch.nonzero(free[i], as_tuple=True)
        origins = centres[i][cam]
        labels = torch.full((len(q),), free_label, dtype=torch.int64, device=sem.device)
        out.append(LabelledPoints(origins + unit[i][cam, q], origins, labels))
    return out


def lidar_points(batch, ignore_label: int = 255, labels_from: str = "pseudo_semantics") -> list[LabelledPoints]:
    """The LiDAR returns of every sample in the ego frame, seen from the LiDAR origin.

    Args:
        batch: with ``points`` (a list of ``(P_b, 4)`` lidar-frame points), ``lidar_to_ego`` ``(B, 4, 4)``
            and, for ``labels_from="pseudo_semantics"``, the camera geometry and ``pseudo_semantics``.
        ignore_label: label of points no camera sees (or without a pseudo class).
        labels_from: ``pseudo_semantics`` (projected into the cameras' 2D pseudo labels) or
            ``point_labels`` (the data set's own point labels, for reference runs).
    """
    if batch.points is None or batch.lidar_to_ego is None:
        raise ValueError("lidar_points: the batch has no LiDAR points")
    if labels_from not in ("pseudo_semantics", "point_labels"):
        raise ValueError(f"lidar_points: labels_from must be 'pseudo_semantics' or 'point_labels', got {labels_from!r}")
    out = []
    for i, pts in enumerate(batch.points):
        to_ego = batch.lidar_to_ego[i].float()
        ego = transform_points(to_ego, pts[:, :3].float())
        origins = to_ego[:3, 3].expand_as(ego)
        if labels_from == "point_labels":
            if batch.point_labels is None:
                raise ValueError("lidar_points: labels_from='point_labels' but the batch has no point_labels")
            labels = batch.point_labels[i].long()
        else:
            labels = _project_labels(batch, i, ego, ignore_label)
        out.append(LabelledPoints(ego, origins, labels))
    return out


def _project_labels(batch, i: int, ego: Tensor, ignore_label: int) -> Tensor:
    """``(P,)`` the pseudo class at each point's pixel in the first camera whose image holds it."""
    labels = torch.full((ego.shape[0],), ignore_label, dtype=torch.int64, device=ego.device)
    sem = batch.pseudo_semantics
    if sem is None:
        return labels
    n, h, w = sem.shape[1:]
    uv, depth = project_to_image(
        ego.expand(n, -1, 3), batch.intrinsics[i].float(), batch.cam_to_ego[i].float(), batch.img_aug[i].float()
    )  # (N, P, 2), (N, P)
    col, row = uv[..., 0].round().long(), uv[..., 1].round().long()
    inside = (depth > 1e-3) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    done = torch.zeros_like(labels, dtype=torch.bool)
    for cam in range(n):
        take = inside[cam] & ~done
        labels[take] = sem[i, cam, row[cam, take], col[cam, take]].long()
        done |= take
    return labels


def to_frame(points: LabelledPoints, src_ego_to_global: Tensor, dst_ego_to_global: Tensor) -> LabelledPoints:
    """Move a set from one ego frame into another of the same scene (``(4, 4)`` float64 poses)."""
    src_to_dst = (invert_pose(dst_ego_to_global.double()) @ src_ego_to_global.double()).float()
    return LabelledPoints(
        transform_points(src_to_dst, points.points),
        transform_points(src_to_dst, points.origins),
        points.labels,
        points.features,
    )
