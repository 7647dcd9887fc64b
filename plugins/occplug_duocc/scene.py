"""DuOcc's scene representations: the 3D-FPN and StreamAgg (``duocc_stream``), and a multi-frame stacking
baseline (``duocc_stacking``), both streaming through the core's :class:`~occplug.streams.StreamState`.

Both read the view transform's ``V_init`` ``(B, C_init, X, Y, Z)`` on the evaluation grid (ego frame), run
the lightweight 3D-FPN (:class:`~occplug_duocc.blocks.fpn3d.VoxelFPN3D`) to ``V_curr`` ``(B, C, X/d, Y/d, Z/d)``
(``d = downsample``, DuOcc: 2, on every axis: the synthetic grids have ``Z = 8``, which halves to 4, so ``Z``
is halved as in the paper) and return a :class:`StreamVoxelScene` on that coarse grid, whose
``label_grid`` is the evaluation grid the ``duocc_decoder`` head upsamples back to.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any, Literal

import torch
from torch import Tensor, nn

from occplug.constraints import Length, Positive, Range, check_choices
from occplug.data import Batch
from occplug.geometry import GridSpec, class_fractions, relative_pose, warp_volume
from occplug.interfaces import DenseVoxelScene, Lifted, ModelOutputs, SceneRepresentation
from occplug.streams import StreamState

from .blocks.fpn3d import VoxelFPN3D
from .blocks.queryagg import QueryAggregation, QueryAggSettings, resolve_detection_classes
from .blocks.stream_agg import StreamAggregation

__all__ = [
    "DETECTION_CLASSES_KEY",
    "DETECTION_KEY",
    "DQA_SELECTED_KEY",
    "FORECAST_KEY",
    "OCCUPIED_KEY",
    "DuOccStacking",
    "DuOccStream",
    "StreamVoxelScene",
    "coarse_grid",
]

#: ``outputs.extras`` key of the occupied-mask logits ``(B, X, Y, Z)`` on the label grid (training only).
OCCUPIED_KEY = "duocc_stream/occupied_logits"
#: ``outputs.extras`` key of the forecasting logits ``(B, K, X, Y, Z)`` on the label grid (training only).
FORECAST_KEY = "duocc_stream/forecast_logits"
#: ``outputs.extras`` key of the detector's :class:`~occplug_duocc.blocks.detector.DetectorOutput` (with ``query_agg``;
#: every stage: boxes ``(B, Q, 9)`` per layer in the current ego frame).
DETECTION_KEY = "duocc_stream/detection"
#: ``outputs.extras`` key of the label id of each detection class (a tuple of ints, detection class order).
DETECTION_CLASSES_KEY = "duocc_stream/detection_classes"
#: ``outputs.extras`` key of the ``(B, Q)`` bool mask of the queries DQA wrote into the voxels.
DQA_SELECTED_KEY = "duocc_stream/dqa_selected"


def coarse_grid(grid: GridSpec, factor: int) -> GridSpec:
    """``grid``'s range at ``factor`` times its voxel size (ego frame); every axis must divide evenly.

    Raises:
        ValueError: a contracted grid, or an axis of ``grid.shape`` not divisible by ``factor`` (one line).
    """
    if grid.contraction is not None:
        raise ValueError("DuOcc's voxel scenes need a metric grid (no contraction)")
    coarse = GridSpec(grid.range, tuple(v * factor for v in grid.voxel_size))
    if any(c * factor != f for c, f in zip(coarse.shape, grid.shape, strict=True)):
        raise ValueError(
            f"DuOcc downsample {factor}: grid shape {grid.shape} is not divisible by {factor} on every axis"
        )
    return coarse


class StreamVoxelScene(DenseVoxelScene):
    """A dense voxel scene on a coarse grid that knows the label grid a decoder upsamples it to.

    Attributes:
        features: ``V_fin`` ``(B, C, x, y, z)`` on ``grid`` (current ego frame).
        grid: the coarse grid (``label_grid`` at ``downsample`` times its voxel size).
        label_grid: the evaluation grid ``(X, Y, Z)``, same range and frame.
        cache: per-forward memo of decoders (``duocc_decoder`` keeps its upsampled volume here, so evaluating
            the forward logits a second time costs nothing); lives as long as this scene object.
    """

    def __init__(self, features: Tensor, grid: GridSpec, label_grid: GridSpec) -> None:
        super().__init__(features, grid)
        self.label_grid = label_grid
        self.cache: dict[Any, Tensor] = {}


class _DuOccVoxels(SceneRepresentation):
    """Shared part: the grid bookkeeping and the 3D-FPN ``V_init -> V_curr``."""

    def __init__(
        self,
        in_channels: int,
        grid: GridSpec,
        channels: int,
        downsample: int,
        fpn_channels: Sequence[int],
        fpn_blocks: Sequence[int],
    ) -> None:
        super().__init__()
        if downsample not in (1, 2):
            raise ValueError(f"downsample must be 1 or 2 (DuOcc: 2), got {downsample}")
        self.grid = grid
        self.downsample = int(downsample)
        self.coarse = coarse_grid(self.grid, self.downsample)
        self.out_channels = int(channels)
        self.fpn = VoxelFPN3D(in_channels, self.out_channels, tuple(fpn_channels), tuple(fpn_blocks))

    def current(self, lifted: Lifted) -> Tensor:
        """``V_curr`` ``(B, C, x, y, z)`` on :attr:`coarse` from ``V_init`` ``(B, C_init, X, Y, Z)`` on :attr:`grid`."""
        volume = lifted.volume
        if volume.dim() != 5 or lifted.grid != self.grid or tuple(volume.shape[2:]) != self.grid.shape:
            raise ValueError(
                f"{type(self).__name__}: the lifted volume {tuple(volume.shape)} on grid {lifted.grid.shape} is not a "
                f"3D volume on the scene's grid {self.grid.shape}; give the view transform and the scene the same grid"
            )
        return self.fpn(volume, self.coarse.shape)

    def scene(self, features: Tensor) -> StreamVoxelScene:
        return StreamVoxelScene(features, self.coarse, self.grid)


def _itself(current: Any) -> Any:
    """The reset of DuOcc's public code: a stream restarts from the current frame's feature, not from zeros."""
    return current


class DuOccStream(_DuOccVoxels):
    """DuOcc's voxel branch: 3D-FPN, then StreamAgg with the history in a :class:`~occplug.streams.StreamState`.

    Per frame (paper §3.1, Tab. 4 B): ``V_curr = FPN3D(V_init)``; the history ``V_fin^{t-1}`` of each batch
    slot is warped into the current ego frame (Eqs. 1-2), refined by RefineNet (Eqs. 3-4) and fused with
    ``V_curr`` (Eq. 5 adds; ``fusion: concat`` is the public code's concatenation + conv); the result is
    ``V_fin^t`` (no query aggregation here: ``V_fin = V_S.A``) and is stored, detached, as the next frame's
    history. At a stream start (``batch.is_sequence_start``, another scene, a frame jump, or more than
    ``max_gap_s`` seconds since the stored frame) the history is ``V_curr`` itself, unwarped (the public
    code's reset), and the state is kept per slot and per stage (train / val / test / predict).
    ``stream: false`` is the single-frame model (Tab. 4 A): ``V_fin = V_curr``, nothing is kept.

    In training the auxiliary heads publish their logits in ``outputs.extras`` (:data:`OCCUPIED_KEY`,
    :data:`FORECAST_KEY`) for the ``duocc_occupied`` and ``duocc_forecast`` supervision sources.

    ``query_agg`` (:class:`~occplug_duocc.blocks.queryagg.QueryAggSettings`, off when None) adds QueryAgg (§3.2) after StreamAgg:
    the image-to-query detector on ``outputs.image_levels``, V2Q into ``V_S.A``, DQA on the selected queries and the
    voxel FFN give ``V_fin``, which is what the history keeps. The detector's state lives in the same
    :class:`~occplug.streams.StreamState` entry as the voxel history (``{"voxels", "detector"}``), so it is kept per
    slot and stage and reset with it. The detections go to ``outputs.extras`` (:data:`DETECTION_KEY`,
    :data:`DETECTION_CLASSES_KEY`, :data:`DQA_SELECTED_KEY`) for the ``duocc_detection`` supervision source.

    Args:
        in_channels: ``C_init`` of ``V_init`` (the view transform's ``out_channels``).
        grid: the evaluation grid of ``V_init`` (ego frame), ``{range, voxel_size}``.
        channels: ``C`` of ``V_curr`` and ``V_fin``.
        downsample: ``d``, the 3D-FPN's output scale (DuOcc: 2; 1 keeps the lifted resolution).
        fpn_channels, fpn_blocks: the 3D-FPN's three stage widths and block counts.
        num_classes: ``K`` of the forecasting head (Occ3D and the synthetic world: 18).
        stream: carry the history (False: the single-frame model A).
        fusion: ``add`` (Eq. 5) or ``concat`` (the public code).
        refine: RefineNet on the warped history (Tab. 5 row 2).
        occupied_head: the occupied-mask head on RefineNet's spatial attention (Tab. 5 row 4; needs ``refine``).
        forecast_head: the forecasting head on the refined history (Tab. 5 row 3).
        occupied_hidden: width of the occupied head's deconvolution (code: 64).
        reduction: RefineNet's channel-attention reduction (code: 16).
        residual_relu: RefineNet's ReLU after the residual (code: on; Eq. 4: off).
        max_gap_s: seconds between frames above which the history restarts (DuOcc: 2.0).
        train_cut_prob: probability of restarting a continuing history in training (not in the paper or
            the code; 0: off): the current frame must then stand alone, as at a stream start.
        query_agg: QueryAgg's settings (a mapping in a config, checked by config validation:
            :class:`~occplug_duocc.blocks.queryagg.QueryAggSettings`: ``v2q``, ``dqa``, ``gt_boxes``, ``selection``,
            ``detector``, ...), or None (off: Tab. 4 B). Needs ``stream: true``.
        level_channels: the image encoder's levels' channels, finest first (given by the model; QueryAgg's
            detector reads those levels).
        class_names: the run's class names (given by the model): QueryAgg's detection classes default to their
            ``dynamic`` group and must be their label ids.
        warp_sampling: StreamAgg's warp (:class:`~occplug_duocc.blocks.stream_agg.StreamAggregation`):
            ``voxel_centres`` (Eqs. 1-2) or ``public_linspace`` (the public code's sampling points).
        history_reset: when the history continues. Both read ``dt`` = current timestamp - stored timestamp
            (seconds; the public code's ``time_interval`` is the same difference, current minus previous).
            ``paper``: the stream continues iff ``0 < dt <= max_gap_s`` and the frame index advances by one
            (also the :class:`~occplug.streams.StreamState` default); ``public``: iff ``0 < |dt| <= max_gap_s``,
            with no frame-index check, as the public code, whose only rule is the time (a step back in time of
            up to 2 s keeps and warps the history). In both, a sequence start or another scene restarts (the code
            reads absolute nuScenes timestamps, where another scene is always a time jump; here scenes may share
            timestamps).
        history_source: what the stream stores for the next frame. ``features`` (DuOcc): ``V_fin``.
            ``ground_truth`` (an oracle of StreamAgg's own mechanism, not in the paper or the code): the frame's
            ground-truth semantic occupancy (``batch.voxel_labels``, at training and evaluation alike) on the coarse
            grid, each coarse voxel the mean of a learned per-class table ``(num_classes, C)`` over its
            ``downsample ** 3`` labelled voxels (:func:`~occplug.geometry.class_fractions`; unknown labels count for
            nothing), then warped, refined and fused exactly as a learned history is. The table learns through the
            warp (the history is embedded in the frame that reads it; it is linear, so embedding then warping is
            warping the class shares then embedding). A stream start reads ``V_curr`` as in ``features``.

    Forward:
        :class:`~occplug.interfaces.Lifted` ``V_init`` ``(B, C_init, X, Y, Z)``, the batch (``scene``,
        ``frame_index``, ``timestamp``, ``is_sequence_start``, ``ego_to_global``) and the model's outputs ->
        :class:`StreamVoxelScene` with ``V_fin`` ``(B, C, X/d, Y/d, Z/d)`` in the current ego frame.
    """

    stateful = True
    reads_outputs = True
    #: the model also gives the run's class names (QueryAgg's detection classes are a class group of them)
    given = (*SceneRepresentation.given, "class_names")

    def __init__(
        self,
        in_channels: int,
        grid: GridSpec,
        num_classes: Annotated[int, Positive],
        channels: Annotated[int, Positive] = 32,
        downsample: Annotated[int, Range(low=1, high=2)] = 2,
        fpn_channels: Annotated[list[Annotated[int, Positive]], Length(exact=3)] = [16, 32, 32],  # noqa: B006
        fpn_blocks: Annotated[list[Annotated[int, Positive]], Length(exact=3)] = [1, 1, 1],  # noqa: B006
        stream: bool = True,
        fusion: Literal["add", "concat"] = "add",
        refine: bool = True,
        occupied_head: bool = True,
        forecast_head: bool = True,
        occupied_hidden: Annotated[int, Positive] = 16,
        reduction: Annotated[int, Positive] = 16,
        residual_relu: bool = False,
        max_gap_s: Annotated[float, Positive] = 2.0,
        train_cut_prob: Annotated[float, Range(low=0.0, high=1.0, high_open=True)] = 0.0,
        query_agg: QueryAggSettings | None = None,
        level_channels: Sequence[int] | None = None,
        class_names: Sequence[str] | None = None,
        warp_sampling: Literal["voxel_centres", "public_linspace"] = "voxel_centres",
        history_reset: Literal["paper", "public"] = "paper",
        history_source: Literal["features", "ground_truth"] = "features",
    ) -> None:
        super().__init__(in_channels, grid, channels, downsample, fpn_channels, fpn_blocks)
        check_choices(
            DuOccStream.__init__,
            "duocc_stream",
            warp_sampling=warp_sampling,
            history_reset=history_reset,
            history_source=history_source,
        )
        self.stream = bool(stream)
        self.history_source = history_source
        if self.history_source == "ground_truth" and not self.stream:
            raise ValueError("duocc_stream history_source: ground_truth needs stream: true (it is a history)")
        self.num_classes = int(num_classes)
        #: ``(K, C)`` the oracle history's per-class embedding (``history_source: ground_truth`` only)
        self.history_embedding: nn.Embedding | None = None
        if self.history_source == "ground_truth":
            self.history_embedding = nn.Embedding(self.num_classes, self.out_channels)
        if query_agg is not None and not self.stream:
            raise ValueError("duocc_stream query_agg needs stream: true (the detector state and V_fin are streamed)")
        self.stateful = self.stream  # the single-frame model keeps nothing (export treats it as stateless)
        self.agg: StreamAggregation | None = None
        if self.stream:
            self.agg = StreamAggregation(
                self.out_channels,
                num_classes,
                self.coarse,
                fusion=fusion,
                refine=refine,
                occupied_head=occupied_head,
                forecast_head=forecast_head,
                upsample=self.downsample,
                occupied_hidden=occupied_hidden,
                reduction=reduction,
                residual_relu=residual_relu,
                warp_sampling=warp_sampling,
            )
            public = history_reset == "public"
            self.history = StreamState(
                on_reset=_itself,
                max_gap_s=max_gap_s,
                max_frame_step=None if public else 1,
                train_cut_prob=train_cut_prob,
                allow_backward=public,
            )
        self.query_agg: QueryAggregation | None = None
        if query_agg is not None:
            if not level_channels:
                raise ValueError(
                    "duocc_stream query_agg needs level_channels, the image encoder's (the model gives them)"
                )
            query_agg = resolve_detection_classes(query_agg, class_names)
            self.query_agg = QueryAggregation(self.out_channels, self.coarse, level_channels, query_agg)

    def forward(self, lifted: Lifted, batch: Batch, outputs: ModelOutputs | None = None) -> StreamVoxelScene:
        """``V_fin`` of this frame; stores it as the history of each slot (see the class docstring)."""
        v_curr = self.current(lifted)
        if self.agg is None:
            return self.scene(v_curr)
        qa = self.query_agg
        oracle = self.history_embedding is not None
        # the oracle stores the class shares (B, K, x, y, z) of this frame; reset slots read them back unused
        stored_now = self._label_shares(batch, v_curr) if oracle else v_curr
        if qa is None:
            read = self.history.get(batch, stored_now)  # reset slots read V_curr itself
            history, det_state = read.value, None
        else:
            det_template = qa.state_template(batch, v_curr.device)
            read = self.history.get(batch, {"voxels": stored_now, "detector": det_template})
            history, det_state = read.value["voxels"], read.value["detector"]
        if oracle:
            # embedded here, in the frame that reads it, so the table gets this frame's gradient
            history = torch.einsum("bkxyz,kc->bcxyz", history.to(v_curr.dtype), self.history_embedding.weight)
        out = self.agg(v_curr, history, read.prev_to_current, read.reset, detach_history=not oracle)
        v_fin = out.fused  # V_S.A
        if qa is not None:
            if outputs is None or not outputs.image_levels:
                raise ValueError("duocc_stream query_agg reads the image levels: call it with the model's outputs")
            q = qa(v_fin, outputs.image_levels, batch, det_state, read.reset, read.prev_to_current, read.dt)
            v_fin = q.volume
            outputs.extras[DETECTION_KEY] = q.detection
            outputs.extras[DETECTION_CLASSES_KEY] = qa.classes
            outputs.extras[DQA_SELECTED_KEY] = q.selected
            self.history.update(batch, {"voxels": v_fin if not oracle else stored_now, "detector": q.state})
        else:
            self.history.update(batch, v_fin if not oracle else stored_now)
        if outputs is not None:
            if out.occupied_logits is not None:
                outputs.extras[OCCUPIED_KEY] = out.occupied_logits
            if out.forecast_logits is not None:
                outputs.extras[FORECAST_KEY] = out.forecast_logits
        return self.scene(v_fin)

    def _label_shares(self, batch: Batch, v_curr: Tensor) -> Tensor:
        """``(B, K, x, y, z)`` this frame's class shares on the coarse grid (the oracle history, before embedding)."""
        labels = batch.voxel_labels
        if labels is None or tuple(labels.shape[1:]) != self.grid.shape:
            got = None if labels is None else tuple(labels.shape)
            raise ValueError(
                f"duocc_stream history_source: ground_truth reads batch.voxel_labels on the grid {self.grid.shape} "
                f"(at training and evaluation), got {got}"
            )
        return class_fractions(labels.to(v_curr.device), self.num_classes, self.downsample)


class DuOccStacking(_DuOccVoxels):
    """Multi-frame stacking baseline: ``V_curr`` concatenated with the ``K`` previous ``V_curr``, warped.

    The state of each slot holds the ``K`` previous frames' ``V_curr`` ``(K, C, x, y, z)``, each in its own ego
    frame, with their ``ego_to_global`` poses ``(K, 4, 4)`` (float64); each step warps every one directly from
    its own frame into the current ego frame (no repeated resampling), concatenates
    ``[V_curr, warp(V_{t-1}), ..., warp(V_{t-K})]`` and fuses them with ``1x1x1 conv -> GroupNorm -> ReLU``.
    ``K`` counts past frames only. At a stream start every past entry is ``V_curr`` (the current frame repeated,
    as the reset of ``duocc_stream``); the first ``K`` frames of a stream therefore repeat their oldest frame.

    Args:
        in_channels, grid, channels, downsample, fpn_channels, fpn_blocks: as ``duocc_stream``.
        num_history: ``K >= 1`` past frames.
        max_gap_s: seconds between frames above which the stack restarts.

    Forward:
        as ``duocc_stream`` (no auxiliary outputs): :class:`StreamVoxelScene` with the fused ``(B, C, x, y, z)``.
    """

    stateful = True

    def __init__(
        self,
        in_channels: int,
        grid: GridSpec,
        channels: Annotated[int, Positive] = 32,
        downsample: Annotated[int, Range(low=1, high=2)] = 2,
        fpn_channels: Annotated[list[Annotated[int, Positive]], Length(exact=3)] = [16, 32, 32],  # noqa: B006
        fpn_blocks: Annotated[list[Annotated[int, Positive]], Length(exact=3)] = [1, 1, 1],  # noqa: B006
        num_history: Annotated[int, Positive] = 2,
        max_gap_s: Annotated[float, Positive] = 2.0,
    ) -> None:
        super().__init__(in_channels, grid, channels, downsample, fpn_channels, fpn_blocks)
        if num_history < 1:
            raise ValueError(f"duocc_stacking num_history must be >= 1 (past frames), got {num_history}")
        self.num_history = int(num_history)
        c = self.out_channels
        self.fuse = nn.Sequential(
            nn.Conv3d((self.num_history + 1) * c, c, 1, bias=False),
            nn.GroupNorm(_groups(c), c),
            nn.ReLU(inplace=True),
        )
        self.history = StreamState(on_reset=_itself, max_gap_s=max_gap_s)

    def forward(self, lifted: Lifted, batch: Batch) -> StreamVoxelScene:
        """Fuse ``V_curr`` with its ``K`` warped predecessors; push ``V_curr`` onto each slot's stack."""
        v_curr = self.current(lifted)
        b, k = v_curr.shape[0], self.num_history
        pose = batch.ego_to_global.to(device=v_curr.device, dtype=torch.float64)
        current = {
            "features": v_curr.detach().unsqueeze(1).expand(b, k, *v_curr.shape[1:]),
            "poses": pose.unsqueeze(1).expand(b, k, 4, 4),
        }
        read = self.history.get(batch, current)  # reset slots: K copies of V_curr at the current pose
        past, poses = read.value["features"], read.value["poses"]
        motion = relative_pose(poses, pose.unsqueeze(1).expand_as(poses))  # (B, K, 4, 4) past ego -> current ego
        warped = warp_volume(past.flatten(0, 1), self.coarse, motion.flatten(0, 1)).view_as(past)
        # a reset slot's entries are this frame's own volume: take them unwarped (bit-exact, as duocc_stream)
        warped = torch.where(read.reset.view(b, 1, 1, 1, 1, 1), current["features"], warped)
        fused = self.fuse(torch.cat([v_curr, warped.flatten(1, 2)], dim=1))
        self.history.update(
            batch,
            {
                "features": torch.cat([v_curr.unsqueeze(1), past[:, : k - 1]], dim=1),
                "poses": torch.cat([pose.unsqueeze(1), poses[:, : k - 1]], dim=1),
            },
        )
        return self.scene(fused)


def _groups(channels: int) -> int:
    """GroupNorm groups: 16 (the public code's fusion) or the largest divisor of ``channels`` below it."""
    return next(g for g in range(min(16, channels), 0, -1) if channels % g == 0)
