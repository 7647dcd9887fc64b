"""Kinds ``encoder`` (images) and ``point_encoder`` (LiDAR points): the model's input branches."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.geometry import GridSpec

from .checks import CHECK_CHANNELS, assert_finite, assert_gradient, eval_twice

__all__ = ["ImageEncoder", "PointEncoder", "feature_levels"]


def feature_levels(output: Tensor | list[Tensor] | tuple[Tensor, ...]) -> list[Tensor]:
    """An encoder's output as a list of levels, finest first (a single tensor is one level)."""
    return [output] if isinstance(output, Tensor) else list(output)


class ImageEncoder(nn.Module, ABC):
    """Turns multi-view images into per-view feature maps, at one scale or several.

    Contract:
        given: nothing (the encoder is the first component).
        declares: ``out_channels`` (``C``) and ``stride`` (input pixels per feature cell) of the
        level the view transform reads (the *primary* level); a multi-scale encoder also sets
        ``level_channels`` and ``level_strides`` (finest first) and ``primary_level`` (the index of
        the primary level among them), and its ``forward`` returns a list of levels. Single-scale
        encoders leave those at their defaults and return one tensor.

    The model hands the view transform the primary level (and ``level_channels`` /
    ``level_strides`` where its constructor takes them); every level reaches heads and supervision
    as :attr:`~occplug.interfaces.ModelOutputs.image_levels`.

    Example:
        >>> enc = registry.build("encoder", {"type": "small_cnn", "out_channels": 32})  # doctest: +SKIP
        >>> enc(images).shape  # images (B, N, 3, H, W)                                  # doctest: +SKIP
        torch.Size([B, N, 32, H // enc.stride, W // enc.stride])

    .. versionadded:: 0.1
    .. versionchanged:: 0.2 multi-scale outputs (``level_channels``, ``level_strides``, ``primary_level``).
    """

    #: Constructor arguments the model fills in (none: the encoder reads the images).
    given: ClassVar[tuple[str, ...]] = ()
    #: Optional :class:`~occplug.data.Frame` fields this component reads (e.g. ``{"points"}``):
    #: data modules skip loading what no component requires (a camera-only model opens no LiDAR file).
    requires: frozenset[str] = frozenset()

    out_channels: int
    stride: int
    #: Index of the primary level in a multi-scale output (0 for a single tensor).
    primary_level: int = 0

    @property
    def level_channels(self) -> tuple[int, ...]:
        """``C`` of each output level, finest first (one level: ``(out_channels,)``)."""
        return getattr(self, "_level_channels", (self.out_channels,))

    @property
    def level_strides(self) -> tuple[int, ...]:
        """Stride of each output level, finest first (one level: ``(stride,)``)."""
        return getattr(self, "_level_strides", (self.stride,))

    @abstractmethod
    def forward(self, images: Tensor) -> Tensor | list[Tensor]:
        """Encode images.

        Args:
            images: ``(B, N, 3, H, W)`` float in [0, 1].

        Returns:
            ``(B, N, C, H // stride, W // stride)`` features, or a list of such tensors (one per
            level, finest first; level ``i`` has ``level_channels[i]`` channels at
            ``level_strides[i]``).
        """

    @classmethod
    def check_conformance(cls, component: ImageEncoder, batch: Batch, grid: GridSpec) -> None:
        """The kind's contract, checked: its levels' shapes match its declared channels and strides, eval is
        deterministic, outputs finite, gradients reach its parameters.

        :func:`occplug.testing.check_component` runs it on every registered component of this kind.
        """
        enc = component
        assert isinstance(enc.out_channels, int) and isinstance(enc.stride, int), "encoder must set out_channels and stride"
        b, n, _, h, w = batch.images.shape
        inputs = type(enc).conformance_inputs(batch, grid, CHECK_CHANNELS)
        first, second = eval_twice(enc, lambda m: feature_levels(m(*inputs)))
        channels, strides = enc.level_channels, enc.level_strides
        assert len(first) == len(channels) == len(strides), f"encoder gave {len(first)} levels, declares {len(channels)}"
        assert 0 <= enc.primary_level < len(first), f"primary_level {enc.primary_level} outside {len(first)} levels"
        assert (channels[enc.primary_level], strides[enc.primary_level]) == (enc.out_channels, enc.stride), (
            "the primary level must have out_channels and stride"
        )
        for level, (a, c, s) in enumerate(zip(first, channels, strides, strict=True)):
            assert a.shape == (b, n, c, h // s, w // s), f"encoder level {level}: {tuple(a.shape)}"
        for a, c in zip(first, second, strict=True):
            assert torch.equal(a, c), "encoder is not deterministic in eval mode"
            assert_finite(a, "encoder output")
        torch.stack([x.square().mean() for x in feature_levels(enc(*inputs))]).sum().backward()
        assert_gradient(enc, "encoder")

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple[Any, ...]:
        """Positional ``forward`` inputs for the conformance check: the batch's images."""
        return (batch.images,)


class PointEncoder(nn.Module, ABC):
    """Turns a batch's LiDAR points into a feature volume (a model's LiDAR branch).

    Contract:
        given: ``grid`` (the evaluation grid, unless the config sets its own).
        declares: ``out_channels`` and ``grid`` (the grid its volume lives on); ``requires``
        includes ``"points"`` so data modules load LiDAR.

    A model may hold several named point encoders; their volumes reach view transforms, scenes
    and heads that read model outputs as :attr:`~occplug.interfaces.ModelOutputs.encoded`.

    .. versionadded:: 0.2
    """

    given: ClassVar[tuple[str, ...]] = ("grid",)
    requires: frozenset[str] = frozenset({"points"})

    out_channels: int
    grid: GridSpec

    @abstractmethod
    def forward(self, batch: Batch) -> Tensor:
        """Encode the batch's points.

        Args:
            batch: supplies ``points`` (per sample ``(P, 4)`` x, y, z, intensity in the lidar
                frame) and ``lidar_to_ego``.

        Returns:
            ``(B, out_channels, X, Y, Z)`` features on ``grid`` in the ego frame.
        """

    @classmethod
    def check_conformance(cls, component: PointEncoder, batch: Batch, grid: GridSpec) -> None:
        """The kind's contract, checked: a ``(B, out_channels, *grid.shape)`` volume, deterministic in eval,
        finite, with gradients.

        :func:`occplug.testing.check_component` runs it on every registered component of this kind.
        """
        enc = component
        assert isinstance(enc.out_channels, int) and isinstance(enc.grid, GridSpec), "point encoder sets out_channels, grid"
        inputs = type(enc).conformance_inputs(batch, grid, CHECK_CHANNELS)
        first, second = eval_twice(enc, lambda m: m(*inputs))
        assert first.shape == (len(batch), enc.out_channels, *enc.grid.shape), f"point encoder output {tuple(first.shape)}"
        assert torch.equal(first, second), "point encoder is not deterministic in eval mode"
        assert_finite(first, "point encoder output")
        enc(*inputs).square().mean().backward()
        assert_gradient(enc, "point encoder")

    @classmethod
    def conformance_inputs(cls, batch: Batch, grid: GridSpec, channels: int) -> tuple[Any, ...]:
        """Positional ``forward`` inputs for the conformance check: the batch itself."""
        return (batch,)

