"""Label fractions: which training frames keep their voxel labels (label-efficient training).

``data.label_fraction: f`` marks ``k = ceil(f * N)`` of the ``N`` training frames as labelled by
interval sampling: frame ``i`` (in sequence order: scene-major, temporal inside a scene) is labelled iff
``i`` is in ``{floor(j * N / k) : j = 0 .. k - 1}``. The set depends on ``N`` and ``f`` only, so it is the
same on every rank and in every run. An unlabelled frame keeps its images, LiDAR and pseudo labels, but
its voxel labels are overwritten with the ignore label and ``Frame.has_voxel_labels`` is False before any
label source, augmentation or loss sees it (visibility masks are kept: they describe the sensors).

``data.label_unit: scene`` labels whole scenes instead: ``k = ceil(f * S)`` of the ``S`` training scenes,
chosen by the same interval rule over the scene order, keep every frame's labels and the other scenes
none (so an unlabelled frame is a whole scene away from any label, not half a second).

``data.subset: all | labelled | unlabelled`` restricts the training split to one side of that cut.
Validation, test and predict splits are never cut.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from torch.utils.data import Dataset

from .frame import Frame
from .sequences import SceneIndex

__all__ = ["LABEL_UNITS", "SUBSETS", "LabelCut", "SubsetDataset", "labelled_indices", "strip_voxel_labels"]

#: The values of ``data.subset``.
SUBSETS: tuple[str, ...] = ("all", "labelled", "unlabelled")
#: The values of ``data.label_unit``.
LABEL_UNITS: tuple[str, ...] = ("frame", "scene")


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
        unit: ``frame`` (interval sampling of frames) or ``scene`` (of whole scenes).
    """

    def __init__(self, fraction: float = 1.0, subset: str = "all", unit: str = "frame") -> None:
        if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or not 0.0 < fraction <= 1.0:
            raise ValueError(f"data.label_fraction: expected a number in (0, 1], got {fraction!r}")
        if subset not in SUBSETS:
            raise ValueError(f"data.subset: expected one of {', '.join(SUBSETS)}, got {subset!r}")
        if subset == "unlabelled" and fraction == 1.0:
            raise ValueError("data.subset: 'unlabelled' with data.label_fraction 1.0 selects no frame")
        if unit not in LABEL_UNITS:
            raise ValueError(f"data.label_unit: expected one of {', '.join(LABEL_UNITS)}, got {unit!r}")
        self.fraction = float(fraction)
        self.subset = subset
        self.unit = unit

    @property
    def active(self) -> bool:
        """Whether the cut changes the split at all."""
        return self.fraction < 1.0 or self.subset != "all"

    def unlabelled(self, n: int, scenes: SceneIndex | None = None) -> frozenset[int]:
        """The indices (of ``n``) whose voxel labels are hidden; ``unit: scene`` needs the ``scenes``."""
        if self.unit == "frame":
            return frozenset(range(n)) - frozenset(labelled_indices(n, self.fraction))
        if scenes is None:
            raise ValueError("data.label_unit: 'scene' needs a training set with a scene structure ('scenes')")
        kept = labelled_indices(len(scenes.items), self.fraction)
        return frozenset(range(n)) - frozenset(i for s in kept for i in scenes.items[s])

    def selected(self, n: int, scenes: SceneIndex | None = None) -> list[int]:
        """The indices of ``n`` the training split keeps, in order."""
        if self.subset == "all":
            return list(range(n))
        hidden = self.unlabelled(n, scenes)
        return [i for i in range(n) if (i in hidden) == (self.subset == "unlabelled")]

    def describe(self) -> dict[str, float | str]:
        """What ``metrics.json`` records."""
        out: dict[str, float | str] = {"label_fraction": self.fraction, "subset": self.subset}
        if self.unit != "frame":
            out["label_unit"] = self.unit
        return out


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
