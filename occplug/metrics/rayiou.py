"""RayIoU: the ray-based occupancy metric of SparseOcc, used by the Occ3D-nuScenes leaderboard.

Definition followed
-------------------
SparseOcc (Liu et al., "Fully Sparse 3D Occupancy Prediction", ECCV 2024), reference code
``ray_metrics.py`` / ``ego_pose_dataset.py`` of github.com/MCG-NJU/SparseOcc, which the Occ3D-nuScenes
leaderboard and the CVPR 2024 occupancy challenge use:

1. **Query rays** emulate a LiDAR: pitch angles ``-(pi/2 - atan(k + 1))`` for ``k = 0..9``, continued
   with the last spacing while the pitch is below 0.21 rad (39 pitches, -0.785..0.219 rad), times
   azimuths 0..359 degrees in 1 degree steps: 14,040 directions (:func:`query_ray_directions`).
2. **Origins**: the LiDAR positions of the frames of the sample's sequence, in the sample's ego
   frame, keeping those with ``|x| < 39`` and ``|y| < 39`` m; when more than 8 remain, the 8 at
   ``round(linspace(0, n - 1, 8))`` (:func:`select_origins`).
3. Each ray is cast through the predicted and the ground-truth grid (occupied = label != free) and
   stops at the first occupied voxel, giving that voxel's class and the ray's **depth**. A ray that
   leaves the grid without a hit has class ``free``.
4. Only rays whose ground-truth class is not ``free`` are evaluated. Over the whole data set, per
   class ``c`` and threshold ``tau``: ``N_gt(c)`` rays with ground-truth class ``c``, ``N_pred(c)``
   evaluated rays with predicted class ``c``, ``TP(c, tau)`` rays with both classes ``c`` and
   ``|d_pred - d_gt| < tau``; ``IoU(c, tau) = TP / (N_gt + N_pred - TP)``.
5. ``RayIoU@tau`` is the mean over the non-free classes for ``tau`` in 1, 2, 4 m, skipping classes
   absent from both (NaN-mean, as the reference's ``np.nanmean``); ``RayIoU`` is the mean of the
   three.

Beyond the reference
--------------------
Summaries that the reference code does not print, for methods that report them (e.g. QueryOcc's
table "Sem. RayIoU, Dyn. RayIoU, Occ. RayIoU"):

* ``RayIoU_dynamic`` / ``RayIoU_static``: the same NaN-mean as ``RayIoU`` over the dynamic / static
  class groups only (:func:`occplug.metrics.base.group_class_ids`, as ``occ3d_miou``'s ``mIoU_dynamic``).
* ``RayIoU_geometry`` (QueryOcc's "Occ. RayIoU"): the **class-agnostic** RayIoU. Every non-free
  label (an ignore label too) is one "occupied" class; the evaluated rays are the same (ground-truth
  class not free), ``N_gt`` is their number, ``N_pred`` the number of them whose predicted ray hits
  something, ``TP(tau)`` those that hit with ``|d_pred - d_gt| < tau`` whatever the two classes;
  ``IoU(tau) = TP / (N_gt + N_pred - TP)``, averaged over the thresholds. A prediction with the right
  depths and wrong classes scores 100 here and 0 in ``RayIoU``.
* ``<key>_excl`` with ``exclude_classes``: ``RayIoU``, ``RayIoU_dynamic`` and ``RayIoU_static`` again
  without the named classes (e.g. those a pseudo-label taxonomy cannot express). The per-threshold
  and class-agnostic keys have no ``_excl`` variant.

Details where this follows the reference code rather than a plain reading of the definition:

* **Depth** is the distance at which the ray *leaves* the first occupied voxel (its far face), not
  where it enters it: the reference's DVR kernel records the distance to the boundary crossed when
  stepping out of each voxel and reports that of the first occupied one. Depths are in metres,
  measured from the origin.
* **Range**: rays have no maximum range; they run until they hit or leave the grid (the reference's
  1 m "end point" only fixes the direction).
* **Voxel size**: the reference casts in voxel units and multiplies the depth by the (cubic) voxel
  size; this casts in metres, which is identical for cubic voxels and the natural extension to
  anisotropic ones. The grid's voxel size therefore changes only the voxelisation, never the rays.
* **Labels other than free are occupied**, an ignore label (255) too, as in the reference; a
  ground-truth ray stopping at such a voxel is evaluated but counts for no class.
* **Predicted ids outside the taxonomy** (anything but ``0..K-1``, e.g. 255 or a negative id) are scored
  as the reference scores them: the voxel is occupied (it stops the predicted ray and counts for the
  class-agnostic ``RayIoU_geometry``) and the ray has no class (it is in no class's ``N_pred`` and no
  true positive). A prediction that sets every car voxel to 255 therefore loses the car class only.
  This differs on purpose from ``occ3d_miou`` and ``ssc``, which refuse such ids
  (:func:`~occplug.metrics.base.check_class_ids`).
* The reference reports fractions; values here are in **percent**, like the other occplug metrics.

Known, negligible differences: the reference rounds directions and origins to float32 and, when a
ray crosses a voxel edge or corner exactly, steps one axis at a time; this casts in float64 with
the exact traversal of :mod:`occplug.geometry.raycast` (ties step diagonally). Results differ only for
rays passing within about 1e-7 voxel of an edge.

**No sequence origins**: when a batch lacks ``sequence_lidar_origins``, the single origin is the
current LiDAR position (``lidar_to_ego[:3, 3]``), or the ego origin when the batch has no LiDAR
either. No evaluation mask is applied: RayIoU evaluates the full ground-truth grid, as the reference
does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Annotated, Literal, NamedTuple

import numpy as np
import torch
from torch import Tensor

from occplug.constraints import Length, NonNegative, Positive
from occplug.data.frame import Batch
from occplug.data.nuscenes.format import OCC3D_GRID
from occplug.geometry import GridSpec
from occplug.geometry.raycast import first_hits

from .base import OccMetric, excluded_class_ids, group_class_ids

#: The ray walks RayIoU can cast with (see :func:`~occplug.geometry.raycast.first_hits`).
RayKernel = Literal["auto", "torch", "numba"]

__all__ = [
    "QueryRays",
    "RayIoU",
    "cast_query_rays",
    "geometry_counts",
    "iou_from_counts",
    "query_ray_directions",
    "rayiou_counts",
    "select_origins",
]


def query_ray_directions(dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> Tensor:
    """The SparseOcc query-ray directions, pitch-major.

    Returns:
        ``(P * 360, 3)`` unit vectors (x forward, y left, z up): row ``p * 360 + a`` has pitch
        ``pitch[p]`` and azimuth ``a`` degrees (counter-clockwise from +x); ``P = 39``.
    """
    pitches = [-(math.pi / 2 - math.atan(k + 1)) for k in range(10)]
    while pitches[-1] < 0.21:
        pitches.append(pitches[-1] + (pitches[-1] - pitches[-2]))
    pitch = torch.tensor(pitches, dtype=torch.float64)[:, None]
    azimuth = torch.deg2rad(torch.arange(360, dtype=torch.float64))[None, :]
    xyz = torch.stack([pitch.cos() * azimuth.cos(), pitch.cos() * azimuth.sin(), pitch.sin().expand(-1, 360)], dim=-1)
    return xyz.reshape(-1, 3).to(dtype=dtype, device=device)


def select_origins(origins: Tensor, limit: float = 39.0, max_origins: int = 8) -> Tensor:
    """The query-ray origins of one sample, as SparseOcc's ``EgoPoseDataset`` picks them.

    Args:
        origins: ``(S, 3)`` LiDAR positions of the sequence's frames in the sample's ego frame, metres.
        limit: keep origins with ``|x| < limit`` and ``|y| < limit`` (39 m: 1 m inside Occ3D's grid).
        max_origins: when more remain, keep those at ``round(linspace(0, n - 1, max_origins))``
            (numpy's rounding, half to even), in sequence order.

    Returns:
        ``(T, 3)`` float64, ``T <= max_origins`` (may be 0).
    """
    origins = origins.to(torch.float64).reshape(-1, 3)
    kept = origins[(origins[:, 0].abs() < limit) & (origins[:, 1].abs() < limit)]
    if kept.shape[0] > max_origins:
        pick = np.round(np.linspace(0, kept.shape[0] - 1, max_origins)).astype(np.int64)
        kept = kept[torch.from_numpy(pick).to(kept.device)]
    return kept


class QueryRays(NamedTuple):
    """Per-ray results of :func:`cast_query_rays` (``R = T * D`` rays, origin-major).

    Attributes:
        gt_class, pred_class: ``(R,)`` int64 class of the first occupied voxel (``free_label``
            without a hit).
        gt_depth, pred_depth: ``(R,)`` float64 depth in metres (``inf`` without a hit).
    """

    gt_class: Tensor
    gt_depth: Tensor
    pred_class: Tensor
    pred_depth: Tensor


def cast_query_rays(
    pred: Tensor,
    gt: Tensor,
    grid: GridSpec,
    origins: Tensor,
    free_label: int,
    directions: Tensor | None = None,
    kernel: RayKernel = "auto",
) -> QueryRays:
    """Cast every query ray from every origin through a prediction and its ground truth.

    Both grids are walked in one pass (:func:`~occplug.geometry.raycast.first_hits`).

    Args:
        pred, gt: ``(X, Y, Z)`` integer class ids on ``grid`` (ego frame).
        grid: the voxel grid.
        origins: ``(T, 3)`` ray origins in the ego frame, metres.
        free_label: the id of empty space; every other id is occupied.
        directions: ``(D, 3)`` unit directions; default :func:`query_ray_directions`.
        kernel: the ray walk (:func:`~occplug.geometry.raycast.first_hits`): ``auto``, ``torch`` (the
            pure-PyTorch reference) or ``numba`` (compiled, CPU, the same results bit for bit).

    Returns:
        :class:`QueryRays` with the class of the first occupied voxel of each ray and the depth at
        which the ray leaves it (see the module docstring).
    """
    device = gt.device
    if directions is None:
        directions = query_ray_directions(device=device)
    directions = directions.to(device=device, dtype=torch.float64)
    origins = origins.to(device=device, dtype=torch.float64)
    o = origins[:, None, :].expand(-1, directions.shape[0], 3).reshape(-1, 3)
    d = directions.expand(origins.shape[0], -1, -1).reshape(-1, 3)
    labels = torch.stack([pred.to(device), gt]).reshape(2, -1).long()
    hits = first_hits((labels != free_label).reshape(2, *grid.shape), grid, o, d, math.inf, kernel=kernel)
    strides = torch.tensor([grid.shape[1] * grid.shape[2], grid.shape[2], 1], device=device)
    found = hits.index[..., 0] >= 0
    flat = (hits.index.clamp_min(0) * strides).sum(-1)
    cls = torch.where(found, labels.gather(1, flat), free_label)
    depth = hits.exit
    return QueryRays(cls[1], depth[1], cls[0], depth[0])


def rayiou_counts(
    rays: QueryRays, num_classes: int, free_label: int, thresholds: Sequence[float]
) -> tuple[Tensor, Tensor, Tensor]:
    """Sum-reducible counts of one set of rays.

    Returns:
        ``gt_count`` ``(K,)``, ``pred_count`` ``(K,)`` and ``tp`` ``(len(thresholds), K)`` int64 over the
        rays whose ground-truth class is not free; classes outside ``[0, K)`` are not counted.
    """
    keep = rays.gt_class != free_label
    gt_class, pred_class = rays.gt_class[keep], rays.pred_class[keep]
    error = (rays.pred_depth[keep] - rays.gt_depth[keep]).abs()

    def count(classes: Tensor) -> Tensor:
        classes = classes[(classes >= 0) & (classes < num_classes)]
        return torch.bincount(classes, minlength=num_classes)

    same = gt_class == pred_class
    tp = torch.stack([count(gt_class[same & (error < tau)]) for tau in thresholds])
    return count(gt_class), count(pred_class), tp


def geometry_counts(rays: QueryRays, free_label: int, thresholds: Sequence[float]) -> tuple[Tensor, Tensor, Tensor]:
    """Sum-reducible counts of the class-agnostic RayIoU (every non-free class is "occupied").

    Returns:
        ``gt_count`` ``()`` evaluated rays (ground-truth class not free), ``pred_count`` ``()`` those
        whose predicted ray hits an occupied voxel and ``tp`` ``(len(thresholds),)`` those that hit
        within ``tau`` of the ground-truth depth, whatever the classes; int64.
    """
    keep = rays.gt_class != free_label
    hit = rays.pred_class[keep] != free_label
    error = (rays.pred_depth[keep] - rays.gt_depth[keep]).abs()
    tp = torch.stack([(hit & (error < tau)).sum() for tau in thresholds])
    return keep.sum(), hit.sum(), tp


def iou_from_counts(gt_count: Tensor, pred_count: Tensor, tp: Tensor) -> Tensor:
    """``(T, K)`` float64 ``TP / (N_gt + N_pred - TP)`` per threshold and class; NaN where a class
    has no ground-truth and no predicted ray (the reference's 0 / 0). Broadcasts: ``()`` counts and
    ``(T,)`` true positives give the ``(T,)`` IoU of one class."""
    tp = tp.to(torch.float64)
    denom = gt_count.to(torch.float64) + pred_count.to(torch.float64) - tp
    return torch.where(denom > 0, tp / denom.clamp_min(1), torch.full_like(tp, math.nan))


class RayIoU(OccMetric):
    """RayIoU as SparseOcc and the Occ3D-nuScenes leaderboard define it (see the module docstring).

    ``compute()`` returns ``RayIoU``, ``RayIoU_<tau>m`` (``RayIoU_1m``, ``RayIoU_2m``, ``RayIoU_4m``),
    ``RayIoU_<class>`` (the class's IoU averaged over the thresholds), ``RayIoU_geometry`` (class-agnostic),
    ``RayIoU_dynamic`` / ``RayIoU_static`` where the class groups are known and, with ``exclude_classes``,
    ``RayIoU_excl`` / ``RayIoU_dynamic_excl`` / ``RayIoU_static_excl``; in percent (see the module
    docstring). States are the counts ``gt_count`` ``(K,)``, ``pred_count`` ``(K,)``, ``tp``
    ``(len(thresholds), K)`` and their class-agnostic ``geo_gt_count`` ``()``, ``geo_pred_count`` ``()``,
    ``geo_tp`` ``(len(thresholds),)``, summed over ranks.

    ``update(pred, batch)`` reads ``batch.voxel_labels`` and the origins from
    ``batch.sequence_lidar_origins`` (else ``batch.lidar_to_ego``, else the ego origin); predicted ids
    outside ``0..K-1`` are occupied with no class (module docstring); non-finite origins raise
    ``ValueError``.

    Args:
        num_classes: ``K``, ids ``0..K-1`` including ``free_label``.
        class_names: names for the per-class keys (defaults to ``class_<id>``).
        free_label: the id of empty space (Occ3D: 17).
        ignore_label: accepted for interface uniformity; such voxels count as occupied (reference).
        grid: the evaluation grid ``{range, voxel_size}`` (the runner fills it from the config's
            top-level ``grid``); ``None`` assumes Occ3D's grid and requires labels of its shape.
        thresholds: depth-error thresholds, metres.
        origin_limit: origins with ``|x|`` or ``|y|`` not below this (metres) are dropped.
        max_origins: at most this many origins per sample.
        dynamic_classes, static_classes: class names of the two groups, replacing the taxonomy's
            (both or neither; as ``occ3d_miou``).
        exclude_classes: semantic class names the ``*_excl`` keys leave out (none: no such keys).
        kernel: the ray walk: ``auto`` (the compiled one for CPU tensors when numba is installed, else
            the pure-PyTorch one), ``torch`` or ``numba``; the scores do not depend on it.
    """

    def __init__(
        self,
        num_classes: Annotated[int, Positive] = 18,
        class_names: Sequence[str] | None = None,
        free_label: Annotated[int, NonNegative] = 17,
        ignore_label: int | None = 255,
        grid: GridSpec | None = None,
        thresholds: Annotated[Sequence[Annotated[float, Positive]], Length(min=1)] = (1.0, 2.0, 4.0),
        origin_limit: Annotated[float, Positive] = 39.0,
        max_origins: Annotated[int, Positive] = 8,
        dynamic_classes: Sequence[str] | None = None,
        static_classes: Sequence[str] | None = None,
        exclude_classes: Sequence[str] = (),
        kernel: RayKernel = "auto",
    ) -> None:
        super().__init__()
        self.kernel = kernel
        self.num_classes = num_classes
        self.class_names = list(class_names) if class_names else [f"class_{i}" for i in range(num_classes)]
        if len(self.class_names) != num_classes:
            raise ValueError(f"class_names has {len(self.class_names)} names for {num_classes} classes")
        if not thresholds or min(thresholds) <= 0:
            raise ValueError(f"rayiou thresholds must be positive distances in metres, got {list(thresholds)}")
        self.free_label = free_label
        self.grid = grid
        self.thresholds = tuple(float(t) for t in thresholds)
        self.origin_limit = float(origin_limit)
        self.max_origins = int(max_origins)
        self.groups = group_class_ids(self.class_names, dynamic_classes, static_classes, "rayiou")
        self.excluded = excluded_class_ids(self.class_names, exclude_classes, free_label, "rayiou")
        summaries = {f"{t:g}m" for t in self.thresholds} | {"geometry", "excl", *self.groups}
        summaries |= {f"{g}_excl" for g in self.groups}
        clash = [n for c, n in enumerate(self.class_names) if c != free_label and n in summaries]
        if clash:
            raise ValueError(f"rayiou: class '{clash[0]}' would share its key RayIoU_{clash[0]} with a summary")
        self._directions: Tensor | None = None
        self.add_state("gt_count", torch.zeros(num_classes, dtype=torch.int64), dist_reduce_fx="sum")
        self.add_state("pred_count", torch.zeros(num_classes, dtype=torch.int64), dist_reduce_fx="sum")
        self.add_state("tp", torch.zeros(len(self.thresholds), num_classes, dtype=torch.int64), dist_reduce_fx="sum")
        self.add_state("geo_gt_count", torch.zeros((), dtype=torch.int64), dist_reduce_fx="sum")
        self.add_state("geo_pred_count", torch.zeros((), dtype=torch.int64), dist_reduce_fx="sum")
        self.add_state("geo_tp", torch.zeros(len(self.thresholds), dtype=torch.int64), dist_reduce_fx="sum")
        # how many origins were cast from, over how many samples (the table reports the mean)
        self.add_state("origins_used", torch.zeros((), dtype=torch.int64), dist_reduce_fx="sum")
        self.add_state("samples", torch.zeros((), dtype=torch.int64), dist_reduce_fx="sum")

    def _grid_for(self, shape: Sequence[int]) -> GridSpec:
        grid = self.grid
        if grid is None:
            if tuple(shape) != OCC3D_GRID.shape:
                raise ValueError(
                    f"rayiou needs the evaluation grid for labels of shape {tuple(shape)}: set grid: "
                    "{range, voxel_size} (runs fill it from the config's top-level grid)"
                )
            grid = OCC3D_GRID
        if tuple(shape) != grid.shape:
            raise ValueError(f"rayiou: labels of shape {tuple(shape)} do not match the grid's shape {grid.shape}")
        return grid

    def _origins(self, batch: Batch, b: int) -> Tensor:
        if batch.sequence_lidar_origins is not None:
            return batch.sequence_lidar_origins[b]
        if batch.lidar_to_ego is not None:
            return batch.lidar_to_ego[b, :3, 3][None]
        return torch.zeros(1, 3)

    def update(self, pred: Tensor, batch: Batch) -> None:  # type: ignore[override]
        """Cast the query rays of every sample of ``batch`` through ``pred`` ``(B, X, Y, Z)`` and the labels."""
        batch.require("voxel_labels", by="rayiou")
        target = batch.voxel_labels
        if pred.shape != target.shape:
            raise ValueError(f"prediction shape {tuple(pred.shape)} differs from label shape {tuple(target.shape)}")
        grid = self._grid_for(target.shape[1:])
        if self._directions is None or self._directions.device != target.device:
            self._directions = query_ray_directions(device=target.device)
        for b in range(target.shape[0]):
            sequence = self._origins(batch, b)
            if not bool(torch.isfinite(sequence).all()):
                raise ValueError(f"rayiou: sample {batch.token[b]!r} has non-finite LiDAR origins (NaN or inf)")
            origins = select_origins(sequence, self.origin_limit, self.max_origins)
            self.origins_used += origins.shape[0]
            self.samples += 1
            rays = cast_query_rays(pred[b], target[b], grid, origins, self.free_label, self._directions, self.kernel)
            gt, pr, tp = rayiou_counts(rays, self.num_classes, self.free_label, self.thresholds)
            self.gt_count += gt
            self.pred_count += pr
            self.tp += tp
            gt, pr, tp = geometry_counts(rays, self.free_label, self.thresholds)
            self.geo_gt_count += gt
            self.geo_pred_count += pr
            self.geo_tp += tp

    def per_class_iou(self) -> Tensor:
        """``(len(thresholds), K)`` float64 IoU in [0, 1]; NaN where a class is absent from both."""
        return iou_from_counts(self.gt_count, self.pred_count, self.tp)

    def geometry_iou(self) -> Tensor:
        """``(len(thresholds),)`` float64 class-agnostic IoU in [0, 1]; NaN without evaluated rays."""
        return iou_from_counts(self.geo_gt_count, self.geo_pred_count, self.geo_tp)

    def _semantic(self) -> list[int]:
        return [c for c in range(self.num_classes) if c != self.free_label]

    def _means(self) -> dict[str, list[int]]:
        """The class-mean keys and their class ids: ``RayIoU`` and the group means."""
        return {"RayIoU": self._semantic(), **{f"RayIoU_{key}": ids for key, ids in self.groups.items()}}

    def compute(self) -> dict[str, Tensor]:
        """``RayIoU``, ``RayIoU_<tau>m`` per threshold, ``RayIoU_<class>``, ``RayIoU_geometry``, the group
        means and the ``*_excl`` means (see the class docstring), in percent."""
        all_iou = self.per_class_iou()
        iou = all_iou[:, self._semantic()]
        # the NaN-mean over (threshold, class) is the mean over thresholds of the per-threshold means:
        # a class is NaN at every threshold or at none (N_gt + N_pred - TP > 0 iff N_gt + N_pred > 0)
        out = {key: torch.nanmean(all_iou[:, ids]) * 100 for key, ids in self._means().items()}
        for tau, row in zip(self.thresholds, iou, strict=True):
            out[f"RayIoU_{tau:g}m"] = torch.nanmean(row) * 100
        for c, column in zip(self._semantic(), iou.T, strict=True):
            out[f"RayIoU_{self.class_names[c]}"] = torch.nanmean(column) * 100
        out["RayIoU_geometry"] = self.geometry_iou().mean() * 100
        if self.excluded:
            for key, ids in self._means().items():
                out[f"{key}_excl"] = torch.nanmean(all_iou[:, [c for c in ids if c not in self.excluded]]) * 100
        return {k: v.to(torch.float32) for k, v in out.items()}

    def describe(self) -> str:
        """The settings, as the table's heading states them."""
        grid = (
            "Occ3D grid"
            if self.grid is None
            else f"grid {'x'.join(map(str, self.grid.shape))} @ {'/'.join(f'{v:g}' for v in self.grid.voxel_size)} m"
        )
        taus = ", ".join(f"{t:g}" for t in self.thresholds)
        return (
            f"RayIoU (SparseOcc / Occ3D-nuScenes leaderboard; thresholds {taus} m; {len(query_ray_directions())} rays "
            f"per origin; up to {self.max_origins} origins with |x|,|y| < {self.origin_limit:g} m; {grid})"
        )

    def mean_origins(self) -> float:
        """Origins cast from per sample, on average (8 on Occ3D-nuScenes sequences; 1 means one fixed origin)."""
        return float(self.origins_used) / max(1, int(self.samples))

    def table(self) -> str:
        """Per-class RayIoU at each threshold (percent), headed by the settings and the origins actually used."""
        iou = self.per_class_iou() * 100
        res = self.compute()
        heads = [f"@{t:g}m" for t in self.thresholds]
        used = f"cast from {self.mean_origins():.2f} origins per sample on average over {int(self.samples)} samples"
        if int(self.samples) and self.mean_origins() < 2:
            used += " (one origin per sample: not comparable with leaderboard RayIoU, which casts from the sequence's LiDAR origins)"
        lines = [self.describe(), used, f"{'class':<24}" + "".join(f"{h:>9}" for h in heads)]
        for c in self._semantic():
            lines.append(f"{self.class_names[c]:<24}" + "".join(f"{v:>9.2f}" for v in iou[:, c].tolist()))
        lines.append(f"{'mean':<24}" + "".join(f"{res[f'RayIoU_{t:g}m'].item():>9.2f}" for t in self.thresholds))
        lines.append(f"{'RayIoU':<24}{res['RayIoU'].item():>9.2f}")
        for key in self.groups:
            lines.append(f"{'RayIoU ' + key:<24}{res[f'RayIoU_{key}'].item():>9.2f}")
        geometry = "".join(f"{v:>9.2f}" for v in (self.geometry_iou() * 100).tolist())
        lines.append(f"{'occupied (geometry)':<24}{geometry}")
        lines.append(f"{'RayIoU geometry':<24}{res['RayIoU_geometry'].item():>9.2f}")
        if self.excluded:
            lines.append(f"without {', '.join(self.class_names[c] for c in self.excluded)}:")
            for key in self._means():
                lines.append(f"{key.replace('_', ' ') + ' excl.':<24}{res[f'{key}_excl'].item():>9.2f}")
        return "\n".join(lines)
