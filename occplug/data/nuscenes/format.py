"""Occ3D-nuScenes ground truth on disk: ``labels.npz`` per sample.

Format (Occ3D, Tian et al. 2023): ``gts/<scene>/<token>/labels.npz`` holding

* ``semantics``: ``(200, 200, 16)`` ``uint8`` class ids 0-17 (17 = free), indexed ``[x, y, z]``
  over the ego-frame grid ``[-40, 40) x [-40, 40) x [-1, 5.4)`` m at 0.4 m (:data:`OCC3D_GRID`);
* ``mask_lidar``, ``mask_camera``: same shape, ``uint8`` (0/1) or ``bool``: voxels observed by the
  LiDAR / the cameras.

The grid matches occplug's :class:`~occplug.geometry.GridSpec` convention and ``Frame.voxel_labels``
directly (no axis permutation). Readers take an ``expected_shape`` so grids of other sizes (e.g.
the synthetic world written in this layout) read too.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from occplug.geometry import GridSpec

from ..formats import FormatError, as_numpy, load_npz, save_npz

__all__ = [
    "OCC3D_GRID",
    "OCC3D_LIDAR_ORIGIN",
    "OCC3D_SHAPE",
    "Occ3DLabels",
    "find_label_files",
    "read_labels",
    "write_labels",
]

#: Occ3D-nuScenes' label grid in the ego frame.
OCC3D_GRID = GridSpec((-40.0, -40.0, -1.0, 40.0, 40.0, 5.4), 0.4)
#: ``(X, Y, Z)`` of Occ3D-nuScenes' label arrays.
OCC3D_SHAPE: tuple[int, int, int] = (200, 200, 16)
#: The nuScenes LiDAR's position in the ego frame, metres (the value SparseOcc's RayIoU code notes).
OCC3D_LIDAR_ORIGIN: tuple[float, float, float] = (0.9858, 0.0, 1.8402)

_MASKS = ("mask_lidar", "mask_camera")


@dataclass(frozen=True)
class Occ3DLabels:
    """One sample's Occ3D ground truth as tensors (the ``Frame`` dtypes).

    Attributes:
        semantics: ``(X, Y, Z)`` uint8 class ids.
        mask_lidar: ``(X, Y, Z)`` bool.
        mask_camera: ``(X, Y, Z)`` bool.
    """

    semantics: Tensor
    mask_lidar: Tensor
    mask_camera: Tensor


def read_labels(path: str | Path, expected_shape: tuple[int, int, int] | None = OCC3D_SHAPE) -> Occ3DLabels:
    """Read one ``labels.npz``.

    Args:
        path: the file.
        expected_shape: the grid every array must have; None accepts any 3-D shape (the masks must
            still match ``semantics``).

    Raises:
        FormatError: one line naming ``path``: unreadable file, a missing key, a wrong shape, or a
            wrong dtype (``semantics`` must be ``uint8``; masks ``uint8`` 0/1 or ``bool``).
    """
    data = load_npz(path)
    for key in ("semantics", *_MASKS):
        if key not in data:
            raise FormatError(f"{path}: missing key '{key}' (keys: {', '.join(sorted(data)) or 'none'})")
    semantics = data["semantics"]
    if semantics.dtype != np.uint8:
        raise FormatError(f"{path}: 'semantics' has dtype {semantics.dtype}; expected uint8")
    shape = tuple(semantics.shape)
    if semantics.ndim != 3 or (expected_shape is not None and shape != tuple(expected_shape)):
        expected = "a 3-D grid" if expected_shape is None else str(tuple(expected_shape))
        raise FormatError(f"{path}: 'semantics' has shape {shape}; expected {expected}")
    masks = {}
    for key in _MASKS:
        mask = data[key]
        if mask.dtype not in (np.uint8, np.bool_):
            raise FormatError(f"{path}: '{key}' has dtype {mask.dtype}; expected uint8 or bool")
        if tuple(mask.shape) != shape:
            raise FormatError(f"{path}: '{key}' has shape {tuple(mask.shape)}; expected {shape} like 'semantics'")
        if mask.dtype == np.uint8 and mask.size and mask.max() > 1:
            raise FormatError(f"{path}: '{key}' holds values other than 0 and 1")
        masks[key] = torch.from_numpy(mask.astype(bool))
    return Occ3DLabels(torch.from_numpy(semantics), masks["mask_lidar"], masks["mask_camera"])


def write_labels(
    path: str | Path, semantics: Tensor | np.ndarray, mask_lidar: Tensor | np.ndarray, mask_camera: Tensor | np.ndarray
) -> None:
    """Write one ``labels.npz`` as Occ3D does (``semantics`` uint8, masks uint8 0/1), atomically.

    Raises:
        ValueError: class ids outside 0..255, or arrays of different shapes.
    """
    sem = as_numpy(semantics)
    masks = {"mask_lidar": as_numpy(mask_lidar), "mask_camera": as_numpy(mask_camera)}
    if sem.ndim != 3:
        raise ValueError(f"{path}: semantics must be a 3-D grid, got shape {sem.shape}")
    if sem.size and (sem.min() < 0 or sem.max() > 255):
        raise ValueError(f"{path}: class ids must lie in 0..255")
    for key, mask in masks.items():
        if mask.shape != sem.shape:
            raise ValueError(f"{path}: {key} has shape {mask.shape}, semantics {sem.shape}")
    save_npz(path, semantics=sem.astype(np.uint8), **{k: m.astype(bool).astype(np.uint8) for k, m in masks.items()})


def find_label_files(root: str | Path) -> dict[str, Path]:
    """``{token: labels.npz}`` under an Occ3D ground-truth folder.

    Accepted layouts, tried in order (the first that holds any file wins):

    1. ``root/gts/<scene>/<token>/labels.npz`` (Occ3D as distributed, ``root`` its parent);
    2. ``root/<scene>/<token>/labels.npz`` (``root`` is the ``gts`` folder itself);
    3. ``root/<token>/labels.npz`` (flat).

    Raises:
        FormatError: a token appears twice (in two scenes).
    """
    root = Path(root)
    for pattern in ("gts/*/*/labels.npz", "*/*/labels.npz", "*/labels.npz"):
        found: dict[str, Path] = {}
        for path in sorted(root.glob(pattern)):
            token = path.parent.name
            if token in found:
                raise FormatError(f"{path}: token {token} also appears at {found[token]}")
            found[token] = path
        if found:
            return found
    return {}
