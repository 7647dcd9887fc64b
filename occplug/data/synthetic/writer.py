"""Frames on disk: one ``.pt`` file per frame (a plain dict that ``torch.load(..., weights_only=True)``
reads) plus a ``meta.json`` describing the world. The data set cache uses the same format.

Layout written by :func:`write_dataset`::

    out_dir/
      meta.json                      world config, cache key, classes, cameras, splits and files
      train/<token>.pt               one file per frame (no adjacent frames: they are files too)
      val/<token>.pt
      test/<token>.pt
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from occplug.data.classes import OCC3D_CLASSES, OCC3D_FREE
from occplug.data.frame import Frame

from .config import CODE_VERSION, SPLITS, SyntheticWorldConfig
from .render import CAMERA_RIG, NO_SURFACE

__all__ = ["FORMAT", "frame_to_record", "read_frame", "record_to_frame", "save_frame", "write_dataset"]

#: Format tag stored in every record and in ``meta.json``.
FORMAT = "occplug-synthetic-frame-2"

# Fields stored in a compact dtype and restored exactly on reading: images are 8-bit levels
# (see :func:`~.render.render_cameras`), class ids fit in a byte.
_BYTE_IMAGES = ("images",)
_BYTE_LABELS = ("semantics_2d", "point_labels", "box_labels")


def frame_to_record(frame: Frame) -> dict[str, Any]:
    """The frame as a plain dict of tensors, strings, numbers and lists (adjacent frames dropped).

    Images (multiples of 1/255) and class ids are stored as uint8; :func:`record_to_frame` restores
    the Frame dtypes exactly.
    """
    record: dict[str, Any] = {"format": FORMAT}
    for f in fields(Frame):
        value = getattr(frame, f.name)
        if f.name == "adjacent":
            continue
        if f.name == "camera_names":
            value = list(value)
        if f.name == "extras":
            value = dict(value)
        if value is not None and f.name in _BYTE_IMAGES:
            value = torch.round(value * 255).to(torch.uint8)
        if value is not None and f.name in _BYTE_LABELS:
            value = value.to(torch.uint8)
        record[f.name] = value
    return record


def record_to_frame(record: dict[str, Any]) -> Frame:
    """Inverse of :func:`frame_to_record`."""
    if record.get("format") != FORMAT:
        raise ValueError(f"not an {FORMAT} record (format {record.get('format')!r})")
    kwargs = {f.name: record[f.name] for f in fields(Frame) if f.name in record}
    for name in _BYTE_IMAGES:
        if kwargs.get(name) is not None:
            kwargs[name] = kwargs[name].to(torch.float32) / 255
    for name in _BYTE_LABELS:
        if kwargs.get(name) is not None:
            kwargs[name] = kwargs[name].to(torch.int64)
    kwargs["camera_names"] = tuple(kwargs.get("camera_names", ()))
    kwargs["extras"] = dict(kwargs.get("extras", {}))
    return Frame(**kwargs)


def save_frame(frame: Frame, path: str | Path) -> None:
    """Write ``frame`` to ``path`` atomically (a temporary file in the same folder, then a rename),
    so concurrent writers and interrupted runs never leave a half-written file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            torch.save(frame_to_record(frame), fh)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_frame(path: str | Path) -> Frame:
    """Load a frame written by :func:`save_frame` / :func:`write_dataset`."""
    return record_to_frame(torch.load(Path(path), weights_only=True))


def write_dataset(config: SyntheticWorldConfig, out_dir: str | Path, splits: Sequence[str] = SPLITS,
                  progress: bool = True) -> int:
    """Generate every frame of ``splits`` and write it under ``out_dir`` (see the module docstring).

    Returns:
        The number of frames written.
    """
    from .dataset import SyntheticDataset  # the dataset imports this module's record format

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    datasets = {split: SyntheticDataset(config, split, cache_dir=None, with_adjacent=False) for split in splits}
    total = sum(len(d) for d in datasets.values())
    meta: dict[str, Any] = {
        "format": FORMAT,
        "code_version": CODE_VERSION,
        "cache_key": config.cache_key(),
        "config": config.to_dict(),
        "class_names": list(OCC3D_CLASSES),
        "free_label": OCC3D_FREE,
        "no_surface_label": NO_SURFACE,
        "camera_names": [c[0] for c in CAMERA_RIG[: config.num_cameras]],
        "fps": config.fps,
        "splits": {},
    }
    written = 0
    with tqdm(total=total, desc="synthetic world", unit="frame", disable=not progress) as bar:
        for split, dataset in datasets.items():
            files = []
            for i in range(len(dataset)):
                frame = dataset[i]
                name = f"{split}/{frame.token}.pt"
                save_frame(frame, out / name)
                files.append(name)
                written += 1
                bar.update(1)
            meta["splits"][split] = {
                "scenes": config.scenes(split),
                "frames_per_scene": config.frames(split),
                "files": files,
            }
    (out / "meta.json").write_text(json.dumps(meta, indent=2))
    return written
