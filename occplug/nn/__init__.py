"""Shared building blocks for components: plain ``nn.Module``s and functions, method-free, registered nowhere.

A plugin that needs a residual block, an attention block, a loss or a matcher takes it from here rather than
writing its own, so each block exists once in the tree.
"""

from .layers import BasicBlock2d, BasicBlock3d, ConvNormAct2d, PixelNet, norm_layer

__all__ = ["BasicBlock2d", "BasicBlock3d", "ConvNormAct2d", "PixelNet", "norm_layer"]
