"""The synthetic world on disk: one ``.pt`` file per frame (:mod:`occplug.data.records`, the format the data
set cache uses too) plus a ``meta.json`` describing the world.

Layout written by :func:`write_dataset`::

    out_dir/
      meta.json                      world config, cache key, classes, cameras, splits and files
      train/<token>.pt               one file per frame (no adjacent frames: they are files too)
      val/<token>.pt
      test/<token>.pt
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

from occplug.data.classes import OCC3D_CLASSES, OCC3D_FREE
from occplug.data.records import FORMAT, frame_to_record, read_frame, record_to_frame, save_frame

from .config import CODE_VERSION, SPLITS, SyntheticWorldConfig
from .dataset import SyntheticDataset
from .render import CAMERA_RIG, NO_SURFACE

__all__ = ["FORMAT", "frame_to_record", "read_frame", "record_to_frame", "save_frame", "write_dataset"]


def write_dataset(config: SyntheticWorldConfig, out_dir: str | Path, splits: Sequence[str] = SPLITS,
                  progress: bool = True) -> int:
    """Generate every frame of ``splits`` and write it under ``out_dir`` (see the module docstring).

    Returns:
        The number of frames written.
    """
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
