"""Kind ``encoder``: per-view image features."""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor, nn

__all__ = ["ImageEncoder"]


class ImageEncoder(nn.Module, ABC):
    """Turns multi-view images into per-view feature maps.

    Subclasses set ``out_channels`` (``C``) and ``stride`` (input pixels per feature cell) in
    ``__init__`` so a view transform can size itself and map feature cells back to pixels.

    Example:
        >>> enc = registry.build("encoder", {"type": "small_cnn", "out_channels": 32})  # doctest: +SKIP
        >>> enc(images).shape  # images (B, N, 3, H, W)                                  # doctest: +SKIP
        torch.Size([B, N, 32, H // enc.stride, W // enc.stride])

    .. versionadded:: 0.1
    """

    #: Optional :class:`~occplug.data.Frame` fields this component reads (e.g. ``{"points"}``):
    #: data modules skip loading what no component requires (a camera-only model opens no LiDAR file).
    requires: frozenset[str] = frozenset()

    out_channels: int
    stride: int

    @abstractmethod
    def forward(self, images: Tensor) -> Tensor:
        """Encode images.

        Args:
            images: ``(B, N, 3, H, W)`` float in [0, 1].

        Returns:
            ``(B, N, C, H // stride, W // stride)`` features.
        """
