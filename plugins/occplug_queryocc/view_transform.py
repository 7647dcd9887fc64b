"""View transform ``queryocc_lift_contract_splat``: QueryOcc's lift of image features into a (contracted) BEV plane.

Three changes to Lift-Splat-Shoot (QueryOcc §3.2), each switchable off for the ablation:

* **log-linear depth bins** (``bins: log_linear``): bin ``i`` of ``D`` sits at ``d(r_i)``, ``r_i = i / (D - 1)``,
  with ``d(r) = (1 - s) * d_near * (d_far / d_near)^r + s * (d_near + r * (d_far - d_near))`` (``s`` =
  ``linear_mix``); ``bins: uniform`` is ``s = 1``;
* **axis-aligned contraction**: a contracted ``grid`` (``{range, voxel_size, contraction: {near, kappa}}``)
  keeps every frustum point (far ones land in the border band); a metric grid drops what lies outside;
* **point encoding** (``point_encoding: true``): each frustum point carries
  ``f = P(p_d * w + (1 - p_d) * e, p_v, p_d, t_c)`` with the cell's context ``w``, a learnable empty
  embedding ``e``, the depth probability ``p_d``, the visibility ``p_v = 1 - sum_{d' < d} p_d'`` and the
  camera's capture-time offset ``t_c``; ``P`` is ``Linear -> ReLU``. ``false`` splats the raw ``p_d * w``.

The frustum geometry and the pooling are the core's :class:`~occplug.ops.FrustumSplatter` (BEV mode:
the cells of a column sum into one BEV cell).
"""

from __future__ import annotations

from typing import Annotated, Literal

import torch
from torch import Tensor, nn

from occplug import RunContext
from occplug.components import build_depth_net
from occplug.config import Slot
from occplug.constraints import NonNegative, Positive, UnitInterval, check_choices
from occplug.data import Batch
from occplug.geometry import GridSpec
from occplug.interfaces import Lifted, ViewTransform
from occplug.ops import FrustumSplatter

__all__ = ["LiftContractSplat", "log_linear_depths", "visibility"]


def log_linear_depths(num_bins: int, near: float, far: float, linear_mix: float = 0.0) -> Tensor:
    """``(D,)`` float32 bin centres ``d(r_i)``, ``r_i = i / (D - 1)`` (QueryOcc Eq. 2): ``d(0) = near``, ``d(1) = far``.

    ``linear_mix`` 0 gives geometric spacing, 1 uniform spacing.
    """
    if num_bins < 2 or not 0 < near < far or not 0.0 <= linear_mix <= 1.0:
        raise ValueError(
            f"depth bins need num_bins >= 2, 0 < near < far and linear_mix in [0, 1]; "
            f"got {num_bins}, {near}, {far}, {linear_mix}"
        )
    r = torch.linspace(0.0, 1.0, num_bins, dtype=torch.float64)
    d = (1 - linear_mix) * near * (far / near) ** r + linear_mix * (near + r * (far - near))
    d[0], d[-1] = near, far  # exact ends (pow rounds)
    return d.float()


def visibility(probs: Tensor, dim: int = 2) -> Tensor:
    """``p_v = 1 - sum_{d' < d} p_d'`` along ``dim`` (the exclusive cumulative sum): 1 at the first bin."""
    return 1.0 - (probs.cumsum(dim) - probs)


