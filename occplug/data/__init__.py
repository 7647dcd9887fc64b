"""Data: the Frame/Batch contract, class taxonomies, labelled points, class statistics and the data modules.

Everything but the contract and the class lists loads on first use, so importing the contract
(``occplug.data.Frame``) does not import Lightning (the data modules subclass ``LightningDataModule``).
"""

from __future__ import annotations

import importlib
from typing import Any

from . import classes
from .classes import *  # noqa: F403 -- the class lists and label mappings are part of this facade
from .frame import Batch, Frame, collate_frames

#: names loaded on first attribute access (the data modules import Lightning; the rest keep the facade light)
_LAZY = {
    "OccDataModule": "occplug.data.datamodule",
    "Occ3DNuScenesDataModule": "occplug.data.nuscenes.reader",
    "SemanticKITTIDataModule": "occplug.data.semantickitti.reader",
    "LabelCut": "occplug.data.label_fraction",
    "LabelledPoints": "occplug.data.labelled_points",
    "free_pixel_rays": "occplug.data.labelled_points",
    "lidar_points": "occplug.data.labelled_points",
    "pseudo_depth_points": "occplug.data.labelled_points",
    "to_frame": "occplug.data.labelled_points",
    "class_counts": "occplug.data.stats",
    "inverse_log_weights": "occplug.data.stats",
    "FrameTransform": "occplug.data.extensions",
    "LabelSource": "occplug.data.extensions",
    "PseudoLabelSource": "occplug.data.pseudo_labels",
    "load_mapping": "occplug.data.pseudo_labels",
    "merge_semantics": "occplug.data.pseudo_labels",
    "save_frame": "occplug.data.records",
    "read_frame": "occplug.data.records",
    "OCC3D_GRID": "occplug.data.nuscenes.format",
    "build_index": "occplug.data.nuscenes.index",
}

__all__ = [
    *classes.__all__,
    "Batch",
    "Frame",
    "collate_frames",
    *_LAZY,
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'occplug.data' has no attribute {name!r}")
