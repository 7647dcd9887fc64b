"""Kind ``view_transform``: lift per-view 2D features into a 3D (or BEV) volume."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

from torch import Tensor, nn

from occplug.data.frame import Batch
from occplug.geometry import GridSpec

__all__ = ["Lifted", "ViewTransform"]


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

    Constructors take ``in_channels`` (the encoder's ``out_channels``, filled in by the model
    when the config leaves it out), ``image_stride`` (likewise from the encoder) and ``grid``.

    .. versionadded:: 0.1
    """

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
