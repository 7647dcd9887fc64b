"""OccLE's heads (§3.2-3.4): ``Y`` (fused occupancy), ``S`` (LiDAR semantics), ``G`` (geometry), ``s`` (image
semantics) and ``y`` (projected segmentation), each reading its grid of an ``occle_scene``.

Voxel heads return logits on the scene's grid, which is the evaluation grid; the model evaluates through any of
them (``model.occupancy_head``: ``occupancy`` for the final model, ``lidar_semantic`` for phase I's ``S``,
``geometry`` for phase II's ``G``). A head whose branch the scene switched off returns ``{}``.
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from occplug.constraints import NonNegative, Positive, check_choices
from occplug.data import Batch
from occplug.geometry import GridSpec
from occplug.interfaces import DEFAULT_QUERY_CHUNK, Head, ModelOutputs, OccupancyHead, Scene
from occplug.nn import UNet2d

from .blocks.geometry_branch import GeometryHead
from .blocks.projection import ProjectionHead, feature_map_intrinsics, scatter_project
from .scene import _no_query, conformance_scene

__all__ = [
    "FusedOccupancyHead",
    "GeometryOccupancyHead",
    "ImageSemanticHead",
    "LidarSemanticHead",
    "ProjectedSegmentationHead",
]

#: Gap below the smaller geometry logit given to the classes a binary geometry head never predicts.
_ABSENT_GAP = 20.0


class _GridHead(OccupancyHead):
    """A 3D header (``layers`` x ``3x3x3 conv -> BN -> ReLU``, then ``1x1x1 conv``) on one grid of the scene."""

    #: Attribute of the scene this head reads (``features`` is the fused grid, present on any dense scene).
    reads_grid: ClassVar[str] = "features"
    queryable = False

    def __init__(
        self,
        in_channels: Annotated[int, Positive],
        num_classes: Annotated[int, Positive],
        hidden: Annotated[int, Positive] = 32,
        layers: Annotated[int, NonNegative] = 1,
    ) -> None:
        super().__init__()
        self.num_classes = int(num_classes)
        self.net = GeometryHead(in_channels, self._outputs(), hidden=hidden, layers=layers)

    def _outputs(self) -> int:
        return self.num_classes

    def _grid(self, scene: Scene) -> Tensor | None:
        return getattr(scene, self.reads_grid, None)

    def forward(self, scene: Scene, batch: Batch) -> dict[str, Tensor]:
        """``{"logits": (B, K, X, Y, Z)}`` on ``scene.grid``; ``{}`` when the scene's branch is off."""
        grid = self._grid(scene)
        return {} if grid is None else {"logits": self.net(grid)}

    def occupancy_logits(self, scene: Scene, grid: GridSpec, chunk_size: int = DEFAULT_QUERY_CHUNK) -> Tensor:
        """``(B, K, X, Y, Z)`` logits; only on the scene's own grid (a conv header is not queryable)."""
        if grid != scene.grid:
            raise ValueError(
                f"{type(self).__name__} answers on its scene's grid only ({scene.grid.shape}), not {grid.shape}"
            )
        out = self.forward(scene, None)  # type: ignore[arg-type]  # the batch is not read
        if "logits" not in out:
            raise ValueError(f"{type(self).__name__}: the scene's '{self.reads_grid}' grid is switched off")
        return out["logits"]


class FusedOccupancyHead(_GridHead):
    """``Y``: the 3D header on the fused grid ``F_3d^f`` (§3.4), the model's semantic occupancy.

    Args:
        in_channels: ``C`` of the scene; num_classes: ``K``; hidden, layers: of the header.

    Forward: an ``occle_scene`` (or any dense voxel scene) -> ``{"logits": (B, K, X, Y, Z)}``.
    """

    reads_grid = "features"


class LidarSemanticHead(_GridHead):
    """``S``: the 3D header on the LiDAR UNet's grid ``F_P^s`` (§3.2), supervised by the lifted pseudo labels.

    Args:
        in_channels: ``C`` of the scene; num_classes: ``K``; hidden, layers: of the header.

    Forward: an ``occle_scene`` -> ``{"logits": (B, K, X, Y, Z)}`` (``{}`` with the semantic branch off).
    """

    reads_grid = "lidar_semantic"

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple[Any, ...]:
        """Random :func:`~.scene.conformance_scene` grids and the batch."""
        return (conformance_scene(batch, grid, channels), batch)


