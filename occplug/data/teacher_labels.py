"""Teacher pseudo labels: one file per frame of a teacher's voxel classes and confidence, and the label
source that puts them into the frames that have no real labels.

Layout of a pseudo-label folder (written by :func:`occplug.run.phases.write_teacher_labels`)::

    meta.json          {"grid": [X, Y, Z], "class_names": [...], "teacher": phase, "head": name, ...}
    <token>.npz        labels (X, Y, Z) uint8 class ids of the head, confidence (X, Y, Z) float16
                       = the largest class probability
    DONE               written last: the folder is complete

Every file is written atomically. Reading checks the keys, shapes and dtypes of every file and that
the folder's grid and classes are the data's, each a one-line :class:`~occplug.data.formats.FormatError`.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import torch

from occplug.constraints import UnitInterval
from occplug.geometry import GridSpec

from .extensions import LabelSource
from .formats import FormatError, load_npz
from .frame import Frame

__all__ = ["TeacherPseudoLabels", "read_teacher_labels", "write_teacher_file"]

META = "meta.json"
DONE = "DONE"


def write_teacher_file(folder: Path, token: str, labels: np.ndarray, confidence: np.ndarray) -> None:
    """Write ``<folder>/<token>.npz`` atomically (``labels`` uint8, ``confidence`` float16, both ``(X, Y, Z)``)."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, labels=labels.astype(np.uint8), confidence=confidence.astype(np.float16))
    fd, tmp = tempfile.mkstemp(prefix=f".{token}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(buffer.getvalue())
        os.replace(tmp, folder / f"{token}.npz")
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_teacher_labels(path: Path, shape: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """``(labels uint8, confidence float16)`` of one file, each ``shape``; FormatError otherwise."""
    arrays = load_npz(path)
    for key, dtype in (("labels", np.uint8), ("confidence", np.float16)):
        if key not in arrays:
            raise FormatError(f"{path}: no array '{key}' (a teacher pseudo-label file has labels and confidence)")
        value = arrays[key]
        if value.dtype != dtype or tuple(value.shape) != tuple(shape):
            raise FormatError(
                f"{path}: '{key}' is {value.dtype} {tuple(value.shape)}, expected {np.dtype(dtype)} {tuple(shape)} "
                "(pseudo labels from another grid?)"
            )
    return arrays["labels"], arrays["confidence"]


class TeacherPseudoLabels(LabelSource):
    """Registered as label source ``teacher_pseudo_labels``: a frame without voxel labels
    (``has_voxel_labels`` False, see :mod:`occplug.data.label_fraction`) gets the teacher's classes as
    its voxel labels, voxels whose confidence is below ``confidence_threshold`` set to the ignore
    label; a frame with real labels keeps them. ``occplug fit`` adds it to a phase with
    ``pseudo_labels_from`` (:mod:`occplug.run.phases`); a config may also name a folder directly.

    Args:
        folder: the pseudo-label folder (see the module docstring).
        confidence_threshold: τ in [0, 1]; voxels with confidence >= τ are kept.
        grid, class_names, ignore_label, free_label: the data module's (given).

    Raises:
        FormatError: the folder is incomplete, or from another grid or class set; a file is missing or bad.
    """

    def __init__(
        self,
        folder: str,
        confidence_threshold: Annotated[float, UnitInterval] = 0.0,
        grid: GridSpec | None = None,
        class_names: Sequence[str] = (),
        ignore_label: int | None = None,
        free_label: int | None = None,
    ) -> None:
        self.dir = Path(folder)
        self.threshold = float(confidence_threshold)
        if not (self.dir / DONE).is_file():
            raise FormatError(f"{self.dir}: not a complete teacher pseudo-label folder (no {DONE} marker)")
        meta: dict[str, Any] = json.loads((self.dir / META).read_text())
        self.shape = tuple(int(v) for v in meta["grid"])
        if grid is not None and self.shape != tuple(grid.shape):
            raise FormatError(
                f"{self.dir / META}: pseudo labels on grid {list(self.shape)}, the data's is {list(grid.shape)}"
            )
        if class_names and list(meta["class_names"]) != list(class_names):
            raise FormatError(
                f"{self.dir / META}: the teacher's classes ({len(meta['class_names'])}: {', '.join(meta['class_names'][:3])}, …) "
                f"are not the data's ({len(class_names)}: {', '.join(list(class_names)[:3])}, …)"
            )
        fill = ignore_label if ignore_label is not None else free_label
        if fill is None:
            raise ValueError("teacher_pseudo_labels: the data set has neither an ignore nor a free label")
        self.fill = int(fill)

    def attach(self, frame: Frame) -> Frame:
        if frame.has_voxel_labels:
            return frame
        path = self.dir / f"{frame.token}.npz"
        if not path.is_file():
            raise FormatError(f"{path}: no teacher pseudo labels for frame {frame.token}")
        labels, confidence = read_teacher_labels(path, self.shape)
        kept = torch.from_numpy(confidence.astype(np.float32)) >= self.threshold
        frame.voxel_labels = torch.where(kept, torch.from_numpy(labels.astype(np.uint8)), self.fill).to(torch.uint8)
        frame.has_voxel_labels = True
        return frame
