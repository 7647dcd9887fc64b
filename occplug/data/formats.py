"""File helpers shared by every data set, and occplug's own prediction files.

The on-disk formats of the real data sets live with their readers:

* :mod:`occplug.data.nuscenes.format` — Occ3D ``labels.npz`` (``semantics``, ``mask_lidar``,
  ``mask_camera``) and the ``gts/<scene>/<token>/`` layout.
* :mod:`occplug.data.semantickitti.format` — SemanticKITTI SSC voxel files (bit-packed ``.bin``,
  ``.invalid``, ``.occluded``; ``uint16`` ``.label``), the learning map to the 20 SSC classes and the
  ``sequences/XX/voxels/`` layout.

Prediction files, as ``occplug predict`` writes them and ``occplug eval`` reads them: one
``<token>.npz`` per sample with key ``pred``, the ``(X, Y, Z)`` class-id grid (``uint8``; any
integer dtype is read). Every reader raises :class:`FormatError` with one line naming the file.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from occplug.errors import UserError

__all__ = [
    "PREDICTION_KEY",
    "FormatError",
    "as_numpy",
    "find_predictions",
    "load_npz",
    "read_prediction",
    "read_split_file",
    "save_npz",
    "write_prediction",
]

#: Key of the class-id grid in a prediction file.
PREDICTION_KEY = "pred"


class FormatError(UserError):
    """A data or prediction file is missing, unreadable or not of the expected layout (one line)."""


def load_npz(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file, read eagerly; :class:`FormatError` if it cannot be read."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except Exception as exc:  # zipfile, pickle and value errors all mean "not a readable npz"
        raise FormatError(
            f"{path}: not a readable .npz file ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None


def save_npz(path: str | Path, **arrays: np.ndarray) -> None:
    """Write a compressed ``.npz`` atomically (a temporary file in the same folder, then a rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp.npz", dir=path.parent)
    os.close(fd)
    try:
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def as_numpy(value: Tensor | np.ndarray) -> np.ndarray:
    """A CPU numpy view or copy of a tensor or array."""
    return value.detach().cpu().numpy() if isinstance(value, Tensor) else np.asarray(value)


def read_prediction(path: str | Path, shape: tuple[int, ...] | None = None) -> Tensor:
    """A prediction file's class-id grid.

    Args:
        path: ``<token>.npz`` with key ``pred``.
        shape: the expected ``(X, Y, Z)``, or None for any 3-D grid.

    Returns:
        ``(X, Y, Z)`` int64 class ids.

    Raises:
        FormatError: missing file or key, a non-integer dtype, or the wrong shape.
    """
    data = load_npz(path)
    if PREDICTION_KEY not in data:
        raise FormatError(f"{path}: no '{PREDICTION_KEY}' array (keys: {', '.join(sorted(data)) or 'none'})")
    pred = data[PREDICTION_KEY]
    if not np.issubdtype(pred.dtype, np.integer):
        raise FormatError(f"{path}: '{PREDICTION_KEY}' has dtype {pred.dtype}; expected integer class ids (uint8)")
    if pred.ndim != 3 or (shape is not None and tuple(pred.shape) != tuple(shape)):
        expected = "a 3-D grid" if shape is None else str(tuple(shape))
        raise FormatError(f"{path}: '{PREDICTION_KEY}' has shape {tuple(pred.shape)}; expected {expected}")
    return torch.from_numpy(pred.astype(np.int64))


def write_prediction(path: str | Path, pred: Tensor | np.ndarray) -> None:
    """Write ``pred`` ``(X, Y, Z)`` class ids (0..255) as ``<path>`` with key ``pred`` (``uint8``)."""
    array = as_numpy(pred)
    if array.size and (array.min() < 0 or array.max() > 255):
        raise ValueError(f"{path}: class ids must lie in 0..255 to be stored as uint8")
    save_npz(path, **{PREDICTION_KEY: array.astype(np.uint8)})


def find_predictions(folder: str | Path) -> dict[str, Path]:
    """``{token: path}`` of every ``<token>.npz`` directly in ``folder`` (hidden files skipped)."""
    return {p.stem: p for p in sorted(Path(folder).glob("*.npz")) if not p.name.startswith(".")}


def read_split_file(path: str | Path, items: str = "scene names") -> dict[str, list[str]]:
    """A JSON split file ``{split: [names]}`` with splits among ``train``, ``val``, ``test``.

    Args:
        path: the file.
        items: what the lists hold, for the error text (``scene names``, ``sequences``).

    Raises:
        FormatError: a missing or malformed file (one line naming it).
    """
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: no such split file")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FormatError(f"{path}: not valid JSON ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict) or not all(isinstance(v, list) for v in data.values()):
        raise FormatError(
            f'{path}: a split file maps split names to lists of {items}, e.g. {{"train": [...], "val": [...]}}'
        )
    for split in data:
        if split not in ("train", "val", "test"):
            raise FormatError(f"{path}: unknown split '{split}' (valid: train, val, test)")
    return {k: [str(s) for s in v] for k, v in data.items()}