class GeometryOccupancyHead(_GridHead):
    """``G``: the 2-class (free, occupied) header on the geometric grid ``F_f^g`` (§3.3, §3.5 ``l_geo``).

    Besides the 2-class ``geometry`` logits it gives them as ``K``-class ``logits`` on the evaluation grid, so
    the core evaluates it (IoU) and a teacher phase writes its pseudo labels through the core's
    ``pseudo_labels_from``, whose labels and confidences are ``K``-class: ``free_label`` gets the free logit,
    ``occupied_label`` the occupied one and every other class a logit 20 below the smaller of the two. Then the
    softmax over ``K`` equals the 2-class softmax to within ``(K - 2) e^-20``, the argmax is ``free_label`` or
    ``occupied_label``, and ``occle_geometry`` reads any non-free label as occupied.

    Args:
        in_channels: ``C`` of the scene; num_classes: ``K`` of the data set; free_label: its free class.
        occupied_label: the class standing for "occupied" in ``logits`` (default: the first class that is not
            ``free_label``).
        hidden, layers: of the header.

    Forward: an ``occle_scene`` -> ``{"geometry": (B, 2, X, Y, Z), "logits": (B, K, X, Y, Z)}`` (``{}`` with the
    geometric branch off); channel 0 of ``geometry`` is free, 1 occupied.
    """

    reads_grid = "geometry"

    def __init__(
        self,
        in_channels: Annotated[int, Positive],
        num_classes: Annotated[int, Positive],
        free_label: Annotated[int, NonNegative] = 17,
        occupied_label: Annotated[int, NonNegative] | None = None,
        hidden: Annotated[int, Positive] = 32,
        layers: Annotated[int, NonNegative] = 1,
    ) -> None:
        super().__init__(in_channels, num_classes, hidden, layers)
        if not 0 <= free_label < num_classes:
            raise ValueError(f"occle_geometry head: free_label {free_label} is not one of {num_classes} classes")
        occupied = (1 if free_label == 0 else 0) if occupied_label is None else int(occupied_label)
        if occupied == free_label or not 0 <= occupied < num_classes:
            raise ValueError(f"occle_geometry head: occupied_label {occupied} must be a class other than free_label")
        self.free_label, self.occupied_label = int(free_label), occupied

    def _outputs(self) -> int:
        return 2

    def forward(self, scene: Scene, batch: Batch) -> dict[str, Tensor]:
        """``{"geometry": (B, 2, X, Y, Z), "logits": (B, K, X, Y, Z)}``; ``{}`` with the geometric branch off."""
        grid = self._grid(scene)
        if grid is None:
            return {}
        g = self.net(grid)
        absent = g.detach().min(dim=1, keepdim=True).values - _ABSENT_GAP
        parts = [absent] * self.num_classes
        parts[self.free_label], parts[self.occupied_label] = g[:, :1], g[:, 1:]
        return {"geometry": g, "logits": torch.cat(parts, dim=1)}

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple[Any, ...]:
        """Random :func:`~.scene.conformance_scene` grids and the batch."""
        return (conformance_scene(batch, grid, channels), batch)


#: Image channels of the random features the image head's conformance check feeds (its default).
_IMAGE_CHANNELS = 32


