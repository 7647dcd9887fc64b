"""Sparse4D's encoded box, as DuOcc's image-to-query detector (:mod:`.detector`) regresses it, and points on a box.

Decoded boxes use the :class:`~occplug.Frame` ``boxes`` layout, ``(..., 9)``
``[cx, cy, cz, l, w, h, yaw, vx, vy]`` in the **ego** frame of the current sample (metres, radians about +z from
+x, m/s), ``l`` along the heading. Anchors and regression live in Sparse4D's encoding (:func:`~.matching.encode_boxes`),
``(..., 10)`` ``[cx, cy, cz, log l, log w, log h, sin yaw, cos yaw, vx, vy]`` (:data:`BOX_DIM`); :func:`decode_boxes`
is its inverse. :func:`box_points` places box-frame fractions of a box's size in the ego frame: the detector's key
points (:mod:`.image_aggregation`) and V2Q's sampling points (:mod:`.v2q`).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["BOX_DIM", "box_points", "decode_boxes"]

#: Width of the encoded box / anchor: ``[cx, cy, cz, log l, log w, log h, sin, cos, vx, vy]``.
BOX_DIM = 10


def decode_boxes(encoded: Tensor) -> Tensor:
    """Inverse of :func:`~.matching.encode_boxes`.

    Args:
        encoded: ``(..., 8)`` ``[x, y, z, log l, log w, log h, sin, cos]`` or ``(..., 10)`` with ``vx, vy``.

    Returns:
        ``(..., 7)`` ``[x, y, z, l, w, h, yaw]`` or ``(..., 9)`` with ``vx, vy`` (yaw from ``atan2(sin, cos)``).
    """
    yaw = torch.atan2(encoded[..., 6], encoded[..., 7])[..., None]
    return torch.cat([encoded[..., :3], encoded[..., 3:6].exp(), yaw, encoded[..., 8:]], dim=-1)


def _yaw_rotate(local: Tensor, sin_cos: Tensor) -> Tensor:
    """Rotate ``(..., P, 3)`` box-frame offsets about +z by the (normalised) ``(..., 1, 2)`` ``[sin, cos]``."""
    norm = sin_cos.norm(dim=-1, keepdim=True).clamp(min=1e-6)
    s, c = (sin_cos / norm).unbind(-1)  # broadcast against the point axis of ``local``
    x, y, z = local.unbind(-1)
    return torch.stack([c * x - s * y, s * x + c * y, z], dim=-1)


def box_points(anchors: Tensor, scales: Tensor) -> Tensor:
    """Ego-frame points of boxes at box-frame fractions of their size.

    Args:
        anchors: ``(B, Q, >=8)`` encoded boxes (:data:`BOX_DIM` layout), ego frame.
        scales: ``(B, Q, P, 3)`` fractions of ``(l, w, h)`` along the box's own axes (0 = centre).

    Returns:
        ``(B, Q, P, 3)`` ego-frame points.
    """
    local = scales * anchors[..., None, 3:6].exp()
    return anchors[..., None, :3] + _yaw_rotate(local, anchors[..., None, 6:8])
