"""OccLE's hook implementations (the only module that uses ``@occplug.hookimpl``)."""

from __future__ import annotations

from importlib.resources import files
from importlib.resources.abc import Traversable

import occplug


@occplug.hookimpl
def occplug_register_components(registry: occplug.Registry) -> None:
    from .heads import (
        FusedOccupancyHead,
        GeometryOccupancyHead,
        ImageSemanticHead,
        LidarSemanticHead,
        ProjectedSegmentationHead,
    )
    from .point_encoder import OccleLidarVoxels
    from .scene import OccleScene
    from .supervision import OccleFusion, OccleGeometry, OccleSemantic

    registry.add("point_encoder", "occle_lidar_voxels", OccleLidarVoxels)
    registry.add("scene", "occle_scene", OccleScene)
    registry.add("head", "occle_occupancy_head", FusedOccupancyHead)
    registry.add("head", "occle_lidar_semantic_head", LidarSemanticHead)
    registry.add("head", "occle_geometry_head", GeometryOccupancyHead)
    registry.add("head", "occle_image_semantic_head", ImageSemanticHead)
    registry.add("head", "occle_projection_head", ProjectedSegmentationHead)
    registry.add("supervision", "occle_semantic", OccleSemantic)
    registry.add("supervision", "occle_geometry", OccleGeometry)
    registry.add("supervision", "occle_fusion", OccleFusion)


@occplug.hookimpl
def occplug_config_dir() -> Traversable:
    return files("occplug_occle") / "configs"
