"""Class taxonomies: Occ3D-nuScenes (the default) and SemanticKITTI SSC."""

from __future__ import annotations

__all__ = ["OCC3D_CLASSES", "OCC3D_FREE", "OCC3D_NUM_CLASSES", "SEMANTIC_KITTI_CLASSES"]

#: Occ3D-nuScenes class names indexed by id; id 17 is ``free`` (empty space).
OCC3D_CLASSES: tuple[str, ...] = (
    "others",
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
    "free",
)
OCC3D_FREE: int = 17
#: Number of ids including ``free`` (the logits dimension of an Occ3D-style head).
OCC3D_NUM_CLASSES: int = 18

#: SemanticKITTI SSC class names indexed by id; 0 is empty, 255 is ignored (not listed).
SEMANTIC_KITTI_CLASSES: tuple[str, ...] = (
    "empty",
    "car",
    "bicycle",
    "motorcycle",
    "truck",
    "other-vehicle",
    "person",
    "bicyclist",
    "motorcyclist",
    "road",
    "parking",
    "sidewalk",
    "other-ground",
    "building",
    "fence",
    "vegetation",
    "trunk",
    "terrain",
    "pole",
    "traffic-sign",
)
