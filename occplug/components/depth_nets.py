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

from occplug.constraints import Length, NonNegative, Positive
from occplug.geometry import effective_intrinsics
from occplug.interfaces.depth_net import DepthAndContext, DepthNet
from occplug.nn import BasicBlock2d, ConvNormAct2d, PixelNet

__all__ = [
    "CAMERA_FEATURES",
    "CameraAwareDepthNet",
    "DepthAndContext",
    "DepthNet",
    "OracleDepthNet",
    "PlainDepthNet",
    "camera_vector",
    "oracle_depth_logits",
]

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


#: Logit of the bins an oracle rules out: ``exp(-1e4)`` is exactly 0 in float32, and -1e4 fits float16.
_RULED_OUT = -1.0e4


def oracle_depth_logits(depth: Tensor, h: int, w: int, centers: Tensor) -> Tensor:
    """One-hot depth logits of each feature cell from a true depth map.

    Cell ``(r, c)`` of an ``(h, w)`` feature map with stride ``s = H / h`` reads the depth of the pixel
    ``(s * r + s // 2, s * c + s // 2)`` (nearest the point the lift unprojects,
    :func:`occplug.ops.feature_cell_centers`); the bin whose centre is nearest that depth gets logit 0
    and every other bin :data:`_RULED_OUT`, so the softmax is exactly one-hot. Cells whose depth lies
    beyond half a bin gap outside the first / last centre, or that have none (sky: 0), get equal
    logits (a uniform distribution). For uniform bins ``[start, stop, step]`` the bin is
    ``floor((z - start) / step)`` and the valid range ``[start, stop)``.

    Args:
        depth: ``(B, N, H, W)`` camera-frame z, metres (0 = no surface).
        h, w: the feature map's size (``H``, ``W`` the same whole multiple of them).
        centers: ``(D,)`` increasing bin centres, metres of camera z.

    Returns:
        ``(B, N, D, h, w)`` float32 logits.
    """
    big_h, big_w = depth.shape[-2:]
    if big_h % h or big_w % w or big_h // h != big_w // w:
        raise ValueError(f"oracle_depth: depth maps {big_h}x{big_w} are not a whole multiple of features {h}x{w}")
    s = big_h // h
    c = centers.to(device=depth.device, dtype=torch.float64)
    num_bins = int(c.shape[0])
    rows = torch.arange(h, device=depth.device) * s + s // 2
    cols = torch.arange(w, device=depth.device) * s + s // 2
    z = depth[..., rows[:, None], cols[None, :]].double()  # (B, N, h, w)
    index = torch.bucketize(z, (c[1:] + c[:-1]) / 2, right=True)
    valid = z > 0
    if num_bins > 1:
        valid &= (z >= c[0] - (c[1] - c[0]) / 2) & (z < c[-1] + (c[-1] - c[-2]) / 2)
    one_hot = torch.nn.functional.one_hot(index, num_bins).movedim(-1, 2).bool()
    logits = torch.where(one_hot, 0.0, _RULED_OUT).float()
    return torch.where(valid[:, :, None], logits, torch.zeros_like(logits))


class OracleDepthNet(DepthNet):
    """Perfect depth: the batch's true depth maps as one-hot depth distributions (a ceiling, not a model).

    The depth logits are :func:`oracle_depth_logits` of ``batch.depth`` (the ground-truth depth the
    synthetic world renders; augmented with the images); the context is a learnt per-cell conv head
    (``3x3 conv -> norm -> ReLU -> 1x1 conv``, or one 1x1 conv with ``hidden: 0``). Any lift-splat model
    is run with perfect depth by ``view_transform.depth_net: {type: oracle_depth}``: the lift then puts
    every feature on its surface (to the bin), and what the model still misses is not depth's fault.
    Sky cells spread their feature uniformly along the ray.

    The bins: ``depth_centers``, which ``lss`` fills in with its own; else ``depth_bins`` ``[start, stop,
    step]``; else ``D`` bins of 1 m from 1 m. A view transform that fills in neither must be given
    ``depth_bins`` matching its own.

    Args:
        in_channels: ``C_in``; num_bins: ``D``; out_channels: ``C``.
        depth_centers: ``(D,)`` bin centres, metres (filled in by ``lss``).
        depth_bins: ``[start, stop, step]`` metres of uniform bins (checked against ``D``).
        hidden: width of the context head's 3x3 conv (0: a single 1x1 conv).
    """

    def __init__(
        self,
        in_channels: int,
        num_bins: int,
        out_channels: int,
        depth_centers: Tensor | list[float] | None = None,
        depth_bins: Annotated[list[float] | None, Length(exact=3)] = None,
        hidden: Annotated[int, NonNegative] = 64,
    ) -> None:
        super().__init__()
        if depth_centers is not None:
            centers = torch.as_tensor(depth_centers, dtype=torch.float32).flatten()
        elif depth_bins is not None:
            start, stop, step = (float(v) for v in depth_bins)
            if step <= 0 or stop <= start:
                raise ValueError(
                    f"oracle_depth: depth_bins [start, stop, step] needs start < stop, step > 0; got {depth_bins}"
                )
            centers = start + step / 2 + step * torch.arange(round((stop - start) / step), dtype=torch.float32)
        else:
            centers = 1.5 + torch.arange(int(num_bins), dtype=torch.float32)
        if centers.shape[0] != num_bins or bool((centers[1:] <= centers[:-1]).any()):
            raise ValueError(
                f"oracle_depth: {centers.shape[0]} increasing depth bins expected to match the view transform's "
                f"{num_bins} (give oracle_depth the view transform's depth_bins)"
            )
        self.num_bins, self.out_channels = int(num_bins), int(out_channels)
        self.register_buffer("centers", centers, persistent=False)
        self.context_net = PixelNet(in_channels, hidden, self.out_channels)

    def forward(self, features: Tensor, batch: Any) -> DepthAndContext:
        """``(B, N, C_in, h, w)`` and ``batch.depth`` ``(B, N, H, W)`` -> :class:`DepthAndContext`."""
        depth = getattr(batch, "depth", None)
        if depth is None:
            raise ValueError("oracle_depth needs the batch's true depth maps ('depth'); this data set has none")
        b, n, _, h, w = features.shape
        logits = oracle_depth_logits(depth, h, w, self.centers).to(features.dtype)
        context = self.context_net(features.flatten(0, 1)).view(b, n, self.out_channels, h, w)
        return DepthAndContext(logits, context)
