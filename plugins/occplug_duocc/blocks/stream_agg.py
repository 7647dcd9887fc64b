"""DuOcc's stream-based voxel feature aggregation (StreamAgg, paper §3.1, Fig. 3, Tab. 5).

Per frame: warp the previous frame's final voxel feature into the current ego frame (Eqs. 1-2, the
core's :func:`~occplug.geometry.warp_volume`), refine it with :class:`RefineNet` (a bottleneck with a
3D CBAM, Eqs. 3-4) and fuse it with the current voxel feature (Eq. 5). Two auxiliary heads supervise
the refinement in training only: the occupied-mask head reads the spatial-attention logits ``M_s``,
the forecasting head reads the refined history (suppl. A.3: a 3D deconvolution, then a pointwise MLP).

All volumes are laid out ``(B, C, X, Y, Z)`` on one :class:`~occplug.geometry.GridSpec` in the ego
frame of their frame. The history is the previous frame's ``V_fin`` (after DQA in the full model),
detached: no gradient flows across frames.

Paper versus the public code (``models/heads/streamagg/streamagg.py``, ``refinenet.py``), and what is chosen here:

* fusion: Eq. 5 adds (``fusion="add"``, default); the code concatenates, then a 1x1x1 conv, GroupNorm
  and ReLU (``fusion="concat"``);
* reset (a sequence start, or a gap outside ``(0, 2] s``): as the code, the history becomes the current
  feature ``V_curr`` itself (detached, no warp), not zeros; when to reset is the scene's (``duocc_stream``
  ``history_reset``: ``public`` keeps the history also for a step back in time of up to 2 s, as the code);
* the occupied head ends in a logit trained with plain BCE-with-logits (:func:`occupied_loss`); the code
  applies a sigmoid and then ``BCEWithLogitsLoss`` (a double sigmoid);
* RefineNet follows Eq. 4 (no activation after the residual); ``residual_relu=True`` adds the code's ReLU;
* warp: each destination voxel centre is read (``align_corners=False``); ``warp_sampling="public_linspace"`` samples
  at the code's ``linspace`` points with ``align_corners=True`` instead (:func:`public_linspace_warp`);
* occupied loss: the mean BCE over the supervised voxels; ``weighting="public_mean"`` multiplies it by the mean of
  the code's per-voxel weights (1.0 occupied, 0.1 free), as the code does (:func:`occupied_loss`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occplug.constraints import Positive, check_choices
from occplug.geometry import GridSpec, warp_volume
from occplug.nn import ChannelAttention, SpatialAttention3d, cbam

__all__ = [
    "PUBLIC_OCCUPIED_WEIGHTS",
    "CBAMAttention",
    "RefineNet",
    "StreamAggOutput",
    "StreamAggregation",
    "UpsampleDecoder",
    "forecast_loss",
    "occupied_loss",
    "public_linspace_warp",
]

#: the public code's per-voxel weights of its occupied-mask BCE (occupied, free).
PUBLIC_OCCUPIED_WEIGHTS = (1.0, 0.1)


@dataclass
class CBAMAttention:
    """The 3D CBAM maps of :class:`RefineNet` (Eq. 3).

    Attributes:
        channel: ``M_c``, ``(B, C, 1, 1, 1)`` in ``(0, 1)``.
        spatial_logits: ``M_s``, ``(B, 1, X, Y, Z)`` before the sigmoid (the occupied head reads these).
    """

    channel: Tensor
    spatial_logits: Tensor

    @property
    def spatial(self) -> Tensor:
        """``sigma(M_s)``, ``(B, 1, X, Y, Z)`` in ``(0, 1)`` (the factor of Eq. 4)."""
        return torch.sigmoid(self.spatial_logits)


class RefineNet(nn.Module):
    """Bottleneck ``C -> C/4 -> C`` with a 3D CBAM (the core's :func:`~occplug.nn.cbam`) and a residual (Eqs. 3-4).

    ``V_out = Bottleneck(V_warp)``;
    ``M_c = sigma(MLP(Avg_s(V_out)) + MLP(Max_s(V_out)))`` (one MLP shared by both descriptors);
    ``M_s = Conv3D([Avg_c(M_c * V_out); Max_c(M_c * V_out)])``;
    ``V_refwarp = sigma(M_s) * (M_c * V_out) + V_warp``.

    Args:
        channels: ``C`` (divisible by ``bottleneck_ratio``).
        bottleneck_ratio: ``C / C_mid`` of the bottleneck (paper: 4).
        reduction: hidden width ``max(1, C // reduction)`` of the channel-attention MLP (code: 16).
        spatial_kernel: odd kernel size of the spatial-attention conv (code: 7).
        residual_relu: apply a ReLU after the residual (the public code does; Eq. 4 does not).

    Forward: ``V_warp (B, C, X, Y, Z)`` -> ``(V_refwarp (B, C, X, Y, Z), CBAMAttention)``.
    """

    def __init__(
        self,
        channels: Annotated[int, Positive],
        bottleneck_ratio: Annotated[int, Positive] = 4,
        reduction: Annotated[int, Positive] = 16,
        spatial_kernel: Annotated[int, Positive] = 7,
        residual_relu: bool = False,
    ) -> None:
        super().__init__()
        if channels % bottleneck_ratio:
            raise ValueError(f"RefineNet: channels {channels} not divisible by bottleneck_ratio {bottleneck_ratio}")
        if spatial_kernel % 2 == 0:
            raise ValueError(f"RefineNet: spatial_kernel must be odd (same-size output), got {spatial_kernel}")
        mid = channels // bottleneck_ratio
        self.bottleneck = nn.Sequential(
            nn.Conv3d(channels, mid, 1, bias=False),
            nn.BatchNorm3d(mid),
            nn.ReLU(inplace=True),
            nn.Conv3d(mid, mid, 3, padding=1, bias=False),
            nn.BatchNorm3d(mid),
            nn.ReLU(inplace=True),
            nn.Conv3d(mid, channels, 1, bias=False),
            nn.BatchNorm3d(channels),
        )
        # the core's CBAM parts, held here by name (not as a CBAM submodule) so the state-dict keys stay
        # ``channel_mlp.*`` / ``spatial_conv.weight``
        self.channel_mlp = ChannelAttention(channels, reduction, dims=3)
        self.spatial_conv = SpatialAttention3d(spatial_kernel)
        self.residual_relu = bool(residual_relu)

    def forward(self, warped: Tensor) -> tuple[Tensor, CBAMAttention]:
        """Refine ``warped`` ``(B, C, X, Y, Z)``; returns the refined volume and the attention maps."""
        out = self.bottleneck(warped)
        attended, channel, spatial_logits = cbam(out, self.channel_mlp, self.spatial_conv)  # M_c * V_out, M_c, M_s
        refined = torch.sigmoid(spatial_logits) * attended + warped
        if self.residual_relu:
            refined = F.relu(refined)
        return refined, CBAMAttention(channel=channel, spatial_logits=spatial_logits)


class UpsampleDecoder(nn.Module):
    """DuOcc's decoder shape (suppl. A.3): a 3D deconvolution by ``scale``, then a pointwise MLP.

    ``ConvTranspose3d(k=s, stride=s) -> BN -> ReLU -> Conv3d 1x1x1`` (``scale=1``: a 1x1x1 conv instead
    of the deconvolution), as the code's occupied and forecasting heads.

    Forward: ``(B, C_in, X, Y, Z)`` -> ``(B, C_out, sX, sY, sZ)``.
    """

    def __init__(
        self,
        in_channels: Annotated[int, Positive],
        hidden: Annotated[int, Positive],
        out_channels: Annotated[int, Positive],
        scale: Annotated[int, Positive] = 2,
    ) -> None:
        super().__init__()
        up = (
            nn.ConvTranspose3d(in_channels, hidden, scale, stride=scale, bias=False)
            if scale > 1
            else nn.Conv3d(in_channels, hidden, 1, bias=False)
        )
        self.net = nn.Sequential(up, nn.BatchNorm3d(hidden), nn.ReLU(inplace=True), nn.Conv3d(hidden, out_channels, 1))

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


@dataclass
class StreamAggOutput:
    """What :class:`StreamAggregation` returns for one frame (all in the current ego frame).

    Attributes:
        fused: ``V_S.A``, ``(B, C, X, Y, Z)`` (Eq. 5).
        warped: ``V_warp``, ``(B, C, X, Y, Z)``: the history warped into this frame; ``V_curr`` itself
            (detached) for reset samples.
        refined: ``V_refwarp``, ``(B, C, X, Y, Z)`` (``warped`` when ``refine=False``).
        attention: RefineNet's CBAM maps, or None when ``refine=False``.
        occupied_logits: ``(B, sX, sY, sZ)`` one logit per label voxel ("not free"), training only, else None.
        forecast_logits: ``(B, K, sX, sY, sZ)`` class logits of the current frame from the history,
            training only, else None.
    """

    fused: Tensor
    warped: Tensor
    refined: Tensor
    attention: CBAMAttention | None = None
    occupied_logits: Tensor | None = None
    forecast_logits: Tensor | None = None


class StreamAggregation(nn.Module):
    """Motion-aware warping, RefineNet and fusion of the history with the current voxel feature (§3.1).

    Each part of DuOcc's StreamAgg ablation (Tab. 5) can be switched off: ``refine=False`` fuses the
    warped history as it is; ``occupied_head`` / ``forecast_head`` drop the auxiliary heads.

    Args:
        channels: ``C`` of the voxel features.
        num_classes: ``K`` classes of the forecasting head (free included, e.g. 18 on Occ3D).
        grid: the grid the volumes lie on (``GridSpec`` or ``{range, voxel_size}``), ego frame.
        fusion: ``"add"`` (Eq. 5) or ``"concat"`` (the public code: concatenate ``[refined, V_curr]``,
            1x1x1 conv to ``C``, GroupNorm, ReLU).
        refine: use :class:`RefineNet` on the warped history.
        occupied_head: add the occupied-mask head (needs ``refine``: it reads ``M_s``).
        forecast_head: add the forecasting head.
        upsample: scale from the feature grid to the label grid of the auxiliary heads (DuOcc: 2).
        occupied_hidden: width of the occupied head's deconvolution (code: 64).
        reduction: RefineNet's channel-attention reduction (code: 16).
        residual_relu: RefineNet's ReLU after the residual (code: on; Eq. 4: off).
        warp_sampling: where the history is read: ``"voxel_centres"`` (Eqs. 1-2: every voxel centre, mapped into
            the previous frame, :func:`~occplug.geometry.warp_volume`) or ``"public_linspace"`` (the public code's
            points, :func:`public_linspace_warp`: translations move the content by ``(N - 1) / N`` of their voxel
            count per axis; needs a square x-y grid without contraction).

    Forward:
        ``(v_curr, v_hist, prev_to_current, reset)`` -> :class:`StreamAggOutput`; see :meth:`forward`.
        The module holds no state: a streaming component keeps the history in a
        :class:`occplug.streams.StreamState` (``max_gap_s=2.0``) and passes ``read.value``,
        ``read.prev_to_current`` and ``read.reset``.
    """

    def __init__(
        self,
        channels: Annotated[int, Positive],
        num_classes: Annotated[int, Positive],
        grid: GridSpec,
        fusion: Literal["add", "concat"] = "add",
        refine: bool = True,
        occupied_head: bool = True,
        forecast_head: bool = True,
        upsample: Annotated[int, Positive] = 2,
        occupied_hidden: Annotated[int, Positive] = 64,
        reduction: Annotated[int, Positive] = 16,
        residual_relu: bool = False,
        warp_sampling: Literal["voxel_centres", "public_linspace"] = "voxel_centres",
    ) -> None:
        super().__init__()
        check_choices(StreamAggregation.__init__, "StreamAggregation", fusion=fusion, warp_sampling=warp_sampling)
        if occupied_head and not refine:
            raise ValueError(
                "StreamAggregation occupied_head reads RefineNet's spatial attention: it needs refine=True"
            )
        self.channels, self.num_classes = int(channels), int(num_classes)
        self.grid = grid
        if warp_sampling == "public_linspace":
            _check_public_linspace_grid(self.grid)
        self.warp_sampling = warp_sampling
        self.fusion = fusion
        self.refine = RefineNet(channels, reduction=reduction, residual_relu=residual_relu) if refine else None
        if fusion == "concat":
            self.fuse = nn.Sequential(
                nn.Conv3d(2 * channels, channels, 1, bias=False),
                nn.GroupNorm(math.gcd(16, channels), channels),
                nn.ReLU(inplace=True),
            )
        self.occupied = UpsampleDecoder(1, occupied_hidden, 1, upsample) if occupied_head else None
        self.forecast = UpsampleDecoder(channels, channels, num_classes, upsample) if forecast_head else None

    def forward(
        self,
        v_curr: Tensor,
        v_hist: Tensor | None = None,
        prev_to_current: Tensor | None = None,
        reset: Tensor | None = None,
        detach_history: bool = True,
    ) -> StreamAggOutput:
        """Aggregate the history into the current frame.

        Args:
            v_curr: ``V_curr``, ``(B, C, X, Y, Z)`` in the current ego frame.
            v_hist: ``V_fin`` of the previous frame, ``(B, C, X, Y, Z)`` in the previous ego frame; it is
                detached here unless ``detach_history`` is False. None: no history at all (every sample is reset).
            prev_to_current: ``(B, 4, 4)`` previous ego -> current ego (``T_{g->e}^t T_{e->g}^{t-1}``,
                Eq. 1; :func:`occplug.geometry.relative_pose`); None: identity. Ignored where ``reset``.
            reset: ``(B,)`` bool, samples whose history is ``V_curr`` itself (detached, unwarped); None: none.
            detach_history: detach ``v_hist`` (a stored history: no gradient across frames); False keeps its
                gradient (a history computed this frame, e.g. the scene's ground-truth oracle's embedding).

        Returns:
            :class:`StreamAggOutput`; the auxiliary logits only in training mode.
        """
        b = v_curr.shape[0]
        if tuple(v_curr.shape[2:]) != self.grid.shape:
            raise ValueError(f"StreamAggregation: volume {tuple(v_curr.shape)} is not on grid {self.grid.shape}")
        if v_hist is None:
            warped = v_curr.detach()
        else:
            if v_hist.shape != v_curr.shape:
                raise ValueError(
                    f"StreamAggregation: history {tuple(v_hist.shape)} and current {tuple(v_curr.shape)} differ"
                )
            if prev_to_current is None:
                prev_to_current = torch.eye(4, dtype=torch.float64, device=v_curr.device).expand(b, 4, 4)
            if self.warp_sampling == "public_linspace":
                warped = public_linspace_warp(v_hist.detach() if detach_history else v_hist, self.grid, prev_to_current)
            else:
                warped = warp_volume(v_hist.detach() if detach_history else v_hist, self.grid, prev_to_current)
            if reset is not None:  # the public code restarts a stream from the current feature, unwarped
                warped = torch.where(reset.view(b, 1, 1, 1, 1).to(warped.device), v_curr.detach(), warped)
        attention = None
        refined = warped
        if self.refine is not None:
            refined, attention = self.refine(warped)
        if self.fusion == "add":
            fused = refined + v_curr
        else:
            fused = self.fuse(torch.cat([refined, v_curr], dim=1))
        out = StreamAggOutput(fused=fused, warped=warped, refined=refined, attention=attention)
        if self.training:
            if self.occupied is not None and attention is not None:
                out.occupied_logits = self.occupied(attention.spatial_logits).squeeze(1)
            if self.forecast is not None:
                out.forecast_logits = self.forecast(refined)
        return out

    def aux_losses(
        self,
        out: StreamAggOutput,
        voxel_labels: Tensor,
        free_label: int,
        mask: Tensor | None = None,
        class_weights: Tensor | None = None,
        ignore_label: int = 255,
    ) -> dict[str, Tensor]:
        """The auxiliary losses of a training forward, unweighted (the paper weighs both by 10, suppl. A.4).

        Args:
            out: this module's training output.
            voxel_labels: ``(B, sX, sY, sZ)`` integer class ids of the current frame on the label grid.
            free_label: the id of free space (Occ3D: 17).
            mask: ``(B, sX, sY, sZ)`` bool voxels to supervise (e.g. ``mask_camera``), or None (all).
            class_weights: ``(K,)`` weights of the forecasting CE, or None.
            ignore_label: label id never supervised.

        Returns:
            ``{"occupied": scalar, "forecast": scalar}`` for the heads that ran.
        """
        losses: dict[str, Tensor] = {}
        if out.occupied_logits is not None:
            losses["occupied"] = occupied_loss(out.occupied_logits, voxel_labels, free_label, mask, ignore_label)
        if out.forecast_logits is not None:
            losses["forecast"] = forecast_loss(out.forecast_logits, voxel_labels, mask, class_weights, ignore_label)
        return losses


def _check_public_linspace_grid(grid: GridSpec) -> None:
    """Refuse a grid the public code's warp cannot sample (its x points take the y count: square grids only)."""
    nx, ny, _ = grid.shape
    if nx != ny:
        raise ValueError(
            f"StreamAggregation warp_sampling='public_linspace' needs a square x-y grid (the public code's x linspace "
            f"takes the y voxel count), got {nx} x {ny}; use warp_sampling='voxel_centres'"
        )
    if grid.is_contracted:
        raise ValueError(
            "StreamAggregation warp_sampling='public_linspace' samples a metric grid, got a contracted one; "
            "use warp_sampling='voxel_centres'"
        )


def public_linspace_warp(volume: Tensor, grid: GridSpec, src_to_dst: Tensor) -> Tensor:
    """The public code's StreamAgg warp: ``linspace`` points over the grid's range, ``align_corners=True``.

    Destination point ``i`` of an axis with range ``[lo, hi]`` and ``N`` voxels is ``lo + i (hi - lo) / (N - 1)``
    (the range's edges, not the voxel centres); it is mapped into ``src`` and normalised by the range's centre and
    half-extent, and ``grid_sample`` with ``align_corners=True`` reads source index ``i + t (N - 1) / (hi - lo)`` for
    a translation ``t``. The identity is exact, but a translation moves the content by ``(N - 1) / N`` of its true
    voxel count ``t N / (hi - lo)`` (the code's 100 x 100 x 8 grid: 0.99 in x and y, 0.875 in z), and rotations are
    read at the same shrunk pitch. The code builds its x points with the y count (and y with the x count): the same
    on a square grid, refused on another (:class:`StreamAggregation`).

    Args:
        volume: ``(B, C, X, Y, Z)`` in frame ``src``, on ``grid`` (metric, square in x-y).
        grid: the grid of both frames.
        src_to_dst: ``(B, 4, 4)`` ``src`` ego -> ``dst`` ego (the code's matrix is its inverse, current -> previous).

    Returns:
        ``(B, C, X, Y, Z)`` in frame ``dst``; points outside the range read zeros.
    """
    _check_public_linspace_grid(grid)
    dtype, device = volume.dtype, volume.device
    lo, hi = grid.range[:3], grid.range[3:]
    nx, ny, nz = grid.shape
    # as the code, in the volume's dtype: x takes the y count and y the x count (equal here)
    axes = [
        torch.linspace(lo[0], hi[0], ny, device=device, dtype=dtype),
        torch.linspace(lo[1], hi[1], nx, device=device, dtype=dtype),
        torch.linspace(lo[2], hi[2], nz, device=device, dtype=dtype),
    ]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)  # (X, Y, Z, 3) in dst
    dst_to_src = torch.linalg.inv(src_to_dst.to(torch.float64)).to(dtype)  # the code's current -> previous
    rot, trans = dst_to_src[:, None, None, None, :3, :3], dst_to_src[:, None, None, None, :3, 3]
    src = (rot @ points[None, ..., None]).squeeze(-1) + trans  # (B, X, Y, Z, 3)
    centre = torch.tensor([(a + c) / 2 for a, c in zip(lo, hi, strict=True)], device=device, dtype=dtype)
    half = torch.tensor([(c - a) / 2 for a, c in zip(lo, hi, strict=True)], device=device, dtype=dtype)
    norm = ((src - centre) / half).flip(-1)  # grid_sample reads (z, y, x) for a (X, Y, Z) volume
    return F.grid_sample(volume, norm, mode="bilinear", padding_mode="zeros", align_corners=True)


def _valid(labels: Tensor, mask: Tensor | None, ignore_label: int) -> Tensor:
    valid = labels != ignore_label
    return valid if mask is None else valid & mask.to(torch.bool)


def occupied_loss(
    logits: Tensor,
    labels: Tensor,
    free_label: int,
    mask: Tensor | None = None,
    ignore_label: int = 255,
    weighting: Literal["per_voxel", "public_mean"] = "per_voxel",
) -> Tensor:
    """Binary cross-entropy with logits of "occupied" (label not free), averaged over the supervised voxels.

    One sigmoid, inside :func:`torch.nn.functional.binary_cross_entropy_with_logits` (the public code's
    head applies a second one before it).

    ``weighting``: ``"per_voxel"`` is the mean of the per-voxel BCE, every supervised voxel weighted alike (the
    paper's plain BCE); ``"public_mean"`` is the public code's formula: its per-voxel weights (1.0 occupied, 0.1
    free, :data:`PUBLIC_OCCUPIED_WEIGHTS`) multiply the already averaged BCE, so the loss is
    ``mean_v(BCE_v) * (0.1 + 0.9 * occupied fraction)`` over the batch's supervised voxels: a factor that depends
    on the batch, not a weighting of the voxels.

    Args:
        logits: ``(B, X, Y, Z)`` occupied logits.
        labels: ``(B, X, Y, Z)`` integer class ids.
        free_label: the id of free space.
        mask: ``(B, X, Y, Z)`` bool, voxels to supervise, or None (all but ``ignore_label``).
        ignore_label: label id never supervised.
        weighting: ``"per_voxel"`` or ``"public_mean"`` (above).

    Returns:
        Scalar; zero (still attached to ``logits``) when no voxel is supervised.
    """
    check_choices(occupied_loss, "occupied_loss", weighting=weighting)
    valid = _valid(labels, mask, ignore_label)
    target = (labels != free_label).to(logits.dtype)
    if not bool(valid.any()):
        return logits.sum() * 0.0
    loss = F.binary_cross_entropy_with_logits(logits[valid], target[valid])
    if weighting == "public_mean":
        occupied_w, free_w = PUBLIC_OCCUPIED_WEIGHTS
        loss = (loss * torch.where(target[valid] == 1, occupied_w, free_w)).mean()
    return loss


def forecast_loss(
    logits: Tensor,
    labels: Tensor,
    mask: Tensor | None = None,
    class_weights: Tensor | None = None,
    ignore_label: int = 255,
) -> Tensor:
    """Cross-entropy of the forecasting head, summed over supervised voxels and divided by their count.

    (With ``class_weights`` this divides by the voxel count, as the public code normalises its occupancy CE,
    not by the summed weights as ``F.cross_entropy(reduction="mean")`` would.)

    Args:
        logits: ``(B, K, X, Y, Z)`` class logits.
        labels: ``(B, X, Y, Z)`` integer class ids in ``[0, K)`` or ``ignore_label``.
        mask: ``(B, X, Y, Z)`` bool, voxels to supervise, or None.
        class_weights: ``(K,)`` per-class weights, or None.
        ignore_label: label id never supervised.

    Returns:
        Scalar; zero (still attached to ``logits``) when no voxel is supervised.
    """
    valid = _valid(labels, mask, ignore_label)
    target = torch.where(valid, labels.long(), torch.full_like(labels, ignore_label, dtype=torch.long))
    weight = None if class_weights is None else class_weights.to(logits)
    per_voxel = F.cross_entropy(logits, target, weight=weight, ignore_index=ignore_label, reduction="none")
    return per_voxel.sum() / valid.sum().clamp(min=1)
