"""How pictures look: the class palette of a data set and the fixed colours of the panels.

Class colours come from the core (:func:`occplug.data.classes.class_colors`: the official
Occ3D-nuScenes and SemanticKITTI palettes); this module only adds what a picture needs around
them: a background for empty space and the colours of the error map.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from occplug.data.classes import class_colors

__all__ = [
    "BACKGROUND",
    "EGO_COLOR",
    "ERROR_COLORS",
    "ERROR_NAMES",
    "FLOOR",
    "FLOOR_LINE",
    "MASK_HALO",
    "MASK_LINE",
    "Palette",
]

#: RGB of empty space (free columns, sky, pixels without a hit): a mid-dark slate teal, at least
#: 30 CIELAB units (Delta E 1976) from every colour of both official palettes, black (Occ3D
#: ``others``) and the light ``manmade`` lavender included; :data:`FLOOR` and
#: :data:`FLOOR_LINE` (the 3D view's ground plane) stay 25 units from every class colour too.
BACKGROUND: tuple[int, int, int] = (44, 72, 80)
#: The 3D view's floor (the grid's ground plane where no voxel is hit) and its 10 m lines.
FLOOR: tuple[int, int, int] = (36, 58, 66)
FLOOR_LINE: tuple[int, int, int] = (56, 86, 94)
#: The camera-mask outline (BEV maps and their legend): white dashes on a black halo, so that one
#: of the two contrasts with any class colour, the background and the figure's white.
MASK_LINE: tuple[int, int, int] = (255, 255, 255)
MASK_HALO: tuple[int, int, int] = (0, 0, 0)
#: RGB of the ego vehicle marker in the 3D view.
EGO_COLOR: tuple[int, int, int] = (0, 255, 127)

#: Error-map categories, index = code of :func:`occplug.viz.bev.error_codes`.
ERROR_NAMES: tuple[str, ...] = ("empty", "correct", "wrong class", "missed", "false occupied")
#: Their colours (code 0, empty, is the background).
ERROR_COLORS: tuple[tuple[int, int, int], ...] = (
    BACKGROUND,
    (90, 200, 90),  # correct: green
    (250, 170, 30),  # wrong class: amber
    (60, 120, 255),  # missed: blue (a ground-truth voxel the prediction left free)
    (235, 50, 50),  # false occupied: red (a prediction where the truth is free)
)


@dataclass(frozen=True)
class Palette:
    """The classes of a data set and their colours.

    Attributes:
        names: ``K`` class names, index = id.
        colors: ``(K, 3)`` uint8 RGB, index = id.
        free_label: id of empty space (drawn as background, left out of legends).
        ignore_label: id to skip (drawn as background), or None.
    """

    names: tuple[str, ...]
    colors: np.ndarray
    free_label: int | None
    ignore_label: int | None = None

    @classmethod
    def for_classes(cls, names: Sequence[str], free_label: int | None, ignore_label: int | None = None) -> Palette:
        """The palette of a taxonomy (official colours for Occ3D-nuScenes and SemanticKITTI)."""
        colors = np.asarray(class_colors(tuple(names)), dtype=np.uint8).reshape(-1, 3)
        return cls(tuple(names), colors, free_label, ignore_label)

    @classmethod
    def from_datamodule(cls, dm: object) -> Palette:
        """The palette of an :class:`~occplug.data.OccDataModule` (its class names and labels)."""
        names = tuple(getattr(dm, "class_names", ()) or ())
        free = getattr(dm, "free_label", None)
        if not names:  # a data set without names: ids as names, Occ3D-sized
            names = tuple(f"class_{i}" for i in range(max(int(free or 0) + 1, 18)))
        return cls.for_classes(names, free, getattr(dm, "ignore_label", None))

    @property
    def num_classes(self) -> int:
        """``K``."""
        return len(self.names)

    def semantic_ids(self) -> list[int]:
        """Ids that are drawn (every id but free), in order."""
        return [i for i in range(self.num_classes) if i != self.free_label]

    def occupied(self, labels: Tensor) -> Tensor:
        """Bool mask of voxels holding a drawable class (not free, not ignored, a known id)."""
        occ = (labels >= 0) & (labels < self.num_classes)
        if self.free_label is not None:
            occ &= labels != self.free_label
        if self.ignore_label is not None:
            occ &= labels != self.ignore_label
        return occ

    def lut(self, background: Sequence[int] = BACKGROUND) -> np.ndarray:
        """``(K + 1, 3)`` uint8 lookup table: the class colours, then ``background`` at index ``K``."""
        return np.concatenate([self.colors, np.asarray(background, np.uint8)[None]], axis=0)

    def colorize(self, ids: Tensor | np.ndarray, background: Sequence[int] = BACKGROUND) -> np.ndarray:
        """``(..., 3)`` uint8 colours of integer class ids ``(...)``.

        Ids that are free, ignored, negative (``-1``: nothing) or unknown get ``background``.
        """
        ids_t = torch.as_tensor(np.asarray(ids) if not isinstance(ids, Tensor) else ids).long()
        idx = torch.where(self.occupied(ids_t), ids_t, torch.full_like(ids_t, self.num_classes))
        return self.lut(background)[idx.cpu().numpy()]

    def present(self, *label_sets: Tensor | np.ndarray | None) -> list[int]:
        """Drawable ids occurring in any of the given label arrays, sorted (for legends)."""
        found: set[int] = set()
        for labels in label_sets:
            if labels is None:
                continue
            t = torch.as_tensor(np.asarray(labels) if not isinstance(labels, Tensor) else labels).long()
            found.update(int(v) for v in torch.unique(t[self.occupied(t)]).tolist())
        return sorted(found)

    def rgb01(self, class_id: int) -> tuple[float, float, float]:
        """Colour of ``class_id`` as floats in [0, 1] (matplotlib)."""
        r, g, b = (int(v) for v in self.colors[class_id])
        return r / 255, g / 255, b / 255
