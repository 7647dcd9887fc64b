"""Kind ``depth_net``: per-cell depth logits and context features for a lift-splat view transform."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar, NamedTuple

import torch
from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.geometry import GridSpec

from .checks import CHECK_CHANNELS, assert_gradient, eval_twice
from .view_transform import random_image_features

__all__ = ["DepthAndContext", "DepthNet"]


class DepthAndContext(NamedTuple):
    """What a depth net returns.

    Attributes:
        depth_logits: ``(B, N, D, h, w)`` unnormalised scores over the ``D`` depth bins (the view
            transform applies the softmax over ``D``).
        context: ``(B, N, C, h, w)`` context features per cell.
    """

    depth_logits: Tensor
    context: Tensor


class DepthNet(nn.Module, ABC):
    """Kind ``depth_net``: image features (+ calibration) -> per-cell depth logits and context.

    A lift-splat view transform runs one on the image features before splatting; a config swaps it
    as a nested node (``view_transform.depth_net: {type: camera_aware}``).

    Contract:
        given: ``in_channels`` (the image features' channels), ``num_bins`` (``D``) and
        ``out_channels`` (``C`` context channels), filled in by the view transform.
        declares: ``num_bins`` and ``out_channels``.

    Attributes:
        num_bins: ``D``.
        out_channels: ``C`` of the context.

    .. versionadded:: 0.2
    """

    #: Constructor arguments the view transform fills in when the config leaves them out.
    given: ClassVar[tuple[str, ...]] = ("in_channels", "num_bins", "out_channels")

    num_bins: int
    out_channels: int

    @abstractmethod
    def forward(self, features: Tensor, batch: Any) -> DepthAndContext:
        """Predict depth and context.

        Args:
            features: ``(B, N, C_in, h, w)`` image features.
            batch: the :class:`~occplug.data.Batch` (``intrinsics``, ``cam_to_ego``, ``img_aug``,
                ``images`` for the image size).

        Returns:
            :class:`DepthAndContext` with ``(B, N, D, h, w)`` logits and ``(B, N, C, h, w)`` context.
        """

    @classmethod
    def check_conformance(cls, component: DepthNet, batch: Batch, grid: GridSpec) -> None:
        """The kind's contract, checked: depth logits and context of the declared shapes, deterministic in eval,
        gradients to the image features and its parameters.

        :func:`occplug.testing.check_component` runs it on every registered component of this kind.
        """
        net = component
        inputs = type(net).conformance_inputs(batch, grid, CHECK_CHANNELS)
        first, second = eval_twice(net, lambda m: m(*inputs))
        b, n, _, h, w = inputs[0].shape
        assert isinstance(first, DepthAndContext), "a depth net returns DepthAndContext"
        assert first.depth_logits.shape == (b, n, net.num_bins, h, w), f"depth logits {tuple(first.depth_logits.shape)}"
        assert first.context.shape == (b, n, net.out_channels, h, w), f"context {tuple(first.context.shape)}"
        assert torch.equal(first.depth_logits, second.depth_logits) and torch.equal(first.context, second.context), (
            "depth net is not deterministic in eval mode"
        )
        out = net(*inputs)
        (out.depth_logits.square().mean() + out.context.square().mean()).backward()
        assert inputs[0].grad is not None and inputs[0].grad.abs().sum() > 0, "no gradient reaches the image features"
        assert_gradient(net, "depth net")

    @classmethod
    def conformance_inputs(cls, batch: Any, grid: Any, channels: int) -> tuple[Any, ...]:
        """Positional ``forward`` inputs for the conformance check: random stride-4 features
        ``(B, N, channels, H // 4, W // 4)`` (requiring grad) and the batch."""
        return (random_image_features(batch, channels), batch)
