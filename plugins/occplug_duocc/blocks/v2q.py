"""DuOcc's voxel-to-query aggregation (V2Q, paper §3.2 Eq. 6): 3D deformable attention of each instance query
into the stream-aggregated volume around its box (:class:`VoxelToQuery`).

QueryAgg (:mod:`.queryagg`) applies it to the detector's queries (``q_img`` -> ``q_vox``); the mask decoder
(:mod:`.mask_decoder`) reuses it as its cross-attention.

Assumptions (where the paper is silent; the public code's choices, from ``models/heads/queryagg/``, are these):

* §3.2 V2Q (Eq. 6): ``heads x points`` learnable offsets per query within +-0.5 x box size, rotated by yaw
  (the code makes 7 of them fixed key points, ``fixed_key_points``; here the offset bias starts on a spread
  pattern instead; the code's other choices are the switches ``offset_input``, ``value_bias``, ``box_rotation``);
  weights are
  a zero-initialised Linear, softmax over each head's points; ``W'_h`` is a bias-free projection applied after
  sampling (identical to projecting the volume first, since trilinear sampling is linear) and ``W_h`` the output
  projection over the concatenated heads.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import torch
from torch import Tensor, nn

from occplug.constraints import Positive, check_choices
from occplug.geometry import GridSpec, sample_volume

from .boxes import box_points
from .image_aggregation import FIXED_KEY_POINTS

__all__ = ["VoxelToQuery"]


class VoxelToQuery(nn.Module):
    """V2Q (§3.2, Eq. 6): each instance query samples the voxel volume around its box and adds the result.

    ``q_vox = q_img + W [concat_h sum_o alpha_hqo W'_h V(c_q + R(yaw_q) (s_hqo * size_q))]`` with offsets
    ``s = sigmoid(Linear(q)) - 0.5`` (fractions of the box's ``(l, w, h)``, so inside the box), weights
    ``alpha = softmax_o(Linear(q))`` per head, trilinear sampling (:func:`~occplug.geometry.sample_volume`, zeros
    outside the grid).

    Args:
        channels: ``C`` of the queries (divisible by ``heads``).
        grid: the grid the volume lies on (``GridSpec`` or ``{range, voxel_size}``), ego frame.
        volume_channels: channels of the volume (default ``C``).
        heads, points: ``H`` heads with ``O`` points each (code 8 x 6).
        dropout: on the output.
        offset_input: the offsets read the query plus ``query_pos`` (``"feature_and_anchor"``, as the weights) or,
            as the public code, the query alone (``"feature"``).
        value_bias: the public code's value projection with a bias, applied to the volume before sampling: zero
            padding then scales the bias by the sampled in-grid mass (it fades at the grid faces).
        fixed_key_points: the first 7 of the ``H * O`` points are the public code's fixed ones (centre and
            +-0.45 of the box size along each box axis), the rest learnable (off: all learnable); point ``p`` of
            the flat list belongs to head ``p // O`` in both.
        box_rotation: ``"yaw"`` reads box column 6 as the yaw; ``"sin_cos"`` reads columns 6 and 7 as the
            detector's raw, unnormalised ``(sin, cos)`` and rotates the offsets by them as they are (the code).
    """

    def __init__(
        self,
        channels: Annotated[int, Positive],
        grid: GridSpec,
        volume_channels: int | None = None,
        heads: Annotated[int, Positive] = 8,
        points: Annotated[int, Positive] = 6,
        dropout: float = 0.1,
        offset_input: Literal["feature_and_anchor", "feature"] = "feature_and_anchor",
        value_bias: bool = False,
        fixed_key_points: bool = False,
        box_rotation: Literal["yaw", "sin_cos"] = "yaw",
    ) -> None:
        super().__init__()
        if channels % heads:
            raise ValueError(f"VoxelToQuery: channels {channels} not divisible by heads {heads}")
        check_choices(VoxelToQuery.__init__, "VoxelToQuery", offset_input=offset_input, box_rotation=box_rotation)
        fixed = len(FIXED_KEY_POINTS) if fixed_key_points else 0
        if heads * points <= fixed:
            raise ValueError(
                f"VoxelToQuery: fixed_key_points needs more than {fixed} points in all, got heads {heads} x points {points}"
            )
        self.grid = grid
        self.channels, self.heads, self.points = int(channels), int(heads), int(points)
        self.offset_input, self.box_rotation, self.fixed = offset_input, box_rotation, fixed
        self.offsets = nn.Linear(channels, (heads * points - fixed) * 3)
        self.attn = nn.Linear(channels, heads * points)
        self.value_proj = nn.Linear(int(volume_channels or channels), channels, bias=False)
        self.value_bias = nn.Parameter(torch.zeros(channels)) if value_bias else None
        self.out_proj = nn.Linear(channels, channels)
        self.drop = nn.Dropout(dropout)
        nn.init.zeros_(self.offsets.weight)
        nn.init.zeros_(self.attn.weight)
        nn.init.zeros_(self.attn.bias)
        with torch.no_grad():  # start on a spread pattern: head h along direction 2 pi h / H, points at growing radius
            theta = 2 * math.pi * torch.arange(heads, dtype=torch.float64) / heads
            radius = 0.45 * (torch.arange(points, dtype=torch.float64) + 1) / points
            frac = torch.stack(
                [
                    radius[None] * theta.cos()[:, None],
                    radius[None] * theta.sin()[:, None],
                    (0.2 * (torch.arange(heads) % 2 * 2 - 1))[:, None].expand(heads, points).to(torch.float64),
                ],
                dim=-1,
            )
            self.offsets.bias.copy_(torch.logit(frac + 0.5).flatten()[fixed * 3 :].float())

    def sample_points(self, queries: Tensor, boxes: Tensor) -> Tensor:
        """``(B, Q, H, O, 3)`` ego-frame sampling points of ``(B, Q, C)`` queries around ``(B, Q, >=7)`` boxes."""
        b, q = queries.shape[:2]
        frac = self.offsets(queries).view(b, q, self.heads * self.points - self.fixed, 3).sigmoid() - 0.5
        if self.fixed:
            fixed = torch.tensor(FIXED_KEY_POINTS, dtype=frac.dtype, device=frac.device)
            frac = torch.cat([fixed.expand(b, q, -1, -1), frac], dim=2)
        if self.box_rotation == "sin_cos":  # the code's rotation matrix of the raw pair, unnormalised
            local = frac * boxes[..., None, 3:6].clamp(min=1e-6)
            s, c = boxes[..., None, 6], boxes[..., None, 7]
            x, y, z = local.unbind(-1)
            pts = torch.stack([c * x - s * y, s * x + c * y, z], dim=-1) + boxes[..., None, :3]
            return pts.view(b, q, self.heads, self.points, 3)
        yaw = boxes[..., 6]
        enc = torch.cat(
            [boxes[..., :3], boxes[..., 3:6].clamp(min=1e-6).log(), yaw.sin()[..., None], yaw.cos()[..., None]], -1
        )
        return box_points(enc, frac).view(b, q, self.heads, self.points, 3)

    def forward(self, volume: Tensor, queries: Tensor, boxes: Tensor, query_pos: Tensor | None = None) -> Tensor:
        """Refine instance queries with the voxel volume.

        Args:
            volume: ``V_S.A``, ``(B, C_v, X, Y, Z)`` on ``grid``, ego frame.
            queries: ``q_img``, ``(B, Q, C)``.
            boxes: ``(B, Q, >=7)`` their boxes ``[cx, cy, cz, l, w, h, yaw, ...]``, ego frame (``box_rotation="sin_cos"``:
                ``(B, Q, >=8)`` ``[cx, cy, cz, l, w, h, sin, cos, ...]``).
            query_pos: ``(B, Q, C)`` added to the queries for predicting offsets and weights (e.g. the anchor
                embedding), or None.

        Returns:
            ``q_vox``, ``(B, Q, C)``.
        """
        if tuple(volume.shape[2:]) != self.grid.shape:
            raise ValueError(f"VoxelToQuery: volume {tuple(volume.shape)} is not on grid {self.grid.shape}")
        b, q, c = queries.shape
        h, o = self.heads, self.points
        src = queries if query_pos is None else queries + query_pos
        pts = self.sample_points(queries if self.offset_input == "feature" else src, boxes)
        flat_pts = pts.reshape(b, q * h * o, 3).to(volume.dtype)
        sampled = sample_volume(volume, self.grid, flat_pts)  # (B, QHO, C_v)
        values = self.value_proj(sampled.to(queries.dtype))
        if self.value_bias is not None:  # biased values sampled with zero padding: the bias times the in-grid mass
            mass = sample_volume(torch.ones_like(volume[:, :1]), self.grid, flat_pts)  # (B, QHO, 1)
            values = values + mass.to(values) * self.value_bias
        values = values.view(b, q, h, o, h, c // h)
        values = torch.diagonal(values, dim1=2, dim2=4).movedim(-1, 2)  # head h reads its own channels: (B,Q,H,O,d)
        alpha = self.attn(src).view(b, q, h, o).softmax(-1)
        out = (alpha[..., None] * values).sum(3).reshape(b, q, c)
        return queries + self.drop(self.out_proj(out))
