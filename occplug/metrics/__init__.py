"""Metrics: torchmetrics classes over predicted occupancy, DDP-synced by torchmetrics."""

from .base import EvalMask, OccMetric, evaluation_mask
from .miou import Occ3DMIoU, confusion_matrix, iou_from_confusion
from .rayiou import RayIoU, cast_query_rays, query_ray_directions, select_origins
from .ssc import SSCMetrics

__all__ = [
    "EvalMask",
    "Occ3DMIoU",
    "OccMetric",
    "RayIoU",
    "SSCMetrics",
    "cast_query_rays",
    "confusion_matrix",
    "evaluation_mask",
    "iou_from_confusion",
    "query_ray_directions",
    "select_origins",
]
