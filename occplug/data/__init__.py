"""Data: the Frame/Batch contract, class taxonomies, data modules and the synthetic world."""

from .classes import OCC3D_CLASSES, OCC3D_FREE, OCC3D_NUM_CLASSES, SEMANTIC_KITTI_CLASSES
from .datamodule import OccDataModule
from .frame import Batch, Frame, collate_frames

__all__ = [
    "OCC3D_CLASSES",
    "OCC3D_FREE",
    "OCC3D_NUM_CLASSES",
    "SEMANTIC_KITTI_CLASSES",
    "Batch",
    "Frame",
    "OccDataModule",
    "collate_frames",
]
