"""Class taxonomies: Occ3D-nuScenes (the default) and SemanticKITTI SSC; their colours and mapping tables."""

from __future__ import annotations

__all__ = [
    "CLASS_GROUPS",
    "OCC3D_CLASSES",
    "OCC3D_COLORS",
    "OCC3D_DYNAMIC",
    "OCC3D_FREE",
    "NUSCENES_LIDARSEG_CATEGORIES",
    "NUSCENES_TO_OCC3D",
    "OCC3D_NUM_CLASSES",
    "class_colors",
    "class_groups",
    "nuscenes_to_occ3d",
    "OCC3D_STATIC",
    "OCC3D_TO_NUSCENES",
    "OCC3D_TO_SEMANTIC_KITTI",
    "SEMANTIC_KITTI_CLASSES",
    "SEMANTIC_KITTI_COLORS",
    "SEMANTIC_KITTI_DYNAMIC",
    "SEMANTIC_KITTI_LEARNING_MAP",
    "SEMANTIC_KITTI_LEARNING_MAP_INV",
    "SEMANTIC_KITTI_STATIC",
]

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


# ---------------------------------------------------------------- dynamic / static groups
# The one definition of each taxonomy's dynamic (object) and static (surface / structure) classes;
# metrics report ``mIoU_dynamic`` / ``mIoU_static`` over them.

#: Occ3D-nuScenes object classes (the ten nuScenes detection classes, barrier and traffic cone
#: included: they are objects, not scene structure, even when they do not move).
OCC3D_DYNAMIC: tuple[str, ...] = (
    "barrier", "bicycle", "bus", "car", "construction_vehicle", "motorcycle", "pedestrian", "traffic_cone", "trailer",
    "truck",
)  # fmt: skip
#: Occ3D-nuScenes surface and structure classes. ``others`` and ``free`` are in neither group.
OCC3D_STATIC: tuple[str, ...] = ("driveable_surface", "other_flat", "sidewalk", "terrain", "manmade", "vegetation")

#: SemanticKITTI movable classes: vehicles and road users (the classes that SemanticKITTI's
#: moving-object labels can mark as moving).
SEMANTIC_KITTI_DYNAMIC: tuple[str, ...] = (
    "car", "bicycle", "motorcycle", "truck", "other-vehicle", "person", "bicyclist", "motorcyclist",
)  # fmt: skip
#: SemanticKITTI ground, structure and nature classes (poles, signs, fences and trunks are fixed
#: structure here, unlike Occ3D's barrier / cone objects). ``empty`` is in neither group.
SEMANTIC_KITTI_STATIC: tuple[str, ...] = (
    "road", "parking", "sidewalk", "other-ground", "building", "fence", "vegetation", "trunk", "terrain", "pole",
    "traffic-sign",
)  # fmt: skip

#: Taxonomy (its class-name tuple) -> ``{"dynamic": names, "static": names}``.
CLASS_GROUPS: dict[tuple[str, ...], dict[str, tuple[str, ...]]] = {
    OCC3D_CLASSES: {"dynamic": OCC3D_DYNAMIC, "static": OCC3D_STATIC},
    SEMANTIC_KITTI_CLASSES: {"dynamic": SEMANTIC_KITTI_DYNAMIC, "static": SEMANTIC_KITTI_STATIC},
}


def class_groups(class_names: tuple[str, ...] | list[str]) -> dict[str, tuple[int, ...]] | None:
    """``{"dynamic": ids, "static": ids}`` of a known taxonomy (Occ3D-nuScenes, SemanticKITTI), else None.

    Ids index ``class_names``; a name list that is not exactly one of the two taxonomies has no groups.
    """
    groups = CLASS_GROUPS.get(tuple(class_names))
    if groups is None:
        return None
    index = {n: i for i, n in enumerate(class_names)}
    return {k: tuple(index[n] for n in names) for k, names in groups.items()}


# ---------------------------------------------------------------- colours
# One ``(r, g, b)`` uint8 triple per class id, so ``numpy.asarray(COLORS, numpy.uint8)`` is the
# ``(K, 3)`` lookup table of a taxonomy. Every picture occplug draws takes its colours from here.

