"""Class frequencies of a data set: voxels per label id over a split (``occplug data stats``).

Losses that weight classes by frequency (MonoScene's ``1 / log(f + 0.001)``, e.g. OccLE's ``class_frequencies``)
take these counts as they are; :func:`inverse_log_weights` is that family of weights (``scale / log(f + eps)``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from occplug.data.frame import Frame

__all__ = ["ClassCounts", "class_counts", "inverse_log_weights"]


@dataclass
class ClassCounts:
    """Voxels per label id over the frames that were counted."""

    #: ``(K,)`` int64: voxels whose label is id ``k`` (ids >= K, e.g. an ignore label 255, are not counted).
    counts: np.ndarray
    #: frames counted (with voxel labels usable for training).
    frames: int
    #: frames skipped: no voxel labels, or ``has_voxel_labels`` False (a label-fraction split's unlabelled frames).
    skipped: int


def class_counts(
    frames: Sequence[Frame], num_classes: int, mask: str = "none", max_frames: int | None = None
) -> ClassCounts:
    """Count voxel labels per class.

    Args:
        frames: a data set's frames (a ``Dataset`` indexable by position works).
        num_classes: ``K``, label ids ``0 .. K-1`` (free included).
        mask: ``"none"`` (every voxel) or ``"camera"`` (only ``mask_camera`` voxels; a frame without one is
            counted whole).
        max_frames: count at most this many frames (from the first), or all.

    Returns:
        :class:`ClassCounts`.
    """
    if mask not in ("none", "camera"):
        raise ValueError(f"class counts: mask must be 'none' or 'camera', got {mask!r}")
    total = np.zeros(num_classes, dtype=np.int64)
    counted = skipped = 0
    limit = len(frames) if max_frames is None else min(int(max_frames), len(frames))
    for i in range(limit):
        frame = frames[i]
        if frame.voxel_labels is None or not frame.has_voxel_labels:
            skipped += 1
            continue
        labels = frame.voxel_labels.to(torch.int64)
        if mask == "camera" and frame.mask_camera is not None:
            labels = labels[frame.mask_camera.to(torch.bool)]
        labels = labels[(labels >= 0) & (labels < num_classes)]
        total += torch.bincount(labels.flatten(), minlength=num_classes).numpy()
        counted += 1
    return ClassCounts(counts=total, frames=counted, skipped=skipped)


def inverse_log_weights(counts: torch.Tensor | Sequence[float], scale: float = 1.0, eps: float = 0.0) -> torch.Tensor:
    """Class weights ``w_c = scale / log(f_c + eps)`` from raw class counts (larger for rarer classes).

    MonoScene's (and OccLE's) weights are ``scale=1, eps=0.001``; the public DuOcc code's are ``scale=5, eps=0``
    (then halves free's).

    Args:
        counts: ``(K,)`` raw voxel (or pixel) counts per class over a training set, e.g. :func:`class_counts`'
            ``counts``; normalised frequencies would make the logarithm negative.
        scale: the numerator.
        eps: added to every count before the logarithm.

    Returns:
        ``(K,)`` float32 weights.

    Raises:
        ValueError: ``counts`` is not 1-D, or a count has ``f + eps <= 1`` (the weight would be negative or
            infinite).
    """
    f = torch.as_tensor(counts, dtype=torch.float64)
    if f.dim() != 1 or bool((f + eps <= 1.0).any()):
        raise ValueError(
            f"class weights scale / log(f + {eps:g}) need a 1-D list of raw class counts, each above {1 - eps:g} "
            f"(the weight is negative or infinite otherwise), got {f.tolist()}"
        )
    return (scale / torch.log(f + eps)).to(torch.float32)
