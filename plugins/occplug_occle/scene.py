"""Scene ``occle_scene``: OccLE's semantic branch grid, geometric branch and semantic-geometric fusion (§3.2-3.4).

One module holds the three 3D parts of Fig. 2 so that each is one switch (Tab. 4(b)) and one parameter prefix
(``model.scene.semantic_branch``, ``model.scene.geometric_branch``, ``model.scene.fusion``) for the phases'
``freeze`` / ``init_from``. Inputs, all on one ego-frame grid ``(X, Y, Z)`` (x forward, y left, z up):

* the lifted image grid (the view transform's volume, Eq. 2 ``F(F_I, K(T P))``) ``(B, C_img, X, Y, Z)``;
* the LiDAR grid of a point encoder (``outputs.encoded[lidar_encoder]``) ``(B, C_lidar, X, Y, Z)``.

Parts:

* semantic branch: the LiDAR 3D UNet ``G_s3d`` gives ``F_P^s`` (read by the ``occle_lidar_semantic`` head, ``S``);
  ``F_f^s`` = ``1x1x1 conv -> BN -> ReLU`` of ``[lifted image, F_P^s]`` ("combine", §3.4);
* geometric branch: cross-plane image/LiDAR synergy (Eq. 3-4) or Tab. 4(a)'s Conv3D + 3D deformable
  attention baseline gives ``F_f^g`` (read by the ``occle_geometry`` head, ``G``);
* fusion: Dual Mamba (Appendix A) of ``F_f^s`` and ``F_f^g`` -> ``F_3d^f``, the scene's ``features``
  (read by ``occle_occupancy`` -> ``Y`` and ``occle_projection`` -> ``y``).

A switched-off branch (``semantic: false`` / ``geometric: false``) is replaced by a plain stem,
``1x1x1 conv -> BN -> ReLU`` of ``[lifted image, LiDAR grid]``, so the fusion still receives two grids; the
branch's heads then return nothing and its losses drop out. ``projection: false`` does the same for the
projected segmentation ``y``. With all three off this is Tab. 4(b)'s baseline.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import torch
import torch.utils.checkpoint
from torch import Tensor, nn

from occplug import RunContext
from occplug.config import Slot
from occplug.constraints import Length, NonNegative, Positive, check_choices
from occplug.data import Batch
from occplug.geometry import GridSpec
from occplug.interfaces import (
    DenseVoxelScene,
    ImageEncoder,
    Lifted,
    ModelOutputs,
    PointEncoder,
    SceneRepresentation,
    ViewTransform,
    feature_levels,
)
from occplug.nn import BasicBlock3d, UNet3d

from .blocks.geometry_branch import Conv3dDeformableBaseline, CrossPlaneFusion
from .blocks.mamba import DualMambaUNet

__all__ = ["OccleGrids", "OccleScene", "conformance_scene"]

#: ``lidar_channels`` of a scene built without the model's ``point_channels`` (and of the conformance LiDAR grid).
_DEFAULT_LIDAR_CHANNELS = 32


class OccleGrids(DenseVoxelScene):
    """The scene OccLE's heads read: the fused grid plus the branch grids, all ``(B, C, X, Y, Z)`` on ``grid``.

    Attributes:
        features: ``F_3d^f``, the Dual Mamba output (sampled by :meth:`sample`), or None where the scene ran one
            branch alone (``occle_scene`` ``compute``).
        grid: the ego-frame grid of every tensor here.
        lidar_semantic: ``F_P^s`` of the LiDAR 3D UNet, or None (semantic branch off).
        semantic: ``F_f^s``, the semantic grid fused, or None (semantic branch off).
        geometry: ``F_f^g``, the geometric grid, or None (geometric branch off).
        projection: whether the projected segmentation ``y`` is on.
    """

    def __init__(
        self,
        features: Tensor | None,
        grid: GridSpec,
        lidar_semantic: Tensor | None = None,
        semantic: Tensor | None = None,
        geometry: Tensor | None = None,
        projection: bool = True,
    ) -> None:
        if features is not None:
            super().__init__(features, grid)
        else:  # one branch alone: no fused grid (the heads on it give nothing)
            present = next(g for g in (lidar_semantic, semantic, geometry) if g is not None)
            self.features, self.grid, self.channels = None, grid, int(present.shape[1])
        self.lidar_semantic = lidar_semantic
        self.semantic = semantic
        self.geometry = geometry
        self.projection = projection


def _stem(in_channels: int, out_channels: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv3d(in_channels, out_channels, 1, bias=False), nn.BatchNorm3d(out_channels), nn.ReLU(inplace=True)
    )


class ConvFusion(nn.Module):
    """A plain fusion of two grids (no Mamba): concatenation, ``1x1x1 conv -> BN -> ReLU``, ``blocks`` 3D blocks.

    Forward: ``(B, C, X, Y, Z)`` twice -> ``(B, C, X, Y, Z)``.
    """

    def __init__(self, channels: int, blocks: int = 1) -> None:
        super().__init__()
        self.mix = _stem(2 * channels, channels)
        self.blocks = nn.Sequential(*(BasicBlock3d(channels, channels) for _ in range(blocks)))

    def forward(self, semantic: Tensor, geometry: Tensor) -> Tensor:
        return self.blocks(self.mix(torch.cat([semantic, geometry], dim=1)))


class OccleScene(SceneRepresentation):
    """OccLE's semantic branch grid, geometric branch and Dual Mamba fusion (§3.2-3.4); see the module docstring.

    Args:
        in_channels: ``C_img`` of the lifted image grid (the view transform's ``out_channels``).
        grid: the grid every input and output lies on (the evaluation grid, ego frame).
        lidar_channels: ``C_lidar`` of the point encoder's volume; None (default): the ``lidar_encoder`` entry's
            ``out_channels`` in ``point_channels`` (32 where the scene is built without them).
        lidar_encoder: which ``model.point_encoders`` entry is the LiDAR grid.
        point_channels: ``{point encoder name: out_channels}`` (given by the model).
        channels: ``C`` of every branch grid and of the fused grid (so every head gets ``in_channels = C``).
        semantic, geometric, projection: Tab. 4(b)'s switches (see the module docstring).
        geometry: ``cross_plane`` (§3.3.1) or ``conv3d`` (Tab. 4(a)'s Conv3D + 3D deformable attention baseline).
        unet_depth: downsampling levels of the LiDAR 3D UNet ``G_s3d`` (dense here; sparse in the paper).
        plane_kernel, attention_heads: of the cross-plane Conv2Ds and axial attention (Eq. 3); the heads also serve
            the baseline's deformable attention.
        fusion: ``dual_mamba`` (Appendix A) or ``conv`` (concatenation + 3D conv, a Mamba-free ablation).
        mamba_channels: widths of the Dual Mamba U-Net's levels, one more than its stages (the paper: 4 stages;
            here 2 by default, for CPU).
        mamba_state: the SSM state size of its Mamba blocks.
        mamba_chunk: chunk length of their chunked selective scan (speed only: equal up to float rounding).
        mamba_checkpoint: recompute the Dual Mamba's mixers in backward instead of keeping their activations
            (:class:`~.mamba.DualMambaBlock`'s ``checkpoint``): the same values and gradients, less of a training
            step's memory where the Dual Mamba dominates it (``occplug_occle.tools.memory``), about one more forward
            of the mixers in time. Off by default; ``occle/semantickitti`` turns it on.
        semantic_checkpoint: recompute the semantic branch (the dense LiDAR UNet ``G_s3d`` and the mix with the
            lifted image grid) in backward instead of keeping its activations: the same values and gradients (its
            norms are GroupNorm, so a second forward changes no running statistics). With ``mamba_checkpoint`` on,
            the UNet is the largest part of what a step keeps (30 % at 128 x 128 x 32,
            ``occplug_occle.tools.memory``); off by default, ``occle/semantickitti`` turns it on.
        compute: what a forward runs: ``all``; ``semantic``, the semantic branch alone (Phase I, whose losses read
            nothing else); ``geometric``, the geometric branch alone (the teacher and student phases). Every
            module is built either way (the state dict and a phase's ``init_from`` are the same); a grid not run is
            None and the heads on it give nothing. The trained values are the same as with ``all`` (no loss reads
            what is not run), without the memory and time of the unread branches and of the Dual Mamba fusion.
        history: past frame offsets the geometric branch fuses with the current frame (§3.3.1's multi-frame
            grids, ``T = len(history) + 1``, a Conv1D over frames per modality); each must be in the model's
            ``input_history`` (``outputs.history``). Empty: one frame. The semantic branch reads the current
            frame only.
        geometry_encoder, geometry_view_transform, geometry_point_encoder: the geometric branch's own image
            encoder, lift and LiDAR encoder (§4.1: the paper's branch has its own ResNet-50 and sparse Conv3D),
            all three or none, under ``model.scene.geometric_inputs`` (``encoder``, ``view_transform``,
            ``point_encoder``): built as the model builds its own (the lift's ``in_channels`` / ``image_stride``
            from this encoder, ``grid`` the scene's), run on the batch's images and points, and fed to the
            geometric branch in place of the model's shared lifted image and LiDAR grids (which the semantic
            branch still reads). None (default): the branch reads the shared grids. One frame only (no
            ``history``).
        context: the run context (handed in by the builder); the geometric branch's own encoders are built
            through it.

    Forward:
        ``lifted`` (volume ``(B, C_img, X, Y, Z)``), ``batch``, ``outputs`` (``encoded[lidar_encoder]``
        ``(B, C_lidar, X, Y, Z)``) -> :class:`OccleGrids` with ``features`` ``(B, C, X, Y, Z)``.
    """

    reads_outputs = True

    def __init__(
        self,
        in_channels: Annotated[int, Positive],
        grid: GridSpec,
        lidar_channels: Annotated[int, Positive] | None = None,
        lidar_encoder: str = "lidar",
        point_channels: dict[str, int] | None = None,
        channels: Annotated[int, Positive] = 32,
        semantic: bool = True,
        geometric: bool = True,
        projection: bool = True,
        geometry: Literal["cross_plane", "conv3d"] = "cross_plane",
        unet_depth: Annotated[int, NonNegative] = 2,
        plane_kernel: Annotated[int, Positive] = 3,
        attention_heads: Annotated[int, Positive] = 4,
        fusion: Literal["dual_mamba", "conv"] = "dual_mamba",
        mamba_channels: Annotated[list[Annotated[int, Positive]], Length(min=2)] = [32, 48, 64],  # noqa: B006 - read only
        mamba_state: Annotated[int, Positive] = 16,
        mamba_chunk: Annotated[int, Positive] = 64,
        mamba_checkpoint: bool = False,
        semantic_checkpoint: bool = False,
        compute: Literal["all", "semantic", "geometric"] = "all",
        history: list[int] | None = None,
        geometry_encoder: Annotated[dict | None, Slot("encoder")] = None,
        geometry_view_transform: Annotated[dict | None, Slot("view_transform")] = None,
        geometry_point_encoder: Annotated[dict | None, Slot("point_encoder")] = None,
        context: RunContext | None = None,
    ) -> None:
        super().__init__()
        check_choices(OccleScene.__init__, "occle_scene", compute=compute, geometry=geometry, fusion=fusion)
        if compute != "all" and not (semantic if compute == "semantic" else geometric):
            raise ValueError(f"occle_scene compute: {compute} runs the {compute} branch alone, which is switched off")
        self.compute = compute
        self.grid = grid
        if lidar_channels is None and point_channels is not None:
            if lidar_encoder not in point_channels:
                raise ValueError(
                    f"occle_scene reads point encoder '{lidar_encoder}', but the model's point encoders are: "
                    f"{', '.join(point_channels) or '(none)'}"
                )
            lidar_channels = point_channels[lidar_encoder]
        self.in_channels = int(in_channels)
        self.lidar_channels = int(_DEFAULT_LIDAR_CHANNELS if lidar_channels is None else lidar_channels)
        self.lidar_encoder = lidar_encoder
        self.out_channels = c = int(channels)
        self.semantic, self.geometric, self.projection = bool(semantic), bool(geometric), bool(projection)
        self.semantic_checkpoint = bool(semantic_checkpoint)
        self.history = [int(k) for k in (history or [])]
        if 0 in self.history or len(set(self.history)) != len(self.history):
            raise ValueError(
                f"occle_scene history: past frame offsets other than 0, each once, got {list(history or [])}"
            )
        frames = len(self.history) + 1
        both = self.in_channels + self.lidar_channels
        own = (geometry_encoder, geometry_view_transform, geometry_point_encoder)
        geo_image, geo_lidar = self.in_channels, self.lidar_channels  # what the geometric branch reads
        if any(node is not None for node in own):
            if any(node is None for node in own):
                raise ValueError(
                    "occle_scene: geometry_encoder, geometry_view_transform and geometry_point_encoder go together "
                    "(the geometric branch's own image encoder, lift and LiDAR encoder); set all three or none"
                )
            if not geometric or self.history:
                raise ValueError("occle_scene: the geometric branch's own encoders need geometric: true and no history")
            if context is None:
                raise ValueError(
                    "occle_scene: the geometric branch's own encoders are built through the run context; build the "
                    "scene with the registry (RunContext.build)"
                )
            self.geometric_inputs = _own_inputs(
                context, geometry_encoder, geometry_view_transform, geometry_point_encoder, grid
            )
            geo_image = int(self.geometric_inputs["view_transform"].out_channels)
            geo_lidar = int(self.geometric_inputs["point_encoder"].out_channels)
        # plain stems stand in for a switched-off branch, so the fusion always sees two grids
        self.stems = nn.ModuleDict()
        if self.semantic:
            unet = UNet3d(self.lidar_channels, num_classes=1, base_channels=c, depth=unet_depth)
            unet.head = nn.Identity()  # S's header is the occle_lidar_semantic head component
            self.semantic_branch = nn.ModuleDict({"lidar_unet": unet, "mix": _stem(self.in_channels + c, c)})
        else:
            self.stems["semantic"] = _stem(both, c)
        if self.geometric:
            if geometry == "cross_plane":
                self.geometric_branch: nn.Module = CrossPlaneFusion(
                    geo_lidar,
                    geo_image,
                    self.grid,
                    c,
                    num_frames=frames,
                    plane_kernel=plane_kernel,
                    heads=attention_heads,
                )
            else:
                baseline = Conv3dDeformableBaseline(
                    geo_lidar, geo_image, self.grid, c, num_frames=frames, heads=attention_heads
                )
                baseline.head = nn.Identity()  # G's header is the occle_geometry head component
                self.geometric_branch = baseline
        else:
            self.stems["geometric"] = _stem(both, c)
        self.fusion_kind = fusion
        self.fusion = (
            DualMambaUNet(
                c,
                c,
                channels=list(mamba_channels),
                d_state=mamba_state,
                chunk_size=mamba_chunk,
                checkpoint=mamba_checkpoint,
            )
            if fusion == "dual_mamba"
            else ConvFusion(c)
        )

    def forward(self, lifted: Lifted, batch: Batch, outputs: ModelOutputs) -> OccleGrids:
        image = lifted.volume
        if self.lidar_encoder not in outputs.encoded:
            raise ValueError(
                f"occle_scene reads point encoder '{self.lidar_encoder}', but the model's point encoders are: "
                f"{', '.join(outputs.encoded) or '(none)'}"
            )
        lidar = outputs.encoded[self.lidar_encoder]
        shape = self.grid.shape
        want_image, want_lidar = (self.in_channels, *shape), (self.lidar_channels, *shape)
        if tuple(image.shape[1:]) != want_image or tuple(lidar.shape[1:]) != want_lidar:
            raise ValueError(
                f"occle_scene expects the lifted image grid (B, {self.in_channels}, {', '.join(map(str, shape))}) and "
                f"the LiDAR grid (B, {self.lidar_channels}, ...) on the same grid; got {tuple(image.shape)} and "
                f"{tuple(lidar.shape)}"
            )
        lidar_semantic = semantic = geometry = None
        if self.compute == "geometric":
            geometry = self.geometric_branch(*self._frames(lidar, image, batch, outputs))
            return OccleGrids(None, self.grid, geometry=geometry, projection=self.projection)
        if self.semantic:
            if self.semantic_checkpoint and torch.is_grad_enabled():
                lidar_semantic, semantic = torch.utils.checkpoint.checkpoint(
                    self._semantic_branch, image, lidar, use_reentrant=False
                )
            else:
                lidar_semantic, semantic = self._semantic_branch(image, lidar)
            sem_in = semantic
            if self.compute == "semantic":
                return OccleGrids(None, self.grid, lidar_semantic, semantic, projection=self.projection)
        else:
            sem_in = self.stems["semantic"](torch.cat([image, lidar], dim=1))
        if self.geometric:
            lidar_frames, image_frames = self._frames(lidar, image, batch, outputs)
            geometry = self.geometric_branch(lidar_frames, image_frames)
            geo_in = geometry
        else:
            geo_in = self.stems["geometric"](torch.cat([image, lidar], dim=1))
        fused = self.fusion(sem_in, geo_in)
        return OccleGrids(fused, self.grid, lidar_semantic, semantic, geometry, self.projection)

    def _semantic_branch(self, image: Tensor, lidar: Tensor) -> tuple[Tensor, Tensor]:
        """``S`` (§3.2): the LiDAR UNet's features and their mix with the lifted image grid, each ``(B, C, X, Y, Z)``."""
        lidar_semantic = self.semantic_branch["lidar_unet"].features(lidar)
        return lidar_semantic, self.semantic_branch["mix"](torch.cat([image, lidar_semantic], dim=1))

    def _frames(self, lidar: Tensor, image: Tensor, batch: Batch, outputs: ModelOutputs) -> tuple[Tensor, Tensor]:
        """``(B, T, C, X, Y, Z)`` LiDAR and image grids: the ``history`` frames in order, then the current one
        (with the branch's own encoders: their grids of the current frame, ``T = 1``)."""
        if hasattr(self, "geometric_inputs"):
            own = self.geometric_inputs
            features = feature_levels(own["encoder"](batch.images))[own["encoder"].primary_level]
            lifted = own["view_transform"](features, batch)
            return own["point_encoder"](batch).unsqueeze(1), lifted.volume.unsqueeze(1)
        missing = [k for k in self.history if k not in outputs.history]
        if missing:
            raise ValueError(
                f"occle_scene history reads past frames {missing}; set model.input_history to include them "
                f"(encoded: {sorted(outputs.history) or 'none'})"
            )
        past = [outputs.history[k] for k in self.history]
        lidars = [p.encoded[self.lidar_encoder] for p in past] + [lidar]
        images = [p.lifted.volume for p in past] + [image]
        return torch.stack(lidars, dim=1), torch.stack(images, dim=1)

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple[Any, ...]:
        """A random lifted grid with ``channels`` channels and a random 32-channel LiDAR grid (the default
        ``lidar_channels``) under ``outputs.encoded["lidar"]``."""
        gen = torch.Generator().manual_seed(0)
        image = torch.randn(len(batch), channels, *grid.shape, generator=gen)
        lidar = torch.randn(len(batch), _DEFAULT_LIDAR_CHANNELS, *grid.shape, generator=gen).relu()
        outputs = ModelOutputs(image_features=None, lifted=None, scene=None, heads={}, query=_no_query)
        outputs.encoded["lidar"] = lidar
        return (Lifted(volume=image, grid=grid), batch, outputs)


def _own_inputs(
    context: RunContext, encoder: dict, view_transform: dict, point_encoder: dict, grid: GridSpec
) -> nn.ModuleDict:
    """The geometric branch's own image encoder, lift and LiDAR encoder, built through the run ``context`` from their
    config nodes with the arguments the core model gives its own (``in_channels`` / ``image_stride`` / levels from
    the encoder, the grid)."""
    enc = context.build("encoder", encoder)
    lift = context.build(
        "view_transform",
        view_transform,
        in_channels=enc.out_channels,
        image_stride=enc.stride,
        level_channels=list(enc.level_channels),
        level_strides=list(enc.level_strides),
        grid=grid,
    )
    points = context.build("point_encoder", point_encoder, grid=grid)
    for built, kind, want in (
        (enc, "encoder", ImageEncoder),
        (lift, "view_transform", ViewTransform),
        (points, "point_encoder", PointEncoder),
    ):
        if not isinstance(built, want):
            raise TypeError(f"occle_scene geometry_{kind}: '{built.__class__.__name__}' is not a {want.__name__}")
    if getattr(lift, "reads_outputs", False) or getattr(lift, "reads", ()):
        raise ValueError("occle_scene geometry_view_transform: a lift that reads the model's outputs cannot run here")
    return nn.ModuleDict({"encoder": enc, "view_transform": lift, "point_encoder": points})


def _no_query(*args: Any, **kwargs: Any) -> Any:
    raise TypeError("no queryable head in the conformance outputs")


def conformance_scene(batch: Batch, grid: GridSpec, channels: int) -> OccleGrids:
    """Random :class:`OccleGrids` with every grid ``(B, channels, X, Y, Z)`` (heads' conformance inputs)."""
    gen = torch.Generator().manual_seed(0)
    grids = [torch.randn(len(batch), channels, *grid.shape, generator=gen) for _ in range(4)]
    return OccleGrids(grids[0], grid, grids[1], grids[2], grids[3], projection=True)