#: Occ3D-nuScenes colours indexed by id, the palette of the Occ3D / CVPR 2023 occupancy-challenge
#: visualisers (barrier orange, car blue, driveable surface magenta, vegetation green, ...);
#: ``free`` (17) is white and is drawn as background.
OCC3D_COLORS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0),  # others
    (255, 120, 50),  # barrier
    (255, 192, 203),  # bicycle
    (255, 255, 0),  # bus
    (0, 150, 245),  # car
    (0, 255, 255),  # construction_vehicle
    (200, 180, 0),  # motorcycle
    (255, 0, 0),  # pedestrian
    (255, 240, 150),  # traffic_cone
    (135, 60, 0),  # trailer
    (160, 32, 240),  # truck
    (255, 0, 255),  # driveable_surface
    (139, 137, 137),  # other_flat
    (75, 0, 75),  # sidewalk
    (150, 240, 80),  # terrain
    (230, 230, 250),  # manmade
    (0, 175, 0),  # vegetation
    (255, 255, 255),  # free
)

#: SemanticKITTI SSC colours indexed by id: the official ``color_map`` of the semantic-kitti-api
#: (``config/semantic-kitti.yaml``, stored there as BGR) converted to RGB through its
#: ``learning_map_inv``; ``empty`` (0) is black and is drawn as background.
SEMANTIC_KITTI_COLORS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0),  # empty
    (100, 150, 245),  # car
    (100, 230, 245),  # bicycle
    (30, 60, 150),  # motorcycle
    (80, 30, 180),  # truck
    (0, 0, 255),  # other-vehicle
    (255, 30, 30),  # person
    (255, 40, 200),  # bicyclist
    (150, 30, 90),  # motorcyclist
    (255, 0, 255),  # road
    (255, 150, 255),  # parking
    (75, 0, 75),  # sidewalk
    (175, 0, 75),  # other-ground
    (255, 200, 0),  # building
    (255, 120, 50),  # fence
    (0, 175, 0),  # vegetation
    (135, 60, 0),  # trunk
    (150, 240, 80),  # terrain
    (255, 240, 150),  # pole
    (255, 0, 0),  # traffic-sign
)


def class_colors(class_names: tuple[str, ...] | list[str]) -> tuple[tuple[int, int, int], ...]:
    """The colour of each class of a taxonomy, index = id.

    The Occ3D-nuScenes and SemanticKITTI taxonomies get their official palettes; any other list
    of names gets distinct, deterministic colours (evenly spaced hues), so a new data set is
    drawable without registering anything.
    """
    names = tuple(class_names)
    if names == OCC3D_CLASSES:
        return OCC3D_COLORS
    if names == SEMANTIC_KITTI_CLASSES:
        return SEMANTIC_KITTI_COLORS
    import colorsys

    out = []
    for i in range(len(names)):
        r, g, b = colorsys.hsv_to_rgb((i * 0.618033988749895) % 1.0, 0.75, 0.95)
        out.append((round(r * 255), round(g * 255), round(b * 255)))
    return tuple(out)


# ---------------------------------------------------------------- mapping tables
# Every table between a data set's own label ids / category names and the taxonomies above lives here,
# so a reader, an exporter and a test never hold private copies that can drift apart.

#: nuScenes category -> Occ3D id (the detection classes; flat / static classes for lidarseg);
#: unlisted categories are 0 ``others`` (:func:`nuscenes_to_occ3d`); ``noise`` and ``vehicle.ego`` are 255 (ignored).
NUSCENES_TO_OCC3D: dict[str, int] = {
    "noise": 255, "vehicle.ego": 255,
    "movable_object.barrier": 1, "vehicle.bicycle": 2, "vehicle.bus.bendy": 3, "vehicle.bus.rigid": 3, "vehicle.car": 4,
    "vehicle.construction": 5, "vehicle.motorcycle": 6, "human.pedestrian.adult": 7, "human.pedestrian.child": 7,
    "human.pedestrian.construction_worker": 7, "human.pedestrian.police_officer": 7, "movable_object.trafficcone": 8,
    "vehicle.trailer": 9, "vehicle.truck": 10, "flat.driveable_surface": 11, "flat.other": 12, "flat.sidewalk": 13,
    "flat.terrain": 14, "static.manmade": 15, "static.vegetation": 16,
}  # fmt: skip

