"""OccLE's losses as supervision sources (§3.5.1, Eq. 6): ``occle_semantic``, ``occle_geometry``, ``occle_fusion``.

* ``occle_semantic``: ``l_sem = l_ce(s, s̄) + l_occ(S, S̄)``. ``s̄`` is the batch's ``pseudo_semantics``: the 2D
  pseudo labels already aligned to the data set's classes, merged from a primary and an auxiliary segmenter
  through mapping tables by the data pipeline (:mod:`occplug.data.pseudo_labels`, OccLE's Table B.1). ``S̄``
  lifts them to 3D (Eq. 2): every LiDAR return takes the class of the pixel it projects to
  (:func:`occplug.data.labelled_points.lidar_points`) and a voxel takes the majority class of its labelled
  returns; ``l_occ`` counts only voxels holding at least ``min_points`` returns ("more than one point").
  Eq. 2 samples ``s̄`` at the projected voxel centre; sampling at the returns themselves labels the surface the
  LiDAR hit, which the voxel centre only approximates.
* ``occle_geometry``: ``l_geo = l_ce(G, Ḡ)`` with ``Ḡ`` = occupied (label is not free) / free from the voxel
  labels of labelled frames; in the student phase the unlabelled frames carry the teacher's confident pseudo
  labels in their voxel labels (the core's ``pseudo_labels_from``).
* ``occle_fusion``: ``l_fus = l_occ(Y, Ȳ) + l_ce(y, s̄)``; ``l_occ`` only on frames with voxel labels, so an
  unlabelled frame gets ``l_ce(y, s̄)`` alone (add ``occle_semantic`` for its ``l_sem``). ``occupancy_weight: 0``
  drops ``l_occ`` and so every voxel label (Table C.2's "w/o limited voxel annotation").

``l_ce`` is class-weighted cross-entropy and ``l_occ`` MonoScene's CE + ``sem_scal`` + ``geo_scal``
(:mod:`.losses`). Class weights are config values: ``class_weights`` (``K`` numbers used as they are) or
``class_frequencies`` (``K`` raw voxel / pixel counts of the training set, turned into MonoScene's
``1 / log(f + 0.001)``); neither gives uniform weights. A source whose head returned nothing (its branch is
switched off in the ``occle_scene``) contributes no loss terms.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any

import torch
from torch import Tensor

from occplug.constraints import NonNegative, Positive
from occplug.data import Batch, lidar_points
from occplug.geometry import GridSpec
from occplug.interfaces import ModelOutputs, SupervisionSource

from .blocks.losses import OccupancyLoss, class_weights_from_frequencies, lidar_count_mask, weighted_cross_entropy
from .heads import upsample_image_logits
from .scene import _no_query

__all__ = ["OccleFusion", "OccleGeometry", "OccleSemantic", "lift_pseudo_labels"]


def _weights(
    class_weights: Sequence[float] | None, class_frequencies: Sequence[float] | None, who: str
) -> Tensor | None:
    if class_weights is not None and class_frequencies is not None:
        raise ValueError(f"{who}: give class_weights or class_frequencies, not both")
    if class_frequencies is not None:
        return class_weights_from_frequencies(class_frequencies)
    return None if class_weights is None else torch.tensor([float(v) for v in class_weights], dtype=torch.float32)


def _head(outputs: ModelOutputs, name: str, who: str) -> dict[str, Tensor]:
    if name not in outputs.heads:
        raise ValueError(
            f"{who} reads head '{name}', but the model's heads are: {', '.join(outputs.heads) or '(none)'}"
        )
    return outputs.heads[name]


def _check_k(weights: Tensor | None, k: int, who: str) -> None:
    if weights is not None and weights.numel() != k:
        raise ValueError(f"{who}: {weights.numel()} class weights for {k} classes")


def image_ce(logits: Tensor, labels: Tensor, weights: Tensor | None, ignore: int) -> Tensor:
    """``l_ce`` of ``(B, N, K, h, w)`` logits (upsampled to the labels) against ``(B, N, H, W)`` class ids."""
    up = upsample_image_logits(logits, tuple(labels.shape[-2:]))
    return weighted_cross_entropy(up.flatten(0, 1), labels.flatten(0, 1).long(), weights, ignore_index=ignore)


def lift_pseudo_labels(
    batch: Batch, grid: GridSpec, num_classes: int, ignore: int, min_points: int
) -> tuple[Tensor, Tensor]:
    """``S̄`` and where it counts: the 2D pseudo labels lifted to the voxels through the LiDAR returns.

    Args:
        batch: with ``points``, ``lidar_to_ego``, the camera geometry and ``pseudo_semantics`` ``(B, N, H, W)``.
        grid: the ego-frame voxel grid ``(X, Y, Z)``.
        num_classes: ``K``; ignore: the ignore id; min_points: returns a voxel needs to count.

    Returns:
        ``(B, X, Y, Z)`` int64 labels (the majority pseudo class of the voxel's labelled returns; ``ignore`` where
        none) and ``(B, X, Y, Z)`` bool mask (at least ``min_points`` returns and a label).
    """
    x, y, z = grid.shape
    v = x * y * z
    labelled = lidar_points(batch, ignore_label=ignore)
    labels = []
    for pts in labelled:
        idx = grid.coord_to_index(pts.points)
        keep = grid.contains(pts.points) & grid.index_in_bounds(idx) & (pts.labels != ignore)
        keep &= (pts.labels >= 0) & (pts.labels < num_classes)
        idx, lab = idx[keep], pts.labels[keep]
        flat = (idx[:, 0] * y + idx[:, 1]) * z + idx[:, 2]
        votes = torch.bincount(flat * num_classes + lab, minlength=v * num_classes).view(v, num_classes)
        winner = votes.argmax(dim=1)
        winner[votes.sum(dim=1) == 0] = ignore
        labels.append(winner.view(x, y, z))
    lifted = torch.stack(labels)
    dense = lidar_count_mask([p.points for p in labelled], grid, min_points).to(lifted.device)
    return lifted, dense & (lifted != ignore)


def _voxel_mask(batch: Batch, labels: Tensor, ignore: int | None, camera_mask: bool, who: str) -> Tensor:
    """``(B, X, Y, Z)`` voxels whose labels count: labelled frames, not ignore, not invalid, camera-visible."""
    keep = batch.has_voxel_labels.to(labels.device).view(-1, 1, 1, 1).expand_as(labels)
    if ignore is not None:
        keep = keep & (labels != ignore)
    if batch.voxel_invalid is not None:
        keep = keep & ~batch.voxel_invalid.bool()
    if camera_mask:
        batch.require("mask_camera", by=f"{who} with camera_mask")
        keep = keep & batch.mask_camera.bool()
    return keep


def _conformance_outputs(batch: Batch, grid: GridSpec, k: int = 18) -> ModelOutputs:
    """Random outputs of every OccLE head (requiring grad) for a tiny batch."""
    gen = torch.Generator().manual_seed(0)
    b, n, _, h, w = batch.images.shape

    def rand(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=gen).requires_grad_(True)

    heads = {
        "image_semantic": {"image_logits": rand(b, n, k, h // 4, w // 4)},
        "lidar_semantic": {"logits": rand(b, k, *grid.shape)},
        "geometry": {"geometry": rand(b, 2, *grid.shape)},
        "occupancy": {"logits": rand(b, k, *grid.shape)},
        "projection": {"image_logits": rand(b, n, k, h // 4, w // 4)},
    }
    return ModelOutputs(image_features=None, lifted=None, scene=None, heads=heads, query=_no_query)


class OccleSemantic(SupervisionSource):
    """``l_sem = l_ce(s, s̄) + l_occ(S, S̄)`` (OccLE Eq. 6, semantic branch); see the module docstring.

    Args:
        weight: scale of every term.
        image_head: head giving ``s`` (``image_logits`` ``(B, N, K, h, w)``).
        lidar_head: head giving ``S`` (``logits`` ``(B, K, X, Y, Z)`` on the evaluation grid).
        grid: the grid of ``S`` (the evaluation grid: the run's, given by the model).
        min_points: LiDAR returns a voxel needs for ``l_occ(S, S̄)`` (2: "more than one point").
        class_weights, class_frequencies: ``K`` CE class weights, or raw class counts (module docstring).
        free_label, ignore_label: the data set's (given).

    Needs batch fields: ``pseudo_semantics`` ``(B, N, H, W)``, ``points``, ``lidar_to_ego``, the cameras.

    Returns:
        ``{"image_ce", "lidar_ce", "lidar_sem_scal", "lidar_geo_scal"}`` (unweighted); ``{}`` when both heads
        returned nothing (semantic branch off).
    """

    requires = frozenset({"pseudo_semantics", "points"})

    def __init__(
        self,
        grid: GridSpec,
        weight: Annotated[float, NonNegative] = 1.0,
        image_head: str = "image_semantic",
        lidar_head: str = "lidar_semantic",
        min_points: Annotated[int, Positive] = 2,
        class_weights: list[Annotated[float, NonNegative]] | None = None,
        class_frequencies: list[Annotated[float, NonNegative]] | None = None,
        free_label: Annotated[int, NonNegative] = 17,
        ignore_label: int | None = 255,
    ) -> None:
        super().__init__()
        self.grid = grid
        self.weight = float(weight)
        self.image_head, self.lidar_head = image_head, lidar_head
        self.min_points = int(min_points)
        self.ignore = 255 if ignore_label is None else int(ignore_label)
        cw = _weights(class_weights, class_frequencies, "occle_semantic")
        self.register_buffer("class_weights", cw, persistent=False)
        self.occ = OccupancyLoss(cw, free_label=free_label, ignore_index=self.ignore)

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        image = _head(outputs, self.image_head, "occle_semantic").get("image_logits")
        lidar = _head(outputs, self.lidar_head, "occle_semantic").get("logits")
        out: dict[str, Tensor] = {}
        if image is not None:
            batch.require("pseudo_semantics", by="occle_semantic")
            _check_k(self.class_weights, image.shape[2], "occle_semantic")
            out["image_ce"] = image_ce(image, batch.pseudo_semantics, self.class_weights, self.ignore)
        if lidar is not None:
            batch.require("points", "lidar_to_ego", "pseudo_semantics", by="occle_semantic")
            if tuple(lidar.shape[2:]) != self.grid.shape:
                raise ValueError(
                    f"occle_semantic: head '{self.lidar_head}' logits {tuple(lidar.shape)} are not on {self.grid.shape}"
                )
            target, mask = lift_pseudo_labels(batch, self.grid, lidar.shape[1], self.ignore, self.min_points)
            terms = self.occ(lidar, target.to(lidar.device), mask.to(lidar.device))
            out.update({f"lidar_{k}": v for k, v in terms.items()})
        return out

    @classmethod
    def conformance_outputs(cls, batch: Batch, grid: Any, channels: int) -> ModelOutputs | None:
        """Random outputs of the OccLE heads."""
        return _conformance_outputs(batch, grid)


class OccleGeometry(SupervisionSource):
    """``l_geo = l_ce(G, Ḡ)`` (OccLE Eq. 6, geometric branch); see the module docstring.

    Args:
        weight: scale of the loss.
        head: head giving ``G`` (``geometry`` ``(B, 2, X, Y, Z)``, channel 1 = occupied).
        camera_mask: count only camera-visible voxels (``batch.mask_camera``).
        class_weights, class_frequencies: 2 CE weights (free, occupied) or raw counts (module docstring).
        free_label, ignore_label: the data set's (given).

    Needs batch fields: ``voxel_labels`` ``(B, X, Y, Z)``, ``has_voxel_labels`` ``(B,)``.

    Returns:
        ``{"geo_ce": loss}`` (unweighted); ``{}`` when the head returned nothing (geometric branch off).
    """

    def __init__(
        self,
        weight: Annotated[float, NonNegative] = 1.0,
        head: str = "geometry",
        camera_mask: bool = False,
        class_weights: list[Annotated[float, NonNegative]] | None = None,
        class_frequencies: list[Annotated[float, NonNegative]] | None = None,
        free_label: Annotated[int, NonNegative] = 17,
        ignore_label: int | None = 255,
    ) -> None:
        super().__init__()
        self.weight = float(weight)
        self.head = head
        self.camera_mask = bool(camera_mask)
        self.free_label, self.ignore_label = int(free_label), ignore_label
        cw = _weights(class_weights, class_frequencies, "occle_geometry")
        _check_k(cw, 2, "occle_geometry")
        self.register_buffer("class_weights", cw, persistent=False)

    @property
    def training_mask(self) -> str:
        """``camera`` or ``none``."""
        return "camera" if self.camera_mask else "none"

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        g = _head(outputs, self.head, "occle_geometry").get("geometry")
        if g is None:
            return {}
        batch.require("voxel_labels", by="occle_geometry")
        labels = batch.voxel_labels.to(g.device).long()
        keep = _voxel_mask(batch, labels, self.ignore_label, self.camera_mask, "occle_geometry")
        target = (labels != self.free_label).long()
        return {"geo_ce": weighted_cross_entropy(g, target, self.class_weights, mask=keep, ignore_index=-100)}

    @classmethod
    def conformance_outputs(cls, batch: Batch, grid: Any, channels: int) -> ModelOutputs | None:
        """Random outputs of the OccLE heads."""
        return _conformance_outputs(batch, grid)


class OccleFusion(SupervisionSource):
    """``l_fus = l_occ(Y, Ȳ) + l_ce(y, s̄)`` (OccLE Eq. 6, fusion); see the module docstring.

    Args:
        weight: scale of every term.
        head: head giving ``Y`` (``logits`` ``(B, K, X, Y, Z)``).
        projection_head: head giving ``y`` (``image_logits`` ``(B, N, K, h, w)``), or None for no ``l_ce(y, s̄)``.
        projection_weight: extra scale of ``l_ce(y, s̄)``.
        occupancy_weight: extra scale of ``l_occ(Y, Ȳ)``; 0 leaves it out (no voxel label is read: the pseudo
            labels alone, Table C.2).
        camera_mask: count only camera-visible voxels in ``l_occ``.
        class_weights, class_frequencies: ``K`` CE weights or raw class counts (module docstring).
        free_label, ignore_label: the data set's (given).

    Needs batch fields: ``voxel_labels``, ``has_voxel_labels``, ``pseudo_semantics`` (for ``y``).

    Returns:
        ``{"occ_ce", "occ_sem_scal", "occ_geo_scal", "projection_ce"}`` (unweighted; the ``occ_*`` terms only
        with ``occupancy_weight > 0``, ``projection_ce`` only when the projection head gave logits).
    """

    requires = frozenset({"pseudo_semantics"})

    def __init__(
        self,
        weight: Annotated[float, NonNegative] = 1.0,
        head: str = "occupancy",
        projection_head: str | None = "projection",
        projection_weight: Annotated[float, NonNegative] = 1.0,
        occupancy_weight: Annotated[float, NonNegative] = 1.0,
        camera_mask: bool = False,
        class_weights: list[Annotated[float, NonNegative]] | None = None,
        class_frequencies: list[Annotated[float, NonNegative]] | None = None,
        free_label: Annotated[int, NonNegative] = 17,
        ignore_label: int | None = 255,
    ) -> None:
        super().__init__()
        self.weight = float(weight)
        self.head, self.projection_head = head, projection_head
        self.projection_weight = float(projection_weight)
        self.occupancy_weight = float(occupancy_weight)
        self.camera_mask = bool(camera_mask)
        self.ignore_label = ignore_label
        self.ignore = 255 if ignore_label is None else int(ignore_label)
        cw = _weights(class_weights, class_frequencies, "occle_fusion")
        self.register_buffer("class_weights", cw, persistent=False)
        self.occ = OccupancyLoss(cw, free_label=free_label, ignore_index=self.ignore)

    @property
    def training_mask(self) -> str:
        """``camera`` or ``none``."""
        return "camera" if self.camera_mask else "none"

    def forward(self, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        logits = _head(outputs, self.head, "occle_fusion").get("logits")
        if logits is None:
            raise ValueError(f"occle_fusion: head '{self.head}' gave no 'logits'")
        out: dict[str, Tensor] = {}
        if self.occupancy_weight > 0:
            batch.require("voxel_labels", by="occle_fusion")
            labels = batch.voxel_labels.to(logits.device).long()
            keep = _voxel_mask(batch, labels, self.ignore_label, self.camera_mask, "occle_fusion")
            w = self.occupancy_weight
            out.update({f"occ_{k}": v if w == 1.0 else w * v for k, v in self.occ(logits, labels, keep).items()})
        if self.projection_head is not None:
            y = _head(outputs, self.projection_head, "occle_fusion").get("image_logits")
            if y is not None:
                batch.require("pseudo_semantics", by="occle_fusion's projection term")
                ce = image_ce(y, batch.pseudo_semantics, self.class_weights, self.ignore)
                out["projection_ce"] = self.projection_weight * ce
        return out

    @classmethod
    def conformance_outputs(cls, batch: Batch, grid: Any, channels: int) -> ModelOutputs | None:
        """Random outputs of the OccLE heads."""
        return _conformance_outputs(batch, grid)
