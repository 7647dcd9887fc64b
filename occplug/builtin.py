"""The core's own plugin: registers the generic components through the public hooks.

It is registered exactly like a third-party plugin (``occplug.plugins``), just first.
"""

from __future__ import annotations

from importlib.resources import files
from typing import TYPE_CHECKING

from .hookspecs import hookimpl

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable

    from .registry import Registry


@hookimpl
def occplug_register_components(registry: Registry) -> None:
    """Register the core's encoders, view transforms, scene, head, supervision, data, metric and model."""
    from . import components as c
    from .components.stateful import DenseVoxelsHistory
    from .data.nuscenes.reader import Occ3DNuScenesDataModule
    from .data.semantickitti.reader import SemanticKITTIDataModule
    from .data.synthetic import SyntheticDataModule
    from .data.teacher_labels import TeacherPseudoLabels
    from .metrics import Occ3DMIoU, RayIoU, SSCMetrics
    from .model import OccModel
    from .run.ema import EMAWeights
    from .viz.callback import BevPanelLogger

    registry.add("encoder", "small_cnn", c.SmallCNN)
    registry.add("encoder", "timm", c.TimmEncoder)
    registry.add("point_encoder", "voxel_points", c.VoxelPoints)
    registry.add("view_transform", "lss", c.LSSViewTransform)
    registry.add("view_transform", "backward_projection", c.BackwardProjection)
    registry.add("depth_net", "plain", c.PlainDepthNet)
    registry.add("depth_net", "camera_aware", c.CameraAwareDepthNet)
    registry.add("depth_net", "oracle_depth", c.OracleDepthNet)
    registry.add("scene", "dense_voxels", c.DenseVoxels)
    registry.add("scene", "dense_voxels_history", DenseVoxelsHistory)
    registry.add("head", "voxel_classifier", c.VoxelClassifier)
    registry.add("supervision", "voxel_ce", c.VoxelCrossEntropy)
    registry.add("supervision", "lidar_depth", c.LidarDepthSupervision)
    registry.add("data", "synthetic", SyntheticDataModule)
    registry.add("data", "occ3d_nuscenes", Occ3DNuScenesDataModule)
    registry.add("data", "semantickitti", SemanticKITTIDataModule)
    registry.add("metric", "occ3d_miou", Occ3DMIoU)
    registry.add("metric", "rayiou", RayIoU)
    registry.add("metric", "ssc", SSCMetrics)
    registry.add("model", "occ_model", OccModel)
    registry.add("callback", "bev_panel_logger", BevPanelLogger)
    registry.add("callback", "ema", EMAWeights)
    registry.add("label_source", "teacher_pseudo_labels", TeacherPseudoLabels)


@hookimpl
def occplug_config_dir() -> Traversable:
    """The core's base configs (``occplug/trainer/default``, ``occplug/data/synthetic``, ...)."""
    return files("occplug") / "configs"
