"""Frames as files: one ``.pt`` per frame, a plain dict that ``torch.load(..., weights_only=True)`` reads.

The synthetic world on disk (:func:`occplug.data.synthetic.write_dataset`) and every reader's frame cache
(:class:`~occplug.data.pipeline.ReaderDataset`) store frames in this one format.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import fields
from pathlib import Path
from typing import Any

import torch

from occplug.errors import UserError

from .frame import Frame

__all__ = ["FORMAT", "frame_to_record", "read_frame", "record_to_frame", "save_frame"]

#: Format tag stored in every record and in ``meta.json``.
FORMAT = "occplug-synthetic-frame-2"

# Fields stored in a compact dtype and restored exactly on reading: images are 8-bit levels
# (see :func:`occplug.data.synthetic.render.render_cameras`), class ids fit in a byte.
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
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise cache_write_error(path, exc) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            torch.save(frame_to_record(frame), fh)
        os.replace(tmp, path)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise cache_write_error(path, exc) from None
        raise


def cache_write_error(path: Path, exc: OSError) -> UserError:
    """One line for a frame file that cannot be written (a cache that is read-only or full, a file where its
    folder goes, a folder where the file goes), naming the file and the ways out."""
    if path.is_dir():
        reason = "a folder is in the way (remove it)"
    elif any(p.exists() and not p.is_dir() for p in path.parents):
        blocker = next(p for p in path.parents if p.exists() and not p.is_dir())
        reason = f"{blocker} is a file, not a folder"
    else:
        reason = exc.strerror or str(exc) or type(exc).__name__
    return UserError(
        f"cannot write cache entry {path}: {reason}; point data.cache_dir (or $OCCPLUG_CACHE) at a writable folder"
        ", or set data.cache=false"
    )


def read_frame(path: str | Path) -> Frame:
    """Load a frame written by :func:`save_frame` / :func:`write_dataset`."""
    return record_to_frame(torch.load(Path(path), weights_only=True))
