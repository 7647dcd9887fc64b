"""Scene representation ``dense_voxels_history``: dense voxels blended with the previous frame's, warped by ego motion.

The smallest stateful core component (a plain-PyTorch cousin of DuOcc's StreamAgg without
RefineNet): it shows how a streaming component uses :class:`occplug.streams.StreamState`.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import torch
from torch import Tensor, nn

from occplug.constraints import NonNegative, Positive, Range, check_choices
from occplug.data.frame import Batch
from occplug.geometry import warp_volume
from occplug.interfaces import Lifted
from occplug.streams import StreamState

from .scenes import DenseVoxels, DenseVoxelScene

__all__ = ["DenseVoxelsHistory"]


def _itself(current: Tensor) -> Tensor:
    return current


class DenseVoxelsHistory(DenseVoxels):
    """``dense_voxels`` features ``V_t``, fused with the previous fused volume warped into this ego frame.

    ``F_t = (1 - w) V_t + w warp(F_{t-1})``, where ``warp`` moves the previous frame's volume into the
    current ego frame with the poses (``T_{g->e}^t T_{e->g}^{t-1}``, trilinear, zero where the old
    grid saw nothing; :func:`occplug.geometry.warp_volume`). ``F_{t-1}`` is held per batch slot and
    per stage and detached (no backpropagation through time). At a stream start (a new scene or run,
    a frame jump, a time gap above ``max_gap_s``) the history is ``V_t`` itself (``reset: current``,
    so ``F_t = V_t`` exactly, as DuOcc does) or zeros (``reset: zeros``).

    Args:
        in_channels, out_channels, num_blocks: as ``dense_voxels``.
        history_weight: ``w`` in ``(0, 1)``.
        learn_weight: make ``w`` a parameter (a logit initialised at ``history_weight``).
        reset: ``current`` or ``zeros``.
        max_gap_s: seconds between frames above which the history is dropped; null = never.

    Forward:
        :class:`~occplug.interfaces.Lifted` ``(B, C_in, X, Y, Z)`` and the batch (``scene``,
        ``frame_index``, ``timestamp``, ``is_sequence_start``, ``ego_to_global``) ->
        :class:`~occplug.components.DenseVoxelScene` with ``F_t`` ``(B, C, X, Y, Z)``, ego frame.
    """

    stateful = True

    def __init__(
        self,
        in_channels: int,
        out_channels: Annotated[int, Positive] = 64,
        num_blocks: Annotated[int, NonNegative] = 2,
        history_weight: Annotated[float, Range(low=0, high=1, low_open=True, high_open=True)] = 0.5,
        learn_weight: bool = False,
        reset: Literal["current", "zeros"] = "current",
        max_gap_s: Annotated[float | None, Positive] = 2.0,
    ) -> None:
        super().__init__(in_channels, out_channels, num_blocks)
        if not 0.0 < history_weight < 1.0:
            raise ValueError(f"dense_voxels_history history_weight must be in (0, 1), got {history_weight}")
        check_choices(DenseVoxelsHistory.__init__, "dense_voxels_history", reset=reset)
        logit = torch.tensor(math.log(history_weight / (1.0 - history_weight)))
        if learn_weight:
            self.weight_logit = nn.Parameter(logit)
        else:
            self.register_buffer("weight_logit", logit, persistent=False)
        self.reset = reset
        self.history = StreamState(on_reset=_itself if reset == "current" else None, max_gap_s=max_gap_s)

    @property
    def history_weight(self) -> Tensor:
        """``w`` (a 0-dim tensor)."""
        return torch.sigmoid(self.weight_logit)

    def forward(self, lifted: Lifted, batch: Batch) -> DenseVoxelScene:
        """Fuse this frame's volume with the warped history of each slot, then store the result."""
        current = super().forward(lifted, batch).features
        read = self.history.get(batch, current)
        grid = lifted.grid
        previous = read.value
        keep = ~read.reset
        if bool(keep.any()):  # reset slots hold this frame's own volume already: no warp
            moved = warp_volume(previous[keep], grid, read.prev_to_current[keep].to(current.dtype))
            previous = previous.clone()
            previous[keep] = moved
        fused = torch.lerp(current, previous, self.history_weight.to(current.dtype))
        self.history.update(batch, fused)
        return DenseVoxelScene(fused, grid)

    def export_forward(self, lifted: Lifted, batch: Batch) -> DenseVoxelScene:
        """:meth:`forward` without its branch on the reset mask, for ``occplug export`` (traceable): every
        slot is warped, then the reset ones take their unwarped value back (what forward computes for them)."""
        current = super().forward(lifted, batch).features
        read = self.history.get(batch, current)
        moved = warp_volume(read.value, lifted.grid, read.prev_to_current.to(current.dtype))
        previous = torch.where(read.reset.view(-1, 1, 1, 1, 1), read.value, moved)
        fused = torch.lerp(current, previous, self.history_weight.to(current.dtype))
        self.history.update(batch, fused)
        return DenseVoxelScene(fused, lifted.grid)
