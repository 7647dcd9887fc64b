"""Floors and ceilings of an evaluation protocol, method-free.

A claim measured on a protocol (grid, evaluation mask, readout, metric) can only be read between the
protocol's **floor** (the best prediction that looks at no image) and its **ceilings** (what a perfect
model, or a perfect version of one mechanism, scores under the same protocol). This module holds the
world-independent pieces; :mod:`occplug.data.synthetic.testbed` measures them on the synthetic world and
``python scripts/ceilings.py`` prints them.

* :func:`read_voxels` turns samples of a field at ``k**3`` points per voxel into one class per voxel
  (the *readout*: ``center`` = ``k = 1``, as a query decoder read at voxel centres; ``any<k>``: occupied
  if any sample is, the most frequent occupied class; ``vote<k>``: the most frequent class, free included).
* :func:`depth_lift` is the perfect-depth ceiling of a lift-based model: every feature cell's true
  surface point, with its true 2D class, splatted into the grid.
* :func:`history_headroom` is the share of scored voxels that earlier (or adjacent) frames of the scene
  observed but the current frame does not: what temporal fusion can add at most.
* :class:`Scorer` accumulates Occ3D's confusion matrix under any mask (:class:`~occplug.metrics.Occ3DMIoU`).
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterable
from dataclasses import dataclass

import torch
from torch import Tensor

from occplug.geometry import GridSpec, invert_pose, unproject_from_image
from occplug.metrics.miou import Occ3DMIoU, confusion_matrix

__all__ = [
    "Headroom",
    "Readout",
    "Scorer",
    "depth_lift",
    "history_headroom",
    "parse_readout",
    "read_voxels",
    "training_prior",
    "vote_points",
]


@dataclass(frozen=True)
class Readout:
    """How a field sampled at ``k**3`` points per voxel becomes one class per voxel.

    Attributes:
        k: sub-samples per voxel edge (1: the voxel centre).
        rule: ``any`` (occupied if any sample is occupied; class: the most frequent occupied one) or
            ``vote`` (the most frequent class, free included). Ties go to the lower class id.
    """

    k: int
    rule: str = "any"

    @property
    def name(self) -> str:
        """``center``, ``any2``, ``vote3``, ..."""
        return "center" if self.k == 1 else f"{self.rule}{self.k}"


def parse_readout(spec: str) -> Readout:
    """``center`` | ``any<k>`` | ``vote<k>`` -> :class:`Readout` (a ``ValueError`` names the forms)."""
    if spec == "center":
        return Readout(1)
    match = re.fullmatch(r"(any|vote)([1-9][0-9]*)", spec)
    if match is None:
        raise ValueError(f"readout '{spec}': expected 'center', 'any<k>' or 'vote<k>' (e.g. any2)")
    return Readout(int(match.group(2)), match.group(1))


def read_voxels(samples: Tensor, rule: str, free: int, num_classes: int) -> Tensor:
    """One class per voxel from ``(X, Y, Z, k, k, k)`` class samples (see :class:`Readout`).

    Returns:
        ``(X, Y, Z)`` int64 class ids.
    """
    if rule not in ("any", "vote"):
        raise ValueError(f"read_voxels: rule must be 'any' or 'vote', got {rule!r}")
    flat = samples.reshape(*samples.shape[:3], -1).long()
    counts = torch.zeros(*samples.shape[:3], num_classes, dtype=torch.int64)
    counts.scatter_add_(-1, flat, torch.ones_like(flat))
    if rule == "vote":
        return counts.argmax(-1)
    occupied = counts.clone()
    occupied[..., free] = -1
    best = occupied.argmax(-1)
    return torch.where(occupied.amax(-1) > 0, best, torch.full_like(best, free))


class Scorer:
    """Occ3D mIoU and geometric IoU of predictions against labels under an explicit mask.

    Args:
        class_names: every class, ``free`` included; free_label: its id.
    """

    def __init__(self, class_names: list[str] | tuple[str, ...], free_label: int) -> None:
        self.metric = Occ3DMIoU(
            num_classes=len(class_names), class_names=list(class_names), free_label=free_label, mask="none"
        )

    def update(self, pred: Tensor, target: Tensor, valid: Tensor | None) -> None:
        """Add ``(X, Y, Z)`` (or batched) ``pred`` against ``target`` where ``valid`` (None: everywhere)."""
        self.metric.confmat += confusion_matrix(pred.long(), target.long(), self.metric.num_classes, valid)

    def compute(self) -> dict[str, float]:
        """``{"IoU": ..., "mIoU": ...}`` in percent."""
        with warnings.catch_warnings():  # the confusion matrix is filled directly, not through update()
            warnings.simplefilter("ignore", UserWarning)
            out = self.metric.compute()
        return {"IoU": float(out["IoU"]), "mIoU": float(out["mIoU"])}


def training_prior(labels: Iterable[Tensor], num_classes: int, free: int) -> tuple[Tensor, int]:
    """The floor's predictions: the per-voxel most frequent class over ``labels`` (``(X, Y, Z)`` each:
    a prior map in the ego frame) and the most frequent occupied class overall."""
    counts: Tensor | None = None
    for lab in labels:
        lab = lab.long()
        if counts is None:
            counts = torch.zeros(*lab.shape, num_classes, dtype=torch.int64)
        counts.scatter_add_(-1, lab[..., None], torch.ones_like(lab)[..., None])
    if counts is None:
        raise ValueError("training_prior: no labels")
    totals = counts.sum((0, 1, 2))
    totals[free] = -1
    return counts.argmax(-1), int(totals.argmax())


def depth_lift(
    depth: Tensor,
    semantics: Tensor,
    intrinsics: Tensor,
    cam_to_ego: Tensor,
    grid: GridSpec,
    stride: int,
    free: int,
    num_classes: int,
) -> Tensor:
    """Perfect depth and perfect 2D classes, lifted: the surface a lift-based model can put features on.

    Every ``stride x stride`` cell of each image reads the pixel nearest its centre (as
    :func:`occplug.components.oracle_depth_logits`), unprojects it at its true depth and votes its
    2D class into the voxel it falls in; voxels no point reaches are free. Pixels without depth
    (0) or with a class outside ``0..num_classes-1`` (sky: 255) are skipped.

    Args:
        depth: ``(N, H, W)`` camera-frame z, metres; semantics: ``(N, H, W)`` class ids.
        intrinsics: ``(N, 3, 3)``; cam_to_ego: ``(N, 4, 4)``.
        grid: the label grid; stride: pixels per feature cell.

    Returns:
        ``(X, Y, Z)`` int64 class ids.
    """
    n, h, w = depth.shape
    rows = torch.arange(h // stride) * stride + stride // 2
    cols = torch.arange(w // stride) * stride + stride // 2
    z = depth[:, rows[:, None], cols[None, :]].double()
    cls = semantics[:, rows[:, None], cols[None, :]].long()
    uv = torch.stack(torch.broadcast_tensors(cols[None, :].double(), rows[:, None].double()), -1).reshape(1, -1, 2)
    pts = unproject_from_image(uv.expand(n, -1, 2), z.reshape(n, -1), intrinsics.double(), cam_to_ego.double())
    pts, cls, z = pts.reshape(-1, 3), cls.reshape(-1), z.reshape(-1)
    keep = z > 0
    return vote_points(pts[keep], cls[keep], grid, free, num_classes)


def vote_points(points: Tensor, classes: Tensor, grid: GridSpec, free: int, num_classes: int) -> Tensor:
    """Voxelise classed points: each voxel takes the most frequent class of the points in it, free where none.

    Args:
        points: ``(P, 3)`` ego-frame points; classes: ``(P,)`` ids (points whose id is outside
            ``0..num_classes-1`` or is ``free`` are skipped, as are points outside the grid).

    Returns:
        ``(X, Y, Z)`` int64 class ids.
    """
    cls = classes.long()
    keep = (cls >= 0) & (cls < num_classes) & (cls != free) & grid.contains(points)
    idx = grid.coord_to_index(points[keep])
    nx, ny, nz = grid.shape
    flat = (idx[:, 0] * ny + idx[:, 1]) * nz + idx[:, 2]
    counts = torch.zeros(nx * ny * nz, num_classes, dtype=torch.int64)
    counts.index_put_((flat, cls[keep]), torch.ones_like(flat), accumulate=True)
    best = counts.argmax(-1)
    return torch.where(counts.sum(-1) > 0, best, torch.full_like(best, free)).reshape(nx, ny, nz)


@dataclass
class Headroom:
    """Voxel counts of :func:`history_headroom`, summed over frames.

    Attributes:
        scored: voxels the protocol scores.
        observed_now: scored voxels the current frame observes.
        earlier_only: scored voxels not observed now but observed by an earlier frame of the scene.
        adjacent_only: scored voxels not observed now but observed by frame ``t - 1`` or ``t + 1``.
    """

    scored: int = 0
    observed_now: int = 0
    earlier_only: int = 0
    adjacent_only: int = 0

    def add(self, other: Headroom) -> None:
        """Add another count in place."""
        for name in ("scored", "observed_now", "earlier_only", "adjacent_only"):
            setattr(self, name, getattr(self, name) + getattr(other, name))

    def shares(self) -> dict[str, float]:
        """Percent of the scored voxels: ``observed_now``, ``earlier_only`` (the history headroom) and
        ``adjacent_only`` (what a t+-1 window can add)."""
        total = max(self.scored, 1)
        return {k: 100.0 * getattr(self, k) / total for k in ("observed_now", "earlier_only", "adjacent_only")}


def _seen_from(observed: Tensor, src_to_dst: Tensor, grid: GridSpec, centers: Tensor) -> Tensor:
    """``(X, Y, Z)`` bool: whether each voxel centre of frame ``src`` lands in an observed voxel of frame ``dst``."""
    pts = centers @ src_to_dst[:3, :3].T + src_to_dst[:3, 3]
    idx = grid.coord_to_index(pts)
    inside = grid.index_in_bounds(idx)
    out = torch.zeros(centers.shape[:-1], dtype=torch.bool)
    i = idx[inside]
    out[inside] = observed[i[..., 0], i[..., 1], i[..., 2]]
    return out


def history_headroom(observed: Tensor, scored: Tensor, ego_to_world: Tensor, grid: GridSpec) -> Headroom:
    """What other frames of one scene observe of the voxels a protocol scores now.

    A scored voxel of frame ``t`` counts as observed by frame ``s`` when its centre, carried through
    the ego motion (``ego_to_world[s]^-1 @ ego_to_world[t]``), lands in a voxel frame ``s`` observes
    (a static-world reading: what the ego-motion warp of a stream can bring).

    Args:
        observed: ``(T, X, Y, Z)`` bool, what each frame's sensors observe (e.g. its camera mask).
        scored: ``(T, X, Y, Z)`` bool, the voxels the protocol scores in each frame (e.g. the same
            camera mask, or all voxels).
        ego_to_world: ``(T, 4, 4)`` float64 poses of the frames in one common frame, in temporal order.
        grid: the label grid.

    Returns:
        the :class:`Headroom` counts summed over the ``T`` frames.
    """
    centers = grid.centers().double()
    out = Headroom()
    steps = observed.shape[0]
    for t in range(steps):
        now = observed[t].bool()
        score = scored[t].bool()
        earlier = torch.zeros_like(now)
        adjacent = torch.zeros_like(now)
        for s in range(steps):
            if s == t:
                continue
            seen = _seen_from(observed[s].bool(), invert_pose(ego_to_world[s]) @ ego_to_world[t], grid, centers)
            if s < t:
                earlier |= seen
            if abs(s - t) == 1:
                adjacent |= seen
        out.add(
            Headroom(
                scored=int(score.sum()),
                observed_now=int((score & now).sum()),
                earlier_only=int((score & ~now & earlier).sum()),
                adjacent_only=int((score & ~now & adjacent).sum()),
            )
        )
    return out
