"""Label fractions: which training frames keep their voxel labels (label-efficient training).

``data.label_fraction: f`` marks ``k = ceil(f * N)`` of the ``N`` training frames as labelled by
interval sampling: frame ``i`` (in sequence order: scene-major, temporal inside a scene) is labelled iff
``i`` is in ``{floor(j * N / k) : j = 0 .. k - 1}``. The set depends on ``N`` and ``f`` only, so it is the
same on every rank and in every run. An unlabelled frame keeps its images, LiDAR and pseudo labels, but
its voxel labels are overwritten with the ignore label and ``Frame.has_voxel_labels`` is False before any
label source, augmentation or loss sees it (visibility masks are kept: they describe the sensors).

``data.subset: all | labelled | unlabelled`` restricts the training split to one side of that cut.
Validation, test and predict splits are never cut.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from torch.utils.data import Dataset

from .frame import Frame

__all__ = ["SUBSETS", "LabelCut", "SubsetDataset", "labelled_indices", "strip_voxel_labels"]

#: The values of ``data.subset``.
SUBSETS: tuple[str, ...] = ("all", "labelled", "unlabelled")


def labelled_indices(n: int, fraction: float) -> list[int]:
    """The labelled frames among ``n``: ``{floor(j * n / k)}`` for ``j < k = ceil(fraction * n)``.

    Args:
        n: frames of the split, in sequence order.
        fraction: in (0, 1]; 1 labels every frame.

    Returns:
        sorted, distinct indices (``k`` of them; none when ``n`` is 0).
    """
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"data.label_fraction: expected a number in (0, 1], got {fraction!r}")
    if n <= 0:
        return []
    k = min(n, math.ceil(fraction * n - 1e-9))  # 1e-9: 0.1 * 30 is 3.0000000000000004 in floating point
    return [j * n // k for j in range(k)]


def strip_voxel_labels(frame: Frame, fill: int) -> Frame:
    """``frame`` with its voxel labels replaced by ``fill`` (the ignore label) and ``has_voxel_labels``
    False, so no loss can read them."""
    if frame.voxel_labels is not None:
        frame.voxel_labels = frame.voxel_labels.new_full(frame.voxel_labels.shape, fill)
    frame.has_voxel_labels = False
    return frame


class LabelCut:
    """The label fraction and subset of a training split (``data.label_fraction``, ``data.subset``).

    Args:
        fraction: in (0, 1].
        subset: ``all``, ``labelled`` or ``unlabelled``.
    """

    def __init__(self, fraction: float = 1.0, subset: str = "all") -> None:
        if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or not 0.0 < fraction <= 1.0:
            raise ValueError(f"data.label_fraction: expected a number in (0, 1], got {fraction!r}")
        if subset not in SUBSETS:
            raise ValueError(f"data.subset: expected one of {', '.join(SUBSETS)}, got {subset!r}")
        if subset == "unlabelled" and fraction == 1.0:
            raise ValueError("data.subset: 'unlabelled' with data.label_fraction 1.0 selects no frame")
        self.fraction = float(fraction)
        self.subset = subset

    @property
    def active(self) -> bool:
        """Whether the cut changes the split at all."""
        return self.fraction < 1.0 or self.subset != "all"

    def unlabelled(self, n: int) -> frozenset[int]:
        """The indices (of ``n``) whose voxel labels are hidden."""
        return frozenset(range(n)) - frozenset(labelled_indices(n, self.fraction))

    def selected(self, n: int) -> list[int]:
        """The indices of ``n`` the training split keeps, in order."""
        if self.subset == "all":
            return list(range(n))
        hidden = self.unlabelled(n)
        return [i for i in range(n) if (i in hidden) == (self.subset == "unlabelled")]

    def describe(self) -> dict[str, float | str]:
        """What ``metrics.json`` records."""
        return {"label_fraction": self.fraction, "subset": self.subset}


class SubsetDataset(Dataset[Frame]):
    """Items ``indices`` of ``base``, in that order (``data.subset``).

    Args:
        base: the full training split.
        indices: the kept items.
    """

    def __init__(self, base: Dataset[Frame], indices: Sequence[int]) -> None:
        self.base = base
        self.indices = list(indices)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index: int) -> Frame:
        return self.base[self.indices[index]]