class LiftContractSplat(ViewTransform):
    """Lift-Contract-Splat: depth distribution per feature cell, point encoding, splat into a BEV plane.

    Args:
        in_channels: ``C_in`` of the image features; image_stride: pixels per feature cell.
        grid: the BEV grid (its z range bounds what is pooled); contracted or metric.
        out_channels: ``C`` of the BEV plane.
        num_bins: ``D`` depth bins; depth_near, depth_far: first and last bin centre (camera z, metres).
        bins: ``log_linear`` (Eq. 2 with ``linear_mix``) or ``uniform``.
        linear_mix: ``s`` of Eq. 2 for ``log_linear``.
        point_encoding: encode each frustum point (see the module docstring) or splat raw features.
        hidden: width of the depth net's 3x3 conv; depth_net: a ``depth_net`` node (default ``plain``, which ignores
            the calibration; ``camera_aware`` gates depth and context by each camera's intrinsics and extrinsics, the
            paper's calibration encoding; ``oracle_depth`` the true depth in this transform's bins, a ceiling).
        context: the run context (handed in by the builder); a ``depth_net`` node is built through it.

    Forward:
        ``(B, N, C_in, h, w)`` features -> :class:`Lifted` with ``volume`` ``(B, C, X, Y)`` on ``grid``,
        ``depth_probs`` ``(B, N, D, h, w)`` and ``depth_bins`` ``(D,)``. ``t_c`` is read from
        ``batch.extras["camera_time_offsets"]`` ``(B, N)`` seconds when present, else 0 (the synthetic
        world's cameras fire together).
    """

    def __init__(
        self,
        in_channels: int,
        image_stride: int,
        grid: GridSpec,
        out_channels: Annotated[int, Positive] = 64,
        num_bins: Annotated[int, Positive] = 32,
        depth_near: Annotated[float, Positive] = 1.0,
        depth_far: Annotated[float, Positive] = 60.0,
        bins: Literal["log_linear", "uniform"] = "log_linear",
        linear_mix: Annotated[float, UnitInterval] = 0.0,
        point_encoding: bool = True,
        hidden: Annotated[int, NonNegative] = 64,
        depth_net: Annotated[dict | None, Slot("depth_net")] = None,
        context: RunContext | None = None,
    ) -> None:
        super().__init__()
        check_choices(LiftContractSplat.__init__, "queryocc_lift_contract_splat", bins=bins)
        self.grid = grid
        self.image_stride = int(image_stride)
        self.out_channels = int(out_channels)
        self.point_encoding = bool(point_encoding)
        mix = 1.0 if bins == "uniform" else float(linear_mix)
        self.register_buffer("depth_centers", log_linear_depths(num_bins, depth_near, depth_far, mix), persistent=False)
        run_context, context = context, self.out_channels  # below, `context` is the depth net's context width
        # depth_centers: a depth net that reads true depth (``oracle_depth``, the perfect-depth ceiling) bins it into
        # these log-linear centres, not its own uniform default; nets without the argument do not receive it
        self.depth_net = build_depth_net(
            depth_net,
            in_channels,
            int(num_bins),
            context,
            hidden=hidden,
            depth_centers=self.depth_centers,
            context=run_context,
        )
        if self.point_encoding:
            self.empty = nn.Parameter(torch.zeros(context))
            # P: one linear map of [p_d w + (1 - p_d) e, p_v, p_d, t_c], then ReLU
            self.encode = nn.Linear(context + 3, self.out_channels)
        self.splatter = FrustumSplatter(self.grid, self.image_stride, bev=True)

    def forward(self, features: Tensor, batch: Batch) -> Lifted:
        """Lift into ``(B, C, X, Y)``; see the class docstring."""
        logits, context = self.depth_net(features, batch)  # (B, N, D, h, w), (B, N, C, h, w)
        probs = logits.softmax(dim=2)
        if not self.point_encoding:
            plane = self.splatter.splat_outer(probs, context, batch, self.depth_centers)
        else:
            plane = self.splatter.splat_points(self._encode(probs, context, batch), batch, self.depth_centers)
        return Lifted(
            volume=plane.contiguous(),
            grid=self.grid,
            depth_probs=probs,
            depth_bins=self.depth_centers,
            image_stride=self.image_stride,
        )

    def _encode(self, probs: Tensor, context: Tensor, batch: Batch) -> Tensor:
        """``(B, N, D, C, h, w)`` encoded frustum points (P is linear before its ReLU, so it is applied per part)."""
        b, n, _, h, w = probs.shape
        c = context.shape[2]
        weight, bias = self.encode.weight, self.encode.bias  # (C_out, C + 3)
        w_ctx, w_pv, w_pd, w_tc = weight[:, :c], weight[:, c], weight[:, c + 1], weight[:, c + 2]
        ctx = torch.einsum("oc,bnchw->bnohw", w_ctx, context)  # P's share of w
        empty = w_ctx @ self.empty  # P's share of e
        p = probs.unsqueeze(3)  # (B, N, D, 1, h, w)
        t_c = batch.extras.get("camera_time_offsets") if isinstance(batch.extras, dict) else None
        tc = 0.0 if t_c is None else torch.as_tensor(t_c, dtype=probs.dtype, device=probs.device).view(b, n, 1, 1, 1, 1)
        out = (
            p * ctx.unsqueeze(2)
            + (1 - p) * empty.view(1, 1, 1, -1, 1, 1)
            + visibility(probs).unsqueeze(3) * w_pv.view(1, 1, 1, -1, 1, 1)
            + p * w_pd.view(1, 1, 1, -1, 1, 1)
            + tc * w_tc.view(1, 1, 1, -1, 1, 1)
            + bias.view(1, 1, 1, -1, 1, 1)
        )
        return torch.relu(out)
