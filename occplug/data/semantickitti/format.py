"""SemanticKITTI semantic scene completion (SSC) voxel files.

Layout (Behley et al., ICCV 2019; semantic-kitti-api): ``sequences/<XX>/voxels/<NNNNNN>.<ext>`` with

* ``.bin`` (occupancy of the input scan), ``.invalid`` (voxels never observed from any pose of the
  sequence, ignored by the benchmark), ``.occluded``: ``256 * 256 * 32`` bits packed 8 per byte,
  most significant bit first (``np.unpackbits`` order);
* ``.label``: ``256 * 256 * 32`` ``uint16`` raw SemanticKITTI label ids (0 = empty / unlabeled).

Arrays are stored in C order over ``(X, Y, Z) = (256, 256, 32)``: x forward 0..51.2 m, y left
-25.6..25.6 m, z up -2..4.4 m, 0.2 m voxels, in the LiDAR frame of the scan (:data:`SSC_GRID`).

Raw ids map to the 20 SSC classes of :data:`~occplug.data.classes.SEMANTIC_KITTI_CLASSES` with the
benchmark's ``learning_map`` (:data:`~occplug.data.classes.SEMANTIC_KITTI_LEARNING_MAP`), adapted for completion as
``evaluate_completion.py`` does: raw 0 stays 0 (empty), every other raw id that the learning map sends
to 0 ("outlier", "other-structure", "other-object") becomes 255 (ignored), and so does any raw id the
map does not know. The sample token of ``sequences/08/voxels/000123.label`` is ``08_000123``
(:func:`sample_token`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from occplug.geometry import GridSpec

from ..classes import SEMANTIC_KITTI_LEARNING_MAP
from ..formats import FormatError, as_numpy

__all__ = [
    "IGNORE",
    "SPLIT_SEQUENCES",
    "SSC_GRID",
    "SSC_SHAPE",
    "SSCVoxels",
    "VOXEL_EXTENSIONS",
    "find_label_files",
    "learning_map_lut",
    "pack",
    "read_bits",
    "read_raw_labels",
    "read_voxels",
    "remap_labels",
    "sample_token",
    "unpack",
    "voxel_file_problem",
    "write_bits",
    "write_raw_labels",
]

#: ``(X, Y, Z)`` of the SSC voxel grids.
SSC_SHAPE: tuple[int, int, int] = (256, 256, 32)
#: The SSC grid in the scan's LiDAR frame.
SSC_GRID = GridSpec((0.0, -25.6, -2.0, 51.2, 25.6, 4.4), 0.2)
#: The id ignored by the SSC benchmark.
IGNORE = 255
#: The standard SSC split: train 00-07, 09, 10; val 08; test 11-21.
SPLIT_SEQUENCES: dict[str, tuple[str, ...]] = {
    "train": ("00", "01", "02", "03", "04", "05", "06", "07", "09", "10"),
    "val": ("08",),
    "test": tuple(f"{i:02d}" for i in range(11, 22)),
}


def learning_map_lut(completion: bool = True) -> np.ndarray:
    """A lookup table over every ``uint16`` raw id: ``lut[raw]`` is the SSC class.

    Args:
        completion: the benchmark's completion variant (see the module docstring): only raw 0 is
            empty, other raw ids mapped to 0 and unknown ids become 255. False gives the plain
            learning map (unknown ids 0).

    Returns:
        ``(65536,)`` uint8.
    """
    lut = np.full(1 << 16, IGNORE if completion else 0, dtype=np.uint8)
    for raw, cls in SEMANTIC_KITTI_LEARNING_MAP.items():
        lut[raw] = IGNORE if completion and cls == 0 and raw != 0 else cls
    return lut


def remap_labels(raw: Tensor | np.ndarray, completion: bool = True) -> Tensor:
    """Raw ``uint16`` label ids (any shape) -> ``uint8`` SSC classes, via :func:`learning_map_lut`."""
    return torch.from_numpy(learning_map_lut(completion)[as_numpy(raw).astype(np.uint16)])


def pack(bits: Tensor | np.ndarray) -> np.ndarray:
    """Bit-pack a bool grid (any shape, C order) 8 voxels per byte, most significant bit first."""
    return np.packbits(as_numpy(bits).astype(bool).reshape(-1))


def unpack(packed: np.ndarray, shape: tuple[int, ...] = SSC_SHAPE) -> Tensor:
    """Inverse of :func:`pack`: ``(prod(shape) / 8,)`` uint8 bytes -> bool tensor of ``shape``."""
    count = int(np.prod(shape))
    if packed.size * 8 != count:
        raise ValueError(f"{packed.size} bytes hold {packed.size * 8} bits, not the {count} of a {shape} grid")
    return torch.from_numpy(np.unpackbits(packed.astype(np.uint8)).astype(bool).reshape(shape))


def _read_array(path: Path, dtype: type, count: int) -> np.ndarray:
    if not path.is_file():
        raise FormatError(f"{path}: no such file")
    data = np.fromfile(path, dtype=dtype)
    if data.size != count:
        item = np.dtype(dtype)
        values = f" ({count} {item.name} values)" if item.itemsize > 1 else ""
        raise FormatError(f"{path}: {path.stat().st_size} bytes; expected {count * item.itemsize}{values}")
    return data


#: The voxel files of a labelled scan, ``voxels/<NNNNNN><ext>``.
VOXEL_EXTENSIONS: tuple[str, ...] = (".bin", ".label", ".invalid", ".occluded")


def voxel_file_problem(suffix: str, size: int, shape: tuple[int, ...] = SSC_SHAPE) -> str | None:
    """What is wrong with the size of a voxel file, or None.

    Args:
        suffix: the file's extension (:data:`VOXEL_EXTENSIONS`): ``.label`` holds ``uint16`` per voxel,
            the others one bit per voxel.
        size: the file size in bytes.
        shape: the voxel grid.
    """
    count = int(np.prod(shape))
    shape = tuple(shape)
    if suffix == ".label":
        expected = f"{2 * count} ({count} uint16 voxels of a {shape} grid)"
        return None if size == 2 * count else f"{size} bytes; expected {expected}"
    if suffix not in VOXEL_EXTENSIONS:
        raise ValueError(f"unknown voxel file extension {suffix!r} (valid: {', '.join(VOXEL_EXTENSIONS)})")
    return None if size * 8 == count else f"{size} bytes; expected {count // 8} ({count} voxels, 8 per byte)"


def read_bits(path: str | Path, shape: tuple[int, ...] = SSC_SHAPE) -> Tensor:
    """A bit-packed ``.bin`` / ``.invalid`` / ``.occluded`` file as a bool tensor of ``shape``.

    Raises:
        FormatError: missing file or a size other than ``prod(shape) / 8`` bytes.
    """
    count = int(np.prod(shape))
    return unpack(_read_array(Path(path), np.uint8, count // 8), shape)


def write_bits(path: str | Path, bits: Tensor | np.ndarray) -> None:
    """Write a bool grid as a bit-packed file (the grid's size must be a multiple of 8)."""
    array = as_numpy(bits)
    if array.size % 8:
        raise ValueError(f"{path}: {array.size} voxels do not pack into whole bytes")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    pack(array).tofile(path)


def read_raw_labels(path: str | Path, shape: tuple[int, ...] = SSC_SHAPE) -> Tensor:
    """A ``.label`` file's raw ``uint16`` ids, as an int32 tensor of ``shape`` (torch has no uint16 maths).

    Raises:
        FormatError: missing file or a size other than ``2 * prod(shape)`` bytes.
    """
    count = int(np.prod(shape))
    return torch.from_numpy(_read_array(Path(path), np.uint16, count).astype(np.int32).reshape(shape))


def write_raw_labels(path: str | Path, raw: Tensor | np.ndarray) -> None:
    """Write raw label ids (0..65535) as a ``uint16`` ``.label`` file in C order."""
    array = as_numpy(raw)
    if array.size and (array.min() < 0 or array.max() > 65535):
        raise ValueError(f"{path}: raw label ids must lie in 0..65535")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    array.astype(np.uint16).reshape(-1).tofile(path)


@dataclass(frozen=True)
class SSCVoxels:
    """One scan's SSC ground truth (the ``Frame`` dtypes).

    Attributes:
        labels: ``(X, Y, Z)`` uint8 SSC classes 0..19, 255 = ignored (unknown or ambiguous raw id).
            Invalid voxels keep their class here; :attr:`invalid` flags them.
        invalid: ``(X, Y, Z)`` bool, from ``.invalid``.
    """

    labels: Tensor
    invalid: Tensor


def read_voxels(label_path: str | Path, shape: tuple[int, ...] = SSC_SHAPE) -> SSCVoxels:
    """``<NNNNNN>.label`` remapped to SSC classes, with the ``.invalid`` file beside it."""
    label_path = Path(label_path)
    labels = remap_labels(read_raw_labels(label_path, shape))
    invalid = read_bits(label_path.with_suffix(".invalid"), shape)
    return SSCVoxels(labels, invalid)


def sample_token(sequence: str | int, frame: str | int) -> str:
    """The occplug token of a scan: ``sample_token(8, 123) == "08_000123"``."""
    return f"{int(sequence):02d}_{int(frame):06d}"


def find_label_files(root: str | Path) -> dict[str, Path]:
    """``{token: .label path}`` of every ``root/sequences/<XX>/voxels/<NNNNNN>.label``."""
    found = {}
    for path in sorted(Path(root).glob("sequences/*/voxels/*.label")):
        seq, frame = path.parent.parent.name, path.stem
        if not (seq.isdigit() and frame.isdigit()):
            raise FormatError(f"{path}: expected sequences/<XX>/voxels/<NNNNNN>.label with numeric names")
        found[sample_token(seq, frame)] = path
    return found
