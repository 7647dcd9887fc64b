"""DuOcc's voxel-to-query aggregation (V2Q, paper §3.2 Eq. 6): 3D deformable attention of each instance query
into the stream-aggregated volume around its box (:class:`VoxelToQuery`).

QueryAgg (:mod:`.queryagg`) applies it to the detector's queries (``q_img`` -> ``q_vox``); the mask decoder
(:mod:`.mask_decoder`) reuses it as its cross-attention.

Assumptions (where the paper is silent; the public code's choices, from ``models/heads/queryagg/``, are these):

* §3.2 V2Q (Eq. 6): ``heads x points`` learnable offsets per query within +-0.5 x box size, rotated by yaw
  (the code adds the 7 fixed key points; here the offset bias starts on a spread pattern instead); weights are
  a zero-initialised Linear, softmax over each head's points; ``W'_h`` is a bias-free projection applied after
  sampling (identical to projecting the volume first, since trilinear sampling is linear) and ``W_h`` the output
  projection over the concatenated heads.
"""

from __future__ import annotations

import math
from typing import Annotated

import torch
from torch import Tensor, nn

from occplug.constraints import Positive
from occplug.geometry import GridSpec, sample_volume

from .boxes import box_points

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
    """

    def __init__(
        self,
        channels: Annotated[int, Positive],
        grid: GridSpec,
        volume_channels: int | None = None,
        heads: Annotated[int, Positive] = 8,
        points: Annotated[int, Positive] = 6,
        dropout: float = 0.1,
    ) -> None:
        super().__init__()
        if channels % heads:
            raise ValueError(f"VoxelToQuery: channels {channels} not divisible by heads {heads}")
        self.grid = grid
        self.channels, self.heads, self.points = int(channels), int(heads), int(points)
        self.offsets = nn.Linear(channels, heads * points * 3)
        self.attn = nn.Linear(channels, heads * points)
        self.value_proj = nn.Linear(int(volume_channels or channels), channels, bias=False)
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
            self.offsets.bias.copy_(torch.logit(frac + 0.5).flatten().float())

    def sample_points(self, queries: Tensor, boxes: Tensor) -> Tensor:
        """``(B, Q, H, O, 3)`` ego-frame sampling points of ``(B, Q, C)`` queries around ``(B, Q, >=7)`` boxes."""
        b, q = queries.shape[:2]
        frac = self.offsets(queries).view(b, q, self.heads * self.points, 3).sigmoid() - 0.5
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
            boxes: ``(B, Q, >=7)`` their boxes ``[cx, cy, cz, l, w, h, yaw, ...]``, ego frame.
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
        pts = self.sample_points(src, boxes)
        sampled = sample_volume(volume, self.grid, pts.reshape(b, q * h * o, 3).to(volume.dtype))  # (B, QHO, C_v)
        values = self.value_proj(sampled.to(queries.dtype)).view(b, q, h, o, h, c // h)
        values = torch.diagonal(values, dim1=2, dim2=4).movedim(-1, 2)  # head h reads its own channels: (B,Q,H,O,d)
        alpha = self.attn(src).view(b, q, h, o).softmax(-1)
        out = (alpha[..., None] * values).sum(3).reshape(b, q, c)
        return queries + self.drop(self.out_proj(out))