class ImageSemanticHead(Head):
    """``s``: per-pixel semantics from the image encoder's features (§3.2's 2D header of ``G_s2d``).

    A small 2D UNet (:class:`occplug.nn.UNet2d`) over the encoder's primary feature level, at its resolution; the
    ``occle_semantic`` loss upsamples the logits to the pseudo labels' resolution. Part of the semantic branch:
    it returns ``{}`` when the ``occle_scene`` switches that branch off.

    Args:
        num_classes: ``K``.
        image_channels: ``C`` of the image features (the encoder's ``out_channels``, given by the model).
        base_channels: width of the UNet's first level; depth: its downsamplings (0: one block).

    Forward: ``(scene, batch, outputs)`` with ``outputs.image_features`` ``(B, N, C, h, w)`` ->
    ``{"image_logits": (B, N, K, h, w)}``.
    """

    reads_outputs = True

    def __init__(
        self,
        num_classes: Annotated[int, Positive],
        image_channels: Annotated[int, Positive] = _IMAGE_CHANNELS,
        base_channels: Annotated[int, Positive] = 16,
        depth: Annotated[int, NonNegative] = 1,
    ) -> None:
        super().__init__()
        self.num_classes, self.image_channels = int(num_classes), int(image_channels)
        self.net = UNet2d(self.image_channels, self.num_classes, base_channels, depth, min_size=2)

    def forward(self, scene: Scene, batch: Batch, outputs: ModelOutputs) -> dict[str, Tensor]:
        """``{"image_logits": (B, N, K, h, w)}``; ``{}`` with the semantic branch off."""
        if getattr(scene, "semantic", True) is None:
            return {}
        feats = outputs.image_features
        if feats is None or feats.dim() != 5 or feats.shape[2] != self.image_channels:
            raise ValueError(
                f"occle_image_semantic expects image features (B, N, {self.image_channels}, h, w) (set image_channels "
                f"to the encoder's out_channels), got {None if feats is None else tuple(feats.shape)}"
            )
        b, n = feats.shape[:2]
        logits = self.net(feats.flatten(0, 1))
        return {"image_logits": logits.view(b, n, *logits.shape[1:])}

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple[Any, ...]:
        """A random scene, the batch and outputs with random stride-4 image features of the default width."""
        b, n, _, h, w = batch.images.shape
        gen = torch.Generator().manual_seed(0)
        outputs = ModelOutputs(image_features=None, lifted=None, scene=None, heads={}, query=_no_query)
        outputs.image_features = torch.randn(b, n, _IMAGE_CHANNELS, h // 4, w // 4, generator=gen)
        return (conformance_scene(batch, grid, channels), batch, outputs)


class ProjectedSegmentationHead(Head):
    """``y``: the fused grid scatter-accumulated onto the image plane (Eq. 5), then a 2D header (§3.4).

    Every voxel centre of ``F_3d^f`` is projected into each camera (through ``img_aug @ intrinsics``, scaled to
    a map ``stride`` times coarser than the image) and its feature added to the cell it lands in
    (:func:`~.projection.scatter_project`); :class:`~.projection.ProjectionHead` turns the map into logits. The
    ``occle_fusion`` loss compares them with the aligned pseudo labels. Returns ``{}`` when the ``occle_scene``
    has ``projection: false``.

    Args:
        in_channels: ``C`` of the scene; num_classes: ``K``.
        stride: image pixels per cell of the projected map (a coarser map catches more voxels per cell).
        mode: ``sum`` (the paper's) or ``distance`` (Appendix C.1's distance-weighted ablation).
        hidden: width of the 2D header's 3x3 layer (0: a 1x1 conv).

    Forward: ``scene`` (``features`` ``(B, C, X, Y, Z)``, ego frame) and a batch with ``images``
    ``(B, N, 3, H, W)``, ``intrinsics``, ``cam_to_ego``, ``img_aug`` -> ``{"image_logits": (B, N, K, H // stride,
    W // stride)}``.
    """

    def __init__(
        self,
        in_channels: Annotated[int, Positive],
        num_classes: Annotated[int, Positive],
        stride: Annotated[int, Positive] = 4,
        mode: Literal["sum", "distance"] = "sum",
        hidden: Annotated[int, NonNegative] = 32,
    ) -> None:
        super().__init__()
        check_choices(ProjectedSegmentationHead.__init__, "occle_projection", mode=mode)
        self.num_classes, self.stride, self.mode = int(num_classes), int(stride), mode
        self.net = ProjectionHead(in_channels, self.num_classes, hidden)

    def forward(self, scene: Scene, batch: Batch) -> dict[str, Tensor]:
        """``{"image_logits": (B, N, K, h, w)}``; ``{}`` with the projection off or no fused grid."""
        if not getattr(scene, "projection", True) or scene.features is None:
            return {}
        b, n, _, big_h, big_w = batch.images.shape
        h, w = big_h // self.stride, big_w // self.stride
        # the map's intrinsics: augmentation first, then the stride (feature_map_intrinsics wants img_aug @ K)
        k = feature_map_intrinsics(batch.img_aug.float() @ batch.intrinsics.float(), self.stride)
        projected = scatter_project(
            scene.features, scene.grid, k, batch.cam_to_ego.float(), (h, w), mode=self.mode
        )  # (B, N, C, h, w)
        logits = self.net(projected.flatten(0, 1))
        return {"image_logits": logits.view(b, n, *logits.shape[1:])}


def upsample_image_logits(logits: Tensor, size: tuple[int, int]) -> Tensor:
    """``(B, N, K, h, w)`` -> ``(B, N, K, H, W)`` bilinear (``align_corners=False``: cell centres map to the
    centres of the pixel blocks they cover)."""
    b, n = logits.shape[:2]
    up = F.interpolate(logits.flatten(0, 1), size=size, mode="bilinear", align_corners=False)
    return up.view(b, n, *up.shape[1:])
