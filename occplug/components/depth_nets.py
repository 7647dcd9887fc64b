"""Depth networks (kind ``depth_net``): per-cell depth logits and context features for a lift-splat transform.

A depth net is what :class:`~occplug.components.LSSViewTransform` runs on the image features
before splatting; a config swaps it as a nested node (``view_transform.depth_net: {type: ...}``).
It sees the batch's calibration, so a net may condition on the cameras (BEVDepth's camera-aware
depth net, ``camera_aware``).

Constructors take ``in_channels`` (the image features' channels), ``num_bins`` (``D``) and
``out_channels`` (``C`` context channels); the view transform fills them in.
"""

from __future__ import annotations

from typing import Annotated, Any

import torch
from torch import Tensor, nn

from occplug.constraints import NonNegative, Positive
from occplug.geometry import effective_intrinsics
from occplug.interfaces.depth_net import DepthAndContext, DepthNet
from occplug.nn import BasicBlock2d, ConvNormAct2d, PixelNet

__all__ = ["CAMERA_FEATURES", "CameraAwareDepthNet", "DepthAndContext", "DepthNet", "PlainDepthNet", "camera_vector"]

#: Length of :func:`camera_vector`.
CAMERA_FEATURES = 18


def camera_vector(batch: Any) -> Tensor:
    """``(B, N, 18)`` float32 description of each camera, the input of a camera-aware depth net.

    The first two rows of the effective intrinsics ``img_aug @ intrinsics`` of the augmented image,
    divided by its width (row 0: ``fx, skew, cx``) and height (row 1: ``., fy, cy``) so that the
    values are O(1) and independent of the resolution; then ``cam_to_ego``'s rotation (row-major,
    9) and translation (metres, 3). Flips and rotations of the image show in the signs and the
    off-diagonal terms.
    """
    b, n = batch.cam_to_ego.shape[:2]
    big_h, big_w = batch.images.shape[-2:]
    k = effective_intrinsics(batch.intrinsics.float(), batch.img_aug.float())
    scale = torch.tensor([float(big_w), float(big_h)], device=k.device).view(1, 1, 2, 1)
    pose = batch.cam_to_ego.float()
    return torch.cat(
        [(k[..., :2, :] / scale).reshape(b, n, 6), pose[..., :3, :3].reshape(b, n, 9), pose[..., :3, 3]], dim=-1
    )


class PlainDepthNet(DepthNet):
    """Per-cell conv head: ``3x3 conv -> norm -> ReLU -> 1x1 conv`` to ``D + C`` channels (calibration unused).

    The default of ``lss``; with the same seed it gives the same numbers as the depth head LSS had built in.

    Args:
        in_channels: ``C_in``; num_bins: ``D``; out_channels: ``C``.
        hidden: width of the 3x3 conv (0: a single 1x1 conv).
    """

    def __init__(
        self, in_channels: int, num_bins: int, out_channels: int, hidden: Annotated[int, NonNegative] = 64
    ) -> None:
        super().__init__()
        self.num_bins, self.out_channels = int(num_bins), int(out_channels)
        self.net = PixelNet(in_channels, hidden, self.num_bins + self.out_channels)

    def forward(self, features: Tensor, batch: Any) -> DepthAndContext:
        """``(B, N, C_in, h, w)`` -> :class:`DepthAndContext`; ``batch`` is not read."""
        b, n, _, h, w = features.shape
        out = self.net(features.flatten(0, 1)).view(b, n, self.num_bins + self.out_channels, h, w)
        return DepthAndContext(out[:, :, : self.num_bins], out[:, :, self.num_bins :])


class _CameraGate(nn.Module):
    """``(B*N, 18)`` camera vector -> ``(B*N, channels)`` SE-style gates in ``(0, 1)``: ``sigmoid(MLP(.))``."""

    def __init__(self, channels: int, hidden: int) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(CAMERA_FEATURES, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, channels))

    def forward(self, camera: Tensor) -> Tensor:
        return torch.sigmoid(self.mlp(camera))


class CameraAwareDepthNet(DepthNet):
    """BEVDepth's camera-aware depth net: the calibration gates the depth and context features.

    ``x = ReLU(norm(conv3x3(features)))``; the camera vector (:func:`camera_vector`: augmented
    intrinsics and ``cam_to_ego``) goes through one MLP per branch to channel gates in ``(0, 1)``
    (squeeze-and-excitation style); the depth branch is ``x * gate_depth`` -> ``depth_blocks``
    residual blocks -> 1x1 conv to ``D`` logits, the context branch ``x * gate_context`` -> 1x1
    conv to ``C``. BEVDepth additionally normalises the camera vector with BatchNorm and runs an
    ASPP on the depth branch; here the vector is scaled by construction (works for one camera).

    Args:
        in_channels: ``C_in``; num_bins: ``D``; out_channels: ``C``.
        hidden: channels of the shared 3x3 conv and of both branches (> 0).
        camera_hidden: hidden width of the camera MLPs.
        depth_blocks: residual blocks on the depth branch.
        norm: ``batch`` or ``group`` (see :func:`~occplug.nn.norm_layer`).
    """

    def __init__(
        self,
        in_channels: int,
        num_bins: int,
        out_channels: int,
        hidden: Annotated[int, Positive] = 64,
        camera_hidden: Annotated[int, Positive] = 64,
        depth_blocks: Annotated[int, NonNegative] = 0,
        norm: str = "batch",
    ) -> None:
        super().__init__()
        if hidden < 1 or camera_hidden < 1 or depth_blocks < 0:
            raise ValueError(
                f"camera_aware depth net needs hidden >= 1, camera_hidden >= 1, depth_blocks >= 0; "
                f"got {hidden}, {camera_hidden}, {depth_blocks}"
            )
        self.num_bins, self.out_channels = int(num_bins), int(out_channels)
        self.reduce = ConvNormAct2d(in_channels, hidden, 3, norm=norm)
        self.depth_gate = _CameraGate(hidden, camera_hidden)
        self.context_gate = _CameraGate(hidden, camera_hidden)
        self.depth_blocks = nn.Sequential(*(BasicBlock2d(hidden, hidden, norm=norm) for _ in range(depth_blocks)))
        self.depth_head = nn.Conv2d(hidden, self.num_bins, 1)
        self.context_head = nn.Conv2d(hidden, self.out_channels, 1)

    def forward(self, features: Tensor, batch: Any) -> DepthAndContext:
        """``(B, N, C_in, h, w)`` and the batch's calibration -> :class:`DepthAndContext`."""
        b, n, _, h, w = features.shape
        x = self.reduce(features.flatten(0, 1))  # (B*N, hidden, h, w)
        camera = camera_vector(batch).to(x.dtype).reshape(b * n, -1)
        depth = self.depth_head(self.depth_blocks(x * self.depth_gate(camera)[..., None, None]))
        context = self.context_head(x * self.context_gate(camera)[..., None, None])
        return DepthAndContext(depth.view(b, n, self.num_bins, h, w), context.view(b, n, self.out_channels, h, w))
