"""Shared building blocks for components: plain ``nn.Module``s and functions, method-free, registered nowhere.

A plugin that needs a residual block, an attention block, a loss or a matcher takes it from here rather than
writing its own, so each block exists once in the tree:

* :mod:`~occplug.nn.layers`: convolution / norm / activation, ResNet basic blocks, the view transforms' pixel head;
* :mod:`~occplug.nn.unet`: small dense 2D / 3D UNets and their anisotropic downsampling rule;
* :mod:`~occplug.nn.attention`: deformable attention (2D maps, 3D grids) and CBAM;
* :mod:`~occplug.nn.losses`: sigmoid focal and dice losses, element-wise and pairwise;
* :mod:`~occplug.nn.matching`: Hungarian matching (scipy, imported only when a match runs).
"""

from .attention import (
    CBAM,
    ChannelAttention,
    DeformableAttention,
    SpatialAttention2d,
    SpatialAttention3d,
    cbam,
    deformable_sample,
    spread_directions,
)
from .layers import BasicBlock2d, BasicBlock3d, ConvNormAct2d, ConvNormAct3d, PixelNet, norm_layer
from .losses import dice_loss, pairwise_dice_loss, pairwise_sigmoid_focal_loss, sigmoid_focal_loss
from .matching import linear_assignment
from .unet import UNet2d, UNet3d, halving_stride

__all__ = [
    "CBAM",
    "BasicBlock2d",
    "BasicBlock3d",
    "ChannelAttention",
    "ConvNormAct2d",
    "ConvNormAct3d",
    "DeformableAttention",
    "PixelNet",
    "SpatialAttention2d",
    "SpatialAttention3d",
    "UNet2d",
    "UNet3d",
    "cbam",
    "deformable_sample",
    "dice_loss",
    "halving_stride",
    "linear_assignment",
    "norm_layer",
    "pairwise_dice_loss",
    "pairwise_sigmoid_focal_loss",
    "sigmoid_focal_loss",
    "spread_directions",
]
