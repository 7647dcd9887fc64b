"""Kind ``view_transform``: lift per-view 2D features into a 3D (or BEV) volume."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.geometry import GridSpec

from .checks import CHECK_CHANNELS, assert_finite, assert_gradient, eval_twice

__all__ = ["Lifted", "ViewTransform", "random_image_features"]


@dataclass
class Lifted:
    """What a view transform produces.

    Attributes:
        volume: ``(B, C, X, Y, Z)`` features on ``grid`` in the ego frame (or ``(B, C, X, Y)``
            for a BEV transform, in which case ``grid``'s z extent is the pooled height range).
        grid: the grid the volume lives on.
        depth_probs: ``(B, N, D, h, w)`` per-pixel depth distributions, if the transform predicts
            them (depth supervision reads this together with ``depth_bins``).
        depth_bins: ``(D,)`` bin centres in metres (camera-frame z) for ``depth_probs``.
        image_stride: image pixels per cell of ``depth_probs`` (the encoder's stride).
        extras: transform-specific outputs for a matching supervision source.
    """

    volume: Tensor
    grid: GridSpec
    depth_probs: Tensor | None = None
    depth_bins: Tensor | None = None
    image_stride: int | None = None
    extras: dict[str, Tensor] = field(default_factory=dict)


class ViewTransform(nn.Module, ABC):
    """Lifts image features into the ego frame using the batch's calibration.

    Contract:
        given: ``in_channels`` and ``image_stride`` (the encoder's primary level; filled in by the
        model when the config leaves them out). A transform whose constructor also takes
        ``level_channels`` / ``level_strides`` receives the encoder's multi-scale layout.
        declares: ``out_channels`` and ``grid``; ``reads_outputs = True`` to be called as
        ``forward(features, batch, outputs)`` with the model's outputs so far (every image level,
        the point encoders' volumes) -- e.g. a camera-LiDAR fusion transform.

    .. versionadded:: 0.1
    """

    #: Constructor arguments the model fills in when the config leaves them out.
    given: ClassVar[tuple[str, ...]] = ("in_channels", "image_stride", "level_channels", "level_strides", "grid")
    #: Whether ``forward`` takes a third argument, the :class:`~occplug.interfaces.ModelOutputs` so far.
    reads_outputs: ClassVar[bool] = False
    #: Whether it carries state from frame to frame (a :class:`~occplug.streams.StreamState`); a stateful model
    #: needs ``data.sequential``.
    stateful: ClassVar[bool] = False

    #: Optional :class:`~occplug.data.Frame` fields this component reads (e.g. ``{"points"}``):
    #: data modules skip loading what no component requires (a camera-only model opens no LiDAR file).
    requires: frozenset[str] = frozenset()

    out_channels: int
    grid: GridSpec

    @abstractmethod
    def forward(self, features: Tensor, batch: Batch) -> Lifted:
        """Lift features.

        Args:
            features: ``(B, N, C, h, w)`` from the image encoder.
            batch: supplies ``intrinsics``, ``cam_to_ego`` and ``img_aug`` (augmented pixels are
                mapped exactly through ``img_aug @ intrinsics``) and the image size.

        Returns:
            A :class:`Lifted` volume in the ego frame.
        """

    @classmethod
    def check_conformance(cls, component: ViewTransform, batch: Batch, grid: GridSpec) -> None:
        """The kind's contract, checked: a :class:`Lifted` volume on its grid, depth probabilities summing to 1,
        deterministic in eval, gradients to the features and its parameters.

        :func:`occplug.testing.check_component` runs it on every registered component of this kind.
        """
        vt = component
        inputs = type(vt).conformance_inputs(batch, grid, CHECK_CHANNELS)
        first, second = eval_twice(vt, lambda m: m(*inputs).volume)
        assert torch.equal(first, second), "view transform is not deterministic in eval mode"
        lifted = vt(*inputs)
        b = len(batch)
        assert isinstance(lifted, Lifted), "a view transform returns Lifted"
        assert lifted.volume.shape[:2] == (b, vt.out_channels), f"volume shape {tuple(lifted.volume.shape)}"
        assert tuple(lifted.volume.shape[2:]) in (lifted.grid.shape, lifted.grid.shape[:2])
        if lifted.depth_probs is not None:
            assert lifted.depth_bins is not None and lifted.depth_probs.shape[2] == lifted.depth_bins.shape[0]
            assert torch.allclose(lifted.depth_probs.sum(2), torch.ones(()), atol=1e-4), "depth_probs must sum to 1"
        assert_finite(lifted.volume, "lifted volume")
        lifted.volume.square().mean().backward()
        feats = inputs[0]
        if isinstance(feats, Tensor) and feats.requires_grad:
            assert feats.grad is not None and feats.grad.abs().sum() > 0, "no gradient reaches the image features"
        assert_gradient(vt, "view transform")

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple[Any, ...]:
        """Positional ``forward`` inputs for the conformance check: random stride-4 features
        ``(B, N, channels, H // 4, W // 4)`` (requiring grad) and the batch."""
        return (random_image_features(batch, channels), batch)


def random_image_features(batch: Batch, channels: int, stride: int = 4) -> Tensor:
    """Seeded random ``(B, N, channels, H // stride, W // stride)`` features requiring grad (conformance inputs)."""
    b, n, _, h, w = batch.images.shape
    gen = torch.Generator().manual_seed(0)
    return torch.randn(b, n, channels, h // stride, w // stride, generator=gen, requires_grad=True)