#: Occ3D id -> the nuScenes category the synthetic exporter writes for a box or a LiDAR point of that class
#: (one representative per id; :data:`NUSCENES_TO_OCC3D` maps each back to its id, ``static.other`` to 0).
OCC3D_TO_NUSCENES: dict[int, str] = {
    0: "static.other", 1: "movable_object.barrier", 2: "vehicle.bicycle", 3: "vehicle.bus.rigid", 4: "vehicle.car",
    5: "vehicle.construction", 6: "vehicle.motorcycle", 7: "human.pedestrian.adult", 8: "movable_object.trafficcone",
    9: "vehicle.trailer", 10: "vehicle.truck", 11: "flat.driveable_surface", 12: "flat.other", 13: "flat.sidewalk",
    14: "flat.terrain", 15: "static.manmade", 16: "static.vegetation",
}  # fmt: skip

#: The 32 nuScenes-lidarseg categories, index = the id stored in ``*_lidarseg.bin``.
NUSCENES_LIDARSEG_CATEGORIES: tuple[str, ...] = (
    "noise", "animal", "human.pedestrian.adult", "human.pedestrian.child", "human.pedestrian.construction_worker",
    "human.pedestrian.personal_mobility", "human.pedestrian.police_officer", "human.pedestrian.stroller",
    "human.pedestrian.wheelchair", "movable_object.barrier", "movable_object.debris",
    "movable_object.pushable_pullable", "movable_object.trafficcone", "static_object.bicycle_rack", "vehicle.bicycle",
    "vehicle.bus.bendy", "vehicle.bus.rigid", "vehicle.car", "vehicle.construction", "vehicle.emergency.ambulance",
    "vehicle.emergency.police", "vehicle.motorcycle", "vehicle.trailer", "vehicle.truck", "flat.driveable_surface",
    "flat.other", "flat.sidewalk", "flat.terrain", "static.manmade", "static.other", "static.vegetation", "vehicle.ego",
)  # fmt: skip


def nuscenes_to_occ3d(category: str) -> int:
    """The Occ3D id of a nuScenes category (:data:`NUSCENES_TO_OCC3D`, else 0 ``others``)."""
    return NUSCENES_TO_OCC3D.get(category, 0)


#: Raw SemanticKITTI label id -> SSC class id 0..19 (``learning_map`` of ``semantic-kitti.yaml``).
SEMANTIC_KITTI_LEARNING_MAP: dict[int, int] = {
    0: 0, 1: 0, 10: 1, 11: 2, 13: 5, 15: 3, 16: 5, 18: 4, 20: 5, 30: 6, 31: 7, 32: 8, 40: 9, 44: 10,
    48: 11, 49: 12, 50: 13, 51: 14, 52: 0, 60: 9, 70: 15, 71: 16, 72: 17, 80: 18, 81: 19, 99: 0,
    252: 1, 253: 7, 254: 6, 255: 8, 256: 5, 257: 5, 258: 4, 259: 5,
}  # fmt: skip
#: SSC class id -> raw label id (``learning_map_inv``).
SEMANTIC_KITTI_LEARNING_MAP_INV: dict[int, int] = {
    0: 0, 1: 10, 2: 11, 3: 15, 4: 18, 5: 20, 6: 30, 7: 31, 8: 32, 9: 40, 10: 44, 11: 48, 12: 49,
    13: 50, 14: 51, 15: 70, 16: 71, 17: 72, 18: 80, 19: 81,
}  # fmt: skip

#: Occ3D id (index) -> SemanticKITTI SSC class (255 = ignored: ``others`` and ``traffic_cone`` have no SSC class;
#: ``free`` -> 0 ``empty``); length 256, so any ``uint8`` Occ3D label indexes it.
OCC3D_TO_SEMANTIC_KITTI: tuple[int, ...] = tuple(
    {0: 255, 1: 14, 2: 2, 3: 5, 4: 1, 5: 5, 6: 3, 7: 6, 8: 255, 9: 5, 10: 4, 11: 9, 12: 12, 13: 11, 14: 17, 15: 13,
     16: 15, 17: 0}.get(i, 255) for i in range(256)
)  # fmt: skip
